"""Find what the simulation left out: calibrate the bench model to tracker or Hall-map
recordings, locate significant residuals, attribute them to catalogued physical effects by nested
model comparison and held-out error, model them and advise. Writes DIR/diagnosis.json,
DIR/report.html with PNG plots, and residual maps DIR/residual_*.vtu.

--reference FIELD: a field map (any format cfm-fem reads), a harmonics CSV (2-D multipole), or
'fit:DEG' / 'fitz:DEG' to fit a curl- and div-free harmonic polynomial of degree DEG to the map
itself (global, or in z windows). A 3-D field map is read between its nodes by the harmonic
fits of its nodes, exact at the nodes (--field-model auto, the default), and where the fits fail
Laplace's test (a measured map, currents or iron) linearly corrected by the field's curvature
from differences of its node values; a planar map linearly. Either way the reference's own
error between its nodes (and a measured map's own noise) is estimated and added to the noise.
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
    refuse_reader_options,
)

NAME = "diagnose"
HELP = "sim vs real: locate the mismatch, name the physics, model it (tracker or Hall map)"


def add_args(p):
    add_recording_args(p)
    p.add_argument(
        "--reference",
        metavar="FIELD",
        help="reference field of a Hall map: harmonics .csv (n,Bn,An), an FEM export, or "
        "fit:DEG / fitz:DEG (a harmonic polynomial fitted to the recording)",
    )
    p.add_argument("--bench", metavar="B.toml", help="bench file (default: the reference bench)")
    p.add_argument("--b-ref", type=float, metavar="T", help="reference field of units (T)")
    p.add_argument(
        "--r-ref",
        type=float,
        metavar="MM",
        help="R_ref for a harmonics file that does not state it",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--no-report",
        action="store_true",
        help="write diagnosis.json and the residual maps only, no report.html and plots "
        "(batch runs)",
    )
    add_reader_args(p, "--reference", "when it is a field map (not a harmonics .csv or fit:DEG)")
    add_field_model_arg(p, "--reference", auto=True)


def run(args) -> int:
    from ..workflows.diagnose.run import check_options

    check_out_dir(args.out)
    if args.tracker is not None:
        refuse_reader_options(args, "--tracker reads no field map (--hall-map --reference does)")
    elif not args.reference:
        raise CfmInputError("--hall-map needs --reference FIELD")
    kind = "tracker" if args.tracker is not None else "hall"
    check_options(kind, args.reference, args.b_ref, args.r_ref, reader_kwargs(args))
    from ..io.lock import output_lock

    with output_lock(args.out, getattr(args, "command_line", None)):  # one run at a time
        return _run(args)


def _run(args) -> int:
    from ..workflows.diagnose.run import run_diagnose

    rec = read_recording_args(args)
    with progress_bar(None, "fits") as bar:
        res = run_diagnose(
            rec, args.reference, args.bench, b_ref_T=args.b_ref, r_ref_mm=args.r_ref,
            field_model=args.field_model, reader=reader_kwargs(args),
            command_line=getattr(args, "command_line", None), progress=bar.update,
            on_start=announcer(bar, "diagnose"),
        )  # fmt: skip
    paths = res.write(args.out, report=not args.no_report)
    _print(res.summary)
    print("wrote " + ", ".join(str(p) for p in paths.values()))  # every file written
    return 0


def _print(s: dict) -> None:
    fit = s["fit"]
    print(f"mismatch: {s['mismatch']}")
    for e in s["effects"]:
        ps = ", ".join(
            f"{k}={v:.3g}+-{e['param_std'][k]:.2g} {e['units'][k]}"
            if k in e["param_std"]
            else f"{k}={v:.3g} {e['units'][k]} (at its {e['at_bound'][k]} bound)"
            for k, v in e["params"].items()
        )
        print(f"  {e['name']}: delta BIC {e['delta_bic']}; {ps}")
    print(
        f"RMS {fit['rms_before']:.3g} -> {fit['rms_after']:.3g} {fit['unit']}; chi2/dof "
        f"{fit['chi2_dof_before']:.3g} -> {fit['chi2_dof_after']:.3g}; held-out RMS "
        f"{fit['cv_rms_before']:.3g} -> {fit['cv_rms_after']:.3g}"
    )
    for c in s.get("implausible", []):
        print(f"  implausible (not claimed): {c['name']}: {c['reason']}")
    for a in s["advice"]:
        print(f"advice: {a}")
