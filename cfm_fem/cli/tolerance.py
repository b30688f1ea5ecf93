"""Design in reverse: for a target U_p per axis, how far can each geometric tolerance go?

Ranks the 21 errors of a bench by their share of U_p^2 = sys^2 + u^2 (up_share: linearised model
with exact HTM sensitivities, Table IV pooling; negative for an error whose mean error opposes the
total systematic error) and reports, for each, the factor by which its tolerance could
be loosened (> 1) or must be tightened (< 1) on its own to meet the target, the U_p that
results, a common factor for all errors, and a short plan that tightens the largest contributors
first. ``--check N`` verifies the plan's U_p with an N-trial Monte Carlo of the full model.
"""

from __future__ import annotations

import textwrap

import numpy as np

from ..errors import CfmInputError
from . import option_type
from ._checks import check_out_dir, trial_count_type
from ._progress import progress_bar

NAME = "tolerance"
HELP = "design in reverse: loosen/tighten the 21 tolerances to meet a target U_p per axis"


def _target(text):
    from ._checks import number_list

    v = number_list(text, "--target", (1, 3), "numbers in um")
    if len(v) == 1:
        v = v * 3
    if len(v) != 3 or any(not (x > 0) for x in v):
        raise CfmInputError(f"--target must be one or three positive numbers in um; got {text!r}")
    return v


def add_args(p):
    p.add_argument(
        "--target",
        required=True,
        type=option_type(_target, "--target"),
        metavar="UX[,UY,UZ]",
        help="target U_p per axis in um (one value for all axes, or X,Y,Z)",
    )
    p.add_argument(
        "--bench", metavar="B.toml", help="bench file (default: the CFM reference bench)"
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="write DIR/tolerance.json, DIR/bench_plan.toml and DIR/report.html",
    )
    p.add_argument(
        "--check",
        type=trial_count_type("--check"),
        default=0,
        metavar="N",
        help="verify the plan with an N-trial Monte Carlo of the exact model (0: skip)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="seed of the check (default 0)")


def run(args) -> int:
    from ..workflows.tolerance import check_options

    if args.out:
        check_out_dir(args.out)
    check_options(args.target, args.check, args.seed)
    if not args.out:
        return _run(args)
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args)


def _run(args) -> int:
    from ..workflows.tolerance import run_tolerance

    if not args.check:
        res = run_tolerance(args.target, args.bench, seed=args.seed)
    else:
        with progress_bar(args.check, "trials") as bar:
            res = run_tolerance(args.target, args.bench, check_trials=args.check,
                                seed=args.seed, progress=bar.update)  # fmt: skip
    _print(res.design)
    if args.out:
        res.write(args.out, getattr(args, "command_line", None))
        print(f"wrote {args.out}/tolerance.json, bench_plan.toml and report.html")
    return 0


def _fmt3(v):
    return " / ".join(f"{x:5.1f}" for x in v)


def _print(d):
    print(f"target U_p X / Y / Z  [um]: {_fmt3(d['target_um'])}")
    print(f"current U_p (linearised):   {_fmt3(d['current_um'])}")
    print(f"floor (vibration + delay):  {_fmt3(d['noise_floor_um'])}")
    print(f"{'error':14}{'tolerance now':>26}{'up_share X/Y/Z %':>26}{'factor':>9}   U_p at factor")
    for r in d["rows"]:
        sh = " / ".join(f"{100 * r['up_share'][a]:5.1f}" for a in "xyz")
        f = r["factor"]
        if f is None:
            fs, up = "cannot", "no factor meets the target alone"
        elif not np.isfinite(f):
            fs, up = "free", "-"
        else:
            fs, up = f"{f:9.3g}", _fmt3(r["up_at_factor_um"])
        print(f"{r['name']:14}{r['pdf']:>26}{sh:>26}{fs:>9}   {up}")
    from ..models.kinematics.budget import UP_SHARE_MEANING

    print(textwrap.fill(f"{UP_SHARE_MEANING}.", width=100, subsequent_indent="  "))
    print(
        f"common factor for all 21 tolerances: {d['common_factor']:.3g} "
        f"-> U_p {_fmt3(d['up_at_common_um'])} um"
    )
    if d["plan"]:
        steps = ", ".join(f"{s['name']} x{s['factor']:.3g}" for s in d["plan"])
        print(
            f"plan (largest contributors first): {steps} -> U_p {_fmt3(d['up_after_plan_um'])} um"
        )
    else:
        print("the target is met with the current tolerances; factors > 1 say how far each may go")
    if "plan_check_mc" in d:
        c = d["plan_check_mc"]
        print(
            f"Monte Carlo check of the plan ({c['trials']} trials): U_p "
            + _fmt3([c[a]["U_p_um"] for a in "xyz"])
            + " um"
        )
    if not d["feasible"]:
        print("note: the target is below the vibration + delay floor on some axis; unreachable")
    print(f"method: {d['method']}")
