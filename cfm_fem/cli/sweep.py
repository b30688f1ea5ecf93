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
from . import option_type
from ._checks import check_out_dir, trial_count_type
from ._progress import announcer, progress_bar
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
        default=None,
        metavar="N",
        # the range: models.sweep.ADAPTIVE_PLAN, written out so that --help stays fast
        help="plain Monte Carlo with N trials per node and U_p (default: under the harmonic "
        "field model in mode gauss, as many trials as U_f's precision needs, 256 to 64000 "
        "per node; 10000 elsewhere)",
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
        "linear on a planar one. A map's fits are kept for its next runs in the user's cache "
        "folder (~/.cache/cfm_fem/fits; the environment variable CFM_FEM_FIT_CACHE names "
        "another, or off for none)",
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


def _note_compile(mode: str, field_model: str, adaptive: bool = False) -> None:
    """Say, before the bar, which of the kernels this sweep runs numba compiles this time: the
    harmonic fit and sweep under the harmonic field model of a 3-D map (a planar map, known
    once meshed, runs the linear sweep), the linear sweep otherwise; the smaller set-up
    kernels load or compile as they are first used. ``adaptive``: the adaptive estimator's
    kernel in mode gauss (no ``--trials``)."""
    from .. import _kernels
    from ..models.sweep import uses_harmonic

    if uses_harmonic(field_model, 3):
        htm = mode == "htm"
        sweep = _kernels.harmonic_htm_sweep if htm else _kernels.harmonic_gauss_sweep
        if adaptive and not htm:
            from ..workflows.sweep import compile_ahead

            sweep = _kernels.harmonic_cv_sweep
            if compile_ahead.start():  # beside the map's reading and fit, on another core
                kernels = (_kernels.harmonic_fit_block,)
                missing = [k.py_func.__name__ for k in kernels if not _kernels.kernels_cached(k)]
                print(f"cfm-fem sweep: compiling {', '.join(missing + [sweep.py_func.__name__])} "
                      "for this machine (the first run after an install or upgrade; the sweep's "
                      "kernel in two more processes while the map is read and fitted; later runs "
                      "load them from numba's cache)", file=sys.stderr)  # fmt: skip
                return
        kernels = (_kernels.harmonic_fit_block, sweep)
    else:
        kernels = (_kernels.gauss_sweep if mode == "gauss" else _kernels.htm_sweep,)
    missing = [k.py_func.__name__ for k in kernels if not _kernels.kernels_cached(k)]
    if missing:
        print(f"cfm-fem sweep: compiling {', '.join(missing)} for this machine (the first run "
              "after an install or upgrade; later runs load them from numba's cache)",
              file=sys.stderr)  # fmt: skip


def _trials_text(s) -> str:
    """'10000 trials per node', or the adaptive estimator's range."""
    if s.get("estimator") == "adaptive":
        from ..models.sweep import ADAPTIVE_PLAN

        return f"adaptive estimator, {ADAPTIVE_PLAN[0]} to {ADAPTIVE_PLAN[1]} trials per node"
    return f"{s['trials']} trials per node"


def run(args) -> int:
    from ..workflows.sweep.run import check_mode_options, check_options

    up_given = args.up is not None
    check_mode_options(args.mode, args.bench, up_given, args.axis_scale)
    args.up = "0:50:10" if args.up is None else args.up
    check_out_dir(args.out)
    up = parse_up_range(args.up)
    # before the map is read and meshed (minutes for a large one), not after
    check_options(
        up_um=up, trials=args.trials, seed=args.seed, mode=args.mode, bench=args.bench,
        axis_scale=args.axis_scale, b_ref_T=args.b_ref, chunk_nodes=args.chunk_nodes,
        pieces=args.pieces, scheduler=args.scheduler, workers=args.workers, slabs=args.slabs,
        max_memory=args.max_memory, region=args.region, table=args.table, up_given=up_given,
    )  # fmt: skip
    # the options are checked before the numerics are imported and the lock of --out is taken:
    # a typo is answered at once, also for a folder in use
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # no other run removes or writes in it
        return _run(args, up)


def _run(args, up) -> int:
    """The sweep, once the options are checked and the lock of ``--out`` is held."""
    from ..workflows.sweep.run import run_sweep

    _note_compile(args.mode, args.field_model, args.trials is None)
    with progress_bar(None, "nodes") as bar:
        res = run_sweep(
            args.field, up, trials=args.trials, seed=args.seed, mode=args.mode,
            bench=args.bench, axis_scale=args.axis_scale, b_ref_T=args.b_ref,
            interpolation=args.interpolation, chunk_nodes=args.chunk_nodes,
            outside=args.outside, hull_slivers=args.hull_slivers, field_model=args.field_model,
            region=args.region, reader=reader_kwargs(args), out_dir=args.out,
            pieces=args.pieces, resume=args.resume, keep_chunks=args.keep_chunks,
            scheduler=args.scheduler, workers=args.workers, slabs=args.slabs,
            max_memory=args.max_memory, table=args.table, command_line=args.command_line,
            progress=bar.update, on_start=announcer(bar, "sweep"),
            log=lambda m: bar.write(f"cfm-fem sweep: {m}", file=sys.stderr),
        )  # fmt: skip
    _print_summary(res.summary, args.out, args.table)
    return 0


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
        f"B_ref = {s['b_ref_T']:.6g} T ({s['b_ref_rule']}); {_trials_text(s)}, "
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
