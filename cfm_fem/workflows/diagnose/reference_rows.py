"""The reference's own error as the rows of a Hall map carry it.

A reference read between its nodes errs by an amount it states itself (the harmonic fits'
spread, a linear map's curvature, 2-D harmonics' truncation). That error is one value per
point, shared by every reading of it, and on a 3-D map by every point in one cell: the rows
carry it as noise weighted so that the point's mean counts it once; a map read by its harmonic
fits carries a smooth term across the scan beside it.
"""

from __future__ import annotations

import numpy as np

from .calibrate import Columns

__all__ = [
    "REF_GROUP",
    "REF_LOCAL_SHARE",
    "REF_SMOOTH_SHARE",
    "reference_error_terms",
    "shared_by",
]


def shared_by(uinv) -> np.ndarray:
    """Readings of the same point as each reading (n,): the factor on a per-point error's
    variance when it enters the rows as independent noise.

    The reference's error at a point is one value, the same in every repetition that reads
    it. Rows weighted as independent with variance v + c r (c readings of the point) give the
    point's mean the variance v / c + r it has, so the fit's evidence and the located point
    means count the reference's error once, not once per repetition; within-point departures
    (drifts, steps) are weighted conservatively.
    """
    return np.bincount(uinv)[uinv].astype(float)


#: Baseline group of the smooth term of a map's error (:func:`smooth_columns`).
REF_GROUP = "reference"

#: Share of a reference map's stated error variance carried by the reading's own noise (the
#: part local to its cell, times the readings that share the cell), and share carried by the
#: smooth term across the scan (:func:`smooth_columns`): the error is stated in
#: full in each.
REF_LOCAL_SHARE = 1.0
REF_SMOOTH_SHARE = 1.0


def smooth_columns(upts, var, uinv) -> Columns:
    """The smooth part of a reference map's error across the scan
    (:func:`~cfm_fem.workflows.diagnose.reference.smooth_error_basis`), a baseline block with
    unit-free coefficients and priors that give it :data:`REF_SMOOTH_SHARE` of the stated
    variance ``var`` (m, 3) T^2 at the distinct points ``upts`` (m, 3) mm.

    Only for a map read by its harmonic fits, whose error is their truncation (the field's
    higher derivatives, smooth over the magnet's scale). The curvature-corrected reading
    serves maps whose fits fail, mostly measured ones, whose node values carry their own noise:
    independent from node to node, part of its stated error, and not smooth across a scan."""
    from .reference import smooth_error_basis

    J, names, s = smooth_error_basis(upts, np.sqrt(REF_SMOOTH_SHARE * var))
    return Columns(J[uinv], names, ["sigma"] * len(names), np.zeros(len(names)), s, REF_GROUP)


def interpolation_error_var(field_fn, upts, spacing_mm, nodes):
    """Interpolation error variance of a linear reference map at the distinct points, T^2: zero
    at a node, its full size half a spacing away."""
    from .noise import reference_error_var

    var = reference_error_var(field_fn, upts, spacing_mm)
    if nodes is not None:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(nodes).query(upts)
        var *= np.clip(2.0 * d / spacing_mm, 0.0, 1.0)[:, None] ** 2
    return var


def reference_error_terms(field_fn, upts, uinv, b_ref, *, ref_error, ref_bound, ref_share,
                          ref_nodes, ref_spacing_mm, smooth):  # fmt: skip
    """The reference's own error as the rows of a Hall map carry it (keywords as
    :func:`~cfm_fem.workflows.diagnose.problem.hall_problem`'s; ``upts`` (m, 3) mm the
    distinct points, ``uinv`` (n,) each row's, ``b_ref`` (T) the field of the display unit).

    Returns
    -------
    var_ref : ndarray, shape (n, 3), T^2, or None
        Stated error variance per row, times the readings that share it (:func:`shared_by`).
    bound : ndarray, shape (n, 3), T^2, or None
        Bound on that error per row, as ``var_ref`` carries it.
    ref_cell : ndarray, shape (n,)
        Readings that share each row's error (its point's, or its cell's on a 3-D map).
    blocks : list of Columns
        The smooth term across the scan of a map read by its harmonic fits, else empty.
    notes : list of str
        What the noise carries, for the problem's notes.
    """
    ref_blocks, note = [], []
    var_ref = bound = None
    ref_cell = shared_by(uinv)
    if ref_error is not None:
        var_ref = np.asarray(ref_error(upts), dtype=float)
        bound = var_ref if ref_bound is None else np.maximum(ref_bound(upts), var_ref)
        if ref_nodes is not None:  # a 3-D map: one error per cell, however many points read it
            from .reference import shared_readings

            if smooth:  # the harmonic fits' truncation: smooth across the scan
                share = np.ones(3) if ref_share is None else np.asarray(ref_share, dtype=float)
                ref_blocks.append(smooth_columns(upts, var_ref * share, uinv))
            count = np.bincount(uinv)  # the repetitions of each point count below
            shared = shared_readings(upts, count, ref_nodes)
            var_ref = var_ref * (shared / count)[:, None]
            bound = bound * (shared / count)[:, None]
            ref_cell = shared[uinv].astype(float)
        var_ref = REF_LOCAL_SHARE * var_ref[uinv]
        bound = REF_LOCAL_SHARE * bound[uinv]
        rms = float(np.sqrt(var_ref.mean())) * 1e4 / b_ref
        how = ("by its harmonic fits: their own error (rms {:.3g} units over the readings, from "
               "the spread of the nearest nodes' fits)" if smooth else
               "corrected by its curvature: its own error (rms {:.3g} units over the readings, "
               "from the map's fourth differences)")  # fmt: skip
        stated = getattr(ref_error, "note", None)
        note.append(
            f"reference: {stated} (rms {rms:.3g} units over the readings)"
            if stated
            else f"reference map read between nodes {how.format(rms)} is added to the noise"
        )
    elif ref_spacing_mm is not None and not smooth:
        var_ref = interpolation_error_var(field_fn, upts, ref_spacing_mm, ref_nodes)[uinv]
        rms = float(np.sqrt(var_ref.mean())) * 1e4 / b_ref
        note.append(
            f"reference map interpolated linearly between nodes {ref_spacing_mm:.3g} mm apart: "
            f"its interpolation error (rms {rms:.3g} units over the readings, from its "
            "curvature) is added to the noise"
        )
    if var_ref is not None:
        var_ref = var_ref * shared_by(uinv)[:, None]
        bound = None if bound is None else bound * shared_by(uinv)[:, None]
    return var_ref, bound, ref_cell, ref_blocks, note
