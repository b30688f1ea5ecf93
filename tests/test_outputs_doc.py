"""docs/outputs.md against what the commands write: each command is run small, and the files,
VTU arrays, JSON keys and table columns written are compared with the page, both ways (nothing
written undocumented, nothing documented unwritten). Every map written is read with meshio and
with pyvista."""

from __future__ import annotations

import json
import re
from pathlib import Path

import meshio
import numpy as np
import pytest
import pyvista as pv

from cfm_fem.cli import main

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "outputs.md"
COMPONENTS = ("Bx", "By", "Bz", "absB")

pytestmark = pytest.mark.slow


def _ticks(text: str) -> list[str]:
    return re.findall(r"`([^`]+)`", text)


def _sections() -> dict:
    """``{command: [(context, header, [(first cell, other cells), ...]), ...]}``: every table of
    each ``## command`` section; context is the last ``###`` heading or backticked
    ``file``: line above the table."""
    out, command, context, table = {}, None, "", None
    for line in PAGE.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            command, context = line[3:].strip(), ""
            out[command] = []
        elif line.startswith("### "):
            context = line[4:].strip()
        elif re.fullmatch(r"`[^`]+`:", line.strip()):
            context = line.strip()[1:-2]
        if command is None:
            continue
        if line.startswith("|"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
            if table is None:
                table = (context, cells[0], [])
                out[command].append(table)
            elif not set(cells[0]) <= set("-: "):
                table[2].append((cells[0], " ".join(cells[1:])))
        else:
            table = None
    return out


def _documented(command: str, header: str, context: str | None = None) -> set[str]:
    """First-cell names of the tables with this header (and context) in a section; names in
    parentheses are parts of the one before (``seconds`` (``pilot``, ``pass``)), not counted."""
    names = set()
    for ctx, head, rows in _sections()[command]:
        if head == header and (context is None or ctx == context):
            for first, _ in rows:
                names.update(_ticks(re.sub(r"\([^)]*\)", "", first)))
    return names


def _expand(names, **values) -> set[str]:
    """``<c>_u_units`` -> ``Bx_u_units``, ...; ``<label>`` likewise."""
    out = set()
    for n in names:
        todo = [n]
        for key, vals in values.items():
            todo = (
                [t.replace(f"<{key}>", v) for t in todo for v in vals]
                if any(f"<{key}>" in t for t in todo)
                else todo
            )
        out.update(todo)
    return out


def _file_pattern(name: str) -> re.Pattern:
    """A documented file name as a pattern: ``<...>`` is any name part, ``piece_0000`` any
    piece number."""
    pat = re.escape(name).replace(re.escape("piece_0000"), r"piece_\d{4}")
    pat = re.sub(r"<[^>]+>", r"[^/]+", pat.replace("\\<", "<").replace("\\>", ">"))
    return re.compile(pat + ("" if name.endswith("/") else "$"))


def _written_files(out: Path) -> set[str]:
    """Files and folders written into ``out`` (relative; a folder's contents once, as
    ``folder/``); the folder's lock (the page's introduction) left out."""
    found = set()
    for p in out.rglob("*"):
        rel = p.relative_to(out).as_posix()
        if rel.startswith(".cfm_fem_") and rel != ".cfm_fem.lock":
            found.add(rel.split("/")[0] + "/")
        elif p.is_file() and rel != ".cfm_fem.lock":
            found.add(rel)
    return found


def _check_files(command: str, runs: list[Path], unavailable=()) -> None:
    """Files written by ``runs`` against the section's file table; ``unavailable``: documented
    files that need what this machine lacks."""
    documented = _documented(command, "file") - set(unavailable)
    patterns = {d: _file_pattern(d) for d in documented if d not in ("...",)}
    seen = set()
    undocumented = []
    for out in runs:
        for f in _written_files(out):
            hits = [d for d, pat in patterns.items() if pat.match(f)]
            seen.update(hits)
            if not hits:
                undocumented.append(f"{out.name}/{f}")
    assert not undocumented, f"{command}: written, not in outputs.md: {undocumented}"
    unwritten = sorted(set(patterns) - seen)
    assert not unwritten, f"{command}: in outputs.md, never written: {unwritten}"


def _read_both(path: Path) -> pv.DataSet:
    """A written map through meshio and pyvista: both must read it whole."""
    m = meshio.read(path)
    g = pv.read(path)
    assert len(m.points) == g.n_points > 0
    assert set(m.point_data) == set(g.point_data)
    assert set(m.field_data) == set(g.field_data)
    for name in g.point_data:
        np.testing.assert_array_equal(
            np.asarray(m.point_data[name]).reshape(g.point_data[name].shape),
            g.point_data[name],
            err_msg=f"{path}: {name}",
        )
    return g


def _csv_map(path: Path, n: int = 6) -> Path:
    ax = np.arange(float(n))
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = np.c_[0.03 * pts[:, 0] ** 2, -0.02 * pts[:, 1] * pts[:, 2], 1.0 + 0.1 * pts[:, 2]]
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    """Sweeps that together write every output of ``sweep``."""
    tmp = tmp_path_factory.mktemp("sweeps")
    path = _csv_map(tmp / "map.csv")
    base = ["sweep", str(path), "--trials", "60", "--chunk-nodes", "100"]
    runs = {
        "plain": [*base, "--up", "0,20", "--table", "csv", "--region", "cylinder:3,1:4"],
        "pieces": [*base, "--up", "0,20", "--pieces", "2", "--keep-chunks",
                   "--field-model", "harmonic"],
        "htm": [*base, "--mode", "htm"],
        "slabs": [*base, "--up", "20", "--slabs", "2", "--keep-chunks"],
    }  # fmt: skip
    if _has_pyarrow():
        runs["parquet"] = [*base, "--up", "20", "--table", "parquet"]
    outs = {}
    for name, argv in runs.items():
        outs[name] = tmp / name
        assert main([*argv, "--out", str(outs[name])]) == 0, name
    return outs


def _has_pyarrow() -> bool:
    try:
        import pyarrow.parquet  # noqa: F401
    except ImportError:
        return False
    return True


def test_sweep_files_match_the_page(sweeps):
    # nodes.parquet: written by --table parquet where pyarrow is installed (the run then adds it)
    _check_files("sweep", list(sweeps.values()), () if _has_pyarrow() else ["nodes.parquet"])


def test_every_sweep_map_reads_in_meshio_and_pyvista_and_its_arrays_are_documented(sweeps):
    point = _expand(_documented("sweep", "array", "Point data of each map"), c=COMPONENTS)
    field = _documented("sweep", "array", "Field data of each map")
    seen_point, seen_field, maps = set(), set(), 0
    for out in sweeps.values():
        for f in sorted(out.rglob("*.vtu")):
            g = _read_both(f)
            maps += 1
            seen_point |= set(g.point_data)
            seen_field |= set(g.field_data)
    assert maps >= 10
    assert not seen_point - point, f"point data not in outputs.md: {seen_point - point}"
    assert not point - seen_point, f"point data in outputs.md, never written: {point - seen_point}"
    assert not seen_field - field, f"field data not in outputs.md: {seen_field - field}"
    assert not field - seen_field, f"field data in outputs.md, never written: {field - seen_field}"


def test_sweep_summary_keys_match_the_page(sweeps):
    documented = _documented("sweep", "key", "summary.json")
    seen = set()
    for out in sweeps.values():
        seen |= set(json.loads((out / "summary.json").read_text()))
    assert not seen - documented, f"summary.json keys not in outputs.md: {seen - documented}"
    assert not documented - seen, f"in outputs.md, never written: {documented - seen}"


def test_nodes_table_columns_match_the_page(sweeps):
    out = sweeps["plain"]
    summary = json.loads((out / "summary.json").read_text())
    documented = _expand(_documented("sweep", "column", "nodes.csv"), label=summary["columns"])
    header = (out / "nodes.csv").read_text().splitlines()[0].split(",")
    assert set(header) == documented
    table = np.genfromtxt(out / "nodes.csv", delimiter=",", names=True)
    assert len(table) == summary["nodes"]


def _top_level(text: str) -> str:
    """``text`` without its parenthesised parts (at any depth)."""
    out, depth = [], 0
    for ch in text:
        depth += ch == "("
        if depth == 0:
            out.append(ch)
        depth -= ch == ")" and depth > 0
    return "".join(out)


def _inline_names(command: str, file: str, top_level: bool = False) -> set[str]:
    """Backticked names in the content cell of ``file``'s row of a section's file table
    (``top_level``: only those outside parentheses)."""
    for _, head, rows in _sections()[command]:
        if head != "file":
            continue
        for first, rest in rows:
            if file in _ticks(first):
                return set(_ticks(_top_level(rest) if top_level else rest))
    raise AssertionError(f"{command}: no row for {file} in outputs.md")


def test_kinematics_outputs_match_the_page(tmp_path):
    out = tmp_path / "kin"
    assert main(["kinematics", "--trials", "60", "--fast-intervals", "--out", str(out)]) == 0
    _check_files("kinematics", [out])
    g = _read_both(out / "points.vtu")
    written = set(g.point_data) | set(g.field_data)
    documented = _inline_names("kinematics", "points.vtu")
    assert written == documented
    keys = set(json.loads((out / "summary.json").read_text()))
    assert keys == _documented("kinematics", "key")


def test_design_and_synth_outputs_match_the_page(tmp_path):
    path = _csv_map(tmp_path / "map.csv", n=5)
    out = tmp_path / "des"
    argv = ["design", str(path), "--uf-max", "50", "--up", "0,20", "--trials", "60",
            "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    _check_files("design", [out])
    keys = set(json.loads((out / "design.json").read_text()))
    assert keys == _documented("design", "key", "design.json")
    for f in out.glob("*.vtu"):
        _read_both(f)
    columns = set()
    for kind, extra in (("tracker", ["--grid", "2,2,2"]), ("hall", [])):
        rec = tmp_path / kind / "rec.csv"
        rec.parent.mkdir()
        assert main(["synth", kind, "--reps", "1", *extra, "--out", str(rec)]) == 0
        assert [p.name for p in rec.parent.iterdir()] == [rec.name]
        header = next(ln for ln in rec.read_text().splitlines() if not ln.startswith("#"))
        columns |= set(header.split(","))
    assert columns == _documented("synth", "column")


def _keys_and_words(obj) -> set[str]:
    """Every key of a JSON document at any depth, and every string value."""
    found = set()
    if isinstance(obj, dict):
        for k, v in obj.items():
            found.add(k)
            found |= _keys_and_words(v)
    elif isinstance(obj, list):
        for v in obj:
            found |= _keys_and_words(v)
    elif isinstance(obj, str):
        found.add(obj)
    return found


def _check_inline_json(command: str, outs, file: str, extra=frozenset(), nested=True) -> None:
    """A JSON file whose keys the page lists in its row: every top-level key written (by the
    runs in ``outs``) is named there, and every name there is a key (at any depth) or a value
    of the file in one of the runs; ``nested=False`` checks this for the names outside
    parentheses only (the fields of list items, e.g. of the effects a diagnosis finds, are
    written only when the list has items)."""
    named = _inline_names(command, file) | set(extra)
    words = set()
    for out in outs:
        doc = json.loads((out / file).read_text())
        assert not set(doc) - named, f"{command} {file}: not in outputs.md: {set(doc) - named}"
        words |= _keys_and_words(doc)
    unwritten = {
        n for n in _inline_names(command, file, top_level=not nested)
        if re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", n) and n not in words
    }  # fmt: skip
    assert not unwritten, f"{command} {file}: in outputs.md, not written: {unwritten}"


def _quadrupole_map(path: Path) -> Path:
    """A 7 x 7 x 11 grid about the z axis holding a quadrupole field, 0.05 T/mm."""
    ax, az = np.linspace(-3.0, 3.0, 7), np.linspace(-10.0, 10.0, 11)
    pts = np.stack(np.meshgrid(ax, ax, az, indexing="ij"), -1).reshape(-1, 3)
    B = np.c_[0.05 * pts[:, 1], 0.05 * pts[:, 0], np.zeros(len(pts))]
    rows = "\n".join(",".join(f"{v:.17g}" for v in r) for r in np.c_[pts, B])
    path.write_text("x [mm],y [mm],z [mm],Bx [T],By [T],Bz [T]\n" + rows + "\n")
    return path


def _check_json_keys(command: str, out: Path, file: str) -> None:
    """The top-level keys of ``file`` against the section's key table of that file."""
    keys = set(json.loads((out / file).read_text()))
    documented = _documented(command, "key", file)
    assert keys == documented, f"{command} {file}: written {keys - documented}, " + (
        f"documented {documented - keys}"
    )


def test_other_commands_outputs_match_the_page(tmp_path):
    path = _csv_map(tmp_path / "map.csv", n=5)
    from cfm_fem.io.harmonics import qfdp4_path

    rec, hall = tmp_path / "rec.csv", tmp_path / "hall.csv"
    assert main(["synth", "tracker", "--reps", "2", "--grid", "2,2,2", "--out", str(rec)]) == 0
    assert main(["synth", "hall", "--reps", "2", "--out", str(hall)]) == 0
    runs = {
        "tolerance": ["tolerance", "--target", "18,13,14", "--check", "100"],
        "coupled": ["coupled", "--trials", "60"],
        "fig4": ["fig4", str(path), "--up", "0,20", "--trials", "60"],
        "compare": ["compare", "--tracker", str(rec), "--trials", "60"],
        "compare_hall": ["compare", "--hall-map", str(hall), "--reference", str(qfdp4_path()),
                         "--trials", "60"],
        "diagnose": ["diagnose", "--tracker", str(rec)],
        "quality": ["quality", str(_quadrupole_map(tmp_path / "quad.csv")), "--r-ref", "2",
                    "--up", "20", "--trials", "100"],
    }  # fmt: skip
    outs = {}
    for name, argv in runs.items():
        outs[name] = tmp_path / name
        assert main([*argv, "--out", str(outs[name])]) == 0, name
        for f in outs[name].glob("*.vtu"):
            _read_both(f)
    sweep_keys = _documented("sweep", "key", "summary.json")
    checks = [
        *((_check_files, (name, [outs[name]])) for name in ("tolerance", "coupled", "fig4")),
        (_check_files, ("diagnose", [outs["diagnose"]])),
        (_check_files, ("compare", [outs["compare"], outs["compare_hall"]])),
        (_check_inline_json, ("tolerance", [outs["tolerance"]], "tolerance.json")),
        (_check_inline_json, ("coupled", [outs["coupled"]], "summary.json")),
        (_check_inline_json, ("fig4", [outs["fig4"]], "fig4.json", sweep_keys)),
        (_check_inline_json, ("compare", [outs["compare"], outs["compare_hall"]], "compare.json")),
        (_check_inline_json, ("diagnose", [outs["diagnose"]], "diagnosis.json", (), False)),
        (_check_files, ("quality", [outs["quality"]])),
        (_check_json_keys, ("quality", outs["quality"], "quality.json")),
    ]
    problems = []
    for check, args in checks:  # every mismatch at once, not the first
        try:
            check(*args)
        except AssertionError as exc:
            problems.append(str(exc).splitlines()[0])
    assert not problems, "\n".join(problems)


def test_the_page_has_a_section_for_every_command():
    import argparse

    from cfm_fem.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(_sections()) == set(sub.choices)
