"""``cfm-fem diagnose`` as one function, `run_diagnose`, behind both the command line and
`cfm_fem.api.run_diagnose`: check the recording (enough points, within the strokes), choose the
bench and the reference field (harmonics, field map, fitted polynomial), build the problem and
diagnose it (`cfm_fem.workflows.diagnose.workflow.diagnose`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from ...errors import CfmInputError
from ..inputs import bench_provenance, choose_bench, recording, refuse_reader_options
from .reference import node_spacing_mm

__all__ = ["DiagnoseRun", "check_options", "run_diagnose", "reference_field", "node_spacing_mm",
           "MIN_POINTS_SINGLE", "truncation_note"]  # fmt: skip

#: Without repeated points the noise comes from the residual scatter of single readings; fewer
#: points than this leave too few degrees of freedom for it (and for the held-out folds).
MIN_POINTS_SINGLE = 10


@dataclass
class DiagnoseRun:
    """Everything ``cfm-fem diagnose`` writes.

    Attributes
    ----------
    diagnosis : cfm_fem.workflows.diagnose.workflow.Diagnosis
        Its ``arrays`` hold the residual maps; the attributes of the diagnosis are reachable
        on the run too (``run.arrays``).
    summary : dict
        ``diagnosis.json``: the diagnosis's summary with ``source`` and ``provenance``.
    source : str
        The recording, as named.
    rows : int
        Readings in the recording.
    bench_sentence : str
        The bench the run assumed (`cfm_fem.io.bench_toml.resolve_bench`).
    """

    diagnosis: object
    summary: dict
    source: str
    rows: int
    bench_sentence: str = ""
    notes: list = field(default_factory=list)

    def __getattr__(self, name):
        if name == "diagnosis":  # not yet set (copy, pickle): no recursion
            raise AttributeError(name)
        return getattr(self.diagnosis, name)

    def report(self):
        """``(report.html text, PNG figures by file name)`` of the diagnosis."""
        from ...report.diagnosis import diagnosis_report
        from ...report.diagnosis_figures import figures
        from ...report.plots import png_bytes

        arrays = self.diagnosis.arrays
        images = {f"{n}.png": png_bytes(fig) for n, fig in figures(self.summary, arrays).items()}
        rep = diagnosis_report(self.summary, images, self.source)
        return rep.render(), rep.images

    def write(self, out_dir, report: bool = True) -> dict:
        """Write ``diagnosis.json``, the residual maps and (``report``) ``report.html`` with
        its figures into ``out_dir``; return the paths by role."""
        from ...io.diagnosis_out import write_diagnosis

        html, images = self.report() if report else (None, {})
        return write_diagnosis(out_dir, self.summary, self.diagnosis.arrays, html, images)


def check_enough(rec) -> None:
    """Refuse a recording too small to diagnose, in the words compare uses."""
    _, index = rec.point_index()
    count = np.bincount(index)
    if count.max() < 2 and count.size < MIN_POINTS_SINGLE:
        raise CfmInputError(
            f"no point has two or more repetitions and only {count.size} point(s) were read; "
            f"the noise estimate needs repetitions (or at least {MIN_POINTS_SINGLE} points "
            "read once)",
            file=rec.source,
        )


def _is_harmonics(spec) -> bool:
    from ...io.reference_field import is_harmonics_file

    return Path(spec).is_file() and is_harmonics_file(Path(spec))


def _tail(mp):
    """Highest stated order N and the modulus c (T at R_ref) the first order left out is
    taken to have: the largest of the last max(2, N // 5) stated ones."""
    c = np.hypot(mp.normal, mp.skew)
    return int(c.size), float(c[-max(2, c.size // 5) :].max())


def truncation_var(mp, points) -> np.ndarray:
    """Variance (n, 3) T^2 of the first order a harmonics file leaves out, at ``points``
    (n, 3) mm: its modulus c (r / R_ref)^N (:func:`_tail`) at each point's radius r, half of
    its square on B_x, half on B_y, none on B_z."""
    n_top, tail = _tail(mp)
    bound = tail * (np.hypot(points[:, 0], points[:, 1]) / mp.r_ref) ** n_top
    var = np.zeros((len(points), 3))
    var[:, :2] = 0.5 * bound[:, None] ** 2
    return var


def truncation_note(mp, points) -> str:
    """What the first order a harmonics file leaves out may add at the readings, for the
    notes (:func:`truncation_var`).

    Parameters
    ----------
    mp : Multipole
    points : ndarray, shape (n, 3), mm
        The readings, magnet frame.

    Returns
    -------
    str
    """
    n_top, tail = _tail(mp)
    rho = float(np.hypot(points[:, 0], points[:, 1]).max()) / mp.r_ref
    units = 1e4 / mp.b_ref
    beyond = (
        f"; the readings reach {rho:.3g} R_ref, where the series need not converge"
        if rho > 1.0
        else ""
    )
    return (
        f"2-D harmonics' truncation: the orders stop at {n_top}; the first left out, taken as "
        f"large at R_ref = {mp.r_ref:.4g} mm as the largest of the last stated "
        f"({tail * units:.3g} units), adds up to {tail * rho**n_top * units:.3g} units at the "
        f"readings' largest radius {rho:.3g} R_ref{beyond}; added to the noise"
    )


def _fitted(spec: str, rec, reader):
    from .harmonic_fit import fit_harmonic_field, fit_piecewise_harmonic

    refuse_reader_options(reader, f"--reference {spec} is fitted to the recording")
    try:
        deg = int(spec.split(":", 1)[1])
    except ValueError:
        raise CfmInputError(f"--reference {spec}: expected fit:DEG, DEG an integer") from None
    if not 1 <= deg <= 12:
        raise CfmInputError(f"--reference {spec}: DEG must be 1..12")
    fit = fit_harmonic_field if spec.startswith("fit:") else fit_piecewise_harmonic
    fn = fit(rec.cmd, rec.B, deg)
    return fn, float(np.abs(rec.B).max()), None, f"harmonic polynomial fit ({spec})"


def reference_field(spec, rec, r_ref=None, field_model: str = "linear", reader=None):
    """The reference field of a Hall map.

    Parameters
    ----------
    spec : str, path-like or FieldMap
        A harmonics file, a field map (file or `FieldMap`), or ``fit:DEG`` / ``fitz:DEG`` (a
        harmonic polynomial of degree DEG fitted to the recording, globally or in z windows).
    rec : Recording
        The Hall map: every commanded point must lie in a field map.
    r_ref : float, optional, mm
        R_ref of a harmonics file that does not state it.
    field_model : {"auto", "harmonic", "linear"}
        A field map between its nodes: the node-exact harmonic fits where they hold (auto: on
        a 3-D map; `cfm_fem.workflows.diagnose.reference.reference_model`), or linear.
    reader : dict, optional
        Keyword arguments of `cfm_fem.io.read_field` for a field map file; refused otherwise.

    Returns
    -------
    tuple
        ``(field function, B_ref in T, node spacing in mm, description)``; the spacing is None
        for a smooth reference (harmonics, fitted polynomial, harmonic field model), else the
        map's, whose linear interpolation error the diagnosis adds to the noise.
    """
    from ...models.field import FieldMap

    text = None if isinstance(spec, FieldMap) else str(spec)
    own_model = text is not None and (text.startswith(("fit:", "fitz:")) or _is_harmonics(text))
    if field_model not in ("auto", "linear") and own_model:
        raise CfmInputError(
            f"--field-model applies to a field map; --reference {text} is a field model of its own"
        )
    if text is not None and text.startswith(("fit:", "fitz:")):
        return _fitted(text, rec, reader)
    if text is not None:
        path = Path(text)
        if not path.exists():
            raise CfmInputError(f"--reference: no such file '{text}'")
        from ...io.reference_field import is_harmonics_file

        # chosen by the header, so a broken harmonics file reports its own error (as compare
        # and coupled do) instead of a field-map "missing column" one
        if is_harmonics_file(path):
            from ...io.harmonics import read_harmonics

            refuse_reader_options(reader, f"--reference {text} is a harmonics file (n, Bn, An)")
            mp = read_harmonics(path, r_ref_mm=r_ref)

            def fn(p):
                return mp.field(p)

            fn.error_var = partial(truncation_var, mp)
            fn.error_var.note = truncation_note(mp, rec.cmd)
            return (
                fn,
                mp.b_ref,
                None,
                (
                    f"2-D multipole {path.name}; a 2-D field states no error of its own: the "
                    "magnet's 3-D departure from it (its ends; in the body, variation along z and "
                    "B_z) is taken as zero and is not in the noise, so residuals varying along z "
                    "or in B_z may be that departure, which fringe_field_3d tests as an effect "
                    "(a 3-D field map as reference states its error)"
                ),
            )
    return _map_reference(spec, rec, field_model, reader)


def _map_reference(spec, rec, field_model, reader):
    """`reference_field` of a field map (file or `FieldMap`): read between its nodes by the
    node-exact harmonic fits where they hold (auto, harmonic), else linearly
    (`cfm_fem.workflows.diagnose.reference.reference_model`); the function carries the
    reference's own error estimate (``error_var``) when the harmonic fits serve."""
    from ...models.field import FieldMap
    from ..inputs import field_map
    from .reference import reference_model

    if isinstance(spec, FieldMap):
        refuse_reader_options(reader, "--reference is a field map already read")
    fm = field_map(spec, reader)
    name = Path(str(spec)).name if not isinstance(spec, FieldMap) else str(fm.source)
    interp, kind, why = reference_model(fm, field_model)
    served = interp.fit.field_at(rec.cmd)[1] if kind == "harmonic" else None
    if kind == "harmonic" and field_model == "auto" and not served.any():
        interp, kind = interp.curved, "curved"  # no fit holds near the readings
        why = (f"the harmonic fits hold at none of the {len(served)} readings (noise in the "
               "map, currents or iron near them)")  # fmt: skip

    def fn(p):
        b, _ = interp.field_at(p)
        return b

    _, inside = interp.field_at(rec.cmd)
    if not inside.all():
        # name the first row and point, like compare; count rows and distinct points apart
        out = ~inside
        i = int(np.argmax(out))
        n_out = len(np.unique(np.round(rec.cmd[out], 9), axis=0))
        n_all = len(np.unique(np.round(rec.cmd, 9), axis=0))
        raise CfmInputError(
            f"commanded point {rec.cmd[i].tolist()} mm is outside the reference field map "
            f"'{spec if not isinstance(spec, FieldMap) else fm.source}' ({n_out} of {n_all} "
            f"points outside, {int(out.sum())} of {len(rec)} rows)",
            file=rec.source,
            line=int(rec.lines[i]) or None,
        )
    spacing = node_spacing_mm(fm.points)
    desc = f"FEM map {name} (nodes {spacing:.3g} mm apart"
    b_ref = float(np.nanmax(np.linalg.norm(fm.B, axis=1)))
    fn.nodes = fm.points  # exact there, either way
    if kind == "harmonic":  # smooth between nodes; its own error estimated by the model
        fn.error_var, fn.spacing = interp.error_var, spacing
        fn.error_bound = interp.error_bound
        n_lin = int((~served).sum())
        fb = (f"; {n_lin} of {len(served)} readings, where no fit holds, read linearly "
              "corrected by the field's curvature") if n_lin else ""  # fmt: skip
        return fn, b_ref, None, (f"{desc}, read between nodes by a harmonic fit per node to its "
                                 f"{interp.fit.k} nearest, exact at the nodes{fb})")  # fmt: skip
    if kind == "curved":  # the linear reading corrected by the curvature; its error estimated
        fn.error_var = interp.error_var
        return fn, b_ref, spacing, (f"{desc}, read between nodes linearly corrected by the "
                                    "field's second and third differences, exact at the nodes; "
                                    f"{why})")  # fmt: skip
    return fn, b_ref, spacing, f"{desc}, read linearly between nodes{'; ' + why if why else ''})"


def check_options(kind, reference, b_ref_T=None, r_ref_mm=None, reader=None) -> None:
    """The checks of the options that need no file read: a tracker recording takes no
    reference, B_ref, R_ref or reader option; B_ref > 0. ``kind``: "tracker" or "hall"."""
    if kind == "tracker":
        if reference is not None:
            raise CfmInputError("--reference is for --hall-map only")
        if b_ref_T is not None:  # tracker residuals are in um: B_ref has no use there
            raise CfmInputError("--b-ref is for --hall-map only")
        if r_ref_mm is not None:
            raise CfmInputError("--r-ref is for --hall-map with a harmonics --reference only")
        refuse_reader_options(reader, "--tracker reads no field map (--hall-map --reference does)")
    elif b_ref_T is not None and not b_ref_T > 0:
        raise CfmInputError(f"--b-ref must be > 0; got {b_ref_T}")


def _reference_input(reference):
    """The provenance entry of the reference: a file, or the spec of a fit."""
    from ...models.field import FieldMap

    if isinstance(reference, FieldMap):
        return {"spec": f"field map {reference.source}"}
    if reference is not None and not Path(str(reference)).is_file():
        return {"spec": str(reference)}  # fit:DEG / fitz:DEG: fitted to the recording itself
    return reference


def run_diagnose(rec, reference=None, bench=None, *, b_ref_T=None, r_ref_mm=None,
                 field_model: str = "auto", reader=None, command_line=None, progress=None,
                 on_start=None) -> DiagnoseRun:  # fmt: skip
    """What the simulation leaves out of a recording (``cfm-fem diagnose``).

    Parameters
    ----------
    rec : Recording or path-like
        A tracker recording or a Hall map (mm, T).
    reference : str, path-like, FieldMap or None
        Hall maps: a harmonics file, a field map, or ``fit:DEG`` / ``fitz:DEG``
        (`reference_field`); None: the paper's QFDp4 harmonics. Refused for a tracker recording.
    bench : Bench, path-like or None
        None: the packaged CFM reference bench.
    b_ref_T : float, optional, T
        Hall maps: B_ref of the units (default the reference's).
    r_ref_mm : float, optional, mm
        R_ref of a harmonics file that does not state it.
    field_model : {"linear", "harmonic"}
        A field map between its nodes.
    reader : dict, optional
        Keyword arguments of `cfm_fem.io.read_field` for a field map reference.
    command_line : str, optional
        For the provenance.
    progress : callable(int), optional
        Called after each candidate fit.
    on_start : callable(str, int or None), optional
        Called once the inputs are checked, with a line naming the recording and the number
        of fits to come (None: not known in advance).

    Returns
    -------
    DiagnoseRun
    """
    from .problem import hall_problem, tracker_problem
    from .workflow import diagnose

    rec = recording(rec)
    if rec.kind == "hall" and reference is None:
        from ...io.harmonics import qfdp4_path

        reference = str(qfdp4_path())
    check_options(rec.kind, reference, b_ref_T, r_ref_mm, reader)
    bench_model, sentence = choose_bench(bench)
    check_enough(rec)
    if rec.kind == "tracker":
        from ..compare import check_within_strokes

        check_within_strokes(rec, bench_model)
        prob = tracker_problem(rec, bench_model)
    else:
        fn, b_ref, spacing, desc = reference_field(reference, rec, r_ref_mm, field_model, reader)
        if b_ref_T is not None:
            b_ref = float(b_ref_T)
        if not (np.isfinite(b_ref) and b_ref > 0):
            raise CfmInputError(
                f"--reference {reference}: its field is zero everywhere (B_ref = max |B| "
                f"= {b_ref:g} T), so field errors have no unit; expected a non-zero field, or "
                "give --b-ref T"
            )
        step = spacing if spacing is not None else getattr(fn, "spacing", None)
        prob = hall_problem(rec, fn, b_ref, bench_model, smooth=spacing is None,
                            ref_spacing_mm=step, ref_nodes=getattr(fn, "nodes", None),
                            ref_error=getattr(fn, "error_var", None),
                            ref_bound=getattr(fn, "error_bound", None))  # fmt: skip
        prob.notes.append(f"reference: {desc}")
    source = str(rec.source)
    if on_start is not None:
        on_start(f"{len(rec)} rows from {source}", None)
    d = diagnose(prob, progress=progress)
    from ...io.provenance import provenance

    role = "tracker" if rec.kind == "tracker" else "hall_map"
    inputs = {"bench": bench_provenance(bench), "tracker": None, "hall_map": None,
              "reference": _reference_input(reference) if rec.kind == "hall" else None}  # fmt: skip
    inputs[role] = source if Path(source).is_file() else None
    s = d.summary
    s["source"] = source
    s["provenance"] = provenance(inputs, command_line)
    return DiagnoseRun(d, s, source, len(rec), sentence)
