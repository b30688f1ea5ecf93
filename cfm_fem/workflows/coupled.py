"""Coupled mechanical-magnetic Monte Carlo (paper eq. 12-15, section III-A, Table V).

For every trial t and scan point i (magnet frame, mm)::

    q_i          = bench.axis_positions_for(p_i)                 commanded axis positions
    E_p[t, i]    = HTM chain with the 21 errors of trial t and the vibration/delay of (t, i)
                   (exactly the kinematics kernels: same samples as `cfm-fem kinematics`)
    x_act[t, i]  = p_i + R_bm E_p[t, i]        (R_bm: bench -> magnet rotation of the placement)
    B_meas[t, i] = probe(B(x_act[t, i]))       (S_HP or the Table I model, probe axes = bench axes)
    E_f[t, i]    = (B_meas - B(p_i)) / B_ref   in units of 1e-4 B_ref

``B`` is a 2-D `Multipole` (QFDp4 by default) or an FEM map through
`cfm_fem.models.interpolation.LinearInterpolator`. Per point and component (Bx, By, Bz, |B|):
systematic error (mean), standard uncertainty (std), 95 % probabilistically symmetric interval, and
U95 = max(|low|, |high|). Pooled as in Table V: systematic = RMS over points of the per-point mean,
uncertainty = RMS over points of the per-point std, U_f = sqrt(systematic^2 + uncertainty^2).

Why B_ref and not the local field (paper eq. 14 divides by B_nom,i): a field component passes
through zero inside the aperture (B_x = 0 on the whole mid-plane y = 0 of a normal quadrupole,
both components at the centre), where B_nom,i -> 0 makes eq. 14 infinite for any finite error;
"units" in magnet measurement are 1e-4 of the main harmonic at R_ref (`Multipole.b_ref`); for
an FEM map B_ref is given or max |B| over the nodes, and every output states it.

Alignment. ``align="placement"`` puts the magnet where the bench file says: a trial's common
offset (the systematic E_p of the bench) is a field error. ``align="probe"`` models the paper's
procedure (section III-B: the magnet frame is located with respect to the probe after the
alignment): per trial the probe error at the alignment point (the magnet-frame origin, no
vibration) is subtracted, so only the variation of E_p over the scan region and the per-point
noise reach the field.

Random numbers: the 21 errors and the noise come from the kinematics counter-based streams of
``seed`` (trial t, point index i); the probe factors of point i from
``SeedSequence(seed, spawn_key=(PROBE_STREAM, i))``. Results do not depend on ``block_points``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from threadpoolctl import threadpool_limits

from .. import _kernels as K
from ..errors import CfmInputError
from ..models.bench import Bench, MagnetPlacement, ReadingDelay
from ..models.field_model import QUANTITIES, FieldModel
from ..models.kinematics.geometry import draw_error_sets, kernel_geometry, noise_keys
from ..models.mc import symmetric_interval
from ..models.multipole import UNIT
from ..models.probe import HallProbe, apply_probe
from ..threads import check_memory

__all__ = [
    "CoupledResult",
    "default_region",
    "centred_on_travel",
    "run_coupled",
    "pool_table_v",
    "field_budget",
]

PROBE_STREAM = 0x50524F42
#: Samples kept per point for the pooled E_f histogram.
HIST_PER_POINT = 256
ALIGN_CHOICES = ("placement", "probe")


# --------------------------------------------------------------------------- field models


def default_region(
    r_max_mm: float = 10.0, step_mm: float = 2.0, z_mm=(-100.0, -50.0, 0.0, 50.0, 100.0)
) -> np.ndarray:
    """Scan points of the coupled model: a transverse grid inside the circle r <= r_max, per z.

    Parameters
    ----------
    r_max_mm : float
        Radius of the region (the default equals QFDp4's assumed R_ref = 10 mm: the paper's probe
        volume "in the magnet aperture", where the harmonics are valid).
    step_mm : float
        Grid step in x and y, centred on the axis.
    z_mm : sequence of float
        Planes along the magnet axis (the 2-D field does not depend on z; the bench errors do).

    Returns
    -------
    ndarray, shape (n, 3), mm, magnet frame
    """
    k = int(np.floor(r_max_mm / step_mm + 1e-9))
    g = step_mm * np.arange(-k, k + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    keep = x**2 + y**2 <= r_max_mm**2 + 1e-9
    xy = np.column_stack([x[keep], y[keep]])
    z = np.asarray(z_mm, dtype=np.float64)
    return np.column_stack([np.tile(xy, (z.size, 1)), np.repeat(z, xy.shape[0])])  # z slowest


def centred_on_travel(bench: Bench) -> Bench:
    """A copy of ``bench`` whose magnet origin sits at mid-travel of X and Y.

    The rotation and the Z travel of the magnet origin are kept: a quick way to make a region
    around the magnet axis reachable on a bench file whose placement is only a placeholder.
    """
    q0 = bench.axis_positions_for(np.zeros((1, 3)))[0]
    q0[0] = 0.5 * bench.strokes_mm[0]
    q0[1] = 0.5 * bench.strokes_mm[1]
    t = q0 + bench.mounts_mm.sum(0) + np.asarray(bench.tool_offset_mm, dtype=np.float64)
    placement = MagnetPlacement(
        rotation_rad=np.asarray(bench.magnet.rotation_rad, dtype=np.float64), translation_mm=t
    )
    note = (
        f"magnet placement moved to mid-travel of X and Y: translation {np.round(t, 6).tolist()} "
        "mm (cfm_fem.workflows.coupled.centred_on_travel)"
    )
    return replace(bench, magnet=placement, assumptions=tuple(bench.assumptions) + (note,))


# --------------------------------------------------------------------------- result


@dataclass
class CoupledResult:
    """Per-point statistics of the field error E_f, in units of 1e-4 B_ref.

    Attributes
    ----------
    points : ndarray, shape (n, 3), mm
        Scan points, magnet frame.
    q_cmd : ndarray, shape (n, 3), mm
        Commanded axis positions.
    B_nom : ndarray, shape (n, 3), T
    mean, std, low, high : ndarray, shape (n, 4), units
        Per point and quantity (Bx, By, Bz, |B|): systematic error, standard uncertainty and the
        95 % probabilistically symmetric interval.
    batch_mean, batch_std : ndarray, shape (h, n, 4), units
        The same per batch of trials (numerical uncertainty of pooled values).
    n_valid : ndarray, shape (n,), int64
        Trials whose actual position stayed inside the map (all of them for a multipole).
    ep_mean, ep_std : ndarray, shape (n, 3), mm
        Probe position error per point (bench frame), as it entered the field model.
    hist_ef : ndarray, shape (n_h, 4), units
        First ``HIST_PER_POINT`` trials of every point, pooled (histograms).
    probe_point : int
        Index of the point whose samples are kept whole (largest |B_nom|).
    samples_ep : ndarray, shape (M, 3), mm
        E_p of every trial at ``probe_point`` (bench frame).
    samples_ef : ndarray, shape (M, 4), units
        E_f of every trial at ``probe_point``.
    field : FieldModel
    trials, seed : int
    align : str
    probe : HallProbe
    region : str
    seconds : float
    notes : list of str
    """

    points: np.ndarray
    q_cmd: np.ndarray
    B_nom: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    batch_mean: np.ndarray
    batch_std: np.ndarray
    n_valid: np.ndarray
    ep_mean: np.ndarray
    ep_std: np.ndarray
    hist_ef: np.ndarray
    probe_point: int
    samples_ep: np.ndarray
    samples_ef: np.ndarray
    field: FieldModel
    trials: int
    seed: int
    align: str
    probe: HallProbe
    region: str
    seconds: float
    notes: list = field(default_factory=list)

    @property
    def u95(self) -> np.ndarray:
        """max(|low|, |high|) per point and quantity, shape (n, 4), units."""
        return np.maximum(np.abs(self.low), np.abs(self.high))

    def pooled(self) -> dict:
        """Table V pooling per quantity and over the model's components ("all"), with the
        numerical standard uncertainty from the batches (see `pool_table_v`)."""
        return pool_table_v(
            self.mean, self.std, self.field.components, self.batch_mean, self.batch_std, self.u95
        )


def pool_table_v(mean, std, components=(0, 1), batch_mean=None, batch_std=None, u95=None) -> dict:
    """Pool per-point statistics as in Table V (and Table IV): RMS over points.

    Parameters
    ----------
    mean, std : ndarray, shape (n, 4), units
        Per point and quantity (Bx, By, Bz, |B|).
    components : tuple of int
        Quantities pooled together in the "all" entry.
    batch_mean, batch_std : ndarray, shape (h, n, 4), optional
        Per-batch statistics; with them each value gets ``*_num_u``, the standard deviation of
        the batch values over sqrt(h) (JCGM 101 7.9.4 style numerical standard uncertainty).
    u95 : ndarray, shape (n, 4), optional
        Per-point 95 % bounds; adds their median, 95th percentile and maximum over points.

    Returns
    -------
    dict of name -> dict, values in units
    """

    def pool(m, s):
        sys_ = np.sqrt(np.mean(m**2))
        u = np.sqrt(np.mean(s**2))
        return sys_, u, np.hypot(sys_, u)

    out = {}
    groups = [(q, [c]) for c, q in enumerate(QUANTITIES)] + [("all", list(components))]
    for name, cols in groups:
        m, s = mean[:, cols], std[:, cols]
        sys_, u, uf = pool(m, s)
        d = {
            "systematic_units": float(sys_),
            "std_units": float(u),
            "U_f_units": float(uf),
            "systematic_mean_units": float(np.mean(m)),
            "systematic_max_abs_units": float(np.max(np.abs(m))),
            "std_max_units": float(np.max(s)),
        }
        if batch_mean is not None:
            b = np.array(
                [
                    pool(bm[:, cols], bs[:, cols])
                    for bm, bs in zip(batch_mean, batch_std, strict=True)
                ]
            )
            h = b.shape[0]
            num = b.std(axis=0, ddof=1) / np.sqrt(h) if h > 1 else np.full(3, np.nan)
            d.update(
                systematic_num_u=float(num[0]), std_num_u=float(num[1]), U_f_num_u=float(num[2])
            )
        if u95 is not None:
            v = u95[:, cols].ravel()
            d.update(
                u95_p50_units=float(np.percentile(v, 50)),
                u95_p95_units=float(np.percentile(v, 95)),
                u95_max_units=float(v.max()),
            )
        out[name] = d
    return out


# --------------------------------------------------------------------------- Monte Carlo


def _probe_factors_rng(seed: int, i: int) -> np.random.Generator:
    return np.random.default_rng(
        np.random.SeedSequence(int(seed), spawn_key=(PROBE_STREAM, int(i)))
    )


#: Bytes held per trial at once: the 21 errors of every trial and their chain terms, and per
#: point of a block its positions, fields, flags and probe draws (about 100 bytes).
TRIAL_BYTES = 8 * 21 * 2 + 400


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
def run_coupled(
    field_model: FieldModel,
    bench: Bench,
    points=None,
    *,
    probe: HallProbe | None = None,
    trials: int = 100_000,
    seed: int = 0,
    align: str = "placement",
    batches: int = 10,
    block_points: int | None = None,
    region: str | None = None,
    progress=None,
) -> CoupledResult:
    """Coupled Monte Carlo of the field error at scan points (paper eq. 12-14).

    Parameters
    ----------
    field_model : FieldModel
    bench : Bench
        Kinematics (21 errors, vibration, delay) and the magnet placement.
    points : ndarray, shape (n, 3), mm, optional
        Scan points in the magnet frame; default `default_region` with r_max = R_ref (multipole)
        or an error for a map (give the points).
    probe : HallProbe, optional
        Default the paper's S_HP (uniform, std 0.15 %).
    trials : int
        Monte Carlo trials M (every point sees every trial).
    seed : int
    align : {"placement", "probe"}
        See the module docstring.
    batches : int
        Trials are split into this many consecutive batches for the numerical uncertainty.
    block_points : int, optional
        Points per block (memory ~ 100 * M * block bytes); results do not depend on it.
    region : str, optional
        Description of ``points`` for outputs.
    progress : callable(int), optional
        Called with the number of points finished.

    Returns
    -------
    CoupledResult
    """
    t_start = time.perf_counter()
    probe = HallProbe() if probe is None else probe
    if align not in ALIGN_CHOICES:
        raise CfmInputError(f"align must be one of {ALIGN_CHOICES}; found {align!r}")
    trials = int(trials)
    if trials < 2 * max(int(batches), 1):
        raise CfmInputError(f"trials must be at least 2 per batch ({2 * batches}); got {trials}")
    check_memory("--trials", trials, TRIAL_BYTES, "trials")
    notes = []
    pts, region = _scan_points(field_model, points, region)
    n = len(pts)
    q, B_nom = _nominal(field_model, bench, pts)
    g = kernel_geometry(bench)
    nkey, fkey = noise_keys(seed)
    params = draw_error_sets(bench, trials, seed)
    e_align = None
    if align == "probe":
        e_align = _probe_at_origin(bench, g, params, nkey, fkey)
        notes.append(
            "align=probe: per trial the probe error at the magnet-frame origin (no vibration) is "
            "subtracted (magnet located with the probe, paper III-B); rotations are not re-aligned"
        )
    acc = _Accumulator(n, trials, max(int(batches), 1), B_nom)
    nb = block_points or max(1, min(n, int(4_000_000 // trials)))
    for a in range(0, n, nb):
        b = min(n, a + nb)
        blk = np.empty((trials, b - a, 3))
        K.coupled_probe_errors(
            params, 0, q[a:b], np.arange(a, b, dtype=np.int64), nkey, fkey, g, blk
        )
        if e_align is not None:
            blk -= e_align
        acc.add_block(a, blk, pts, field_model, bench, probe, seed)
        if progress is not None:
            progress(b - a)
    notes += _run_notes(field_model, int((trials - acc.n_valid).sum()), n * trials)
    return CoupledResult(
        points=pts,
        q_cmd=q,
        B_nom=B_nom,
        mean=acc.mean,
        std=acc.std,
        low=acc.low,
        high=acc.high,
        batch_mean=acc.bmean,
        batch_std=acc.bstd,
        n_valid=acc.n_valid,
        ep_mean=acc.ep_mean,
        ep_std=acc.ep_std,
        hist_ef=acc.hist[np.isfinite(acc.hist[:, 0])],
        probe_point=acc.probe_point,
        samples_ep=acc.samples_ep,
        samples_ef=acc.samples_ef,
        field=field_model,
        trials=trials,
        seed=int(seed),
        align=align,
        probe=probe,
        region=region or f"{n} user-given points",
        seconds=time.perf_counter() - t_start,
        notes=notes,
    )


def _scan_points(field_model: FieldModel, points, region):
    """The scan points, shape (n, 3) mm, checked, and their description (default region of a
    multipole when ``points`` is None)."""
    if points is None:
        if field_model.multipole is None:
            raise CfmInputError("give the scan points for a field map (no default region)")
        points = default_region(field_model.multipole.r_ref)
        region = region or (
            f"default: transverse grid step 2 mm inside r <= R_ref = "
            f"{field_model.multipole.r_ref:g} mm, z in -100, -50, 0, 50, 100 mm"
        )
    pts = np.ascontiguousarray(np.atleast_2d(np.asarray(points, dtype=np.float64)))
    if pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise CfmInputError(f"points must be finite, shape (n, 3) in mm; got {pts.shape}")
    return pts, region


def _nominal(field_model: FieldModel, bench: Bench, pts):
    """Commanded axis positions (n, 3) mm and nominal field (n, 3) T of the scan points;
    refuses points outside the strokes or the field map."""
    q = bench.axis_positions_within_strokes(pts, "the scan region (--radius, --step, --z)")
    B_nom, inside = field_model.field(pts)
    if not inside.all():
        i = int(np.argmax(~inside))
        raise CfmInputError(
            f"scan point {i} at {pts[i].tolist()} mm is outside the field map; check the scan "
            "region (--radius, --step, --z)"
        )
    return q, B_nom


def _probe_at_origin(bench: Bench, g, params, nkey, fkey):
    """Probe error of every trial at the magnet-frame origin without vibration, (M, 1, 3) mm."""
    q0 = np.ascontiguousarray(bench.axis_positions_for(np.zeros((1, 3))))
    e_align = np.empty((len(params), 1, 3))
    still = g._replace(sig=np.zeros(3), speed=np.zeros(3), tau_code=-1)  # no vibration
    K.coupled_probe_errors(params, 0, q0, np.zeros(1, dtype=np.int64), nkey, fkey, still, e_align)
    return e_align


class _Accumulator:
    """Per-point statistics of the field error E_f of `run_coupled`, filled block by block."""

    def __init__(self, n: int, trials: int, h: int, B_nom):
        self.trials = trials
        self.B_nom = B_nom
        self.absB_nom = np.sqrt((B_nom**2).sum(1))
        self.edges = np.linspace(0, trials, h + 1).astype(int)
        self.mean = np.zeros((n, 4))
        self.std = np.zeros((n, 4))
        self.low = np.zeros((n, 4))
        self.high = np.zeros((n, 4))
        self.bmean = np.zeros((h, n, 4))
        self.bstd = np.zeros((h, n, 4))
        self.n_valid = np.zeros(n, dtype=np.int64)
        self.ep_mean = np.zeros((n, 3))
        self.ep_std = np.zeros((n, 3))
        self.keep = min(HIST_PER_POINT, trials)
        self.hist = np.empty((n * self.keep, 4))
        self.probe_point = int(np.argmax(self.absB_nom))
        self.samples_ep = self.samples_ef = None

    def add_block(self, a: int, blk, pts, field_model, bench, probe, seed) -> None:
        """Points a .. a + k - 1 with their probe errors ``blk`` (M, k, 3), bench frame, mm."""
        trials, k = blk.shape[0], blk.shape[1]
        b = a + k
        r_bm = bench.bench_to_magnet_rotation()
        self.ep_mean[a:b] = blk.mean(axis=0)
        self.ep_std[a:b] = blk.std(axis=0, ddof=1)
        actual = pts[a:b][None, :, :] + blk @ r_bm.T  # (M, k, 3) magnet frame
        B_act, ok = field_model.field(actual.reshape(-1, 3))
        B_act = B_act.reshape(trials, k, 3)
        ok = ok.reshape(trials, k)
        to_units = 1.0 / (UNIT * field_model.b_ref_T)
        for j in range(k):
            i = a + j
            draws = probe.sample(_probe_factors_rng(seed, i), (trials,))
            if probe.model == "paper":
                Bm = draws.gain * B_act[:, j]
            else:  # probe axes = bench axes: rotate into the probe, read, rotate back
                Bm = apply_probe(B_act[:, j] @ r_bm, draws) @ r_bm.T
            err = np.empty((trials, 4))
            err[:, :3] = (Bm - self.B_nom[i]) * to_units
            err[:, 3] = (np.sqrt((Bm**2).sum(1)) - self.absB_nom[i]) * to_units
            if not ok[:, j].all():
                err[~ok[:, j]] = np.nan
            self._point(i, err, ok[:, j], pts)
            if i == self.probe_point:
                self.samples_ep = blk[:, j].copy()
                self.samples_ef = err.copy()

    def _point(self, i: int, err, v, pts) -> None:
        """Statistics of point i from its errors ``err`` (M, 4) units, ``v`` the valid trials."""
        trials = self.trials
        self.n_valid[i] = int(v.sum())
        e_ok = err[v] if self.n_valid[i] < trials else err
        if len(e_ok) < 2:
            raise CfmInputError(
                f"scan point {i} at {pts[i].tolist()} mm: the perturbed positions leave the "
                "field map in (nearly) every trial; choose points farther from its border"
            )
        self.mean[i] = e_ok.mean(axis=0)
        self.std[i] = e_ok.std(axis=0, ddof=1)
        lo, hi = symmetric_interval(e_ok, 0.95, axis=0)
        self.low[i], self.high[i] = lo, hi
        for s in range(len(self.edges) - 1):
            e = err[self.edges[s] : self.edges[s + 1]]
            e = e[np.isfinite(e[:, 0])]
            self.bmean[s, i] = e.mean(axis=0)
            self.bstd[s, i] = e.std(axis=0, ddof=1)
        keep = self.keep
        self.hist[i * keep : (i + 1) * keep] = err[:keep]


def _run_notes(field_model: FieldModel, lost: int, total: int) -> list[str]:
    """The notes of a coupled run on what its numbers leave out."""
    notes = []
    if lost:
        notes.append(
            f"{lost} of {total} perturbed positions fell outside the field map and were left "
            "out of the statistics of their point"
        )
    if field_model.multipole is not None:
        notes.append(
            "2-D multipole: B_z = 0 everywhere and nothing depends on z (no fringe field); the "
            "'all' pooling covers Bx and By"
        )
    notes.append(
        "probe axes are taken parallel to the bench axes; the carriage rotations (urad) do not "
        "turn the probe in the model"
    )
    return notes


def _bench_without_errors(bench: Bench) -> Bench:
    quiet = bench.scaled_errors(0.0)
    return replace(
        quiet,
        vibration_std_mm=np.zeros(3),
        delay=ReadingDelay(model="normal", std_mm=np.zeros(3)),
    )


def field_budget(
    field_model: FieldModel,
    bench: Bench,
    points,
    *,
    probe: HallProbe | None = None,
    trials: int = 20_000,
    seed: int = 0,
    align: str = "placement",
) -> dict:
    """Split of the pooled E_f between positioning and probe (two extra Monte Carlo runs).

    Returns
    -------
    dict
        ``positioning_only`` (exact probe) and ``probe_only`` (bench without errors, vibration or
        delay): the "all" pooling of each (units), with the trial count; the two variances add up
        to the total one when the effects are independent and small.
    """
    probe = HallProbe() if probe is None else probe
    exact = HallProbe.exact(probe.model)
    kw = dict(trials=trials, seed=seed, align=align)
    pos = run_coupled(field_model, bench, points, probe=exact, **kw).pooled()["all"]
    prb = run_coupled(field_model, _bench_without_errors(bench), points, probe=probe, **kw)
    return {
        "trials": int(trials),
        "positioning_only": pos,
        "probe_only": prb.pooled()["all"],
        "definition": "pooled 'all' row of Table V with the probe exact (positioning_only) and "
        "with the bench free of geometric errors, vibration and delay (probe_only)",
    }
