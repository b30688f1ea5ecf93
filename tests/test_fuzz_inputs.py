"""Property-based fuzzing of every reader, the bench TOML and the recordings parser, seeded
with the bundled maps, the packaged bench and harmonics, generated recordings and the real
files of ``../shared/data`` (when present).

Each generated input must be read or refused with one `CfmInputError` whose message holds no
raw control character; nothing else may escape (a traceback), and no case may take more than a
few seconds (a hang). `scripts/fuzz_inputs.py` runs the same kind of mutations through the
command line.
"""

from __future__ import annotations

import re
import signal
import warnings
from importlib import resources
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_field
from cfm_fem.io.bench_toml import parse_bench
from cfm_fem.io.harmonics import read_harmonics
from cfm_fem.io.recordings import read_recording

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"
#: Seeds: (name, bytes); large files are cut to their first lines (the mutations reach the
#: header and the numbers alike, and each case stays fast).
HEAD_LINES = 60


def _head(path: Path, lines: int = HEAD_LINES) -> bytes:
    with open(path, "rb") as f:
        return b"".join(f.readline() for _ in range(lines))


def _seeds() -> dict:
    seeds = {
        "map.txt": _head(ROOT / "meshes" / "quadrupole_comsol.txt"),
        "map.table": _head(ROOT / "meshes" / "quadrupole_opera.table"),
    }
    real = {
        "emphatic/mfMapMeasured_5mm.txt": "real.txt",
        "emphatic/CylinderGrid_Section1_231025-112209.txt": "section.txt",
        "emphatic/EMPHATIC_body_scan_5280148.csv": "real.csv",
        "cctpy/test_opera_field_table.table": "real.table",
    }
    for rel, name in real.items():
        if (DATA / rel).is_file():
            seeds[name] = _head(DATA / rel, 200)
    return seeds


SEEDS = _seeds()
BENCH = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_bytes()
HARMONICS = resources.files("cfm_fem.data").joinpath("qfdp4_harmonics.csv").read_bytes()
RECORDING = (
    "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas,t_s\n"
    + "".join(
        f"{i // 2},{i % 2},{i}.5,2.25,30,{i}.5013,2.2489,30.0021,{i * 7}\n" for i in range(12)
    )
).encode()

#: Tokens met in fuzzing: digit separators, non-ASCII digits, overflow, escapes, cut numbers.
TOKENS = ["1_000", "\u0661\u0662", "2\u00b9", "1e308", "-1e309", "1e300", "9" * 400, "\x1b[2J",
          "\x07", "\u202e", "\x85", "\xff", "E-0", "E", ".", "-", "nan", "inf", "#REF!",
          '"1,066.67"', "\x00", "\r", "\n", ",", ";", "\t", " ", "%", "#", "[", "]", "=", '"',
          "0"]  # fmt: skip

mutation = st.one_of(
    st.tuples(st.just("insert"), st.floats(0, 1), st.sampled_from(TOKENS)),
    st.tuples(st.just("replace"), st.floats(0, 1), st.sampled_from(TOKENS)),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 30)),
    st.tuples(st.just("cut_end"), st.floats(0, 1), st.integers(1, 12)),
    st.tuples(st.just("byte"), st.floats(0, 1), st.integers(0, 255)),
    st.tuples(st.just("dup_line"), st.floats(0, 1), st.just(0)),
)


def mutate(data: bytes, ops) -> bytes:
    """Apply ``ops`` (from ``mutation``) to ``data``."""
    for op, where, arg in ops:
        i = int(where * len(data))
        if op == "insert":
            data = data[:i] + arg.encode("utf-8") + data[i:]
        elif op == "replace":  # the number (or word) at i
            m = re.compile(rb"[^\s,;]+").search(data, i)
            if m:
                data = data[: m.start()] + arg.encode("utf-8") + data[m.end() :]
        elif op == "delete":
            data = data[:i] + data[i + arg :]
        elif op == "cut_end":
            data = data[: max(len(data) - arg, 0)]
        elif op == "byte":
            data = data[:i] + bytes([arg]) + data[i + 1 :]
        else:
            lines = data.split(b"\n")
            k = min(i * len(lines) // max(len(data), 1), len(lines) - 1)
            lines.insert(k, lines[k])
            data = b"\n".join(lines)
    return data


_RAW_CONTROL = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202a-\u202e]")


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout


def check(read, arg, seconds: int = 10) -> None:
    """``read(arg)`` returns or raises one clean `CfmInputError`, within ``seconds``."""
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(seconds)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            read(arg)
    except CfmInputError as exc:
        assert str(exc) and not _RAW_CONTROL.search(str(exc)), repr(str(exc))
    except _Timeout:
        pytest.fail(f"no answer in {seconds} s")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


SETTINGS = settings(
    max_examples=80,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@pytest.mark.parametrize("name", sorted(SEEDS))
@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=3))
def test_field_readers(folder, name, ops):
    path = folder / name
    path.write_bytes(mutate(SEEDS[name], ops))
    options = {"length_unit": "mm"} if name in ("real.csv", "section.txt") else {}
    check(lambda p: read_field(p, **options), path)


@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=3))
def test_bench_toml(ops):
    text = mutate(BENCH, ops).decode("utf-8", errors="replace")
    check(lambda t: parse_bench(t, source="bench.toml"), text)


FILE_READERS = {"harmonics": (HARMONICS, read_harmonics), "recording": (RECORDING, read_recording)}


@pytest.mark.parametrize("kind", sorted(FILE_READERS))
@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=3))
def test_harmonics_and_recordings(folder, kind, ops):
    seed, read = FILE_READERS[kind]
    path = folder / f"{kind}.csv"
    path.write_bytes(mutate(seed, ops))
    check(read, path)


def _fuzz_script():
    """``scripts/fuzz_inputs.py`` as a module (a script, not part of the package); imported by
    name, so that its worker processes import it too."""
    import importlib
    import sys

    if str(ROOT / "scripts") not in sys.path:
        sys.path.insert(0, str(ROOT / "scripts"))
    return importlib.import_module("fuzz_inputs")


def test_command_line_fuzz_subset(tmp_path):
    """A bounded-time subset of the command-line fuzzer (some 30 s): the packaged bench without
    each optional table, and options of every command set to fuzzing tokens. Every case ends
    in exit 0 with finite outputs or in exit 2 naming its input; nothing else."""
    import random

    fuzz = _fuzz_script()
    cases = fuzz.make_cases(10, random.Random(3), kinds=("tables",), commands={"kinematics"})
    cases += fuzz.make_cases(16, random.Random(5), kinds=("options",))
    counts, failures = fuzz.run_cases(cases, workers=1, timeout=60, keep=tmp_path / "keep")
    assert not failures, "\n".join(f"{label}: {outcome}: {tail}"
                                   for _, label, outcome, _, tail in failures)  # fmt: skip
    outcomes = {o for _, o in counts}
    assert outcomes <= {"exit 0", "exit 2"} and sum(counts.values()) == len(cases)
