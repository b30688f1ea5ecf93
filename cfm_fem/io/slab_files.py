"""Files of the out-of-core sweep: the staged map, the per-slab results and the piecewise output.

`stage` streams a table or Opera map once into a work folder (rows as float64, source lines as
int64, memory-mapped back); `SlabStore` keeps each slab's arrays and a done record; the work
folder of a resumable run carries a manifest naming its run; `write_slab_outputs` writes one
``.vtu`` piece per slab and U_p value, the ``.pvtu`` indices, ``sweep.pvd`` and
``summary.json``. The sweep itself is `cfm_fem.workflows.sweep.slabs`.
"""

from __future__ import annotations

import json
import mmap
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..models.field import FieldMap
from ..models.mesh import (
    FLAT_TOL,
)
from ..models.sweep import SweepResult
from ._atomic import write_json
from .paraview_script import write_paraview_script
from .pvtu import GHOST_ARRAY, ghost_flags, write_pvtu
from .streaming import check_opera_counts, open_stream
from .sweep_out import (
    _point_data,
    map_field_data,
    retire_index,
    vtu_name,
)
from .vtk import write_pvd, write_vtu

__all__ = [
    "SLAB_WORK",
    "Staged",
    "stage",
    "staged_fieldmap",
    "SlabStore",
    "read_manifest",
    "new_work_dir",
    "temp_work_dir",
    "remove_work_dir",
    "make_per_node_file",
    "open_per_node",
    "drop_pages",
    "read_slab_piece",
    "SlabMapWriter",
]

#: Work folder of a resumable out-of-core run (staged rows, per-slab results, manifest).
SLAB_WORK = ".cfm_fem_slabs"

#: Distinct values per axis tracked while staging; more means "not a grid".
MAX_DISTINCT = 1 << 20


#: Rows per block when streaming or scanning the staged rows.
BLOCK = 1 << 16


def drop_pages(mm, start: int = 0, length: int | None = None) -> None:
    """Drop resident pages of a file mapping from this process (Linux/macOS; no-op elsewhere).
    Shared file pages stay in the page cache, so nothing is lost and a later access re-reads."""
    if mm is None or not hasattr(mmap, "MADV_DONTNEED"):
        return
    if length is None:
        mm.madvise(mmap.MADV_DONTNEED)
    elif length > 0:
        mm.madvise(mmap.MADV_DONTNEED, start, length)


@dataclass
class Staged:
    """The streamed map on disk (see `stage`).

    Attributes
    ----------
    rows : numpy.memmap, shape (n, 6), float64
        x, y, z (mm), Bx, By, Bz (T) of every kept row (placeholder rows already dropped if
        asked), in file order.
    lines : numpy.memmap, shape (n,), int64
        1-based source line of each row.
    lo, hi : ndarray, shape (3,), mm
        Bounding box.
    b_max : float, T
        Largest |B| over the rows (the default B_ref, as `FieldMap.b_max`).
    b_abs_max : float, T
        Largest |B component| (the scale of the duplicate-field test of `FieldMap`).
    distinct : list of ndarray or None
        Sorted distinct coordinate values per axis, None if more than `MAX_DISTINCT`.
    dim : int
        3, or 2 / 1 for planar / collinear maps (left to the in-memory path).
    spelled : list of str
    notes : list of str
    """

    rows: np.ndarray
    lines: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    b_max: float
    b_abs_max: float
    distinct: list
    dim: int
    spelled: list
    notes: list
    maps: tuple = ()  # the mmap objects behind rows and lines
    workdir: Path | None = None  # where rows.f8 and lines.i8 are (None: rows held in memory)

    def __getstate__(self):
        """Pickled as the files' folder: a worker maps the rows itself (never a copy)."""
        state = dict(self.__dict__)
        if self.workdir is not None:
            state.update(rows=None, lines=None, maps=())
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if self.workdir is not None:
            self.rows, self.lines, self.maps = _map_rows(self.workdir)

    def release(self, a: int = 0, b: int | None = None) -> None:
        """Drop the pages of rows a..b-1 from this process (they stay in the page cache and
        come back on the next access): scans of the whole file then keep RSS at one block."""
        b = len(self.rows) if b is None else min(b, len(self.rows))
        for mm, width in zip(self.maps, (48, 8), strict=False):
            start = (a * width // mmap.PAGESIZE) * mmap.PAGESIZE
            stop = b * width
            drop_pages(mm, start, stop - start)


def stage(path, fmt, workdir, *, length_unit=None, field_unit=None, zero_rows="warn") -> Staged:
    """Stream a table or Opera map once into ``workdir`` (see the module docstring, step 1).

    Memory: one block of rows (`BLOCK`) and the distinct-value sets.

    Raises
    ------
    CfmInputError
        As `cfm_fem.io.read_field` for the same file (file, line, column).
    """
    from ._parse import check_zero_rows, zero_rows_dropped, zero_rows_kept

    check_zero_rows(zero_rows)
    stream = open_stream(path, fmt, length_unit=length_unit, field_unit=field_unit)
    workdir = Path(workdir)
    n = 0
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    b_max = b_abs = 0.0
    distinct = [np.empty(0), np.empty(0), np.empty(0)]
    ref = None
    scatter = np.zeros((3, 3))
    total = np.zeros(3)
    n_zero, first_zero = 0, None
    with open(workdir / "rows.f8", "wb") as fr, open(workdir / "lines.i8", "wb") as fl:
        for values, lines in stream.blocks(BLOCK):
            zero = np.all(values[:, 3:] == 0.0, axis=1)
            if zero.any():
                if first_zero is None:
                    first_zero = int(lines[np.flatnonzero(zero)[0]])
                n_zero += int(zero.sum())
                if zero_rows == "drop":
                    values, lines = values[~zero], lines[~zero]
            if not len(values):
                continue
            p = values[:, :3]
            lo, hi = np.minimum(lo, p.min(axis=0)), np.maximum(hi, p.max(axis=0))
            b_max = max(b_max, float(np.sqrt((values[:, 3:] ** 2).sum(axis=1)).max()))
            b_abs = max(b_abs, float(np.abs(values[:, 3:]).max()))
            for k in range(3):
                if distinct[k] is not None:
                    d = np.union1d(distinct[k], p[:, k])
                    distinct[k] = d if len(d) <= MAX_DISTINCT else None
            ref = p[0].copy() if ref is None else ref
            q = p - ref  # shifted sums: the flatness test needs no second pass
            scatter += q.T @ q
            total += q.sum(axis=0)
            fr.write(np.ascontiguousarray(values).tobytes())
            fl.write(np.ascontiguousarray(lines, dtype=np.int64).tobytes())
            n += len(values)
    notes = list(stream.notes)
    if stream.fmt == "opera":
        notes += check_opera_counts(stream, [None if d is None else len(d) for d in distinct])
    if n_zero:
        what = (
            f"{n_zero} row(s) have {', '.join(stream.spelled[3:])} exactly 0 0 0 (first at line "
            f"{first_zero})"
        )
        if zero_rows == "drop":
            notes.append(zero_rows_dropped(what))
        else:
            notes.append(zero_rows_kept(stream.file, what, zero_rows, stacklevel=2))
    dim = 0
    if n >= 3:
        cov = scatter - np.outer(total, total) / n
        s = np.sqrt(np.clip(np.linalg.eigvalsh(cov)[::-1], 0.0, None))
        dim = 1 if (s[0] == 0 or s[1] <= FLAT_TOL * s[0]) else 2 if s[2] <= FLAT_TOL * s[0] else 3
    if not n:
        return Staged(np.empty((0, 6)), np.empty(0, dtype=np.int64), lo, hi, b_max, b_abs,
                      distinct, dim, stream.spelled, notes)  # fmt: skip
    rows, lines, maps = _map_rows(workdir)
    return Staged(rows, lines, lo, hi, b_max, b_abs, distinct, dim, stream.spelled, notes,
                  maps, workdir)  # fmt: skip


def staged_fieldmap(st: Staged, path) -> FieldMap:
    """The staged map as the `FieldMap` `cfm_fem.io.read_field` reads from the same file
    (same points, field, lines, notes; duplicates merged as it does), held in memory.

    For maps that are not 3-D, run in memory: the file is then read once, and its warnings
    (units, thousands separators, placeholder rows) are given once.
    """
    values = np.array(st.rows)  # a copy: the staged files are removed after the run
    return FieldMap.from_arrays(values[:, :3], values[:, 3:], source=str(path),
                                lines=np.array(st.lines), notes=list(st.notes),
                                columns=tuple(st.spelled))  # fmt: skip


def _map_rows(workdir: Path):
    """The staged rows (n, 6) and lines (n,) of ``workdir``, read-only, and their mmaps."""
    maps = []
    for name in ("rows.f8", "lines.i8"):  # mapped by hand: `Staged.release` needs the mmap
        with open(workdir / name, "rb") as f:
            maps.append(mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ))
    rows = np.frombuffer(maps[0], dtype=np.float64).reshape(-1, 6)
    lines = np.frombuffer(maps[1], dtype=np.int64)
    return rows, lines, tuple(maps)


class SlabStore:
    """Per-slab results on disk (``.npy``), read back by node id."""

    def __init__(self, root: Path):
        self.root = root
        self.ids = []

    def save(self, k, **arrays):
        d = self.root / f"slab{k:04d}"
        d.mkdir(parents=True, exist_ok=True)
        for name, arr in arrays.items():
            np.save(d / f"{name}.npy", arr)

    def mark_done(self, k, record: dict) -> None:
        """Slab k is complete: its arrays are saved and ``record`` holds what the merge needs
        (written last and atomically, so a present record means a usable slab)."""
        write_json(self.root / f"slab{k:04d}" / "done.json", record)

    def done(self, k) -> dict | None:
        """The record of a completed slab k, or None."""
        f = self.root / f"slab{k:04d}" / "done.json"
        try:
            return json.loads(f.read_text())
        except (OSError, ValueError):
            return None

    def load(self, k, name):
        return np.load(self.root / f"slab{k:04d}" / f"{name}.npy", mmap_mode="r")

    def gather(self, ids, n_slabs, names):
        """Arrays ``names`` of the node ids ``ids`` (any slab), in the order of ``ids``."""
        out = {}
        found = np.zeros(len(ids), dtype=bool)
        for k in range(n_slabs):
            own = self.load(k, "ids")
            pos = np.clip(np.searchsorted(own, ids), 0, max(len(own) - 1, 0))
            hit = (own[pos] == ids) if len(own) else np.zeros(len(ids), bool)
            if not hit.any():
                continue
            for name in names:
                src = self.load(k, name)
                if name not in out:
                    out[name] = np.empty((len(ids),) + src.shape[1:], src.dtype)
                out[name][hit] = src[pos[hit]]
            found |= hit
        if not found.all():  # pragma: no cover - every cell vertex is owned by some slab
            raise RuntimeError(f"{int((~found).sum())} node(s) of the pieces have no results")
        return out


def make_per_node_file(path: Path, dtype, shape, resume: bool) -> None:
    """Create a per-node array file (`_SlabJob.per_node`), or keep it when resuming: the
    finished slabs' rows are in it."""
    if resume and path.exists():
        arr = np.lib.format.open_memmap(path, "r")
        if arr.shape == shape and arr.dtype == dtype:
            return
        del arr
    np.lib.format.open_memmap(path, "w+", dtype, shape).flush()


#: Per-node arrays a slab piece's map is made of (`SlabStore.gather`); ``fit_*`` with the
#: harmonic field model only.
PIECE_ARRAYS = ("points", "B", "stats", "n_out", "n_lost", "n_left", "star", "gradient", "pos",
                "volume")  # fmt: skip


def read_slab_piece(store: SlabStore, p: int, K: int, harmonic: bool):
    """The nodes of slab ``p``'s map piece: its own nodes and the halo nodes its cells use.

    Returns
    -------
    cells : ndarray, shape (c, 4), int64
        The piece's cells in local indices (into the rows of ``arrays``).
    ghost : ndarray, shape (m,), uint8
        `ghost_flags`: 1 at halo nodes (copies of another slab's nodes).
    arrays : dict of ndarray
        `PIECE_ARRAYS` (and ``fit_degree``, ``fit_residual`` if ``harmonic``), m rows each.
    """
    ids = np.asarray(store.load(p, "ids"))
    cells = np.asarray(store.load(p, "cells"))
    nodes = np.union1d(ids, cells.ravel())
    names = list(PIECE_ARRAYS) + (["fit_degree", "fit_residual"] if harmonic else [])
    arrays = store.gather(nodes, K, names)
    return np.searchsorted(nodes, cells), ghost_flags(np.isin(nodes, ids)), arrays


class SlabMapWriter:
    """Writes an out-of-core run's maps: one piece per slab and U_p value (`write_piece`), then
    the .pvtu indices, sweep.pvd and summary.json (`finish`).

    Parameters
    ----------
    out : Path
    summary : dict
        The run's summary (``columns``, ``up_um``, ``provenance``).
    cfg : SweepConfig
    b_ref : float
        B_ref, T.
    """

    def __init__(self, out: Path, summary: dict, cfg, b_ref: float):
        self.out, self.summary, self.cfg, self.b_ref = Path(out), summary, cfg, float(b_ref)
        self.labels, self.ups = summary["columns"], summary["up_um"]
        self.written = {k: [] for k in range(len(self.labels))}
        self.example = {}
        retire_index(self.out)  # an interrupted write leaves no earlier summary beside new maps

    def write_piece(self, p: int, res: SweepResult, cells, ghost) -> None:
        """Write slab ``p``'s piece of every column's map: ``res`` (its nodes, in the order of
        `read_slab_piece`), ``cells`` and ``ghost`` as that returns them."""
        prov = self.summary["provenance"]
        for k, label in enumerate(self.labels):
            path = self.out / vtu_name(label).removesuffix(".vtu") / f"piece_{p:04d}.vtu"
            data = dict(_point_data(res, k), **{GHOST_ARRAY: ghost})
            fields = map_field_data(self.ups[k], label, self.b_ref, self.cfg, prov, piece=p)
            write_vtu(path, res.fieldmap.points, cells, data, fields)
            self.written[k].append(path)
            self.example[k] = {name: v[:1] for name, v in data.items()}

    def finish(self, K: int) -> None:
        """The .pvtu index of each column, sweep.pvd, the ParaView script and summary.json."""
        prov = self.summary["provenance"]
        htm = self.cfg.mode == "htm"
        entries = []
        for k, label in enumerate(self.labels):
            path = self.out / vtu_name(label).replace(".vtu", ".pvtu")
            write_pvtu(path, self.written[k], self.example[k], provenance=prov)
            entries.append((float(k) if htm else float(self.ups[k]), path))
        write_pvd(self.out / "sweep.pvd", entries, provenance=prov)
        write_paraview_script(self.out)
        self.summary["pieces"] = K
        write_json(self.out / "summary.json", self.summary)


def read_manifest(work: Path) -> dict | None:
    """The manifest of a work folder (``{"key": .., "run": ..}``), or None if it has none."""
    try:
        return json.loads((Path(work) / "manifest.json").read_text())
    except (OSError, ValueError):
        return None


def new_work_dir(work: Path, manifest: dict) -> Path:
    """Replace ``work`` by an empty folder holding only ``manifest.json``."""
    work = Path(work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    write_json(work / "manifest.json", manifest)
    return work


def temp_work_dir(out: Path) -> Path:
    """A fresh temporary work folder inside ``out`` (made if absent)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=SLAB_WORK + ".", dir=out))


def remove_work_dir(work: Path) -> None:
    """Remove a work folder and everything in it (nothing if it is gone)."""
    shutil.rmtree(work, ignore_errors=True)


def open_per_node(path: Path, mode: str = "r") -> np.ndarray:
    """A per-node array file (`make_per_node_file`) as a memory map, ``mode`` "r" or "r+"."""
    return np.lib.format.open_memmap(path, mode)
