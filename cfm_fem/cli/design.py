"""The design question of the paper: which U_p keeps U_f at or below X units over a share of the
nodes (default 95 %), in the whole map or a region? Or, with --quantity Q --max X --r-ref MM:
which U_p keeps U95 of a field-quality figure (b_n, a_n, centre, roll, length of
``cfm-fem quality``) at or below X?

Runs a sweep over U_p (Gaussian, paper eq. 16), takes the coverage percentile of U_f over the
nodes with a U_f figure per U_p, and interpolates where it crosses X; the Monte Carlo standard
uncertainty of the answer comes from a bootstrap of the nodes' U_f. Writes the sweep's outputs
(maps, sweep.pvd, summary.json), DIR/design.json and DIR/report.html with the answer on top.
With --quantity: bisects on U_p with the quality Monte Carlo in mode gauss
(`cfm_fem.workflows.design_quality`) and writes DIR/design.json.
"""

from __future__ import annotations

import sys

from ..errors import CfmInputError
from . import option_type
from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import announcer, note_first_compile, progress_bar
from ._reader import add_field_model_arg, add_reader_args, reader_kwargs

NAME = "design"
HELP = (
    "largest U_p that keeps U_f <= X units over 95 %% of the nodes (or a region), or U95 of a "
    "field-quality figure <= X"
)
#: Trials per U_p of --quantity when --trials is not given.
QUALITY_TRIALS = 2000


def _region(text):
    from ..models.region import parse_region

    return parse_region(text)


def add_args(p):
    p.add_argument("field", metavar="FIELD", help="field map (any format cfm-fem sweep reads)")
    p.add_argument("--uf-max", type=float, metavar="X",
                   help="target U_f, units of 1e-4 B_ref (or --quantity and --max)")  # fmt: skip
    p.add_argument("--quantity", metavar="Q",
                   help="field-quality figure instead of U_f: b1..b15, a1..a15 (units), "
                   "centre_x_um, centre_y_um, roll_mrad, magnetic_length_mm")  # fmt: skip
    p.add_argument("--max", type=float, metavar="X",
                   help="with --quantity: largest U95 of it, in its unit")  # fmt: skip
    p.add_argument("--r-ref", type=float, metavar="MM",
                   help="with --quantity: reference radius of the harmonics, mm")  # fmt: skip
    p.add_argument("--coverage", type=float, default=0.95, metavar="P",
                   help="share of the nodes that must meet it (default 0.95)")  # fmt: skip
    p.add_argument("--region", type=option_type(_region, "--region"),
                   metavar="XMIN:XMAX,YMIN:YMAX,ZMIN:ZMAX|cylinder:R,ZMIN:ZMAX",
                   help="only the nodes in this box, or in this cylinder about the z axis "
                   "(radius R, z range), mm (an empty end is unbounded, e.g. -10:10,-10:10,: or "
                   "cylinder:7,-30:30); B_ref defaults to the largest |B| in it")  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument("--up", default="0:50:10", metavar="START:STOP:STEP",
                   help="U_p values of the sweep, um (default 0:50:10); a target beyond the "
                   "largest is extrapolated by the proportional law, and said so")  # fmt: skip
    p.add_argument("--trials", type=trial_count_type(), metavar="N",
                   help="trials per node and U_p (default 10000); with --quantity, trials of "
                   f"the quality Monte Carlo per U_p (default {QUALITY_TRIALS})")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--b-ref", type=float, metavar="T",
                   help="reference field for units (default: max |B| over the nodes of "
                   "--region, or of the map)")  # fmt: skip
    p.add_argument(
        "--outside",
        choices=["exclude", "extrapolate"],
        default="exclude",
        help="trials that leave the map: as in cfm-fem sweep (default exclude)",
    )
    add_field_model_arg(p, "FIELD", auto=True)
    add_reader_args(p)


def run(args) -> int:
    from ..workflows.design_run import check_question
    from ..workflows.sweep.problem import check_options
    from .sweep import parse_up_range

    check_out_dir(args.out)
    check_seed(args.seed)
    if args.quantity is not None or args.max is not None:
        return _run_quality_design(args)
    if args.uf_max is None:
        raise CfmInputError("design needs --uf-max X, or --quantity Q --max X --r-ref MM")
    if args.r_ref is not None:
        raise CfmInputError("--r-ref applies to --quantity; --uf-max takes no reference radius")
    args.trials = 10000 if args.trials is None else args.trials
    up = parse_up_range(args.up)
    check_question(up, args.uf_max, args.coverage)
    check_options(args.trials, (1.0, 1.0, 1.0), args.b_ref, len(up))
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):
        return _run(args, up)


def _run(args, up) -> int:
    from .. import _kernels
    from ..workflows.design_run import run_design

    note_first_compile(_kernels.gauss_sweep)
    with progress_bar(None, "nodes") as bar:
        res = run_design(
            args.field, args.uf_max, up_um=up, coverage=args.coverage, region=args.region,
            trials=args.trials, seed=args.seed, b_ref_T=args.b_ref, outside=args.outside,
            field_model=args.field_model, reader=reader_kwargs(args),
            command_line=args.command_line, progress=bar.update,
            on_start=announcer(bar, "design"),
        )  # fmt: skip
    res.write(args.out)
    ans = res.answer
    print(ans.sentence())
    for u, p, s in zip(ans.up_um, ans.percentile_units, ans.u_percentile_units, strict=True):
        text = "-" if p is None else f"{p:.4g} +- {'-' if s is None else f'{s:.2g}'}"
        print(f"  U_p = {u:g} um: p{100 * args.coverage:g} of U_f = {text} units")
    print(f"wrote {args.out}/design.json, report.html, sweep.pvd and the maps")
    return 0


def _run_quality_design(args) -> int:
    from ..io.lock import output_lock
    from ..io.provenance import provenance
    from ..workflows.design_quality import QUANTITIES, quality_up_max

    for flag, value in (("--quantity", args.quantity), ("--max", args.max),
                        ("--r-ref", args.r_ref)):  # fmt: skip
        if value is None:
            raise CfmInputError(f"--quantity Q --max X needs {flag}")
    if args.uf_max is not None or args.region is not None:
        raise CfmInputError("--uf-max and --region apply to U_f; --quantity replaces them")
    if args.quantity not in QUANTITIES:
        raise CfmInputError(
            "--quantity must be one of b1..b15, a1..a15, centre_x_um, centre_y_um, roll_mrad, "
            f"magnetic_length_mm; got {args.quantity!r}"
        )
    trials = QUALITY_TRIALS if args.trials is None else args.trials
    with output_lock(args.out, args.command_line):
        print(f"cfm-fem design: U95({args.quantity}) <= {args.max:g} by bisection on U_p, "
              f"{trials} trials per U_p", file=sys.stderr)  # fmt: skip
        with progress_bar(None, "trials") as bar:
            ans = quality_up_max(args.field, args.r_ref, args.quantity, args.max, trials=trials,
                                 seed=args.seed, field_model=_quality_model(args.field_model),
                                 reader=reader_kwargs(args), progress=bar.update)  # fmt: skip
        ans.write(args.out, provenance({"field": args.field}, args.command_line))
    print(ans.sentence())
    for up, u in ans.evaluations:
        print(f"  U_p = {up:.4g} um: U95({args.quantity}) = {u:.4g} {ans.unit}")
    print(f"wrote {args.out}/design.json")
    return 0


def _quality_model(field_model) -> str:
    """``--field-model`` of the quality Monte Carlo: auto is the local harmonic model."""
    return "harmonic" if field_model in (None, "auto") else field_model
