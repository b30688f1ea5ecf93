"""Find what the simulation left out: calibrate the bench model to tracker or Hall-map
recordings, locate significant residuals, attribute them to catalogued physical effects by nested
model comparison and held-out error, model them and advise. Writes DIR/diagnosis.json,
DIR/report.html with PNG plots, and residual maps DIR/residual_*.vtu.

--reference FIELD: a field map (any format cfm-fem reads), a harmonics CSV (2-D multipole), or
'fit:DEG' / 'fitz:DEG' to fit a curl- and div-free harmonic polynomial of degree DEG to the map
itself (global, or in z windows). A 3-D field map is read between its nodes by the harmonic
fits of its nodes, exact at the nodes (--field-model auto, the default), and linearly where the
fits fail Laplace's test; a planar map, or one whose fits hold at no reading, linearly. Either
way the reference's own error between its nodes is estimated and added to the noise.
"""

from __future__ import annotations

import sys

from ..errors import CfmInputError
from ._checks import check_out_dir
from ._progress import progress_bar
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


#: Without repeated points the noise comes from the residual scatter of single readings; fewer
#: points than this leave too few degrees of freedom for it (and for the held-out folds).
MIN_POINTS_SINGLE = 10


def _check_enough(rec):
    """Refuse a recording too small to diagnose, in the words compare uses."""
    import numpy as np

    _, index = rec.point_index()
    count = np.bincount(index)
    if count.max() < 2 and count.size < MIN_POINTS_SINGLE:
        raise CfmInputError(
            f"no point has two or more repetitions and only {count.size} point(s) were read; "
            f"the noise estimate needs repetitions (or at least {MIN_POINTS_SINGLE} points "
            "read once)",
            file=rec.source,
        )


def node_spacing_mm(points) -> float:
    """Typical node spacing of a map (median distance to the nearest other node), mm."""
    from ..workflows.diagnose.reference import node_spacing_mm as spacing

    return spacing(points)


def _is_harmonics(spec) -> bool:
    from pathlib import Path

    from ..io.reference_field import is_harmonics_file

    return Path(spec).is_file() and is_harmonics_file(Path(spec))


def _reference(spec, rec, r_ref=None, args=None):
    """(field function, b_ref, node spacing, description); node spacing (mm) None for a smooth
    reference (harmonics, fitted polynomial), else the map's, whose linear interpolation error
    the diagnosis adds to the noise; ``r_ref`` (mm) for a harmonics file; ``args``: the
    command line's reader options (`_reader`) and ``--field-model``, for a field map (None: a
    map read linearly)."""
    from pathlib import Path

    import numpy as np

    from ..workflows.diagnose.harmonic_fit import fit_harmonic_field, fit_piecewise_harmonic

    field_model = "linear" if args is None else args.field_model
    own = spec.startswith(("fit:", "fitz:")) or _is_harmonics(spec)
    if args is not None and field_model != "auto" and own:
        raise CfmInputError(
            f"--field-model applies to a field map; --reference {spec} is a field model of its own"
        )
    if spec.startswith(("fit:", "fitz:")):
        if args is not None:
            refuse_reader_options(args, f"--reference {spec} is fitted to the recording")
        try:
            deg = int(spec.split(":", 1)[1])
        except ValueError:
            raise CfmInputError(f"--reference {spec}: expected fit:DEG, DEG an integer") from None
        if not 1 <= deg <= 12:
            raise CfmInputError(f"--reference {spec}: DEG must be 1..12")
        fn = (fit_harmonic_field if spec.startswith("fit:") else fit_piecewise_harmonic)(
            rec.cmd, rec.B, deg
        )
        return fn, float(np.abs(rec.B).max()), None, f"harmonic polynomial fit ({spec})"
    path = Path(spec)
    if not path.exists():
        raise CfmInputError(f"--reference: no such file '{spec}'")
    from ..io.reference_field import is_harmonics_file

    # choose the reader by the header, so a broken harmonics file reports its own error
    # (as compare and coupled do) instead of a field-map "missing column" one
    if is_harmonics_file(path):
        from ..io.harmonics import read_harmonics

        if args is not None:
            refuse_reader_options(args, f"--reference {spec} is a harmonics file (n, Bn, An)")

        mp = read_harmonics(path, r_ref_mm=r_ref)
        return mp.field, mp.b_ref, None, f"2-D multipole {path.name}"
    from ..io import read_field
    from ..workflows.diagnose.reference import reference_model

    fm = read_field(path, **({} if args is None else reader_kwargs(args)))
    interp, kind, why = reference_model(fm, field_model)
    served = interp.fit.field_at(rec.cmd)[1] if kind == "harmonic" else None
    if kind == "harmonic" and field_model == "auto":
        if not served.any():  # no fit holds near the readings: the map is read linearly
            interp, kind = interp.linear, "linear"
            why = (
                f"the harmonic fits hold at none of the {len(served)} readings (noise in the "
                "map, currents or iron near them)"
            )

    def fn(p):
        b, inside = interp.field_at(p)
        return b

    b, inside = interp.field_at(rec.cmd)
    if not inside.all():
        # name the first row and point, like compare; count rows and distinct points apart
        out = ~inside
        i = int(np.argmax(out))
        n_out = len(np.unique(np.round(rec.cmd[out], 9), axis=0))
        n_all = len(np.unique(np.round(rec.cmd, 9), axis=0))
        raise CfmInputError(
            f"commanded point {rec.cmd[i].tolist()} mm is outside the reference field map "
            f"'{spec}' ({n_out} of {n_all} points outside, {int(out.sum())} of {len(rec)} rows)",
            file=rec.source,
            line=int(rec.lines[i]) or None,
        )
    spacing = node_spacing_mm(fm.points)
    desc = f"FEM map {path.name} (nodes {spacing:.3g} mm apart"
    b_ref = float(np.nanmax(np.linalg.norm(fm.B, axis=1)))
    if kind == "harmonic":  # smooth between nodes; its own error estimated by the model
        fn.error_var = interp.error_var
        fn.nodes, fn.spacing = fm.points, spacing  # exact at its nodes, as a linear map
        n_lin = int((~served).sum())
        fb = f"; {n_lin} of {len(served)} readings read linearly: no fit holds" if n_lin else ""
        return (
            fn,
            b_ref,
            None,
            (
                f"{desc}, read between nodes by a harmonic fit per node to its {interp.fit.k} "
                f"nearest, exact at the nodes{fb})"
            ),
        )
    fn.nodes = fm.points  # the interpolation is exact there
    return fn, b_ref, spacing, f"{desc}, read linearly between nodes{'; ' + why if why else ''})"


def _provenance(args) -> dict:
    """What produced the diagnosis: the recording, the reference (a file, or a fit: spec) and
    the bench (given, or the packaged one), with their SHA-256, as the other commands record."""
    from pathlib import Path

    from ..io.provenance import bench_input, provenance

    ref = args.reference
    if ref is not None and not Path(ref).is_file():
        ref = {"spec": ref}  # fit:DEG / fitz:DEG: fitted to the recording itself
    inputs = {"bench": bench_input(args.bench), "tracker": args.tracker,
              "hall_map": args.hall_map, "reference": ref}  # fmt: skip
    return provenance(inputs, getattr(args, "command_line", None))


def _report(summary, arrays, source):
    """(report.html text, PNG figures by file name) of a diagnosis."""
    from ..report.diagnosis import diagnosis_report
    from ..report.plots import png_bytes
    from ..workflows.diagnose.report import figures

    images = {f"{name}.png": png_bytes(fig) for name, fig in figures(summary, arrays).items()}
    rep = diagnosis_report(summary, images, source)
    return rep.render(), rep.images


def run(args) -> int:
    check_out_dir(args.out)
    if args.tracker:
        if args.reference:
            raise CfmInputError("--reference is for --hall-map only")
        if args.b_ref is not None:  # tracker residuals are in um: B_ref has no use there
            raise CfmInputError("--b-ref is for --hall-map only")
        if args.r_ref is not None:
            raise CfmInputError("--r-ref is for --hall-map with a harmonics --reference only")
        refuse_reader_options(args, "--tracker reads no field map (--hall-map --reference does)")
    elif not args.reference:
        raise CfmInputError("--hall-map needs --reference FIELD")
    elif args.b_ref is not None and not args.b_ref > 0:
        raise CfmInputError(f"--b-ref must be > 0; got {args.b_ref}")
    from ..io.lock import output_lock

    with output_lock(args.out, getattr(args, "command_line", None)):  # one run at a time
        return _run(args)


def _run(args) -> int:
    import numpy as np

    from ..io.bench_toml import read_bench, read_reference_bench
    from ..io.diagnosis_out import write_diagnosis
    from ..workflows.diagnose.problem import hall_problem, tracker_problem
    from ..workflows.diagnose.workflow import diagnose

    bench = read_reference_bench() if args.bench is None else read_bench(args.bench)
    if args.tracker:
        from ..workflows.compare import check_within_strokes

        rec = read_recording_args(args)
        _check_enough(rec)
        check_within_strokes(rec, bench)
        prob = tracker_problem(rec, bench)
        src = args.tracker
    else:
        rec = read_recording_args(args)
        _check_enough(rec)
        fn, b_ref, spacing, desc = _reference(args.reference, rec, args.r_ref, args)
        if args.b_ref is not None:
            b_ref = args.b_ref
        if not (np.isfinite(b_ref) and b_ref > 0):
            raise CfmInputError(
                f"--reference {args.reference}: its field is zero everywhere (B_ref = max |B| "
                f"= {b_ref:g} T), so field errors have no unit; expected a non-zero field, or "
                "give --b-ref T"
            )
        nodes = getattr(fn, "nodes", None)
        step = spacing if spacing is not None else getattr(fn, "spacing", None)
        prob = hall_problem(
            rec,
            fn,
            b_ref,
            bench,
            smooth=spacing is None,
            ref_spacing_mm=step,
            ref_nodes=nodes,
            ref_error=getattr(fn, "error_var", None),
        )
        prob.notes.append(f"reference: {desc}")
        src = args.hall_map
    print(f"cfm-fem diagnose: {len(rec)} rows from {src}", file=sys.stderr)
    with progress_bar(None, "fits") as bar:
        d = diagnose(prob, progress=bar.update)
    s = d.summary
    s["source"] = str(src)
    s["provenance"] = _provenance(args)
    report = (None, {}) if args.no_report else _report(s, d.arrays, str(src))
    paths = write_diagnosis(args.out, s, d.arrays, *report)
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
    print("wrote " + ", ".join(str(p) for p in paths.values()))  # every file written
    return 0
