"""Bench kinematics: the HTM chain of paper eq. 1-10, its Monte Carlo, budget and design.

Sections of this module:

1. exact reference in plain numpy: full rotation matrices (eq. 4, no small-angle shortcut),
   4x4 HTMs (eq. 2) multiplied along the chain (eq. 5), the probe error as actual minus nominal
   probe position (eq. 8) with vibration and reading delay added to the commanded positions
   (eq. 10); the numba kernels in :mod:`cfm_fem._kernels` use the same math and are
   tested against it;
2. the GUM-S1 Monte Carlo over the scan grid (``run_kinematics``), streamed, with exact
   per-point coverage intervals, Table IV pooling and the JCGM 101 7.9 adaptive option;
3. the seam for other workflows: ``draw_error_sets`` (per-trial error amplitudes from the seed
   alone), ``kernel_geometry`` and ``noise_keys`` (arguments of the njit functions
   ``_kernels.probe_error_mm`` and ``axis_noise_mm``);
4. the uncertainty budget and the design in reverse (linearised model, exact sensitivities).

Chain. Body j (j = 1, 2, 3 from the foundation) is the carriage of axis ``stack[j]``; with
commanded travel q_j, axis-position noise n_j, error values delta_j, eps_j (both evaluated at the
commanded q_j, as in eq. 10) and travel direction d_j::

    M_{j-1,j} = Trans(m_j + (q_j + n_j) d_j + delta_j) . Rot(eps_j)
    P_actual  = M_{0,1} M_{1,2} M_{2,3} [tool; 1]
    P_nominal = m_1 + m_2 + m_3 + q + tool          (M* = pure translations)
    E         = P_actual - P_nominal                (bench frame, mm)

Squareness. ``alpha_ab`` tilts the travel direction of the upper of the two axes a, b (the one
stacked later) towards the positive direction of the other, by a rotation about the third axis;
``alpha_ab > 0`` means the two travel directions make an angle of 90 deg - alpha_ab. The
foundation axis defines the bench frame and has no squareness term.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import _kernels as K
from .bench import AXES, ERROR_DESCRIPTIONS, ERROR_NAMES, Bench
from .errors import CfmInputError, check_seed
from .mc import gum_validation, numerical_tolerance, ppf_numpy, symmetric_ranks

__all__ = [
    "rotation_zyx",
    "htm",
    "squareness_angles",
    "travel_directions",
    "error_values",
    "probe_positions",
    "probe_errors",
    "probe_errors_for_bench",
    "sensitivities",
    "QUANTITIES",
    "KernelGeometry",
    "kernel_geometry",
    "draw_error_sets",
    "noise_keys",
    "draw_error_sets_numpy",
    "point_noise",
    "KinematicsResult",
    "pool_table_iv",
    "run_kinematics",
    "LinearModel",
    "linear_model",
    "uncertainty_budget",
    "design_tolerances",
    "gum_check",
]

_I = {name: k for k, name in enumerate(ERROR_NAMES)}


def rotation_zyx(phi, theta, psi) -> np.ndarray:
    """Rotation matrix of paper eq. 4: R = Rz(psi) Ry(theta) Rx(phi).

    Parameters
    ----------
    phi, theta, psi : float or ndarray, shape (...), rad
        Rotations about x, y and z.

    Returns
    -------
    ndarray, shape (..., 3, 3)
    """
    phi, theta, psi = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (phi, theta, psi))
    )
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(theta), np.sin(theta)
    cp, sp = np.cos(psi), np.sin(psi)
    r = np.empty(phi.shape + (3, 3))
    r[..., 0, 0] = cp * ct
    r[..., 0, 1] = cp * sf * st - cf * sp
    r[..., 0, 2] = sf * sp + cf * cp * st
    r[..., 1, 0] = ct * sp
    r[..., 1, 1] = cf * cp + sf * sp * st
    r[..., 1, 2] = cf * sp * st - cp * sf
    r[..., 2, 0] = -st
    r[..., 2, 1] = ct * sf
    r[..., 2, 2] = cf * ct
    return r


def htm(rotation, translation) -> np.ndarray:
    """Homogeneous transformation matrix of eq. 2.

    Parameters
    ----------
    rotation : ndarray, shape (..., 3, 3)
    translation : ndarray, shape (..., 3), mm

    Returns
    -------
    ndarray, shape (..., 4, 4)
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    m = np.zeros(shape + (4, 4))
    m[..., :3, :3] = rotation
    m[..., :3, 3] = translation
    m[..., 3, 3] = 1.0
    return m


def squareness_angles(stack, alphas) -> np.ndarray:
    """Zyx angles that tilt each axis' travel direction (module docstring convention).

    Parameters
    ----------
    stack : sequence of int, shape (3,)
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3.
    alphas : ndarray, shape (..., 3), rad
        (alpha_xy, alpha_xz, alpha_yz).

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``[..., a, :]`` = (phi, theta, psi) of bench axis a.
    """
    alphas = np.asarray(alphas, dtype=np.float64)
    out = np.zeros(alphas.shape[:-1] + (3, 3))
    level = {int(a): j for j, a in enumerate(stack)}
    for col, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
        upper, lower = (a, b) if level[a] > level[b] else (b, a)
        c = 3 - a - b
        cyclic = (upper, lower, c) in ((0, 1, 2), (1, 2, 0), (2, 0, 1))
        out[..., upper, c] += (1.0 if cyclic else -1.0) * alphas[..., col]
    return out


def travel_directions(stack, alphas) -> np.ndarray:
    """Unit travel direction of each bench axis, shape (..., 3 axes, 3), in its parent frame."""
    ang = squareness_angles(stack, alphas)
    r = rotation_zyx(ang[..., 0], ang[..., 1], ang[..., 2])  # (..., 3, 3, 3)
    return np.stack([r[..., a, :, a] for a in range(3)], axis=-2)


def error_values(params, q_cmd, strokes, profiles) -> np.ndarray:
    """Values of the 21 errors at the commanded positions: amplitude x profile(q / stroke).

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Amplitudes (mm, rad) in ``ERROR_NAMES`` order.
    q_cmd : ndarray, shape (n, 3), mm
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)

    Returns
    -------
    ndarray, shape (m, n, 21)
    """
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    profiles = np.asarray(profiles, dtype=np.float64)
    u = q / np.asarray(strokes, dtype=np.float64)  # (n, 3)
    axis_of_error = np.array([AXES.index(n[-2]) if "(" in n else 0 for n in ERROR_NAMES])
    uk = u[:, axis_of_error]  # (n, 21)
    p = np.zeros_like(uk)
    for c in profiles.T[::-1]:  # Horner
        p = p * uk + c
    return params[:, None, :] * p[None, :, :]


def probe_positions(params, q_cmd, dq, stack, mounts, tool, strokes, profiles) -> np.ndarray:
    """Actual probe position P_r by the HTM chain (eq. 5, 10), bench frame.

    Parameters
    ----------
    params : ndarray, shape (m, 21)
        Error amplitudes per trial (mm, rad).
    q_cmd : ndarray, shape (n, 3), mm
        Commanded positions of the x, y, z axes.
    dq : ndarray, shape (m, n, 3) or broadcastable, mm
        Vibration + reading delay added to the commanded positions (eq. 10).
    stack : sequence of int, shape (3,)
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)

    Returns
    -------
    ndarray, shape (m, n, 3), mm
    """
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    m, n = params.shape[0], q.shape[0]
    dq = np.broadcast_to(np.asarray(dq, dtype=np.float64), (m, n, 3))
    ev = error_values(params, q, strokes, profiles)  # (m, n, 21)
    dirs = travel_directions(stack, params[:, 18:21])  # (m, 3, 3)
    chain = np.broadcast_to(np.eye(4), (m, n, 4, 4))
    for j, a in enumerate(stack):
        base = 6 * int(a)
        delta = ev[..., base : base + 3]
        eps = ev[..., base + 3 : base + 6]
        rot = rotation_zyx(eps[..., 0], eps[..., 1], eps[..., 2])
        travel = (q[None, :, a] + dq[..., a])[..., None] * dirs[:, None, a, :]
        chain = chain @ htm(rot, mounts[j] + travel + delta)
    tool_h = np.append(np.asarray(tool, dtype=np.float64), 1.0)
    return (chain @ tool_h)[..., :3]


def probe_errors(params, q_cmd, dq, stack, mounts, tool, strokes, profiles) -> np.ndarray:
    """Probe position error E = P_actual - P_nominal (eq. 8, 10), shape (m, n, 3), mm.

    Arguments as :func:`probe_positions`.
    """
    q = np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    nominal = q + np.asarray(mounts, dtype=np.float64).sum(0) + np.asarray(tool, dtype=np.float64)
    return probe_positions(params, q, dq, stack, mounts, tool, strokes, profiles) - nominal


def probe_errors_for_bench(bench: Bench, params, q_cmd, dq=0.0) -> np.ndarray:
    """:func:`probe_errors` with the geometry taken from ``bench``; shape (m, n, 3), mm."""
    return probe_errors(
        params,
        q_cmd,
        dq,
        bench.stack_indices,
        bench.mounts_mm,
        bench.tool_offset_mm,
        bench.strokes_mm,
        bench.profiles,
    )


def sensitivities(bench: Bench, q_cmd, at=None, rel_step: float = 1e-3) -> np.ndarray:
    """Sensitivity coefficients dE/dX_k of the exact model (central differences).

    Parameters
    ----------
    bench : Bench
    q_cmd : ndarray, shape (n, 3), mm
    at : ndarray, shape (21,), optional
        Expansion point (mm, rad); default the means of the error PDFs.
    rel_step : float
        Step as a fraction of each error's std (absolute 1e-9 mm/rad when the std is 0).
        The model is a product of rotations, nearly linear at these scales, so the central
        difference is accurate to ~step**2 relative.

    Returns
    -------
    ndarray, shape (n, 3, 21)
        mm per mm (translations) and mm per rad (angles).
    """
    x0 = bench.error_means() if at is None else np.asarray(at, dtype=np.float64)
    h = np.where(bench.error_stds() > 0, bench.error_stds() * rel_step, 1e-9)
    k = len(x0)
    pts = np.vstack([x0 + np.diag(h), x0 - np.diag(h)])  # (2k, 21)
    e = probe_errors_for_bench(bench, pts, q_cmd)  # (2k, n, 3)
    return np.moveaxis((e[:k] - e[k:]) / (2.0 * h)[:, None, None], 0, -1)


# ---------------------------------------------------------------------------------------------
# Monte Carlo over the scan grid (GUM-S1 at paper scale)
# ---------------------------------------------------------------------------------------------

#: Quantities per point in the statistics arrays: the three error components and |E_p|.
QUANTITIES = ("x", "y", "z", "norm")


@dataclass(frozen=True)
class KernelGeometry:
    """Bench arrays in the layout the numba kernels take (``kernel_geometry``).

    Attributes
    ----------
    stack : ndarray, shape (3,), int64
        Bench axis index (0=x, 1=y, 2=z) of bodies 1, 2, 3 from the foundation.
    mounts : ndarray, shape (3, 3), mm
        Mount offsets in stack order.
    tool : ndarray, shape (3,), mm
        Probe offset in the top carriage frame.
    strokes : ndarray, shape (3,), mm
    profiles : ndarray, shape (21, n_coef)
    codes, pars : ndarray, shape (21,) int64 and (21, 4)
        Kernel PDF codes and parameters of the error amplitudes (mm, rad).
    sig : ndarray, shape (3,), mm
        Normal std of the axis-position noise (vibration, and the delay when it is normal).
    speed : ndarray, shape (3,), mm/s
        Speeds of the eq. 9 delay (zeros when the delay is normal).
    tau_code : int
        PDF code of tau, or -1.
    tau_par : ndarray, shape (4,)
    linear : bool
        True when all profiles are constant: the per-trial collapsed chain applies.
    """

    stack: np.ndarray
    mounts: np.ndarray
    tool: np.ndarray
    strokes: np.ndarray
    profiles: np.ndarray
    codes: np.ndarray
    pars: np.ndarray
    sig: np.ndarray
    speed: np.ndarray
    tau_code: int
    tau_par: np.ndarray
    linear: bool


def kernel_geometry(bench: Bench) -> KernelGeometry:
    """Arrays of ``bench`` for the kernels (and for the user's own ``@njit`` code)."""
    codes, pars = zip(*(e.pdf.kernel_code() for e in bench.errors), strict=True)
    if bench.delay.model == "speed_tau":
        tau_code, tau_par = bench.delay.tau_pdf.kernel_code()
        speed = np.asarray(bench.delay.speed_mm_s, dtype=np.float64)
    else:
        tau_code, tau_par, speed = -1, np.zeros(4), np.zeros(3)
    return KernelGeometry(
        stack=bench.stack_indices,
        mounts=np.ascontiguousarray(bench.mounts_mm),
        tool=np.asarray(bench.tool_offset_mm, dtype=np.float64),
        strokes=bench.strokes_mm,
        profiles=np.ascontiguousarray(bench.profiles),
        codes=np.array(codes, dtype=np.int64),
        pars=np.ascontiguousarray(np.array(pars, dtype=np.float64)),
        sig=bench.noise_std_mm(),
        speed=speed,
        tau_code=int(tau_code),
        tau_par=np.asarray(tau_par, dtype=np.float64),
        linear=not bench.position_dependent,
    )


def _keys(seed: int):
    check_seed(seed)  # the one seed rule and message of every command and of the API
    s = np.uint64(int(seed))
    # numba boxes uint64 results as Python ints; keep them uint64 for the kernels
    return tuple(
        np.uint64(int(K.stream_key(s, st)))
        for st in (K.STREAM_ERRORS, K.STREAM_NOISE, K.STREAM_FALLBACK)
    )


def noise_keys(seed: int) -> tuple[np.uint64, np.uint64]:
    """Stream keys (nkey, fkey) of the per-point noise for ``seed``: the first two arguments of
    ``_kernels.axis_noise_mm``, so user kernels draw the same noise as kinematics."""
    _, nkey, fkey = _keys(seed)
    return nkey, fkey


def draw_error_sets(bench: Bench, n_trials: int, seed: int, start: int = 0) -> np.ndarray:
    """The error amplitudes of trials ``start .. start+n_trials-1``: one row per trial.

    Reproducible from ``seed`` alone: row t depends only on (seed, t), not on threads, on
    ``start`` or on how the trials are split, so ``draw_error_sets(b, 10, s)[5:]`` equals
    ``draw_error_sets(b, 5, s, start=5)``.

    Parameters
    ----------
    bench : Bench
    n_trials : int
    seed : int in [0, 2**63)
    start : int
        Index of the first trial.

    Returns
    -------
    ndarray, shape (n_trials, 21), float64
        Columns in ``cfm_fem.bench.ERROR_NAMES`` order; translations in mm, angles in rad
        (amplitudes: an error's value at axis position q is amplitude x profile(q / stroke)).
    """
    g = kernel_geometry(bench)
    ekey, _, _ = _keys(seed)
    out = np.empty((int(n_trials), len(ERROR_NAMES)))
    K.draw_error_params(ekey, int(start), int(n_trials), g.codes, g.pars, out)
    return out


def _splitmix_numpy(key, counters):
    z = (np.uint64(key) + counters.astype(np.uint64) * K.GAMMA).astype(np.uint64)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def draw_error_sets_numpy(bench: Bench, n_trials: int, seed: int, start: int = 0) -> np.ndarray:
    """Plain-numpy twin of :func:`draw_error_sets` (scipy's ndtri for the normals); for tests."""
    ekey, _, _ = _keys(seed)
    t = np.arange(start, start + n_trials, dtype=np.uint64)[:, None]
    ctr = t * np.uint64(32) + np.arange(len(ERROR_NAMES), dtype=np.uint64)[None, :]
    with np.errstate(over="ignore"):
        h = _splitmix_numpy(ekey, ctr)
    u = ((h >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    g = kernel_geometry(bench)
    return np.stack([ppf_numpy(g.codes[k], g.pars[k], u[:, k]) for k in range(u.shape[1])], -1)


def point_noise(bench: Bench, trial: int, points, seed: int) -> np.ndarray:
    """Axis-position noise (vibration + delay) of trial ``trial`` at point indices ``points``.

    Returns
    -------
    ndarray, shape (len(points), 3), mm
        The same numbers the Monte Carlo kernels use for (seed, trial, point).
    """
    g = kernel_geometry(bench)
    _, nkey, fkey = _keys(seed)
    out = np.empty((len(points), 3))
    for r, i in enumerate(points):
        K.axis_noise_mm(
            nkey, fkey, int(trial), int(i), g.sig, g.speed, g.tau_code, g.tau_par, out[r]
        )
    return out


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

    def window(self, a, n, q, pidx, shift, wlo, winv, acc, below, whist):
        """Generic pass 1 over trials a .. a+n-1 (counts in slot windows)."""
        K.pass_window(self.model, a, n, q, pidx, shift, wlo, winv, acc, below, whist)

    def capture(self, a, n, q, pidx, wlo, winv, target, vlo, vhi, offset, fill, buf):
        K.pass_capture(self.model, a, n, q, pidx, wlo, winv, target, vlo, vhi, offset, fill, buf)

    def keep(self, a, n, q, pidx, shift, lo, hi, acc, below, store):
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

    Returns
    -------
    KinematicsResult
    """
    timer = _Timer()
    q = bench.grid_points() if q_cmd is None else np.atleast_2d(np.asarray(q_cmd, dtype=np.float64))
    q = np.ascontiguousarray(q)
    npts = q.shape[0]
    if npts >= 2**30:
        raise CfmInputError(f"at most 2**30 points; found {npts}")
    if adaptive_digits is None and int(trials) < 2:
        raise CfmInputError(f"trials must be >= 2; found {trials}")
    if point_index is None:
        pidx = np.arange(npts, dtype=np.int64)
    else:
        pidx = np.ascontiguousarray(point_index, dtype=np.int64)
        if pidx.shape != (npts,):
            raise CfmInputError(f"point_index must have shape ({npts},); found {pidx.shape}")
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
        lo, hi = _value_windows(pil[..., :-1])
        store = _Store(npts, cap)
        ends = _one_pass(eng, q, pidx, shift, lo, hi, store, total, p, acc, progress)
        del store
        _mean_std(shift, acc, total, bench.source)  # refuses NaN positions before any recount
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
                eng, sub, pidx[redo], pil[redo], probs, total, p, True, window_slots, None,
                source=bench.source,
            )  # fmt: skip
            low[redo], high[redo] = r_low, r_high
            notes.append(
                f"{len(redo)} point(s) whose window lost its interval end were recounted in two "
                "passes (exact)"
            )
            notes += sub_notes
            timer.mark("recount")
    else:
        acc, low, high, sub_notes, method = _two_pass_intervals(
            eng, q, pidx, pil, probs, total, p, exact, window_slots, progress, timer=timer,
            source=bench.source,
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
    eng.keep(a, n, q, pidx, shift, lo, hi, acc, np.zeros((npts, 4, 2), np.int64), _Store(npts, 0))


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


def _one_pass(eng, q, pidx, shift, lo, hi, store, total, p, acc, progress):
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
        eng.keep(a, n, q, pidx, shift, lo, hi, acc, below, store)
        if progress is not None:
            progress(n)
    ends = np.empty((npts, 4, 2))
    values, off, cap, fill, below_flat = flat
    K.select_ends(values, off, fill, cap, below_flat, lo.reshape(-1), hi.reshape(-1),
                  rank.reshape(-1), ends.reshape(-1))  # fmt: skip
    ends[lost] = np.nan
    return ends


def _two_pass_intervals(eng, q, pidx, pil, probs, total, p, exact, window_slots, progress,
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
        eng.window(a, n, q, pidx, shift, wlo, winv, acc, below, whist)
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
            eng.window(a, n, q_sel, p_sel, shift[sel], wlo[sel], winv[sel], junk, b_sel, h_sel)
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
            eng.capture(a, n, q, pidx, wlo, winv, slot, vlo, vhi, offset, fill, buf)
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

NOISE_NAME = "vibration+delay"

#: The two shares of the budget (`uncertainty_budget`), for its ``estimator`` text and the tables
#: that print them (``cfm-fem kinematics``, ``cfm-fem tolerance``).
VAR_SHARE_MEANING = (
    "var_share = the error's share of the variance u^2 (random part only; the first-order Sobol "
    "index of the linear model, in [0, 1])"
)
UP_SHARE_MEANING = (
    "up_share = the error's share of U_p^2 = sys^2 + u^2: (its variance + the mean over points of "
    "its mean error times the total mean error) / U_p^2, i.e. (1/2) d ln U_p^2 / d ln s_k for its "
    "tolerance scaled by s_k; the shares of an axis sum to 1 (100 %), and an error's is negative "
    "where its mean error opposes the total systematic error (tightening it slightly, alone, "
    "raises U_p)"
)


@dataclass(frozen=True)
class LinearModel:
    """First-order model of the pooled Table IV quantities in the 21 error amplitudes.

    With sensitivities c_ika = dE_a(point i)/dX_k at X = 0 (exact model, central differences),
    amplitude means mu_k and standard deviations sigma_k, and the axis-noise variance v_ia:

        mean_ia(s) = sum_k s_k c_ika mu_k                   (s_k scales error k)
        var_ia(s)  = sum_k s_k**2 c_ika**2 sigma_k**2 + v_ia
        U_p,a(s)**2 = mean_i [mean_ia(s)**2 + var_ia(s)]    (= sys_a**2 + u_a**2 of Table IV)

    Attributes
    ----------
    b : ndarray, shape (n, 3, 21), mm
        c_ika mu_k, the systematic contribution of each error.
    v : ndarray, shape (n, 3, 21), mm**2
        (c_ika sigma_k)**2, the variance contribution.
    noise_var : ndarray, shape (n, 3), mm**2
    """

    b: np.ndarray
    v: np.ndarray
    noise_var: np.ndarray

    def pooled(self, scale=None):
        """(systematic, std, U_p) per axis, each shape (3,), mm, for scale factors (21,)."""
        s = np.ones(self.b.shape[-1]) if scale is None else np.asarray(scale, dtype=np.float64)
        mean = (self.b * s).sum(-1)
        var = (self.v * s**2).sum(-1) + self.noise_var
        sys2 = np.mean(mean**2, axis=0)
        u2 = np.mean(var, axis=0)
        return np.sqrt(sys2), np.sqrt(u2), np.sqrt(sys2 + u2)

    def up2_coefficients(self, k: int):
        """U_p,a**2 = A s**2 + B s + C when only error k is scaled by s; arrays of shape (3,)."""
        bk = self.b[..., k]
        rest = self.b.sum(-1) - bk
        a = np.mean(bk**2 + self.v[..., k], axis=0)
        b = 2.0 * np.mean(bk * rest, axis=0)
        c = np.mean(rest**2 + self.v.sum(-1) - self.v[..., k] + self.noise_var, axis=0)
        return a, b, c

    def shares(self):
        """Budget per axis, shape (3, 22) each (21 errors + noise).

        Returns
        -------
        var_share : shares of the variance u**2 = mean_i var_ia: mean_i v_ika / u_a**2, in [0, 1]
            (linearised GUM; equal to first-order Sobol indices here since the inputs are
            independent and the model is linear to 1e-5). The systematic part is not in them.
        up_share : shares of U_p**2 = sys**2 + u**2: (mean_i b_ika m_ia + mean_i v_ika) /
            U_p,a**2, m_ia = sum_k b_ika the total mean error at point i; equal to
            (1/2) d ln U_p**2 / d ln s_k (elasticity: how much of U_p**2 goes with error k when
            its tolerance is scaled). They sum to 1; one is negative where error k's mean error
            opposes the total one (b_ika m_ia < 0 outweighs its variance), and is not a variance
            share.
        """
        mean = self.b.sum(-1)  # (n, 3)
        var_k = np.mean(self.v, axis=0)  # (3, 21)
        var_n = np.mean(self.noise_var, axis=0)  # (3,)
        u2 = var_k.sum(-1) + var_n
        sys_k = np.mean(self.b * mean[..., None], axis=0)  # (3, 21)
        up2 = np.mean(mean**2, axis=0) + u2
        # an axis with u = 0 (a bench with no error at all) has no shares to split: 0/0 is
        # reported as 0 (`uncertainty_budget` says so in a note) instead of NaN, which JSON refuses
        var_share = _share(np.concatenate([var_k, var_n[:, None]], axis=1), u2)
        up_share = _share(np.concatenate([sys_k + var_k, var_n[:, None]], axis=1), up2)
        return var_share, up_share


def _share(parts, total):
    """``parts / total[:, None]``, 0 where ``total`` is 0."""
    out = np.zeros_like(parts)
    np.divide(parts, total[:, None], out=out, where=total[:, None] > 0)
    return out


def linear_model(bench: Bench, q_cmd=None) -> LinearModel:
    """Sensitivities of the exact HTM model at zero error, for the budget and the design."""
    q = bench.grid_points() if q_cmd is None else np.atleast_2d(q_cmd)
    c = sensitivities(bench, q, at=np.zeros(len(ERROR_NAMES)))  # (n, 3, 21)
    mu, sd = bench.error_means(), bench.error_stds()
    g = kernel_geometry(bench)
    # noise enters through D_a ~ unit vectors: variance of the axis noise itself
    if g.tau_code >= 0:
        tau = bench.delay.tau_pdf
        nv = g.sig**2 + g.speed**2 * (tau.std**2 + tau.mean**2)
    else:
        nv = g.sig**2
    return LinearModel(b=c * mu, v=(c * sd) ** 2, noise_var=np.broadcast_to(nv, (q.shape[0], 3)))


def uncertainty_budget(bench: Bench, q_cmd=None) -> dict:
    """Share of each of the 21 errors (and of the noise) in u**2 and U_p**2 per axis.

    Estimator: the linearised model of :class:`LinearModel` with exact sensitivities (central
    differences of the HTM chain). ``var_share``, the share of the variance u**2, is the
    first-order (here also total) Sobol index for this near-linear model with independent
    inputs, in [0, 1]. ``up_share``, the share of U_p**2 = sys**2 + u**2, also counts the
    error's mean error times the total mean error: an elasticity, which sums to 1 over the rows
    and is negative for an error whose mean opposes the total systematic error
    (`LinearModel.shares`).

    Returns
    -------
    dict
        ``rows``: one dict per error (name, description, pdf, mean, std, per-axis shares);
        ``predicted``: linearised pooled systematic/std/U_p per axis in um.
    """
    lm = linear_model(bench, q_cmd)
    var_share, up_share = lm.shares()
    sys, u, up = lm.pooled()
    rows = []
    for k, spec in enumerate(bench.errors):
        unit_scale = 1e6 if spec.is_angle else 1e3  # rad -> urad, mm -> um
        rows.append(
            {
                "name": spec.name,
                "description": ERROR_DESCRIPTIONS[spec.name],
                "pdf": spec.pdf.scaled(unit_scale).describe(spec.unit if spec.unit else ""),
                "mean": spec.pdf.mean * unit_scale,
                "std": spec.pdf.std * unit_scale,
                "unit": "urad" if spec.is_angle else "um",
                "var_share": {a: float(var_share[j, k]) for j, a in enumerate("xyz")},
                "up_share": {a: float(up_share[j, k]) for j, a in enumerate("xyz")},
            }
        )
    rows.append(
        {
            "name": NOISE_NAME,
            "description": "vibration and reading delay (per point and trial)",
            "pdf": "normal per axis",
            "mean": 0.0,
            "std": float(np.mean(np.sqrt(lm.noise_var[0])) * 1e3),
            "unit": "um",
            "var_share": {a: float(var_share[j, -1]) for j, a in enumerate("xyz")},
            "up_share": {a: float(up_share[j, -1]) for j, a in enumerate("xyz")},
        }
    )
    notes = []
    for j, a in enumerate("xyz"):
        if not up[j] > 0:
            notes.append(f"U_p = 0 on axis {a}: no error contributes; its shares are written as 0")
        elif not u[j] > 0:
            notes.append(f"u = 0 on axis {a}: no random error; its var_share is written as 0")
    return {
        "estimator": (
            "linearised model with exact sensitivities (central differences of the HTM chain at "
            f"zero error); {VAR_SHARE_MEANING}; {UP_SHARE_MEANING}"
        ),
        "notes": notes,
        "rows": rows,
        "predicted": {
            a: {"systematic_um": 1e3 * sys[j], "std_um": 1e3 * u[j], "U_p_um": 1e3 * up[j]}
            for j, a in enumerate("xyz")
        },
    }


def design_tolerances(bench: Bench, target_up_mm, q_cmd=None) -> dict:
    """Design in reverse: how far each tolerance may be loosened (or must be tightened).

    Scaling a tolerance by s scales that error's PDF about zero (mean and width). For each error
    alone, the largest s that keeps U_p,a <= target_a on every axis follows from the quadratic
    U_p,a**2(s) = A s**2 + B s + C. A common factor for all 21 errors is given too.

    Parameters
    ----------
    bench : Bench
    target_up_mm : array_like, shape (3,), mm
        Target U_p per axis (x, y, z); ``inf`` leaves an axis free.

    Returns
    -------
    dict
        ``current``: U_p per axis (um); ``rows`` sorted by the largest absolute ``up_share`` first
        (share of U_p**2, `LinearModel.shares`: may be negative), each with
        ``factor`` (largest admissible s; > 1 loosen, < 1 tighten, None if no s works alone,
        inf if the error does not matter), ``up_at_factor_um``; ``common_factor`` and
        ``up_at_common_um``; ``noise_floor_um`` (U_p with all 21 errors at zero).
    """
    target = np.broadcast_to(np.asarray(target_up_mm, dtype=np.float64), (3,))
    lm = linear_model(bench, q_cmd)
    _, _, up_now = lm.pooled()
    _, up_share = lm.shares()
    t2 = target**2
    nerr = len(bench.errors)
    rows = []
    for k, spec in enumerate(bench.errors):
        s_max = _factor_alone(lm, k, np.ones(nerr), t2)
        up_at = None
        if s_max is not None and np.isfinite(s_max):
            s = np.ones(nerr)
            s[k] = s_max
            up_at = (1e3 * lm.pooled(s)[2]).tolist()
        rows.append(
            {
                "name": spec.name,
                "description": ERROR_DESCRIPTIONS[spec.name],
                "pdf": spec.pdf.scaled(1e6 if spec.is_angle else 1e3).describe(spec.unit),
                "up_share": {a: float(up_share[j, k]) for j, a in enumerate("xyz")},
                "factor": s_max,
                "up_at_factor_um": up_at,
            }
        )
    order = sorted(range(nerr), key=lambda k: -max(abs(up_share[:, k])))
    rows = [rows[k] for k in order]
    # common factor f for all errors: U_p^2 = f^2 (sys^2 + u_err^2) + noise (b scales with f)
    mean = lm.b.sum(-1)
    err2 = np.mean(mean**2, axis=0) + np.mean(lm.v.sum(-1), axis=0)
    noise = np.mean(lm.noise_var, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f_axes = np.sqrt(np.maximum(t2 - noise, 0.0) / err2)
    f_axes = np.where(t2 <= noise, 0.0, f_axes)
    common = float(np.min(f_axes))
    # common = inf when no error matters (a bench without errors): any factor leaves U_p as is
    up_common = (1e3 * lm.pooled(np.full(nerr, common if np.isfinite(common) else 1.0))[2]).tolist()
    # greedy plan: tighten the largest contributors to a violated axis, one at a time
    s = np.ones(nerr)
    plan = []
    for _ in range(3 * nerr):
        up = lm.pooled(s)[2]
        bad = np.nonzero(up > target * (1 + 1e-12))[0]
        if len(bad) == 0:
            break
        a = bad[np.argmax(up[bad] / target[bad])]
        _, shares_now = LinearModel(lm.b * s, lm.v * s**2, lm.noise_var).shares()
        cand = [
            k for k in np.argsort(-shares_now[a, :nerr]) if s[k] > 0.05 and shares_now[a, k] > 0
        ]
        if not cand:
            break
        k = int(cand[0])
        f = _factor_alone(lm, k, s, t2, axes=[a])
        new = max(0.5 * s[k], f * s[k] if f is not None and f < 1 else 0.5 * s[k])
        s[k] = new
        plan.append({"name": bench.errors[k].name, "factor": float(new)})
    merged = {}
    for step in plan:
        merged[step["name"]] = step["factor"]
    return {
        "target_um": (1e3 * target).tolist(),
        "current_um": (1e3 * up_now).tolist(),
        "noise_floor_um": (1e3 * np.sqrt(noise)).tolist(),
        "rows": rows,
        "common_factor": common,
        "up_at_common_um": up_common,
        "plan": [{"name": n, "factor": f} for n, f in merged.items()],
        "up_after_plan_um": (1e3 * lm.pooled(s)[2]).tolist(),
        "feasible": bool(np.all(t2 > noise)),
        "method": (
            "linearised Table IV pooling, U_p^2 = mean over points of (mean error^2 + variance); "
            "scaling a tolerance by s scales that error's PDF about zero; 'factor' is the largest "
            "s for that error alone that keeps every axis it influences within target"
        ),
    }


def _factor_alone(lm, k, s0, t2, axes=None):
    """Largest multiplier of s0[k] meeting the targets on the axes error k influences."""
    base = LinearModel(lm.b * s0, lm.v * s0**2, lm.noise_var)
    a, b, c = base.up2_coefficients(k)
    infl = a > 1e-9 * (a + np.abs(b) + c)
    if axes is not None:
        infl = infl & np.isin(np.arange(3), axes)
    if not np.any(infl):
        return np.inf
    return _largest_admissible(a[infl], b[infl], c[infl], t2[infl])


def _largest_admissible(a, b, c, t2):
    """Largest s >= 0 with a s^2 + b s + c <= t2 on every axis; inf if unbounded, None if none."""
    lo, hi = 0.0, np.inf
    for ai, bi, ci, ti in zip(a, b, c, t2, strict=True):
        if not np.isfinite(ti):
            continue
        cc = ci - ti
        if ai <= 1e-30 * max(abs(bi), abs(cc), 1e-300):  # error k has no effect on this axis
            if abs(bi) < 1e-300:
                if cc > 0:
                    return None
                continue
            root = -cc / bi
            if bi > 0:
                hi = min(hi, root)
            else:
                lo = max(lo, root)
            continue
        disc = bi * bi - 4 * ai * cc
        if disc < 0:
            return None
        r1 = (-bi - np.sqrt(disc)) / (2 * ai)
        r2 = (-bi + np.sqrt(disc)) / (2 * ai)
        lo, hi = max(lo, r1), min(hi, r2)
    if hi < max(lo, 0.0):
        return None
    return float(hi)


def gum_check(bench: Bench, result: KinematicsResult, ndig: int = 2) -> dict:
    """JCGM 101 section 8 per point and axis: linearised GUM interval vs the Monte Carlo one.

    GUM: y = linearised mean, u = linearised std, interval y -+ 1.96 u (normal output);
    delta = numerical tolerance of the Monte Carlo u for ``ndig`` significant digits.

    Returns
    -------
    dict of axis -> {"valid_fraction", "max_d_um", "median_delta_um"}
    """
    lm = linear_model(bench, result.q_cmd)
    y = lm.b.sum(-1)
    u = np.sqrt(lm.v.sum(-1) + lm.noise_var)
    k = 1.959963984540054
    out = {}
    for j, a in enumerate("xyz"):
        delta = numerical_tolerance(result.std[:, j], ndig)
        d_low, d_high, ok = gum_validation(
            y[:, j], k * u[:, j], result.low[:, j], result.high[:, j], delta
        )
        out[a] = {
            "valid_fraction": float(np.mean(ok)),
            "max_d_um": 1e3 * float(np.max(np.maximum(d_low, d_high))),
            "median_delta_um": 1e3 * float(np.median(delta)),
        }
    return out
