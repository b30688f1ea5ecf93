"""Small synthetic recordings of a simulated bench (tests, README example, demonstrations).

A "real" bench is one draw of the 21 error amplitudes from the bench's PDFs (the same streams as
`kinematics.draw_error_sets`, trial ``bench_trial``); each reading adds its own vibration and
reading delay (normal, the bench's stds) and, optionally, tracker noise or a reversal
(backlash) on one axis. Everything is computed with the exact plain-numpy HTM chain
(`kinematics.probe_errors_for_bench`), so these files test the comparison against an independent
implementation of the same model. The per-reading axis noise is normal with the bench's
``noise_std_mm`` (vibration and a normal reading delay); a speed x tau delay is not simulated.
"""

from __future__ import annotations

import numpy as np

from ..models.bench import AXES, Bench
from ..models.kinematics.chain import probe_errors_for_bench
from ..models.kinematics.geometry import draw_error_sets
from ..models.multipole import Multipole
from ..models.probe import HallProbe
from ..models.recordings import Recording

__all__ = ["synthetic_tracker", "synthetic_hall_map", "hall_map_points"]


def _axis_noise(bench: Bench, rng, n) -> np.ndarray:
    return rng.standard_normal((n, 3)) * bench.noise_std_mm()


def synthetic_tracker(
    bench: Bench,
    *,
    seed: int = 0,
    bench_trial: int = 0,
    reps: int = 5,
    grid=(3, 3, 3),
    tracker_std_um: float = 0.0,
    iso_axis: str | None = "x",
    iso_targets: int = 5,
    iso_runs: int = 3,
    reversal_um: float = 0.0,
    drift_um_per_s: float = 0.0,
) -> Recording:
    """A laser-tracker recording of one simulated bench.

    Parameters
    ----------
    bench : Bench
    seed : int
        Seed of the bench draw (with ``bench_trial``) and of the per-reading noise.
    bench_trial : int
        Which trial of ``draw_error_sets(bench, ., seed)`` is "the real bench".
    reps : int
        Repetitions of the volumetric grid.
    grid : tuple of 3 int
        Points per axis of the volumetric grid (linspace over each stroke).
    tracker_std_um : float
        Standard deviation of the tracker's own noise per coordinate, um.
    iso_axis : {"x", "y", "z"} or None
        Add a bidirectional single-axis run (ISO 230-2) along this axis at mid-travel of the
        others, with ``dir`` columns; None for none.
    iso_targets, iso_runs : int
        Targets of that run and runs per direction.
    reversal_um : float
        Reversal value added to the single-axis run: +reversal/2 on positive approaches,
        -reversal/2 on negative ones, along ``iso_axis``.
    drift_um_per_s : float
        Thermal drift along z, um per second of recording (every reading takes 2 s).

    Returns
    -------
    Recording
        ``kind="tracker"`` with ``t_s`` (and ``dir`` when ``iso_axis`` is set).
    """
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0x53594E54,)))
    params = draw_error_sets(bench, 1, seed, start=bench_trial)
    strokes = bench.strokes_mm
    axes = [np.linspace(0.0, strokes[k], int(grid[k])) for k in range(3)]
    q_grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    rows_q, rows_id, rows_rep, rows_dir = [], [], [], []
    for r in range(reps):
        rows_q.append(q_grid)
        rows_id.append(np.arange(len(q_grid)))
        rows_rep.append(np.full(len(q_grid), r + 1))
        rows_dir.append(np.zeros((len(q_grid), 3), dtype=int))
    if iso_axis is not None:
        a = AXES.index(iso_axis)
        base = 0.5 * strokes
        targets = np.linspace(0.1 * strokes[a], 0.9 * strokes[a], int(iso_targets))
        first_id = len(q_grid)
        for run in range(iso_runs):
            for sign, order in ((1, targets), (-1, targets[::-1])):
                q = np.repeat(base[None, :], len(order), axis=0)
                q[:, a] = order
                ids = first_id + np.searchsorted(targets, order)
                rows_q.append(q)
                rows_id.append(ids)
                rows_rep.append(np.full(len(order), 2 * run + (1 if sign > 0 else 2)))
                d = np.zeros((len(order), 3), dtype=int)
                d[:, a] = sign
                rows_dir.append(d)
    q = np.concatenate(rows_q)
    pid = np.concatenate(rows_id)
    rep = np.concatenate(rows_rep)
    direction = np.concatenate(rows_dir)
    n = len(q)
    dq = _axis_noise(bench, rng, n)
    e = probe_errors_for_bench(bench, params, q, dq[None])[0]
    if iso_axis is not None and reversal_um:
        a = AXES.index(iso_axis)
        e[:, a] += 0.5e-3 * reversal_um * direction[:, a]
    t_s = 2.0 * np.arange(n)
    e[:, 2] += 1e-3 * drift_um_per_s * t_s
    meas = bench.nominal_probe_mm(q) + e + 1e-3 * tracker_std_um * rng.standard_normal((n, 3))
    return Recording(
        kind="tracker",
        point_id=pid,
        rep=rep,
        cmd=q,
        meas=meas,
        t_s=t_s,
        dir=direction if iso_axis is not None else None,
        speed=np.zeros(n),
        source=f"synthetic tracker (seed {seed}, bench trial {bench_trial})",
    )


def hall_map_points(step_mm: float = 2.0, r_max_mm: float = 8.0, z_mm=(-50.0, 0.0, 50.0)):
    """Points of a Fig. 11-like map: the mid-plane y = 0, |x| <= r_max, a few z; (n, 3), mm."""
    k = int(np.floor(r_max_mm / step_mm + 1e-9))
    x = step_mm * np.arange(-k, k + 1)
    z = np.asarray(z_mm, dtype=np.float64)
    xx, zz = np.meshgrid(x, z, indexing="ij")
    return np.column_stack([xx.ravel(), np.zeros(xx.size), zz.ravel()])


def synthetic_hall_map(
    multipole: Multipole,
    bench: Bench,
    *,
    seed: int = 0,
    bench_trial: int = 0,
    reps: int = 10,
    points=None,
    probe: HallProbe | None = None,
    magnet_offset_mm=(0.0, 0.0),
) -> Recording:
    """A Hall map of a multipole measured by one simulated bench and probe.

    Parameters
    ----------
    multipole : Multipole
        The true field (optionally displaced by ``magnet_offset_mm``).
    bench : Bench
        Bench model; its magnet placement maps the points to axis positions.
    seed, bench_trial : int
        As `synthetic_tracker`.
    reps : int
        Repetitions of the map.
    points : ndarray, shape (n, 3), mm, optional
        Commanded points in the magnet frame; default `hall_map_points`.
    probe : HallProbe, optional
        Default the paper's S_HP, drawn per reading.
    magnet_offset_mm : (float, float)
        True transverse offset of the magnet (feed-down), mm; (0, 0) for a perfect placement.

    Returns
    -------
    Recording
        ``kind="hall"``, coordinates in the magnet frame, B in T.
    """
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(0x48414C4C,)))
    probe = HallProbe() if probe is None else probe
    pts = hall_map_points() if points is None else np.asarray(points, dtype=np.float64)
    params = draw_error_sets(bench, 1, seed, start=bench_trial)
    m = pts.shape[0]
    cmd = np.tile(pts, (reps, 1))
    pid = np.tile(np.arange(m), reps)
    rep = np.repeat(np.arange(1, reps + 1), m)
    n = len(cmd)
    q = bench.axis_positions_for(cmd)
    e = probe_errors_for_bench(bench, params, q, _axis_noise(bench, rng, n)[None])[0]
    actual = cmd + e @ bench.bench_to_magnet_rotation().T
    true = multipole.moved(*magnet_offset_mm)
    B = probe.measure(true.field(actual), rng)
    return Recording(
        kind="hall",
        point_id=pid,
        rep=rep,
        cmd=cmd,
        B=B,
        t_s=2.0 * np.arange(n),
        source=f"synthetic Hall map (seed {seed}, bench trial {bench_trial})",
    )
