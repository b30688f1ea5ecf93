"""Non-linear magnet registration of a Hall map: Gauss-Newton on the magnet's pose.

The magnet's offset and rotation enter the field non-linearly: through a fringe a few mm long,
a 0.3 mm shift leaves second-order terms far above a Hall probe's noise, which a linearisation
at the nominal placement cannot absorb and other signatures would then take. The problem is
linearised at a pose (:func:`~cfm_fem.workflows.diagnose.problem.hall_problem`: reference field
and gradient re-evaluated with the magnet moved there) and the pose is moved to the fitted
registration until the step is far below its standard uncertainty. The reported uncertainties
are those of the final linearisation.

The bench's errors move the probe by tens of um on a long lever; a Hall map's readings are
first expanded to third order in that move at the errors the calibrated baseline fits
(Gauss-Newton from their prior means,
:func:`~cfm_fem.workflows.diagnose.problem.bench_expansion`), each step kept when it lowers the
MAP objective.

The Hall elements' offsets (``sensor_offset``) enter the readings non-linearly too: an
element read a millimetre from the probe's point, where the field curves over that distance,
changes its reading by more than the gradient times its offset. Once the effect is found, the
problem is linearised at the offsets the selected model fits (:func:`relinearise_elements`:
Gauss-Newton with that model, each element's field and gradient taken at its own point,
:mod:`~cfm_fem.workflows.diagnose.elements`), and the attribution is done again there.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np

from ...models.bench import ERROR_NAMES
from .calibrate import Columns, fit_map, stack
from .effects import sensor_offset
from .elements import STEP_TOL as ELEMENT_TOL
from .elements import curvature_chi2, element_target
from .problem import REG_NAMES, Problem, model_sigma, subset_rows
from .reference_rows import REF_GROUP

__all__ = [
    "applies",
    "register",
    "repose",
    "share_reference_error",
    "pose_step",
    "bench_step",
    "bench_target",
    "registration_note",
    "relinearise_elements",
]

#: Converged when every registration step is below this fraction of its std.
STEP_TOL = 0.05


def applies(prob: Problem) -> bool:
    """Whether the registration of ``prob`` is made non-linear: a Hall map against a 3-D
    reference map (smooth, or interpolated linearly with the readings on its nodes), against
    2-D harmonics while the problem is at the nominal placement (read exactly at the pose:
    :func:`~cfm_fem.workflows.diagnose.problem.hall_problem`, ``planar``; the baseline
    places the magnet once, the selected model does not move it again), or against any
    reference that varies along z at the readings.

    A 3-D map holds the magnet's ends where its nodes reach them, so a pose fitted against it
    has nothing to steer it but the data; and in a magnet's body the pose's second-order terms
    are still there: a rotation about x or y of a few tens of urad turns a transverse field
    shifted by a magnet offset of tens of um into a Bz offset of tenths of a uT, above a
    low-noise probe's floor over a few hundred readings. Against 2-D harmonics the offsets
    of a sextupole or higher leave g (dx^2 - dy^2), a constant field, which a linear pose
    leaves to a Hall offset. Between the nodes of a linear map its curvature is not known
    better than its own interpolation error (added to the noise), which is of the order of
    the second-order terms of a move of up to a node spacing."""
    if prob.kind != "hall" or prob.ctx.rebuild is None:
        return False
    if not prob.ctx.smooth and prob.ctx.node_step is None:
        return False
    if getattr(prob.ctx.rebuild, "keywords", {}).get("planar"):
        return not np.any(prob.ctx.pose)  # placed once, by the baseline (:func:`register`)
    if prob.ctx.reference_3d:
        return True
    G = prob.ctx.G
    return bool(np.abs(G[:, :, 2]).max() > 1e-3 * max(np.abs(G[:, :, :2]).max(), 1e-300))


def _objective(prob: Problem):
    """MAP objective and fit of the calibrated baseline (noise from its own residuals)."""
    base = stack(prob.baseline)
    sigma = model_sigma(prob, base)
    fit = fit_map(prob.y, sigma, base)
    return fit.objective, base, fit


def repose(prob: Problem, pose, **kw) -> Problem:
    """The same problem (same rows) linearised at the registration ``pose`` (um, urad);
    ``kw``: other arguments of the rebuild (``bench_at``)."""
    full = prob.ctx.rebuild(pose=np.asarray(pose, dtype=float), **kw)
    full.notes = list(prob.notes)  # with what the caller added
    rows = prob.ctx.rows
    if len(rows) == full.n:
        return full
    keep = np.zeros(full.n, dtype=bool)
    keep[rows] = True
    return subset_rows(full, keep)


def pose_step(prob: Problem, model, fit) -> tuple[np.ndarray, bool]:
    """The registration a fit puts the magnet at, and whether it moved beyond the tolerance.

    Parameters
    ----------
    prob : Problem
        A Hall-map problem linearised at ``prob.ctx.pose``.
    model : Columns
        The model fitted (its registration columns named as :data:`REG_NAMES`).
    fit : Fit

    Returns
    -------
    pose : ndarray, shape (6,), um and urad
    moved : bool
        Some step exceeds ``STEP_TOL`` times its std.
    """
    pose = np.array(prob.ctx.pose, dtype=float)
    new = pose.copy()
    moved = False
    for k, nm in enumerate(REG_NAMES):
        if nm in model.names:
            i = model.names.index(nm)
            new[k] = fit.theta[i]
            moved |= bool(abs(fit.theta[i] - pose[k]) > STEP_TOL * max(fit.std[i], 1e-12))
    return new, moved


def bench_target(prob: Problem, model, fit) -> tuple[np.ndarray | None, bool]:
    """The bench errors a fit puts the probe at, and whether they moved beyond the tolerance.

    Parameters
    ----------
    prob : Problem
        A Hall-map problem expanded at the bench errors of its ``ctx.rebuild`` (``bench_at``;
        None: their prior means).
    model : Columns
        The model fitted (its bench columns named as ``ERROR_NAMES``).
    fit : Fit

    Returns
    -------
    at : ndarray, shape (21,), display units of the bench errors, or None
        None where the problem has no bench to expand at.
    moved : bool
        Some error moved by more than ``STEP_TOL`` times its std.
    """
    if prob.ctx.rebuild is None or prob.ctx.bench is None:
        return None, False
    if not set(ERROR_NAMES) <= set(model.names):
        return None, False
    idx = [model.names.index(n) for n in ERROR_NAMES]
    at = np.asarray(fit.theta[idx], dtype=float)
    now = _bench_now(prob, model)
    std = np.maximum(np.asarray(fit.std[idx], dtype=float), 1e-12)
    return at, bool(np.any(np.abs(at - np.asarray(now, dtype=float)) > STEP_TOL * std))


def _bench_now(prob: Problem, model) -> np.ndarray:
    """The bench errors ``prob`` is expanded at (their prior means unless stated)."""
    now = getattr(prob.ctx.rebuild, "keywords", {}).get("bench_at")
    if now is None:
        now = [model.prior_mean[model.names.index(n)] for n in ERROR_NAMES]
    return np.asarray(now, dtype=float)


def share_reference_error(prob: Problem) -> Problem:
    """The problem with its reference's smooth error term scaled to the share the readings
    show (:func:`~cfm_fem.workflows.diagnose.noise.reference_share`).

    A map read by its harmonic fits states one error per point, from the map alone; it enters
    twice, as noise local to each cell and as a smooth term across the scan
    (:func:`~cfm_fem.workflows.diagnose.reference_rows.smooth_columns`). Both are the same
    error: where the point means of the baseline's residuals show only a share f_c of it in a
    component (a multipole's B_z, read to 1 uT where the map's coarse cells state tens), the
    smooth term keeps f_c of its variance too, so that it no longer takes whatever smooth
    signal that component carries. f_c is the one-sided 95 % upper bound the baseline's
    residuals allow, never above 1; a problem without such a term is returned as it is."""
    rebuild = prob.ctx.rebuild
    keywords = getattr(rebuild, "keywords", {})
    if prob.var_ref is None or rebuild is None or keywords.get("ref_share") is not None:
        return prob
    if not any(b.group == REF_GROUP for b in prob.baseline):
        return prob
    from .noise import estimate_noise

    base = stack(prob.baseline)
    sigma = model_sigma(prob, base)
    fit = fit_map(prob.y, sigma, base)
    share = estimate_noise(prob, fit.resid, fit.edf).ref_share
    if np.all(share >= 1.0):
        return prob
    return repose(prob, prob.ctx.pose, ref_share=share)


def register(prob: Problem, max_iter: int = 6) -> Problem:
    """Gauss-Newton on the magnet's pose and the bench errors the readings are expanded at,
    with the calibrated baseline (registration priors kept): the problem linearised at the
    registration and the bench errors it fits.

    A Hall map's readings are first expanded at the bench errors the baseline fits
    (:func:`bench_step`). The pose and those errors then step together: a pose fitted at
    bench errors fitted at another pose leaves their product terms (on a sextupole's or an
    octupole's axis, where the gradient vanishes, the field is all second- and third-order
    terms of the probe's move and the readings' noise is the probe's floor alone). A step
    that raises the MAP objective is halved (three times at most, then the pose alone steps,
    likewise; else they stay). A problem :func:`applies` rejects keeps its pose.
    """
    prob = bench_step(prob)
    if not applies(prob):
        return prob
    nominal = prob
    obj, base, fit = _objective(prob)
    for _ in range(max_iter):
        pose, moved = pose_step(prob, base, fit)
        at, at_moved = bench_target(prob, base, fit)
        at_moved = at_moved and not _bench_steered(prob, base, at)
        if not (moved or at_moved):
            break
        step = _step(prob, obj, pose, (at, _bench_now(prob, base)) if at_moved else None)
        if step is None and at_moved and moved:
            step = _step(prob, obj, pose, None)  # the pose alone
        if step is None:
            break
        prob, obj, base, fit = step
    return repose(nominal, np.zeros(len(REG_NAMES)), planar=False) if _steered(prob) else prob


def _step(prob: Problem, obj: float, pose, bench=None, objective=None):
    """The problem relinearised at ``pose`` (and, ``bench = (at, now)``, at the bench errors
    ``at`` instead of ``now``) with its objective and fit, the step halved while it raises
    the MAP objective; None if it still does after three halvings. ``objective``: (objective,
    model, fit) of a problem, default the calibrated baseline's (:func:`_objective`)."""
    objective = _objective if objective is None else objective
    start = np.asarray(prob.ctx.pose, dtype=float)
    at, at0 = (None, None) if bench is None else bench
    for _half in range(4):
        trial = repose(prob, pose) if at is None else repose(prob, pose, bench_at=at)
        obj_t, base_t, fit_t = objective(trial)
        if obj_t <= obj * (1.0 + 1e-9):
            return trial, obj_t, base_t, fit_t
        pose = 0.5 * (start + pose)
        if at is not None:
            at = 0.5 * (at0 + at)
    return None


#: Against a 2-D reference, a baseline pose beyond this many survey stds is steered by what
#: the reference lacks (the magnet's ends), not the magnet's placement.
STEERED_STD = 4.0


def _steered(prob: Problem) -> bool:
    """Whether the pose the baseline fits against a 2-D reference is beyond
    :data:`STEERED_STD` survey stds in some parameter: a map through the magnet's ends, which
    a 2-D field lacks, pulls the baseline's pose by hundreds of urad; relinearised there, the
    2-D field is read where the magnet is not: it is then read linearly at the nominal
    placement."""
    if not getattr(prob.ctx.rebuild, "keywords", {}).get("planar"):
        return False
    reg = next(b for b in prob.baseline if b.group == "registration")
    return bool(np.any(np.abs(np.asarray(prob.ctx.pose)) > STEERED_STD * reg.prior_std))


def _bench_steered(prob: Problem, model, at) -> bool:
    """Whether bench errors ``at`` (display units, in :data:`ERROR_NAMES` order) that a fit
    against a 2-D reference puts the probe at lie beyond :data:`STEERED_STD` prior stds of
    some error: a map through the magnet's ends, which a 2-D field lacks, pulls the linear
    baseline's bench errors by hundreds of their stds (tens of mrad of angular error) to
    take the field's fall-off. Expanded there, the readings would be read where no bench
    put the probe, and the soft-end model tested from that point: the expansion stays at
    the errors the problem holds."""
    if at is None or not getattr(prob.ctx.rebuild, "keywords", {}).get("planar"):
        return False
    idx = [model.names.index(n) for n in ERROR_NAMES]
    mean, std = model.prior_mean[idx], model.prior_std[idx]
    beyond = np.abs(np.asarray(at, dtype=float) - mean) > STEERED_STD * std
    return bool(np.any(beyond & np.isfinite(std)))


def bench_step(prob: Problem, max_iter: int = 3) -> Problem:
    """A Hall map's problem expanded at the bench errors the calibrated baseline fits
    (Gauss-Newton, while each step lowers the MAP objective, until the steps are below
    ``STEP_TOL`` of their std); else ``prob`` itself."""
    if prob.kind != "hall" or prob.ctx.rebuild is None or prob.ctx.bench is None:
        return prob
    obj, base, fit = _objective(prob)
    if not set(ERROR_NAMES) <= set(base.names):
        return prob
    for _ in range(max_iter):
        at = np.array([fit.theta[base.names.index(n)] for n in ERROR_NAMES])
        if _bench_steered(prob, base, at):
            break
        trial = repose(prob, prob.ctx.pose, bench_at=at)
        obj_t, base_t, fit_t = _objective(trial)
        if obj_t > obj * (1.0 + 1e-9):
            break
        step = np.array([fit_t.theta[base_t.names.index(n)] for n in ERROR_NAMES]) - at
        std = np.array([fit_t.std[base_t.names.index(n)] for n in ERROR_NAMES])
        prob, obj, base, fit = trial, obj_t, base_t, fit_t
        if np.all(np.abs(step) <= STEP_TOL * np.maximum(std, 1e-12)):
            break
    return prob


def refit_step(prob: Problem, model: Columns, fit, sigma, keep=(), checked=True):
    """``prob`` linearised at the pose and bench errors ``model`` fits there; ``prob`` itself
    when the model fits them where they are.

    ``checked``: the step is halved while the model's MAP objective rises (its baseline
    columns formed anew at each linearisation, the noise ``sigma`` held), and None is returned
    when it still rises after three halvings, as :func:`register` steps the baseline. A model
    with no effect selected is the baseline: a step :func:`register` refused would move the
    pose where the baseline fits worse (a pose whose second-order terms reach a low-noise
    component's floor), and the misfit left there would be attributed to an effect. A model
    with an effect is stepped unchecked: its linear optimum is the pose the effect's
    parameters are fitted at, and against a coarse map the objective barely tells two
    linearisations apart (the reading error moves with the pose) while the effect's
    parameters do. ``keep``: baseline columns an effect replaced."""
    pose, moved = pose_step(prob, model, fit)
    at, at_moved = bench_target(prob, model, fit)
    if not (moved or at_moved):
        return prob
    if not checked:
        return repose(prob, pose, bench_at=at) if at_moved else repose(prob, pose)
    held = partial(_objective_of, model=model, sigma=sigma, keep=keep)
    bench = (at, _bench_now(prob, model)) if at_moved else None
    step = _step(prob, held(prob)[0], pose, bench, objective=held)
    return None if step is None else step[0]


def registration_note(prob: Problem) -> str | None:
    """What the non-linear registration did, for the notes of the diagnosis."""
    pose = prob.ctx.pose if prob.kind == "hall" else None
    if pose is None or not np.any(pose):
        return None
    moved = ", ".join(f"{n} {v:.4g}" for n, v in zip(REG_NAMES, pose, strict=True))
    return (
        "registration non-linear: reference field and gradient re-evaluated with the magnet at "
        f"its fitted pose ({moved}; um, urad), iterated until each step is below "
        f"{STEP_TOL:g} of its std"
    )


#: The elements' displacements the model may fit (each element along each direction).
OFFSET_NAMES = frozenset(f"e_{e}_{a}" for e in "xyz" for a in "xyz")


def _model_at(prob: Problem, model: Columns, keep=()) -> Columns:
    """``model`` with its baseline columns and its elements' offsets formed at ``prob``'s
    linearisation (same names, priors and order); the other columns, and those named in
    ``keep`` (baseline columns an effect replaced), as they are."""
    fresh = stack(prob.baseline)
    blk = sensor_offset(prob)
    cols = dict(zip(fresh.names, np.moveaxis(fresh.J, -1, 0), strict=True))
    cols.update(zip(blk.names, np.moveaxis(blk.J, -1, 0), strict=True))
    J = model.J.copy()
    for k, nm in enumerate(model.names):
        if nm in cols and nm not in keep:
            J[..., k] = cols[nm]
    return replace(model, J=J)


def _objective_of(prob: Problem, model: Columns, sigma, keep=()):
    """MAP objective, model and fit of ``model`` formed at ``prob``'s linearisation, with the
    noise ``sigma`` (n, 3) held (the same weights at every linearisation)."""
    m = _model_at(prob, model, keep)
    fit = fit_map(prob.y, sigma, m)
    return fit.objective, m, fit


def _offsets_of(model: Columns, fit) -> tuple[np.ndarray, np.ndarray]:
    """Values and stds (um) of the elements' offsets a fit of ``model`` holds."""
    idx = [k for k, nm in enumerate(model.names) if nm in OFFSET_NAMES]
    return np.asarray(fit.theta[idx]), np.asarray(fit.std[idx])


def relinearise_elements(prob: Problem, model: Columns, fit, sigma, keep=(), max_iter: int = 8,
                         max_halvings: int = 6) -> Problem:  # fmt: skip
    """The problem linearised at the Hall elements' offsets ``model`` fits (Gauss-Newton).

    Each step moves the elements to the offsets the model fits at the current linearisation
    (:func:`~cfm_fem.workflows.diagnose.elements.element_target`), with the model's structure
    held: its columns of the baseline and of the offsets formed anew at each linearisation,
    the other effects' as they are. The magnet's pose stays: the attribution moves it
    (:func:`~cfm_fem.workflows.diagnose.workflow._attribute`), and a pose moved here would
    change the offsets where the field is linear over them. A step that raises the MAP
    objective is halved (``max_halvings`` times at most, then the iteration stops); the
    iteration stops once every offset's step is below ``STEP_TOL`` of its std.

    Where the field is linear over the offsets, the offsets and stds at the final
    linearisation are those of ``fit`` (within ``STEP_TOL`` of their std): ``prob`` itself is
    returned, so that the attribution need not be done again.

    Parameters
    ----------
    prob : Problem
        A Hall-map problem, linearised at ``prob.ctx.elements_at`` (None: zero offsets).
    model : Columns
        The selected model (the offsets' columns named ``e_<element>_<direction>``).
    fit : Fit
        Its fit at ``prob``.
    sigma : ndarray, shape (n, 3)
        The noise of that fit, held at every linearisation.
    keep : iterable of str
        Baseline columns an effect of the model replaced (``fringe_field_3d``): held as they
        are.

    Returns
    -------
    Problem
        ``prob`` itself, or the same rows linearised at the elements' offsets the model
        converges to (the pose unchanged).
    """
    target, moved = element_target(prob, model, fit)
    if target is None or not moved:
        return prob
    curved = _curved_directions(prob, target, sigma)
    if not curved.any():
        return prob  # the field is linear over the offsets: the linear fit holds
    theta0, std0 = _offsets_of(model, fit)
    obj, m, f = fit.objective, model, fit
    cur = prob
    for _ in range(max_iter):
        target, moved = element_target(cur, m, f, curved)
        if not moved:
            break
        step = _element_step(cur, obj, target, model, sigma, keep, max_halvings)
        if step is None:
            break
        cur, obj, m, f = step
    if cur is prob:
        return prob
    theta, std = _offsets_of(m, f)
    tol = ELEMENT_TOL * np.maximum(std0, 1e-12)
    if np.all(np.abs(theta - theta0) <= tol) and np.all(np.abs(std - std0) <= tol):
        return prob  # the linear fit holds: the field is linear over the offsets
    return cur


def _elements_at(prob: Problem) -> np.ndarray:
    """The elements' offsets (3, 3) um ``prob`` is linearised at (zero: at the probe's
    point)."""
    now = prob.ctx.elements_at
    return np.zeros((3, 3)) if now is None else np.asarray(now, dtype=float)


def _curved_directions(prob: Problem, target, sigma) -> np.ndarray:
    """The directions (3,) bool to linearise at: those ``prob`` is linearised along already,
    and those along which the field curves over the offsets ``target`` (3, 3) um, their
    departure from their linear term reaching ``STEP_TOL``
    (:func:`~cfm_fem.workflows.diagnose.elements.curvature_chi2`). Along the others the
    linear fit holds, and their offsets (which a later attribution may not fit again) stay
    out of the linearisation. All of them where the departure is not known (a map read from
    its nodes)."""
    now = _elements_at(prob)
    out = np.zeros(3, dtype=bool)
    for j in range(3):
        if np.any(now[:, j]):
            out[j] = True
            continue
        at = now.copy()
        at[:, j] = target[:, j]
        chi2 = curvature_chi2(prob, at, sigma)
        out[j] = chi2 is None or chi2 >= ELEMENT_TOL**2
    return out


def _element_step(prob: Problem, obj: float, at, model, sigma, keep, max_halvings: int):
    """The problem relinearised at the elements' offsets ``at`` (3, 3) um with its objective,
    model and fit, the step halved while it raises the MAP objective; None if it still does
    after ``max_halvings`` halvings."""
    at = np.asarray(at, dtype=float)
    at0 = _elements_at(prob)
    for _half in range(max_halvings + 1):
        trial = repose(prob, prob.ctx.pose, elements_at=at)
        obj_t, m_t, f_t = _objective_of(trial, model, sigma, keep)
        if obj_t <= obj * (1.0 + 1e-9):
            return trial, obj_t, m_t, f_t
        at = 0.5 * (at0 + at)
    return None
