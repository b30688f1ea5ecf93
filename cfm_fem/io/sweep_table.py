"""A sweep's per-node table, ``nodes.csv`` (or ``nodes.parquet``), for pandas and spreadsheets.

One row per node of the map (every node once: the ghost copies of the pieces are left out),
read back from the maps the sweep wrote, one piece of every map at a time (bounded memory):

- ``x_mm``, ``y_mm``, ``z_mm``: the node;
- ``absB_nominal_T``: |B| of the map at the node;
- ``node_volume_mm3``: the volume the node stands for, the weight of the summary's percentiles;
- ``in_region``: 1 for a node of ``--region`` (only when one was given);
- per column of the sweep (``<label>`` = ``up20um``, ``htm_total``, ...):
  ``U_f_units_<label>`` (NaN where the node has no U_f figure), ``complete_<label>`` (1: every
  trial has a value), ``absB_systematic_units_<label>``, ``absB_u_units_<label>`` (mean and
  standard deviation of the error of |B|, NaN where incomplete) and
  ``outside_fraction_<label>``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import CfmInputError
from ._atomic import atomic_path
from .sweep_maps import map_files, read_map_arrays, read_summary

__all__ = ["TABLE_FORMATS", "table_name", "check_table_format", "write_sweep_table",
           "remove_stale_table", "table_columns"]  # fmt: skip

#: Formats of ``--table``.
TABLE_FORMATS = ("csv", "parquet")

#: Per-column arrays of a map that go into the table, with their names there.
_PER_COLUMN = {
    "U_f_units": "U_f_units",
    "complete": "complete",
    "absB_systematic_units": "absB_systematic_units",
    "absB_u_units": "absB_u_units",
    "outside_fraction": "outside_fraction",
}
#: Arrays that are the same in every map (read from the first).
_PER_NODE = ("absB_nominal_T", "node_volume_mm3")


def table_name(fmt: str) -> str:
    """``nodes.csv`` or ``nodes.parquet``."""
    return f"nodes.{fmt}"


def check_table_format(fmt: str) -> None:
    """Refuse a format that cannot be written here, before any work.

    Raises
    ------
    CfmInputError
        ``parquet`` without pyarrow installed, or an unknown format.
    """
    if fmt not in TABLE_FORMATS:
        raise CfmInputError(f"--table must be csv or parquet; got {fmt!r}")
    if fmt == "parquet":
        try:
            import pyarrow  # noqa: F401
            import pyarrow.parquet  # noqa: F401
        except ImportError:
            raise CfmInputError(
                "--table parquet needs pyarrow, which is not installed here (pip install "
                "pyarrow); --table csv writes the same table"
            ) from None


def table_columns(labels, with_region: bool) -> list[str]:
    """Column names of the table, in order, for the sweep columns ``labels``."""
    names = ["x_mm", "y_mm", "z_mm", *_PER_NODE] + (["in_region"] if with_region else [])
    for label in labels:
        names += [f"{name}_{label}" for name in _PER_COLUMN.values()]
    return names


def _piece_rows(files_of_piece, with_region: bool) -> np.ndarray:
    """The table rows of one piece (the same piece of every map), shape (m, columns)."""
    first = [*_PER_NODE] + (["in_region"] if with_region else [])
    cols = []
    points = None
    for k, f in enumerate(files_of_piece):
        names = list(_PER_COLUMN) + (first if k == 0 else [])
        pts, arrays = read_map_arrays(f, names)
        if points is None:
            points = pts
            cols += [pts[:, 0], pts[:, 1], pts[:, 2]] + [arrays[n] for n in first]
        elif pts.shape != points.shape or not np.array_equal(pts, points):
            raise CfmInputError(f"{f}: its nodes differ from the other maps' of this sweep")
        cols += [arrays[n] for n in _PER_COLUMN]
    return np.column_stack([np.asarray(c, dtype=np.float64) for c in cols])


def write_sweep_table(out_dir, fmt: str = "csv") -> Path:
    """Write ``out_dir/nodes.<fmt>`` from the sweep written in ``out_dir`` (atomically).

    Parameters
    ----------
    out_dir : path-like
        A finished sweep's folder (``summary.json``, ``sweep.pvd`` and its maps).
    fmt : {"csv", "parquet"}
        ``parquet`` needs pyarrow (`check_table_format`).

    Returns
    -------
    Path
        The file written.
    """
    check_table_format(fmt)
    out = Path(out_dir)
    summary = read_summary(out)
    labels = summary["columns"]
    with_region = summary.get("region") is not None
    maps = map_files(out)
    if len(maps) != len(labels) or len({len(m) for m in maps}) != 1:
        raise CfmInputError(f"{out / 'sweep.pvd'}: its maps do not match summary.json's columns")
    names = table_columns(labels, with_region)
    path = out / table_name(fmt)
    with atomic_path(path) as tmp:
        if fmt == "csv":
            _write_csv(tmp, names, maps, with_region)
        else:
            _write_parquet(tmp, names, maps, with_region)
    return path


def _formats(names) -> list[str]:
    """numpy formats per column: integers for the flags, 9 digits for coordinates, 7 for the
    float32 statistics (all their digits)."""
    fmts = []
    for n in names:
        if n.startswith("complete_") or n == "in_region":
            fmts.append("%d")
        elif n.endswith("_mm") or n == "absB_nominal_T":
            fmts.append("%.9g")
        else:
            fmts.append("%.7g")
    return fmts


def _write_csv(tmp: Path, names, maps, with_region) -> None:
    fmts = _formats(names)
    with open(tmp, "w", encoding="utf-8", newline="\n") as f:
        f.write(",".join(names) + "\n")
        for p in range(len(maps[0])):
            rows = _piece_rows([m[p] for m in maps], with_region)
            np.savetxt(f, rows, fmt=fmts, delimiter=",")


def _write_parquet(tmp: Path, names, maps, with_region) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    writer = None
    try:
        for p in range(len(maps[0])):
            rows = _piece_rows([m[p] for m in maps], with_region)
            columns = {}
            for j, n in enumerate(names):
                flag = n.startswith("complete_") or n == "in_region"
                columns[n] = rows[:, j].astype(np.uint8 if flag else np.float64)
            table = pa.table(columns)
            if writer is None:
                writer = pq.ParquetWriter(str(tmp), table.schema)
            writer.write_table(table)
    finally:
        if writer is not None:
            writer.close()


def remove_stale_table(out_dir, keep: str | None) -> list[str]:
    """Remove the ``nodes.csv`` an earlier sweep with ``--table`` left in ``out_dir`` when this
    run wrote another table or none (``keep``: the format written, or None): its figures would
    be the earlier run's. Only a file whose header is a sweep table's is removed, and a
    ``nodes.parquet`` only when it has this run's columns' first names (a parquet file is
    recognised by its schema). Returns the names removed."""
    out = Path(out_dir)
    removed = []
    for fmt in TABLE_FORMATS:
        path = out / table_name(fmt)
        if fmt == keep or not path.is_file() or path.is_symlink():
            continue
        if _written_by_sweep(path, fmt):
            path.unlink()
            removed.append(path.name)
    return removed


def _written_by_sweep(path: Path, fmt: str) -> bool:
    head = ",".join(table_columns([], False))
    if fmt == "csv":
        with open(path, encoding="utf-8", errors="replace") as f:
            return f.readline().startswith(head)
    try:
        import pyarrow.parquet as pq
    except ImportError:
        return False
    try:
        return ",".join(pq.read_schema(str(path)).names).startswith(head)
    except Exception:  # not a parquet file: not ours
        return False
