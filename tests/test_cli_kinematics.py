"""`cfm-fem kinematics` and `cfm-fem tolerance` as a user runs them."""

import json

import numpy as np
import pytest
import pyvista as pv

from cfm_fem.cli import main


def test_kinematics_writes_contract_outputs(tmp_path, capsys):
    out = tmp_path / "kin"
    rc = main(["kinematics", "--trials", "3000", "--seed", "4", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["trials"] == 3000 and s["points"] == 936 and s["seed"] == 4
    for a in "xyz":
        ax = s["axes"][a]
        assert {"systematic_um", "std_um", "U_p_um"} <= set(ax)
        assert ax["U_p_um"] == pytest.approx(np.hypot(ax["systematic_um"], ax["std_um"]))
        assert 1 < ax["std_um"] < 30  # um, the scale of Table IV
    assert (
        s["bench"]["assumptions"] and s["paper_table_iv"]["simulation"]["x"]["systematic_um"] == 16
    )
    assert len(s["budget"]["rows"]) == 22
    lines = [ln for ln in (out / "points.csv").read_text().splitlines() if not ln.startswith("#")]
    header = lines[0]
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    assert table.shape == (936, 27)
    assert header.startswith("point,x_cmd_mm") and "norm_Up_um" in header
    # per-point U_p is sqrt(sys^2 + std^2) and the interval brackets the mean
    cols = header.split(",")
    sys_x, std_x, up_x = (table[:, cols.index(c)] for c in ("x_sys_um", "x_std_um", "x_Up_um"))
    np.testing.assert_allclose(up_x, np.hypot(sys_x, std_x), rtol=1e-5)
    assert np.all(table[:, cols.index("x_low_um")] < sys_x)
    assert np.all(table[:, cols.index("x_high_um")] > sys_x)
    html = (out / "report.html").read_text()
    assert 'id="table_iv"' in html and 'data-file="fig10.png"' in html
    assert f"<td>{s['axes']['z']['U_p_um']:.3g}</td>" in html  # the summary's numbers
    assert s["provenance"]["command_line"] in html
    mesh = pv.read(out / "points.vtu")
    assert mesh.points.shape == (936, 3)
    assert mesh.point_data["U_p_um"].shape == (936, 3)
    text = capsys.readouterr().out
    assert "paper Table IV" in text and "assumption:" in text
    # the printed budget is up_share, which can be negative: not "contributions", not variances
    assert "largest shares of U_p^2 = sys^2 + u^2 (up_share; not variance shares)" in text
    assert "negative" in text and "contributions" not in text


def test_kinematics_bad_input_exit_2(tmp_path, capsys):
    bad = tmp_path / "b.toml"
    bad.write_text('format = "cfm-bench"\n[frame]\nstack = ["z", "x"]\n')
    assert main(["kinematics", "--bench", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "frame.stack" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    assert main(["kinematics", "--trials", "1", "--out", str(tmp_path / "o")]) == 2
    assert main(["kinematics", "--adaptive", "9", "--out", str(tmp_path / "o")]) == 2


def test_tolerance_design_in_reverse(tmp_path, capsys):
    out = tmp_path / "tol"
    rc = main(["tolerance", "--target", "18,13,14", "--check", "3000", "--out", str(out)])
    assert rc == 0
    d = json.loads((out / "tolerance.json").read_text())
    assert d["target_um"] == pytest.approx([18.0, 13.0, 14.0])
    assert np.all(np.array(d["up_after_plan_um"]) <= np.array(d["target_um"]) + 1e-9)
    # the Monte Carlo check of the plan agrees with the linearised U_p within its MC spread
    for j, a in enumerate("xyz"):
        mc = d["plan_check_mc"][a]["U_p_um"]
        assert mc == pytest.approx(d["up_after_plan_um"][j], abs=5 * 13 / np.sqrt(3000) + 0.1)
    assert (out / "bench_plan.toml").exists()
    # the report: the plan, its Monte Carlo check and every error's factor
    html = (out / "report.html").read_text()
    assert "the plan below meets the target" in html and 'id="plan"' in html
    assert "plan, Monte Carlo (3000 trials)" in html
    assert all(f">{s['name']}<" in html for s in d["plan"])
    assert html.count("<tr>") >= 21 + 1 + len(d["plan"]) and (out / "up_share.png").exists()
    text = capsys.readouterr().out
    assert "factor" in text and "up_share X/Y/Z %" in text
    assert "up_share = the error's share of U_p^2 = sys^2 + u^2" in " ".join(text.split())
    assert main(["tolerance", "--target", "-3", "--out", str(out)]) == 2


def test_tolerance_check_shows_progress_over_the_trials(tmp_path, monkeypatch):
    """tolerance --check N shows a progress bar over the trials of its Monte Carlo."""
    import contextlib

    import cfm_fem.cli.tolerance

    seen = []

    @contextlib.contextmanager
    def bar(total, unit):
        done = []

        class _Bar:
            def update(self, n=1):
                done.append(n)

        yield _Bar()
        seen.append((total, unit, sum(done)))

    monkeypatch.setattr(cfm_fem.cli.tolerance, "progress_bar", bar, raising=False)
    assert main(["tolerance", "--target", "18,13,14", "--check", "500"]) == 0
    assert seen == [(500, "trials", 500)]
