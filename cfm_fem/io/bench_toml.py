"""Bench description files (TOML): read into a :class:`cfm_fem.models.bench.Bench`, write back.

The layout is the shipped ``cfm_fem/data/cfm_reference_bench.toml``, which documents every key.
Units are converted once, here: lengths to mm, angles to rad, times to s. Unknown keys and
impossible values raise :class:`~cfm_fem.errors.CfmInputError` naming the file, the line (found
by scanning the text; tomllib does not report positions), the key and what was expected.
"""

from __future__ import annotations

import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import CfmInputError
from ..models.bench import (
    AXES,
    ERROR_NAMES,
    Axis,
    Bench,
    ErrorSpec,
    Grid,
    MagnetPlacement,
    ReadingDelay,
)
from ..models.mc import PDF_PARAMETERS, Pdf
from ._atomic import write_text
from ._files import open_regular

__all__ = [
    "read_bench",
    "read_reference_bench",
    "resolve_bench",
    "BenchChoice",
    "bench_to_toml",
    "write_bench",
    "REFERENCE_BENCH",
]

#: Name of the shipped reference bench inside the package data.
REFERENCE_BENCH = "cfm_reference_bench.toml"

#: Most scan points of a bench grid: kinematics needs about 30 kB per point (100,800 points
#: with 1,000 trials: 3.1 GB, 40 s), so 100,000 is a few GB; num = 1e8 would ask for 54 GB at once.
MAX_GRID_POINTS = 100_000
#: Largest stroke, and largest error a bench may describe (|mean| + 10 std, times the largest
#: profile value): 1e5 mm and 1e3 mm (1 m) for a translation, 1 rad for an angle, 1e6 um for
#: vibration and reading delay. Larger values are typos or overflow: std = 1e300 um would make the
#: kinematics Monte Carlo loop for ever on NaN positions.
MAX_STROKE_MM = 1e5
#: Largest mount, tool or magnet offset (mm), magnet rotation (deg) and axis speed (mm/s) a
#: bench may state: larger is a typo (1e300 mm was accepted and overflowed downstream).
MAX_OFFSET_MM = 1e5
MAX_ROTATION_DEG = 360.0
MAX_SPEED_MM_S = 1e6
MAX_ERROR = {"length": 1e3, "angle": 1.0}
MAX_NOISE_UM = 1e6

_LENGTH_UNITS = {"mm": 1.0, "um": 1e-3, "µm": 1e-3, "nm": 1e-6}
_ANGLE_UNITS = {
    "rad": 1.0,
    "mrad": 1e-3,
    "urad": 1e-6,
    "µrad": 1e-6,
    "deg": np.pi / 180,
    "arcsec": np.pi / 180 / 3600,
}
_ERROR_KEYS = {"pdf", "unit", "note", "profile"} | {p for ps in PDF_PARAMETERS.values() for p in ps}
_ERROR_GROUPS = {
    "x": [f"{k}_{c}" for k in ("delta", "eps") for c in AXES],
    "y": [f"{k}_{c}" for k in ("delta", "eps") for c in AXES],
    "z": [f"{k}_{c}" for k in ("delta", "eps") for c in AXES],
    "squareness": ["alpha_xy", "alpha_xz", "alpha_yz"],
}


class _Doc:
    """The parsed TOML with the raw text, to turn a dotted key into a line number."""

    def __init__(self, path, text):
        self.path = str(path)
        self.lines = text.splitlines()

    def line_of(self, dotted: str) -> int | None:
        """1-based line where ``dotted`` (``'errors.x.delta_x.low'``) is set or its table opens."""
        parts = dotted.split(".")
        table: list[str] = []
        best = None
        header = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
        keyline = re.compile(r"^\s*([A-Za-z0-9_\-\"']+)\s*=")
        for n, line in enumerate(self.lines, 1):
            m = header.match(line)
            if m:
                table = [p.strip().strip("\"'") for p in m.group(1).split(".")]
                if table == parts:
                    return n
                # a table only named inside a longer header ([errors.w.delta_y] for errors.w)
                if table[: len(parts)] == parts and best is None:
                    best = n
                continue
            k = keyline.match(line)
            if not k:
                continue
            full = table + [k.group(1).strip("\"'")]
            if full == parts:
                return n
            # a key inside an inline table: report the line of the parent key
            if len(parts) > len(full) and parts[: len(full)] == full and best is None:
                best = n
        if best is not None:
            return best
        if len(parts) > 1:
            return self.line_of(".".join(parts[:-1]))
        return None

    def error(self, key: str, what: str) -> CfmInputError:
        return CfmInputError(f"'{key}' {what}", file=self.path, line=self.line_of(key))


def _check_keys(doc: _Doc, table: dict, allowed, prefix: str):
    for k in table:
        if k not in allowed:
            key = f"{prefix}.{k}" if prefix else k
            raise doc.error(
                key, f"is not a known key; expected one of {', '.join(sorted(allowed))}"
            )


def _float(v) -> float:
    """``float(v)``, or inf for an integer too large for a float (TOML integers are unbounded;
    numpy's isfinite refused a 400-digit one with a TypeError)."""
    try:
        return float(v)
    except OverflowError:
        return float("inf")


def _shown(v) -> str:
    """``repr(v)`` cut to 60 characters (a 400-digit integer in a message helps no one)."""
    text = repr(v)
    return text if len(text) <= 60 else f"{text[:40]}...{text[-10:]} ({len(text)} characters)"


def _get(doc, table, key, prefix, kind, default=None, required=False, expect=None):
    full = f"{prefix}.{key}" if prefix else key
    if key not in table:
        if required:
            raise CfmInputError(
                f"'{full}' is missing; expected {expect or kind}",
                file=doc.path,
                line=doc.line_of(prefix) if prefix else None,
            )
        return default
    v = table[key]
    if kind == "number":
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(_float(v)):
            raise doc.error(full, f"must be a finite number; found {_shown(v)}")
        return float(v)
    if kind == "integer":
        if isinstance(v, bool) or not isinstance(v, int):
            raise doc.error(full, f"must be an integer; found {_shown(v)}")
        return v
    if kind == "string":
        if not isinstance(v, str):
            raise doc.error(full, f"must be a string; found {v!r}")
        return v
    if kind == "vector3":
        ok = isinstance(v, list) and len(v) == 3
        ok = ok and all(not isinstance(x, bool) and isinstance(x, (int, float)) for x in v)
        if not ok or not all(np.isfinite(_float(x)) for x in v):
            raise doc.error(full, f"must be a list of 3 finite numbers; found {_shown(v)}")
        return np.array(v, dtype=np.float64)
    if kind == "numbers":
        ok = isinstance(v, list) and len(v) > 0
        ok = ok and all(not isinstance(x, bool) and isinstance(x, (int, float)) for x in v)
        if not ok or not all(np.isfinite(_float(x)) for x in v):
            raise doc.error(full, f"must be a non-empty list of finite numbers; found {_shown(v)}")
        return tuple(float(x) for x in v)
    if kind == "table":
        if not isinstance(v, dict):
            raise doc.error(full, f"must be a table; found {v!r}")
        return v
    raise AssertionError(kind)


#: What a bench without its vibration or reading-delay figures is asked for: these are
#: uncertainty contributions, and one left out would make U_p smaller than the bench's without a
#: word, so a missing table is an error, never a silent zero.
_NO_VIBRATION = (
    "the bench's vibration as a standard deviation per axis, e.g. [vibration] std_um = 2.5 "
    "(write std_um = 0.0 for a bench without vibration)"
)
_NO_DELAY = (
    'the bench\'s reading delay, e.g. [reading_delay] model = "normal", std_um = 1.0 (write '
    'std_um = 0.0 for none), or model = "speed_tau" with speed_mm_s and tau'
)
#: Notes of defaults taken for tables or keys a bench file leaves out start with this; they are
#: added to the bench's assumptions (printed and written with every output) and not written
#: back by `bench_to_toml`, which states every table.
DEFAULT_NOTE = "Not in the bench file, default taken: "


def _required_table(doc, data, key, expect) -> dict:
    """A top-level table the bench must state (an uncertainty contribution)."""
    if key not in data:
        raise CfmInputError(f"[{key}] is missing; expected {expect}", file=doc.path)
    return _get(doc, data, key, "", "table")


def _require_key(doc, table, key, prefix, expect) -> None:
    if key not in table:
        raise CfmInputError(
            f"'{prefix}.{key}' is missing; expected {expect}",
            file=doc.path,
            line=doc.line_of(prefix),
        )


def _std_or_vector(doc, table, key, prefix, default):
    """A std given as one number (all axes) or as 3 numbers, in um -> mm."""
    if key not in table:
        return np.full(3, default)
    v = table[key]
    full = f"{prefix}.{key}"
    if isinstance(v, list):
        vec = _get(doc, table, key, prefix, "vector3")
    else:
        vec = np.full(3, _get(doc, table, key, prefix, "number"))
    if np.any(vec < 0):
        raise doc.error(full, f"must be >= 0 (a standard deviation); found {v!r}")
    if np.any(vec > MAX_NOISE_UM):
        raise doc.error(full, f"must be <= {MAX_NOISE_UM:g} um (1 m); found {_shown(v)}")
    return vec * 1e-3


def _pdf(doc, table, prefix, scale, unit_kind):
    kind = _get(doc, table, "pdf", prefix, "string", required=True)
    if kind not in PDF_PARAMETERS:
        raise doc.error(
            f"{prefix}.pdf", f"must be one of {', '.join(PDF_PARAMETERS)}; found {kind!r}"
        )
    params = {}
    for name in PDF_PARAMETERS[kind]:
        params[name] = _get(doc, table, name, prefix, "number", required=True)
    extra = [
        k
        for k in table
        if k in _ERROR_KEYS - {"pdf", "unit", "note", "profile"} and k not in PDF_PARAMETERS[kind]
    ]
    if extra:
        raise doc.error(
            f"{prefix}.{extra[0]}",
            f"is not a parameter of pdf '{kind}'; it takes {', '.join(PDF_PARAMETERS[kind])}",
        )
    try:
        pdf = Pdf.from_params(kind, **params)
    except CfmInputError as exc:
        raise doc.error(f"{prefix}.pdf", f"has impossible parameters: {exc}") from None
    try:
        pdf.kernel_code()
    except CfmInputError as exc:
        raise doc.error(f"{prefix}.pdf", str(exc)) from None
    # beta of a trapezoid is dimensionless; everything else scales with the unit
    if kind == "trapezoidal":
        return Pdf(kind, (pdf.params[0] * scale, pdf.params[1] * scale, pdf.params[2]))
    return pdf.scaled(scale)


def _read_error(doc, table, group, key):
    name = f"{key}({group})" if group != "squareness" else key
    prefix = f"errors.{group}.{key}"
    _check_keys(doc, table, _ERROR_KEYS, prefix)
    is_angle = key.startswith(("eps", "alpha"))
    units = _ANGLE_UNITS if is_angle else _LENGTH_UNITS
    unit = _get(doc, table, "unit", prefix, "string", required=True,
                expect=f"one of {', '.join(units)} (a value without a unit is ambiguous by "
                "factors of 1000)")  # fmt: skip
    if unit not in units:
        raise doc.error(
            f"{prefix}.unit",
            f"must be one of {', '.join(units)} for {'an angle' if is_angle else 'a length'}; "
            f"found {unit!r}",
        )
    pdf = _pdf(doc, table, prefix, units[unit], "angle" if is_angle else "length")
    profile = _get(doc, table, "profile", prefix, "numbers", default=(1.0,))
    if group == "squareness" and any(c != 0 for c in profile[1:]):
        raise doc.error(f"{prefix}.profile", "is not allowed: squareness is position independent")
    kind = "angle" if is_angle else "length"
    with np.errstate(over="ignore", invalid="ignore"):
        # sum |c_k| bounds the profile on u in [0, 1]
        size = (abs(pdf.mean) + 10.0 * pdf.std) * float(np.sum(np.abs(profile)))
    if not size <= MAX_ERROR[kind]:
        limit = "1 m" if kind == "length" else "1 rad"
        raise doc.error(
            prefix,
            f"describes errors up to {size:.3g} {'mm' if kind == 'length' else 'rad'} (|mean| + "
            f"10 std, times the profile); expected at most {limit}: check the values and the unit",
        )
    note = _get(doc, table, "note", prefix, "string", default="")
    return ErrorSpec(name=name, pdf=pdf, profile=profile, unit=unit, note=note)


def read_bench(path) -> Bench:
    """Read a bench TOML file.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    Bench
        In internal units (mm, rad, s).

    Raises
    ------
    CfmInputError
        Unreadable file, TOML syntax error, unknown key, missing or impossible value.
    """
    given, path = str(path), Path(path)  # messages name the file as given (Path drops "//")
    try:
        with open_regular(given, "a bench TOML file", "the bench file") as f:
            raw = f.read()
    except OSError as exc:
        raise CfmInputError(
            f"cannot read the bench file: {exc.strerror or exc}", file=given
        ) from None
    try:
        text = raw.decode("utf-8-sig")  # Windows Notepad writes a BOM
    except UnicodeDecodeError as exc:  # TOML is UTF-8: say where it is not
        line = raw.count(b"\n", 0, exc.start) + 1
        column = exc.start - raw.rfind(b"\n", 0, exc.start)
        raise CfmInputError(
            f"the bench file is not UTF-8 text: byte 0x{raw[exc.start]:02x} at column {column} "
            "is not valid UTF-8 (TOML files are UTF-8); save it as UTF-8",
            file=path,
            line=line,
        ) from None
    return parse_bench(text, source=str(path))


def read_reference_bench() -> Bench:
    """The shipped CFM reference bench: stated assumptions where the paper gives no geometry
    (stack Z, X, Y from the foundation, strokes 800/150/150 mm, probe arm offset), Table II
    PDFs for the 21 errors; each assumption is written in the file and in the outputs."""
    ref = resources.files("cfm_fem.data").joinpath(REFERENCE_BENCH)
    with resources.as_file(ref) as p:
        return read_bench(p)


class BenchChoice(NamedTuple):
    """The bench a command runs on (`resolve_bench`), unpacked as ``bench, sentence``."""

    bench: Bench
    #: What was assumed: the packaged reference bench, or the defaults the file leaves out.
    sentence: str


#: How outputs name the packaged bench when no bench is given.
PACKAGED_BENCH = "(packaged CFM reference bench)"


def resolve_bench(bench=None) -> BenchChoice:
    """The bench of a command: the one given, the file named, or the packaged reference bench.

    Parameters
    ----------
    bench : Bench, path-like or None
        A bench model, a bench TOML file, or None for the packaged CFM reference bench
        (`read_reference_bench`).

    Returns
    -------
    BenchChoice
        ``(bench, sentence)``: the model, and the sentence outputs print about it, e.g.
        ``"bench model (packaged CFM reference bench)"`` or ``"bench model b.toml; not in the
        file, defaults taken: [grid] ..."``.

    Raises
    ------
    CfmInputError
        The file cannot be read or describes no valid bench (`read_bench`).
    """
    if isinstance(bench, Bench):
        model, origin = bench, f"bench model {bench.name} ({bench.source})"
    elif bench is None:
        model, origin = read_reference_bench(), f"bench model {PACKAGED_BENCH}"
    else:
        model, origin = read_bench(bench), f"bench model {bench}"
    taken = [n.removeprefix(DEFAULT_NOTE) for n in model.assumptions if n.startswith(DEFAULT_NOTE)]
    if taken and bench is not None:
        origin += f"; not in the file, defaults taken: {'; '.join(taken)}"
    return BenchChoice(model, origin)


def parse_bench(text: str, source: str = "<string>") -> Bench:
    """Parse bench TOML text (``source`` names it in messages)."""
    doc = _Doc(source, text)
    data = _load_toml(text, source)
    _check_keys(doc, data, _TOP_KEYS, "")
    fmt = _get(doc, data, "format", "", "string", default="cfm-bench")
    if fmt != "cfm-bench":
        raise doc.error("format", f"must be 'cfm-bench'; found {_shown(fmt)}")
    version = _get(doc, data, "version", "", "integer", default=1)
    if version != 1:
        raise doc.error(
            "version", f"must be 1 (the only bench format version); found {_shown(version)}"
        )
    name = _get(doc, data, "name", "", "string", default=Path(source).stem)

    frame = _get(doc, data, "frame", "", "table", required=True)
    _check_keys(doc, frame, {"stack", "tool_offset_mm", "description"}, "frame")
    assumed: list[str] = []  # defaults taken, said in the bench's assumptions
    if "stack" not in frame:
        assumed.append(DEFAULT_NOTE + "[frame] stack = [\"z\", \"x\", \"y\"] (Z on the "
                       "foundation, X on Z, Y on X, as the reference bench)")  # fmt: skip
    stack = frame.get("stack", ["z", "x", "y"])
    if not (isinstance(stack, list) and sorted(map(str, stack)) == sorted(AXES)):
        raise doc.error(
            "frame.stack", f"must list 'x', 'y' and 'z' once each; found {_shown(stack)}"
        )
    tool = _offset(doc, frame, "tool_offset_mm", "frame", required=True)
    axes = _read_axes(doc, data)
    grid_args = _read_grid(doc, data, axes, assumed)

    err_t = _get(doc, data, "errors", "", "table", required=True)
    _check_keys(doc, err_t, set(_ERROR_GROUPS), "errors")
    specs = {}
    for group, keys in _ERROR_GROUPS.items():
        gt = _get(doc, err_t, group, "errors", "table", required=True)
        _check_keys(doc, gt, set(keys), f"errors.{group}")
        for key in keys:
            t = _get(doc, gt, key, f"errors.{group}", "table", required=True)
            spec = _read_error(doc, t, group, key)
            specs[spec.name] = spec
    errors = tuple(specs[n] for n in ERROR_NAMES)

    vib_t = _required_table(doc, data, "vibration", _NO_VIBRATION)
    _check_keys(doc, vib_t, {"std_um"}, "vibration")
    _require_key(doc, vib_t, "std_um", "vibration", _NO_VIBRATION)
    vib = _std_or_vector(doc, vib_t, "std_um", "vibration", 0.0)
    delay = _read_delay(doc, data, assumed)

    mag_t = _get(doc, data, "magnet", "", "table", default={})
    for key, value in (("rotation_deg", "[0, 0, 0]"), ("translation_mm", "[0, 0, 0]")):
        if key not in mag_t:
            assumed.append(
                f"{DEFAULT_NOTE}[magnet] {key} = {value} (magnet frame = bench frame there; "
                "used by sweep --mode htm, coupled, compare and diagnose)"
            )
    _check_keys(doc, mag_t, {"rotation_deg", "translation_mm", *_SURVEY_KEYS}, "magnet")
    rot = _get(doc, mag_t, "rotation_deg", "magnet", "vector3", default=np.zeros(3))
    if np.any(np.abs(rot) > MAX_ROTATION_DEG):
        raise doc.error(
            "magnet.rotation_deg",
            f"must be within +-{MAX_ROTATION_DEG:g} deg per angle; found {_shown(rot.tolist())}",
        )
    trans = _offset(doc, mag_t, "translation_mm", "magnet")
    survey = {k: _survey_std(doc, mag_t, k) for k in _SURVEY_KEYS}

    ass_t = _get(doc, data, "assumptions", "", "table", default={})
    _check_keys(doc, ass_t, {"notes"}, "assumptions")
    notes = ass_t.get("notes", [])
    if not (isinstance(notes, list) and all(isinstance(n, str) for n in notes)):
        raise doc.error("assumptions.notes", "must be a list of strings")

    try:
        return Bench(
            name=name,
            stack=tuple(str(s) for s in stack),
            axes=axes,
            tool_offset_mm=tool,
            errors=errors,
            vibration_std_mm=vib,
            delay=delay,
            magnet=MagnetPlacement(
                np.deg2rad(rot),
                trans,
                survey_std_mm=survey["survey_std_um"],
                survey_std_rad=survey["survey_std_urad"],
            ),
            grid=Grid(**grid_args),
            assumptions=tuple(notes) + tuple(assumed),
            source=source,
        )
    except CfmInputError as exc:  # model-level checks: name the file, the key is in the text
        key = exc.what.split(" ")[0].strip("'")
        raise CfmInputError(exc.what, file=source, line=doc.line_of(key)) from None


_TOP_KEYS = {"format", "version", "name", "frame", "axes", "grid", "errors", "vibration",
             "reading_delay", "magnet", "assumptions"}  # fmt: skip


def _load_toml(text: str, source: str) -> dict:
    """``tomllib.loads`` with every failure a `CfmInputError`: syntax (with its line), arrays
    nested thousands deep (Python's recursion limit) and integers of thousands of digits."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        line = int(m.group(1)) if m else None
        if line is None and "end of document" in str(exc):  # a file cut short: its last line
            line = max(len(text.rstrip().splitlines()), 1)
        raise CfmInputError(f"not valid TOML: {exc}", file=source, line=line) from None
    except RecursionError:
        raise CfmInputError(
            "arrays or tables nested too deep to read; expected a bench description (at most "
            "a few levels)",
            file=source,
        ) from None
    except ValueError as exc:  # an integer beyond Python's digit limit for conversions
        raise CfmInputError(
            f"a value the bench cannot hold ({str(exc).split(':')[0]}); expected numbers of "
            "plausible size",
            file=source,
        ) from None


#: Keys of the magnet's survey uncertainty (1 sigma per axis): key -> (unit, factor to mm or
#: rad, largest value: 1 m, 1 rad).
_SURVEY_KEYS = {"survey_std_um": ("um", 1e-3, 1e6), "survey_std_urad": ("urad", 1e-6, 1e6)}


def _survey_std(doc, table, key) -> float | None:
    """``[magnet] survey_std_um`` / ``survey_std_urad`` in mm / rad, None when absent."""
    v = _get(doc, table, key, "magnet", "number")
    if v is None:
        return None
    unit, factor, largest = _SURVEY_KEYS[key]
    if not 0.0 < v <= largest:
        raise doc.error(
            f"magnet.{key}",
            f"must be > 0 and <= {largest:g} {unit} (a standard deviation); found {_shown(v)}",
        )
    return v * factor


def _offset(doc, table, key, prefix, required=False) -> np.ndarray:
    """A vector3 of mm within `MAX_OFFSET_MM` (a mount offset of 1e300 mm is a typo)."""
    v = _get(doc, table, key, prefix, "vector3", default=np.zeros(3), required=required)
    if np.any(np.abs(v) > MAX_OFFSET_MM):
        raise doc.error(
            f"{prefix}.{key}",
            f"must be within +-{MAX_OFFSET_MM:g} mm per component; found {_shown(v.tolist())}",
        )
    return v


def _read_axes(doc, data) -> dict:
    """``[axes.x]``, ``[axes.y]``, ``[axes.z]``: stroke and mount offset of each axis."""
    axes_t = _get(doc, data, "axes", "", "table", required=True)
    _check_keys(doc, axes_t, set(AXES), "axes")
    axes = {}
    for a in AXES:
        t = _get(doc, axes_t, a, "axes", "table", required=True)
        _check_keys(doc, t, {"stroke_mm", "mount_offset_mm"}, f"axes.{a}")
        stroke = _get(doc, t, "stroke_mm", f"axes.{a}", "number", required=True)
        if not 0 < stroke <= MAX_STROKE_MM:
            raise doc.error(
                f"axes.{a}.stroke_mm", f"must be > 0 and <= {MAX_STROKE_MM:g} mm; found {stroke:g}"
            )
        axes[a] = Axis(a, stroke, _offset(doc, t, "mount_offset_mm", f"axes.{a}"))
    return axes


#: Points per axis of the grid a bench file without ``[grid]`` gets: the reference bench's.
DEFAULT_GRID_POINTS = {"x": 9, "y": 8, "z": 13}


def _read_grid(doc, data, axes, assumed) -> dict:
    """``[grid]``: (start, stop, num) per axis, within its stroke. An axis the file leaves out
    gets its full stroke with the reference bench's point count (`DEFAULT_GRID_POINTS`), said
    in ``assumed``."""
    grid_t = _get(doc, data, "grid", "", "table", default={})
    _check_keys(doc, grid_t, {f"{a}_mm" for a in AXES}, "grid")
    grid_args = {}
    for a in AXES:
        key = f"{a}_mm"
        if key not in grid_t:
            grid_args[a] = (0.0, axes[a].stroke_mm, DEFAULT_GRID_POINTS[a])
            assumed.append(
                f"{DEFAULT_NOTE}[grid] {key} = {{ start = 0, stop = {axes[a].stroke_mm:g}, "
                f"num = {DEFAULT_GRID_POINTS[a]} }} (the whole stroke, the reference bench's "
                "point count)"
            )
            continue
        g = _get(doc, grid_t, key, "grid", "table")
        _check_keys(doc, g, {"start", "stop", "num"}, f"grid.{key}")
        start = _get(doc, g, "start", f"grid.{key}", "number", required=True)
        stop = _get(doc, g, "stop", f"grid.{key}", "number", required=True)
        num = _get(doc, g, "num", f"grid.{key}", "integer", required=True)
        if not 1 <= num <= MAX_GRID_POINTS:
            raise doc.error(
                f"grid.{key}.num", f"must be >= 1 and <= {MAX_GRID_POINTS:,}; found {_shown(num)}"
            )
        if min(start, stop) < 0 or max(start, stop) > axes[a].stroke_mm + 1e-9:
            raise doc.error(
                f"grid.{key}",
                f"must stay within the stroke [0, {axes[a].stroke_mm:g}] mm; "
                f"found start={start:g}, stop={stop:g}",
            )
        grid_args[a] = (start, stop, num)
    n_grid = int(np.prod([int(g[2]) for g in grid_args.values()], dtype=object))
    if n_grid > MAX_GRID_POINTS:
        raise doc.error(
            "grid",
            f"has {n_grid:,} points; expected at most {MAX_GRID_POINTS:,} (about 30 kB "
            "of memory per point in kinematics)",
        )
    return grid_args


def _read_delay(doc, data, assumed) -> ReadingDelay:
    """``[reading_delay]``: model 'normal' (std_um) or 'speed_tau' (speed_mm_s and tau); the
    table is required (`_NO_DELAY`); a tau without a unit is in s, said in ``assumed``."""
    del_t = _required_table(doc, data, "reading_delay", _NO_DELAY)
    _check_keys(doc, del_t, {"model", "std_um", "speed_mm_s", "tau"}, "reading_delay")
    model = _get(doc, del_t, "model", "reading_delay", "string", default="normal")
    if model == "normal":
        for k in ("speed_mm_s", "tau"):
            if k in del_t:
                raise doc.error(f"reading_delay.{k}", "is only used with model = 'speed_tau'")
        _require_key(doc, del_t, "std_um", "reading_delay", _NO_DELAY)
        return ReadingDelay("normal", _std_or_vector(doc, del_t, "std_um", "reading_delay", 0.0))
    if model != "speed_tau":
        raise doc.error(
            "reading_delay.model", f"must be 'normal' or 'speed_tau'; found {_shown(model)}"
        )
    if "std_um" in del_t:
        raise doc.error("reading_delay.std_um", "is only used with model = 'normal'")
    speed = _get(doc, del_t, "speed_mm_s", "reading_delay", "vector3", required=True)
    if np.any(np.abs(speed) > MAX_SPEED_MM_S):
        raise doc.error(
            "reading_delay.speed_mm_s",
            f"must be within +-{MAX_SPEED_MM_S:g} mm/s; found {_shown(speed.tolist())}",
        )
    tau_t = _get(doc, del_t, "tau", "reading_delay", "table", required=True)
    _check_keys(doc, tau_t, _ERROR_KEYS - {"profile", "note"}, "reading_delay.tau")
    unit = _get(doc, tau_t, "unit", "reading_delay.tau", "string", default="s")
    if "unit" not in tau_t:
        assumed.append(DEFAULT_NOTE + "[reading_delay] tau in s (tau states no unit)")
    scales = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
    if unit not in scales:
        raise doc.error("reading_delay.tau.unit", f"must be one of s, ms, us; found {_shown(unit)}")
    tau = _pdf(doc, tau_t, "reading_delay.tau", scales[unit], "time")
    lowest = _lowest(tau)
    if lowest < 0:
        raise doc.error(
            "reading_delay.tau",
            f"reaches {lowest / scales[unit]:.3g} {unit}; expected a delay >= 0 (a reading "
            "cannot come before its position): a PDF on [0, ...), e.g. uniform with low >= 0"
            + (" or a normal whose mean - 3 std >= 0" if tau.kind == "normal" else ""),
        )
    return ReadingDelay("speed_tau", np.zeros(3), speed, tau)


def _lowest(pdf: Pdf) -> float:
    """The lowest value ``pdf`` takes (for a normal or Student t: mean - 3 std)."""
    if pdf.kind in ("normal", "student_t"):
        return pdf.mean - 3.0 * pdf.std
    return float(pdf.params[0])


def _fmt(v) -> str:
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    return repr(float(v))


def bench_to_toml(bench: Bench) -> str:
    """TOML text that :func:`parse_bench` reads back into an equal bench (round trip)."""
    out = [
        "# cfm_fem bench description, written by cfm_fem (cfm_reference_bench.toml explains keys)",
        'format = "cfm-bench"',
        "version = 1",
        f"name = {_fmt(bench.name)}",
        "",
        "[frame]",
        f"stack = {_fmt(list(bench.stack))}",
        f"tool_offset_mm = {_fmt(bench.tool_offset_mm)}",
    ]
    for a in AXES:
        ax = bench.axes[a]
        out += [
            "",
            f"[axes.{a}]",
            f"stroke_mm = {_fmt(ax.stroke_mm)}",
            f"mount_offset_mm = {_fmt(ax.mount_offset_mm)}",
        ]
    out += ["", "[grid]"]
    for a in AXES:
        s, e, n = getattr(bench.grid, a)
        out.append(f"{a}_mm = {{ start = {_fmt(s)}, stop = {_fmt(e)}, num = {int(n)} }}")
    for spec in bench.errors:
        name = spec.name
        group, key = ("squareness", name) if "(" not in name else (name[-2], name[:-3])
        units = _ANGLE_UNITS if spec.is_angle else _LENGTH_UNITS
        pdf = spec.pdf
        if pdf.kind == "trapezoidal":
            s = 1.0 / units[spec.unit]
            shown = Pdf(pdf.kind, (pdf.params[0] * s, pdf.params[1] * s, pdf.params[2]))
        else:
            shown = pdf.scaled(1.0 / units[spec.unit])
        out += ["", f"[errors.{group}.{key}]"]
        if spec.note:
            out.append(f"note = {_fmt(spec.note)}")
        out.append(f"pdf = {_fmt(shown.kind)}")
        out += [f"{k} = {_fmt(v)}" for k, v in shown.named_params().items()]
        out.append(f"unit = {_fmt(spec.unit)}")
        if tuple(spec.profile) != (1.0,):
            out.append(f"profile = {_fmt(list(spec.profile))}")
    out += ["", "[vibration]", f"std_um = {_fmt(np.asarray(bench.vibration_std_mm) * 1e3)}"]
    d = bench.delay
    out += ["", "[reading_delay]", f"model = {_fmt(d.model)}"]
    if d.model == "normal":
        out.append(f"std_um = {_fmt(np.asarray(d.std_mm) * 1e3)}")
    else:
        out.append(f"speed_mm_s = {_fmt(d.speed_mm_s)}")
        tau = ", ".join(f"{k} = {_fmt(v)}" for k, v in d.tau_pdf.named_params().items())
        out.append(f'tau = {{ pdf = {_fmt(d.tau_pdf.kind)}, {tau}, unit = "s" }}')
    out += [
        "",
        "[magnet]",
        f"rotation_deg = {_fmt(np.rad2deg(bench.magnet.rotation_rad))}",
        f"translation_mm = {_fmt(bench.magnet.translation_mm)}",
        *_survey_lines(bench.magnet),
        "",
        "[assumptions]",
        "notes = [",
        *[f"  {_fmt(n)}," for n in bench.assumptions if not n.startswith(DEFAULT_NOTE)],
        "]",
        "",
    ]
    return "\n".join(out)


def _survey_lines(magnet) -> list:
    """The ``[magnet]`` survey keys a bench states (none when it states none)."""
    out = []
    values = (magnet.survey_std_mm, magnet.survey_std_rad)
    for key, value in zip(_SURVEY_KEYS, values, strict=True):
        if value is not None:
            out.append(f"{key} = {_fmt(float(f'{value / _SURVEY_KEYS[key][1]:.12g}'))}")
    return out


def write_bench(path, bench: Bench) -> None:
    """Write ``bench`` as TOML, atomically."""
    write_text(path, bench_to_toml(bench))
