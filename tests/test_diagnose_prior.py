"""What the diagnosis takes from the bench and the probe for its reported parameters.

``[magnet] survey_std_um`` and ``survey_std_urad`` (1 sigma per axis) set the prior of the
magnet-to-bench registration the diagnosis fits; without them it takes 50 um and 100 urad. An
effect on the field an element senses is reported per that element's gain.
"""

from __future__ import annotations

import json
from importlib import resources

import numpy as np
import pytest

from cfm_fem.errors import CfmInputError
from cfm_fem.io.bench_toml import bench_to_toml, parse_bench, read_bench, read_reference_bench
from cfm_fem.workflows.diagnose.problem import REG_NAMES, registration_prior

SURVEY = "[magnet]\nsurvey_std_um = 20.0\nsurvey_std_urad = 50.0\n"


@pytest.fixture(scope="module")
def ref_text():
    return resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_text()


def _with_survey(text, lines=SURVEY):
    assert "\n[magnet]\n" in text
    return text.replace("[magnet]\n", lines, 1)


def test_survey_std_is_read_written_and_sets_the_prior(ref_text):
    bench = parse_bench(_with_survey(ref_text), "survey.toml")
    assert bench.magnet.survey_std_mm == pytest.approx(0.02)
    assert bench.magnet.survey_std_rad == pytest.approx(50e-6)
    again = parse_bench(bench_to_toml(bench), "again.toml")
    assert again.magnet.survey_std_mm == pytest.approx(0.02)
    assert again.magnet.survey_std_rad == pytest.approx(50e-6)
    prior = registration_prior(bench)
    assert prior["translation_mm"] == pytest.approx(0.02)
    assert prior["rotation_rad"] == pytest.approx(50e-6)
    assert prior["translation_source"] == prior["rotation_source"] == "bench file"
    assert prior["bench_file"] == "survey.toml"
    # an argument wins over the bench file; a bench file without the keys keeps the default
    assert registration_prior(bench, reg_std_rad=1e-5)["rotation_source"] == "argument"
    default = registration_prior(read_reference_bench())
    assert (default["translation_mm"], default["rotation_rad"]) == (0.05, 1e-4)
    assert default["translation_source"] == default["rotation_source"] == "default"
    assert "survey_std" not in bench_to_toml(read_reference_bench()).split("[magnet]")[1]


@pytest.mark.parametrize(
    "lines, fragments",
    [
        ("[magnet]\nsurvey_std_um = -20.0\n", ["magnet.survey_std_um", "> 0"]),
        ("[magnet]\nsurvey_std_urad = 0.0\n", ["magnet.survey_std_urad", "> 0"]),
        ('[magnet]\nsurvey_std_um = "20"\n', ["magnet.survey_std_um", "finite number"]),
        ("[magnet]\nsurvey_std_urad = 2e6\n", ["magnet.survey_std_urad", "<= 1e+06 urad"]),
        ("[magnet]\nsurvey_std = 20.0\n", ["magnet.survey_std", "not a known key"]),
    ],
)
def test_bad_survey_std_names_file_line_and_key(tmp_path, ref_text, lines, fragments):
    path = tmp_path / "bad.toml"
    text = _with_survey(ref_text, lines)
    path.write_text(text)
    with pytest.raises(CfmInputError) as info:
        read_bench(path)
    msg = str(info.value)
    for f in (str(path), *fragments):
        assert f in msg, msg
    assert text.splitlines()[info.value.line - 1].startswith("survey_std")


def test_bench_file_prior_reaches_the_fit(tmp_path):
    """A Hall map diagnosed through the command line with the survey in its bench file: the
    registration's prior is that survey, and the calibration's posterior is narrower than with
    the default prior on the same recording."""
    pytest.importorskip("magpylib")
    from cfm_fem.cli import main
    from cfm_fem.io.recordings import read_hall_map
    from cfm_fem.simulation import write_case
    from cfm_fem.workflows.diagnose.problem import hall_problem
    from cfm_fem.workflows.diagnose.run import reference_field as _reference
    from cfm_fem.workflows.diagnose.workflow import _calibrate

    files = write_case("null_hall", 20260107, tmp_path, size="small")
    assert "--bench" in files["args"]
    out = tmp_path / "d"
    assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    summary = json.loads((out / "diagnosis.json").read_text())
    prior = summary["calibration"]["registration_prior"]
    assert prior["translation_um"] == 20.0 and prior["rotation_urad"] == 50.0
    assert prior["bench_file"] == str(files["bench"])
    stated = {p["name"]: p["prior_std"] for p in summary["calibration"]["parameters"]}
    assert [stated[n] for n in REG_NAMES] == [20.0] * 3 + [50.0] * 3
    assert any("survey_std_um" in n and str(files["bench"]) in n for n in summary["notes"])

    # the same recording calibrated with each prior: the survey's 20 um narrows the posterior
    # of the translations (the data alone hold them to about 12 um on this small map)
    rec = read_hall_map(files["recording"])
    fn, b_ref, spacing, _ = _reference(str(files["reference"]), rec)
    std = {}
    benches = {"survey": read_bench(files["bench"]), "default": read_reference_bench()}
    for name, bench in benches.items():
        prob = hall_problem(rec, fn, b_ref, bench, smooth=False, ref_spacing_mm=spacing,
                            ref_nodes=fn.nodes)  # fmt: skip
        cal = _calibrate(prob)
        std[name] = np.array([cal.fit_b.std[cal.base.names.index(n)] for n in REG_NAMES])
    assert np.all(std["survey"][:3] < 0.95 * std["default"][:3]), std
    assert np.all(std["survey"] <= std["default"] * (1 + 1e-9)), std


def test_mixing_is_reported_per_element_gain():
    """An element reads (1 + gain) times the field it senses, its mixing included: the fit's
    mixing column takes m (1 + gain); the reported m is divided by the fitted gain."""
    from types import SimpleNamespace

    from cfm_fem.workflows.diagnose.calibrate import Columns, fit_map, stack
    from cfm_fem.workflows.diagnose.workflow import _per_gain

    rng = np.random.default_rng(3)
    B = rng.normal(0.0, 0.2, (400, 3))  # sensed field, T
    m_zx, gain_z = 0.5, 3.0  # mrad, %
    y = np.zeros_like(B)
    y[:, 2] = (1 + 1e-2 * gain_z) * (B[:, 2] + 1e-3 * m_zx * B[:, 0]) - B[:, 2]
    Jg = np.zeros((400, 3, 3))
    Jg[:, [0, 1, 2], [0, 1, 2]] = B * 1e-2
    gains = Columns(Jg, ["gain_x", "gain_y", "gain_z"], ["%"] * 3, np.zeros(3),
                    np.full(3, 10.0), "probe")  # fmt: skip
    Jm = np.zeros((400, 3, 1))
    Jm[:, 2, 0] = B[:, 0] * 1e-3
    mix = Columns(Jm, ["m_zx"], ["mrad"], np.zeros(1), np.full(1, 1e3), "probe_misalignment",
                  element=(2,))  # fmt: skip
    model = stack([gains, mix])
    fit = fit_map(y, np.full_like(y, 1e-7), model)
    assert fit.theta[-1] == pytest.approx(m_zx * (1 + 1e-2 * gain_z), rel=1e-6)
    cand = SimpleNamespace(cols=mix)
    theta, cov = _per_gain([cand], model, fit, ["m_zx"])
    assert theta[0] == pytest.approx(m_zx, rel=1e-6)
    assert cov.shape == (1, 1) and 0 < cov[0, 0] <= fit.cov[-1, -1] * 1.01
