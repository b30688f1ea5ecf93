"""Compare the numbers two runs wrote: ``python scripts/compare_outputs.py OLD_DIR NEW_DIR``.

Every file under OLD_DIR is paired with the file of the same relative path under NEW_DIR:

- ``.json``: every number and boolean, compared exactly (NaN equals NaN; null equals null),
  key by key and item by item; keys that hold run times, paths or provenance
  (`IGNORED_KEYS`, and keys ending in ``_seconds``) are skipped; text values are not compared;
- ``.csv``: the header and every column whose cells are numbers, compared exactly (empty cells
  equal empty cells); ``#`` comment lines are skipped;
- ``.vtu``: the points, the cells and every point and cell data array, exactly (meshio);
- other files (HTML, PNG, ``.pvd``, ``.py``, logs): present on both sides, contents not compared.

A file on one side only is a difference. Prints one line per difference and a count of what
was compared; exit code 0 when nothing differs, 1 otherwise, 2 on bad arguments.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np

#: JSON keys skipped at any depth: wall-clock times, paths and provenance of the run.
IGNORED_KEYS = frozenset({"provenance", "seconds", "timings", "time_s", "elapsed_s",
                          "created", "timestamp", "command_line", "path", "paths"})  # fmt: skip


class Tally:
    """Differences found and values compared."""

    def __init__(self):
        self.diffs: list[str] = []
        self.values = 0
        self.files = 0

    def differ(self, where: str, what: str) -> None:
        self.diffs.append(f"{where}: {what}")


def _ignored(key: str) -> bool:
    return key in IGNORED_KEYS or key.endswith("_seconds")


def _same_number(a, b) -> bool:
    """Exactly equal numbers (an int equals the same float; NaN equals NaN), or equal booleans."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if not (isinstance(a, (int, float)) and isinstance(b, (int, float))):
        return False
    return a == b or (math.isnan(a) and math.isnan(b))


def compare_json(a, b, where: str, tally: Tally) -> None:
    """Compare the numbers of two JSON values, recursively."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if _ignored(k):
                continue
            if k not in a or k not in b:
                side = "new" if k not in a else "old"
                tally.differ(f"{where}.{k}", f"only in the {side} run")
                continue
            compare_json(a[k], b[k], f"{where}.{k}", tally)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            tally.differ(where, f"list of {len(a)} vs {len(b)} items")
            return
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            compare_json(x, y, f"{where}[{i}]", tally)
    elif isinstance(a, (int, float, bool)) or isinstance(b, (int, float, bool)):
        tally.values += 1
        if not _same_number(a, b):
            tally.differ(where, f"{a!r} vs {b!r}")
    elif a is None or b is None:
        tally.values += 1
        if (a is None) != (b is None):
            tally.differ(where, f"{a!r} vs {b!r}")
    elif type(a) is not type(b):
        tally.differ(where, f"{type(a).__name__} vs {type(b).__name__}")


def _csv_rows(path: Path) -> list[list[str]]:
    with open(path, newline="", encoding="utf-8") as f:
        return [r for r in csv.reader(line for line in f if not line.startswith("#"))]


def _numeric(cells) -> bool:
    try:
        for c in cells:
            if c.strip():
                float(c)
    except ValueError:
        return False
    return True


def compare_csv(old: Path, new: Path, where: str, tally: Tally) -> None:
    """Compare the header and the numeric columns of two CSV tables."""
    a, b = _csv_rows(old), _csv_rows(new)
    if not a or not b or a[0] != b[0]:
        tally.differ(where, f"header {a[:1]} vs {b[:1]}")
        return
    if len(a) != len(b):
        tally.differ(where, f"{len(a) - 1} vs {len(b) - 1} rows")
        return
    for j, name in enumerate(a[0]):
        col_a = [r[j] if j < len(r) else "" for r in a[1:]]
        col_b = [r[j] if j < len(r) else "" for r in b[1:]]
        if not (_numeric(col_a) and _numeric(col_b)):
            continue
        for i, (x, y) in enumerate(zip(col_a, col_b, strict=True)):
            tally.values += 1
            same = (not x.strip() and not y.strip()) or (
                x.strip() and y.strip() and _same_number(float(x), float(y))
            )
            if not same:
                tally.differ(f"{where} column {name!r} row {i + 1}", f"{x!r} vs {y!r}")
                break


def _arrays_equal(x, y) -> bool:
    x, y = np.asarray(x), np.asarray(y)
    if x.shape != y.shape:
        return False
    if x.dtype.kind == "f" or y.dtype.kind == "f":
        return bool(np.array_equal(x, y, equal_nan=True))
    return bool(np.array_equal(x, y))


def compare_vtu(old: Path, new: Path, where: str, tally: Tally) -> None:
    """Compare the points, cells and data arrays of two VTU files."""
    import meshio

    a, b = meshio.read(old), meshio.read(new)
    pairs = [("points", a.points, b.points)]
    cells_a = [(c.type, c.data) for c in a.cells]
    cells_b = [(c.type, c.data) for c in b.cells]
    if [t for t, _ in cells_a] != [t for t, _ in cells_b]:
        tally.differ(where, "cell types differ")
        return
    pairs += [(f"cells {t}", x, y) for (t, x), (_, y) in zip(cells_a, cells_b, strict=True)]
    for kind, da, db in (("point", a.point_data, b.point_data), ("cell", a.cell_data,
                                                                  b.cell_data)):  # fmt: skip
        if set(da) != set(db):
            tally.differ(where, f"{kind} data {sorted(da)} vs {sorted(db)}")
        for name in sorted(set(da) & set(db)):
            pairs.append((f"{kind} data {name!r}", da[name], db[name]))
    for name, x, y in pairs:
        if isinstance(x, list):  # cell data: one array per cell block
            same = len(x) == len(y) and all(_arrays_equal(p, q) for p, q in zip(x, y, strict=True))
            size = sum(np.size(p) for p in x)
        else:
            same, size = _arrays_equal(x, y), np.size(x)
        tally.values += int(size)
        if not same:
            tally.differ(where, f"{name} differs")


def compare_dirs(old_dir, new_dir) -> Tally:
    """Compare every file under ``old_dir`` with its namesake under ``new_dir``."""
    old_dir, new_dir = Path(old_dir), Path(new_dir)
    tally = Tally()
    names_a = {p.relative_to(old_dir) for p in old_dir.rglob("*") if p.is_file()}
    names_b = {p.relative_to(new_dir) for p in new_dir.rglob("*") if p.is_file()}
    for rel in sorted(names_a ^ names_b):
        if not rel.name.startswith("."):  # the lock of a run in progress
            tally.differ(str(rel), f"only in the {'old' if rel in names_a else 'new'} run")
    for rel in sorted(names_a & names_b):
        old, new, suffix = old_dir / rel, new_dir / rel, rel.suffix.lower()
        tally.files += 1
        if suffix == ".json":
            a = json.loads(old.read_text(encoding="utf-8"))
            b = json.loads(new.read_text(encoding="utf-8"))
            compare_json(a, b, str(rel), tally)
        elif suffix == ".csv":
            compare_csv(old, new, str(rel), tally)
        elif suffix == ".vtu":
            compare_vtu(old, new, str(rel), tally)
    return tally


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2 or not all(Path(a).is_dir() for a in argv):
        print(__doc__.splitlines()[0], file=sys.stderr)
        print("error: expected two folders, OLD_DIR NEW_DIR", file=sys.stderr)
        return 2
    tally = compare_dirs(*argv)
    for d in tally.diffs:
        print(f"differs: {d}")
    print(f"{tally.files} files paired, {tally.values} values compared, "
          f"{len(tally.diffs)} difference(s)")  # fmt: skip
    return 1 if tally.diffs else 0


if __name__ == "__main__":
    sys.exit(main())
