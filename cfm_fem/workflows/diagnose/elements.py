"""Hall elements read where they sit: the problem linearised at the elements' offsets.

``sensor_offset`` models the three Hall elements displaced from their centroid: element i
reads B_i at p + d_i, not at the probe's point p. Its columns are the field's gradient times
the offsets, exact while the field is linear over the displacement. Where the offsets are
large against the field's curvature they are not: in an octupole read on four lines at the
corners of a square 5.7 mm wide, where dB_x/dy vanishes, an element 0.94 mm off changes B_x
by the field's curvature alone, 98 % off its gradient times its offset (rms over the B_x
readings, family case 82128); the second-order change of one element in a quadratic field
has the shape of a sensitive volume's averaging.

The problem is therefore linearised at the offsets the fit finds (Gauss-Newton, as the
magnet's pose: :mod:`~cfm_fem.workflows.diagnose.register`): each element's component of
the reference, its gradient and its Hessian are taken at the element's own point
(:func:`at_elements`), every column (the effect's, the registration's, the bench's) is formed
there, and the residual carries the offsets' linear term (:func:`linear_term`), so that the
fitted offsets are the elements' whole offsets, not an increment. The offsets are moved to
their estimate until every step is below ``STEP_TOL`` of its std
(:func:`element_target`); the reported uncertainties are those of the final linearisation.

The elements' common shift is not part of the linearisation point: it moves the readings as
the magnet's offset does, and once the effect is accepted the magnet's offsets are free and
the relinearised pose carries it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ELEMENTS", "ELEMENT_SHARE", "element_map", "at_elements", "element_offsets",
           "element_target", "linear_term", "curvature_chi2", "holds_offsets",
           "elements_note"]  # fmt: skip

#: The Hall elements, by the field component each reads.
ELEMENTS = "xyz"
#: Converged when every offset's step is below this fraction of its std (as the pose).
STEP_TOL = 0.05
#: Display unit of the offsets, mm per um.
UM = 1e-3
#: Offsets from the elements' centroid (x, y, z elements) per unit displacement of element i
#: from the other two, row i.
ELEMENT_SHARE = np.eye(3) - 1.0 / 3.0


def element_map(names, direction: str) -> np.ndarray:
    """The matrix (3, len(names)) from the fitted element displacements ``e_<i>_<direction>``
    among ``names`` to the three elements' offsets from their centroid along ``direction``
    (zero columns for the other names)."""
    A = np.zeros((3, len(names)))
    for k, nm in enumerate(names):
        if nm.startswith("e_") and nm.endswith(f"_{direction}"):
            A[:, k] = ELEMENT_SHARE["xyz".index(nm[2])]
    return A


def element_offsets(elements_at) -> np.ndarray | None:
    """The elements' offsets (3, 3) mm from their centroid, or None when all are zero.

    Parameters
    ----------
    elements_at : array_like, shape (3, 3), um, or None
        Row i: the offset of element i (x, y, z) along x, y, z from the elements' centroid
        (the rows sum to zero).
    """
    if elements_at is None:
        return None
    D = np.asarray(elements_at, dtype=float).reshape(3, 3) * UM
    return D if np.any(D) else None


def at_elements(evaluate, D, nominal) -> tuple:
    """Per-reading field quantities with each element's component taken at its own point.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(shift (3,) mm) -> tuple`` of arrays whose axis 1 is the field component
        (field (k, 3) T, gradient (k, 3, 3) T/mm, Hessian (k, 3, 3, 3) T/mm^2, ...; None for
        one not available), every point moved by ``shift``.
    D : ndarray, shape (3, 3), mm
        The elements' offsets (:func:`element_offsets`).
    nominal : tuple
        The same quantities at the points themselves (``evaluate`` of a zero shift).

    Returns
    -------
    tuple
        ``nominal`` with component i of every quantity replaced by its value at the points
        moved by element i's offset ``D[i]``.
    """
    out = [None if a is None else np.array(a, dtype=float) for a in nominal]
    seen = {}
    for i in range(3):
        if not np.any(D[i]):
            continue
        key = tuple(D[i])
        if key not in seen:  # elements displaced alike share one evaluation
            seen[key] = evaluate(D[i])
        for k, a in enumerate(seen[key]):
            if out[k] is not None and a is not None:
                out[k][:, i] = a[:, i]
    return tuple(out)


def linear_term(G, D) -> np.ndarray:
    """The offsets' linear term of the readings, sum_j dB_i/dx_j D_ij (n, 3) T.

    Added to the residual of a problem linearised at the offsets ``D`` (3, 3) mm, with ``G``
    (n, 3, 3) T/mm the gradient each element's columns are formed from: the effect's columns
    then fit the whole offsets."""
    return np.einsum("nij,ij->ni", G, D)


def element_target(prob, model, fit, directions=None) -> tuple[np.ndarray | None, bool]:
    """The offsets a fit puts the elements at, and whether they moved beyond the tolerance.

    Parameters
    ----------
    prob : Problem
        A Hall-map problem linearised at the offsets ``prob.ctx.elements_at``.
    model : Columns
        The model fitted (the elements' displacements named ``e_<element>_<direction>``:
        element i's from the elements not fitted along that direction).
    fit : Fit
    directions : array_like of bool, shape (3,), optional
        The directions to linearise at (default all): zero along the others.

    Returns
    -------
    elements_at : ndarray, shape (3, 3), um, or None
        The elements' offsets from their centroid; zero along a direction the model does not
        fit; None where the problem is not relinearised: no rebuild, or a map read linearly
        between its nodes (its curvature is known no better than its interpolation error, as
        for the magnet's pose).
    moved : bool
        Some offset moved by more than ``STEP_TOL`` times its std, or a direction the
        problem is linearised at is no longer fitted.
    """
    if prob.kind != "hall" or prob.ctx.rebuild is None:
        return None, False
    if not prob.ctx.smooth and prob.ctx.node_step is None:
        return None, False
    now = prob.ctx.elements_at
    now = np.zeros((3, 3)) if now is None else np.asarray(now, dtype=float)
    new = np.zeros((3, 3))
    moved = False
    use = np.ones(3, dtype=bool) if directions is None else np.asarray(directions, dtype=bool)
    for j, a in enumerate(ELEMENTS):
        # a direction the model does not fit (or not linearised along) is held at zero, as
        # in the fit
        A = element_map(model.names, a) if use[j] else np.zeros((3, model.p))
        if not A.any():
            moved |= bool(np.any(now[:, j]))
            continue
        new[:, j] = A @ fit.theta
        std = np.sqrt(np.clip(np.einsum("ik,kl,il->i", A, fit.cov, A), 0.0, None))
        moved |= bool(np.any(np.abs(new[:, j] - now[:, j]) > STEP_TOL * np.maximum(std, 1e-12)))
    return new, moved


def curvature_chi2(prob, at, sigma) -> float | None:
    """How far the readings depart from the offsets' linear term over a step of the offsets:
    sum over the readings of ((B_i(p + a_i) - B_i(p + c_i) - dB_i/dx (a_i - c_i)) / sigma)^2,
    ``c`` the offsets ``prob`` is linearised at, ``a`` the offsets ``at`` (3, 3) um, the field
    and its gradient those of the reference with the magnet at the problem's pose.

    Below ``STEP_TOL**2`` the field is linear over the step: the departure moves no offset's
    estimate by more than ``STEP_TOL`` of its std (a misfit's projection on the offsets'
    columns is at most its norm in units of the noise), and the gradient's change over the
    step (the Hessian times the step: twice the departure over the step, for a quadratic
    field) changes the offsets' signature by as little, so the linear fit holds.

    Parameters
    ----------
    prob : Problem
        A Hall-map problem read from a smooth reference (``ctx.field_fn``).
    at : ndarray, shape (3, 3), um
    sigma : ndarray, shape (n, 3)
        The noise of the readings (T).

    Returns
    -------
    float, or None for a reference read linearly from its nodes (no field between them).
    """
    ctx = prob.ctx
    if not ctx.smooth or ctx.field_fn is None or ctx.upts is None:
        return None
    now = np.zeros((3, 3)) if ctx.elements_at is None else np.asarray(ctx.elements_at)
    step = (np.asarray(at, dtype=float) - now) * UM
    m = np.zeros((len(ctx.upts), 3))
    for i in range(3):
        if not np.any(step[i]):
            continue
        c = ctx.upts + now[i] * UM
        m[:, i] = ctx.field_fn(c + step[i])[:, i] - ctx.field_fn(c)[:, i]
    G = np.zeros((len(ctx.upts), 3, 3))
    G[ctx.uinv] = ctx.G  # rows of one point share its gradient
    m -= np.einsum("mij,ij->mi", G, step)
    return float(np.nansum((m[ctx.uinv] / sigma) ** 2))


def holds_offsets(prob, model) -> bool:
    """Whether ``model`` fits some element along every direction ``prob`` is linearised at
    (along which the elements' offsets are non-zero): else the residual carries a linear term
    of the offsets that no column gives back. Where the elements sit along a fitted direction
    is the iteration's concern (:func:`element_target`)."""
    now = prob.ctx.elements_at if prob.kind == "hall" else None
    if now is None:
        return True
    return all(
        any(f"e_{e}_{a}" in model.names for e in ELEMENTS)
        for j, a in enumerate(ELEMENTS)
        if np.any(np.asarray(now)[:, j])
    )


def elements_note(prob) -> str | None:
    """What the relinearisation at the elements' offsets did, for the notes of the diagnosis."""
    D = prob.ctx.elements_at if prob.kind == "hall" else None
    if D is None or not np.any(D):
        return None
    at = ", ".join(
        f"d_{e}_{a} {D[i][j]:.4g}"
        for i, e in enumerate(ELEMENTS)
        for j, a in enumerate(ELEMENTS)
        if D[i][j]
    )
    return (
        "Hall elements read where they sit: reference field, gradient and Hessian of each "
        f"element's component taken at its fitted offset ({at}; um from the elements' "
        f"centroid), iterated until each step is below {STEP_TOL:g} of its std"
    )
