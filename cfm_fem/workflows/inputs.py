"""Inputs every command entry of `cfm_fem.workflows` takes the same way: a bench (model, file or
None), a recording (object or file), a field map (object or file) with the reader's options, and
the provenance entry of a bench.

The command line and `cfm_fem.api` both call the entries; these functions let each entry take
either what the command line has already read (with its own messages) or a path.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import CfmInputError
from ..io._parse import CLI_OPTIONS
from ..io.bench_toml import BenchChoice, resolve_bench
from ..models.bench import Bench
from ..models.field import FieldMap
from ..models.recordings import Recording

__all__ = [
    "READER_DEFAULTS",
    "bench_provenance",
    "choose_bench",
    "field_map",
    "given_reader_options",
    "recording",
    "refuse_reader_options",
]

#: Keyword arguments of `cfm_fem.io.read_field` and their defaults; an option left at its
#: default was not given.
READER_DEFAULTS = {"fmt": None, "length_unit": None, "field_unit": None, "zero_rows": "warn",
                   "solution": None}  # fmt: skip


def choose_bench(bench=None) -> BenchChoice:
    """``(bench, sentence)`` of `cfm_fem.io.bench_toml.resolve_bench`: a `Bench`, a bench file
    or None (the packaged CFM reference bench)."""
    return resolve_bench(bench)


def bench_provenance(bench=None) -> dict:
    """The provenance entry of the bench a run used (`cfm_fem.io.provenance.bench_input`): the
    file given, the packaged reference bench (None), or the file a `Bench` was read from."""
    from ..io.provenance import bench_input

    if isinstance(bench, Bench):
        src = Path(str(bench.source))
        if not src.is_file():
            return {"name": bench.name, "source": str(bench.source), "packaged_default": False}
        entry = bench_input(src)
        entry["packaged_default"] = src.resolve() == Path(bench_input(None)["path"]).resolve()
        return entry
    return bench_input(bench)


def recording(rec, kind: str | None = None) -> Recording:
    """A `Recording` as given, or read from a file (`cfm_fem.io.recordings`, mm and T)."""
    if isinstance(rec, Recording):
        return rec
    from ..io.recordings import read_hall_map, read_tracker
    from ..io.recordings import read_recording as read_any

    readers = {None: read_any, "tracker": read_tracker, "hall": read_hall_map}
    if kind not in readers:
        raise CfmInputError(f"kind must be 'tracker' or 'hall'; got {kind!r}")
    return readers[kind](rec)


def field_map(field, reader: dict | None = None) -> FieldMap:
    """A `FieldMap` as given, or read from a file with the reader options ``reader``
    (keyword arguments of `cfm_fem.io.read_field`)."""
    if isinstance(field, FieldMap):
        return field
    from ..io import read_field

    return read_field(field, **(reader or {}))


def given_reader_options(reader: dict | None) -> list[str]:
    """The reader options of ``reader`` not left at their default, as the command line spells
    them (``--format``, ``--length-unit``, ...)."""
    reader = reader or {}
    return [CLI_OPTIONS[k][0] for k, v in READER_DEFAULTS.items() if reader.get(k, v) != v]


def refuse_reader_options(reader: dict | None, why: str) -> None:
    """Refuse reader options given where no field map is read; ``why`` says what is read."""
    given = given_reader_options(reader)
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise CfmInputError(f"{' and '.join(given)} {verb} to a field map only; {why}")
