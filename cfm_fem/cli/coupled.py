"""Coupled mechanical-magnetic Monte Carlo (paper eq. 12-14): the field error E_f per point from
the bench's positioning errors and the Hall probe together, pooled as the paper's Table V.

Writes DIR/summary.json (Table V beside the paper, B_ref, R_ref, region, every assumption),
DIR/points.csv (per point and component), DIR/report.html and its PNG figures.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CfmInputError
from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import progress_bar
from ._reader import (
    add_field_model_arg,
    add_reader_args,
    reader_kwargs,
    refuse_reader_options,
)

if TYPE_CHECKING:
    from ..models.field_model import FieldModel

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
    if args.trials < 20:
        raise CfmInputError(f"--trials must be >= 20; got {args.trials}")
    check_seed(args.seed)


def load_bench(args):
    """The bench (reference bench by default), centred when ``--centre-magnet``; and a note."""
    from ..io.bench_toml import read_bench, read_reference_bench
    from ..workflows.coupled import centred_on_travel

    bench = read_reference_bench() if args.bench is None else read_bench(args.bench)
    if args.centre_magnet:
        return centred_on_travel(bench), "magnet moved to mid-travel of X and Y (--centre-magnet)"
    return bench, None


def _parse_z(text):
    from ._checks import number_list

    return number_list(text, "--z", what="numbers in mm")


#: Most scan points of --radius/--step: each point is a full Monte Carlo of --trials (default
#: 1e5) probe positions, so 100,000 points are already hours; --step 0.002 (metres typed as mm)
#: would ask for 78.5 million points and a 1.2 GB array before the run.
MAX_REGION_POINTS = 100_000


def _region(args, fm: FieldModel):
    from ..workflows.coupled import default_region

    z = None if args.z is None else _parse_z(args.z)
    if fm.multipole is not None:
        r = fm.multipole.r_ref if args.radius is None else args.radius
        z = [-100.0, -50.0, 0.0, 50.0, 100.0] if z is None else z
        what = f"R_ref = {fm.multipole.r_ref:g} mm" if args.radius is None else "--radius"
    else:
        pts = fm.fieldmap.points
        half = min(np.abs(pts[:, 0]).max(), np.abs(pts[:, 1]).max())
        r = 0.8 * half if args.radius is None else args.radius
        if z is None:
            z0, z1 = pts[:, 2].min(), pts[:, 2].max()
            z = list(np.linspace(0.75 * z0 + 0.25 * z1, 0.25 * z0 + 0.75 * z1, 5))
        what = "0.8 x the map's transverse extent" if args.radius is None else "--radius"
    if not (r > 0 and args.step > 0):
        raise CfmInputError("--radius and --step must be > 0 mm")
    n_est = np.pi * (r / args.step) ** 2 * len(z)  # grid points inside the circle, all planes
    if not n_est <= MAX_REGION_POINTS:
        raise CfmInputError(
            f"--step {args.step:g} mm inside r <= {r:g} mm ({what}) on {len(z)} plane(s) asks "
            "for about "
            f"{n_est:.3g} scan points; expected at most {MAX_REGION_POINTS:,} (the step is in mm: "
            f"{r * np.sqrt(np.pi * len(z) / MAX_REGION_POINTS):.2g} mm or more here)"
        )
    pts = default_region(r, args.step, z)
    desc = (
        f"transverse grid step {args.step:g} mm inside r <= {r:g} mm ({what}), "
        f"z planes {', '.join(f'{v:g}' for v in z)} mm (magnet frame); {len(pts)} points"
    )
    return pts, desc


def _check_region_inside(args, fm, points, field_path) -> None:
    """Name the map and the options when the scan region leaves a field map (the default region
    is centred on the z axis, which a map need not be)."""
    if fm.multipole is not None:
        return
    _, inside = fm.field(points)
    if inside.all():
        return
    i = int(np.argmax(~inside))
    pts = fm.fieldmap.points
    span = ", ".join(
        f"{a} {lo:g}..{hi:g}" for a, lo, hi in zip("xyz", pts.min(0), pts.max(0), strict=True)
    )
    why = "the default region is centred on the z axis: " if args.radius is None else ""
    raise CfmInputError(
        f"scan point {points[i].tolist()} mm is outside the field map, which spans {span} mm; "
        f"{why}set --radius and --z to a region inside the map",
        file=field_path,
    )


def run(args) -> int:
    check_out_dir(args.out)
    check_common(args)
    if args.field is None:
        refuse_reader_options(args, "without --field the bundled QFDp4 harmonics are used")
        if args.field_model != "linear":
            raise CfmInputError(
                "--field-model applies to a field map given with --field; without --field the "
                "bundled QFDp4 harmonics are used"
            )
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):  # one run at a time in --out
        return _run(args)


def _run(args) -> int:
    from ..io.compare_out import coupled_points_csv, coupled_summary
    from ..io.harmonics import qfdp4_path, read_qfdp4
    from ..io.provenance import bench_input, provenance
    from ..io.reference_field import read_reference
    from ..io.run_files import write_run
    from ..models.field_model import FieldModel
    from ..models.kinematics.budget import uncertainty_budget
    from ..models.probe import HallProbe
    from ..workflows.coupled import field_budget, run_coupled

    bench, bench_note = load_bench(args)
    if args.field is None:
        fm = FieldModel.from_multipole(read_qfdp4())
        field_path = qfdp4_path()
    else:
        fm = read_reference(
            args.field, b_ref_T=args.b_ref, r_ref_mm=args.r_ref,
            field_model=args.field_model, **reader_kwargs(args),
        )  # fmt: skip
        field_path = args.field
    points, region = _region(args, fm)
    _check_region_inside(args, fm, points, field_path)
    probe = HallProbe(model=args.probe)
    print(
        f"cfm-fem coupled: {fm.describe()}; {region}; {args.trials} trials, seed {args.seed}, "
        f"align {args.align}",
        file=sys.stderr,
    )
    with progress_bar(len(points), "points") as bar:
        res = run_coupled(
            fm,
            bench,
            points,
            probe=probe,
            trials=args.trials,
            seed=args.seed,
            align=args.align,
            region=region,
            progress=bar.update,
        )
    fb = None
    if not args.no_budget:
        fb = field_budget(
            fm,
            bench,
            points,
            probe=probe,
            trials=min(args.trials, 20_000),
            seed=args.seed,
            align=args.align,
        )
    if bench_note:
        res.notes.append(bench_note)
    prov = provenance({"bench": bench_input(args.bench), "field": field_path}, args.command_line)
    summary = coupled_summary(
        res,
        bench,
        field_budget=fb,
        bench_budget=uncertainty_budget(bench, res.q_cmd),
        extra={"provenance": prov},
    )
    from ..report.runs import coupled_report  # matplotlib: loaded only when used

    rep = coupled_report(res, summary, args.command_line)
    files = {"summary.json": summary, "points.csv": coupled_points_csv(res)}
    files.update(rep.images)
    files["report.html"] = rep.render()
    paths = write_run(args.out, files)
    print_table_v(summary)
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
