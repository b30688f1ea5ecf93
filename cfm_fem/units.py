"""Unit names accepted in file headers and on the command line, converted once to mm and T."""

from __future__ import annotations

from .errors import CfmInputError

__all__ = ["LENGTH_TO_MM", "FIELD_TO_T", "length_scale", "field_scale"]

#: Multiply a length in the named unit by this to get mm. Keys are lower case.
LENGTH_TO_MM = {
    "m": 1000.0,
    "metre": 1000.0,
    "meter": 1000.0,
    "metres": 1000.0,
    "meters": 1000.0,
    "cm": 10.0,
    "mm": 1.0,
    "um": 1e-3,
    "µm": 1e-3,
    "micron": 1e-3,
    "in": 25.4,
    "inch": 25.4,
    "inches": 25.4,
    "ft": 304.8,
}

#: Multiply a field in the named unit by this to get T. Keys are lower case.
FIELD_TO_T = {
    "t": 1.0,
    "tesla": 1.0,
    "mt": 1e-3,
    "ut": 1e-6,
    "µt": 1e-6,
    "g": 1e-4,
    "gauss": 1e-4,
    "kg": 0.1,
    "kgauss": 0.1,
    "kilogauss": 0.1,
}


def _scale(table, kind, unit, file, line, column):
    key = str(unit).strip().lower()
    if key in table:
        return table[key]
    known = ", ".join(sorted({k for k in table if k.isascii()}))
    where = f"column '{column}': " if column else ""
    raise CfmInputError(
        f"{where}unknown {kind} unit '{unit}'; expected one of {known}",
        file=file,
        line=line,
        column=column,
    )


def length_scale(unit: str, *, file=None, line=None, column=None) -> float:
    """Factor that converts a length in ``unit`` to mm (``'METRE'`` -> 1000.0)."""
    return _scale(LENGTH_TO_MM, "length", unit, file, line, column)


def field_scale(unit: str, *, file=None, line=None, column=None) -> float:
    """Factor that converts a flux density in ``unit`` to T (``'kG'`` -> 0.1)."""
    return _scale(FIELD_TO_T, "field", unit, file, line, column)
