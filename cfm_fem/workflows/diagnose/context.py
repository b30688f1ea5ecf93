"""The model pieces of a diagnosis problem that its effect catalogue reads: `ProblemContext`.

A tracker problem fills the bench, the nominal probe positions, the point ids and the
registration prior; a Hall-map problem the reference field and its derivatives at the
readings, the registration pose it is linearised at and the bench's lever on the field. The
fields ``U``, ``HU``, ``V``, ``W3`` and ``H`` are caches the effects fill when first needed.

Each field is either per row (its first axis the problem's rows, sliced with them by
`ProblemContext.subset`), per distinct position (``upts`` and the caches indexed like it,
read through ``uinv``) or whole.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ...models.bench import Bench

__all__ = ["ProblemContext"]

#: Marks a field whose first axis is the rows of the problem.
_PER_ROW = {"per_row": True}


def _row_field():
    return field(default=None, metadata=_PER_ROW)


@dataclass
class ProblemContext:
    """Model pieces the effect catalogue of a diagnosis problem needs.

    ``n`` is the number of rows of the problem, ``m`` the number of distinct measured
    positions of a Hall map (``upts``), ``n_points`` the number of distinct point ids.

    Attributes
    ----------
    bench : Bench or None
        The bench the recording was taken on; None for a Hall map whose bench is unknown or
        whose map exceeds the bench strokes (no positioning-error columns).
    point_ids : ndarray, shape (n_points,), or None
        The recording's id of each distinct point (index = ``Problem.point``).
    registration_prior : dict or None
        Prior std of the registration and where it comes from: ``translation_mm``,
        ``rotation_rad`` (1 sigma per axis), ``translation_source``, ``rotation_source``
        and, for a Hall map, ``bench_file``
        (:func:`~cfm_fem.workflows.diagnose.problem.registration_prior`).
    nominal : ndarray, shape (n, 3), mm, or None
        Tracker: nominal probe position of each row (bench frame). Per row.
    b_ref : float, T, or None
        Hall map: reference field of 'units' (1 unit = 1e-4 ``b_ref``).
    B0 : ndarray, shape (n, 3), T, or None
        Hall map: reference field at each reading with the magnet at ``pose``. Per row.
    B_read : ndarray, shape (n, 3), T, or None
        Hall map: the field the probe senses, the reference with the magnet at ``pose`` read
        where the bench errors the problem is expanded at move the probe (to second order,
        :func:`~cfm_fem.workflows.diagnose.problem.bench_expansion`); ``B0`` without a bench
        model and against 2-D harmonics (whose pose a scan through the ends pulls: the
        effects' columns keep the nominal placement there, as ``B0``). Per row.
    G : ndarray, shape (n, 3, 3), T/mm, or None
        Hall map: its gradient dB_i/dx_j at each reading (magnet frame). Per row.
    reference_fn : callable or None
        Hall map: ``reference_fn(points (k, 3) mm) -> B (k, 3) T``, the reference in the
        magnet's own frame (nominal placement).
    field_fn : callable or None
        Hall map: the same with the magnet moved to ``pose``
        (:func:`~cfm_fem.workflows.diagnose.problem.posed_field`).
    pose : ndarray, shape (6,), or None
        Hall map: registration the problem is linearised at, um (3 translations) and urad
        (3 rotations), in the order of :data:`~cfm_fem.workflows.diagnose.problem.REG_NAMES`.
    elements_at : ndarray, shape (3, 3), or None
        Hall map: the Hall elements' offsets (um) from their centroid the problem is
        linearised at (row i: element x, y, z; :mod:`~cfm_fem.workflows.diagnose.elements`);
        None: the elements at the probe's point.
    rows : ndarray, shape (n,), int, or None
        Hall map: index of each row in the problem ``rebuild`` returns (all rows of the
        recording). Per row.
    rebuild : callable or None
        Hall map: ``rebuild(pose=ndarray (6,)) -> Problem``, the whole problem linearised at
        another registration (um, urad).
    smooth : bool
        False for a reference interpolated linearly between its nodes (no second
        derivatives between them); True otherwise and for a tracker.
    node_step : float, mm, or None
        Node spacing of a linear reference map when every reading lies on one of its nodes
        (second differences of that step read node values), else None.
    reference_3d : bool
        Hall map: the reference is a map whose nodes span z (it holds the magnet's ends where
        its nodes reach them); False for 2-D harmonics, a planar map and a tracker.
    upts : ndarray, shape (m, 3), mm, or None
        Hall map: the distinct measured positions (magnet frame).
    uinv : ndarray, shape (n,), int, or None
        Hall map: index into ``upts`` of each row. Per row.
    bench_disp : ndarray, shape (n, 3, 21), or None
        Hall map on a known bench: probe displacement (magnet frame, mm) per display unit
        (um or urad) of each of the 21 bench errors. Per row.
    lever : ndarray, shape (n, 3, 3), T/mm, or None
        Hall map on a known bench: change of the reading per bench-frame probe displacement
        (the gradient turned into the bench frame). Per row.
    axis_var : ndarray, shape (3,), mm^2, or None
        Hall map on a known bench: variance of the bench's vibration along each axis.
    U : ndarray, shape (layers, m, 3), or None
        Cache: potential layers U_k (T mm^(2k+1)) and their transverse gradients
        (T mm^(2k)) at ``upts`` (:func:`~cfm_fem.workflows.diagnose.fringe.potential_layers`).
    HU : ndarray, shape (layers, m, 2, 2), T mm^(2k-1), or None
        Cache: transverse Hessians of those layers at ``upts``.
    V : ndarray, shape (m,), T mm, or None
        Cache: scalar potential of the transverse field at ``upts`` (zero on the axis).
    W3 : ndarray, shape (m, 3), or None
        Cache: W (T mm^3) with lap_perp W = V and its gradient dW/dx, dW/dy (T mm^2) at
        ``upts``.
    H : ndarray, shape (n, 3, 3), T/mm^2, or None
        Cache: second derivatives d^2 B_i / dx_j^2 of the reference at each reading
        [row, component i, direction j]. Per row.
    """

    bench: Bench | None = None
    point_ids: np.ndarray | None = None
    registration_prior: dict | None = None
    nominal: np.ndarray | None = _row_field()
    b_ref: float | None = None
    B0: np.ndarray | None = _row_field()
    B_read: np.ndarray | None = _row_field()
    G: np.ndarray | None = _row_field()
    reference_fn: Callable | None = None
    field_fn: Callable | None = None
    pose: np.ndarray | None = None
    elements_at: np.ndarray | None = None
    rows: np.ndarray | None = _row_field()
    rebuild: Callable | None = None
    smooth: bool = True
    node_step: float | None = None
    reference_3d: bool = False
    upts: np.ndarray | None = None
    uinv: np.ndarray | None = _row_field()
    bench_disp: np.ndarray | None = _row_field()
    lever: np.ndarray | None = _row_field()
    axis_var: np.ndarray | None = None
    U: np.ndarray | None = None
    HU: np.ndarray | None = None
    V: np.ndarray | None = None
    W3: np.ndarray | None = None
    H: np.ndarray | None = _row_field()

    def subset(self, keep: np.ndarray, points: np.ndarray) -> ProblemContext:
        """The context of the rows ``keep``.

        Parameters
        ----------
        keep : ndarray, shape (n,), bool
            Rows kept.
        points : ndarray, shape (n_kept_points,), int
            The distinct points (indices into ``point_ids``) the kept rows measure, ascending.

        Returns
        -------
        ProblemContext
            Per-row fields sliced, ``point_ids`` restricted to ``points``, the rest (caches per
            distinct position included) shared.
        """
        cut = {
            f.name: getattr(self, f.name)[keep]
            for f in fields(self)
            if f.metadata.get("per_row") and getattr(self, f.name) is not None
        }
        if self.point_ids is not None:
            cut["point_ids"] = self.point_ids[points]
        return replace(self, **cut)
