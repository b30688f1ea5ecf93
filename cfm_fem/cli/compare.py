"""Simulation against recordings (CSV, one header row, '#' comments; optional columns t_s,
dir_x, dir_y, dir_z, speed, temp_C).

``--tracker REC.csv``: Table IV of the recording and of the kinematic Monte Carlo at the same
commanded positions, per-point standardised residuals, the Fig. 12 view and ISO 230-2 for any
bidirectional single-axis runs in the recording. ``--hall-map REC.csv --reference FIELD``: Table V
of the map against the reference field (harmonics or FEM export) and of the coupled Monte Carlo,
the Fig. 13 view. Writes DIR/compare.json, DIR/points.csv, DIR/report.html and PNG figures.
"""

from __future__ import annotations

from ..errors import CfmInputError
from ._checks import check_out_dir
from ._progress import announcer, progress_bar
from ._reader import (
    add_field_model_arg,
    add_reader_args,
    add_recording_args,
    read_recording_args,
    reader_kwargs,
)
from .coupled import add_common, check_common

NAME = "compare"
HELP = "recordings against the simulation: Table IV / Fig. 12 (tracker), Table V / Fig. 13 (Hall)"


def add_args(p):
    add_recording_args(p)
    p.add_argument(
        "--reference",
        metavar="FIELD",
        help="reference field of a Hall map: harmonics .csv (n,Bn,An) or an FEM export",
    )
    p.add_argument(
        "--tracker-u-um",
        type=float,
        default=0.0,
        metavar="UM",
        help="standard uncertainty of the tracker, added to the simulated std in the "
        "residuals (default 0; the paper's LT: 5)",
    )
    p.add_argument(
        "--no-budget",
        action="store_true",
        help="Hall map: skip the positioning-only / probe-only split",
    )
    add_common(p)
    add_reader_args(p, "--reference", "when it is a field map (not a harmonics .csv)")
    add_field_model_arg(p, "--reference")


def run(args) -> int:
    from ..workflows.compare_run import check_options

    check_out_dir(args.out)
    check_common(args)
    if args.hall_map is not None and not args.reference:
        raise CfmInputError("--hall-map needs --reference FIELD (harmonics .csv or FEM export)")
    kind = "tracker" if args.tracker is not None else "hall"
    check_options(kind, args.reference, args.tracker_u_um, reader_kwargs(args))
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args)


def _run(args) -> int:
    from ..workflows.compare_run import run_compare

    rec = read_recording_args(args)
    with progress_bar(None, "trials") as bar:
        res = run_compare(
            rec, args.reference, args.bench, trials=args.trials, seed=args.seed,
            tracker_u_um=args.tracker_u_um, probe=args.probe, align=args.align,
            centre_magnet=args.centre_magnet, b_ref_T=args.b_ref, r_ref_mm=args.r_ref,
            field_model=args.field_model, reader=reader_kwargs(args), budget=not args.no_budget,
            command_line=args.command_line, progress=bar.update,
            on_start=announcer(bar, "compare"),
        )  # fmt: skip
    paths = res.write(args.out)
    (_print_tracker if args.tracker is not None else _print_hall)(res.summary)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


def _print_tracker(s: dict) -> None:
    t = s["table_iv"]
    print(
        f"Table IV, E_p [um]: {s['points']} points, {s['readings']} readings; simulation "
        f"{s['trials']} trials, seed {s['seed']}"
    )
    print(
        f"{'axis':6}{'exp sys':>9}{'exp std':>9}{'sim sys':>9}{'sim std':>9}"
        f"{'z RMS':>8}{'|z|>2':>7}  Fig. 12"
    )
    for r in s["fig12"]:
        a = r["name"]
        e, m = t["experiment"][a], t["simulation"][a]
        pp = s["per_point"]
        print(
            f"{a.upper():6}{e['systematic_um']:9.1f}{e['std_um']:9.1f}{m['systematic_um']:9.1f}"
            f"{m['std_um']:9.1f}{pp['z_rms'][a]:8.2f}{pp['fraction_abs_z_above_2'][a]:7.2f}  "
            + ("overlap" if r["overlap"] else "NO overlap")
        )
    for line in s["iso230_2"]:
        v = line["axis_values_um"]
        print(
            f"ISO 230-2 {line['axis'].upper()} at {line['fixed_mm']} mm: "
            + ", ".join(f"{k} {v[k]:.2f}" for k in ("A", "E", "M", "R", "B", "B_mean"))
            + " um"
        )
    for note in s["notes"]:
        print(f"note: {note}")


def _print_hall(s: dict) -> None:
    t = s["table_v"]
    print(
        f"Table V, E_f [units of 1e-4 B_ref = {s['b_ref_T']:.6g} T]: {s['points']} points, "
        f"{s['readings']} readings; simulation {s['trials']} trials, seed {s['seed']}"
    )
    print(
        f"{'':8}{'exp sys':>9}{'exp std':>9}{'exp U_f':>9}{'sim sys':>9}{'sim std':>9}"
        f"{'sim U_f':>9}  Fig. 13"
    )
    for r in s["fig13"]:
        q = r["name"]
        e, m = t["experiment"][q], t["simulation"][q]
        print(
            f"{q:8}{e['systematic_units']:9.2f}{e['std_units']:9.2f}{e['U_f_units']:9.2f}"
            f"{m['systematic_units']:9.2f}{m['std_units']:9.2f}{m['U_f_units']:9.2f}  "
            + ("overlap" if r["overlap"] else "NO overlap")
        )
    for note in s["notes"]:
        print(f"note: {note}")
