"""One concealed effect per test on small twins (moderate SNR), null cases, hard cases."""

from __future__ import annotations

import numpy as np
import pytest
from diagnose_grids import BENCH, P, Q

from cfm_fem.workflows.diagnose.problem import hall_problem, tracker_problem
from cfm_fem.workflows.diagnose.twin import hall_twin, tracker_twin
from cfm_fem.workflows.diagnose.workflow import diagnose


def run_tracker(effects=None, seed=0, reps=6, speeds=None):
    rec, truth = tracker_twin(seed, effects, n_reps=reps, points=Q, speeds=speeds, dt_s=30.0)
    return diagnose(tracker_problem(rec, BENCH)).summary, truth


def run_hall(effects=None, seed=0, reps=6, dt_s=4.0):
    rec, truth, ctx = hall_twin(seed, effects, n_reps=reps, points=P, dt_s=dt_s)
    mp = ctx["multipole"]
    return diagnose(hall_problem(rec, mp.field, mp.b_ref, ctx["bench"])).summary, truth


def check(summary, name, truth_params, k=3.0):
    """The right name first, every true value within k reported standard uncertainties, the
    held-out error lower with the effect (a new signature must also pass the paired test)."""
    assert summary["mismatch"]
    assert summary["effects"], summary["candidates"]
    first = summary["effects"][0]
    assert first["name"] == name, summary["candidates"]
    for p, v in truth_params.items():
        est, sd = first["params"][p], first["param_std"][p]
        assert abs(est - v) < k * sd, (p, est, sd, v)
    assert first["cv_rms_after"] < first["cv_rms_before"]
    f = summary["fit"]
    assert f["cv_rms_after"] < f["cv_rms_before"]
    assert f["chi2_dof_after"] < f["chi2_dof_before"]
    return first


@pytest.mark.parametrize("seed", [11, 12])
def test_tracker_null(seed):
    s, _ = run_tracker(seed=seed)
    assert s["mismatch"] is False and s["effects"] == []


def test_reversal():
    s, _ = run_tracker({"reversal": {"backlash_z": 6.0, "backlash_x": 4.0}})
    first = check(s, "reversal", {"backlash_z": 6.0, "backlash_x": 4.0})
    # each axis's backlash is a function of its own: the two concealed ones, and no other
    assert sorted(first["functions"]) == ["backlash_x", "backlash_z"]


def test_thermal_drift():
    s, _ = run_tracker({"thermal_drift": {"drift_y": 2.0, "scale_drift_z": 3.0}})
    first = check(s, "thermal_drift", {"drift_y": 2.0, "scale_drift_z": 3.0})
    # each axis's drift is a function of its own: the two concealed ones, and no other
    assert sorted(first["functions"]) == ["drift_y", "scale_drift_z"]


def test_arm_deflection():
    s, _ = run_tracker({"arm_deflection": {"sag_z": 8.0}})
    first = check(s, "arm_deflection", {"sag_z": 8.0})
    # each carriage's sag is a function of its own: the concealed one, and no other
    assert first["functions"] == ["sag_z"] and "sag_x" not in first["params"]


def joint_chi2(effect, truth):
    """(estimate - truth)' C^-1 (estimate - truth) over the determined parameters, C from the
    reported standard uncertainties and correlations; and their number."""
    names = list(effect["params"])
    d = np.array([effect["params"][n] - truth.get(n, 0.0) for n in names])
    sd = np.array([effect["param_std"][n] for n in names])
    C = np.array(effect["param_corr"]) * np.outer(sd, sd)
    return float(d @ np.linalg.solve(C, d)), len(names)


def test_position_dependent_geometric():
    # a roll of the Z carriage growing as u_z^2 (200 urad at full stroke)
    from scipy import stats

    truth = {"eps_z(z)_u2": 200.0}
    s, _ = run_tracker({"position_dependent_geometric": truth})
    e = check(s, "position_dependent_geometric", truth)
    # the one error function is found on its own and named; its reported profile terms agree
    # with the truth at the 3-sigma level (two-sided normal 0.27 %) of their covariance
    assert e["functions"] == ["eps_z(z)"], e
    assert set(e["params"]) <= {"eps_z(z)_u1", "eps_z(z)_u2"}
    chi2, k = joint_chi2(e, truth)
    assert chi2 < stats.chi2.isf(2 * stats.norm.sf(3.0), k), (chi2, k)
    # a linear term reported without its quadratic one is the slope of the chosen order
    alone = {"eps_z(z)_u1"} if "eps_z(z)_u2" not in e["params"] else set()
    assert set(e.get("model_dependent", ())) == alone


def test_position_dependent_geometric_linear_alone_is_model_dependent():
    # a curved error (u_x^2) over the part of the stroke a scan covers looks straight: the
    # linear term the selection fits alone is reported as model-dependent
    from cfm_fem.workflows.diagnose.calibrate import Columns
    from cfm_fem.workflows.diagnose.workflow import _lower_order

    cols = Columns(np.zeros((1, 3, 1)), ["eps_z(x)_u1"], ["urad"], np.zeros(1), np.ones(1), "g")
    cols.lower_order = {"eps_z(x)_u1": "eps_z(x)_u2"}
    alone = type("C", (), {"cols": cols, "param_names": ["eps_z(x)_u1"]})()
    e = {"params": {"eps_z(x)_u1": -36.4}}
    _lower_order(e, [alone])
    assert e["model_dependent"] == ["eps_z(x)_u1"]
    both = type("C", (), {"cols": cols, "param_names": ["eps_z(x)_u1", "eps_z(x)_u2"]})()
    e = {"params": {"eps_z(x)_u1": 1.0, "eps_z(x)_u2": -33.6}}
    _lower_order(e, [both])
    assert "model_dependent" not in e


def test_parameter_bias():
    # alpha_xy is N(32.3, 12.8) urad in Table II; the bench really has 200 urad
    s, _ = run_tracker({"parameter_bias": {"alpha_xy": 200.0}})
    e = check_release(s, "parameter_bias", {"alpha_xy": 200.0})
    assert e["conflict_z"]["alpha_xy"] > 5


def check_release(summary, name, truth_params, k=3.0):
    """A prior release: found first on the prior-data conflict, truth within k u; the fit of
    the data barely moves (the calibration already followed the data), so the held-out error
    must not get significantly worse rather than drop."""
    assert summary["mismatch"] and summary["effects"], summary["candidates"]
    first = summary["effects"][0]
    assert first["name"] == name, summary["candidates"]
    assert first["evidence"].startswith("prior-data conflict")
    for p, v in truth_params.items():
        est, sd = first["params"][p], first["param_std"][p]
        assert abs(est - v) < k * sd, (p, est, sd, v)
    assert first["cv_z"] > -2.0  # paired held-out test: not significantly worse
    return first


def test_reading_delay_two_speeds():
    s, _ = run_tracker({"reading_delay": {"tau": 0.5}}, speeds=[10.0, 20.0])
    check(s, "reading_delay", {"tau": 0.5})


def test_delay_one_speed_is_not_separable_and_says_so():
    s, _ = run_tracker({"reading_delay": {"tau": 0.5}}, speeds=[20.0])
    assert s["mismatch"] and s["effects"]
    assert s["effects"][0]["name"] in ("reading_delay", "reversal")
    assert any("second speed" in a for a in s["advice"]), s["advice"]


def test_two_effects_at_once():
    s, _ = run_tracker({"reversal": {"backlash_z": 6.0}, "thermal_drift": {"drift_x": 2.0}})
    names = [e["name"] for e in s["effects"]]
    assert set(names[:2]) == {"reversal", "thermal_drift"}


def test_unrevealable_effect_reversal_without_direction():
    rec, _ = tracker_twin(5, {"reversal": {"backlash_z": 6.0}}, n_reps=6, points=Q)
    rec.dir = None  # the recording does not say the approach direction
    s = diagnose(tracker_problem(rec, BENCH)).summary
    assert all(e["name"] != "reversal" for e in s["effects"])
    assert any("both directions" in a for a in s["advice"])


def test_hall_null():
    s, _ = run_hall(seed=21)
    assert s["mismatch"] is False and s["effects"] == []


def test_probe_misalignment():
    s, _ = run_hall({"probe_misalignment": {"m_zx": 1.0, "m_zy": -0.5}})
    check(s, "probe_misalignment", {"m_zx": 1.0, "m_zy": -0.5})


def test_planar_hall():
    s, _ = run_hall({"planar_hall": {"k_z": 0.03}})
    check(s, "planar_hall", {"k_z": 0.03})


def test_hall_offset():
    s, _ = run_hall({"hall_offset_gain": {"offset_z": 40.0}})
    check(s, "hall_offset_gain", {"offset_z": 40.0})


def test_sensor_offset_in_pure_quadrupole_is_absorbed_not_invented():
    # dB_y/dx of a quadrupole is uniform: a shifted y element reads a constant offset, the same
    # signature as a magnet offset. The tool must say it is absorbed, not claim it: in a pure
    # 2-D quadrupole every element's offset is (no B_z, no gradient along z)
    s, _ = run_hall({"sensor_offset": {"d_y_x": 150.0}})
    assert all(e["name"] != "sensor_offset" for e in s["effects"])
    cand = {c["name"]: c for c in s["candidates"]}
    assert "e_y_x" in cand["sensor_offset"]["absorbed_params"]
    assert cand["sensor_offset"]["status"] == "absorbed"
    assert any("'sensor_offset' is absorbed" in a and "probe flipped" in a for a in s["advice"])


def test_magnet_offset_and_roll():
    s, truth = run_hall({"magnet_misalignment": {"magnet_dx": 300.0, "magnet_roll": 600.0}})
    reg = truth["registration"]  # survey-sized draw + the concealed misalignment
    check_release(
        s,
        "magnet_misalignment",
        {"magnet_dx": reg["t_mm"][0] * 1e3, "magnet_roll": reg["rot_rad"][2] * 1e6},
    )


def test_hall_offset_and_gain():
    # a 1 % gain error is about 6 times the S_HP prior std (0.15 %)
    s, truth = run_hall({"hall_offset_gain": {"offset_z": 20.0, "gain_x": 1.0}})
    # the fitted gain is the whole gain error: S_HP draw of the twin + the concealed 1 %
    e = check(s, "hall_offset_gain", {"offset_z": 20.0, "gain_x": truth["gains_pct"][0] + 1.0})
    assert e["evidence"] == "prior-data conflict and new signature"
    assert e["cv_z"] > 2.0


def test_in_plane_hall_offset_is_absorbed_with_advice():
    # a constant B_x, B_y is what a magnet offset gives in a quadrupole: absorbed, with advice
    s, _ = run_hall({"hall_offset_gain": {"offset_x": 20.0}})
    assert all("offset_x" not in e["params"] for e in s["effects"])
    cand = {c["name"]: c for c in s["candidates"]}
    assert {"offset_x", "offset_y"} <= set(cand["hall_offset_gain"]["absorbed_params"])
    assert any("offset_x" in a and "zero-gauss" in a for a in s["advice"]), s["advice"]


def test_magnet_temperature():
    # SmCo-like -300 ppm/K over a 7 h map (30 s per point) with the twin's +-0.4 K swing
    s, _ = run_hall({"magnet_temperature": {"beta": -300.0}}, dt_s=30.0)
    check(s, "magnet_temperature", {"beta": -300.0})


def _multipole(b6=None, pure=False):
    """QFDp4 (Table III), or its pure quadrupole, or with the normal 12-pole b6 set to ``b6``
    (fraction of B_ref at R_ref)."""
    from dataclasses import replace

    from cfm_fem.io.harmonics import read_qfdp4

    mp = read_qfdp4()
    normal, skew = mp.normal.copy(), mp.skew.copy()
    if pure:
        normal[:] = 0.0
        normal[1] = mp.normal[1]
        skew[:] = 0.0
    if b6 is not None:
        normal[5] = b6 * mp.b_ref
    return replace(mp, normal=normal, skew=skew)


def run_hall_mp(mp, effects, seed=0, reps=6):
    rec, truth, ctx = hall_twin(seed, effects, n_reps=reps, points=P, multipole=mp)
    return diagnose(hall_problem(rec, mp.field, mp.b_ref, ctx["bench"])).summary, truth


def test_sensor_volume_averaging_where_the_field_is_curved():
    # a quadrupole with a 2 % 12-pole (b6 at R_ref = 10 mm): d2B/dx2 ~ r^3 reaches 2e-3 B_ref/mm^2
    # at the map corners; a 1.5 x 0.3 x 0.5 mm Hall plate. In a 2-D field only the anisotropy
    # dw_xy = (a_x^2 - a_y^2) / 24 shows (no z curvature; the isotropic part never shows).
    from cfm_fem.workflows.diagnose.effects import averaging_params

    a = {"a_x": 1.5, "a_y": 0.3, "a_z": 0.5}
    s, _ = run_hall_mp(_multipole(b6=0.02), {"sensor_volume_averaging": a})
    truth = averaging_params([a["a_x"], a["a_y"], a["a_z"]])
    e = check(s, "sensor_volume_averaging", {"dw_xy": truth["dw_xy"]})
    assert "dw_z" not in e["params"]  # no z curvature in a 2-D reference: not estimated
    cand = {c["name"]: c for c in s["candidates"]}
    assert cand["sensor_volume_averaging"]["absorbed_params"] == ["dw_z"]
    assert e["cv_z"] > 2.0


def test_sensor_volume_averaging_in_a_pure_quadrupole_cannot_be_revealed():
    # B linear in position: the box average equals the centre value whatever the box. The tool
    # must say it cannot test it, with the measurement that would, and claim nothing.
    from cfm_fem.workflows.diagnose import effects as fx

    s, _ = run_hall_mp(_multipole(pure=True), {"sensor_volume_averaging": {"a_x": 1.5}})
    assert s["mismatch"] is False and s["effects"] == []
    why = s["untestable"]["sensor_volume_averaging"]
    assert why.startswith("the reference field has no curvature at the mapped points")
    expected = (
        f"sensor_volume_averaging cannot be tested: {why}. To test it: "
        f"{fx.ADVICE['sensor_volume_averaging']}."
    )
    assert expected in s["advice"]
    assert "sensor_volume_averaging" not in {c["name"] for c in s["candidates"]}


FRINGE = {"fringe_field_3d": {"z_entry": -250.0, "z_exit": 250.0, "lambda": 30.0}}


def _fringe_truth(truth):
    """Edges in the map frame: the body-frame edges moved by the magnet's true z offset."""
    tz = truth["registration"]["t_mm"][2]
    f = truth["effects"]["fringe_field_3d"]
    return {"z_entry": f["z_entry"] + tz, "z_exit": f["z_exit"] + tz, "lambda": f["lambda"]}


def _plane_profiles(e):
    """{plane z (mm): {order name: (value, std)}} of a fringe_field_3d entry."""
    out = {}
    for p, v in e["params"].items():
        name, _, z = p.partition("@")
        if z:
            out.setdefault(float(z), {})[name] = (v, e["param_std"][p])
    return out


def test_fringe_field_found_with_physical_parameters():
    # Enge/Fermi ends at +-250 mm, 30 mm fringe length, in a map over z = +-300 mm
    s, truth = run_hall(FRINGE)
    e = s["effects"][0]
    assert e["name"] == "fringe_field_3d", s["candidates"]
    shape = {"z_entry", "z_exit", "lambda"}
    assert shape <= set(e["params"])
    assert set(e["model_dependent"]) == shape | ({"amplitude"} & set(e["params"]))
    assert {e["units"][k] for k in shape} == {"mm"}
    # every plane within 16 fringe lengths of an end has its own g, g', g''
    planes = _plane_profiles(e)
    assert planes and all(set(v) == {"g", "g'", "g''"} for v in planes.values())
    assert e["units"][f"g'@{min(planes):g}"] == "1/mm"
    # held-out RMS from the fringe deficit (~1e3 units) down to the noise (1 unit per component)
    f = s["fit"]
    assert f["cv_rms_before"] > 100 and f["cv_rms_after"] < 3.0, f
    assert f["chi2_dof_after"] < 1.5, f


def test_fringe_field_parameters_contain_the_truth():
    # the bench errors and the magnet registration act on the 3-D field in the fit: the bench's
    # z errors (no signature in the 2-D reference) move the probe through the fringe gradient
    # and their Table II uncertainty propagates into the edges (u ~ 25 um at this SNR)
    from cfm_fem.workflows.diagnose.fringe import fringe_derivatives

    s, truth = run_hall(FRINGE)
    e = s["effects"][0]
    assert e["name"] == "fringe_field_3d"
    assert [x["name"] for x in s["effects"]] == ["fringe_field_3d"]  # nothing spurious after
    want = _fringe_truth(truth)
    for p, v in want.items():
        assert abs(e["params"][p] - v) < 3 * e["param_std"][p], (p, e["params"][p], v)
    # each plane's profile values against the twin's profile at the plane (map frame)
    planes = _plane_profiles(e)
    z = np.array(sorted(planes))
    exact = fringe_derivatives(z, want["z_entry"], want["z_exit"], want["lambda"], 2)
    pulls = np.array(
        [
            (planes[zk][name][0] - exact[m, k]) / planes[zk][name][1]
            for k, zk in enumerate(z)
            for m, name in enumerate(("g", "g'", "g''"))
        ]
    )
    assert np.abs(pulls).max() < 4.5, pulls
    assert abs(pulls.mean()) < 3.0 / np.sqrt(len(pulls)) and 0.5 < pulls.std() < 1.5, pulls


def test_fringe_field_on_scattered_points_is_the_fermi_profile():
    # no z plane holds enough points to be fitted on its own: the ends are the Fermi profile
    rng = np.random.default_rng(5)
    pts = np.column_stack(
        [rng.uniform(-8, 8, 400), rng.uniform(-8, 8, 400), rng.uniform(-300, 300, 400)]
    )
    rec, truth, ctx = hall_twin(0, FRINGE, n_reps=4, points=pts, dt_s=4.0)
    mp = ctx["multipole"]
    s = diagnose(hall_problem(rec, mp.field, mp.b_ref, ctx["bench"])).summary
    e = s["effects"][0]
    assert e["name"] == "fringe_field_3d"
    assert set(e["params"]) == {"amplitude", "z_entry", "z_exit", "lambda"}
    for p, v in {**_fringe_truth(truth), "amplitude": 1.0}.items():
        assert abs(e["params"][p] - v) < 3 * e["param_std"][p], (p, e["params"][p], v)
