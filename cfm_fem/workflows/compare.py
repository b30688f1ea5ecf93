"""Simulation against recordings: Table IV / Fig. 12 (tracker) and Table V / Fig. 13 (Hall map).

Tracker. The measured probe error of a reading is E = meas - nominal, nominal = cmd + mount
offsets + tool offset (bench frame: the tracker measures the probe's reflector in the bench
frame, `cfm_fem.io.recordings`). Per point: mean over repetitions (systematic)
and standard deviation (ddof = 1). Pooled as Table IV (`kinematics.pool_table_iv`: RMS over
points). The simulated distribution at the same commanded positions comes from
`kinematics.run_kinematics`. Per point and axis the standardised residual is
z = (mean_exp - mean_sim) / sqrt(std_sim^2 + u_tracker^2): under the model a real bench is one
draw of the trial distribution, so |z| > 2 at many points says the model misses something.

Fig. 12 / Fig. 13 view: per axis (per field component) the interval systematic -+ 2 u (k = 2, as
the paper's "95 %" bars) of simulation and experiment, and whether they overlap.

Hall map. E_f = (B_meas - B_ref_field(cmd)) / B_ref per reading, in units; per point mean and std
over repetitions; pooled as Table V (`coupled.pool_table_v`). The simulated side is
`coupled.run_coupled` at the map's points.

ISO 230-2. Rows whose ``dir`` is non-zero on exactly one axis and that share the other two
commanded coordinates form a single-axis line; a line with >= 2 targets and >= 2 runs per
direction at every target is evaluated with `iso230.evaluate_records` (deviation = E along that
axis).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import CfmInputError
from ..models.bench import AXES, Bench
from ..models.field_model import QUANTITIES, FieldModel
from ..models.iso230 import evaluate_records
from ..models.kinematics.monte_carlo import KinematicsResult, pool_table_iv, run_kinematics
from ..models.multipole import UNIT
from ..models.probe import HallProbe
from ..models.recordings import Recording, check_hall_scale, check_tracker_scale
from .coupled import CoupledResult, pool_table_v, run_coupled

__all__ = [
    "TrackerComparison",
    "HallComparison",
    "per_point_stats",
    "interval_view",
    "iso_lines",
    "compare_tracker",
    "compare_hall",
]

K_COVERAGE = 2.0


def per_point_stats(rec: Recording, values: np.ndarray):
    """Mean and standard deviation (ddof = 1) of ``values`` over the repetitions of each point.

    Parameters
    ----------
    rec : Recording
    values : ndarray, shape (n, k)
        One row per recording row.

    Returns
    -------
    ids : ndarray, shape (m,), int64
    count : ndarray, shape (m,), int64
    mean, std : ndarray, shape (m, k)
        ``std`` is NaN for a point with a single repetition.
    """
    ids, index = rec.point_index()
    count = np.bincount(index, minlength=ids.size)
    k = values.shape[1]
    s = np.zeros((ids.size, k))
    np.add.at(s, index, values)
    mean = s / count[:, None]
    d = np.zeros((ids.size, k))
    np.add.at(d, index, (values - mean[index]) ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        std = np.where(count[:, None] > 1, np.sqrt(d / np.maximum(count - 1, 1)[:, None]), np.nan)
    return ids, count.astype(np.int64), mean, std


def interval_view(sim: dict, exp: dict, names, unit: str, k: float = K_COVERAGE) -> list[dict]:
    """Fig. 12/13 rows: systematic -+ k u of simulation and experiment, and their overlap.

    Parameters
    ----------
    sim, exp : dict of name -> {"systematic_<unit>": .., "std_<unit>": ..}
    names : sequence of str
    unit : str
        ``"um"`` or ``"units"`` (the key suffix).

    Returns
    -------
    list of dict
        ``{"name", "sim": {"systematic", "std", "low", "high"}, "exp": {...}, "overlap"}``.
    """
    rows = []
    for name in names:
        row = {"name": name}
        for side, d in (("sim", sim), ("exp", exp)):
            s, u = d[name][f"systematic_{unit}"], d[name][f"std_{unit}"]
            row[side] = {"systematic": s, "std": u, "low": s - k * u, "high": s + k * u}
        a, b = row["sim"], row["exp"]
        row["overlap"] = bool(a["low"] <= b["high"] and b["low"] <= a["high"])
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- tracker


@dataclass
class TrackerComparison:
    """Tracker recording against the kinematic simulation.

    Attributes
    ----------
    ids : ndarray, shape (m,), int64
    cmd, nominal : ndarray, shape (m, 3), mm
    count : ndarray, shape (m,), int64
        Repetitions per point.
    exp_mean, exp_std : ndarray, shape (m, 4), mm
        Measured error per point (x, y, z, |E|), bench frame.
    sim : KinematicsResult
        Simulation at ``cmd``.
    z : ndarray, shape (m, 3)
        Standardised residual of the per-point mean (module docstring).
    inside : ndarray, shape (m, 3), bool
        Measured mean inside the simulated 95 % interval of the point.
    readings_inside : ndarray, shape (3,)
        Fraction of single readings inside their point's simulated 95 % interval.
    pooled_exp, pooled_sim : dict
        Table IV pooling (`pool_table_iv`), um.
    fig12 : list of dict
        `interval_view` rows per axis.
    iso : list of dict
        ISO 230-2 results of the single-axis lines found.
    tracker_u_um : float
    notes : list of str
    """

    ids: np.ndarray
    cmd: np.ndarray
    nominal: np.ndarray
    count: np.ndarray
    exp_mean: np.ndarray
    exp_std: np.ndarray
    sim: KinematicsResult
    z: np.ndarray
    inside: np.ndarray
    readings_inside: np.ndarray
    pooled_exp: dict
    pooled_sim: dict
    fig12: list
    iso: list
    tracker_u_um: float
    source: str
    notes: list = field(default_factory=list)


def _with_norm(e: np.ndarray) -> np.ndarray:
    return np.column_stack([e, np.sqrt((e**2).sum(1))])


def check_within_strokes(rec: Recording, bench: Bench) -> list:
    """Refuse a tracker recording with a commanded position outside the bench's strokes (the
    bench model has no errors there; the first such row is named) or in another length unit
    than mm (`check_tracker_scale`); returns the notes of a gross mismatch."""
    outside = bench.outside_stroke(rec.cmd)
    if outside.any():
        i = int(np.argmax(outside))
        raise CfmInputError(
            f"commanded position {rec.cmd[i].tolist()} mm is outside the strokes "
            f"{bench.strokes_mm.tolist()} mm of the bench",
            file=rec.source,
            line=int(rec.lines[i]) or None,
        )
    if rec.meas is None:
        return []
    return check_tracker_scale(rec.cmd, rec.meas, bench.nominal_probe_mm, source=rec.source)


def compare_tracker(
    rec: Recording,
    bench: Bench,
    *,
    trials: int = 100_000,
    seed: int = 0,
    tracker_u_um: float = 0.0,
    progress=None,
) -> TrackerComparison:
    """Compare a laser-tracker recording with the kinematic Monte Carlo of ``bench``.

    Parameters
    ----------
    rec : Recording
        ``kind="tracker"``.
    bench : Bench
    trials, seed : int
        Monte Carlo of the simulated side.
    tracker_u_um : float
        Standard uncertainty of the tracker itself, um; added in quadrature to the simulated
        std in the standardised residuals (the paper's LT: 5 um).
    progress : callable(int), optional

    Returns
    -------
    TrackerComparison
    """
    if rec.kind != "tracker":
        raise CfmInputError(f"{rec.source}: expected a tracker recording; got a {rec.kind} map")
    check_within_strokes(rec, bench)
    e = rec.meas - bench.nominal_probe_mm(rec.cmd)
    ids, count, mean, std = per_point_stats(rec, _with_norm(e))
    _, cmd = rec.point_cmd()
    rep_pts = count > 1
    if not rep_pts.any():
        raise CfmInputError(
            "no point has two or more repetitions; the experimental uncertainty needs them",
            file=rec.source,
        )
    notes = []
    if not rep_pts.all():
        notes.append(
            f"{int((~rep_pts).sum())} point(s) with a single reading: left out of the pooled std"
        )
    pooled_exp = pool_table_iv(mean[rep_pts], std[rep_pts])
    sim = run_kinematics(bench, trials=trials, seed=seed, q_cmd=cmd, progress=progress)
    pooled_sim = sim.pooled
    u_sim = np.hypot(sim.std[:, :3], 1e-3 * tracker_u_um)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (mean[:, :3] - sim.mean[:, :3]) / u_sim
    inside = (mean[:, :3] >= sim.low[:, :3]) & (mean[:, :3] <= sim.high[:, :3])
    _, index = rec.point_index()
    r_in = (e >= sim.low[index, :3]) & (e <= sim.high[index, :3])
    fig12 = interval_view(pooled_sim, pooled_exp, AXES, "um")
    iso = iso_lines(rec, e)
    notes.append(
        "Table IV / Fig. 12 compare as the paper does, but the two stds differ in kind: the "
        "experimental std is the repeatability of this one bench (noise, drift, tracker), the "
        "simulated std the spread over all benches the error PDFs describe; the per-point z "
        "residuals are the like-for-like test"
    )
    if tracker_u_um:
        notes.append(
            f"tracker standard uncertainty {tracker_u_um:g} um added in quadrature to the "
            "simulated std in the standardised residuals"
        )
    else:
        notes.append(
            "the experimental values include the tracker's own uncertainty (not subtracted; "
            "--tracker-u-um adds it to the simulated side of the residuals)"
        )
    return TrackerComparison(
        ids=ids,
        cmd=cmd,
        nominal=bench.nominal_probe_mm(cmd),
        count=count,
        exp_mean=mean,
        exp_std=std,
        sim=sim,
        z=z,
        inside=inside,
        readings_inside=r_in.mean(axis=0),
        pooled_exp=pooled_exp,
        pooled_sim=pooled_sim,
        fig12=fig12,
        iso=iso,
        tracker_u_um=float(tracker_u_um),
        source=rec.source,
        notes=notes,
    )


def iso_lines(rec: Recording, e: np.ndarray, min_targets: int = 2) -> list[dict]:
    """ISO 230-2 evaluation of every bidirectional single-axis line of a tracker recording.

    Parameters
    ----------
    rec : Recording
        Needs ``dir``; without it the result is empty.
    e : ndarray, shape (n, 3), mm
        Measured error of each row (bench frame).

    Returns
    -------
    list of dict
        ``{"axis", "fixed_mm": {..}, "targets", "runs_up", "runs_down", "axis_values_um",
        "per_target": {...}}``; lengths in um.
    """
    if rec.dir is None:
        return []
    out = []
    moving = rec.dir != 0
    for a, name in enumerate(AXES):
        sel = moving[:, a] & (moving.sum(1) == 1)
        if sel.sum() < 2 * 2 * min_targets:
            continue
        others = [k for k in range(3) if k != a]
        key = np.round(rec.cmd[sel][:, others], 6)
        lines, which = np.unique(key, axis=0, return_inverse=True)
        rows = np.flatnonzero(sel)
        for li, fixed in enumerate(lines):
            r = rows[which.ravel() == li]
            pos = rec.cmd[r, a]
            d = rec.dir[r, a]
            targets = np.unique(np.round(pos, 6))
            if targets.size < min_targets:
                continue
            ok = all(
                (np.sum((np.abs(pos - t) < 1e-6) & (d > 0)) >= 2)
                and (np.sum((np.abs(pos - t) < 1e-6) & (d < 0)) >= 2)
                for t in targets
            )
            if not ok:
                continue
            res = evaluate_records(pos, e[r, a] * 1e3, d, tol=1e-6)
            out.append(
                {
                    "axis": name,
                    "fixed_mm": {AXES[k]: float(v) for k, v in zip(others, fixed, strict=True)},
                    "targets": int(targets.size),
                    "runs_up": int(res.n_up.min()),
                    "runs_down": int(res.n_down.min()),
                    "axis_values_um": res.axis_values(),
                    "per_target": {
                        "targets_mm": res.targets.tolist(),
                        "mean_up_um": res.mean_up.tolist(),
                        "mean_down_um": res.mean_down.tolist(),
                        "reversal_um": res.reversal.tolist(),
                        "repeatability_um": res.repeatability.tolist(),
                    },
                }
            )
    return out


# --------------------------------------------------------------------------- Hall map


@dataclass
class HallComparison:
    """Hall map against the reference field and the coupled simulation.

    Attributes
    ----------
    ids : ndarray, shape (m,), int64
    points : ndarray, shape (m, 3), mm
        Commanded points, magnet frame.
    count : ndarray, shape (m,), int64
    B_reference : ndarray, shape (m, 3), T
        Reference field at the commanded points.
    exp_mean, exp_std : ndarray, shape (m, 4), units
        Measured E_f per point (Bx, By, Bz, |B|).
    sim : CoupledResult
    z : ndarray, shape (m, 4)
        (mean_exp - mean_sim) / std_sim.
    pooled_exp, pooled_sim : dict
        Table V pooling (`pool_table_v`), units.
    fig13 : list of dict
        `interval_view` rows per component and "all".
    b_ref_T : float
    notes : list of str
    """

    ids: np.ndarray
    points: np.ndarray
    count: np.ndarray
    B_reference: np.ndarray
    exp_mean: np.ndarray
    exp_std: np.ndarray
    sim: CoupledResult
    z: np.ndarray
    pooled_exp: dict
    pooled_sim: dict
    fig13: list
    b_ref_T: float
    source: str
    notes: list = field(default_factory=list)


def compare_hall(
    rec: Recording,
    reference: FieldModel,
    bench: Bench,
    *,
    probe: HallProbe | None = None,
    trials: int = 100_000,
    seed: int = 0,
    align: str = "placement",
    progress=None,
) -> HallComparison:
    """Compare a Hall map with the reference field and with the coupled Monte Carlo.

    Parameters
    ----------
    rec : Recording
        ``kind="hall"``, commanded points in the magnet frame.
    reference : FieldModel
        The reference field (rotating-coil harmonics or an FEM map) and its B_ref.
    bench : Bench
    probe : HallProbe, optional
    trials, seed : int
    align : {"placement", "probe"}
        See `cfm_fem.workflows.coupled`.
    progress : callable(int), optional

    Returns
    -------
    HallComparison
    """
    if rec.kind != "hall":
        raise CfmInputError(f"{rec.source}: expected a Hall map; got a {rec.kind} recording")
    ref_B, inside = reference.field(rec.cmd)
    if not inside.all():
        i = int(np.argmax(~inside))
        raise CfmInputError(
            f"commanded point {rec.cmd[i].tolist()} mm is outside the reference field map",
            file=rec.source,
            line=int(rec.lines[i]) or None,
        )
    scale_notes = check_hall_scale(
        rec.B, ref_B, source=rec.source, reference=f"'{reference.source}'"
    )
    scale = 1.0 / (UNIT * reference.b_ref_T)
    err = np.column_stack(
        [
            (rec.B - ref_B) * scale,
            (np.sqrt((rec.B**2).sum(1)) - np.sqrt((ref_B**2).sum(1))) * scale,
        ]
    )
    ids, count, mean, std = per_point_stats(rec, err)
    _, pts = rec.point_cmd()
    rep_pts = count > 1
    if not rep_pts.any():
        raise CfmInputError(
            "no point has two or more repetitions; the experimental uncertainty needs them",
            file=rec.source,
        )
    notes = list(scale_notes)
    if not rep_pts.all():
        notes.append(
            f"{int((~rep_pts).sum())} point(s) with a single reading: left out of the pooled std"
        )
    comps = reference.components
    pooled_exp = pool_table_v(mean[rep_pts], std[rep_pts], comps)
    sim = run_coupled(
        reference,
        bench,
        pts,
        probe=probe,
        trials=trials,
        seed=seed,
        align=align,
        region=f"the {len(pts)} points of {rec.source}",
        progress=progress,
    )
    pooled_sim = sim.pooled()
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (mean - sim.mean) / sim.std
    names = [QUANTITIES[c] for c in comps] + ["all"]
    fig13 = interval_view(pooled_sim, pooled_exp, names, "units")
    notes.append(
        "E_f = (B_meas - B_reference(cmd)) / B_ref per reading; the reference field's own "
        "uncertainty is not included"
    )
    return HallComparison(
        ids=ids,
        points=pts,
        count=count,
        B_reference=reference.field(pts)[0],
        exp_mean=mean,
        exp_std=std,
        sim=sim,
        z=z,
        pooled_exp=pooled_exp,
        pooled_sim=pooled_sim,
        fig13=fig13,
        b_ref_T=reference.b_ref_T,
        source=rec.source,
        notes=notes,
    )
