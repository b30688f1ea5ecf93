"""The family's significance against a coarse reference: the reference's own error where a
standard reader reads it between its nodes, shared by every repetition of a point, widens each
reading's whitening std; effects are sized against it; a magnet's temperature coefficient, the
Hall elements' offsets, the planar Hall coefficients, the averaging disc and the tracker's scale
drift stay within what the hardware has."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from cfm_fem.simulation import family as F
from cfm_fem.simulation import family_hall as FH
from cfm_fem.simulation import family_reference as FR
from cfm_fem.simulation import magnets, scans, significance

COARSE_SEED = 8  # small: a coil octupole on circles against a coarse map, a probe tilt
EXACT_SEED = 1  # small: a quadrupole on lines against the exact field
HARMONICS_SEED = 7  # small: a quadrupole's body against 2-D harmonics
REDRAWN_SEED = 1  # small effect: a temperature coefficient beyond 2000 ppm/K on its first two
# configurations
#: Small effect cases whose effect needs more than its physical range on the seed's own
#: configuration along every direction tried (seed, kind, effect), and the range of each
#: parameter (display units).
BEYOND_RANGE = [
    (15, "hall", "sensor_offset"),  # 1 mm per element offset
    (109042, "hall", "planar_hall"),  # 0.05 /T
    (109049, "hall", "sensor_volume_averaging"),  # a disc of 2 mm
    (4, "tracker", "thermal_drift"),  # 25 ppm/K of scale drift, 50 um/K of offset drift
]
RANGES = {"d_": 1000.0, "k_": 0.05, "disc_mm": 2.0, "scale_drift_": 25.0, "drift_": 50.0}


def _truth(files) -> dict:
    return json.loads(files["truth"].read_text())


@pytest.fixture(scope="module")
def coarse_case(tmp_path_factory):
    """The coarse effect case, written once."""
    folder = tmp_path_factory.mktemp("coarse")
    return F.write_family_case(COARSE_SEED, folder, "small", role="effect", kind="hall")


def _read_table(path):
    """Grid axes and values (nx, ny, nz, 3) of a written reference table, from its text."""
    rows = [r for r in path.read_text().splitlines() if not r.startswith("#")][1:]  # less header
    data = np.array([[float(v) for v in r.split(",")] for r in rows])
    axes = [np.unique(data[:, k]) for k in range(3)]
    assert len(data) == np.prod([len(a) for a in axes])  # a full regular grid
    order = np.lexsort((data[:, 2], data[:, 1], data[:, 0]))  # x slowest, z fastest
    return axes, data[order, 3:].reshape(*(len(a) for a in axes), 3)


def test_shared_error_std_by_hand():
    sigma = np.full((4, 3), 2.0)
    point = np.array([0, 1, 0, 0])  # point 0 read three times, point 1 once
    error = np.array([[1.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    w = significance.shared_error_std(sigma, point, error)
    assert w[0] == pytest.approx([np.sqrt(4.0 + 3.0), 2.0, 2.0])
    assert w[1] == pytest.approx([2.0, np.sqrt(4.0 + 9.0), 2.0])
    # the mean of point 0's three readings: variance sigma^2 / 3 + e^2
    assert w[0, 0] ** 2 / 3.0 == pytest.approx(4.0 / 3.0 + 1.0)
    assert significance.shared_error_std(sigma, point, np.zeros((2, 3))) is sigma


@pytest.mark.parametrize("seed", [EXACT_SEED, HARMONICS_SEED])
def test_reference_error_is_zero_but_for_a_coarse_table(seed):
    cfg = F.draw_config(seed, "small", "null", "hall")
    assert cfg["reference"] != "coarse"
    err = FR.reading_error(cfg)
    assert err.shape == (len(scans.map_points(cfg["scan"])), 3)
    assert not np.any(err)


def test_coarse_reference_error_is_the_cubic_readers(tmp_path):
    files = F.write_family_case(COARSE_SEED, tmp_path, "small", role="null", kind="hall")
    cfg = _truth(files)["config"]
    assert cfg["reference"] == "coarse"
    err = FR.reading_error(cfg)
    pts = scans.map_points(cfg["scan"])
    assert err.shape == (len(pts), 3)
    assert np.sqrt(np.mean(err**2)) > 1e-7  # tens of uT on a coil octupole's coarse map
    # the file as written, read by its own cubic reader, at a few of the map's points
    axes, values = _read_table(files["reference"])
    reader = RegularGridInterpolator(axes, values, method="cubic")
    worst = np.argsort(np.abs(err).max(1))[-3:]
    pick = np.r_[np.linspace(0, len(pts) - 1, 5).astype(int), worst]
    own = reader(pts[pick]) - magnets.field(cfg["magnet"], pts[pick])
    assert np.abs(own).max() > 1e-5  # tens of uT where it is worst
    # within the file's digits: its nodes to 1 nm move the reader's by up to 0.5 nm, a few nT
    # where the field changes by tenths of a T per mm
    assert np.allclose(err[pick], own, rtol=0, atol=3e-8)


def test_reference_error_raises_outside_its_grid():
    cfg = F.draw_config(COARSE_SEED, "small", "null", "hall")
    (gx, gy, gz), values = FR.table(cfg)
    narrow = ((gx[1:-1], gy, gz), values[1:-1])  # the map's outermost x beyond the nodes
    with pytest.raises(ValueError):
        FR.reading_error(cfg, narrow)


def test_significance_with_the_reference_error_is_not_above_the_noise_only():
    cfg = F.draw_config(COARSE_SEED, "small", "effect", "hall") | {"replica": 0}
    ctx = FH.context(cfg)
    base = FH.forward(cfg, ctx, {}, noisy=False)
    grad = FH.gradient(cfg, ctx)
    sigma = FH.noise_std(cfg, ctx, grad)
    total = significance.shared_error_std(sigma, ctx["scan"].point, FR.reading_error(cfg))
    assert np.all(total >= sigma) and np.any(total > 1.5 * sigma)
    effect = cfg["effect"]
    others = FH.signatures(cfg, ctx, F._neighbour_names(cfg, effect), base=base, grad=grad)
    F._relative_offsets(others)
    vec = list(others.values())
    names = [(effect, p) for p in FH.PARAMS[effect]]
    for name, s in FH.signatures(cfg, ctx, names, base=base, grad=grad).items():
        z_total = significance.per_unit(s, vec, total)[0]
        z_noise = significance.per_unit(s, vec, sigma)[0]
        assert z_total <= z_noise * (1 + 1e-9), name


def test_coarse_effect_is_sized_against_the_reference_error(coarse_case):
    truth = _truth(coarse_case)
    cfg, sig = truth["config"], truth["significance"]
    assert truth["strata"]["reference"] == "coarse" and truth["attempts"] == 1
    assert 5.0 <= sig["sigma_drawn"] <= 8.0
    assert sig["sigma_noise_only"] >= sig["sigma_drawn"]
    assert len(sig["reference_error_rms"]) == 3 and min(sig["reference_error_rms"]) > 1.0
    # the recorded effect, whitened with and without the reference's error
    effect = truth["expected"]
    ctx = FH.context(cfg)
    quiet = ctx | {"vib": np.zeros_like(ctx["vib"]), "noise": np.zeros_like(ctx["noise"])}
    signal = FH.forward(cfg, quiet, truth["effects"]) - FH.forward(cfg, quiet, {})
    base = FH.forward(cfg, ctx, {}, noisy=False)
    grad = FH.gradient(cfg, ctx)
    sigma = FH.noise_std(cfg, ctx, grad)
    err = FR.reading_error(cfg)
    assert FR.error_rms_uT(err) == pytest.approx(sig["reference_error_rms"], rel=1e-12)
    total = significance.shared_error_std(sigma, ctx["scan"].point, err)
    others = FH.signatures(cfg, ctx, F._neighbour_names(cfg, effect), base=base, grad=grad)
    F._relative_offsets(others)
    vec = list(others.values())
    assert significance.per_unit(signal, vec, total)[0] == pytest.approx(
        sig["sigma_drawn"], rel=0.01
    )
    assert significance.per_unit(signal, vec, sigma)[0] == pytest.approx(
        sig["sigma_noise_only"], rel=0.01
    )


def test_same_seed_same_truth(coarse_case, tmp_path):
    again = F.write_family_case(COARSE_SEED, tmp_path, "small", role="effect", kind="hall")
    assert again["truth"].read_text() == coarse_case["truth"].read_text()
    assert again["reference"].read_bytes() == coarse_case["reference"].read_bytes()


def test_an_effect_may_be_named_without_changing_the_other_draws():
    drawn = F.draw_config(COARSE_SEED, "small", "effect", "hall")
    named = F.draw_config(COARSE_SEED, "small", "effect", "hall", effect="magnet_temperature")
    assert named["effect"] == "magnet_temperature" != drawn["effect"]
    assert drawn["effect"] in named["fallback"] and "magnet_temperature" not in named["fallback"]
    skip = ("effect", "fallback")
    assert {k: v for k, v in named.items() if k not in skip} == {
        k: v for k, v in drawn.items() if k not in skip
    }
    with pytest.raises(ValueError, match="effect"):
        F.draw_config(COARSE_SEED, "small", "effect", "tracker", effect="magnet_temperature")


def test_magnet_temperature_within_the_range_of_magnet_materials(tmp_path):
    first = F.draw_config(REDRAWN_SEED, "small", "effect", "hall")
    assert first["effect"] == "magnet_temperature"
    # the seed's own configuration needs more than 2000 ppm/K for its drawn significance
    assert F._sized_case(first | {"replica": 0}, redraw=True) is None
    a = F.write_family_case(REDRAWN_SEED, tmp_path / "a", "small", role="effect", kind="hall")
    b = F.write_family_case(REDRAWN_SEED, tmp_path / "b", "small", role="effect", kind="hall")
    truth = _truth(a)
    assert a["truth"].read_text() == b["truth"].read_text()
    assert truth["expected"] == "magnet_temperature"
    assert truth["attempts"] > 1
    assert truth["seed"] == REDRAWN_SEED != truth["config"]["seed"]
    assert truth["config"]["seed"] == F._attempt_seed(REDRAWN_SEED, truth["attempts"])
    assert abs(truth["effects"]["magnet_temperature"]["beta"]) <= 2000.0
    assert 5.0 <= truth["significance"]["sigma_drawn"] <= 8.0


def _range(param: str) -> float:
    return next(bound for start, bound in RANGES.items() if param.startswith(start))


@pytest.mark.parametrize(("seed", "kind", "effect"), BEYOND_RANGE)
def test_an_effect_beyond_its_physical_range_is_drawn_on_another_configuration(
    seed, kind, effect, tmp_path
):
    first = F.draw_config(seed, "small", "effect", kind, effect=effect)
    assert F._sized_case(first | {"replica": 0}, redraw=True) is None
    files = F.write_family_case(seed, tmp_path, "small", role="effect", kind=kind, effect=effect)
    truth = _truth(files)
    assert truth["expected"] == effect
    assert truth["attempts"] > 1
    assert truth["config"]["seed"] == F._attempt_seed(seed, truth["attempts"])
    values = truth["effects"][effect]
    assert values and all(abs(v) <= _range(p) for p, v in values.items())
    assert 5.0 <= truth["significance"]["sigma_drawn"] <= 8.0


def test_written_config_is_the_configuration_written(tmp_path):
    seed, kind, effect = BEYOND_RANGE[0]
    written = F.written_config(seed, "small", "effect", kind, effect)
    truth = _truth(F.write_family_case(seed, tmp_path, "small", "effect", kind, effect=effect))
    assert written["attempts"] == truth["attempts"] > 1
    assert json.loads(json.dumps(written)) == truth["config"] | {"attempts": truth["attempts"]}
    # a null without 2-D harmonics is its seed's draw
    null = F.written_config(EXACT_SEED, "small", "null", "hall")
    assert null == F.draw_config(EXACT_SEED, "small", "null", "hall") | {
        "replica": 0,
        "attempts": 1,
    }
