"""Coupled mechanical-magnetic Monte Carlo (paper eq. 12-14): the field error E_f per point from
the bench's positioning errors and the Hall probe together, pooled as the paper's Table V.

Writes DIR/summary.json (Table V beside the paper, B_ref, R_ref, region, every assumption),
DIR/points.csv (per point and component), DIR/report.html and its PNG figures.
"""

from __future__ import annotations

from ._checks import check_out_dir, trial_count_type
from ._progress import announcer, progress_bar
from ._reader import add_field_model_arg, add_reader_args, reader_kwargs

NAME = "coupled"
HELP = "field error E_f from positioning and probe together (eq. 12-14): Table V"


def add_common(p):
    """Options shared with ``compare``: bench, probe, alignment, Monte Carlo."""
    p.add_argument(
        "--bench", metavar="B.toml", help="bench file (default: the CFM reference bench)"
    )
    p.add_argument(
        "--trials",
        type=trial_count_type(),
        default=100_000,
        metavar="N",
        help="Monte Carlo trials (default 1e5; the paper used 1e6)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument(
        "--probe",
        choices=["paper", "table1"],
        default="paper",
        help="paper: S_HP uniform, std 0.15 %% (default); table1: every Table I line",
    )
    p.add_argument(
        "--align",
        choices=["placement", "probe"],
        default="placement",
        help="placement: magnet where the bench file puts it (bench offsets count); "
        "probe: magnet located with the probe, per-trial common offset removed",
    )
    p.add_argument(
        "--centre-magnet",
        action="store_true",
        help="move the magnet origin to mid-travel of X and Y (keeps its Z travel)",
    )
    p.add_argument(
        "--b-ref",
        type=float,
        metavar="T",
        help="B_ref of a field map (default max |B|); harmonics use the main harmonic",
    )
    p.add_argument(
        "--r-ref",
        type=float,
        metavar="MM",
        help="R_ref for a harmonics file that does not state it",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")


def add_args(p):
    p.add_argument(
        "--field",
        metavar="FIELD",
        help="harmonics .csv (n,Bn,An) or FEM export (default: bundled QFDp4, Table III, "
        "R_ref = 10 mm assumed)",
    )
    p.add_argument(
        "--radius",
        type=float,
        metavar="MM",
        help="scan region radius (default R_ref; for a map 0.8 x its transverse extent)",
    )
    p.add_argument(
        "--step",
        type=float,
        default=2.0,
        metavar="MM",
        help="transverse grid step of the region (default 2 mm)",
    )
    p.add_argument(
        "--z",
        default=None,
        metavar="Z1,Z2,..",
        help="planes along the magnet axis, mm (default -100,-50,0,50,100; for a map "
        "five planes over the middle half of its length)",
    )
    p.add_argument(
        "--no-budget",
        action="store_true",
        help="skip the positioning-only / probe-only split (two extra runs)",
    )
    add_common(p)
    add_reader_args(p, "--field", "when it is a field map (not a harmonics .csv)")
    add_field_model_arg(p, "--field")


def check_common(args):
    from ..workflows.coupled_run import check_trials

    check_trials(args.trials, args.seed)


def _parse_z(text):
    from ._checks import number_list

    return number_list(text, "--z", what="numbers in mm")


def run(args) -> int:
    check_out_dir(args.out)
    check_common(args)
    z = None if args.z is None else _parse_z(args.z)
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args, z)


def _run(args, z) -> int:
    from ..workflows.coupled_run import run_coupled

    with progress_bar(None, "points") as bar:
        res = run_coupled(
            args.field, args.bench, radius_mm=args.radius, step_mm=args.step, z_mm=z,
            trials=args.trials, seed=args.seed, probe=args.probe, align=args.align,
            centre_magnet=args.centre_magnet, b_ref_T=args.b_ref, r_ref_mm=args.r_ref,
            field_model=args.field_model, reader=reader_kwargs(args), budget=not args.no_budget,
            command_line=args.command_line, progress=bar.update,
            on_start=announcer(bar, "coupled"),
        )  # fmt: skip
    paths = res.write(args.out)
    print_table_v(res.summary)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


def print_table_v(s: dict) -> None:
    """Table V of this run beside the paper's, with B_ref, R_ref and the region."""
    from ..models.field_model import PAPER_TABLE_V

    t = s["table_v"]["simulated"]
    print(f"E_f [units of 1e-4 B_ref], B_ref = {s['b_ref_T']:.6g} T ({s['b_ref_rule']})")
    print(f"region: {s['region']}; {s['trials']} trials, seed {s['seed']}, align {s['align']}")
    print(f"{'':26}{'systematic':>11}{'std':>8}{'U_f':>8}")
    print(
        f"{'this run':26}{t['systematic_units']:11.2f}{t['std_units']:8.2f}"
        f"{t['U_f_units']:8.2f}   (num. u {t['systematic_num_u']:.2g} / {t['std_num_u']:.2g} / "
        f"{t['U_f_num_u']:.2g})"
    )
    for label, key in (("paper, simulated", "simulation"), ("paper, experimental", "experiment")):
        p = PAPER_TABLE_V[key]
        print(f"{label:26}{p['systematic_units']:11.1f}{p['std_units']:8.1f}{p['U_f_units']:8.1f}")
    fb = s.get("field_budget")
    if fb:
        for label, key in (("positioning only", "positioning_only"), ("probe only", "probe_only")):
            d = fb[key]
            print(
                f"{label:26}{d['systematic_units']:11.2f}{d['std_units']:8.2f}"
                f"{d['U_f_units']:8.2f}   ({fb['trials']} trials)"
            )
    for note in s["notes"]:
        print(f"note: {note}")
