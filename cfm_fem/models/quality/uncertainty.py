"""Monte Carlo of the field quality a bench gets from a map (JCGM 101, adaptive 7.9.4).

Each trial t moves every scan point p_i by a displacement e[t, i] (magnet frame), reads the
field there from the model between nodes (`LocalField`), passes it through the Hall probe, and
redoes the analysis (`analyse`) with the scan points at their nominal
places, as the measurement would. The displacements:

``gauss``
    e[t, i] ~ N(0, U_p^2) per axis, independent per point and trial; random numbers of trial t
    from ``SeedSequence(seed, spawn_key=(GAUSS_STREAM, t))``.
``htm``
    The bench's probe error at p_i: the 21 geometric errors of trial t (common to the whole
    scan: they shift, tilt and bend the scanned pattern together) and the vibration and reading
    delay of (t, i), from the kinematics streams of ``seed`` (`cfm_fem.models.kinematics`),
    turned into the magnet frame.

The probe is one instrument for the whole scan: its errors (gain, offsets, non-orthogonality,
`cfm_fem.models.probe`) are drawn once per trial from ``SeedSequence(seed, spawn_key=
(PROBE_STREAM, t))``, its axes parallel to the bench axes (to the magnet axes in ``gauss``).

Statistics of each quantity's deviation from the map's value: mean, standard deviation, the
95 % probabilistically symmetric interval [low, high] and U95 = max(|low|, |high|) (the
convention of ``sweep``'s U_f). Adaptive stopping: batches of trials until twice the standard
deviation of the batch values of mean, std, low and high over sqrt(batches) is within the
numerical tolerance (JCGM 101 7.9.2, ``digits`` significant digits of the standard deviation)
for every quantity but b_N (the main harmonic in units of itself, `_check`), or a trial cap is
reached. Every trial's numbers depend on (seed, t) only:
the same seed gives the same results whatever the batch size or the number of threads.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from threadpoolctl import threadpool_limits

from ... import _kernels as K
from ...errors import CfmInputError
from ..bench import ERROR_NAMES, Bench, ReadingDelay
from ..kinematics.geometry import draw_error_sets, kernel_geometry, noise_keys
from ..mc import numerical_tolerance, symmetric_interval
from ..probe import HallProbe
from .harmonics import VECTOR_NAMES, ScanPlan, analyse
from .sampling import LocalField

__all__ = [
    "Sources",
    "McQuality",
    "run_quality_mc",
    "budget_groups",
    "trial_reader",
    "GAUSS_STREAM",
    "PROBE_STREAM",
]

GAUSS_STREAM = 0x51475353
PROBE_STREAM = 0x51505242
#: Trials evaluated together (memory ~ 80 bytes x trials x scan points).
CHUNK_POINTS = 2_000_000


@dataclass
class Sources:
    """What moves the probe and what it reads.

    Attributes
    ----------
    mode : {"gauss", "htm"}
    up_mm : float, mm
        Standard deviation per axis of ``gauss``.
    bench : Bench or None
        The bench of ``htm``.
    probe : HallProbe
    label : str
        Name in the budget.
    """

    mode: str
    up_mm: float = 0.0
    bench: Bench | None = None
    probe: HallProbe = field(default_factory=lambda: HallProbe.exact())
    label: str = "all"

    def __post_init__(self):
        if self.mode not in ("gauss", "htm"):
            raise CfmInputError(f"mode must be gauss or htm; got {self.mode!r}")
        if self.mode == "htm" and self.bench is None:
            raise CfmInputError("mode htm needs a bench")
        if self.mode == "gauss" and not (np.isfinite(self.up_mm) and self.up_mm >= 0):
            raise CfmInputError(f"U_p must be a finite number >= 0 um; got {self.up_mm * 1e3}")


class _Displacer:
    """Displacements (m, n, 3) mm of trials t0 .. t0 + m - 1 at the scan points."""

    def __init__(self, src: Sources, points, seed: int, what: str = "the scan (--radius, --dz)"):
        self.src, self.seed, self.n = src, int(seed), len(points)
        self.r_probe = np.eye(3)
        if src.mode == "htm":
            b = src.bench
            self.q = b.axis_positions_within_strokes(points, what)
            self.geo = kernel_geometry(b)
            self.keys = noise_keys(seed)
            self.r_bm = b.bench_to_magnet_rotation()
            self.r_probe = self.r_bm

    def __call__(self, t0: int, m: int) -> np.ndarray:
        if self.src.mode == "gauss":
            out = np.empty((m, self.n, 3))
            for j in range(m):
                rng = np.random.default_rng(
                    np.random.SeedSequence(self.seed, spawn_key=(GAUSS_STREAM, t0 + j))
                )
                out[j] = rng.normal(0.0, self.src.up_mm, (self.n, 3))
            return out
        params = draw_error_sets(self.src.bench, m, self.seed, start=t0)
        out = np.empty((m, self.n, 3))
        pidx = np.arange(self.n, dtype=np.int64)
        K.coupled_probe_errors(params, t0, self.q, pidx, *self.keys, self.geo, out)
        return out @ self.r_bm.T


def trial_reader(src: Sources, points, seed: int):
    """``read(local, t0, m) -> B (m, n, 3)``: the readings of trials t0 .. t0 + m - 1 at
    ``points`` (n, 3) mm (those of ``local``, a `LocalField`), each moved as the Monte Carlo
    moves a scan point and read through the trial's probe; NaN where a reading left the model."""
    disp = _Displacer(src, points, seed, "the nodes around the trajectory")

    def read(local: LocalField, t0: int, m: int) -> np.ndarray:
        b, _ = local.read(disp(t0, m))
        return _probe_read(src.probe, b, t0, seed, disp.r_probe)

    return read


def _probe_read(probe: HallProbe, B, t0: int, seed: int, r_probe) -> np.ndarray:
    """Readings of one probe per trial (trials t0 ..), B (m, n, 3) T in the magnet frame."""
    if probe == HallProbe.exact(probe.model):
        return B
    m = B.shape[0]
    draws = [
        probe.sample(np.random.default_rng(
            np.random.SeedSequence(int(seed), spawn_key=(PROBE_STREAM, t0 + j))), ())
        for j in range(m)
    ]  # fmt: skip
    gain = np.stack([x.gain for x in draws])[:, None]  # (m, 1, 3)
    if probe.model == "paper":  # one factor for the three components, no offset, no tilt
        return B * gain
    offset = np.stack([x.offset_T for x in draws])[:, None]
    directions = np.stack([x.directions for x in draws])  # (m, 3, 3)
    mixed = np.einsum("mij,mnj->mni", directions, B @ r_probe)  # B_meas_i = g_i n_i . B + o_i
    return (gain * mixed + offset) @ r_probe.T


@dataclass
class McQuality:
    """Monte Carlo result: deviations of every quantity of `VECTOR_NAMES` from the map's value.

    Attributes
    ----------
    deviations : ndarray, shape (M, Q)
        Per valid trial (units, mm, mrad, mm, T mm as `QualityNumbers.vector`).
    mean, std, low, high, u95 : ndarray, shape (Q,)
        Statistics of the deviations (95 % probabilistically symmetric interval).
    u95_spread : ndarray, shape (Q,)
        Twice the standard deviation of the batch values of U95 over sqrt(batches): the
        numerical tolerance U95 is known to.
    delta : ndarray, shape (Q,)
        Numerical tolerance target (JCGM 101 7.9.2) of the standard deviation.
    converged : bool
    trials, lost, batches, batch_trials, seed : int
    digits : int
    mode, label : str
    """

    deviations: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    u95: np.ndarray
    u95_spread: np.ndarray
    delta: np.ndarray
    converged: bool
    trials: int
    lost: int
    batches: int
    batch_trials: int
    seed: int
    digits: int
    mode: str
    label: str

    def of(self, name: str) -> int:
        return VECTOR_NAMES.index(name)


def _stats(dev):
    """(mean, std, low, high, u95) over the rows of dev (M, Q), NaN columns stay NaN."""
    mean = dev.mean(axis=0)
    std = dev.std(axis=0, ddof=1)
    low, high = symmetric_interval(dev, 0.95, axis=0)
    return mean, std, low, high, np.maximum(np.abs(low), np.abs(high))


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
def run_quality_mc(plan: ScanPlan, local: LocalField, src: Sources, nominal_vector,
                   main_order: int, z_length: float, *, seed: int = 0, trials: int | None = None,
                   batch_trials: int = 500, max_trials: int = 20_000, digits: int = 1,
                   progress=None) -> McQuality:  # fmt: skip
    """Monte Carlo of the field quality (module docstring).

    Parameters
    ----------
    plan : ScanPlan
    local : LocalField
        Over ``plan.points``.
    src : Sources
    nominal_vector : ndarray, shape (Q,)
        `QualityNumbers.vector` of the map.
    main_order : int
    z_length : float, mm
        Plane of the magnetic length.
    seed : int
    trials : int, optional
        Fixed number of trials (in 10 batches); default adaptive.
    batch_trials : int
        Trials per batch of the adaptive procedure.
    max_trials : int
        Cap of the adaptive procedure (``converged`` False when reached first).
    digits : int
        Significant digits of the standard deviations the adaptive procedure asks for.
    progress : callable(int), optional
        Called with the trials finished.

    Returns
    -------
    McQuality
    """
    if trials is not None:
        trials = int(trials)
        if trials < 20:
            raise CfmInputError(f"trials must be >= 20; got {trials}")
        edges = list(np.linspace(0, trials, 11).astype(int))
    else:
        batch_trials = max(int(batch_trials), 10)
        edges = [0, batch_trials]
    disp = _Displacer(src, plan.points, seed)
    chunk = max(1, CHUNK_POINTS // max(len(plan.points), 1))
    values, lost, h = [], 0, 0
    while True:
        a, b = edges[h], edges[h + 1]
        rows = []
        for t0 in range(a, b, chunk):
            m = min(chunk, b - t0)
            B, _ = local.read(disp(t0, m))
            B = _probe_read(src.probe, B, t0, seed, disp.r_probe)
            rows.append(analyse(plan, B, main_order, z_length).vector())
            if progress is not None:
                progress(m)
        v = np.concatenate(rows) - nominal_vector[None]
        ok = np.all(np.isfinite(v) | ~np.isfinite(nominal_vector)[None], axis=1)
        lost += int((~ok).sum())
        values.append(v[ok])
        h += 1
        conv, spread, delta = _check(values, digits, ignore=main_order - 1)
        if trials is not None:
            if h == len(edges) - 1:
                break
            continue
        if conv or b + batch_trials > max_trials:
            break
        edges.append(b + batch_trials)
    dev = np.concatenate(values)
    if len(dev) < 2:
        cause = (f"--up {src.up_mm * 1e3:g} um" if src.mode == "gauss"
                 else "the bench's errors (--bench)")  # fmt: skip
        raise CfmInputError(
            f"the scan points displaced by {cause} left the field model in (nearly) every "
            "trial; choose a smaller --up, --radius or z range"
        )
    mean, std, low, high, u95 = _stats(dev)
    return McQuality(dev, mean, std, low, high, u95, spread, delta, bool(conv), len(dev), lost,
                     h, edges[1] - edges[0], int(seed), int(digits), src.mode,
                     src.label)  # fmt: skip


def _check(values, digits, ignore=None):
    """(converged, U95 spread, delta) of the batches so far (JCGM 101 7.9.4).

    ``ignore``: index of a column left out of the convergence test (b_N, the main harmonic in
    units of itself: 1e4 up to second order in the roll, a one-sided deviation of 1e-5 units
    whose interval ends converge far slower than any figure of interest).
    """
    h = len(values)
    q = values[0].shape[1]
    if h < 2 or any(len(v) < 2 for v in values):
        return False, np.full(q, np.nan), np.full(q, np.nan)
    st = np.array([np.stack(_stats(v)) for v in values])  # (h, 5, Q)
    two_s = 2.0 * st.std(axis=0, ddof=1) / np.sqrt(h)
    std_all = np.concatenate(values).std(axis=0, ddof=1)
    delta = numerical_tolerance(std_all, digits)
    finite = np.isfinite(std_all)
    if ignore is not None:
        finite[ignore] = False
    conv = bool(np.all(two_s[:4, finite] <= delta[finite]))
    return conv, two_s[4], delta


# --------------------------------------------------------------------------- budget

#: Error groups of the HTM budget: name -> indices into ERROR_NAMES.
HTM_GROUPS = {
    "X axis": [i for i, n in enumerate(ERROR_NAMES) if n.endswith("(x)")],
    "Y axis": [i for i, n in enumerate(ERROR_NAMES) if n.endswith("(y)")],
    "Z axis": [i for i, n in enumerate(ERROR_NAMES) if n.endswith("(z)")],
    "squareness": [i for i, n in enumerate(ERROR_NAMES) if n.startswith("alpha")],
}


def _quiet(bench: Bench) -> Bench:
    return replace(bench, vibration_std_mm=np.zeros(3),
                   delay=ReadingDelay(model="normal", std_mm=np.zeros(3)))  # fmt: skip


def budget_groups(src: Sources) -> list[Sources]:
    """One `Sources` per error group, each with only that group active.

    ``gauss``: positioning (U_p), probe. ``htm``: the geometric errors of each axis, the
    squareness errors, vibration and reading delay, probe.
    """
    exact = HallProbe.exact(src.probe.model)
    probe_on = src.probe != exact
    if src.mode == "gauss":
        groups = [replace(src, probe=exact, label="positioning (U_p)")]
        if probe_on:
            groups.append(replace(src, up_mm=0.0, label="probe"))
        return groups
    bench = src.bench
    groups = []
    for name, idx in HTM_GROUPS.items():
        f = np.zeros(len(ERROR_NAMES))
        f[idx] = 1.0
        b = _quiet(bench.scaled_errors(f))
        groups.append(replace(src, bench=b, probe=exact, label=name))
    noise = bench.scaled_errors(0.0)
    groups.append(replace(src, bench=noise, probe=exact, label="vibration and reading delay"))
    if probe_on:
        groups.append(replace(src, bench=_quiet(noise), label="probe"))
    return groups
