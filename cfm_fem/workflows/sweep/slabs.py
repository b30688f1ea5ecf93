"""Out-of-core sweep of maps larger than memory: spatial slabs with a halo, one .pvtu piece each.

``cfm-fem sweep FIELD --slabs K`` (or ``--max-memory SIZE``, which chooses K) runs the sweep of
`cfm_fem.workflows.sweep.problem` without ever holding the whole map, mesh or statistics in memory:

1. **Stage** (`stage`): the input is streamed once (`cfm_fem.io.streaming`, plain tables and
   Opera tables) into a temporary float64 file of rows (x, y, z mm, Bx, By, Bz T) read back as a
   numpy memmap, collecting on the way the bounding box, max |B|, the zero rows, the distinct
   coordinate values per axis (for the grid test) and the scatter matrix (planar maps).
2. **Partition**: K slabs along the longest axis, with equal node counts (histogram of that
   coordinate); each slab file (``.npy``) holds its own rows plus those of a halo of width
   ``h`` on both sides.
3. **Duplicates** are merged per slab as `cfm_fem.models.field.FieldMap.from_arrays` does, and
   each kept row gets the node index the in-memory reader would give it (row minus the dropped rows
   before it), because the random numbers of a node are a function of that index.
4. **Per slab**: the mesh is built on slab + halo (`cfm_fem.models.mesh.build_mesh`, with the
   method decided for the whole map: Kuhn grid or Delaunay), the sweep runs on the slab's own
   nodes only, and the statistics go to disk.
5. **Output**: every U_p value gets a ``.pvtu`` with one ``.vtu`` piece per slab (the cells
   whose highest node the slab owns), ``sweep.pvd`` and ``summary.json``, whose figures are
   merged exactly from per-slab counts and a per-node float64 U_f file on disk (percentiles by
   exact order statistics, `disk_percentiles`).

**Halo rule.** ``h = halo_cells * L + 6 * sigma_max``, with L the largest grid step along the
slab axis (grid) or the mean node spacing (volume / nodes)^(1/3) (Delaunay), ``halo_cells = 4``
by default, and sigma_max the largest U_p times the largest axis scale (mm; mode htm below). It
is checked, not trusted:

- every cell incident to an own node must be *certified*: for a grid, every Kuhn cell of
  slab + halo is a cell of the whole map's triangulation; for Delaunay, a cell is certified when
  its circumsphere stays inside the slab + halo along the slab axis (then no node outside can
  lie in it, so it is a Delaunay cell of the whole map), on the nodes as Delaunay triangulates
  them (`cfm_fem.models.mesh.delaunay_coords`: moved by 1e-6 of the whole map's size, keyed by
  their coordinates, so that the triangulation is unique), and when no node of it is in an
  uncertified cell (a node keeps its move when one of its cells is flat without it: only then
  is that decided as in the whole map). Otherwise h is doubled and the slab rebuilt.
- with ``hull_slivers="remove"``, every slab tests its cells against the whole map's convex
  hull (`hull_points`, so a cell is removed in a slab when the whole map removes it), and the
  removed cells within two rings of cells of an own node must be certified too; the faces they
  leave are the map's border.
- faces through which a walk would leave the certified region (a boundary face of slab + halo
  that is not provably on the map's own hull, or a face towards an uncertified cell) lead to a
  sentinel cell whose field is NaN. A trial that reaches one poisons its node's statistics,
  which are then recomputed with those faces closed (the mesh border): **such trials count as
  outside, never silently as a value**. Their number is in ``summary.json`` (``slabs``,
  ``halo_outside_nodes``) and in a note.

**Equal to the in-memory run.** Own nodes get exactly the numbers of ``cfm-fem sweep`` without
slabs when the triangulation of slab + halo equals the global one around them: always for a
grid (the Kuhn triangulation is local; bit for bit, `tests/test_slabs.py`); for Delaunay, Qhull
orders the vertices of a simplex by its insertion order, so barycentric coordinates are
rounded differently and values agree to ~1e-15 relative, not bit for bit.

**Memory.** Bounded by one slab + halo (map rows, mesh, statistics): the kernel runs on the
slab's own arrays and keys each node's random stream by a hash of its coordinates
(`cfm_fem.workflows.sweep.problem.node_keys`), so the numbers are those of the whole-map run.
What grows with the map lives on disk: the staged rows and the per-node U_f file
(memory-mapped, written once).

**Mode htm.** The halo takes, in place of 6 sigma_max, the bench's largest probe error near
the map (`htm_reach_mm`); nodes key their noise streams by their coordinates as above.

**Resume and workers.** Each slab is a chunk of a `_SlabJob`
(`cfm_fem.workflows.sweep.problem.serial_map`, or
`cfm_fem.workflows.sweep.distributed.dask_chunk_map` on workers that see the work folder: the staged
rows are pickled as their folder). A finished slab writes its arrays, then a done record; a
resumable run (``description`` given) keeps them in ``DIR/.cfm_fem_slabs`` under its key, so an
interrupted run continues from its finished slabs. Records are merged in slab order: the outputs do
not depend on where or in which order the slabs ran.

Limits: 3-D maps of plain or Opera tables; other formats and planar maps are run in memory
(the caller says so; a planar map from its staged rows, `staged_fieldmap`, not read again).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import CfmInputError, CfmInputWarning, check_seed
from ...io.lock import output_lock
from ...io.slab_files import (
    SLAB_WORK,
    SlabStore,
    Staged,
    drop_pages,
    make_per_node_file,
    new_work_dir,
    open_per_node,
    read_manifest,
    remove_work_dir,
    stage,
    staged_fieldmap,
    temp_work_dir,
)
from ...io.sweep_out import (
    remove_earlier_outputs,
)
from ...models.field import FieldMap
from ...models.mesh import (
    build_mesh,
    delaunay_coords,
    morton_order,
)
from ...models.node_weights import node_volumes
from ...models.sweep import (
    HTM_PARTS,
    SweepConfig,
    assemble_result,
    summarize,
    uses_harmonic,
)
from .problem import (
    field_fit_info,
    prepare_sweep,
    serial_map,
    sweep_gradients,
    up_too_large,
    with_bench,
)
from .slab_outputs import (
    disk_percentiles,
    disk_weighted_percentiles,
    merge_slabs,
    write_slab_outputs,
    zero_sums,
)
from .slab_plan import (
    SlabPlan,
    at_cut,
    beyond_boxes,
    certify,
    extract_slab,
    faces_of,
    htm_reach_mm,
    hull_face_ok,
    hull_points,
    lattice_keys,
    merge_duplicates,
    plan_slabs,
    settled,
    slab_search,
    slabs_for_memory,
)

__all__ = [
    "run_slab_sweep",
    "disk_percentiles",
    "disk_weighted_percentiles",
]

#: Default halo: this many cell sizes plus 6 sigma of the largest U_p.
HALO_CELLS = 4.0
#: A slab's halo is doubled for removed hull slivers it cannot certify only while slab + halo
#: holds at most this many times a slab's share of the rows (or `SMALL_SLAB_ROWS`). Surface
#: nodes in degenerate positions (the mantle of a cylinder: generator lines of co-planar nodes)
#: make slivers whose choice depends on nodes anywhere along the map, so no halo short of the
#: whole map certifies them all; beyond the limit, the faces they leave are halo borders.
GONE_ROWS_FACTOR = 2.0
#: Rows a slab + halo may always grow to for those slivers (little memory, and the same
#: numbers as the in-memory run).
SMALL_SLAB_ROWS = 20_000


def run_slab_sweep(
    path,
    cfg: SweepConfig,
    out_dir,
    *,
    n_slabs: int | None = None,
    max_memory: float | None = None,
    fmt: str = "table",
    length_unit=None,
    field_unit=None,
    zero_rows="warn",
    provenance: dict | None = None,
    halo_cells: float = HALO_CELLS,
    log=None,
    progress=None,
    progress_total=None,
    description: dict | None = None,
    resume: bool = False,
    keep: bool = False,
    map_chunks=None,
    flat_map=None,
    remove_stale: bool = True,
) -> dict | None:
    """Out-of-core sweep (module docstring); writes the outputs and returns the summary.

    Parameters
    ----------
    path : path-like
        Plain or Opera table.
    cfg : SweepConfig
        Mode gauss or htm. With ``outside="extrapolate"``, a node whose walks reached the halo
        border of its slab is run again without extrapolation: its trials that left (the map or
        the slab) are left out, and the node has no U_f figure (as by default).
    out_dir : path-like
    n_slabs : int, optional
        K; else from ``max_memory`` (bytes, `slabs_for_memory`).
    fmt : {'table', 'opera'}
    provenance : dict, optional
    halo_cells : float
        Cell sizes in the halo (plus 6 sigma of the largest U_p).
    log : callable(str), optional
        Messages for the user.
    progress : callable(int), optional
        Called with the number of nodes finished: block by block (``cfg.chunk_nodes`` nodes)
        within each slab when the slabs run in this process, slab by slab otherwise; a slab's
        last nodes are reported once it is saved.
    progress_total : callable(int), optional
        Called once with the number of nodes, when it is known (after staging).
    description : dict, optional
        Everything that determines the numbers (`cfm_fem.workflows.sweep.resume.describe_sweep` plus
        the slab options). Given, the work files live in ``out_dir/.cfm_fem_slabs`` under that run's
        key and survive an interruption (not a bad input); else in a temporary folder.
    resume : bool
        Reuse the slabs finished by an interrupted run with the same description; refused,
        naming what differs, for another run.
    keep : bool
        Keep ``out_dir/.cfm_fem_slabs`` after a successful run.
    map_chunks : callable(job, chunks) -> iterable of ((k, k + 1), record), optional
        Runs the slabs (default `cfm_fem.workflows.sweep.problem.serial_map`, one after the other
        here; e.g. `cfm_fem.workflows.sweep.distributed.dask_chunk_map` on workers that share
        ``out_dir``). The outputs do not depend on it.
    flat_map : callable(FieldMap), optional
        Given, a map that is not 3-D is handed to it as read from the staged rows
        (`staged_fieldmap`), so the caller runs it in memory without reading the file again.
    remove_stale : bool
        Once the outputs are complete, remove what an earlier sweep left in ``out_dir`` that
        they do not use (`cfm_fem.io.sweep_out.remove_earlier_outputs`), as
        `cfm_fem.io.sweep_out.write_sweep` does; False leaves them.

    Returns
    -------
    dict or None
        The summary written; None for a map that is not 3-D (the caller then runs in memory).

    Raises
    ------
    CfmInputError
        A seed that is not an integer in [0, 2**63) (`cfm_fem.errors.check_seed`, checked
        before the file is read or ``out_dir`` made), or bad input in the file or options. Or
        another run writes into ``out_dir``: the call holds its lock for the whole run
        (`cfm_fem.io.lock.output_lock`, shared with a caller that holds it), so it never
        removes another run's work folder or maps.
    """
    t0 = time.perf_counter()
    check_seed(cfg.seed)  # the CLI's rule and message, before anything is read or written
    # one run at a time in out_dir: the work folder and an earlier run's maps are removed
    with output_lock(out_dir, option="out_dir"):
        log = log or (lambda s: None)
        out = Path(out_dir)
        if description is None:
            work = temp_work_dir(out)
            resume = keep = False
        else:
            work = _slab_work_dir(out, description, resume)
            resume = resume and any(work.glob("results/slab*/done.json"))
        finished = False
        try:
            st = stage(path, fmt, work, length_unit=length_unit, field_unit=field_unit,
                       zero_rows=zero_rows)  # fmt: skip
            if st.dim != 3:
                if flat_map is not None:
                    flat_map(staged_fieldmap(st, path))
                finished = True
                return None
            summary = _run(st, path, cfg, out, work, n_slabs=n_slabs, max_memory=max_memory,
                           prov=provenance, halo_cells=halo_cells, log=log, progress=progress,
                           t0=t0, resume=resume, map_chunks=map_chunks,
                           progress_total=progress_total)  # fmt: skip
            finished = True
        except CfmInputError:
            finished = True  # bad input: nothing kept
            raise
        finally:  # an interrupted resumable run keeps its finished slabs for --resume
            if description is None or (finished and not keep):
                remove_work_dir(work)
        if remove_stale:  # the new outputs are complete: now the old maps can go
            remove_earlier_outputs(out)
        return summary


def _slab_work_dir(out: Path, description: dict, resume: bool) -> Path:
    """``out/.cfm_fem_slabs`` for this run: the one an interrupted identical run left (resume),
    or a fresh one (an earlier store is replaced). Refuses, naming what differs, to resume a
    store made by another run."""
    from .resume import _differences, run_key

    work = out / SLAB_WORK
    key = run_key(description)
    if resume and work.exists():
        made = read_manifest(work)
        if made is not None and made.get("key") != key:
            raise CfmInputError(
                "cannot resume: the slab store was made by a different run ("
                + _differences(made.get("run", {}), description)
                + "); use the same input and options, or run without --resume to start again",
                file=work,
            )
        if made is not None:
            return work
    return new_work_dir(work, {"key": key, "run": description})


@dataclass
class _Layout:
    """How an out-of-core run cuts its map: the mesh kind and the slabs with their halo."""

    cfg: SweepConfig
    b_ref: float
    sigma: float  # mm: the halo's probe error (std of the largest U_p; htm: its reach / 6)
    n_col: int
    n_slabs: int
    span: float  # mm: the map's longest side
    kind: str  # "grid" or "delaunay"
    grid_shape: tuple | None
    halo_cells: float
    step: float = 0.0  # mm: cell size
    halo: float = 0.0  # mm
    plan: SlabPlan | None = None
    reach: str = ""

    @property
    def htm(self) -> bool:
        return self.cfg.mode == "htm"

    def cut(self, st, step: float) -> None:
        """Slabs of cells of size ``step`` (mm) with the halo they need."""
        self.step = step
        self.halo = self.halo_cells * step + 6.0 * self.sigma
        self.plan = plan_slabs(st, self.n_slabs, self.halo)


def _layout(st, cfg, file, n_slabs, max_memory, halo_cells) -> _Layout:
    """The run's `_Layout` before duplicates are merged (options refused with a
    `CfmInputError` naming ``file``)."""
    n_rows = len(st.rows)
    htm = cfg.mode == "htm"
    b_ref = st.b_max if cfg.b_ref_T is None else float(cfg.b_ref_T)
    extent = float((st.hi - st.lo).min())
    if htm:  # the halo takes "6 sigma" = the bench's largest probe error near the map
        cfg = with_bench(cfg)
        sigma = htm_reach_mm(cfg.bench, cfg.trials, cfg.seed, st.lo, st.hi) / 6.0
    else:
        sigma = max(cfg.up_um) * 1e-3 * max(cfg.axis_scale)
    if not htm and sigma * 5.0 > extent:
        raise CfmInputError(up_too_large(cfg, extent), file=file)
    n_col = len(HTM_PARTS) if htm else len(cfg.up_um)
    if n_slabs is None:
        n_slabs = slabs_for_memory(n_rows, max_memory, n_col)
    n_slabs = max(1, min(int(n_slabs), n_rows // 8 or 1))
    span = float((st.hi - st.lo).max())
    axis = int(np.argmax(st.hi - st.lo))
    # interpolation decided for the whole map, as build_mesh would on all nodes
    keys = None
    if cfg.interpolation in ("auto", "grid") and all(d is not None for d in st.distinct):
        keys = [np.unique(lattice_keys(d, span)) for d in st.distinct]
    kind = cfg.interpolation
    if kind == "native":
        raise CfmInputError("--interpolation native needs tetrahedra in the export; this map has "
                            "none", file=file)  # fmt: skip
    grid_shape = None if keys is None else tuple(len(k) for k in keys)
    if kind in ("auto", "grid"):
        kind = "grid" if grid_shape is not None and min(grid_shape) >= 2 else "delaunay"
    lay = _Layout(
        cfg=cfg,
        b_ref=b_ref,
        sigma=sigma,
        n_col=n_col,
        n_slabs=n_slabs,
        span=span,
        kind=kind,
        grid_shape=grid_shape,
        halo_cells=halo_cells,
        reach="the bench's largest probe error" if htm else "6 sigma of the largest U_p",
    )
    if kind == "grid":
        lay.cut(st, float(np.diff(keys[axis]).max()) * span * 1e-9)
    else:
        lay.cut(st, float(np.prod(st.hi - st.lo) / n_rows) ** (1.0 / 3.0))
    return lay


def _merge_duplicates(st, lay: _Layout, file, log):
    """Pass A over the slabs: duplicate rows merged (and the grid test: one node per lattice
    point); a sparse grid under ``--interpolation auto`` becomes Delaunay (``lay`` re-cut).

    Returns
    -------
    dropped : ndarray, int64
        Rows merged into an earlier one.
    notes : list of str
    """
    n_rows = len(st.rows)
    log(f"slabs: {lay.plan.n_slabs} along {'xyz'[lay.plan.axis]}, halo {lay.halo:.4g} mm "
        f"({lay.halo_cells:g} cells of {lay.step:.4g} mm + {lay.reach}, "
        f"{6 * lay.sigma * 1e3:.4g} um); {n_rows} rows staged")  # fmt: skip
    dropped = []
    for k in range(lay.plan.n_slabs):
        rows, _ = extract_slab(st, lay.plan, k, 1e-6)  # a group split by an edge is seen by both
        dropped.append(merge_duplicates(st, rows, file))
        st.release()
    dropped = np.unique(np.concatenate(dropped)) if dropped else np.empty(0, np.int64)
    n = n_rows - len(dropped)
    notes = list(st.notes)
    if len(dropped):
        msg = f"{file}: merged {len(dropped)} duplicate node(s) with identical position and field"
        warnings.warn(msg, CfmInputWarning, stacklevel=4)
        notes.append(msg)
    auto = lay.cfg.interpolation == "auto"
    if lay.kind == "grid" and auto and np.prod(lay.grid_shape, dtype=float) > 4.0 * n:
        lay.kind = "delaunay"
        lay.cut(st, float(np.prod(st.hi - st.lo) / n_rows) ** (1.0 / 3.0))
    if lay.kind == "grid":
        missing = int(np.prod(lay.grid_shape)) - n
        if missing:
            notes.append(f"nodes on a rectilinear grid with {missing} grid point(s) missing: "
                         "cells touching a missing point are left out, not bridged")  # fmt: skip
    return dropped, notes


def _run_slabs(job, store, K, resume, map_chunks, progress, log):
    """Run every slab not finished by an interrupted run; returns ({slab: record}, number of
    slabs taken from that run)."""
    records = {}
    for k in range(K):
        record = store.done(k) if resume else None
        if record is not None:  # finished by an interrupted run with the same key
            records[k] = record
            if progress is not None:
                progress(record["nodes"])
    reused = len(records)
    todo = [(k, k + 1) for k in range(K) if k not in records]
    for (k, _), record in (map_chunks or serial_map)(job, todo):
        for m in record["log"]:
            log(m)
        records[k] = record
        if progress is not None:  # the rest of the slab's nodes, now that it is saved
            early = 0 if job.progress is None else _reported_early(record["nodes"],
                                                                   job.cfg.chunk_nodes)  # fmt: skip
            progress(record["nodes"] - early)
    return records, reused


def _run(st, path, cfg, out, work, *, n_slabs, max_memory, prov, halo_cells, log, progress, t0,
         resume=False, map_chunks=None, progress_total=None):  # fmt: skip
    """The out-of-core run once staged: layout, duplicates, slabs, summary and outputs."""
    file = str(path)
    lay = _layout(st, cfg, file, n_slabs, max_memory, halo_cells)
    cfg = lay.cfg
    dropped, notes = _merge_duplicates(st, lay, file, log)
    n = len(st.rows) - len(dropped)
    # the whole map's hull: a slab removes the hull slivers the whole map removes
    hull = hull_points(st) if lay.kind == "delaunay" and cfg.hull_slivers == "remove" else None
    store = SlabStore(work / "results")
    harmonic = uses_harmonic(cfg.field_model, 3)  # slabs cut 3-D maps only
    for name, dtype, cols in (("uf", np.float64, lay.n_col), ("complete", np.bool_, lay.n_col),
                              ("volume", np.float64, 1), ("e2", np.float64, lay.n_col),
                              ("fit", np.float64, 2)):  # fmt: skip
        if name not in ("e2", "fit") or (lay.htm if name == "e2" else harmonic):
            make_per_node_file(work / f"{name}.npy", dtype, (n, cols), resume)
    job = _SlabJob(st=st, plan=lay.plan, dropped=dropped, cfg=cfg, file=file, kind=lay.kind,
                   halo=lay.halo, b_ref=lay.b_ref, n_col=lay.n_col, htm=lay.htm, span=lay.span,
                   work=work, hull=hull)  # fmt: skip
    if map_chunks is None:  # slabs run here: progress block by block within each slab
        job.progress = progress
    if progress_total is not None:
        progress_total(n)
    K = lay.plan.n_slabs
    records, reused = _run_slabs(job, store, K, resume, map_chunks, progress, log)
    summary = merge_slabs(records, K, work, lay, n, notes, file)
    if reused:
        summary["notes"].append(f"resumed: {reused} of {K} slabs taken from the interrupted run")
    summary["seconds"] = time.perf_counter() - t0
    summary["provenance"] = prov or {}
    write_slab_outputs(out, store, K, cfg, lay.b_ref, summary)
    return summary


@dataclass
class _SlabJob:
    """One out-of-core run's slabs as chunks: picklable (the staged rows travel as their file
    paths), so slabs run in this process or on Dask workers that share the work folder."""

    st: Staged
    plan: SlabPlan
    dropped: np.ndarray
    cfg: SweepConfig
    file: str
    kind: str
    halo: float
    b_ref: float
    n_col: int
    htm: bool
    span: float
    work: Path
    hull: np.ndarray | None = None  # hull slivers removed: the whole map's hull vertices (k, 3)
    #: Called with the number of own nodes finished, block by block (`_run_blocks`); set only
    #: when the slabs run in this process, never pickled.
    progress: object = None

    def __getstate__(self):
        return dict(self.__dict__, progress=None)

    def per_node(self, name: str):
        """The per-node file ``name`` (uf, complete, e2) of the run, mapped read-write."""
        return open_per_node(self.work / f"{name}.npy", "r+")

    def _certified_slab(self, k: int, messages: list):
        """Slab k with a halo wide enough that every cell of an own node is certified (or the
        halo reached the map's ends): its rows, map, mesh and certification flags. Appends a
        message per widening to ``messages``."""
        st, plan, dropped, file = self.st, self.plan, self.dropped, self.file
        kind, span, cfg = self.kind, self.span, self.cfg
        h = self.halo
        limit = max(GONE_ROWS_FACTOR * len(st.rows) / plan.n_slabs, SMALL_SLAB_ROWS)
        while True:
            rows, own = extract_slab(st, plan, k, h)
            keep = ~np.isin(rows, dropped)
            rows, own = rows[keep], own[keep]
            ids = rows - np.searchsorted(dropped, rows)
            pts = np.array(st.rows[rows, :3])
            B = np.array(st.rows[rows, 3:])
            lfm = FieldMap(points=pts, B=B, source=file, lines=np.array(st.lines[rows]))
            st.release()
            mesh = build_mesh(lfm, kind, cfg.hull_slivers, self.hull, jitter_span=span)
            gone = mesh.hull_slivers
            boxes = beyond_boxes(st, plan.axis, plan.edges[k] - h, plan.edges[k + 1] + h)
            if kind == "grid":  # the Kuhn triangulation is local: every cell is the map's own
                cert = np.ones(len(mesh.simplices), dtype=bool)
                cert_gone = np.ones(0, dtype=bool)
            else:  # the removed hull slivers too: where the map ends around own nodes
                both = np.concatenate([mesh.simplices, gone])
                moved = delaunay_coords(pts, span)  # 3-D: the mesh frame is the map frame
                cert, cert_gone = np.split(certify(st, plan, k, h, moved, both, boxes, span),
                                           [len(mesh.simplices)])  # fmt: skip
                cert &= settled(mesh.simplices, cert)[mesh.simplices].all(axis=1)
            own_cells = own[mesh.simplices].any(axis=1)
            # removed cells a walk from an own node can meet: two rings of cells around it
            near = own.copy()
            for _ in range(2):
                near[mesh.simplices[near[mesh.simplices].any(axis=1)]] = True
            own_ok = cert[own_cells].all()
            gone_bad = int((~cert_gone[near[gone].any(axis=1)]).sum())
            if own_ok and gone_bad == 0 or not boxes:
                break
            if own_ok:  # only removed slivers left: widen while slab + halo stays in the limit
                wider = len(extract_slab(st, plan, k, 2.0 * h)[0])
                st.release()
                if wider > limit:
                    messages.append(
                        f"slab {k}: {gone_bad} removed hull sliver(s) near its nodes could not be "
                        f"certified with a halo of {h:.4g} mm (surface nodes in degenerate "
                        "positions, e.g. co-planar on a cylinder's mantle); trials reaching the "
                        "faces they leave are counted at the halo border"
                    )
                    break
            h *= 2.0
            why = "a cell of an own node" if not own_ok else "a removed hull sliver near one"
            messages.append(f"slab {k}: halo widened to {h:.4g} mm ({why} was not certified)")
        return own, ids, pts, B, lfm, mesh, gone, boxes, cert, cert_gone

    def run_chunk(self, a: int, b: int) -> dict:
        """Sweep slab a (b = a + 1: the chunk interface of
        `cfm_fem.workflows.sweep.problem.serial_map` and
        `cfm_fem.workflows.sweep.distributed.dask_chunk_map`), store its arrays and done record,
        return it."""
        k = int(a)
        st, plan, cfg, file = self.st, self.plan, self.cfg, self.file
        kind, b_ref, n_col, htm, span = self.kind, self.b_ref, self.n_col, self.htm, self.span
        store = SlabStore(self.work / "results")
        sums = zero_sums(n_col)
        messages = []
        own, ids, pts, B, lfm, mesh, gone, boxes, cert, cert_gone = self._certified_slab(
            k, messages
        )
        # per-slab notes left out: grid gaps, strokes, hull slivers and flat cells of
        # co-spherical nodes are counted over slabs
        counted = ("grid point", "outside the strokes", "Delaunay hull", "co-spherical")
        mesh_notes = [m for m in mesh.notes if not any(c in m for c in counted)]
        lcfg = dataclasses.replace(cfg, b_ref_T=b_ref)
        mesh, problem, _ = prepare_sweep(lfm, lcfg, mesh)
        gp, start_l, nb_b, search_b = _sentinel_problem(
            problem, mesh, cert, gone, cert_gone, boxes=boxes, plan=plan, st=st, kind=kind,
            span=span, nl=len(ids),
        )  # fmt: skip
        own_ids = ids[own]
        own_local = np.flatnonzero(own)
        own_keys = problem.keys[own_local]  # hashes of the coordinates, as the whole map's
        stats, n_out, n_lost, star, pos = _run_blocks(gp, own_local, own_keys, cfg.chunk_nodes,
                                                      self.progress)  # fmt: skip
        lost_all = (n_out + n_lost) >= cfg.trials
        skipped = start_l[own_local, 0] < 0  # in no cell, or out of the bench's strokes: NaN
        hit = (np.isnan(stats[..., :2]).any(axis=(2, 3)) & ~lost_all).any(axis=1) & ~skipped
        n_left = n_out.copy() if cfg.outside == "exclude" else np.zeros_like(n_out)
        if hit.any():  # a halo border is not the map's surface: never extrapolated across
            no_exit = np.empty((0,) + gp.exit_grad.shape[1:])
            redo = dataclasses.replace(gp, neighbors=nb_b, exit_grad=no_exit,
                                       search=search_b).run_nodes(own_local[hit],
                                                                  keys=own_keys[hit])  # fmt: skip
            first_out = n_out[hit]
            stats[hit], n_out[hit], n_lost[hit], star[hit], pos[hit] = redo
            n_left[hit] = n_out[hit]
            # a node with one trial left has NaN statistics too: it reached the halo only if
            # the closed faces turned trials into outside ones
            sums["halo_nodes"] += int((n_out[hit] > first_out).any(axis=1).sum())
        del start_l, gp
        grad = sweep_gradients(mesh, lfm.B, problem.harmonic)[own]
        fit = field_fit_info(problem.harmonic)
        fit_box = None
        if fit is not None:  # degree and residual per node; the box of the linear ones
            fit = {key: v[own] if isinstance(v, np.ndarray) else v for key, v in fit.items()}
            fit_all = self.per_node("fit")
            fit_all[own_ids] = np.c_[fit["degree"], fit["residual_T"]]
            fit_all.flush()
            del fit_all
            lin = pts[own][fit["degree"] == 0]
            fit_box = [lin.min(axis=0).tolist(), lin.max(axis=0).tolist()] if len(lin) else None
        sub = FieldMap(points=pts[own], B=B[own], source=file)
        if htm:
            q_own = cfg.bench.axis_positions_for(pts[own])
            sums["unreachable"] += int(cfg.bench.outside_stroke(q_own).sum())
            e2_all = self.per_node("e2")
            e2_all[own_ids] = (pos[:, :, 0] ** 2).sum(-1) + (pos[:, :, 1] ** 2).sum(-1)
            e2_all.flush()
            del e2_all
        volume = node_volumes(mesh)[0][own]  # the halo holds every cell around an own node
        res = assemble_result(sub, mesh, cfg, b_ref, (stats, n_out, n_lost, star,
                              pos if htm else None), grad, n_left_out=n_left, field_fit=fit,
                              node_volume_mm3=volume)  # fmt: skip
        uf, complete = res.uf_units(), res.complete()
        uf_all, ok_all = self.per_node("uf"), self.per_node("complete")
        vol_all = self.per_node("volume")
        uf_all[own_ids], ok_all[own_ids], vol_all[own_ids, 0] = uf, complete, volume
        for arr in (uf_all, ok_all, vol_all):  # written through; keep RSS at one slab
            arr.flush()
            drop_pages(getattr(arr, "_mmap", None))  # numpy's memmap keeps its mmap here
        processed = (n_out + n_lost > 0).any(axis=1) | np.isfinite(stats[:, :, 3, 1]).any(axis=1)
        sums["processed"] += int(processed.sum())
        sums["star"] += int(star[processed].sum())
        sums["n_out"] += n_out.sum(axis=0)
        sums["n_lost"] += n_lost.sum(axis=0)
        for c in range(n_col):
            sums["dis"][c] += res.gum_check(c)[2][complete[:, c]].sum(axis=0)
        # cells drawn by this slab's piece: certified, highest node owned here
        cells = mesh.simplices[cert]
        top = cells.max(axis=1)  # local indices increase with node ids
        cells = ids[cells[own[top]]]
        sums["cells"] += len(cells)
        if mesh.tie_nodes is not None:  # own nodes that keep their Delaunay move
            sums["ties"] += int(mesh.tie_nodes[own].sum())
        if len(gone):  # counted, like the piece's cells, by their highest node
            sums["slivers"] += int(own[gone[cert_gone].max(axis=1)].sum())
        store.save(k, ids=own_ids, points=pts[own], B=B[own], stats=stats, n_out=n_out,
                   n_lost=n_lost, n_left=n_left, star=star, gradient=grad, pos=pos,
                   cells=cells, volume=volume, **_fit_arrays(fit))  # fmt: skip
        record = {"sums": {key: np.asarray(v).tolist() for key, v in sums.items()},
                  "mesh_notes": mesh_notes, "template": summarize(res), "nodes": len(own_ids),
                  "log": messages, "fit_box": fit_box}  # fmt: skip
        store.mark_done(k, record)
        return record


def _fit_arrays(fit) -> dict:
    """The per-node harmonic-fit arrays a slab stores (none for the linear model)."""
    if fit is None:
        return {}
    return {"fit_degree": fit["degree"], "fit_residual": fit["residual_T"]}


def _sentinel_problem(problem, mesh, cert, gone, cert_gone, *, boxes, plan, st, kind, span, nl):
    """The slab's problem with a sentinel node (NaN field) and cell (zero transform) that
    suspect faces lead to: faces to an uncertified cell, or border faces not provably on the
    map's hull.

    Returns
    -------
    gp : SweepProblem
        Walks through a suspect face reach the sentinel (their trials poison the node).
    start_l : ndarray
        Start cells of the slab's nodes and the sentinel.
    nb_b, search_b
        Neighbours and search arrays with the suspect faces closed (the mesh border).
    """
    # suspect faces: to an uncertified cell, or a border face not provably on the map's hull
    nb = mesh.neighbors
    m, dp1 = nb.shape
    suspect = np.zeros_like(nb, dtype=bool)
    suspect[nb >= 0] = ~cert[nb[nb >= 0]]
    s_idx, j_idx = np.nonzero(nb < 0)
    hull = hull_face_ok(mesh.coords, mesh.simplices, s_idx, j_idx, boxes, 1e-9 * span)
    hull |= faces_of(mesh.simplices, s_idx, j_idx, gone[cert_gone])  # left by removal
    if kind == "grid":  # a notch or a gap of the grid: border faces off the cut planes
        hull |= ~at_cut(mesh.coords, mesh.simplices, s_idx, j_idx, plan.axis,
                         st.lo[plan.axis], st.hi[plan.axis], 1e-9 * span)  # fmt: skip
    suspect[s_idx[~hull], j_idx[~hull]] = True
    suspect[~cert] = False  # never entered
    # the slab's own arrays plus a sentinel node (NaN field) and cell (zero transform) that
    # suspect faces lead to
    coords_l = np.concatenate([problem.coords, np.zeros((1, problem.coords.shape[1]))])
    values_l = np.concatenate([problem.values, np.full((1, 3), np.nan)])
    start_l = np.concatenate([problem.start_cells,
                              np.full((1, problem.start_cells.shape[1]), -1)])  # fmt: skip
    search_a, search_b, unc = slab_search(problem.search, cert)
    simp = np.concatenate([problem.simplices, np.full((1 + len(unc), dp1), nl)])
    simp = simp.astype(np.int64)
    trans = np.concatenate([problem.transform, np.zeros((1, dp1, dp1 - 1)),
                            problem.transform[unc]])  # fmt: skip
    nb_a = np.concatenate([np.where(suspect, m, nb), np.full((1 + len(unc), dp1), -1)])
    nb_b = np.concatenate([np.where(suspect, -1, nb), np.full((1 + len(unc), dp1), -1)])
    gp = dataclasses.replace(problem, coords=coords_l, values=values_l, simplices=simp,
                             transform=trans, neighbors=nb_a, start_cells=start_l,
                             search=search_a)  # fmt: skip
    return gp, start_l, nb_b, search_b


def _run_blocks(problem, nodes, keys, block: int, progress=None):
    """``problem.run_nodes(nodes, keys=keys)``, by blocks of ``block`` nodes when there is a
    ``progress`` to report to: it is called with each block's node count but the last one's,
    which the caller reports once the slab is saved (`_reported_early`), so progress never
    counts a slab as done before it can be resumed from.

    The same numbers either way (a node's depend on its key only); the blocks are runs of the
    Z-order curve over ``nodes``, the order `SweepProblem.run_nodes` visits them in, so each
    block keeps its neighbours' cells in cache as one call would.
    """
    if progress is None or len(nodes) <= block:
        return problem.run_nodes(nodes, keys=keys)
    order = morton_order(problem.coords[nodes])
    parts = []
    for a in range(0, len(nodes), block):
        sel = order[a : a + block]
        parts.append(problem.run_nodes(nodes[sel], keys=keys[sel]))
        if a + block < len(nodes):
            progress(len(sel))
    back = np.empty_like(order)
    back[order] = np.arange(len(order))
    return tuple(np.concatenate(arrays)[back] for arrays in zip(*parts, strict=True))


def _reported_early(nodes: int, block: int) -> int:
    """Nodes of a slab of ``nodes`` own nodes that `_run_blocks` reported before it ended."""
    return block * ((nodes - 1) // block) if nodes > 0 else 0
