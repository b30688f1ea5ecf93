"""Probe positioning error of a bench by GUM-S1 Monte Carlo over the scan grid (paper Table IV).

Each trial draws the 21 geometric errors once (common to all points) and, per point, vibration
and reading delay; the exact HTM chain gives the probe error. Writes DIR/summary.json (pooled per
axis as in Table IV, with the assumptions), DIR/points.csv and DIR/points.vtu (per point) and
DIR/report.html, and prints the result beside the paper's simulated Table IV.
"""

from __future__ import annotations

import sys
import textwrap

from ..errors import CfmInputError
from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import note_first_compile, progress_bar
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
    bench would otherwise be reported instead of the bad option) and before any output.

    Raises
    ------
    CfmInputError
        ``--trials`` < 2 (without ``--adaptive``), ``--adaptive`` not 1..4, a seed numba cannot
        take, ``--workers`` < 1 or Dask missing, ``--adaptive`` with ``--scheduler``/``--workers``,
        or an ``--out`` that cannot be a folder.
    """
    from ..workflows.sweep.distributed import check_scale_out

    if args.adaptive is None and args.trials < 2:
        raise CfmInputError(f"--trials must be >= 2; got {args.trials}")
    if args.adaptive is not None and not 1 <= args.adaptive <= 4:
        raise CfmInputError(f"--adaptive must be 1..4 significant digits; got {args.adaptive}")
    check_seed(args.seed)
    # the conflict first: installing Dask, as the next check would say, would not help
    if args.adaptive is not None and (args.scheduler is not None or args.workers is not None):
        raise CfmInputError(
            "--adaptive stops on the pooled result of all points and cannot be split over Dask "
            "workers; drop --scheduler/--workers or --adaptive"
        )
    check_scale_out(args.scheduler, args.workers)
    check_out_dir(args.out)


def run(args) -> int:
    check_options(args)
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args)


def _run(args) -> int:
    from ..io.bench_toml import read_bench, read_reference_bench
    from ..io.kinematics_out import kinematics_summary, write_kinematics
    from ..io.provenance import bench_input, provenance
    from ..models.kinematics.budget import gum_check, uncertainty_budget
    from ..models.kinematics.monte_carlo import run_kinematics
    from ..workflows.sweep.distributed import dask_client, run_kinematics_dask

    bench = read_reference_bench() if args.bench is None else read_bench(args.bench)
    npts = len(bench.grid_points())
    passes = 1 if args.fast_intervals else 2
    print(
        f"cfm-fem kinematics: {bench.name} ({bench.source}); {npts} points; "
        + (f"adaptive to {args.adaptive} digits" if args.adaptive else f"{args.trials} trials")
        + f", seed {args.seed}",
        file=sys.stderr,
    )
    on_dask = args.scheduler is not None or args.workers is not None
    if not on_dask:  # (Dask workers compile in their own processes)
        from .. import _kernels

        note_first_compile(_kernels.pass_keep)
    if on_dask:
        with dask_client(args.scheduler, args.workers) as client:
            with progress_bar(npts, "points") as bar:
                res = run_kinematics_dask(
                    client,
                    bench,
                    args.trials,
                    args.seed,
                    exact=not args.fast_intervals,
                    progress=bar.update,
                )
    else:
        total = None if args.adaptive else args.trials
        with progress_bar(total, "trials") as bar:
            res = run_kinematics(
                bench,
                trials=args.trials,
                seed=args.seed,
                exact=not args.fast_intervals,
                adaptive_digits=args.adaptive,
                progress=_per_pass(bar.update, 1 if args.adaptive else passes),
            )
    budget = uncertainty_budget(bench, res.q_cmd)
    gum = gum_check(bench, res)
    prov = provenance({"bench": bench_input(args.bench)}, args.command_line)  # packaged or given
    prov.update(
        bench_name=bench.name,
        seed=int(args.seed),
        trials=int(res.trials),
        backend=(
            f"dask scheduler {args.scheduler}"
            if args.scheduler
            else f"dask LocalCluster, {args.workers} worker process(es)"
            if args.workers
            else "this process (numba threads)"
        ),
    )
    summary = kinematics_summary(res, bench, budget=budget, gum=gum, extra={"provenance": prov})
    paths = write_kinematics(args.out, res, bench, summary)
    from ..io.run_files import write_run
    from ..report.kinematics import kinematics_report  # matplotlib: loaded only when used

    rep = kinematics_report(res, summary)
    report = write_run(args.out, {**rep.images, "report.html": rep.render()})
    print_table_iv(summary)
    print(f"wrote {paths['summary']}, {paths['csv']}, {paths['vtu']}, {report[-1]}")
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


def _per_pass(update, passes: int):
    """A progress callback for work that runs every trial ``passes`` times (the exact
    intervals take a second pass): it advances ``update`` in trials, so that the bar of a
    20,000-trial run ends at 20,000 trials."""
    state = {"draws": 0, "shown": 0}

    def step(n: int = 1) -> None:
        state["draws"] += n
        now = state["draws"] // passes
        if now > state["shown"]:
            update(now - state["shown"])
            state["shown"] = now

    return step
