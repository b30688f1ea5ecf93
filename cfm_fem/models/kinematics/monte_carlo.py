"""GUM-S1 Monte Carlo of the bench kinematics over the scan grid (paper Table IV).

``run_kinematics`` streams the trials, with exact per-point coverage intervals, Table IV
pooling and the JCGM 101 7.9 adaptive option.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ... import _kernels as K
from ...errors import CfmInputError
from ...threads import check_run_time, paced
from ..bench import ERROR_NAMES, Bench
from ..mc import numerical_tolerance, symmetric_ranks
from .geometry import _keys, kernel_geometry

__all__ = ["KinematicsResult", "pool_table_iv", "run_kinematics"]


# ---------------------------------------------------------------------------------------------
# Monte Carlo over the scan grid (GUM-S1 at paper scale)
# ---------------------------------------------------------------------------------------------

#: Quantities per point in the statistics arrays: the three error components and |E_p|.
QUANTITIES = ("x", "y", "z", "norm")


@dataclass
class KinematicsResult:
    """Per-point and pooled Monte Carlo statistics of the probe position error.

    Arrays are per point and quantity (E_x, E_y, E_z, |E_p|), in mm, bench frame.

    Attributes
    ----------
    q_cmd : ndarray, shape (n, 3), mm
        Commanded axis positions.
    nominal : ndarray, shape (n, 3), mm
        Nominal probe positions (bench frame).
    mean, std : ndarray, shape (n, 4), mm
        Systematic error (mean) and standard uncertainty (std, 1/(M-1) normalisation).
    low, high : ndarray, shape (n, 4), mm
        Probabilistically symmetric 95 % coverage interval (exact order statistics unless
        ``interval_method`` says otherwise).
    trials, seed : int
    pooled : dict
        Table IV pooling per axis (see :func:`pool_table_iv`).
    seconds : dict
        Wall time of each stage.
    interval_method : str
    notes : list of str
    """

    q_cmd: np.ndarray
    nominal: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    trials: int
    seed: int
    pooled: dict
    seconds: dict
    interval_method: str
    p: float = 0.95
    notes: list = field(default_factory=list)
    adaptive: dict | None = None

    @property
    def n_points(self) -> int:
        return self.q_cmd.shape[0]

    @property
    def up(self) -> np.ndarray:
        """U_p = sqrt(sys**2 + u**2) per point and quantity, shape (n, 4), mm."""
        return np.hypot(self.mean, self.std)

    @property
    def u95(self) -> np.ndarray:
        """max(|low|, |high|) per point and quantity: the 95 % bound of the error, (n, 4), mm."""
        return np.maximum(np.abs(self.low), np.abs(self.high))


def pool_table_iv(mean, std) -> dict:
    """Pool per-point statistics as in Table IV.

    Per axis: ``systematic`` = RMS over points of the per-point mean error, ``std`` = RMS over
    points of the per-point standard uncertainty, ``U_p = sqrt(systematic**2 + std**2)``, which is
    the RMS of the error over all points and trials. Other poolings ride along.

    Parameters
    ----------
    mean, std : ndarray, shape (n, 4), mm

    Returns
    -------
    dict of axis -> dict, values in um
    """
    out = {}
    for c, name in enumerate(QUANTITIES):
        m, s = mean[:, c], std[:, c]
        sys_rms = float(np.sqrt(np.mean(m**2)))
        u_rms = float(np.sqrt(np.mean(s**2)))
        out[name] = {
            "systematic_um": 1e3 * sys_rms,
            "std_um": 1e3 * u_rms,
            "U_p_um": 1e3 * float(np.hypot(sys_rms, u_rms)),
            "systematic_mean_um": 1e3 * float(np.mean(m)),
            "systematic_mean_abs_um": 1e3 * float(np.mean(np.abs(m))),
            "systematic_max_abs_um": 1e3 * float(np.max(np.abs(m))),
            "std_max_um": 1e3 * float(np.max(s)),
            "U_p_max_um": 1e3 * float(np.max(np.hypot(m, s))),
        }
    return out


#: Trials per kernel call. Part of the fixed layout: sums are grouped per block, so results are
#: bit-identical for any number of threads (not for another block size: last-bit rounding).
BLOCK = 4096
#: Half-width of the pilot's interval-end brackets in binomial standard deviations. A window
#: that misses its order statistic costs a recount of that point alone.
PILOT_SIGMAS = 4.0
#: Slots per interval-end window of the two-pass way (counting pass, then a pass that keeps
#: the values of the slot holding each end).
WINDOW_SLOTS = 32
#: Most widening rounds of a missed interval window (two-pass way). Each round widens a window
#: at least 5-fold, so 200 rounds span any finite range; only NaN or infinite positions (a bench
#: whose errors overflow) could miss for ever, and they are refused before the loop.
MAX_WIDEN_ROUNDS = 200
#: One pass: the windows narrow when the trials seen reach NARROW_FIRST and at each doubling,
#: up to three quarters of the run; each narrowing keeps the ranks that hold the final order
#: statistic with near certainty (NARROW_SIGMAS hypergeometric standard deviations,
#: `_narrow_ranks`). A window that loses its order statistic all the same is recounted in two
#: passes (one point).
NARROW_FIRST = 4 * BLOCK
NARROW_SIGMAS = 5.0
#: Largest store of window values of the one pass (125 MB for 1e6 trials on the reference
#: grid, 464 MB for 1e7); a run that would need more takes the two-pass way.
STORE_BYTES = 2**30


def _terms_array(n):
    """Chain terms of n trials, (n, 21) column-major: the hot loops read one term for
    consecutive trials (vectorised loads). The leading dimension is padded so that the 21
    columns do not all fall into the same L1 cache sets (a stride of 4096 * 8 bytes does)."""
    return np.empty((n + 8, 21), order="F")


def _blocks(t0, t1, block):
    for a in range(t0, t1, block):
        yield a, min(t1, a + block)


class _Engine:
    """Runs the kernels over blocks of trials for one bench and seed."""

    def __init__(self, bench, seed, block):
        self.g = kernel_geometry(bench)
        self.ekey, self.nkey, self.fkey = _keys(seed)
        self.block = int(block)
        self.params = np.empty((self.block, len(ERROR_NAMES)))
        self.terms = _terms_array(self.block)
        self.tkeys = np.empty(self.block, dtype=np.uint64)
        self.dirs = np.zeros((1 if self.g.linear else self.block, 9))
        self.dummy = np.zeros((1, 21))

    @property
    def fast(self) -> bool:
        """Constant profiles and normal noise: the hand-written hot loops apply."""
        return self.g.linear and self.g.tau_code < 0

    def prepare(self, a, b):
        """Draw the errors of trials a..b-1 (and the collapsed chain terms); return b - a."""
        n = b - a
        g = self.g
        K.draw_error_params(self.ekey, a, n, g.codes, g.pars, self.params)
        if g.linear:
            K.trial_terms(self.params[:n], g.stack, g.mounts, g.tool, self.terms)
        else:
            K.trial_directions(self.params[:n], g.stack, self.dirs)
        K.trial_keys(self.nkey, a, n, self.tkeys)
        return n

    @property
    def model(self):
        """The tuple the generic kernels take (`_kernels.fill_values`)."""
        g = self.g
        return (
            g.linear,
            self.terms if g.linear else self.dummy,
            self.params,
            g.sig,
            g.speed,
            g.tau_code,
            g.tau_par,
            self.nkey,
            self.tkeys,
            self.fkey,
            g.stack,
            g.mounts,
            g.tool,
            g.strokes,
            g.profiles,
            self.dirs,
        )

    def pilot_quantiles(self, n, q, pidx, kth, out):
        """Pilot order statistics of trials 0..n-1 (may exceed one block)."""
        big = _Engine.__new__(_Engine)
        big.__dict__.update(self.__dict__)
        big.block = n
        big.params = np.empty((n, len(ERROR_NAMES)))
        big.terms = _terms_array(n)
        big.tkeys = np.empty(n, dtype=np.uint64)
        big.dirs = np.zeros((1 if self.g.linear else n, 9))
        big.prepare(0, n)
        K.pass_pilot_quantiles(big.model, 0, n, q, pidx, kth, out)

    def pilot(self, a, n, q, pidx, out):
        K.pass_pilot(self.model, a, n, q, pidx, out)

    def window(self, a, n, q, pidx, *, shift, wlo, winv, acc, below, whist):
        """Generic pass 1 over trials a .. a+n-1 (counts in slot windows)."""
        K.pass_window(self.model, a, n, q, pidx, shift, wlo, winv, acc, below, whist)

    def capture(self, a, n, q, pidx, *, wlo, winv, target, vlo, vhi, offset, fill, buf):
        K.pass_capture(self.model, a, n, q, pidx, wlo, winv, target, vlo, vhi, offset, fill, buf)

    def keep(self, a, n, q, pidx, *, shift, lo, hi, acc, below, store):
        """The one-pass counting and keeping over the prepared block of trials a .. a+n-1
        (`_kernels.pass_keep` on the hot path, `_kernels.pass_keep_model` otherwise)."""
        g = self.g
        st = (store.values, store.off, store.cap, store.fill)
        if self.fast:
            K.pass_keep(self.terms, n, q, pidx, g.sig, self.tkeys, self.fkey, shift, lo, hi, acc,
                        below, *st)  # fmt: skip
        else:
            K.pass_keep_model(self.model, a, n, q, pidx, shift, lo, hi, acc, below, *st)


def _locate(ranks, below, whist):
    """Slot of each target rank inside its window.

    Returns
    -------
    slot : ndarray (npts, 4, 2), int64
        Window slot holding the order statistic; -1 below the window, -2 above it.
    within : ndarray (npts, 4, 2), int64
        1-based rank inside that slot.
    """
    cum = below[..., None] + np.cumsum(whist, axis=-1)  # (npts, 4, 2, W)
    r = np.asarray(ranks)[None, None, :]
    slot = np.argmax(cum >= r[..., None], axis=-1)
    before = (
        np.take_along_axis(cum, slot[..., None], -1)[..., 0]
        - np.take_along_axis(whist, slot[..., None], -1)[..., 0]
    )
    within = r - before
    slot = np.where(r <= below, -1, np.where(cum[..., -1] < r, -2, slot))
    return slot.astype(np.int64), within.astype(np.int64)


def run_kinematics(
    bench: Bench,
    trials: int = 1_000_000,
    seed: int = 0,
    *,
    q_cmd=None,
    p: float = 0.95,
    exact: bool = True,
    window_slots: int = WINDOW_SLOTS,
    pilot: int = 4096,
    adaptive_digits: int | None = None,
    max_trials: int = 10_000_000,
    progress=None,
    point_index=None,
    option: str = "--trials",
) -> KinematicsResult:
    """Monte Carlo of the probe position error over the scan grid (paper section III-A).

    Each trial draws the 21 error amplitudes once (common to all points) and, at every point,
    the vibration and reading delay; every (trial, point) sample enters the statistics.
    Nothing of size trials x points is kept in memory.

    Mean and standard deviation: shifted sums (shift = pilot mean), one pass.

    95 % intervals, exact order statistics (JCGM 101 7.7.2 ranks). A pilot of the first
    ``pilot`` trials places, per point, quantity and interval end, a window in value space that
    holds the end with near certainty (pilot quantiles at p_end -+ PILOT_SIGMAS binomial standard
    deviations, read conservatively from a histogram of the pilot). Then one pass: every sample
    is counted below its windows or kept in them; as the trials accumulate, each window narrows
    to the values that can still hold its end (`_narrow_ranks`), and at the end the end is
    selected from the kept values. Constant error profiles with normal noise (the reference
    bench) take the hand-vectorised kernel (`_kernels.pass_keep`), other benches the same pass
    over `_kernels.fill_values` (`_kernels.pass_keep_model`).

    A point whose window lost its end (rare) or overflowed its store is recounted in two passes,
    as is every point when the stores would pass STORE_BYTES: pass 1 counts the values below
    each window and in each of its ``window_slots`` slots; the counts give the slot holding
    each end and its rank in the slot; pass 2 regenerates every sample (counter-based RNG: the
    same numbers) and keeps the values of the target slots, which are then partially sorted. A
    window that missed its order statistic is widened and recounted for the points concerned.
    ``exact=False`` stops the two-pass way after pass 1 and interpolates inside the slot (the
    one pass is exact either way).

    Parameters
    ----------
    bench : Bench
    trials : int
        Number of Monte Carlo trials M (ignored with ``adaptive_digits``).
    seed : int
    q_cmd : ndarray, shape (n, 3), mm, optional
        Commanded axis positions; default the bench grid.
    p : float
        Coverage probability of the per-point intervals.
    window_slots : int
        Slots per window of the two-pass way.
    pilot : int
        Trials of the pilot.
    adaptive_digits : int, optional
        Adaptive procedure of JCGM 101 7.9 on the pooled per-axis systematic error, standard
        uncertainty and U_p: batches until twice the standard deviation of the batch results is
        within the numerical tolerance for ``adaptive_digits`` significant digits of u; the
        intervals then come from a run of that many trials.
    max_trials : int
        Cap of the adaptive run.
    progress : callable(int), optional
        Called with the number of trials just processed in a pass (e.g. a tqdm ``update``).
    point_index : ndarray, shape (n,), int, optional
        Index of each point of ``q_cmd`` in the full grid: it keys the point's vibration and
        delay stream, so a block of points run alone (e.g. on a Dask worker) draws the same
        numbers as in the full run. Default 0 .. n-1.
    option : str
        The option that set ``trials``, for the message refusing a run no machine ends.

    Returns
    -------
    KinematicsResult
    """
    timer = _Timer()
    q, pidx = _points(bench, q_cmd, point_index, trials, adaptive_digits)
    npts = q.shape[0]
    most = max_trials if adaptive_digits is not None else trials
    check_run_time(option, most, npts, "trials")
    progress = paced(option, most, "trials", progress)
    eng = _Engine(bench, seed, BLOCK)
    notes = []

    # Pilot: window placement and the shift of the sums (one point at a time in the kernel).
    n_pilot = int(pilot) if adaptive_digits is not None else max(2, min(int(pilot), int(trials)))
    kth, probs = _pilot_ranks(n_pilot, p)
    pil = np.empty((npts, 4, len(kth) + 1))
    eng.pilot_quantiles(n_pilot, q, pidx, kth, pil)
    shift = np.ascontiguousarray(pil[..., -1])
    timer.mark("pilot")

    adaptive = None
    acc = np.zeros((npts, 4, 2))
    if adaptive_digits is None:
        total = int(trials)
    else:  # the stopping rule on the sums alone, then the intervals of a run of that length
        total, adaptive = _adaptive_pass1(
            eng, lambda a, n, bacc: _sums_only(eng, a, n, q, pidx, shift, bacc), shift, acc,
            adaptive_digits, max_trials, progress,
        )  # fmt: skip
        timer.mark("adaptive")
        acc[...] = 0.0
    cap = _store_capacity(total, p, kth, n_pilot)
    if npts * 8 * (cap + 1) * 8 <= STORE_BYTES:
        low, high, method = _one_pass_intervals(
            eng, q, pidx, shift, pil, probs, cap=cap, total=total, p=p, acc=acc,
            window_slots=window_slots, progress=progress, timer=timer, notes=notes,
            source=bench.source,
        )  # fmt: skip
    else:
        acc, low, high, sub_notes, method = _two_pass_intervals(
            eng, q, pidx, pil, probs, total=total, p=p, exact=exact, window_slots=window_slots,
            progress=progress, timer=timer, source=bench.source,
        )  # fmt: skip
        notes += sub_notes

    mean, std = _mean_std(shift, acc, total, bench.source)
    notes.append(f"95 % intervals: {method}")
    if eng.g.tau_code < 0:
        notes.append(
            "vibration and normal reading delay are drawn as one normal per axis with the "
            "combined std sqrt(s_vib^2 + s_delay^2): the same distribution as two draws"
        )
    return KinematicsResult(
        q_cmd=q,
        nominal=bench.nominal_probe_mm(q),
        mean=mean,
        std=std,
        low=low,
        high=high,
        trials=total,
        seed=int(seed),
        pooled=pool_table_iv(mean, std),
        seconds=timer.seconds,
        interval_method=method,
        p=p,
        notes=notes,
        adaptive=adaptive,
    )


def _points(bench: Bench, q_cmd, point_index, trials, adaptive_digits):
    """Commanded positions (n, 3) mm (default the bench's scan grid) and their point indices,
    checked with the number of trials."""
    q = bench.grid_points() if q_cmd is None else np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    q = np.ascontiguousarray(q)
    npts = q.shape[0]
    if npts >= 2**30:
        raise CfmInputError(f"at most 2**30 points; found {npts}")
    if adaptive_digits is None and int(trials) < 2:
        raise CfmInputError(f"trials must be >= 2; found {trials}")
    if point_index is None:
        return q, np.arange(npts, dtype=np.int64)
    pidx = np.ascontiguousarray(point_index, dtype=np.int64)
    if pidx.shape != (npts,):
        raise CfmInputError(f"point_index must have shape ({npts},); found {pidx.shape}")
    return q, pidx


def _one_pass_intervals(
    eng, q, pidx, shift, pil, probs, *, cap, total, p, acc, window_slots, progress, timer, notes,
    source,
):  # fmt: skip
    """Intervals of every point in one pass with kept values (`_one_pass`); points whose window
    lost an interval end are recounted in two passes. Fills ``acc`` and appends to ``notes``.

    Returns
    -------
    low, high : ndarray, shape (n, 4), mm
    method : str
    """
    lo, hi = _value_windows(pil[..., :-1])
    store = _Store(q.shape[0], cap)
    ends = _one_pass(eng, q, pidx, shift, lo, hi, store=store, total=total, p=p, acc=acc,
                     progress=progress)  # fmt: skip
    del store
    _mean_std(shift, acc, total, source)  # refuses NaN positions before any recount
    timer.mark("pass")
    low, high = ends[..., 0].copy(), ends[..., 1].copy()
    redo = np.nonzero(np.isnan(ends).any(axis=(1, 2)))[0]
    method = (
        "exact order statistics (JCGM 101 7.7.2 ranks): one pass counting each value below "
        "its pilot-placed window or keeping it there, the windows narrowing as the trials "
        "accumulate, the end then selected from the kept values"
    )
    if len(redo):
        sub = np.ascontiguousarray(q[redo])
        _, r_low, r_high, sub_notes, _ = _two_pass_intervals(
            eng, sub, pidx[redo], pil[redo], probs, total=total, p=p, exact=True,
            window_slots=window_slots, progress=None, source=source,
        )  # fmt: skip
        low[redo], high[redo] = r_low, r_high
        notes.append(
            f"{len(redo)} point(s) whose window lost its interval end were recounted in two "
            "passes (exact)"
        )
        notes += sub_notes
        timer.mark("recount")
    return low, high, method


def _mean_std(shift, acc, total, source):
    """Mean and std (npts, 4) from the shifted sums; a CfmInputError naming the bench file
    when they are not finite (errors that overflow the positions)."""
    m = float(total)
    mean = shift + acc[..., 0] / m
    std = np.sqrt(np.maximum(acc[..., 1] - acc[..., 0] ** 2 / m, 0.0) / (m - 1.0))
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std))):
        raise CfmInputError(
            "the bench's errors give infinite or NaN probe positions (an overflow): check the "
            "sizes of its error PDFs and profiles",
            file=source,
        )
    return mean, std


def _sums_only(eng, a, n, q, pidx, shift, acc):
    """The one pass for its sums alone (windows that hold nothing; adaptive batches)."""
    npts = q.shape[0]
    lo = np.full((npts, 4, 2), np.inf)
    hi = np.full((npts, 4, 2), -np.inf)
    eng.keep(a, n, q, pidx, shift=shift, lo=lo, hi=hi, acc=acc,
             below=np.zeros((npts, 4, 2), np.int64), store=_Store(npts, 0))  # fmt: skip


class _Store:
    """Values kept in the one pass's windows: window w (flat index over (npts, 4, 2)) owns
    values[w * (cap + 1) : (w + 1) * (cap + 1)] (the last place is a spare that overflowing
    writes land on) and holds fill[w] values; fill[w] > cap means it overflowed."""

    def __init__(self, npts, cap):
        self.cap = np.full((npts, 4, 2), int(cap), dtype=np.int64)
        self.off = np.arange(npts * 8, dtype=np.int64).reshape(npts, 4, 2) * (int(cap) + 1)
        self.fill = np.zeros((npts, 4, 2), dtype=np.int64)
        self.values = np.empty(npts * 8 * (int(cap) + 1))


def _narrowings(total):
    """Trial counts at which the one pass's windows narrow: NARROW_FIRST and its doublings up
    to three quarters of the run."""
    out = []
    s = NARROW_FIRST
    while 4 * s <= 3 * total:
        out.append(s)
        s *= 2
    return out


def _margin(expect):
    """Places for a Poisson count of mean ``expect``: exceeded with negligible probability (an
    overflow only sends the point to the two-pass way)."""
    return np.ceil(1.3 * expect + 8.0 * np.sqrt(expect) + 64.0)


def _store_capacity(total, p, kth, n_pilot):
    """Places per window the one pass needs over the run: the pilot window's share of the
    trials before the first narrowing, then, after each, the values kept (the ranks of
    `_narrow_ranks`, widened by the histogram bins that hold the two edge ranks) and their share
    of the trials up to the next one."""
    frac = max(kth[1] - kth[0] + 1, kth[3] - kth[2] + 1) / n_pilot
    stops = _narrowings(total)
    need = _margin(frac * (stops[0] if stops else total))
    rank = np.array(symmetric_ranks(total, p))
    for k, s in enumerate(stops):
        held = min(need, frac * s)  # values in the window before it narrows
        klo, khi = _narrow_ranks(rank, total, s)
        kept = max(float(np.max(khi - klo + 1)), 0.0) + 8.0 * held / K.NARROW_BINS
        frac = kept / s
        following = (stops[k + 1] if k + 1 < len(stops) else total) - s
        need = max(need, kept + _margin(frac * following))
    return int(need)


def _value_windows(qs):
    """Windows [lo, hi] (npts, 4, 2) around each interval end from the pilot brackets qs
    (npts, 4, 6), padded by 1 % of the bracket (and 1e-9 of the pilot's range)."""
    vmin, vmax = qs[..., 4], qs[..., 5]
    span = np.maximum(vmax - vmin, 1e-12)
    lo = np.empty(qs.shape[:2] + (2,))
    hi = np.empty(qs.shape[:2] + (2,))
    for e in range(2):
        a, b = qs[..., 2 * e], qs[..., 2 * e + 1]
        pad = 0.01 * (b - a) + 1e-9 * span
        lo[..., e] = a - pad
        hi[..., e] = b + pad
    return np.ascontiguousarray(lo), np.ascontiguousarray(hi)


def _narrow_ranks(rank, total, seen):
    """Ranks among the first ``seen`` trials between which the final order statistic of rank
    ``rank`` (1-based among ``total``) lies with near certainty: (klo, khi), arrays like rank.

    The number C of the first ``seen`` values at or below the final order statistic is
    hypergeometric (mean seen r / total); the statistic lies between the C-th and (C+1)-th
    smallest of them. The range spans NARROW_SIGMAS standard deviations of C either side, plus
    one rank."""
    r = np.asarray(rank, dtype=np.float64)
    f = seen / total
    sd = np.sqrt(seen * (r / total) * (1.0 - r / total) * (1.0 - f))
    klo = np.floor(r * f - NARROW_SIGMAS * sd) - 1
    khi = np.ceil(r * f + NARROW_SIGMAS * sd) + 2
    return np.maximum(klo, 1).astype(np.int64), np.minimum(khi, seen).astype(np.int64)


def _one_pass(eng, q, pidx, shift, lo, hi, *, store, total, p, acc, progress):
    """The one pass: sums into ``acc`` and the interval ends (npts, 4, 2), NaN where a window
    lost its end or overflowed (that point needs the two-pass way). ``lo``, ``hi``:
    the pilot windows (narrowed in place); ``store``: a `_Store` of `_store_capacity`."""
    npts = q.shape[0]
    rank = np.empty((npts, 4, 2), np.int64)
    rank[..., 0], rank[..., 1] = symmetric_ranks(total, p)
    below = np.zeros((npts, 4, 2), dtype=np.int64)
    flat = [x.reshape(-1) for x in (store.values, store.off, store.cap, store.fill, below)]
    lost = np.zeros((npts, 4, 2), dtype=bool)
    stops = _narrowings(total)
    for a, b in _blocks(0, total, BLOCK):
        if stops and a == stops[0]:
            stops.pop(0)
            lost |= store.fill > store.cap
            lo[lost], hi[lost] = np.inf, -np.inf  # a lost window takes no more values
            klo, khi = _narrow_ranks(rank, total, a)
            K.narrow_windows(*flat, lo.reshape(-1), hi.reshape(-1), klo.ravel(), khi.ravel())
        n = eng.prepare(a, b)
        eng.keep(a, n, q, pidx, shift=shift, lo=lo, hi=hi, acc=acc, below=below, store=store)
        if progress is not None:
            progress(n)
    ends = np.empty((npts, 4, 2))
    values, off, cap, fill, below_flat = flat
    K.select_ends(values, off, fill, cap, below_flat, lo.reshape(-1), hi.reshape(-1),
                  rank.reshape(-1), ends.reshape(-1))  # fmt: skip
    ends[lost] = np.nan
    return ends


def _two_pass_intervals(eng, q, pidx, pil, probs, *, total, p, exact, window_slots, progress,
                        timer=None, source=None):  # fmt: skip
    """The two-pass way: counting pass, widening of missed windows, then the pass that keeps
    the values of the target slots. ``source``: the bench file, named when its positions are
    not finite.

    Returns acc (npts, 4, 2), low, high (npts, 4), notes, method."""
    npts = q.shape[0]
    shift = np.ascontiguousarray(pil[..., -1])
    wlo, winv = _windows(pil[..., :-1], probs, window_slots)
    notes = []
    acc = np.zeros((npts, 4, 2))
    below = np.zeros((npts, 4, 2), dtype=np.int64)
    whist = np.zeros((npts, 4, 2, window_slots), dtype=np.int64)
    for a, b in _blocks(0, total, eng.block):
        n = eng.prepare(a, b)
        eng.window(a, n, q, pidx, shift=shift, wlo=wlo, winv=winv, acc=acc, below=below,
                   whist=whist)  # fmt: skip
        if progress is not None:
            progress(n)
    _mean_std(shift, acc, total, source)  # NaN positions would miss every window for ever
    if timer is not None:
        timer.mark("pass1")
    ranks = symmetric_ranks(total, p)
    slot, within = _locate(ranks, below, whist)
    widened = 0
    for _round in range(MAX_WIDEN_ROUNDS + 1):
        if not np.any(slot < 0):
            break
        if _round == MAX_WIDEN_ROUNDS:
            raise RuntimeError(
                f"interval windows still miss their order statistic after {MAX_WIDEN_ROUNDS} "
                "widenings"
            )
        # a window missed its order statistic: widen, recount those points
        sel = np.unique(np.nonzero(slot < 0)[0])
        widened += int(np.count_nonzero(slot < 0))
        width = window_slots / winv[sel]
        span = np.maximum(pil[sel][..., 5] - pil[sel][..., 4], 1e-12)[..., None]
        miss_low, miss_high = slot[sel] == -1, slot[sel] == -2
        new_lo = np.where(
            miss_low, wlo[sel] - 4 * (width + span), np.where(miss_high, wlo[sel] + width, wlo[sel])
        )
        new_w = np.where(miss_low | miss_high, 4 * (width + span) + width, width)
        wlo[sel] = new_lo
        winv[sel] = window_slots / new_w
        b_sel = np.zeros((len(sel), 4, 2), dtype=np.int64)
        h_sel = np.zeros((len(sel), 4, 2, window_slots), dtype=np.int64)
        junk = np.zeros((len(sel), 4, 2))
        q_sel, p_sel = np.ascontiguousarray(q[sel]), pidx[sel]
        for a, b in _blocks(0, total, eng.block):
            n = eng.prepare(a, b)
            eng.window(a, n, q_sel, p_sel, shift=shift[sel], wlo=wlo[sel], winv=winv[sel],
                       acc=junk, below=b_sel, whist=h_sel)  # fmt: skip
        below[sel], whist[sel] = b_sel, h_sel
        slot, within = _locate(ranks, below, whist)
    if widened:
        notes.append(
            f"{widened} interval-end windows missed by the pilot were widened and recounted"
        )
    if timer is not None:
        timer.mark("refine")

    count = np.take_along_axis(whist, slot[..., None], -1)[..., 0]
    width = 1.0 / winv
    low = np.empty((npts, 4))
    high = np.empty((npts, 4))
    if exact:
        offset = np.zeros_like(count)
        offset.ravel()[1:] = np.cumsum(count.ravel())[:-1]
        buf = np.empty(int(count.sum()))
        fill = np.zeros_like(count)
        slack = 1e-9 * width + 1e-300
        vlo = wlo + slot * width - slack
        vhi = wlo + (slot + 1) * width + slack
        for a, b in _blocks(0, total, eng.block):
            n = eng.prepare(a, b)
            eng.capture(a, n, q, pidx, wlo=wlo, winv=winv, target=slot, vlo=vlo, vhi=vhi,
                        offset=offset, fill=fill, buf=buf)  # fmt: skip
            if progress is not None:
                progress(n)
        if not np.array_equal(fill, count):  # same samples, same slots: cannot happen
            raise RuntimeError("pass 2 did not reproduce the pass 1 counts")
        ends = (low, high)
        for i in range(npts):
            for c in range(4):
                for e in range(2):
                    o, k, r = offset[i, c, e], count[i, c, e], within[i, c, e]
                    ends[e][i, c] = np.partition(buf[o : o + k], r - 1)[r - 1]
        method = (
            "exact order statistics (JCGM 101 7.7.2 ranks) by counting in pilot-placed windows "
            f"({window_slots} slots each) and a second pass that regenerates every sample and "
            "keeps those of the slot holding each end"
        )
        if timer is not None:
            timer.mark("pass2")
    else:
        val = wlo + (slot + (within - 0.5) / np.maximum(count, 1)) * width
        low[...], high[...] = val[..., 0], val[..., 1]
        method = (
            f"interpolated in the slot holding each order statistic ({window_slots}-slot windows; "
            f"error below {1e3 * float(np.max(width)):.2g} um)"
        )
    return acc, low, high, notes, method


def _pilot_ranks(n, p):
    """0-based order statistics of an n-trial pilot that bracket each interval end.

    Around each end (probability p_e of the symmetric interval) the pilot quantiles at
    p_e -+ (PILOT_SIGMAS binomial standard deviations + 3/n); ranks outside the sample become
    its extremes.

    Returns
    -------
    kth : ndarray (6,) int64
        For each end: lower, upper bracket; then the sample minimum and maximum.
    probs : tuple
    """
    r_lo, r_hi = symmetric_ranks(10**6, p)  # probability of each end; M only sets the rounding
    kth = []
    for r in (r_lo, r_hi):
        pe = r / 10**6
        delta = PILOT_SIGMAS * np.sqrt(pe * (1 - pe) / n) + 3.0 / n
        kth += [int(np.clip(np.floor((pe - delta) * n) - 1, 0, n - 1)),
                int(np.clip(np.ceil((pe + delta) * n) - 1, 0, n - 1))]  # fmt: skip
    kth += [0, n - 1]
    return np.array(kth, dtype=np.int64), (r_lo, r_hi)


def _windows(qs, probs, slots):
    """Generic-path windows (low edge, slots per mm) from the pilot brackets qs (npts, 4, 6):
    the one pass's value windows (`_value_windows`) cut into ``slots`` slots."""
    lo, hi = _value_windows(qs)
    return lo, np.ascontiguousarray(slots / (hi - lo))


def _adaptive_pass1(eng, run_block, shift, acc, ndig, max_trials, progress):
    """JCGM 101 7.9.4 on the pooled per-axis (systematic, std, U_p); ``run_block(a, n, bacc)``
    adds the sums (shifted by ``shift``) of the prepared block to bacc. Fills acc; returns
    (total, adaptive info)."""
    block = eng.block
    batch = ((10_000 + block - 1) // block) * block  # JCGM: M = max(J, 1e4) trials per batch
    results = []
    total = 0
    while True:
        bacc = np.zeros_like(acc)
        for a, b in _blocks(total, total + batch, block):
            n = eng.prepare(a, b)
            run_block(a, n, bacc)
            if progress is not None:
                progress(n)
        total += batch
        acc += bacc
        bm = shift + bacc[..., 0] / batch
        bs = np.sqrt(np.maximum(bacc[..., 1] - bacc[..., 0] ** 2 / batch, 0) / (batch - 1))
        pooled = pool_table_iv(bm, bs)
        results.append([pooled[a][k] for a in "xyz" for k in ("systematic_um", "std_um", "U_p_um")])
        h = len(results)
        if h < 2:
            continue
        r = np.array(results)
        two_s = 2 * r.std(axis=0, ddof=1) / np.sqrt(h)
        m = float(total)
        mean = shift + acc[..., 0] / m
        std = np.sqrt(np.maximum(acc[..., 1] - acc[..., 0] ** 2 / m, 0) / (m - 1))
        allp = pool_table_iv(mean, std)
        delta = numerical_tolerance(np.repeat([allp[a]["std_um"] for a in "xyz"], 3), ndig)
        converged = bool(np.all(two_s <= delta))
        if converged or total + batch > max_trials:
            return total, {
                "digits": int(ndig),
                "batches": h,
                "batch_trials": int(batch),
                "converged": converged,
                "delta_um": delta[::3].tolist(),
                "two_s_um": two_s.tolist(),
                "quantities": [f"{a}.{k}" for a in "xyz" for k in ("systematic", "std", "U_p")],
            }


class _Timer:
    def __init__(self):
        self.t = time.perf_counter()
        self.seconds = {}

    def mark(self, name):
        now = time.perf_counter()
        self.seconds[name] = now - self.t
        self.t = now


# ---------------------------------------------------------------------------------------------
# Uncertainty budget and design in reverse (linearised model, exact sensitivities)
# ---------------------------------------------------------------------------------------------
