"""Field quality of a map (integrated harmonics b_n, a_n at R_ref, magnetic centre, roll,
magnetic length) and how well a bench determines it: U95 of each by Monte Carlo, with the
scan points perturbed by N(0, U_p) (--up) or placed by the bench model (--mode htm), and the
budget by error group.

Writes DIR/quality.json, DIR/planes.csv (harmonics per plane), DIR/report.html and its figures.
"""

from __future__ import annotations

import sys

from ..errors import CfmInputError
from ._checks import check_out_dir, check_seed, trial_count_type
from ._progress import progress_bar
from ._reader import add_reader_args, reader_kwargs

NAME = "quality"
HELP = "field quality (b_n, a_n, centre, roll, length) of a map and its U95 from the bench"


def add_args(p):
    p.add_argument("field", metavar="FIELD", help="field map (VTU, COMSOL text, Opera, CSV, ...)")
    p.add_argument("--r-ref", type=float, required=True, metavar="MM",
                   help="reference radius of the harmonics, mm")  # fmt: skip
    src = p.add_mutually_exclusive_group()
    src.add_argument("--up", type=float, metavar="UM",
                     help="mode gauss: scan points moved by N(0, U_p^2) per axis, um")  # fmt: skip
    src.add_argument(
        "--mode",
        choices=["gauss", "htm"],
        help="htm (default without --up): the bench model places the probe",
    )
    p.add_argument(
        "--bench",
        metavar="B.toml",
        help="bench file of mode htm (default: the CFM reference bench)",
    )
    p.add_argument(
        "--centre-magnet",
        action="store_true",
        help="mode htm: move the magnet origin to mid-travel of X and Y",
    )
    p.add_argument(
        "--trials",
        type=trial_count_type(),
        metavar="N",
        help="fixed number of trials (default: adaptive, JCGM 101 7.9.4)",
    )
    p.add_argument(
        "--max-trials",
        type=trial_count_type("--max-trials"),
        default=20_000,
        metavar="N",
        help="cap of the adaptive procedure (default 20000; on the bundled quadrupole the "
        "1-digit rule stops near 11000 trials)",
    )
    p.add_argument("--digits", type=int, default=1, choices=[1, 2],
                   help="significant digits the adaptive procedure asks of each standard "
                   "deviation (default 1)")  # fmt: skip
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--probe", choices=["exact", "paper", "table1"], default="paper",
                   help="Hall probe errors, one draw per scan: paper (S_HP, default), table1 "
                   "(Table I: gains, offsets, non-orthogonality) or exact")  # fmt: skip
    p.add_argument(
        "--main-order",
        type=int,
        metavar="N",
        help="main harmonic (default: the largest integrated one)",
    )
    p.add_argument(
        "--sampling",
        choices=["auto", "nodes", "circles"],
        default="auto",
        help="nodes: the map's nodes in its z planes; circles: circles read from the "
        "model between nodes; auto (default): nodes when the map lies in z planes",
    )
    p.add_argument("--radius", type=float, metavar="MM",
                   help="disk (nodes) or circle radius, mm (default: the disk the map covers, "
                   "0.9 of it for circles)")  # fmt: skip
    p.add_argument(
        "--dz",
        type=float,
        metavar="MM",
        help="plane spacing of the circle sampling, mm (default: the larger of the median "
        "node spacing and a quarter of the circle radius)",
    )
    p.add_argument(
        "--angles", type=int, default=64, metavar="K", help="points per circle (default 64)"
    )
    p.add_argument("--tolerances", metavar="FILE",
                   help="CSV 'quantity,tolerance' (b3,2 / centre_x_um,20 / roll_mrad,0.3 / "
                   "magnetic_length_mm,0.5 ...) shown against U95")  # fmt: skip
    p.add_argument(
        "--budget-trials",
        type=trial_count_type("--budget-trials"),
        default=200,
        metavar="N",
        help="trials per error group of the budget (default 200)",
    )
    p.add_argument("--no-budget", action="store_true", help="skip the budget by error group")
    beam = p.add_mutually_exclusive_group()
    beam.add_argument("--rigidity", type=float, metavar="TM",
                      help="track a particle of this rigidity B rho (T m) along the axis "
                      "through the map: deflection and sagitta (dipoles)")  # fmt: skip
    beam.add_argument(
        "--energy",
        type=float,
        metavar="GEV",
        help="or give its kinetic energy, GeV (with --particle)",
    )
    p.add_argument(
        "--particle",
        choices=["electron", "proton"],
        default="electron",
        help="particle of --energy (default electron)",
    )
    p.add_argument(
        "--trajectory-step",
        type=float,
        default=0.5,
        metavar="MM",
        help="Runge-Kutta step of the trajectory, mm (default 0.5)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_reader_args(p, "FIELD")
    p.add_argument("--field-model", choices=["harmonic", "linear"], default="harmonic",
                   help="the field between the map's nodes, for displaced readings and circles: "
                   "per node a least-squares fit of a harmonic potential's gradient (default), "
                   "or linear interpolation in the map's cells")  # fmt: skip


def _check(args):
    check_out_dir(args.out)
    check_seed(args.seed)
    if not (args.r_ref > 0 and args.r_ref < float("inf")):
        raise CfmInputError(f"--r-ref must be a positive radius in mm; got {args.r_ref:g}")
    if args.up is not None and not (0 <= args.up < float("inf")):
        raise CfmInputError(f"--up must be a length >= 0 in um; got {args.up:g}")
    if args.trials is not None and args.trials < 20:
        raise CfmInputError(f"--trials must be >= 20; got {args.trials}")
    for opt, v, low in (("--max-trials", args.max_trials, 20),
                        ("--budget-trials", args.budget_trials, 20),
                        ("--angles", args.angles, 3)):  # fmt: skip
        if v < low:
            raise CfmInputError(f"{opt} must be >= {low}; got {v}")
    for opt, v, what in (
        ("--radius", args.radius, "length in mm"),
        ("--dz", args.dz, "length in mm"),
        ("--rigidity", args.rigidity, "rigidity in T m"),
        ("--energy", args.energy, "kinetic energy in GeV"),
        ("--trajectory-step", args.trajectory_step, "length in mm"),
    ):
        if v is not None and not (0 < v < float("inf")):
            raise CfmInputError(f"{opt} must be a positive {what}; got {v:g}")
    if args.mode == "gauss" and args.up is None:
        raise CfmInputError("--mode gauss needs --up UM")
    if args.up is not None and (args.bench or args.centre_magnet):
        raise CfmInputError("--bench and --centre-magnet apply to mode htm, not to --up")


def run(args) -> int:
    _check(args)
    from ..io.lock import output_lock

    with output_lock(args.out, args.command_line):
        return _run(args)


def _run(args) -> int:
    from ..io.provenance import bench_input, provenance
    from ..workflows.quality import run_quality

    mode = "gauss" if args.up is not None else "htm"
    inputs = {"field": args.field, "tolerances": args.tolerances}
    if mode == "htm":
        inputs["bench"] = bench_input(args.bench)
    prov = provenance(inputs, args.command_line)
    with progress_bar(args.trials, "trials") as bar:

        def set_total(n: int) -> None:
            bar.total = n
            bar.refresh()

        res = run_quality(
            args.field, args.r_ref, up_um=args.up, mode=mode, bench=args.bench,
            trials=args.trials, seed=args.seed, main_order=args.main_order, probe=args.probe,
            field_model=args.field_model, sampling=args.sampling, radius_mm=args.radius,
            dz_mm=args.dz, n_angles=args.angles, centre_magnet=args.centre_magnet,
            tolerances=args.tolerances, budget=not args.no_budget,
            budget_trials=args.budget_trials, digits=args.digits, max_trials=args.max_trials,
            rigidity_Tm=args.rigidity, energy_gev=args.energy, particle=args.particle,
            trajectory_step_mm=args.trajectory_step,
            reader=reader_kwargs(args), provenance=prov, progress=bar.update,
            progress_total=set_total,
        )  # fmt: skip
    paths = res.write(args.out, args.command_line)
    _print_summary(res.summary)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


def _print_summary(s: dict) -> None:
    u = s.get("uncertainty") or {}

    def pm(v, e, scale=1.0, digits=4):
        v = "-" if v is None else f"{v * scale:.{digits}g}"
        return v if e is None else f"{v} +- {e * scale:.2g}"

    tol = u.get("numerical_tolerance") or {}
    how = ""
    if tol.get("converged") is not None:
        how = (f"; the adaptive rule reached {tol['digits']} digit(s)" if tol["converged"]
               else "")  # fmt: skip
    print(f"main order {s['main_order']}, R_ref = {s['r_ref_mm']:g} mm, z "
          f"{s['z_range_mm'][0]:g} .. {s['z_range_mm'][1]:g} mm; U95 from {u.get('trials')} "
          f"trials (mode {u.get('mode')}, seed {u.get('seed')}{how})",
          file=sys.stderr)  # fmt: skip
    c, uc = s["centre_mm"], s["U95_centre_mm"] or [None, None]
    print(f"centre x {pm(c[0], uc[0], 1e3)} um, y {pm(c[1], uc[1], 1e3)} um")
    print(f"roll {pm(s['roll_mrad'], s['U95_roll_mrad'])} mrad")
    print(f"magnetic length {pm(s['magnetic_length_mm'], s['U95_magnetic_length_mm'], 1, 6)} mm")
    t = s.get("trajectory")
    if t:
        print(f"trajectory (B rho = {t['rigidity_Tm']:.6g} T m, step {t['step_mm']:g} mm): "
              f"deflection {pm(t['deflection_mrad'], t['U95_deflection_mrad'], 1, 6)} mrad, "
              f"sagitta {t['sagitta_mm']:.4g} mm")  # fmt: skip
    integ = s["integrated"]
    for k in range(len(integ["n"])):
        ub = (integ["U95_b_n_units"] or [None] * 15)[k]
        ua = (integ["U95_a_n_units"] or [None] * 15)[k]
        print(f"  n={k + 1:2d}  b {pm(integ['b_n_units'][k], ub):>22}  "
              f"a {pm(integ['a_n_units'][k], ua):>22}  units")  # fmt: skip
    for note in s["notes"]:
        print(f"note: {note}", file=sys.stderr)
