"""Probe positioning error of a bench by GUM-S1 Monte Carlo over the scan grid (paper Table IV).

Each trial draws the 21 geometric errors once (common to all points) and, per point, vibration
and reading delay; the exact HTM chain gives the probe error. Writes DIR/summary.json (pooled per
axis as in Table IV, with the assumptions), DIR/points.csv and DIR/points.vtu (per point) and
DIR/report.html, and prints the result beside the paper's simulated Table IV.
"""

from __future__ import annotations

import textwrap

from ._checks import check_out_dir, trial_count_type
from ._progress import announcer, note_first_compile, progress_bar
from .sweep import add_scale_out_args

NAME = "kinematics"
HELP = "probe positioning error of the bench (21 errors, HTM, Monte Carlo): Table IV per point"


def add_args(p):
    p.add_argument(
        "--bench", metavar="B.toml", help="bench file (default: the CFM reference bench)"
    )
    p.add_argument(
        "--trials",
        type=trial_count_type(),
        default=1_000_000,
        metavar="N",
        help="Monte Carlo trials (default 1e6)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--adaptive",
        type=int,
        metavar="NDIG",
        help="adaptive Monte Carlo (JCGM 101 7.9): stop when the pooled results are stable to "
        "NDIG significant digits (--trials is then ignored)",
    )
    p.add_argument(
        "--fast-intervals",
        action="store_true",
        help="runs too long for the one exact pass (its stores above 1 GiB: beyond ~1e8 "
        "trials on the reference grid) count in a first pass and regenerate in a second: skip "
        "that second pass, interval ends interpolated inside their slot",
    )
    add_scale_out_args(p)


def check_options(args) -> None:
    """Every check of the options that needs no file read, run before the bench is read (a bad
    bench would otherwise be reported instead of the bad option) and before any output
    (`cfm_fem.workflows.kinematics.check_options`, and an ``--out`` that cannot be a folder)."""
    from ..workflows.kinematics import check_options as check

    check(args.trials, args.seed, args.adaptive, args.scheduler, args.workers)
    check_out_dir(args.out)


def run(args) -> int:
    check_options(args)
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args)


def _run(args) -> int:
    from ..workflows.kinematics import run_kinematics

    if args.scheduler is None and args.workers is None:  # Dask workers compile on their own
        from .. import _kernels

        note_first_compile(_kernels.pass_keep)
    with progress_bar(None, "trials") as bar:
        res = run_kinematics(
            args.bench, trials=args.trials, seed=args.seed, adaptive_digits=args.adaptive,
            fast_intervals=args.fast_intervals, scheduler=args.scheduler, workers=args.workers,
            command_line=args.command_line, progress=bar.update,
            on_start=announcer(bar, "kinematics"),
        )  # fmt: skip
    paths = res.write(args.out)
    print_table_iv(res.summary)
    print(f"wrote {paths['summary']}, {paths['csv']}, {paths['vtu']}, {paths['report']}")
    return 0


def print_table_iv(s: dict) -> None:
    """Print the pooled result beside the paper's Table IV, then the assumptions."""
    from ..io.kinematics_out import PAPER_TABLE_IV

    sim = PAPER_TABLE_IV["simulation"]
    exp = PAPER_TABLE_IV["experiment"]
    print(
        f"Probe positioning error E_p [um], {s['points']} points, {s['trials']} trials, "
        f"seed {s['seed']}"
    )
    print(f"{'':14}{'this run':>27}   {'paper Table IV, simulated':>27}   {'experiment':>12}")
    cols = f"{'systematic':>11}{'std':>8}{'U_p':>8}"
    print(f"{'axis':14}{cols}   {cols}   {'sys':>5}{'std':>6}")
    for a in "xyz":
        r, p, e = s["axes"][a], sim[a], exp[a]
        up_paper = (p["systematic_um"] ** 2 + p["std_um"] ** 2) ** 0.5
        print(
            f"{a.upper():14}{r['systematic_um']:11.1f}{r['std_um']:8.1f}{r['U_p_um']:8.1f}"
            f"   {p['systematic_um']:11.0f}{p['std_um']:8.0f}{up_paper:8.1f}"
            f"   {e['systematic_um']:5.0f}{e['std_um']:6.0f}"
        )
    n = s["norm"]
    print(f"{'|E_p|':14}{n['systematic_um']:11.1f}{n['std_um']:8.1f}{n['U_p_um']:8.1f}")
    print(f"pooling: {s['pooling']}")
    g = s.get("gum_validation")
    if g:
        print(
            "GUM (linearised) vs Monte Carlo intervals, JCGM 101 section 8, valid at: "
            + ", ".join(f"{a.upper()} {100 * g[a]['valid_fraction']:.0f} %" for a in "xyz")
            + " of the points"
        )
    b = s.get("budget")
    if b:
        from ..models.kinematics.budget import UP_SHARE_MEANING

        print("largest shares of U_p^2 = sys^2 + u^2 (up_share; not variance shares), per axis "
              "X / Y / Z:")  # fmt: skip
        rows = sorted(b["rows"], key=lambda r: -max(abs(v) for v in r["up_share"].values()))
        for r in rows[:6]:
            sh = " / ".join(f"{100 * r['up_share'][a]:5.1f}" for a in "xyz")
            print(f"  {r['name']:16} {r['pdf']:24} {sh} %")
        text = f"{UP_SHARE_MEANING}. The variance shares (var_share) are in summary.json."
        print(textwrap.fill(text, width=100, initial_indent="  ", subsequent_indent="  "))
    bench = s["bench"]
    print(
        f"geometry: stack {' / '.join(bench['stack_from_foundation'])} from the foundation; "
        f"tool offset {bench['tool_offset_mm']} mm; strokes {bench['strokes_mm']} mm"
    )
    for note in bench["assumptions"]:
        print(f"assumption: {note}")
    for note in s["notes"]:
        print(f"note: {note}")
    if "adaptive" in s:
        a = s["adaptive"]
        print(
            f"adaptive: {a['batches']} batches of {a['batch_trials']} trials, "
            f"converged={a['converged']}"
        )
    print("seconds: " + ", ".join(f"{k} {v:.2f}" for k, v in s["seconds"].items()))
