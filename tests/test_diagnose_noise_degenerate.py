"""The noise model where a component carries no scatter or little gradient, and the inputs
that used to end in a traceback (a component fitted exactly, an all-zero field)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.workflows.diagnose.noise import _from_lines, _from_repeats


def _sextupole_scatter(seed, reps=4):
    """Repeated readings on a transverse grid through a sextupole's axis: the vibration is
    seen through a gradient growing as r, the same bench motion in both transverse
    components; x's gradient vanishes along y = 0 (half the grid on few lines)."""
    g = np.linspace(-10.0, 10.0, 11)
    X, Y = np.meshgrid(g, g, indexing="ij")
    x, y = X.ravel(), Y.ravel()
    vk = np.column_stack([(0.02 * x * y) ** 2, (0.02 * np.hypot(x, y)) ** 2 / 2, 0 * x])
    floor = np.array([0.01, 0.01, 0.01])
    point = np.repeat(np.arange(x.size), reps)
    sd = np.sqrt(floor[None, :] + vk)[point]
    rng = np.random.default_rng(seed)
    resid = sd * rng.standard_normal(sd.shape)
    return point, resid, vk[point], x.size, sd


@pytest.mark.parametrize("seed", range(5))
def test_no_component_collapses_below_its_own_scatter(seed):
    point, resid, vk, m, sd = _sextupole_scatter(seed)
    floor, scale, _ = _from_repeats(point, resid, vk, m)
    sigma = np.sqrt(floor[None, :] + scale[None, :] * vk)
    ratio = np.mean((sd / sigma) ** 2, axis=0)  # true over modelled variance, per component
    assert np.all((ratio > 0.6) & (ratio < 1.6)), (ratio, floor, scale)
    assert scale[0] == scale[1] == scale[2]  # one bench, one vibration scale


def test_a_component_without_scatter_gives_finite_weights():
    point, resid, vk, m, _ = _sextupole_scatter(0)
    resid[:, 2] = 0.0  # a component reproduced exactly
    floor, scale, _ = _from_repeats(point, resid, vk, m)
    assert np.all(np.isfinite(floor)) and np.all(np.isfinite(scale))
    assert floor[2] == 0.0
    pos = np.column_stack([np.arange(m, dtype=float), np.zeros(m), np.zeros(m)])
    got = _from_lines(np.arange(m), pos, resid[::4] * 0.0, vk[::4], m)
    assert got is not None and np.all(np.isfinite(got[0])) and np.all(got[0] == 0.0)


@pytest.fixture(scope="module")
def synth_hall(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth")
    assert main(["synth", "hall", "--out", str(d / "h.csv")]) == 0
    return d / "h.csv"


@pytest.mark.slow
def test_a_polynomial_reference_fitting_a_component_exactly_runs(synth_hall, tmp_path):
    """Bz is zero on the mid-plane map of a 2-D quadrupole, and so is the fitted reference's:
    that component's residual vanishes; the diagnosis still runs and states finite noise."""
    out = tmp_path / "d"
    args = ["diagnose", "--hall-map", str(synth_hall), "--reference", "fit:3"]
    assert main([*args, "--no-report", "--out", str(out)]) == 0
    s = json.loads((out / "diagnosis.json").read_text())
    assert all(np.isfinite(s["fit"]["noise_std"]))


def test_an_all_zero_field_is_refused_with_the_input_named(synth_hall, tmp_path, capsys):
    lines = synth_hall.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    rows = [ln.split(",") for ln in lines if not ln.startswith("#")]
    cols = rows[0]
    for r in rows[1:]:
        for c in ("Bx", "By", "Bz"):
            r[cols.index(c)] = "0.0"
    zero = tmp_path / "zero.csv"
    zero.write_text("\n".join(head + [",".join(r) for r in rows]) + "\n")
    out = tmp_path / "d"
    args = ["diagnose", "--hall-map", str(zero), "--reference", "fit:3", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "--reference fit:3" in err and "zero everywhere" in err and "Traceback" not in err
    assert not (out / "diagnosis.json").exists()


def _shifted(path, out, dx_mm):
    lines = path.read_text().splitlines()
    rows = [ln.split(",") for ln in lines if not ln.startswith("#")]
    i = rows[0].index("x_cmd")
    for r in rows[1:]:
        r[i] = repr(float(r[i]) + dx_mm)
    out.write_text("\n".join([ln for ln in lines if ln.startswith("#")]
                             + [",".join(r) for r in rows]) + "\n")  # fmt: skip
    return out


def _tesla_harmonics(out):
    from importlib import resources

    text = resources.files("cfm_fem.data").joinpath("qfdp4_harmonics.csv").read_text()
    out.write_text(text.replace("# convention: paper_units", "# convention: tesla"))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("case", ["fitz:4", "tesla", "500 mm off"])
def test_inputs_that_ended_in_nnls_tracebacks_run(synth_hall, tmp_path, case):
    """Residuals of a component exactly zero made the noise fit's weights infinite; each of
    these inputs ran into it. They run now, with finite noise stated."""
    if case == "fitz:4":
        rec, ref = synth_hall, "fitz:4"
    elif case == "tesla":
        rec, ref = synth_hall, str(_tesla_harmonics(tmp_path / "q.csv"))
    else:
        ref = str(_tesla_harmonics(tmp_path / "q.csv").with_name("q.csv"))
        from importlib import resources

        text = resources.files("cfm_fem.data").joinpath("qfdp4_harmonics.csv").read_text()
        (tmp_path / "q.csv").write_text(text)
        rec = _shifted(synth_hall, tmp_path / "off.csv", 500.0)
    out = tmp_path / "d"
    assert main(["diagnose", "--hall-map", str(rec), "--reference", ref, "--no-report",
                 "--out", str(out)]) == 0  # fmt: skip
    s = json.loads((out / "diagnosis.json").read_text())
    assert all(np.isfinite(s["fit"]["noise_std"]))


def test_a_tracker_whose_repetitions_are_identical_runs(tmp_path, capsys):
    """Repetitions that agree to the last digit leave no scatter to fit a noise floor to: the
    diagnosis still runs and writes finite figures."""
    rows = ["point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas"]
    for i, (x, y, z) in enumerate([(0, 20, 0), (10, 20, 50), (20, 40, 100), (30, 60, 150),
                                   (40, 80, 200), (50, 100, 250)]):  # fmt: skip
        for rep in (0, 1):
            rows.append(f"{i},{rep},{x},{y},{z},{x + 0.0021},{y - 59.9978},{z + 500.0013}")
    rec = tmp_path / "same_reps.csv"
    rec.write_text("\n".join(rows) + "\n")
    out = tmp_path / "d"
    assert main(["diagnose", "--tracker", str(rec), "--no-report", "--out", str(out)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    fit = json.loads((out / "diagnosis.json").read_text())["fit"]
    assert np.isfinite(fit["rms_before"]) and np.isfinite(fit["chi2_dof_before"])
