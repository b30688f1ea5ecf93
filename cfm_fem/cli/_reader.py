"""The field-map reader's options, written once for every command that reads a field map.

The reader's messages tell the user to pass ``--format``, ``--length-unit``, ``--field-unit``,
``--zero-rows`` or ``--solution`` (`cfm_fem.io._parse.option_hint`), so each command that reads
a map takes them under these names, with these help texts: ``sweep`` and ``fig4`` (FIELD),
``coupled --field``, ``compare --reference`` and ``diagnose --reference`` (when a field map).
"""

from __future__ import annotations

from ..errors import CfmInputError
from . import option_type

__all__ = [
    "add_reader_args",
    "add_recording_args",
    "read_recording_args",
    "reader_kwargs",
    "given_reader_options",
    "refuse_reader_options",
]

#: Default of each reader argument, by argparse dest; an option left at it was not given.
_DEFAULTS = {"fmt": None, "length_unit": None, "field_unit": None, "zero_rows": "warn",
             "solution": None}  # fmt: skip
_OPTIONS = {"fmt": "--format", "length_unit": "--length-unit", "field_unit": "--field-unit",
            "zero_rows": "--zero-rows", "solution": "--solution"}  # fmt: skip


def add_reader_args(p, what: str = "FIELD", when: str | None = None) -> None:
    """Add the reader options to parser ``p``, in a group of their own.

    Parameters
    ----------
    p : argparse.ArgumentParser
    what : str
        The argument or option that names the map (``'FIELD'``, ``'--reference'``).
    when : str, optional
        When the options apply, for the group's description (e.g. "when it is a field map, not
        a harmonics .csv"); said once there rather than in each option's help.
    """
    g = p.add_argument_group(
        f"how {what} is read",
        f"apply to {what} {when}; refused otherwise" if when else None,
    )
    g.add_argument(
        "--format",
        dest="fmt",
        metavar="FMT",
        help="input format if the extension is ambiguous: comsol, opera, table (or csv), or a "
        "meshio format (vtu, vtk, gmsh, xdmf, ...)",
    )
    g.add_argument(
        "--length-unit",
        metavar="UNIT",
        type=option_type(_check_unit("length"), "--length-unit"),
        help="unit of the coordinates (mm, m, in, ...); overrides a unit the file states (with "
        "a warning when they differ); needed when the file states none (mesh files: mm assumed)",
    )
    g.add_argument(
        "--field-unit",
        metavar="UNIT",
        type=option_type(_check_unit("field"), "--field-unit"),
        help="unit of the field (T, mT, G, kG); overrides a unit the file states (with a "
        "warning when they differ); needed when the file states none (mesh files: T assumed)",
    )
    g.add_argument(
        "--zero-rows",
        choices=["warn", "drop", "keep"],  # io._parse.ZERO_ROWS_CHOICES; not imported: fast --help
        default="warn",
        help="rows with B exactly 0 0 0 (placeholders of measured maps): warn and keep "
        "(default), drop, keep",
    )
    g.add_argument(
        "--solution",
        metavar="TAG",
        help="COMSOL export of a parametric or time-dependent study (columns such as "
        "'mf.Bx (T) @ I0=200'): the solution to read, by its tag, e.g. --solution I0=200 or "
        "--solution t=0.1 (compared as written in the file; blanks around = and , and a "
        "leading @ do not matter); COMSOL exports only",
    )


def add_recording_args(p) -> None:
    """Add the required choice of recording, ``--tracker`` or ``--hall-map`` (REC.csv), to
    parser ``p``, naming the columns each must have (``compare`` and ``diagnose``)."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--tracker",
        metavar="REC.csv",
        help="laser-tracker recording: point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas (mm)",
    )
    src.add_argument(
        "--hall-map",
        metavar="REC.csv",
        help="Hall-probe map recording: point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz (mm, T)",
    )
    g = p.add_argument_group("how the recording is read")
    g.add_argument(
        "--recording-length-unit",
        metavar="UNIT",
        type=option_type(_check_unit("length"), "--recording-length-unit"),
        help="unit of the recording's positions and speed (mm, m, in, ...; default mm)",
    )
    g.add_argument(
        "--recording-field-unit",
        metavar="UNIT",
        type=option_type(_check_unit("field"), "--recording-field-unit"),
        help="unit of a Hall map's Bx, By, Bz (T, mT, G, kG; default T)",
    )


def _check_unit(kind):
    def unit(text):
        from ..units import field_scale, length_scale

        (length_scale if kind == "length" else field_scale)(text)
        return text

    unit.__name__ = f"{kind} unit"
    return unit


def read_recording_args(args):
    """The recording named by ``--tracker`` or ``--hall-map``, converted to mm and T from the
    ``--recording-*-unit`` options."""
    from ..io.recording_units import read_recording_in_units

    tracker = args.tracker is not None
    if tracker and args.recording_field_unit is not None:
        raise CfmInputError("--recording-field-unit applies to --hall-map only (a tracker "
                            "recording has no field)")  # fmt: skip
    kind, path = ("tracker", args.tracker) if tracker else ("hall", args.hall_map)
    return read_recording_in_units(
        path, kind, args.recording_length_unit, args.recording_field_unit
    )


def add_field_model_arg(p, what: str, auto: bool = False) -> None:
    """Add ``--field-model``: how the map ``what`` is modelled between nodes. ``auto``: offer
    and default to "auto" (harmonic on a 3-D map, linear on a planar one), else default linear."""
    p.add_argument(
        "--field-model",
        choices=["auto", "linear", "harmonic"] if auto else ["linear", "harmonic"],
        default="auto" if auto else "linear",
        help=f"the field of {what} between its nodes: linear interpolation in its cells, or per "
        "node a least-squares fit of a harmonic potential's gradient (div B = curl B = 0) to its "
        "nearest nodes (3-D maps); "
        + (
            "auto (default): harmonic on a 3-D map, linear on a planar one"
            if auto
            else "default linear"
        ),
    )


def reader_kwargs(args) -> dict:
    """The reader options of ``args`` as keyword arguments of `cfm_fem.io.read_field`."""
    return {k: getattr(args, k) for k in _DEFAULTS}


def given_reader_options(args) -> list[str]:
    """The reader options given on the command line (not left at their default), as spelt."""
    return [_OPTIONS[k] for k, v in _DEFAULTS.items() if getattr(args, k) != v]


def refuse_reader_options(args, why: str) -> None:
    """Refuse reader options given where no field map is read; ``why`` says what is read."""
    given = given_reader_options(args)
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise CfmInputError(f"{' and '.join(given)} {verb} to a field map only; {why}")
