"""Files of a simulated recording: the CSV of the recording contract, the truth beside it, and
the reference a user would give the diagnosis (a field table, or 2-D harmonics)."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = [
    "write_csv",
    "write_json",
    "write_text",
    "write_reference_table",
    "write_harmonics",
    "COLUMN_FORMAT",
]

#: printf format of each column (positions to 1 nm, fields to 1 nT).
COLUMN_FORMAT = {
    "point_id": "%d", "rep": "%d", "dir_x": "%d", "dir_y": "%d", "dir_z": "%d",
    "x_cmd": "%.6f", "y_cmd": "%.6f", "z_cmd": "%.6f",
    "x_meas": "%.6f", "y_meas": "%.6f", "z_meas": "%.6f",
    "Bx": "%.9f", "By": "%.9f", "Bz": "%.9f",
    "t_s": "%.3f", "speed": "%.3f", "v_x": "%.3f", "v_y": "%.3f", "v_z": "%.3f",
    "temp_C": "%.4f",
}  # fmt: skip


def _atomic_write(path, text: str) -> Path:
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _table(names, arrays, fmts, comments=()) -> str:
    lines = [f"# {c}" for c in comments] + [",".join(names)]
    data = np.column_stack([np.asarray(a, dtype=float) for a in arrays])
    fmt = ",".join(fmts)
    lines += [fmt % tuple(row) for row in data]
    return "\n".join(lines) + "\n"


def write_csv(path, columns: dict, comments=(), drop=()) -> Path:
    """Write a recording (columns in the given order, less ``drop``) as CSV, atomically."""
    names = [k for k in columns if k not in drop]
    fmts = [COLUMN_FORMAT.get(k, "%.9g") for k in names]
    return _atomic_write(path, _table(names, [columns[k] for k in names], fmts, comments))


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON, atomically."""
    return _atomic_write(path, json.dumps(obj, indent=1, sort_keys=True) + "\n")


def write_text(path, text: str) -> Path:
    """Write ``text`` (a bench file) atomically."""
    return _atomic_write(path, text)


def write_reference_table(path, points_mm, b_t, comments=()) -> Path:
    """A field table (``x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]``) a field-map reader takes."""
    names = ["x [mm]", "y [mm]", "z [mm]", "Bx [T]", "By [T]", "Bz [T]"]
    arrays = [*np.asarray(points_mm).T, *np.asarray(b_t).T]
    return _atomic_write(path, _table(names, arrays, ["%.6f"] * 3 + ["%.10e"] * 3, comments))


def write_harmonics(path, rows, r_ref_mm: float, comments=(), main: int = 2) -> Path:
    """2-D multipoles (rows n, B_n, A_n in T at ``r_ref_mm``; main harmonic of order ``main``)
    as a harmonics CSV."""
    head = [*comments, f"r_ref_mm: {r_ref_mm:g}", "convention: tesla", f"main: {int(main)}"]
    rows = np.asarray(rows, dtype=float)
    return _atomic_write(path, _table(["n", "Bn", "An"], rows.T, ["%d", "%.10e", "%.10e"], head))
