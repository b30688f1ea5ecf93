"""From a recording to a diagnosis problem: residuals, positions, aux columns, baseline model.

Tracker: y = measured - nominal probe position (bench frame, mm); baseline = the 21 geometric
errors (exact HTM chain, linearised at zero, Table II priors) + the tracker-to-bench registration
(3 translations, 3 small rotations about the centroid of the points).

Hall map: y = measured - reference field (magnet frame, T); baseline = the 21 errors seen through
the field gradient, the magnet-to-bench registration (translation, small rotation about the
magnet origin; survey-sized priors), the probe gains (S_HP, 0.15 % std). The problem may be
linearised at a registration other than the nominal one (``pose``: the reference evaluated with
the magnet moved there; :mod:`~cfm_fem.workflows.diagnose.register` iterates it).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from ...models.bench import AXES, ERROR_NAMES, Bench
from ...models.kinematics.chain import probe_errors_for_bench, sensitivities
from ...models.recordings import check_hall_scale
from .calibrate import Columns
from .context import ProblemContext
from .derivatives import (
    debiased_jacobian,
    field_derivatives,
    field_hessian,
    field_hessian_diag,
    field_jacobian,
    field_third,
)
from .elements import at_elements, element_offsets, linear_term
from .motion import axis_velocities
from .reference_rows import REF_LOCAL_SHARE, reference_error_terms

__all__ = ["Problem", "tracker_problem", "hall_problem", "field_jacobian", "subset_rows"]

UM, URAD = 1e-3, 1e-6  # display units of the bench errors (mm, rad per unit)


@dataclass
class Problem:
    """Everything the diagnosis needs, independent of file formats.

    Attributes
    ----------
    kind : {'tracker', 'hall'}
    y : ndarray, shape (n, 3)
        Residual to explain (mm or T).
    pos : ndarray, shape (n, 3), mm
        Position of each row for maps and regions (bench frame or magnet frame).
    q : ndarray, shape (n, 3), mm
        Commanded axis positions (bench axes).
    point : ndarray, shape (n,), int
        Index of the distinct point of each row.
    rep : ndarray, shape (n,), int
    t_h, speed, temp : ndarray, shape (n,), or None
        Time (h), speed (mm/s), temperature (degC).
    dir : ndarray, shape (n, 3), or None
        Each axis's own last approach direction (-1, +1; 0 unknown).
    vel : ndarray, shape (n, 3), mm/s, or None
        Signed axis velocities at acquisition (recorded, or inferred by
        :func:`~cfm_fem.workflows.diagnose.motion.axis_velocities`).
    var_ref : ndarray, shape (n, 3), or None
        Variance of the reference's own interpolation error (y units^2), added to the noise
        at the share the residuals show (:func:`~cfm_fem.workflows.diagnose.noise.reference_share`);
        None for an exact reference.
    ref_cell : ndarray, shape (n,), or None
        Factor by which each row's ``var_ref`` exceeds its point's own error variance: the
        readings that share that error
        (:func:`~cfm_fem.workflows.diagnose.reference_rows.shared_by`, and the point's cell on
        a 3-D map).
    ref_bound : ndarray, shape (n, 3), or None
        A bound on the reference's error per row, as ``var_ref`` carries it (>= ``var_ref``):
        what a point or plane must depart by to be named (:func:`located_sigma`).
    to_display : float
        Factor from the unit of ``y`` to the reported unit (``unit``).
    unit : str
    var_known : ndarray, shape (n, 3)
        Variance known from the bench model (vibration + delay through the gradient), y units^2.
    baseline : list of Columns
    ctx : ProblemContext
        Model pieces the effect catalogue needs (field values, gradients, bench).
    notes : list of str
    """

    kind: str
    y: np.ndarray
    pos: np.ndarray
    q: np.ndarray
    point: np.ndarray
    rep: np.ndarray
    t_h: np.ndarray | None
    dir: np.ndarray | None
    speed: np.ndarray | None
    temp: np.ndarray | None
    to_display: float
    unit: str
    var_known: np.ndarray
    baseline: list
    ctx: ProblemContext = field(default_factory=ProblemContext)
    notes: list = field(default_factory=list)
    vel: np.ndarray | None = None
    var_ref: np.ndarray | None = None
    ref_cell: np.ndarray | None = None
    ref_bound: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.y.shape[0]

    @property
    def n_points(self) -> int:
        return int(self.point.max()) + 1

    @property
    def n_reps(self) -> int:
        return int(np.bincount(self.point).max())


def subset_rows(prob: Problem, keep) -> Problem:
    """The problem restricted to the rows ``keep`` (bool (n,)): every per-row array, the
    baseline columns and the per-row model pieces of ``ctx`` sliced, points renumbered."""
    keep = np.asarray(keep, dtype=bool)
    n = prob.n

    def take(a):
        return a[keep] if isinstance(a, np.ndarray) and a.ndim >= 1 and a.shape[0] == n else a

    kept, point = np.unique(prob.point[keep], return_inverse=True)
    return replace(
        prob,
        y=prob.y[keep],
        pos=prob.pos[keep],
        q=prob.q[keep],
        point=point.reshape(-1),
        rep=prob.rep[keep],
        t_h=take(prob.t_h),
        dir=take(prob.dir),
        speed=take(prob.speed),
        temp=take(prob.temp),
        var_known=prob.var_known[keep],
        baseline=[
            Columns(
                b.J[keep],
                b.names,
                b.units,
                b.prior_mean,
                b.prior_std,
                b.group,
                b.bounds,
                b.release,
                b.release_bounds,
            )
            for b in prob.baseline
        ],
        ctx=prob.ctx.subset(keep, kept),
        notes=list(prob.notes),
        vel=take(prob.vel),
        var_ref=take(prob.var_ref),
        ref_cell=take(prob.ref_cell),
        ref_bound=take(prob.ref_bound),
    )


def _aux(rec):
    t_h = None if rec.t_s is None else rec.t_s / 3600.0
    d = None if rec.dir is None else rec.dir.astype(np.float64)
    return t_h, d, rec.speed, rec.temp_C


def _velocities(rec, notes):
    """Axis velocities at acquisition (recorded or inferred), with a note on their source."""
    vel, source = axis_velocities(rec.cmd, rec.speed, rec.t_s, rec.vel)
    if source == "inferred" and rec.speed is not None and np.any(rec.speed > 0):
        notes.append(
            "axis velocities at acquisition inferred from the commanded positions, t_s and "
            "speed (no v_x, v_y, v_z columns)"
        )
    return vel


def bench_columns(bench: Bench, q, lever_to=None) -> Columns:
    """The 21 errors as columns (n, 3, 21) of probe displacement, mm per um or urad.

    ``lever_to``: optional (n, 3, 3) matrix applied to the displacement (gradient for a Hall map).
    """
    upts, inv = np.unique(np.round(q, 9), axis=0, return_inverse=True)
    s = sensitivities(bench, upts, at=np.zeros(len(ERROR_NAMES)))  # (m, 3, 21) mm/mm, mm/rad
    unit = np.where([n.startswith(("eps", "alpha")) for n in ERROR_NAMES], URAD, UM)
    J = s[inv.reshape(-1)] * unit
    if lever_to is not None:
        J = np.einsum("nij,njp->nip", lever_to, J)
    mean = bench.error_means() / unit
    std = bench.error_stds() / unit
    std = np.where(std > 0, std, 1e-6)
    units = ["urad" if u == URAD else "um" for u in unit]
    return Columns(J, list(ERROR_NAMES), units, mean, std, "bench")


#: Prior std of the tracker-to-bench registration: mm, rad (1 sigma per axis). The tracker is
#: set up anywhere near the bench: its registration is found by the fit, not known before it.
TRACKER_REG_STD_DEFAULT = (1.0, 1e-3)


def tracker_problem(rec, bench: Bench, reg_std_mm: float | None = None,
                    reg_std_rad: float | None = None):  # fmt: skip
    """Problem of a laser-tracker recording (bench frame, mm).

    Parameters
    ----------
    rec : Recording, kind 'tracker'
    bench : Bench
    reg_std_mm, reg_std_rad : float, optional
        Prior std of the tracker-to-bench registration (translation mm, rotation rad);
        None: :data:`TRACKER_REG_STD_DEFAULT`.
    """
    t_mm, r_rad = TRACKER_REG_STD_DEFAULT
    prior = {
        "translation_mm": t_mm if reg_std_mm is None else float(reg_std_mm),
        "rotation_rad": r_rad if reg_std_rad is None else float(reg_std_rad),
        "translation_source": "default" if reg_std_mm is None else "argument",
        "rotation_source": "default" if reg_std_rad is None else "argument",
    }
    reg_std_mm, reg_std_rad = prior["translation_mm"], prior["rotation_rad"]
    ids, point = np.unique(rec.point_id, return_inverse=True)
    q = rec.cmd
    nominal = bench.nominal_probe_mm(q)
    y = rec.meas - nominal
    n = len(rec)
    base = bench_columns(bench, q)
    c = nominal - nominal.mean(0)
    reg = np.zeros((n, 3, 6))
    for a in range(3):
        reg[:, a, a] = UM
    for a in range(3):  # small rotation about axis a: omega x c
        e = np.zeros(3)
        e[a] = URAD
        reg[:, :, 3 + a] = np.cross(e, c)
    regc = Columns(
        reg,
        ["t_x", "t_y", "t_z", "rot_x", "rot_y", "rot_z"],
        ["um"] * 3 + ["urad"] * 3,
        np.zeros(6),
        np.r_[np.full(3, reg_std_mm / UM), np.full(3, reg_std_rad / URAD)],
        "registration",
    )
    t_h, d, speed, temp = _aux(rec)
    notes = [
        "tracker residual = measured - (commanded + mounts + tool offset), bench frame",
        f"registration prior: {reg_std_mm * 1e3:g} um, {reg_std_rad * 1e6:g} urad (1 sigma)",
    ]
    return Problem(
        kind="tracker",
        y=y,
        pos=nominal,
        q=q,
        point=point.reshape(-1),
        rep=rec.rep,
        t_h=t_h,
        dir=d,
        speed=speed,
        temp=temp,
        to_display=1e3,
        unit="um",
        var_known=np.zeros_like(y),
        baseline=[base, regc],
        ctx=ProblemContext(bench=bench, nominal=nominal, point_ids=ids, registration_prior=prior),
        notes=notes,
        vel=_velocities(rec, notes),
    )


#: The magnet-to-bench registration parameters of a Hall map (um, um, um, urad, urad, urad).
REG_NAMES = ("magnet_dx", "magnet_dy", "magnet_dz", "magnet_rot_x", "magnet_rot_y", "magnet_roll")


def posed_field(field_fn, pose):
    """The reference field of a magnet moved by ``pose``: B'(p) = R B(R^T (p - t)).

    Parameters
    ----------
    field_fn : callable
        ``field_fn(points (k, 3) mm) -> B (k, 3) T`` in the magnet's own frame.
    pose : ndarray, shape (6,)
        Translation t (um) and rotation vector of R (urad), in the order of :data:`REG_NAMES`.

    Returns
    -------
    callable
        The field at map points (k, 3) mm, T; ``field_fn`` itself for a zero pose.
    """
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=float)
    if not np.any(pose):
        return field_fn
    t = pose[:3] * UM
    R = Rotation.from_rotvec(pose[3:] * URAD).as_matrix()

    def fn(p):
        return field_fn((np.asarray(p, dtype=float) - t) @ R) @ R.T

    return fn


def _registration_and_gains(B0, G, p, reg_std_mm, reg_std_rad, gain_std_pct, B_gain=None) -> list:
    """The magnet-to-bench registration (translation, small rotation about the magnet origin)
    and the Hall gains as baseline columns of a Hall map, with their priors.

    ``B0``, ``G``: the field and its gradient at the readings, the magnet at its current pose;
    ``p``: the readings' positions from the magnet origin (mm); ``B_gain``: the field the
    gains multiply (default ``B0``)."""
    B_gain = B0 if B_gain is None else B_gain
    n = len(p)
    reg = np.zeros((n, 3, 6))
    reg[:, :, 0:3] = -G * UM  # magnet moved by +t: B(p - t)
    for a in range(3):
        e = np.zeros(3)
        e[a] = URAD
        reg[:, :, 3 + a] = np.cross(e, B0) - np.einsum("nij,nj->ni", G, np.cross(e, p))
    gain = np.zeros((n, 3, 3))
    for i in range(3):
        gain[:, i, i] = B_gain[:, i] * 1e-2
    return [
        Columns(
            reg,
            list(REG_NAMES),
            ["um"] * 3 + ["urad"] * 3,
            np.zeros(6),
            np.r_[np.full(3, reg_std_mm / UM), np.full(3, reg_std_rad / URAD)],
            "registration",
        ),
        Columns(
            gain,
            ["gain_x", "gain_y", "gain_z"],
            ["%"] * 3,
            np.zeros(3),
            np.full(3, gain_std_pct),
            "probe",
        ),  # fmt: skip
    ]


def bench_expansion(bench: Bench, q, p, theta, B0, G, H, T=None):
    """The field where the bench's errors ``theta`` put the probe, to third order.

    The bench columns model a reading as the field at the probe's point, moved by the errors
    along their linear sensitivities D: B(p) + G D theta. That line leaves out the
    higher-order terms of the move, d^T H d / 2, which on a multipole scanned far from the
    bench's origin (angular errors of tens of urad on levers of hundreds of mm: moves of tens
    of um) is above a Hall probe's noise and shares the signature of a sensor's volume
    averaging, and T d d d / 6, all there is on an octupole's axis, where G and H vanish.
    Expanded at ``theta`` instead, a reading is

        B(p + d) + G D (theta' - theta),  B(p + d) = B + G d + H d d / 2 + T d d d / 6,

    d the exact move of the bench's kinematic chain, H and T the reference's second and third
    derivatives over a step of half a mm or a node spacing (a reference read between nodes is
    not differentiable at them on the scale of the move; its curvature over a cell is). The
    columns of the bench and of the registration take the gradient where the probe is,
    G + H d + T d d / 2 (:func:`moved_gradient`), so that the Gauss-Newton iterations
    (:func:`~cfm_fem.workflows.diagnose.register.bench_step`) stop at the optimum: on a
    sextupole's axis G vanishes, while H d, for a move of tens of um, is what the readings
    there say about the errors and the magnet's offset.

    Parameters
    ----------
    bench : Bench
    q : ndarray, shape (n, 3), mm
        Axis positions of the readings.
    p : ndarray, shape (n, 3), mm
        The readings' points, magnet frame.
    theta : ndarray, shape (21,)
        The errors, in the bench columns' units (um, urad).
    B0, G : ndarray, shapes (n, 3) T and (n, 3, 3) T/mm
        Field and gradient at ``p``.
    H : ndarray, shape (n, 3, 3, 3), T/mm^2, or None
        Hessian at ``p`` (None only with all errors zero).
    T : ndarray, shape (n, 3, 3, 3, 3), T/mm^3, optional
        Third derivatives at ``p``; None: the expansion stops at second order.

    Returns
    -------
    ndarray, shape (n, 3), T
        B(p + d) to third order.
    """
    d = bench_move(bench, q, theta)
    if d is None or len(p) != len(B0):
        return B0
    Hd = np.einsum("nijk,nk->nij", H, d)
    if T is not None:
        Hd = Hd + np.einsum("nijkl,nk,nl->nij", T, d, d) / 3.0
    return B0 + np.einsum("nij,nj->ni", G + 0.5 * Hd, d)


def moved_gradient(bench: Bench, q, theta, G, H, T=None):
    """The field's gradient where the bench errors ``theta`` put the probe, to second order.

    The bench errors put the probe d away from its nominal point; the readings' Jacobian in
    the errors and in the magnet's offset, and the lever of the axes' vibration, are the
    gradient there, G + H d + T d d / 2. On a sextupole's axis G vanishes while H d, for a
    move of tens of um, turns a few um of vibration into several uT (far above a low-noise
    probe's floor) and an error of the registration into as much; on an octupole's axis H
    vanishes too and the gradient there is T d d / 2.

    Parameters
    ----------
    bench : Bench
    q : ndarray, shape (n, 3), mm
        Axis positions of the readings.
    theta : ndarray, shape (21,)
        The errors, in the bench columns' units (um, urad).
    G : ndarray, shape (n, 3, 3), T/mm
        Gradient at the nominal points.
    H : ndarray, shape (n, 3, 3, 3), T/mm^2, or None
        Hessian there; None: ``G`` itself is returned.
    T : ndarray, shape (n, 3, 3, 3, 3), T/mm^3, optional
        Third derivatives there; None: the term in d d is left out.

    Returns
    -------
    ndarray, shape (n, 3, 3), T/mm
    """
    d = None if H is None else bench_move(bench, q, theta)
    if d is None or len(H) != len(G):
        return G
    out = G + np.einsum("nijk,nk->nij", H, d)
    if T is not None:
        out = out + 0.5 * np.einsum("nijkl,nk,nl->nij", T, d, d)
    return out


def bench_move(bench: Bench, q, theta):
    """The probe's exact move by the bench errors ``theta`` (um, urad; order of
    ``ERROR_NAMES``) at the axis positions ``q`` (n, 3) mm: (n, 3) mm in the magnet frame,
    or None for all errors zero."""
    unit = np.where([n.startswith(("eps", "alpha")) for n in ERROR_NAMES], URAD, UM)
    th = np.asarray(theta, dtype=float) * unit  # mm, rad
    if not np.any(th):
        return None
    R = bench.bench_to_magnet_rotation()
    return probe_errors_for_bench(bench, th[None, :], q)[0] @ R.T


def _node_step(upts, spacing_mm, nodes):
    """The node spacing of a linear reference map when every reading's point is one of its
    nodes (second differences of that step then read the map's node values), else None."""
    if spacing_mm is None or nodes is None:
        return None
    from scipy.spatial import cKDTree

    d, _ = cKDTree(nodes).query(upts)
    return float(spacing_mm) if np.all(d <= 1e-3 * spacing_mm) else None


def _field_at_pose(field_fn, upts, pose, h, smooth, h2=None, derivs=None, shift=None):
    """Field (m, 3) T and gradient (m, 3, 3) T/mm at the points ``upts`` with the magnet at
    ``pose``, the posed field function, and the Hessian (m, 3, 3, 3) T/mm^2 there (None
    without ``derivs``). ``h2``: step of the Hessian of a linear map (its node spacing: a
    shorter step sees no curvature inside a cell), default ``h``. ``derivs``: the Hessian and
    third derivatives (m, 3, 3, 3, 3) T/mm^3 at the nominal placement, or None. ``shift``
    (3,) mm: every point moved by it (a Hall element's offset,
    :func:`~cfm_fem.workflows.diagnose.elements.at_elements`), the derivatives still those
    at ``upts``.

    A smooth reference is evaluated at the moved points. A map interpolated linearly between
    its nodes is not: between nodes its kinks would make the fit jump from one linearisation
    to the next, and a point moved outside it has no value. Its field is expanded to third
    order about the points instead (value, gradient and higher derivatives by differences of
    step ``h``: node values on a map with nodes either side of each point), which holds the
    second- and third-order terms of the move. The Hessian at the pose is the nominal one
    moved by the third derivatives: on an octupole's axis the nominal Hessian vanishes, while
    a magnet offset of tens of um gives it T s."""
    from scipy.spatial.transform import Rotation

    fn = posed_field(field_fn, pose)
    H0, T = (None, None) if derivs is None else derivs
    if not np.any(pose) and shift is None:
        return field_fn(upts), debiased_jacobian(field_fn, upts, h, T), fn, H0
    pts = upts if shift is None else upts + np.asarray(shift, dtype=float)
    R = Rotation.from_rotvec(pose[3:] * URAD).as_matrix()
    d = (pts - pose[:3] * UM) @ R - upts  # where the magnet frame sees each point, less it
    H = H0
    if H is None and not smooth:
        H = field_hessian(field_fn, upts, h if h2 is None else max(h, h2))
    Hp = None
    if H is not None:
        Hp = H if T is None else H + np.einsum("nijkl,nl->nijk", T, d)
        Hp = np.einsum("ia,najk,bj,ck->nibc", R, Hp, R, R)
    if smooth:
        return fn(pts), debiased_jacobian(fn, pts, h, T), fn, Hp
    B, G = field_fn(upts), debiased_jacobian(field_fn, upts, h, T)
    Hd = np.einsum("nijk,nk->nij", H, d)
    dG = Hd if T is None else Hd + 0.5 * np.einsum("nijkl,nk,nl->nij", T, d, d)
    B = B + np.einsum("nij,nj->ni", G + 0.5 * Hd, d)
    if T is not None:
        B = B + np.einsum("nijkl,nj,nk,nl->ni", T, d, d, d) / 6.0
    G = G + dG
    return B @ R.T, np.einsum("ab,nbc,dc->nad", R, G, R), fn, Hp


def _without_fn(at_pose) -> tuple:
    """Field, gradient and Hessian of a :func:`_field_at_pose` result (its function left out)."""
    return at_pose[0], at_pose[1], at_pose[3]


def _axis_positions(bench, p, notes):
    """The bench's axis positions (n, 3) mm of the readings ``p`` and the bench (None when
    the map exceeds its strokes); a map placed outside the strokes is centred in them. The
    assumptions made are appended to ``notes``."""
    if bench is None:
        return np.zeros_like(p), None
    q = bench.axis_positions_for(p)
    if np.any(bench.outside_stroke(q)):
        span = p.max(0) - p.min(0)
        if np.any(span > bench.strokes_mm):
            notes.append(
                "the map is larger than the bench strokes: positioning errors not modelled"
            )
            return np.zeros_like(p), None
        q = q - q.mean(0) + bench.strokes_mm / 2
        notes.append(
            "bench magnet placement puts the map outside the strokes; the map was "
            "centred in the working volume (assumption)"
        )
    return q, bench


def _planar_at_pose(field_fn, p, pose, h, bench, q, at, shift=None):
    """A 2-D reference at the readings: field (n, 3) T and gradient (n, 3, 3) T/mm of the
    registration's columns, and the exact reading (n, 3) T.

    Both are evaluated where the bench errors ``at`` move the probe (exact chain), moved
    further by ``shift`` (3,) mm if given (a Hall element's offset). The reading is the field
    with the magnet at the whole ``pose``; the registration is linearised with the magnet
    offset and rolled only, which keeps the field 2-D (see :func:`hall_problem`,
    ``planar``)."""
    d = None if bench is None else bench_move(bench, q, at)
    moved = p if d is None else p + d
    if shift is not None:
        moved = moved + np.asarray(shift, dtype=float)
    fn = posed_field(field_fn, pose * (1.0, 1.0, 1.0, 0.0, 0.0, 1.0))
    return fn(moved), field_jacobian(fn, moved, h), posed_field(field_fn, pose)(moved)


def _is_planar(field_fn, upts, h) -> bool:
    """Whether a reference is a 2-D field at the points ``upts`` (mm): B_z and every
    derivative along z zero there (2-D harmonics)."""
    B = field_fn(upts)
    if np.any(B[:, 2]):
        return False
    e = np.array([0.0, 0.0, h])
    return not (np.any(field_fn(upts + e) - B) or np.any(field_fn(upts - e) - B))


#: Prior std of the magnet-to-bench registration where neither the caller nor the bench file
#: (``[magnet] survey_std_um``, ``survey_std_urad``) states it: mm, rad (1 sigma per axis).
SURVEY_STD_DEFAULT = (0.05, 1e-4)


def registration_prior(bench: Bench | None, reg_std_mm=None, reg_std_rad=None) -> dict:
    """The magnet-to-bench registration prior of a Hall map and where it comes from.

    Each std is the one given, else the bench's survey (``[magnet] survey_std_um``,
    ``survey_std_urad`` of its file), else :data:`SURVEY_STD_DEFAULT`.

    Returns
    -------
    dict
        ``translation_mm``, ``rotation_rad`` (1 sigma per axis), the source of each
        (``translation_source``, ``rotation_source``: ``'argument'``, ``'bench file'`` or
        ``'default'``) and ``bench_file`` (the bench's source).
    """
    magnet = None if bench is None else bench.magnet
    stated = (None, None) if magnet is None else (magnet.survey_std_mm, magnet.survey_std_rad)
    out = {"bench_file": None if bench is None else str(bench.source)}
    given = (reg_std_mm, reg_std_rad)
    keys = (("translation_mm", "translation_source"), ("rotation_rad", "rotation_source"))
    for (k, k_src), g, b, d in zip(keys, given, stated, SURVEY_STD_DEFAULT, strict=True):
        value, src = (g, "argument") if g is not None else (b, "bench file")
        if value is None:
            value, src = d, "default"
        out[k], out[k_src] = float(value), src
    return out


def _prior_note(prior: dict) -> str:
    """Where the registration prior of a Hall map comes from, for the notes."""
    src = {prior["translation_source"], prior["rotation_source"]}
    head = (
        f"registration prior (survey of the magnet, 1 sigma per axis): "
        f"{prior['translation_mm'] * 1e3:g} um, {prior['rotation_rad'] * 1e6:g} urad"
    )
    if src == {"bench file"}:
        return f"{head} from [magnet] survey_std_um, survey_std_urad of {prior['bench_file']}"
    if src == {"default"}:
        return f"{head}, the default: the bench states no [magnet] survey_std_um, survey_std_urad"
    return (
        f"{head}; translation from the {prior['translation_source']}, rotation from the "
        f"{prior['rotation_source']}"
    )


#: Finite-difference step of the gradient of a smooth reference, mm.
STEP_SMOOTH_MM = 0.05
#: Finite-difference step of the gradient of a map read linearly, mm.
STEP_MAP_MM = 0.5


def hall_problem(
    rec,
    field_fn,
    b_ref: float,
    bench: Bench | None,
    *,
    reg_std_mm: float | None = None,
    reg_std_rad: float | None = None,
    gain_std_pct: float = 0.15,
    smooth: bool = True,
    h: float | None = None,
    ref_spacing_mm: float | None = None,
    ref_nodes=None,
    pose=None,
    ref_error=None,
    bench_at=None,
    hessian=None,
    planar=None,
    elements_at=None,
    ref_share=None,
    ref_bound=None,
):
    """Problem of a Hall map against a reference field.

    The model is linearised in the registration at ``pose`` (Gauss-Newton): the reference is
    evaluated with the magnet moved there (:func:`posed_field`), its gradient too, and the
    residual is ``y = B_meas - B'(pose) + J_reg pose``, so that the registration parameters
    fitted to ``y`` are the magnet's whole offset and rotation, not an increment
    (:func:`~cfm_fem.workflows.diagnose.register.register` moves ``pose`` to their estimate).

    Parameters
    ----------
    rec : Recording, kind 'hall'
    field_fn : callable
        ``field_fn(points (k, 3) mm, magnet frame) -> B (k, 3) T``.
    b_ref : float, T
        Reference field of 'units' (1e-4 b_ref).
    bench : Bench or None
        None: no positioning-error columns (bench unknown).
    reg_std_mm, reg_std_rad : float, optional
        Prior std of the magnet-to-bench registration (survey after alignment), mm and rad per
        axis; None: the bench's ``[magnet] survey_std_um`` / ``survey_std_urad``, else
        :data:`SURVEY_STD_DEFAULT` (:func:`registration_prior`).
    gain_std_pct : float
        Prior std of each Hall element's gain (S_HP of Table I), percent.
    smooth : bool
        False for a map read between its nodes from differences of its node values (linear,
        or corrected by its curvature): its field is expanded about the readings, never
        evaluated at moved points.
    h : float, mm, optional
        Step of the finite-difference gradient; None: :data:`STEP_SMOOTH_MM` for a smooth
        reference (a difference quotient over a shorter step is closer to the derivative: on
        the axis of an octupole, where the gradient vanishes, a 0.5 mm step reads
        B(0.5 mm) / 0.5 mm), :data:`STEP_MAP_MM` for a map read linearly (differences over its
        nodes 0.5 mm either side of a reading read node values).
    ref_spacing_mm : float, optional
        Node spacing of a reference map. Read linearly (``smooth`` False), its interpolation
        error is estimated (:func:`~cfm_fem.workflows.diagnose.noise.reference_error_var`) and
        added to the noise. Either way, when every reading lies on a node, the curvature of the
        field there (``ctx.node_step``) is taken from second differences of node values.
    ref_nodes : ndarray, shape (k, 3), mm, optional
        Nodes of that map: the error vanishes at a node and grows to its full size half a
        spacing away, so it is scaled by the distance to the nearest node.
    pose : ndarray, shape (6,), optional
        Registration (um, urad; order of :data:`REG_NAMES`) the model is linearised at;
        None: the nominal placement.
    ref_error : callable, optional
        ``ref_error(points (m, 3) mm) -> variance (m, 3) T^2`` of a reference map's own error
        between its nodes, added to the noise in place of the linear estimate: a map read by
        its harmonic fits (``smooth``,
        :meth:`~cfm_fem.workflows.diagnose.reference.NodeExactHarmonic.error_var`) or by the
        curvature-corrected reading (not ``smooth``,
        :meth:`~cfm_fem.workflows.diagnose.reference.CurvatureCorrected.error_var`).
    bench_at : ndarray, shape (21,), optional
        The bench errors (um, urad; order of ``ERROR_NAMES``) the readings are expanded at
        (:func:`bench_expansion`); None: their prior means.
    hessian : tuple of ndarray, optional
        The reference's Hessian (m, 3, 3, 3) T/mm^2 and third derivatives (m, 3, 3, 3, 3)
        T/mm^3 at the distinct points, nominal placement (:func:`field_derivatives`;
        computed once, then passed on by ``ctx.rebuild``).
    planar : bool, optional
        The reference is a 2-D field (:func:`_is_planar`: 2-D harmonics); None: decided from
        the field at the nominal placement (then passed on by ``ctx.rebuild``). Against a 2-D
        field the readings are taken exactly with the magnet at ``pose`` and the probe where
        the bench errors ``bench_at`` move it (the field is analytic). The registration's
        columns are linearised there too, with the magnet offset and rolled only: the
        offsets' second-order terms (a sextupole's g (dx^2 - dy^2), a constant) carry much of
        what the data say about the offsets, and depend on the magnet's offset less the
        bench's. The bench's columns see the probe's moves through that same gradient (else
        a registration column less a bench offset's would leave the field's curvature times
        the move, the signature of volume averaging). The gains, ``ctx.B0``, ``ctx.G`` and
        ``ctx.field_fn`` stay those of the nominal placement: the pose's rotations about x
        and y give the 2-D field a B_z and a variation along z, which in the columns would
        reproduce a tilted Hall element, and which the soft ends' model
        (``fringe_field_3d``, built on ``ctx``) does not expect of a 2-D field.
    elements_at : ndarray, shape (3, 3), um, optional
        The Hall elements' offsets from their centroid the problem is linearised at (row i:
        element x, y, z; the rows sum to zero; :mod:`~cfm_fem.workflows.diagnose.elements`):
        each element's component of the field, the gradient and the Hessian (``ctx.B0``,
        ``ctx.G``, ``ctx.B_read``, every column) is taken at its own point, and the residual
        carries the offsets' linear term, so that ``sensor_offset`` fits the whole offsets.
        None: the elements at the probe's point.
    ref_share : ndarray, shape (3,), optional
        Share of ``ref_error``'s variance per component given to the smooth term of a map read
        by its harmonic fits (:func:`~cfm_fem.workflows.diagnose.register.share_reference_error`);
        None: the stated error in full.
    ref_bound : callable, optional
        ``ref_bound(points (m, 3) mm) -> variance (m, 3) T^2``: a bound on the reference's
        error per point, above ``ref_error`` (:meth:`.reference.NodeExactHarmonic.error_bound`),
        for naming points and planes; None: ``ref_error``.
    """
    if h is None:
        h = STEP_SMOOTH_MM if smooth else STEP_MAP_MM
    ids, point = np.unique(rec.point_id, return_inverse=True)
    point = point.reshape(-1)
    p = rec.cmd
    upts, uinv = np.unique(np.round(p, 9), axis=0, return_inverse=True)
    uinv = uinv.reshape(-1)
    pose = np.zeros(len(REG_NAMES)) if pose is None else np.asarray(pose, dtype=float)
    rebuild = partial(hall_problem, rec, field_fn, b_ref, bench, reg_std_mm=reg_std_mm,
                      reg_std_rad=reg_std_rad, gain_std_pct=gain_std_pct, smooth=smooth, h=h,
                      ref_spacing_mm=ref_spacing_mm, ref_nodes=ref_nodes,
                      ref_error=ref_error, bench_at=bench_at,
                      elements_at=elements_at, ref_share=ref_share,
                      ref_bound=ref_bound)  # fmt: skip
    D = element_offsets(elements_at)
    prior = registration_prior(bench, reg_std_mm, reg_std_rad)
    reg_std_mm, reg_std_rad = prior["translation_mm"], prior["rotation_rad"]
    if planar is None:  # decided once, at the first linearisation
        planar = smooth and ref_nodes is None and _is_planar(field_fn, upts, h)
    rebuild = partial(rebuild, planar=planar)
    notes = [f"Hall residual = measured - reference field; B_ref = {b_ref:.6g} T"]
    q, bench = _axis_positions(bench, p, notes)
    at = None
    if bench is not None:
        at = bench_columns(bench, q).prior_mean if bench_at is None else np.asarray(bench_at)
    moved = bench is not None and np.any(at)
    if hessian is None and not planar and (moved or (not smooth and np.any(pose))):
        # the second and third derivatives at the nominal placement, once: a move of the
        # magnet by s changes the Hessian by T s (to first order, exact for an octupole's
        # body), so every relinearisation of this map reuses them
        h2 = max(STEP_MAP_MM, h if ref_spacing_mm is None else max(h, ref_spacing_mm))
        hessian = field_derivatives(field_fn, upts, h2)
    if hessian is not None:
        rebuild = partial(rebuild, hessian=hessian)
    at_pose = partial(
        _field_at_pose, field_fn, upts, np.zeros_like(pose) if planar else pose, h, smooth,
        ref_spacing_mm, derivs=None if planar else hessian,
    )  # fmt: skip
    B0u, Gu, fn_posed, Hu = at_pose()
    if D is not None:  # each element's component where the element sits
        B0u, Gu, Hu = at_elements(lambda s: _without_fn(at_pose(shift=s)), D, (B0u, Gu, Hu))
    B0, G = B0u[uinv], Gu[uinv]
    B_reg, G_reg, B_pose = B0, G, B0
    if planar:
        planar_at = partial(_planar_at_pose, field_fn, p, pose, h, bench, q, at)
        B_reg, G_reg, B_pose = planar_at()
        if D is not None:
            B_reg, G_reg, B_pose = at_elements(lambda s: planar_at(shift=s), D,
                                               (B_reg, G_reg, B_pose))  # fmt: skip
    B_read = B_pose  # the field the probe senses: where the bench moves it, below
    H = T = G_move = None
    if bench is not None:
        if Hu is not None:
            H, T = Hu[uinv], hessian[1][uinv]
        # the gradient where the errors ``at`` put the probe: the Jacobian of the readings
        # in the registration and the bench errors, and the vibration's lever
        G_move = moved_gradient(bench, q, at, G_reg, H, T)
    lever_pt = p - pose[:3] * UM  # from the magnet origin
    notes += check_hall_scale(rec.B, B0, source=rec.source)
    y = rec.B - B_pose
    if D is not None:  # the offsets' linear term: ``sensor_offset`` fits the whole offsets
        y = y + linear_term(G, D)
    blocks = []
    var_known = np.zeros_like(y)
    lever = axis_var = None  # the vibration's lever (n, 3, 3) and variance per axis (3,)
    disp = None
    if bench is not None:
        R = bench.bench_to_magnet_rotation()
        # a 2-D field is read where the errors put the probe already
        Bb = B0 if planar else bench_expansion(bench, q, p, at, B0, G, H, T)
        B_read = B_pose if planar else Bb
        lever = np.einsum("nij,jk->nik", G_move, R)  # dB per bench-frame probe displacement
        bcols = bench_columns(bench, q, lever_to=lever)
        blocks.append(bcols)
        # expanded at the errors ``at``: B(p + d(at)) + G(p + d(at)) D (theta - at)
        y = y - (Bb - B0) + np.einsum("nkp,p->nk", bcols.J, at)
        # probe displacement (magnet frame, mm per display unit) of each bench error
        disp = np.einsum("ij,njp->nip", R, bench_columns(bench, q).J)
        axis_var = bench.noise_std_mm() ** 2
        var_known = np.einsum("nik,k->ni", lever**2, axis_var)
    # a gain scales the field the element senses, where the bench moves the probe: on a
    # multipole that field departs from the nominal one by G d, and a gain of 0.1 % times
    # a move of tens of um is above a Hall probe's noise
    reg_gain = _registration_and_gains(
        B_reg, G_reg if G_move is None else G_move, lever_pt, reg_std_mm, reg_std_rad,
        gain_std_pct, B_gain=B_read
    )  # fmt: skip
    y = y + np.einsum("nkp,p->nk", reg_gain[0].J, pose)
    blocks += reg_gain
    notes.append(_prior_note(prior))
    notes.append(f"Hall gain prior {gain_std_pct:g} % (Table I S_HP); offsets assumed zeroed")
    var_ref, bound, ref_cell, ref_blocks, ref_note = reference_error_terms(
        field_fn, upts, uinv, b_ref, ref_error=ref_error, ref_bound=ref_bound,
        ref_share=ref_share, ref_nodes=ref_nodes, ref_spacing_mm=ref_spacing_mm, smooth=smooth,
    )  # fmt: skip
    blocks += ref_blocks
    notes += ref_note
    t_h, d, speed, temp = _aux(rec)
    ctx = ProblemContext(
        node_step=_node_step(upts, ref_spacing_mm, ref_nodes),
        reference_3d=ref_nodes is not None and bool(np.ptp(np.asarray(ref_nodes)[:, 2]) > 0),
        reference_fn=field_fn,
        B0=B0,
        B_read=B_read,
        G=G,
        field_fn=fn_posed,
        b_ref=b_ref,
        pose=pose,
        elements_at=None if D is None else np.asarray(elements_at, dtype=float),
        rows=np.arange(len(p)),
        registration_prior=prior,
        rebuild=rebuild,
        smooth=smooth,
        upts=upts,
        uinv=uinv,
        point_ids=ids,
        bench=bench,
        bench_disp=disp,
        lever=lever,
        axis_var=axis_var,
    )
    return Problem(
        kind="hall",
        y=y,
        pos=p,
        q=q,
        point=point,
        rep=rec.rep,
        t_h=t_h,
        dir=d,
        speed=speed,
        temp=temp,
        to_display=1e4 / b_ref,
        unit="units",
        var_known=var_known,
        baseline=blocks,
        ctx=ctx,
        notes=notes,
        vel=_velocities(rec, notes),
        var_ref=var_ref,
        ref_cell=None if var_ref is None else ref_cell / REF_LOCAL_SHARE,
        ref_bound=bound,
    )


def noise_sigma(
    prob: Problem, resid, edf: float = 0.0, var_known=None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-observation sigma from the noise model fitted to ``resid``
    (:func:`~cfm_fem.workflows.diagnose.noise.estimate_noise`: a floor per component plus the bench
    model's vibration, scaled by the data).

    ``var_known``: in place of ``prob.var_known`` (a model whose effects change the gradient
    the vibration is seen through, :attr:`Columns.var_known`).

    Returns
    -------
    sigma : ndarray, shape (n, 3)
    a : ndarray, shape (3,)
        The estimated floor (instrument noise variance) per component (y units^2).
    """
    from .noise import estimate_noise

    vk = prob.var_known if var_known is None else var_known
    model = estimate_noise(prob, resid, edf, vk)
    return model.sigma(vk, prob.var_ref), model.floor


def located_sigma(prob: Problem, sigma, resid, edf: float = 0.0, var_known=None) -> np.ndarray:
    """``sigma`` (n, 3) with the reference's stated error restored in full, for the tests that
    name single points and planes (:func:`~cfm_fem.workflows.diagnose.locate.locate`).

    The share of that error the noise carries
    (:func:`~cfm_fem.workflows.diagnose.noise.reference_share`) is one factor per component
    over all points, fitted to the point means of ``resid``; the stated error is a bound per
    point, and where the map's real error lies above its share at one point (a cell the map
    resolves worse than its neighbours' fits tell) that point would stand out of clean data.
    A point or plane is therefore named only beyond the bound the reference states per point
    (``prob.ref_bound``, else its stated error in full); effects are tested at the share."""
    if prob.var_ref is None:
        return sigma
    from .noise import estimate_noise

    vk = prob.var_known if var_known is None else var_known
    share = estimate_noise(prob, resid, edf, vk).ref_share
    bound = prob.var_ref if prob.ref_bound is None else prob.ref_bound
    return np.sqrt(sigma**2 + bound - share[None, :] * prob.var_ref)


def model_sigma(prob: Problem, model: Columns, var_known=None):
    """Per-observation sigma (n, 3) of the readings about ``model``, its noise fitted to the
    model's own residuals.

    The floor and the vibration scale come from the within-point scatter (or the scan lines'
    second differences) and hardly depend on the fit; the share of a reference's stated error
    (:func:`~cfm_fem.workflows.diagnose.noise.reference_share`) comes from the point means,
    which an unweighted fit leaves full of the components read least precisely (a multipole's
    transverse components, hundreds of uT of vibration, pull the fit off a B_z read to 1 uT).
    With a stated reference error the noise is therefore fitted again to the residuals of the
    fit weighted by the first estimate."""
    from .calibrate import fit_map

    fit = fit_map(prob.y, np.ones_like(prob.y), model)
    sigma = noise_sigma(prob, fit.resid, fit.edf, var_known)[0]
    if prob.var_ref is not None:
        fit = fit_map(prob.y, sigma, model)
        sigma = noise_sigma(prob, fit.resid, fit.edf, var_known)[0]
    return sigma


__all__ += [
    "ProblemContext",
    "located_sigma",
    "model_sigma",
    "noise_sigma",
    "bench_columns",
    "bench_move",
    "field_hessian_diag",
    "field_hessian",
    "field_third",
    "field_derivatives",
    "AXES",
    "REG_NAMES",
    "posed_field",
    "registration_prior",
    "SURVEY_STD_DEFAULT",
    "TRACKER_REG_STD_DEFAULT",
]
