"""Paper Fig. 4 analogue: U_f (95 %) against U_p = 0..50 um on an FEM map (isotropic Gaussian
positioning error, eq. 16), as a table and plots beside the paper's two values, with the linear
scaling law U_f = 1.96 U_p |grad |B|| / B_ref.

Writes DIR/fig4.json, DIR/fig4.csv, DIR/fig4_curve.png, DIR/fig4_plane.png and DIR/report.html.
"""

from __future__ import annotations

from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import announcer, progress_bar
from ._reader import add_field_model_arg, add_reader_args, reader_kwargs
from .sweep import parse_up_range

NAME = "fig4"
HELP = "Fig. 4 analogue: U_f (95 %%) against U_p on an FEM map, table and plots"


def add_args(p):
    p.add_argument("field", metavar="FIELD", help="FEM export (e.g. meshes/quadrupole.vtu)")
    p.add_argument(
        "--up",
        default="0:50:10",
        metavar="START:STOP:STEP",
        help="U_p values in um (default 0:50:10)",
    )
    p.add_argument(
        "--trials",
        type=trial_count_type(),
        default=2000,
        metavar="N",
        help="trials per node and U_p (default 2000)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--b-ref", type=float, metavar="T", help="B_ref (default max |B| of the map)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_reader_args(p)
    add_field_model_arg(p, "FIELD")


def run(args) -> int:
    check_out_dir(args.out)
    check_seed(args.seed)
    up = parse_up_range(args.up)
    from ..workflows.sweep.problem import check_options

    check_options(args.trials, (1.0, 1.0, 1.0), args.b_ref, len(up))
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args, up)


def _run(args, up) -> int:
    from ..workflows.fig4_run import run_fig4

    with progress_bar(None, "nodes") as bar:
        res = run_fig4(
            args.field, up, trials=args.trials, seed=args.seed, b_ref_T=args.b_ref,
            field_model=args.field_model, reader=reader_kwargs(args),
            command_line=args.command_line, progress=bar.update, on_start=announcer(bar, "fig4"),
        )  # fmt: skip
    paths = res.write(args.out)
    summary = res.summary
    # the body nodes that kept every trial: fewer at U_p > 0 (surface nodes lose trials)
    print(
        f"U_f (95 %) over the magnet-body nodes (|z| <= {summary['body_half_length_mm']:g} mm) "
        f"that kept every trial, B_ref = {summary['b_ref_T']:.6g} T; {args.trials} trials/node "
        f"(+-{100 * summary['uf_relative_mc_std']:.1f} % per node)"
    )
    print(f"{'U_p [um]':>9}{'nodes':>8}{'p50':>8}{'p95':>8}{'max':>8}{'law':>8}{'paper':>7}")
    for r in summary["table"]:
        paper = "" if r["paper"] is None else f"{r['paper']:g}"
        cells = "".join(
            f"{'-':>8}" if r[k] is None else f"{r[k]:8.1f}"
            for k in ("p50", "p95", "max", "analytic")
        )  # None: no complete body node, or no gradient for the law
        print(f"{r['up_um']:9g}{r['nodes']:8d}{cells}{paper:>7}")
    print(summary["explanation"])
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0
