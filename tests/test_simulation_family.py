"""The randomized family of simulated recordings: reproducible from the seed, every stratum
reachable, bench files the tool reads, significance, exact fields, one case diagnosed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cfm_fem.simulation import bench as B
from cfm_fem.simulation import benches, magnets, scans, significance
from cfm_fem.simulation.family import (
    HALL_EFFECTS,
    TRACKER_EFFECTS,
    draw_config,
    effect_pool,
    write_family_case,
    written_config,
)
from cfm_fem.simulation.scoring import score


def test_configuration_and_files_reproducible_from_the_seed(tmp_path):
    assert draw_config(11) == draw_config(11)
    assert draw_config(11) != draw_config(12)
    a = write_family_case(7, tmp_path / "a", role="effect", kind="tracker")
    b = write_family_case(7, tmp_path / "b", role="effect", kind="tracker")
    assert a["recording"].read_bytes() == b["recording"].read_bytes()
    assert a["bench"].read_bytes() == b["bench"].read_bytes()
    ta, tb = (json.loads(f["truth"].read_text()) for f in (a, b))
    assert ta == tb and ta["seed"] == 7 and ta["role"] == "effect"
    assert set(ta["strata"]) >= {"magnet", "bench_stack", "scan", "noise"}


def test_every_stratum_reachable():
    seen = {}
    effects = set()
    for seed in range(300):
        cfg = draw_config(seed)
        for k, v in cfg["strata"].items():
            seen.setdefault(k, set()).add(v)
        effects.update(effect_pool(cfg))
    assert seen["magnet"] == {"dipole", "quadrupole", "sextupole", "octupole", "solenoid", "none"}
    assert seen["source"] == {"pm", "coil", "solenoid", "none"}
    assert seen["ends"] == {"both", "one", "body", "none"}
    assert seen["bench_stack"] == {benches.stack_label(s) for s in benches.STACKS}
    assert seen["scan"] == set(scans.SCAN_KINDS)
    assert seen["noise"] == {"low", "mid", "high"}
    assert seen["reference"] == {"exact", "coarse", "harmonics", "none"}
    assert effects == set(HALL_EFFECTS) | set(TRACKER_EFFECTS)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_bench_file_read_by_the_tool(seed):
    from cfm_fem.io.bench_toml import parse_bench

    bench = benches.draw_bench(np.random.default_rng(seed))
    read = parse_bench(benches.bench_toml(bench), source="family.toml")
    assert read.stack == tuple(bench["stack"])
    assert np.allclose(read.tool_offset_mm, bench["tool_mm"])
    assert np.allclose(read.magnet.translation_mm, bench["magnet_mm"])
    assert read.magnet.survey_std_mm == pytest.approx(bench["survey_std"][0] * 1e-3)
    assert read.magnet.survey_std_rad == pytest.approx(bench["survey_std"][1] * 1e-6)


def test_chain_of_the_reference_stack_matches_the_reference_bench():
    rng = np.random.default_rng(3)
    errors = B.draw_errors(rng)
    bench = {"stack": list(B.STACK), "tool_mm": list(B.TOOL_MM)}
    q = rng.uniform(0.0, 150.0, (20, 3))
    assert np.allclose(benches.probe_position(q, errors, bench), B.probe_position(q, errors))


def test_squareness_leans_the_upper_axis_towards_the_lower():
    bench = {"stack": ["x", "y", "z"], "tool_mm": [0.0, 0.0, 0.0]}
    q = np.array([[0.0, 0.0, 100.0]])
    p = benches.probe_position(q, {"alpha_xz": 1000.0}, bench)  # z rides on x and y
    assert p[0, 0] == pytest.approx(100.0 * np.sin(1e-3), rel=1e-9)


def _signature_and_neighbour():
    """Noise 2 on 4 readings; a signature whitened to (1, 1, 0, ...) and a neighbour whitened
    to (2.5, 0, ...) per unit amplitude."""
    sigma = np.full((4, 3), 2.0)
    s = np.zeros((4, 3))
    s[0, 0], s[1, 0] = 2.0, 2.0
    other = np.zeros((4, 3))
    other[0, 0] = 5.0
    return s, other, sigma


def test_significance_by_hand():
    s, other, sigma = _signature_and_neighbour()  # the neighbour removes the first entry
    z, kept = significance.per_unit(s, [other], sigma)
    assert z == pytest.approx(1.0)
    assert kept == pytest.approx(1.0 / np.sqrt(2.0))
    z0, kept0 = significance.per_unit(s, [], sigma)
    assert z0 == pytest.approx(np.sqrt(2.0)) and kept0 == pytest.approx(1.0)
    # a prior release: data std 1 / z = 1 and prior 3 -> 6 sigma needs 6 sqrt(10)
    assert significance.excess_for(6.0, 1.0, 3.0) == pytest.approx(6.0 * np.sqrt(10.0))


def test_significance_with_priors_by_hand():
    s, other, sigma = _signature_and_neighbour()
    # min_c (1 - 2.5 c)^2 + 1 + (c / p)^2 = 1 + 1 / (1 + 6.25 p^2): 1.5 at p = 0.4
    z, kept = significance.per_unit_prior(s, [other], sigma, [0.4])
    assert z == pytest.approx(np.sqrt(1.5))
    assert kept == pytest.approx(np.sqrt(1.5 / 2.0))
    free = significance.per_unit_prior(s, [other], sigma, [np.inf])
    assert free == pytest.approx(significance.per_unit(s, [other], sigma))
    assert significance.per_unit_prior(s, [other], sigma, [1e-9])[0] == pytest.approx(np.sqrt(2))


@pytest.mark.parametrize(("seed", "kept"), [(22083, False), (50027, True)])
def test_harmonics_null_needs_a_body_within_its_priors(seed, kept, tmp_path):
    # 22083: a sextupole's body whose own B_z (the ends' field) is 11.8 sigma from the 2-D
    # field; a free gain of B_z near -100 % would absorb it, its 0.15 % prior does not
    files = write_family_case(seed, tmp_path, role="null", kind="hall")
    truth = json.loads(files["truth"].read_text())
    assert draw_config(seed, role="null", kind="hall")["reference"] == "harmonics"
    z = truth["significance"]["body_vs_2d_sigma"]
    assert (z <= 1.0) == kept
    assert truth["strata"]["reference"] == ("harmonics" if kept else "exact")
    assert files["reference"].name.endswith(".harmonics.csv" if kept else ".reference.csv")
    written = written_config(seed, role="null", kind="hall")
    assert written["strata"] == truth["strata"] and written["attempts"] == truth["attempts"] == 1


def test_drawn_effect_has_its_stated_significance(tmp_path):
    files = write_family_case(21, tmp_path, role="effect", kind="tracker")
    truth = json.loads(files["truth"].read_text())
    sig = truth["significance"]
    assert 5.0 <= sig["sigma_drawn"] <= 8.0
    ((name, block),) = truth["effects"].items()
    amp = np.sqrt(sum(v**2 for k, v in block.items() if k != "from_rep"))
    if name != "parameter_bias":
        assert amp * sig["z_per_unit"] == pytest.approx(sig["sigma_drawn"], rel=1e-9)
    assert 0.05 <= sig["kept"] <= 1.0


@pytest.mark.parametrize("source", ["pm", "coil"])
@pytest.mark.parametrize("order", [1, 2, 3, 4])
def test_multipole_order_from_a_circle_fit(source, order):
    spec = {"source": source, "order": order, "bore_mm": 12.0, "length_mm": 200.0,
            "scale_T": 0.4}  # fmt: skip
    rows = magnets.harmonics_2d(spec, 3.0, 10)
    amp = np.hypot(rows[:, 1], rows[:, 2])
    assert int(rows[np.argmax(amp), 0]) == order
    assert np.delete(amp, order - 1).max() < 1e-3 * amp[order - 1]
    # the normalisation: |B| = scale at half the bore radius in the centre plane
    b = magnets.field(spec, [[6.0, 0.0, 0.0]])
    assert np.linalg.norm(b) == pytest.approx(0.4, rel=1e-9)


@pytest.mark.parametrize(
    "spec",
    [
        {"source": "pm", "order": 3, "bore_mm": 10.0, "length_mm": 120.0, "scale_T": 0.5},
        {"source": "coil", "order": 2, "bore_mm": 15.0, "length_mm": 120.0, "scale_T": 0.2},
        {"source": "solenoid", "order": 0, "bore_mm": 20.0, "length_mm": 150.0, "scale_T": 0.3},
    ],
)
def test_field_is_divergence_free(spec):
    rng = np.random.default_rng(5)
    p = rng.uniform(-3.0, 3.0, (30, 3)) + [0.0, 0.0, 55.0]  # near an end: 3-D field
    h = 1e-3
    div = sum(
        (magnets.field(spec, p + h * e)[:, k] - magnets.field(spec, p - h * e)[:, k]) / (2 * h)
        for k, e in enumerate(np.eye(3))
    )
    grad_scale = np.abs(magnets.field(spec, p + [h, 0, 0]) - magnets.field(spec, p)).max() / h
    assert np.abs(div).max() < 1e-4 * max(grad_scale, 1e-3)


def test_one_family_case_through_the_command_line(tmp_path):
    from cfm_fem.cli import main

    files = write_family_case(21, tmp_path / "sim", role="effect", kind="tracker")
    out = tmp_path / "diag"
    assert main(["diagnose", *files["args"], "--no-report", "--out", str(out)]) == 0
    summary = json.loads((out / "diagnosis.json").read_text())
    result = score(summary, json.loads(files["truth"].read_text()))
    assert result["expected"] == files["expected"] and result["detected"] is not None


def _null_chi2(seed):
    """chi2/dof of a Hall null against the exact field at the map points after a linear fit of
    the baseline alone (registration, gains, bench errors), with the simulator's noise model."""
    from cfm_fem.simulation import family as F
    from cfm_fem.simulation import family_hall as FH

    cfg = draw_config(seed, "small", "null", "hall")
    ctx = FH.context(cfg)
    rec = FH.forward(cfg, ctx, {})
    nominal = magnets.field(cfg["magnet"], ctx["scan"].q - benches.travel_offset(cfg["bench"]))
    base = FH.forward(cfg, ctx, {}, noisy=False)
    grad = FH.gradient(cfg, ctx)
    sigma = FH.noise_std(cfg, ctx, grad)
    names = [k for k in F._neighbour_names(cfg, None) if k[0] in ("bench", "pose", "gain")]
    sig = FH.signatures(cfg, ctx, names, base=base, grad=grad)
    a = significance.whitened(list(sig.values()), sigma)
    a = a / np.linalg.norm(a, axis=0)
    y = ((rec - nominal) / sigma).ravel()
    coef, _, rank, _ = np.linalg.lstsq(a, y, rcond=1e-8)
    return float(np.sum((y - a @ coef) ** 2) / (len(y) - rank)), float(np.mean(y**2))


@pytest.mark.parametrize("order", [2, 3])
def test_hall_null_is_the_baseline_within_the_noise(order):
    seed = next(
        s
        for s in range(1000)
        if draw_config(s, "small", "null", "hall")["magnet"]["order"] == order
        and draw_config(s, "small", "null", "hall")["magnet"]["source"] == "pm"
    )
    after, before = _null_chi2(seed)
    assert before > 3.0  # the bench errors and the survey are seen
    assert 0.85 < after < 1.2


def test_family_summary_per_stratum():
    from cfm_fem.simulation.family_summary import markdown_family, summarise_family
    from cfm_fem.simulation.scoring import clopper_pearson_upper

    def run(seed, magnet, expected=None, claimed=(), sigma=None, pulls=None, mismatch=False):
        strata = {k: "a" for k in ("source", "ends", "scan", "noise", "reference")}
        strata |= {"magnet": magnet, "bench_stack": "Z-X-Y" if seed % 2 else "X-Y-Z"}
        null = expected is None
        return {"seed": seed, "role": "null" if null else "effect", "kind": "hall",
                "expected": expected, "strata": strata, "sigma": sigma,
                "false_alarm": bool(claimed) if null else None, "mismatch": mismatch,
                "rank1": None if null else bool(claimed) and claimed[0] == expected,
                "detected": None if null else expected in claimed,
                "pulls": {expected: pulls} if pulls else {}}  # fmt: skip

    runs = [run(s, "quadrupole") for s in range(97)] + [run(98, "dipole", claimed=["x"])]
    runs += [run(97, "quadrupole", mismatch=True)]  # a residual located, nothing claimed
    runs += [run(200 + s, "dipole", "planar_hall", ["planar_hall"], 6.5, {"k_x": 0.1 * s - 1})
             for s in range(18)]  # fmt: skip
    runs += [run(300, "dipole", "planar_hall", [], 7.0), run(301, "dipole", "planar_hall", [], 5.5)]
    out = summarise_family(runs)
    assert out["pooled"]["nulls"]["false_alarms"] == [2, 99]
    assert out["pooled"]["nulls"]["claimed"] == [1, 99]
    quad = out["strata"]["magnet"]["quadrupole"]["nulls"]
    assert quad["false_alarms"] == [1, 98]
    assert quad["seeds"] == [97]
    assert out["strata"]["noise"]["a"]["nulls"]["cp95_upper"] == pytest.approx(
        clopper_pearson_upper(2, 99)
    )
    dip = out["strata"]["magnet"]["dipole"]
    assert dip["nulls"]["seeds"] == [98]
    assert dip["effects"]["rank1_strong"] == [18, 19]  # the 5.5 sigma miss is not counted
    assert dip["effects"]["missed_seeds"] == [(300, "planar_hall"), (301, "planar_hall")]
    assert out["goals"]["false_alarm_pooled"] is False  # 2 in 99 > 1 %
    assert out["goals"]["rank1_per_magnet"] is False  # 18 / 19 < 95 %
    assert out["per_effect"]["planar_hall"]["pull_n"] == 18
    assert "| magnet | dipole |" in markdown_family(out, "header")
    effects_only = summarise_family([r for r in runs if r["role"] == "effect"])
    assert "false_alarm_cp95_per_stratum" not in effects_only["goals"]  # no null to judge
    assert effects_only["goals"]["rank1_per_magnet"] is False


@pytest.mark.parametrize("kind", ["hall", "tracker"])
def test_a_replica_redraws_the_readings_noise_alone(kind, tmp_path):
    from cfm_fem.simulation import family_hall as FH
    from cfm_fem.simulation import family_tracker as FT

    sim = FH if kind == "hall" else FT
    cfg = draw_config(1003, role="effect", kind=kind)
    ctx0 = sim.context(cfg)
    assert all(np.array_equal(ctx0[k], sim.context(cfg | {"replica": 0})[k]) for k in ctx0
               if isinstance(ctx0[k], np.ndarray))  # fmt: skip
    ctx1, ctx2 = (sim.context(cfg | {"replica": k}) for k in (1, 2))
    for key, v in ctx0.items():
        if not isinstance(v, np.ndarray):
            continue
        fresh = key in ("vib", "noise")
        assert np.array_equal(v, ctx1[key]) != fresh, key
        assert np.array_equal(ctx1[key], ctx2[key]) != fresh, key
    if kind == "hall":  # white noise and vibration drawn afresh at the same size
        assert np.std(ctx1["noise"]) == pytest.approx(np.std(ctx0["noise"]), rel=0.2)
    a = write_family_case(1003, tmp_path, role="effect", kind=kind)
    b = write_family_case(1003, tmp_path, role="effect", kind=kind, replica=1)
    ta, tb = (json.loads(f["truth"].read_text()) for f in (a, b))
    assert b["recording"].name == "family_1003_r1.csv" and tb["replica"] == 1
    assert ta["effects"] == tb["effects"] and ta["params"] == tb["params"]
    assert a["recording"].read_bytes() != b["recording"].read_bytes()
    with pytest.raises(ValueError, match="replica"):
        sim.context(cfg | {"replica": -1})


def test_pulls_over_replicas_are_taken_about_each_cases_mean():
    from cfm_fem.simulation.family_summary import markdown_family, summarise_family

    def run(seed, replica, pull):
        return {"seed": seed, "replica": replica, "role": "effect", "kind": "tracker",
                "expected": "step_event", "strata": dict.fromkeys(
                    ("magnet", "bench_stack", "source", "ends", "scan", "noise", "reference"),
                    "a"), "sigma": 6.5, "rank1": True, "detected": True,
                "pulls": {"step_event": {"step_x": pull}}}  # fmt: skip

    # two cases biased by +3 and -3, each with pulls of std 1 about its own mean
    runs = [run(1, k, 3.0 + d) for k, d in enumerate((-1.0, 0.0, 1.0))]
    runs += [run(2, k, -3.0 + d) for k, d in enumerate((-1.0, 0.0, 1.0))]
    runs += [run(3, 0, 0.5)]  # one replica: no spread of its own
    out = summarise_family(runs)
    rep = out["replicas"]
    assert [c["seed"] for c in rep["cases"]] == [1, 2]
    assert rep["cases"][0]["params"]["step_x"] == pytest.approx({"n": 3, "mean": 3.0, "std": 1.0})
    row = rep["per_effect"]["step_event"]
    assert row["cases"] == 2 and row["n"] == 6
    assert row["within_std"] == pytest.approx(1.0)
    assert out["per_effect"]["step_event"]["pull_std"] > 2.5  # across cases: the biases too
    md = markdown_family(out, "header")
    assert "| 1 | step_event | 3 | step_x | 3 | 3.00 | 1.00 |" in md
    assert "| step_event | 2 | 6 | 1.00 |" in md
    assert "replicas" not in markdown_family(summarise_family([run(3, 0, 0.5)]), "h")


def _fitted_t(files):
    """t of the concealed effect's signature fitted to the noisy recording with every
    neighbour and nuisance signature (the drawn significance, measured)."""
    from cfm_fem.simulation import family as F
    from cfm_fem.simulation import family_hall as FH
    from cfm_fem.simulation import family_tracker as FT

    truth = json.loads(files["truth"].read_text())
    cfg, eff = truth["config"], truth["expected"]
    hall = cfg["kind"] == "hall"
    sim = FH if hall else FT
    ctx = sim.context(cfg)
    rec = sim.forward(cfg, ctx, truth["effects"])
    if hall:
        nominal = magnets.field(cfg["magnet"], ctx["scan"].q - benches.travel_offset(cfg["bench"]))
        grad = FH.gradient(cfg, ctx)
        sigma = FH.noise_std(cfg, ctx, grad)
    else:
        nominal, grad = ctx["scan"].q + np.asarray(cfg["bench"]["tool_mm"]), None
        sigma = FT.noise_std(cfg, ctx)
    base = sim.forward(cfg, ctx, {}, noisy=False)
    others = sim.signatures(cfg, ctx, F._neighbour_names(cfg, eff), base=base, grad=grad)
    if eff != "sensor_offset":
        F._relative_offsets(others)
    direction = truth["significance"]["direction"]
    sig = sim.signatures(cfg, ctx, [(eff, p) for p in direction], base=base, grad=grad)
    s = sum(u * sig[eff, p] for p, u in direction.items())
    a = significance.whitened([*others.values(), s], sigma)
    norm = np.linalg.norm(a, axis=0)
    a = a[:, norm > 0] / norm[norm > 0]
    coef = np.linalg.lstsq(a, ((rec - nominal) / sigma).ravel(), rcond=1e-9)[0]
    cov = np.linalg.pinv(a.T @ a, rcond=1e-9)
    return coef[-1] / np.sqrt(cov[-1, -1]), truth["significance"]["sigma_drawn"]


@pytest.mark.parametrize("seed", [1003, 1023, 1022])
def test_drawn_significance_is_measured_on_the_recording(seed, tmp_path):
    files = write_family_case(seed, tmp_path, role="effect")
    t, drawn = _fitted_t(files)
    assert abs(abs(t) - drawn) < 3.0  # t ~ N(drawn, 1)


def test_a_prior_conflict_the_truth_has_is_no_false_alarm():
    truth = {"expected": None, "effects": {}, "params": {"magnet_rot_y": 131.6, "gain_z": 0.2}}
    base = {"effects": [], "located": [], "outliers": [], "mismatch": True}

    def conflict(name, std):
        return {"name": name, "prior_mean": 0.0, "prior_std": std, "z": 4.1}

    drawn_far = score(base | {"prior_conflicts": [conflict("magnet_rot_y", 31.5)]}, truth)
    assert drawn_far["true_conflicts"] == ["magnet_rot_y"] and not drawn_far["alarm"]
    # the truth within its prior (1.3 sigma): the conflict is a false statement
    drawn_near = score(base | {"prior_conflicts": [conflict("gain_z", 0.15)]}, truth)
    assert drawn_near["true_conflicts"] == [] and drawn_near["alarm"]
    # a true conflict beside a located residual: still an alarm
    located = base | {"located": [{"component": "x"}]}
    both = score(located | {"prior_conflicts": [conflict("magnet_rot_y", 31.5)]}, truth)
    assert both["alarm"]
    # an effect claimed, no conflict: no true conflict to speak of
    claimed = score(base | {"effects": [{"name": "planar_hall", "params": {}}]}, truth)
    assert claimed["alarm"] and not claimed["mismatch_true"]
