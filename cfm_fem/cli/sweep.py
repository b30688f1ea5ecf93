"""Per-node field uncertainty U_f of an FEM map for a sweep of positioning uncertainties U_p.

Writes DIR/uf_up<U_p>um.vtu per U_p value, DIR/sweep.pvd (open it in ParaView; U_p is the time
axis), DIR/open_in_paraview.py (pvpython: the slice through the axis at the largest U_p, nodes
with a U_f figure), DIR/summary.json (U_f percentiles weighted by the volume each node stands
for, over the map or --region) and DIR/report.html (design curve, slices, histograms, GUM
flags); --table csv adds DIR/nodes.csv, one row per node. Maps an
earlier sweep left in DIR that this run does not write (other U_p values, pieces instead of one
file or the reverse) are removed once the new outputs are complete, and named on stderr; files a
sweep did not write are never deleted.
"""

from __future__ import annotations

import math
import sys
import textwrap
from pathlib import Path

from ..errors import CfmInputError
from . import interrupted, option_type
from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import progress_bar
from ._reader import add_reader_args, reader_kwargs

#: Most U_p values one sweep accepts (a typo such as 0:50:0.001 would otherwise ask for 50,001
#: maps and exhaust the memory before anything is computed).
MAX_UP_VALUES = 1000

NAME = "sweep"
HELP = "U_f maps (95 %%) of a field map for a sweep of U_p; VTK output for ParaView"


def _triplet(text):
    from ._checks import number_list

    v = number_list(text, "--axis-scale", (1, 3))
    return tuple(v * 3 if len(v) == 1 else v)


def add_args(p):
    p.add_argument(
        "field",
        metavar="FIELD",
        help="field map: .vtu/.vtk/.msh/..., COMSOL .txt, Opera .table, .csv",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--up",
        metavar="START:STOP:STEP",
        help="U_p values in um, STOP included, or a comma list (default 0:50:10; mode gauss)",
    )
    p.add_argument(
        "--trials",
        type=trial_count_type(),
        default=10000,
        metavar="N",
        help="trials per node and U_p (default 10000)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument(
        "--mode",
        choices=["gauss", "htm"],
        default="gauss",
        help="gauss: N(0, U_p) per coordinate (paper eq. 16); htm: bench kinematic model",
    )
    p.add_argument("--bench", metavar="B.toml", help="bench description (mode htm)")
    p.add_argument(
        "--b-ref",
        type=float,
        metavar="T",
        help="reference field for units (default: max |B| over the nodes of --region, or "
        "of the map)",
    )
    p.add_argument(
        "--axis-scale",
        type=option_type(_triplet, "--axis-scale"),
        metavar="SX,SY,SZ",
        help="per-axis multiplier of U_p (default 1,1,1: isotropic; mode gauss)",
    )
    p.add_argument(
        "--interpolation",
        choices=["auto", "native", "grid", "delaunay"],
        default="auto",
        help="auto: the export's cells if any, Kuhn triangulation of a grid, else Delaunay",
    )
    p.add_argument(
        "--field-model",
        choices=["auto", "linear", "harmonic"],  # models.sweep.FIELD_MODELS; --help stays fast
        default="auto",
        help="the field between nodes: per node a least-squares fit of a harmonic potential's "
        "gradient (div B = curl B = 0) to its nearest nodes, right where the field bends (3-D "
        "maps; nodes where the fit shows Laplace's equation violated keep the linear model), or "
        "linear interpolation in the mesh's cells; auto (default): harmonic on a 3-D map, "
        "linear on a planar one",
    )
    p.add_argument(
        "--outside",
        choices=["exclude", "extrapolate"],
        default="exclude",
        help="trials whose perturbed position leaves the map: exclude them from the node's "
        "statistics (the node gets no U_f figure; default), or give them the node's first-order "
        "Taylor expansion B + grad B . delta (surface nodes keep every trial); counted in "
        "outside_fraction either way",
    )
    p.add_argument(
        "--hull-slivers",
        choices=["keep", "remove"],  # interpolation.HULL_SLIVERS; not imported: --help stays fast
        default="remove",
        help="scattered maps (Delaunay): remove the flat cells that line the convex hull "
        "(default; trials in a removed cell count as outside), or keep them: their interpolant "
        "is far off the field, and so are U_f and the gradient of the nodes on the hull",
    )
    p.add_argument(
        "--chunk-nodes",
        type=int,
        default=20000,
        metavar="K",
        help="nodes per chunk (memory/progress; results do not depend on it)",
    )
    add_scale_out_args(p)
    p.add_argument(
        "--resume",
        action="store_true",
        help="reuse the finished chunks of an interrupted run with the same input and options "
        "(kept in DIR/.cfm_fem_chunks, or DIR/.cfm_fem_slabs with --slabs); refused, naming "
        "what differs, if they do not match",
    )
    p.add_argument(
        "--keep-chunks",
        action="store_true",
        help="keep DIR/.cfm_fem_chunks (DIR/.cfm_fem_slabs) after a successful run (deleted by "
        "default)",
    )
    p.add_argument(
        "--pieces",
        type=int,
        metavar="K",
        help="write each U_p map as K .vtu pieces and a .pvtu index (ParaView opens it as one "
        "map), holding one piece's statistics in memory at a time; for maps whose statistics "
        "do not fit in memory",
    )
    p.add_argument(
        "--region",
        type=option_type(_region, "--region"),
        metavar="XMIN:XMAX,YMIN:YMAX,ZMIN:ZMAX|cylinder:R,ZMIN:ZMAX",
        help="region of interest, mm: a box, or a cylinder of radius R about the z axis over a "
        "z range (an empty end is unbounded, e.g. cylinder:7,-30:30); the U_f percentiles of "
        "summary.json are over its nodes and B_ref defaults to the largest |B| in it; the maps "
        "cover every node and flag the region's (in_region)",
    )
    p.add_argument(
        "--table",
        choices=["csv", "parquet"],  # io.sweep_table.TABLE_FORMATS; --help stays fast
        help="also write DIR/nodes.csv (or nodes.parquet, which needs pyarrow): one row per "
        "node with x, y, z, node volume, and U_f and the |B| statistics per U_p",
    )
    add_slab_args(p)  # maps larger than memory
    add_reader_args(p)


def _region(text):
    from ..models.region import parse_region

    return parse_region(text)


def add_slab_args(p):
    """``--slabs`` and ``--max-memory``: the out-of-core path of `cfm_fem.workflows.sweep.slabs`."""
    p.add_argument(
        "--slabs",
        type=int,
        metavar="K",
        help="maps larger than memory: stream the file (CSV/blank table or Opera .table) into K "
        "slabs along the longest axis and sweep one slab (plus a halo) at a time; each U_p map "
        "is a .pvtu of K pieces. Other formats are read whole (said so) and written as pieces",
    )
    p.add_argument(
        "--max-memory",
        metavar="SIZE",
        help="choose the number of slabs for this memory budget (e.g. 2G, 500M)",
    )


def _size(text) -> float:
    """'2G', '500M', '1.5GB', '800000000' to bytes."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(t[-1:], 1)
    try:
        v = float(t[:-1] if t[-1:] in "KMGT" else t) * mult
    except ValueError:
        v = -1.0
    if not (v > 0 and v < float("inf")):
        raise CfmInputError(f"--max-memory must be a size such as 2G or 500M; got {text!r}")
    return v


def _remove_stale_maps(out) -> None:
    """After a successful run: remove the maps of an earlier run in ``out`` that this run does
    not use (`cfm_fem.io.sweep_out.remove_stale_maps`: only files a sweep wrote), and the
    temporaries a killed run left (`cfm_fem.io.sweep_out.remove_leftover_temporaries`), and
    say so. The writers leave these to it (``remove_stale=False``): it names them."""
    from ..io.sweep_out import remove_earlier_outputs

    temps, removed, kept = remove_earlier_outputs(out)
    if temps:
        shown = ", ".join(temps[:3]) + (", ..." if len(temps) > 3 else "")
        print(f"cfm-fem sweep: removed {len(temps)} leftover temporary file(s) of an interrupted "
              f"run from {out}: {shown}", file=sys.stderr)  # fmt: skip
    if removed:
        pieces, items = {}, []
        for r in removed:
            top, _, rest = r.partition("/")
            if not rest and not r.endswith("/"):
                items.append(top)
            elif rest:
                pieces[top] = pieces.get(top, 0) + 1
        for top, n in pieces.items():
            gone = f"{top}/" in removed
            items.append(f"{top}/ ({n} piece(s){', folder removed' if gone else ''})")
        n_files = sum(not r.endswith("/") for r in removed)
        print(f"cfm-fem sweep: removed {n_files} map file(s) of an earlier run from {out} that "
              f"are not part of this run (sweep.pvd does not name them): "
              f"{', '.join(items)}", file=sys.stderr)  # fmt: skip
    if kept:
        print(f"cfm-fem sweep: note: left in {out}: {', '.join(kept)}: named like a map, but "
              "not part of this run and not written by cfm-fem sweep", file=sys.stderr)  # fmt: skip


def _check_slab_options(args) -> None:
    """The checks of ``--slabs`` / ``--max-memory`` that need no file, before any output."""
    if args.slabs is not None and args.slabs < 1:
        raise CfmInputError(f"--slabs must be >= 1; got {args.slabs}")
    if args.max_memory:
        _size(args.max_memory)
    if args.pieces:
        raise CfmInputError("--slabs/--max-memory cannot be combined with --pieces (slabs are "
                            "written as pieces already)")  # fmt: skip
    if args.region is not None:
        raise CfmInputError("--region cannot be combined with --slabs/--max-memory (the "
                            "out-of-core run summarises every node); leave one out")  # fmt: skip


def _run_slabs(args, up):
    """Dispatch of ``--slabs`` / ``--max-memory``: (exit code, None), or (None, the map or
    None) when the map must be run in memory (a map that is not 3-D comes back as read while
    staging: the file is read, and its warnings given, once). Options checked
    (`_check_slab_options`); the caller holds the lock of ``--out``, and a run that fails
    leaves the folder as it was (`cfm_fem.io.lock.output_lock`)."""
    from ..io.provenance import bench_input, file_sha256, provenance
    from ..io.streaming import is_streamable
    from ..models.sweep import SweepConfig
    from ..workflows.sweep.distributed import dask_chunk_map, dask_client
    from ..workflows.sweep.resume import describe_sweep
    from ..workflows.sweep.slabs import SLAB_WORK, run_slab_sweep

    budget = _size(args.max_memory) if args.max_memory else None
    kind = is_streamable(args.field, args.fmt)
    if kind is not None:  # the streaming readers bypass read_field: refuse its way
        from ..io import check_solution

        check_solution(args.field, kind, args.solution)
    if kind is None:
        print(
            f"cfm-fem sweep: {args.field} is not a plain or Opera table: it is read whole "
            "(not streamed) and the statistics are written as pieces",
            file=sys.stderr,
        )
        return None, None
    bench = None
    if args.mode == "htm":
        from ..io.bench_toml import read_bench, read_reference_bench

        bench = read_bench(args.bench) if args.bench else read_reference_bench()
    cfg = SweepConfig(up_um=up, trials=args.trials, seed=args.seed, axis_scale=args.axis_scale,
                      b_ref_T=args.b_ref, interpolation=args.interpolation, mode=args.mode,
                      bench=bench, chunk_nodes=args.chunk_nodes, outside=args.outside,
                      hull_slivers=args.hull_slivers, field_model=args.field_model)  # fmt: skip
    bench_entry = bench_input(args.bench) if cfg.mode == "htm" else None  # packaged or given
    prov = provenance({"field": args.field, "bench": bench_entry}, args.command_line)
    prov.update(seed=cfg.seed, trials=cfg.trials, backend="this process, slabs (out of core)")
    what = (f"U_p = {', '.join(f'{u:g}' for u in up)} um" if cfg.mode == "gauss" else
            f"mode htm: bench model {args.bench or '(packaged CFM reference bench)'}")  # fmt: skip
    print(f"cfm-fem sweep: streaming {args.field} ({kind}) into slabs; {what}; {cfg.trials} "
          f"trials per node, seed {cfg.seed}", file=sys.stderr)  # fmt: skip
    _note_compile(cfg)
    description = describe_sweep(cfg, file_sha256(args.field), reader_kwargs(args),
                                 bench_entry and bench_entry["sha256"])  # fmt: skip
    description.update(slabs=args.slabs, max_memory=args.max_memory)
    flat = []  # a map that is not 3-D, as staged (run in memory, not read again)
    try:
        with dask_client(args.scheduler, args.workers) as client:
            if client is not None:  # the workers map the staged rows in DIR: a shared folder
                prov["backend"] = _backend(args) + ", slabs (out of core)"
            # the node count is known only once the file is staged (inside run_slab_sweep),
            # which then sets the bar's total; it advances by blocks of --chunk-nodes nodes
            # within each slab (slab by slab on Dask workers); messages go above it
            # (tqdm's write), not into its line
            with progress_bar(None, "nodes") as bar:

                def set_total(n, bar=bar):
                    bar.total = n
                    bar.refresh()

                summary = run_slab_sweep(
                    args.field, cfg, args.out, n_slabs=args.slabs, max_memory=budget, fmt=kind,
                    length_unit=args.length_unit, field_unit=args.field_unit,
                    zero_rows=args.zero_rows, provenance=prov,
                    log=lambda m: bar.write(f"cfm-fem sweep: {m}", file=sys.stderr),
                    progress=bar.update, progress_total=set_total, description=description,
                    resume=args.resume,
                    keep=args.keep_chunks,
                    map_chunks=None if client is None else dask_chunk_map(client),
                    flat_map=flat.append,
                    remove_stale=False,  # removed below, and named
                )  # fmt: skip
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted(exc):
            raise
        store = Path(args.out) / SLAB_WORK
        done = len(list(store.glob("results/slab*/done.json")))
        if done:
            print(f"cfm-fem sweep: {done} finished slab(s) kept in {store}; run the same "
                  "command with --resume to continue", file=sys.stderr)  # fmt: skip
        raise KeyboardInterrupt from None  # numba wraps a Ctrl-C in a SystemError
    if summary is None:
        print("cfm-fem sweep: the map is not 3-D: run in memory", file=sys.stderr)
        return None, (flat[0] if flat else None)
    _remove_stale_maps(args.out)  # the new outputs are complete: now the old maps can go
    _finish(args, summary)
    return 0, None


def add_scale_out_args(p):
    """``--scheduler`` and ``--workers`` (shared with ``kinematics``)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run on a running Dask cluster (pip install 'cfm_fem[dask]'); same numbers",
    )
    g.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="start a local Dask cluster of N worker processes for the run; same numbers",
    )


def parse_up_range(text: str) -> list[float]:
    """Parse ``START:STOP:STEP`` (STOP included) or a comma list of U_p values in um; at most
    MAX_UP_VALUES of them (a range is counted before it is expanded: a typo such as 0:50:1e-9
    must not exhaust the memory)."""
    bad = CfmInputError(
        f"--up must be START:STOP:STEP with STEP > 0 or a comma list of um; got {text!r}"
    )
    try:
        parts = [float(v) for v in text.split(":" if ":" in text else ",")]
    except ValueError:
        raise bad from None
    if ":" in text:
        if len(parts) != 3 or not (parts[2] > 0 and parts[1] >= parts[0]):
            raise bad
        start, stop, step = parts
        count = (stop - start) / step + 1
        if count > MAX_UP_VALUES:
            raise CfmInputError(
                f"--up {text} asks for {count:.3g} U_p values; expected at most "
                f"{MAX_UP_VALUES} (is STEP in um?)"
            )
        values = [start + i * step for i in range(int(math.floor(count - 1 + 1e-9)) + 1)]
    else:
        values = parts
    if not values or any(not math.isfinite(v) or v < 0 for v in values):
        raise CfmInputError(f"--up values must be finite and >= 0 um; got {text!r}")
    if len(values) > MAX_UP_VALUES:
        raise CfmInputError(
            f"--up gives {len(values)} U_p values; expected at most {MAX_UP_VALUES}"
        )
    from ..workflows.sweep.problem import check_up_distinct

    check_up_distinct(values, "--up")
    return values


def _note_compile(cfg) -> None:
    """Say, before the bar, which of the kernels this sweep runs numba compiles this time: the
    harmonic fit and sweep under the harmonic field model of a 3-D map (a planar map, known
    once meshed, runs the linear sweep), the linear sweep otherwise; the smaller set-up
    kernels load or compile as they are first used."""
    from .. import _kernels
    from ..models.sweep import uses_harmonic

    if uses_harmonic(cfg.field_model, 3):
        htm = cfg.mode == "htm"
        sweep = _kernels.harmonic_htm_sweep if htm else _kernels.harmonic_gauss_sweep
        kernels = (_kernels.harmonic_fit_block, sweep)
    else:
        kernels = (_kernels.gauss_sweep if cfg.mode == "gauss" else _kernels.htm_sweep,)
    missing = [k.py_func.__name__ for k in kernels if not _kernels.kernels_cached(k)]
    if missing:
        print(f"cfm-fem sweep: compiling {', '.join(missing)} for this machine (the first run "
              "after an install or upgrade; later runs load them from numba's cache)",
              file=sys.stderr)  # fmt: skip


def run(args) -> int:
    if args.bench is not None and args.mode != "htm":  # gauss draws N(0, U_p): no bench in it
        raise CfmInputError(
            "--bench is used by --mode htm only (mode gauss has no bench model); "
            "add --mode htm or leave out --bench"
        )
    given = [o for o, v in (("--up", args.up), ("--axis-scale", args.axis_scale)) if v is not None]
    if given and args.mode == "htm":  # htm draws the probe error from the bench: no U_p in it
        raise CfmInputError(
            f"{' and '.join(given)} {'is' if len(given) == 1 else 'are'} used by --mode gauss "
            "only (--mode htm draws the probe error from the bench model); leave "
            f"{'it' if len(given) == 1 else 'them'} out"
        )
    args.up = "0:50:10" if args.up is None else args.up
    args.axis_scale = (1.0, 1.0, 1.0) if args.axis_scale is None else args.axis_scale
    check_out_dir(args.out)
    check_seed(args.seed)
    up = parse_up_range(args.up)
    if args.chunk_nodes < 1:
        raise CfmInputError(f"--chunk-nodes must be >= 1; got {args.chunk_nodes}")
    if args.pieces is not None and args.pieces < 1:
        raise CfmInputError(f"--pieces must be >= 1; got {args.pieces}")
    # before the map is read and meshed (minutes for a large one), not after
    from ..workflows.sweep.distributed import check_scale_out
    from ..workflows.sweep.problem import check_options

    check_options(args.trials, args.axis_scale, args.b_ref, len(up), args.mode)
    check_scale_out(args.scheduler, args.workers)
    if args.slabs is not None or args.max_memory is not None:
        _check_slab_options(args)
    if args.table is not None:
        from ..io.sweep_table import check_table_format

        check_table_format(args.table)
    # the options are checked before the numerics are imported and the lock of --out is taken:
    # a typo is answered at once, also for a folder in use
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # no other run removes or writes in it
        return _run(args, up)


def _run(args, up) -> int:
    """The sweep, once the options are checked and the lock of ``--out`` is held."""
    from ..io import read_field
    from ..io.bench_toml import read_bench, read_reference_bench
    from ..io.provenance import bench_input, file_sha256, provenance
    from ..io.sweep_out import write_sweep, write_sweep_pieces
    from ..models.sweep import SweepConfig
    from ..workflows.sweep.distributed import dask_chunk_map, dask_client
    from ..workflows.sweep.in_memory import run_sweep
    from ..workflows.sweep.pieces import run_sweep_pieces
    from ..workflows.sweep.problem import chunk_ranges
    from ..workflows.sweep.resume import ResumableRun, describe_sweep

    fm = None
    if args.slabs is not None or args.max_memory is not None:  # out of core
        rc, fm = _run_slabs(args, up)  # fm: a map that is not 3-D, read while staging
        if rc is not None:
            return rc
        args.pieces = args.pieces or args.slabs or 8  # read whole: statistics still by pieces
    bench = None
    if args.bench is not None:
        bench = read_bench(args.bench)
    elif args.mode == "htm":
        bench = read_reference_bench()
    if fm is None:
        fm = read_field(args.field, **reader_kwargs(args))
    cfg = SweepConfig(
        up_um=up,
        trials=args.trials,
        seed=args.seed,
        axis_scale=args.axis_scale,
        b_ref_T=args.b_ref,
        interpolation=args.interpolation,
        mode=args.mode,
        bench=bench,
        chunk_nodes=args.chunk_nodes,
        outside=args.outside,
        hull_slivers=args.hull_slivers,
        field_model=args.field_model,
        region=args.region,
    )
    what = (
        f"U_p = {', '.join(f'{u:g}' for u in up)} um"
        if cfg.mode == "gauss"
        else "mode htm: bench model " + (args.bench or "(packaged CFM reference bench)")
    )
    print(
        f"cfm-fem sweep: {fm.n_nodes} nodes from {fm.source}; {what}; "
        f"{cfg.trials} trials per node, seed {cfg.seed}",
        file=sys.stderr,
    )
    _note_compile(cfg)
    read_options = reader_kwargs(args)
    # the bench used, the packaged one included: a default-bench run and one given a copy of
    # the same file have the same key (same numbers), and both name the file they used
    bench_entry = bench_input(args.bench) if cfg.mode == "htm" else None
    bench_sha = bench_entry and bench_entry["sha256"]
    description = describe_sweep(cfg, file_sha256(args.field), read_options, bench_sha)
    runner = ResumableRun(args.out, description, resume=args.resume)
    runner.check()  # a store made by another run: refuse before any work
    if not args.resume and runner.store.completed():
        print(
            f"cfm-fem sweep: {len(runner.store.completed())} chunk(s) of an earlier run in "
            f"{runner.store.path} are discarded (add --resume to continue that run instead)",
            file=sys.stderr,
        )
    try:
        with dask_client(args.scheduler, args.workers) as client:
            mapper = runner.mapper(None if client is None else dask_chunk_map(client))
            with progress_bar(fm.n_nodes, "nodes") as bar:
                if args.pieces:
                    res = run_sweep_pieces(fm, cfg, mapper, progress=bar.update)
                else:
                    res = run_sweep(fm, cfg, progress=bar.update, map_chunks=mapper)
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted(exc):
            raise
        if runner.store.completed():
            print(
                f"cfm-fem sweep: {len(runner.store.completed())} finished chunk(s) kept in "
                f"{runner.store.path}; run the same command with --resume to continue",
                file=sys.stderr,
            )
        raise KeyboardInterrupt from None  # numba wraps a Ctrl-C in a SystemError
    if args.resume:
        print(
            f"resumed: {runner.loaded} chunk(s) read from {runner.store.path}, "
            f"{runner.computed} computed"
            + (
                f" ({runner.rejected} unreadable chunk file(s) recomputed)"
                if runner.rejected
                else ""
            ),
            file=sys.stderr,
        )
    prov = provenance({"field": args.field, "bench": bench_entry}, args.command_line)
    prov.update(
        seed=cfg.seed,
        trials=cfg.trials,
        run_key=runner.key,
        backend=_backend(args),
        resumed_chunks=runner.loaded,
    )
    res.mesh = res.mesh.for_output()  # point location is done: its arrays are freed here
    if args.pieces:
        chunks = chunk_ranges(fm.n_nodes, cfg.chunk_nodes)
        summary = write_sweep_pieces(
            args.out,
            res,
            args.pieces,
            lambda nodes: runner.gather(nodes, chunks),
            prov,
            remove_stale=False,
        )
    else:
        summary = write_sweep(args.out, res, prov, remove_stale=False)
    _remove_stale_maps(args.out)  # the new outputs are complete: now the old maps can go
    _finish(args, summary, runner, res)
    return 0


def _finish(args, summary, runner=None, result=None) -> None:
    """The per-node table (``--table``), the report and the printed summary, once the maps,
    ``sweep.pvd`` and ``summary.json`` are written; the chunk store of ``runner`` goes after
    every output, so a run stopped before then resumes from it. ``result``: the sweep's result
    in memory, the report's figures drawn from it."""
    from ..io.sweep_table import remove_stale_table, write_sweep_table

    gone = remove_stale_table(args.out, args.table)
    if gone:
        print(f"cfm-fem sweep: removed {', '.join(gone)} of an earlier run from {args.out} "
              "(this run writes no such table)", file=sys.stderr)  # fmt: skip
    if args.table is not None:
        write_sweep_table(args.out, args.table)
    _write_report(args.out, result)
    if runner is not None:
        runner.finish(keep=args.keep_chunks)
    _print_summary(summary, args.out, args.table)


def _write_report(out, result=None) -> None:
    """``report.html`` and its figures, from the outputs just written (their figures from
    ``result`` when it is in memory)."""
    from ..report.sweep import write_sweep_report  # matplotlib: loaded only when used

    write_sweep_report(out, result=result)


def _backend(args) -> str:
    if args.scheduler:
        return f"dask scheduler {args.scheduler}"
    if args.workers:
        return f"dask LocalCluster, {args.workers} worker process(es)"
    return "this process (numba threads)"


def _explain_outside(s):
    """Why 'outside' barely moves with U_p: say where the lost trials come from (largest U_p)."""
    k = max(range(len(s["up_um"])), key=lambda j: s["up_um"][j])
    # the fractions are over the simulated nodes; nodes in no cell have no figure either
    losing = s["processed_nodes"] - s["uf_nodes"][k]
    if s["outside_fraction"][k] <= 0 or losing <= 0 or any(s["walk_failed_fraction"]):
        return
    share = s["outside_fraction"][k] * s["processed_nodes"] / losing
    text = (
        f"outside: perturbed points that left the map (never extrapolated). At U_p = "
        f"{s['up_um'][k]:g} um they come from the {losing} nodes without a U_f figure, which "
        f"lost {100 * share:.0f} % of their trials on average: nodes on the map's surface lose "
        "about half of them whatever U_p is, so this fraction hardly grows with U_p"
    )
    print(textwrap.fill(text, width=100, subsequent_indent="  "))


def _print_summary(s, out, table=None):
    from ..io.sweep_table import table_name

    h = s.get("harmonic")
    if h is None:
        print(f"field model: the linear interpolant at every node ({s['interpolation']})")
    elif not h["nodes_by_degree"]:
        print(
            f"field model: the linear interpolant at every node ({s['interpolation']}): no "
            f"node's harmonic fit holds ({h['fallback_rule']})"
        )
    else:
        degrees = ", ".join(f"{n} of degree {d}" for d, n in h["nodes_by_degree"].items())
        print(
            f"field model: harmonic fit per node to its {h['neighbours']} nearest nodes "
            f"({degrees}); RMS residual p95 {h['residual_units']['p95']:.3g} units; "
            f"{h['linear_fallback_nodes']} node(s) on the linear interpolant "
            f"({s['interpolation']})"
        )
    print(
        f"B_ref = {s['b_ref_T']:.6g} T ({s['b_ref_rule']}); {s['trials']} trials per node, "
        f"U_f of one node known to +-{100 * s['uf_relative_mc_std']:.1f} % (1 sigma, Monte Carlo)"
    )
    if "region_description" in s:
        weighting = (
            "each node weighted by the volume it stands for"
            if s["statistics_weighting"].startswith("volume")
            else "every node counted once"
        )
        print(f"U_f percentiles over {s['region_description']} ({s['region_nodes']} nodes), "
              f"{weighting}")  # fmt: skip
    print(
        f"{'U_p [um]':>9} {'U_f p50':>9} {'p95':>9} {'p99':>9} {'max':>9}  [units]  "
        f"{'outside':>9} {'nodes':>8}"
    )
    for k, up in enumerate(s["up_um"]):
        row = [s["uf_units"][q][k] for q in ("p50", "p95", "p99", "max")]
        cells = " ".join(f"{v:9.3g}" if v is not None else f"{'-':>9}" for v in row)
        label = "" if s["mode"] == "gauss" else f"  {s['columns'][k]}"
        print(
            f"{up:9.3g} {cells}           {100 * s['outside_fraction'][k]:8.3f}% "
            f"{s['uf_nodes'][k]:8d}{label}"
        )
    if s["mode"] == "htm":
        print("(htm: U_p is the RMS over nodes of the 3-D probe position error of that column)")
    if s.get("outside") == "extrapolate":
        if any(s["outside_fraction"]):
            text = f"outside: perturbed points that left the map, each {s['outside_rule']}"
            print(textwrap.fill(text, width=100, subsequent_indent="  "))
    elif s["mode"] != "htm":
        _explain_outside(s)
    for note in s["notes"]:
        print(f"note: {note}")
    if "slabs" in s:
        print(f"slabs: {s['slabs']['count']} along {s['slabs']['axis']}, halo "
              f"{s['slabs']['halo_mm']:.4g} mm; {s['slabs']['halo_outside_nodes']} node(s) with "
              "trials stopped at a halo border (counted outside)")  # fmt: skip
    maps = (
        f"{len(s['up_um'])} .pvtu maps of {s['pieces']} pieces"
        if "pieces" in s
        else (f"{len(s['up_um'])} .vtu maps")
    )
    table = f", {table_name(table)}" if table else ""
    print(f"{s['seconds']:.1f} s; wrote {Path(out) / 'sweep.pvd'}, {maps}, summary.json"
          f"{table}, report.html and open_in_paraview.py")  # fmt: skip
