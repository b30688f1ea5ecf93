"""Property-based tests of every reader: generated and mutated files never raise anything but
`CfmInputError` (warnings allowed). The number of cases run is printed in the terminal summary.
"""

from __future__ import annotations

import collections
import contextlib
import warnings
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import cfm_fem.io.recordings as recordings_io
from cfm_fem.errors import CfmInputError
from cfm_fem.io import read_comsol, read_field, read_meshfile, read_opera, read_table
from cfm_fem.io.bench_toml import parse_bench
from cfm_fem.io.harmonics import read_harmonics

SETTINGS = settings(
    max_examples=120,
    deadline=None,
    derandomize=True,  # the same cases in every run (and in CI)
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
CASES = collections.Counter()


@pytest.fixture(scope="module", autouse=True)
def _report_counts(request):
    yield
    plugins = request.config.pluginmanager
    reporter = plugins.get_plugin("terminalreporter")
    capture = plugins.get_plugin("capturemanager")
    if reporter is not None and CASES:
        total = sum(CASES.values())
        per = ", ".join(f"{k} {v}" for k, v in sorted(CASES.items()))
        with capture.global_and_fixture_disabled() if capture else contextlib.nullcontext():
            reporter.write_line(f"\nreaders property tests: {total} cases ({per})")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("prop")


def _check(name, read, path):
    """Run one reader; anything but success or CfmInputError fails the test."""
    CASES[name] += 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            read(path)
        except CfmInputError as exc:
            assert str(exc)  # one message, never empty


# --------------------------------------------------------------------------- mutations

TOKENS = ["nan", "inf", "-inf", "1e999", "abc", "O.3", ",", ";", "\t", " ", "%", "#", '"', "'",
          "\n", "\r", "\x00", "-", "+", ".", "1,066.67", "[mm]", "(T)", "[furlong]", "0", "1",
          "-1", "é", "\ufeff", "[", "]", "(", ")", "=", "{", "}", "x", "Bx", "% Length unit: m",
          "1 X [METRE]", "2"]  # fmt: skip

mutation = st.one_of(
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 40)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.sampled_from(TOKENS)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.text(max_size=8)),
    st.tuples(st.just("truncate"), st.floats(0, 1), st.just(0)),
    st.tuples(st.just("dup_line"), st.floats(0, 1), st.just(0)),
    st.tuples(st.just("drop_line"), st.floats(0, 1), st.just(0)),
    st.tuples(st.just("swap_lines"), st.floats(0, 1), st.floats(0, 1)),
    st.tuples(st.just("byte"), st.floats(0, 1), st.integers(0, 255)),
)


def _mutate(data: bytes, ops) -> bytes:
    for op, where, arg in ops:
        i = int(where * len(data))
        if op == "delete":
            data = data[:i] + data[i + arg :]
        elif op == "insert":
            data = data[:i] + str(arg).encode("utf-8") + data[i:]
        elif op == "truncate":
            data = data[:i]
        elif op == "byte":
            data = data[:i] + bytes([arg]) + data[i + 1 :]
        else:
            lines = data.split(b"\n")
            k = min(int(where * len(lines)), len(lines) - 1)
            if op == "dup_line":
                lines.insert(k, lines[k])
            elif op == "drop_line":
                del lines[k]
            else:
                j = min(int(arg * len(lines)), len(lines) - 1)
                lines[k], lines[j] = lines[j], lines[k]
            data = b"\n".join(lines)
    return data


# --------------------------------------------------------------------------- generated maps

number = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@st.composite
def fieldmaps(draw):
    """A small valid map: a grid or scattered nodes, with or without repeated values."""
    from cfm_fem.models.field import FieldMap

    n = draw(st.integers(1, 4))
    ax = np.sort(np.unique(np.round(draw(st.lists(number, min_size=n, max_size=n)), 3)))
    pts = np.stack(np.meshgrid(ax, ax[::-1], ax, indexing="ij"), -1).reshape(-1, 3)
    B = np.array(draw(st.lists(st.tuples(number, number, number), min_size=len(pts),
                               max_size=len(pts))), dtype=float).reshape(-1, 3)  # fmt: skip
    return FieldMap(points=pts, B=B * 1e-3)


def _writer(fmt):
    from cfm_fem.io import write_comsol, write_opera, write_table

    return {"table": write_table, "comsol": write_comsol, "opera": write_opera}[fmt]


READERS = {
    "table": (read_table, "map.csv"),
    "comsol": (read_comsol, "map.txt"),
    "opera": (read_opera, "map.table"),
}


@pytest.mark.parametrize("fmt", list(READERS))
@SETTINGS
@given(fm=fieldmaps(), ops=st.lists(mutation, max_size=4))
@pytest.mark.slow
def test_text_readers(folder, fmt, fm, ops):
    read, name = READERS[fmt]
    path = folder / name
    try:
        _writer(fmt)(path, fm)
    except CfmInputError:
        return  # not a full grid for Opera: nothing to mutate
    path.write_bytes(_mutate(path.read_bytes(), ops))
    _check(fmt, read, path)
    _check(f"read_field[{fmt}]", read_field, path)


@SETTINGS
@given(fm=fieldmaps(), ops=st.lists(mutation, max_size=4))
def test_mesh_reader_on_ascii_vtu(folder, fm, ops):
    import meshio

    path = folder / "map.vtu"
    cells = [("vertex", np.arange(len(fm.points))[:, None])]
    meshio.write(path, meshio.Mesh(fm.points, cells, {"B": fm.B}), binary=False)
    path.write_bytes(_mutate(path.read_bytes(), ops))
    _check("meshio vtu", read_meshfile, path)


@SETTINGS
@given(data=st.binary(max_size=400), suffix=st.sampled_from([".csv", ".txt", ".table", ".vtu"]))
def test_any_bytes(folder, data, suffix):
    path = folder / f"junk{suffix}"
    path.write_bytes(data)
    _check("random bytes", read_field, path)


# --------------------------------------------------------------------------- bench, harmonics

BENCH = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_bytes()
HARMONICS = resources.files("cfm_fem.data").joinpath("qfdp4_harmonics.csv").read_bytes()


@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=4))
def test_bench_reader(ops):
    text = _mutate(BENCH, ops).decode("utf-8", errors="replace")
    _check("bench toml", lambda t: parse_bench(t, source="bench.toml"), text)


@SETTINGS
@given(ops=st.lists(mutation, min_size=1, max_size=4))
def test_harmonics_reader(folder, ops):
    path = folder / "harmonics.csv"
    path.write_bytes(_mutate(HARMONICS, ops))
    _check("harmonics", read_harmonics, path)


# --------------------------------------------------------------------------- recordings


@st.composite
def recordings(draw):
    kind = draw(st.sampled_from(["tracker", "hall"]))
    cols = ["point_id", "rep", "x_cmd", "y_cmd", "z_cmd"]
    cols += ["x_meas", "y_meas", "z_meas"] if kind == "tracker" else ["Bx", "By", "Bz"]
    cols += draw(st.lists(st.sampled_from(["t_s", "dir_x", "speed", "temp_C", "note"]),
                          unique=True, max_size=3))  # fmt: skip
    n = draw(st.integers(1, 6))
    rows = []
    for i in range(n):
        vals = [str(i // 2), str(i % 2)] + [repr(draw(number)) for _ in cols[2:]]
        rows.append(",".join(vals))
    return kind, ",".join(cols) + "\n" + "\n".join(rows) + "\n"


@SETTINGS
@given(rec=recordings(), ops=st.lists(mutation, max_size=4))
def test_recording_readers(folder, rec, ops):
    mod = recordings_io
    kind, text = rec
    path = folder / "rec.csv"
    path.write_bytes(_mutate(text.encode(), ops))
    read = mod.read_tracker if kind == "tracker" else mod.read_hall_map
    _check(f"recordings {kind}", read, path)


def test_cases_were_counted():
    # runs last in this file (pytest keeps file order): every reader above ran
    assert CASES, "no property case ran"
    assert all(v > 0 for v in CASES.values())
    print(f"\nreaders property tests: {sum(CASES.values())} cases: {dict(CASES)}")


def test_mutation_helper():
    assert _mutate(b"abc\ndef", [("delete", 0.0, 1)]) == b"bc\ndef"
    assert _mutate(b"abc\ndef", [("swap_lines", 0.0, 0.9)]) == b"def\nabc"
    assert Path  # noqa: B018 (keep the import used when the file is trimmed)


def test_harmonics_not_utf8_found_by_hypothesis(tmp_path):
    # a file that is not UTF-8 (a Latin-1 byte at the start) is read as Latin-1
    path = tmp_path / "h.csv"
    path.write_bytes(b"\x80" + HARMONICS[1:])
    _check("harmonics", read_harmonics, path)
