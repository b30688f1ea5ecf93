"""Read the reference field of a comparison: a harmonics file or any FEM export.

A ``.csv`` whose header names the columns ``n``, ``Bn``, ``An`` is a harmonics file
(`cfm_fem.io.harmonics.read_harmonics`); anything else goes to `cfm_fem.io.read_field`.
"""

from __future__ import annotations

import csv
from pathlib import Path

from ..models.field_model import FieldModel
from . import read_field
from ._parse import option_hint, read_lines
from .harmonics import read_harmonics

__all__ = ["is_harmonics_file", "read_reference"]


def is_harmonics_file(path) -> bool:
    """True when ``path`` is a CSV whose first non-comment line names n, Bn and An."""
    if Path(path).suffix.lower() != ".csv":
        return False
    for line in read_lines(path, max_bytes=65536):
        s = line.strip()
        if s and not s.startswith("#"):
            names = {n.strip().lower() for n in next(csv.reader([s]))}
            return {"n", "bn", "an"} <= names
    return False


def read_reference(
    path,
    *,
    b_ref_T: float | None = None,
    r_ref_mm: float | None = None,
    fmt: str | None = None,
    length_unit: str | None = None,
    field_unit: str | None = None,
    zero_rows: str = "warn",
    solution: str | None = None,
    field_model: str = "linear",
):
    """The reference field as a `FieldModel`.

    Parameters
    ----------
    path : str or path-like
        Harmonics file (``n, Bn, An``) or FEM export.
    b_ref_T : float, optional
        Reference field for units of a map (default max |B| of the map). For harmonics B_ref is
        the main harmonic at R_ref and this must not be given.
    r_ref_mm : float, optional
        R_ref for a harmonics file that does not state it.
    fmt, length_unit, field_unit, zero_rows, solution
        How a field map is read (`cfm_fem.io.read_field`); refused for a harmonics file.
    field_model : {"linear", "harmonic"}
        How a map is modelled between its nodes (`FieldModel.from_map`); a harmonics file is
        a field model of its own (``"harmonic"`` refused).

    Returns
    -------
    FieldModel
    """
    from ..errors import CfmInputError

    if is_harmonics_file(path):
        if b_ref_T is not None:
            raise CfmInputError(
                f"{option_hint('b_ref_T')} applies to field maps; for harmonics B_ref is the "
                "main harmonic at R_ref",
                file=path,
            )
        reader = {"fmt": fmt, "length_unit": length_unit, "field_unit": field_unit,
                  "zero_rows": None if zero_rows == "warn" else zero_rows,
                  "solution": solution,
                  "field_model": None if field_model == "linear" else field_model}  # fmt: skip
        given = [option_hint(k, v) for k, v in reader.items() if v is not None]
        if given:
            verb = "applies" if len(given) == 1 else "apply"
            raise CfmInputError(
                f"{' and '.join(given)} {verb} to field maps; this is a harmonics file "
                "(n, Bn, An), read as it is",
                file=path,
            )
        return FieldModel.from_multipole(read_harmonics(path, r_ref_mm=r_ref_mm))
    fm = read_field(
        path, fmt=fmt, length_unit=length_unit, field_unit=field_unit, zero_rows=zero_rows,
        solution=solution,
    )  # fmt: skip
    return FieldModel.from_map(fm, b_ref_T, field_model)
