"""Write a synthetic recording of one simulated bench (a CSV in the recording contract).

tracker: a laser-tracker recording of a grid over the strokes (and a bidirectional ISO 230-2
run along one axis); hall: a Hall map of a multipole (QFDp4 by default) on the mid-plane y = 0,
measured by the simulated bench and the paper's S_HP probe. The bench's errors are one draw from
its PDFs; the same seed gives the same file. Feed the file to `cfm-fem compare` or
`cfm-fem diagnose`.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from ..errors import CfmInputError
from ._checks import check_seed, number_list

NAME = "synth"
HELP = "write a synthetic tracker recording or Hall map of a simulated bench (CSV)"


def add_args(p):
    p.add_argument("kind", choices=["tracker", "hall"], help="which recording")
    p.add_argument("--out", required=True, metavar="FILE.csv", help="the CSV to write")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--bench", metavar="B.toml", help="bench file (default: the reference bench)")
    p.add_argument("--reps", type=int, metavar="N", help="repetitions (default 5 / 10)")
    g = p.add_argument_group("tracker")
    g.add_argument("--grid", default="3,3,3", metavar="NX,NY,NZ",
                   help="grid points per axis over the strokes (default 3,3,3)")  # fmt: skip
    g.add_argument("--tracker-std-um", type=float, default=0.0, metavar="UM",
                   help="tracker noise per coordinate, um (default 0)")  # fmt: skip
    g.add_argument("--iso-axis", choices=["x", "y", "z", "none"], default="x",
                   help="axis of the bidirectional ISO 230-2 run (default x)")  # fmt: skip
    g.add_argument("--reversal-um", type=float, default=0.0, metavar="UM",
                   help="reversal added to the ISO run, um (default 0)")  # fmt: skip
    g.add_argument("--drift-um-per-s", type=float, default=0.0, metavar="R",
                   help="thermal drift along z, um per s of recording (default 0)")  # fmt: skip
    g = p.add_argument_group("hall")
    g.add_argument("--harmonics", metavar="H.csv",
                   help="magnet as a harmonics file (default: the paper's QFDp4)")  # fmt: skip
    g.add_argument("--r-ref", type=float, metavar="MM",
                   help="R_ref of a harmonics file that does not state it")  # fmt: skip
    g.add_argument("--magnet-offset", default="0,0", metavar="DX,DY",
                   help="true transverse offset of the magnet, mm (default 0,0)")  # fmt: skip


def _numbers(text, count, option, kind=float):
    v = number_list(text, option, count)
    if kind is int:
        if any(x != int(x) for x in v):
            raise CfmInputError(f"{option} must be {count} comma-separated whole numbers; "
                                f"got {text!r}")  # fmt: skip
        v = [int(x) for x in v]
    return v


def _check(args):
    check_seed(args.seed)
    out = Path(args.out)
    try:
        is_dir, parent_is_dir = out.is_dir(), out.parent.is_dir()
        is_file = out.exists() and not is_dir
        if is_file:  # stat() it too: a name the file system refuses fails here, not later
            out.stat()
    except OSError as exc:  # a name too long, a loop of links, ...
        raise CfmInputError(
            f"--out {args.out!r} cannot be used: {exc.strerror or exc}; expected a file name "
            "the file system takes"
        ) from None
    if is_dir:
        raise CfmInputError(f"--out {args.out!r} is a folder; expected a file name (FILE.csv)")
    if not parent_is_dir:
        raise CfmInputError(f"--out {args.out!r}: folder {str(out.parent)!r} does not exist")
    if args.reps is not None and args.reps < 1:
        raise CfmInputError(f"--reps must be >= 1; got {args.reps}")
    given = {"tracker": [("--harmonics", args.harmonics), ("--r-ref", args.r_ref)],
             "hall": [("--tracker-std-um", args.tracker_std_um or None),
                      ("--reversal-um", args.reversal_um or None),
                      ("--drift-um-per-s", args.drift_um_per_s or None)]}  # fmt: skip
    wrong = [o for o, v in given[args.kind] if v is not None]
    if wrong:
        raise CfmInputError(f"{', '.join(wrong)}: not an option of 'synth {args.kind}'")
    if args.tracker_std_um < 0:
        raise CfmInputError(f"--tracker-std-um must be >= 0; got {args.tracker_std_um}")
    grid = _numbers(args.grid, 3, "--grid", int)
    if min(grid) < 1:
        raise CfmInputError(f"--grid counts must be >= 1; got {args.grid!r}")
    _check_rows(args, grid)
    return grid, _numbers(args.magnet_offset, 2, "--magnet-offset")


#: Bytes a synthetic recording holds per row until it is written: its arrays (positions,
#: ids, directions, the bench chain's intermediates) and the text of its CSV row.
ROW_BYTES = 1000


def _check_rows(args, grid) -> None:
    """Refuse a recording whose rows do not fit in memory, before any is made."""
    from ..threads import check_memory

    if args.kind == "tracker":
        what, points = "--grid and --reps", math.prod(grid)
        reps = args.reps or 5
    else:
        from ..workflows.synthetic import hall_map_points

        what, points = "--reps", len(hall_map_points())
        reps = args.reps or 10
    check_memory(f"synth {args.kind} {what}", points * reps, ROW_BYTES, "rows")


def _given(args) -> str:
    """The numeric options of ``args`` that differ from their defaults, as typed."""
    options = [("--grid", args.grid, "3,3,3"), ("--reps", args.reps, None),
               ("--tracker-std-um", args.tracker_std_um, 0.0),
               ("--reversal-um", args.reversal_um, 0.0),
               ("--drift-um-per-s", args.drift_um_per_s, 0.0),
               ("--magnet-offset", args.magnet_offset, "0,0"),
               ("--r-ref", args.r_ref, None)]  # fmt: skip
    return ", ".join(f"{o} {v:g}" if isinstance(v, float) else f"{o} {v}"
                     for o, v, default in options if v != default)  # fmt: skip


def run(args) -> int:
    grid, offset = _check(args)
    from ..io.bench_toml import resolve_bench
    from ..io.harmonics import read_harmonics, read_qfdp4
    from ..io.recordings import write_hall_map, write_tracker
    from ..workflows.synthetic import synthetic_hall_map, synthetic_tracker

    bench, _ = resolve_bench(args.bench)
    if args.kind == "tracker":
        rec = synthetic_tracker(
            bench, seed=args.seed, reps=args.reps or 5, grid=grid,
            tracker_std_um=args.tracker_std_um,
            iso_axis=None if args.iso_axis == "none" else args.iso_axis,
            reversal_um=args.reversal_um, drift_um_per_s=args.drift_um_per_s,
        )  # fmt: skip
        write = write_tracker
    else:
        magnet = (
            read_qfdp4()
            if args.harmonics is None
            else read_harmonics(args.harmonics, r_ref_mm=args.r_ref)
        )
        rec = synthetic_hall_map(
            magnet, bench, seed=args.seed, reps=args.reps or 10, magnet_offset_mm=offset
        )
        write = write_hall_map
    comments = [f"synthetic: {rec.source}", f"written by: {args.command_line}"]
    try:
        write(args.out, rec, comments=comments)
    except CfmInputError as exc:  # the numbers come from the options: name those given
        raise CfmInputError(f"{exc.what} (options given: {_given(args) or 'none'})",
                            file=exc.file) from None  # fmt: skip
    print(f"wrote {args.out} ({len(rec)} rows; {rec.source})", file=sys.stderr)
    return 0
