"""Field models of the coupled Monte Carlo: the nominal field B(x) with its reference field.

A 2-D multipole (paper Table III) or an interpolated FEM map; also the quantities per point
and the paper's Table V that the coupled outputs are set against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError
from .interpolation import LinearInterpolator
from .multipole import Multipole

#: Quantities per point: the three field components and |B|.
QUANTITIES = ("Bx", "By", "Bz", "absB")


#: Table V of the paper, units (1e-4 of the reference field).
PAPER_TABLE_V = {
    "simulation": {"systematic_units": 4.0, "std_units": 5.0, "U_f_units": 6.5},
    "experiment": {"systematic_units": 4.0, "std_units": 6.0, "U_f_units": 7.5},
}


@dataclass
class FieldModel:
    """The nominal field B(x) of the coupled model, with its reference field.

    Build with `FieldModel.from_multipole` or `FieldModel.from_map`.

    Attributes
    ----------
    kind : {"multipole", "fem"}
    b_ref_T : float, T
        Reference field of "units".
    b_ref_rule : str
        How ``b_ref_T`` was chosen (stated in every output).
    components : tuple of int
        Components pooled in the "all" row: (0, 1) for a 2-D multipole (B_z = 0 identically),
        (0, 1, 2) for a map.
    source : str
    multipole : Multipole or None
    interpolator : LinearInterpolator, HarmonicFit or None
        The map's field between nodes: anything with ``field_at(points) -> (B, inside)``.
    field_model : {"linear", "harmonic"}
        How a map is modelled between its nodes (`cfm_fem.models.sweep.FIELD_MODELS`).
    fieldmap : FieldMap or None
        The map of a ``"fem"`` model.
    """

    kind: str
    b_ref_T: float
    b_ref_rule: str
    components: tuple
    source: str
    multipole: Multipole | None = None
    interpolator: object | None = None
    field_model: str = "linear"
    fieldmap: object | None = None

    @classmethod
    def from_multipole(cls, m: Multipole) -> FieldModel:
        """2-D multipole field; B_ref = |B_main + i A_main| at R_ref."""
        return cls(
            kind="multipole",
            b_ref_T=m.b_ref,
            b_ref_rule=f"|B{m.main} + i A{m.main}| at R_ref = {m.r_ref:g} mm (main harmonic)",
            components=(0, 1),
            source=m.source,
            multipole=m,
        )

    @classmethod
    def from_map(cls, fm, b_ref_T: float | None = None, field_model: str = "linear") -> FieldModel:
        """FEM map, piecewise linear or the per-node harmonic fits (3-D maps; nodes where the
        fit fails use the linear interpolant); B_ref given or max |B| over the nodes."""
        b_ref = fm.b_max if b_ref_T is None else float(b_ref_T)
        if not (np.isfinite(b_ref) and b_ref > 0):
            raise CfmInputError(f"B_ref must be a positive field in T; found {b_ref}")
        if field_model not in ("linear", "harmonic"):
            raise CfmInputError(f"--field-model must be linear or harmonic; got {field_model!r}")
        if field_model == "harmonic":
            from .harmonic import fit_harmonic

            interp = fit_harmonic(fm.points, fm.B, source=fm.source)
        else:
            interp = LinearInterpolator(fm)
        return cls(
            kind="fem",
            b_ref_T=b_ref,
            b_ref_rule="max |B| over the map nodes" if b_ref_T is None else "given by the user",
            components=(0, 1, 2),
            source=fm.source,
            interpolator=interp,
            field_model=field_model,
            fieldmap=fm,
        )

    @property
    def r_ref_mm(self) -> float | None:
        return None if self.multipole is None else self.multipole.r_ref

    def field(self, points) -> tuple[np.ndarray, np.ndarray]:
        """B at ``points`` (shape (k, 3), mm, magnet frame).

        Returns
        -------
        B : ndarray, shape (k, 3), T (NaN outside a map)
        inside : ndarray, shape (k,), bool
        """
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if self.multipole is not None:
            return self.multipole.field(pts), np.ones(len(pts), dtype=bool)
        return self.interpolator.field_at(pts)

    def describe(self) -> str:
        if self.multipole is not None:
            m = self.multipole
            return (
                f"2-D multipole, {m.n_orders} orders, main n = {m.main}, R_ref = {m.r_ref:g} mm "
                f"({m.source})"
            )
        if self.field_model == "harmonic":
            fit = self.interpolator
            return (
                f"FEM map, harmonic fit per node to its {fit.k} nearest nodes "
                f"({int((~fit.use).sum())} node(s) on the linear interpolant; {self.source})"
            )
        return (
            f"FEM map, linear interpolation ({self.interpolator.mesh.description}; {self.source})"
        )
