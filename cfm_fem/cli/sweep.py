"""Per-node field uncertainty U_f of an FEM map for a sweep of positioning uncertainties U_p.

Writes DIR/uf_up<U_p>um.vtu per U_p value, DIR/sweep.pvd (open it in ParaView; U_p is the time
axis) and DIR/summary.json.
"""

from __future__ import annotations

import sys

from ..errors import CfmInputError
from ..io import read_field
from ..io.bench_toml import read_bench, read_reference_bench
from ..io.provenance import provenance
from ..io.sweep_out import write_sweep
from ..sweep import SweepConfig, parse_up_range, run_sweep
from ._progress import progress_bar

NAME = "sweep"
HELP = "U_f maps (95 %%) of a field map for a sweep of U_p; VTK output for ParaView"


def _triplet(text):
    try:
        v = tuple(float(x) for x in text.split(","))
        if len(v) == 1:
            v = v * 3
        if len(v) != 3:
            raise ValueError
        return v
    except ValueError:
        raise CfmInputError(
            f"--axis-scale must be one number or three comma-separated numbers; got {text!r}"
        ) from None


def add_args(p):
    p.add_argument(
        "field",
        metavar="FIELD",
        help="field map: .vtu/.vtk/.msh/..., COMSOL .txt, Opera .table, .csv",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--up",
        default="0:50:10",
        metavar="START:STOP:STEP",
        help="U_p values in um, STOP included, or a comma list (default 0:50:10)",
    )
    p.add_argument(
        "--trials",
        type=int,
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
        help="reference field for units (default: max |B| of the map)",
    )
    p.add_argument(
        "--axis-scale",
        type=_triplet,
        default=(1.0, 1.0, 1.0),
        metavar="SX,SY,SZ",
        help="per-axis multiplier of U_p (default 1,1,1: isotropic)",
    )
    p.add_argument(
        "--interpolation",
        choices=["auto", "native", "grid", "delaunay"],
        default="auto",
        help="auto: the export's cells if any, Kuhn triangulation of a grid, else Delaunay",
    )
    p.add_argument(
        "--format", dest="fmt", metavar="FMT", help="input format if the extension is ambiguous"
    )
    p.add_argument(
        "--length-unit",
        metavar="UNIT",
        help="unit of the coordinates if the file does not say (mm, m, in, ...)",
    )
    p.add_argument(
        "--field-unit",
        metavar="UNIT",
        help="unit of the field if the file does not say (T, mT, G, kG)",
    )
    p.add_argument(
        "--zero-rows",
        choices=["warn", "drop", "keep"],
        default="warn",
        help="rows with B exactly 0 0 0 (placeholders of measured maps): warn and keep, drop, keep",
    )
    p.add_argument(
        "--chunk-nodes",
        type=int,
        default=20000,
        metavar="K",
        help="nodes per chunk (memory/progress; results do not depend on it)",
    )


def run(args) -> int:
    up = parse_up_range(args.up)
    if args.chunk_nodes < 1:
        raise CfmInputError(f"--chunk-nodes must be >= 1; got {args.chunk_nodes}")
    bench = None
    if args.bench is not None:
        bench = read_bench(args.bench)
    elif args.mode == "htm":
        bench = read_reference_bench()
    fm = read_field(
        args.field,
        fmt=args.fmt,
        length_unit=args.length_unit,
        field_unit=args.field_unit,
        zero_rows=args.zero_rows,
    )
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
    )
    print(
        f"cfm-fem sweep: {fm.n_nodes} nodes from {fm.source}; "
        f"U_p = {', '.join(f'{u:g}' for u in up)} um; "
        f"{cfg.trials} trials per node, seed {cfg.seed}",
        file=sys.stderr,
    )
    with progress_bar(fm.n_nodes, "nodes") as bar:
        res = run_sweep(fm, cfg, progress=bar.update)
    prov = provenance({"field": args.field, "bench": args.bench}, args.command_line)
    summary = write_sweep(args.out, res, prov)
    _print_summary(summary, args.out)
    return 0


def _print_summary(s, out):
    print(f"interpolation: {s['interpolation']}")
    print(
        f"B_ref = {s['b_ref_T']:.6g} T ({s['b_ref_rule']}); {s['trials']} trials per node, "
        f"U_f of one node known to +-{100 * s['uf_relative_mc_std']:.1f} % (1 sigma, Monte Carlo)"
    )
    print(
        f"{'U_p [um]':>9} {'U_f p50':>9} {'p95':>9} {'p99':>9} {'max':>9}  [units]  "
        f"{'outside':>9} {'nodes':>8}"
    )
    for k, up in enumerate(s["up_um"]):
        row = [s["uf_units"][q][k] for q in ("p50", "p95", "p99", "max")]
        cells = " ".join(f"{v:9.3g}" if v is not None else f"{'-':>9}" for v in row)
        print(
            f"{up:9g} {cells}           {100 * s['outside_fraction'][k]:8.3f}% "
            f"{s['uf_nodes'][k]:8d}"
        )
    for note in s["notes"]:
        print(f"note: {note}")
    print(
        f"{s['seconds']:.1f} s; wrote {out}/sweep.pvd, {len(s['up_um'])} .vtu maps and summary.json"
    )
