"""Simulation against recordings: per-point statistics, Fig. 12/13 intervals, ISO 230-2 lines,
tracker and Hall comparisons on data with known answers, and the ``compare`` command."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.io.harmonics import qfdp4_path
from cfm_fem.io.recordings import read_tracker, write_hall_map, write_tracker
from cfm_fem.models.bench import ReadingDelay
from cfm_fem.models.field_model import FieldModel
from cfm_fem.models.kinematics.monte_carlo import run_kinematics
from cfm_fem.models.multipole import Multipole
from cfm_fem.models.probe import HallProbe
from cfm_fem.models.recordings import Recording
from cfm_fem.workflows.compare import (
    compare_hall,
    compare_tracker,
    interval_view,
    iso_lines,
    per_point_stats,
)
from cfm_fem.workflows.synthetic import synthetic_hall_map, synthetic_tracker

R_REF, B2 = 10.0, 0.0696


def no_noise(bench):
    return replace(bench, vibration_std_mm=np.zeros(3), delay=ReadingDelay(std_mm=np.zeros(3)))


def quiet(bench):
    return no_noise(bench.scaled_errors(0.0))


def tracker_rec(bench, cmd, err_um, pid, rep, direction=None):
    cmd = np.asarray(cmd, dtype=float)
    meas = bench.nominal_probe_mm(cmd) + 1e-3 * np.asarray(err_um, dtype=float)
    return Recording(
        kind="tracker", point_id=pid, rep=rep, cmd=cmd, meas=meas, dir=direction, source="t.csv"
    )


def test_per_point_stats_by_hand(bench):
    rec = tracker_rec(
        bench,
        [[1, 1, 1], [1, 1, 1], [2, 2, 2], [1, 1, 1]],
        [[1, 0, 0], [3, 0, 0], [5, 0, 0], [5, 0, 0]],
        pid=[4, 4, 9, 4],
        rep=[1, 2, 1, 3],
    )
    ids, count, mean, std = per_point_stats(rec, 1e3 * (rec.meas - bench.nominal_probe_mm(rec.cmd)))
    assert ids.tolist() == [4, 9] and count.tolist() == [3, 1]
    np.testing.assert_allclose(mean[:, 0], [3.0, 5.0])
    assert std[0, 0] == pytest.approx(2.0) and np.isnan(std[1, 0])


def test_interval_view_overlap():
    sim = {"x": {"systematic_um": 10.0, "std_um": 2.0}, "y": {"systematic_um": 0.0, "std_um": 1}}
    exp = {"x": {"systematic_um": 15.0, "std_um": 0.5}, "y": {"systematic_um": 5.0, "std_um": 1}}
    rows = interval_view(sim, exp, ["x", "y"], "um")
    assert rows[0]["sim"]["high"] == 14.0 and rows[0]["exp"]["low"] == 14.0
    assert rows[0]["overlap"] is True and rows[1]["overlap"] is False


def test_iso_line_hand_computed(bench):
    # X line at y = 5, z = 7: targets 10 and 20 mm, two runs per direction
    dev = {(10, 1): [1, 3], (10, -1): [-1, -3], (20, 1): [2, 2], (20, -1): [0, 0]}
    cmd, err, d, pid, rep = [], [], [], [], []
    for (t, s), vals in dev.items():
        for j, v in enumerate(vals):
            cmd.append([t, 5, 7])
            err.append([v, 0.5, -0.5])
            d.append([s, 0, 0])
            pid.append(t)
            rep.append(j + (1 if s > 0 else 3))
    # volumetric rows without a direction are ignored
    cmd += [[0, 0, 0], [0, 0, 0]]
    err += [[9, 9, 9], [9, 9, 9]]
    d += [[0, 0, 0], [0, 0, 0]]
    pid += [99, 99]
    rep += [1, 2]
    rec = tracker_rec(bench, cmd, err, pid, rep, np.array(d))
    lines = iso_lines(rec, rec.meas - bench.nominal_probe_mm(rec.cmd))
    assert len(lines) == 1
    line = lines[0]
    assert line["axis"] == "x" and line["fixed_mm"] == {"y": 5.0, "z": 7.0}
    v = line["axis_values_um"]
    s2 = np.sqrt(2.0)
    assert v["B"] == pytest.approx(4.0) and v["B_mean"] == pytest.approx(3.0)
    assert v["M"] == pytest.approx(1.0) and v["E"] == pytest.approx(4.0)
    assert v["R"] == pytest.approx(4 * s2 + 4) and v["A"] == pytest.approx(4 + 4 * s2)
    assert iso_lines(replace(rec, dir=None), rec.meas) == []


def test_synthetic_tracker_recovers_injected_reversal(bench):
    rec = synthetic_tracker(no_noise(bench), seed=1, reps=2, grid=(2, 2, 2), reversal_um=4.0)
    lines = iso_lines(rec, rec.meas - bench.nominal_probe_mm(rec.cmd))
    assert [ln["axis"] for ln in lines] == ["x"]
    v = lines[0]["axis_values_um"]
    assert v["B_mean"] == pytest.approx(4.0, abs=1e-9) and v["R"] == pytest.approx(4.0, abs=1e-9)


def test_compare_tracker_statistics(bench):
    rec = synthetic_tracker(bench, seed=2, reps=4, grid=(2, 2, 3), iso_axis=None)
    comp = compare_tracker(rec, bench, trials=1000, seed=5)
    e = rec.meas - bench.nominal_probe_mm(rec.cmd)
    _, _, mean, std = per_point_stats(rec, e)
    rms = 1e3 * np.sqrt(np.mean(mean**2, axis=0))
    for k, a in enumerate("xyz"):
        assert comp.pooled_exp[a]["systematic_um"] == pytest.approx(rms[k])
        assert comp.pooled_exp[a]["std_um"] == pytest.approx(1e3 * np.sqrt(np.mean(std[:, k] ** 2)))
    sim = run_kinematics(bench, trials=1000, seed=5, q_cmd=comp.cmd)
    np.testing.assert_allclose(comp.sim.mean, sim.mean)
    z = (mean - sim.mean[:, :3]) / sim.std[:, :3]
    np.testing.assert_allclose(comp.z, z)
    assert len(comp.fig12) == 3 and comp.iso == []


def test_compare_hall_known_offset(bench):
    """Magnet displaced by dx, perfect bench and probe: E_f,y = -1e4 dx / R_ref exactly."""
    m = Multipole([0.0, B2], [0.0, 0.0], R_REF, main=2)
    dx = 0.01
    rec = synthetic_hall_map(
        m, quiet(bench), seed=1, reps=3, probe=HallProbe.exact(), magnet_offset_mm=(dx, 0.0)
    )
    comp = compare_hall(
        rec, FieldModel.from_multipole(m), quiet(bench), probe=HallProbe.exact(), trials=40
    )
    np.testing.assert_allclose(comp.exp_mean[:, 1], -1e4 * dx / R_REF, rtol=1e-9)
    np.testing.assert_allclose(comp.exp_mean[:, 0], 0.0, atol=1e-9)
    assert comp.pooled_exp["By"]["systematic_units"] == pytest.approx(10.0, rel=1e-9)
    assert comp.pooled_sim["all"]["U_f_units"] == 0.0
    rows = {r["name"]: r for r in comp.fig13}
    assert set(rows) == {"Bx", "By", "all"} and rows["By"]["overlap"] is False


@pytest.mark.slow
def test_cli_compare_tracker_and_bad_input(tmp_path, bench, capsys):
    rec = synthetic_tracker(bench, seed=3, reps=3, grid=(2, 2, 2), reversal_um=4.0)
    path = tmp_path / "tracker.csv"
    write_tracker(path, rec)
    assert len(read_tracker(path)) == len(rec)
    out = tmp_path / "cmp"
    code = main(["compare", "--tracker", str(path), "--trials", "500", "--out", str(out)])
    assert code == 0
    names = {p.name for p in out.iterdir()}
    assert {"compare.json", "points.csv", "report.html", "fig12.png"} <= names
    assert "ISO 230-2 X" in capsys.readouterr().out
    inputs = json.loads((out / "compare.json").read_text())["provenance"]["inputs"]
    assert inputs["bench"]["packaged_default"] is True  # no --bench: the packaged bench, named
    assert inputs["bench"]["path"].endswith("cfm_reference_bench.toml")
    assert len(inputs["bench"]["sha256"]) == 64
    bad = tmp_path / "bad.csv"
    bad.write_text(path.read_text().replace("\n1,1,", "\n1,1,NaN-ish", 1))
    out2 = tmp_path / "cmp2"
    assert main(["compare", "--tracker", str(bad), "--out", str(out2)]) == 2
    assert not out2.exists()
    err = capsys.readouterr().err
    assert f"{bad}:" in err and "must be a number" in err


def test_cli_hall_needs_reference(tmp_path, bench):
    m = Multipole([0.0, B2], [0.0, 0.0], R_REF, main=2)
    path = tmp_path / "hall.csv"
    write_hall_map(path, synthetic_hall_map(m, bench, seed=1, reps=2))
    out = tmp_path / "h"
    assert main(["compare", "--hall-map", str(path), "--out", str(out)]) == 2
    assert not out.exists()
    args = ["compare", "--hall-map", str(path), "--reference", str(qfdp4_path())]
    assert main([*args, "--trials", "200", "--no-budget", "--out", str(out)]) == 0
    assert (out / "fig13.png").exists()
