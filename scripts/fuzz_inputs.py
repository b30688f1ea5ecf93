"""Fuzz the command line with mutated inputs and options, and count what happens.

Three kinds of case, each run as one command with a timeout:

- files: the bundled maps (``meshes/``), the real files of ``../shared/data/`` (when present;
  large ones cut to their first lines, Opera counts set to match, so each case runs in about a
  second), the packaged bench, a tracker recording, a Hall map and a harmonics file, each
  mutated (bytes replaced, inserted or deleted, numbers replaced by tokens fuzzing met, the end
  cut off, lines repeated) and given to every command that reads that kind of file (a map to
  ``sweep``, ``design``, ``fig4``, ``coupled --field``; a bench to ``kinematics``,
  ``tolerance``, ``coupled``, ``sweep --mode htm``, ``compare``, ``diagnose``, ``synth``; ...);
- bench tables: the packaged bench without one of its optional tables or keys (``[grid]`` or
  one axis of it, ``[vibration]``, ``[reading_delay]``, ``[magnet]``, ``[assumptions]``, an
  error's ``unit``, ``[frame] stack``) or with an impossible reading delay, then mutated;
- options: one option of one of the commands (every option their parsers declare) set to
  a token (``nan``, ``inf``, ``-1``, ``1e14``, ``""``, a folder, a file of the wrong kind,
  ...), the other options left at a valid, fast setting.

Outcomes:

- ``exit 0``: and no output holds NaN or infinity (JSON, CSV, text);
- ``exit 2``: one ``cfm-fem: error:`` line naming the input (the mutated file's name, or the
  option), no traceback, no raw control character on stderr and no output left;
- failures: ``traceback`` (any other exit, a traceback, a worker that died), ``hang`` (past the
  timeout), ``non-finite output``, ``message not naming its input``, ``not one error line``,
  ``raw control character``, ``output left``; each printed with a reproducer (the inputs are
  kept in ``--keep``).

Cases run in worker processes that call ``cfm_fem.cli.main`` (no interpreter start per case); a
worker that hangs past the timeout or dies (a crash) is replaced. ``--subprocess`` runs each
case as its own ``python -m cfm_fem`` instead. ``--commands`` limits the cases to some commands
(to run a campaign in chunks); ``--kinds`` to some kinds of case.

    python scripts/fuzz_inputs.py --cases 500 --workers 2 --seed 1
    python scripts/fuzz_inputs.py --cases 120 --commands kinematics,tolerance --seed 2
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import multiprocessing as mp
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from importlib import resources
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / ".." / "shared" / "data"
TOKENS = ["1_000", "\u0661\u0662", "2\u00b9", "1e308", "-1e309", "1e300", "9" * 400, "\x1b[2J",
          "\x07", "\x85", "\xff", "E-0", "E", ".", "-", "nan", "inf", "#REF!", '"1,066.67"',
          "\x00", "\r", "\n", ",", ";", "\t", " ", "%", "#", "[", "]", "=", '"', "0", "1e9",
          "[[[[[[[[", "0.0", "-0"]  # fmt: skip
_RAW_CONTROL = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def _head(path: Path, lines: int) -> bytes:
    """The first ``lines`` lines of a file (all of a shorter one)."""
    out = []
    with open(path, "rb") as f:
        for line in f:
            out.append(line)
            if len(out) == lines:
                break
    return b"".join(out)


def _opera_head(path: Path, lines: int) -> bytes:
    """The first ``lines`` lines of an Opera table with line 1's point counts set to the rows
    kept (as one column of points): a cut seed that is not refused as cut short."""
    data = _head(path, lines).split(b"\n")
    end = next(i for i, line in enumerate(data) if line.strip() == b"0")
    rows = sum(1 for line in data[end + 1 :] if line.strip())
    data[0] = f" {rows} 1 1 2".encode()
    return b"\n".join(data)


def _tracker_rows() -> str:
    """12 points, 2 repetitions each, measured a few um off their nominal positions."""
    rows = "".join(
        f"{i // 2},{i % 2},{(i // 2) * 10}.0,20.0,{(i // 2) * 50}.0,"
        f"{(i // 2) * 10 + 0.0021 + 0.0007 * (i % 2) - 0.0002 * (i % 3):.4f},"
        f"{-39.9978 - 0.0004 * (i % 2) + 0.0001 * (i % 5):.4f},"
        f"{(i // 2) * 50 + 500 + 0.0013 + 0.0005 * (i % 2) - 0.0003 * (i % 3):.4f}\n"
        for i in range(24)
    )
    return "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n" + rows


def _hall_rows() -> str:
    """A Hall map of a quadrupole of 6.96 T/m (the packaged QFDp4's gradient) at 27 points, 2
    repetitions with 0.01 % noise."""
    rows = []
    points = [(x, y, z) for x in (-4, 0, 4) for y in (-4, 0, 4) for z in (-50, 0, 50)]
    for i, (x, y, z) in enumerate(points):
        for rep in (1, 2):
            noise = 1 + 1e-4 * ((i + 3 * rep) % 5 - 2)
            bx, by = 6.96e-3 * y * noise, 6.96e-3 * x * noise
            rows.append(f"{i},{rep},{x}.0,{y}.0,{z}.0,{bx:.7g},{by:.7g},{1e-6 * (rep - 1.5):.3g}\n")
    return "point_id,rep,x_cmd,y_cmd,z_cmd,Bx,By,Bz\n" + "".join(rows)


def _package(name: str) -> bytes:
    return resources.files("cfm_fem.data").joinpath(name).read_bytes()


def _small_bench() -> bytes:
    """The packaged bench with a 3 x 3 x 3 grid: kinematics and tolerance in about a second."""
    text = _package("cfm_reference_bench.toml").decode()
    for axis in "xyz":
        text = re.sub(rf"({axis}_mm = {{.*num = )\d+", r"\g<1>3", text)
    return text.encode()


def seeds() -> list[tuple[str, str, bytes, list[str]]]:
    """(name, kind, bytes, extra options) of each seed; kind: map, bench, tracker, hall,
    harmonics."""
    out = [
        ("quadrupole.txt", "map", _head(ROOT / "meshes" / "quadrupole_comsol.txt", 400), []),
        ("quadrupole.table", "map", _opera_head(ROOT / "meshes" / "quadrupole_opera.table", 700),
         []),
    ]  # fmt: skip
    real = [("emphatic/mfMapMeasured_5mm.txt", 600, []),
            ("emphatic/CylinderGrid_Section1_231025-112209.txt", 300, ["--length-unit", "mm"]),
            ("emphatic/EMPHATIC_body_scan_5280148.csv", 300, ["--length-unit", "in"]),
            ("cctpy/test_opera_field_table.table", 20_000, [])]  # fmt: skip
    for rel, lines, extra in real:
        if (DATA / rel).is_file():
            cut = _opera_head if rel.endswith(".table") else _head
            out.append((Path(rel).name, "map", cut(DATA / rel, lines), extra))
    out.append(("bench.toml", "bench", _small_bench(), []))
    out.append(("tracker.csv", "tracker", _tracker_rows().encode(), []))
    out.append(("hall.csv", "hall", _hall_rows().encode(), []))
    out.append(("harmonics.csv", "harmonics", _package("qfdp4_harmonics.csv"), []))
    return out


def mutate(data: bytes, rng: random.Random) -> bytes:
    """One to three random mutations of ``data``."""
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(data) + 1)
        op = rng.choice(["insert", "replace", "replace", "delete", "cut_end", "byte", "dup_line"])
        if op == "insert":
            data = data[:i] + rng.choice(TOKENS).encode() + data[i:]
        elif op == "replace":
            m = re.compile(rb"[^\s,;]+").search(data, i)
            if m:
                data = data[: m.start()] + rng.choice(TOKENS).encode() + data[m.end() :]
        elif op == "delete":
            data = data[:i] + data[i + rng.randint(1, 30) :]
        elif op == "cut_end":
            data = data[: max(len(data) - rng.randint(1, 12), 0)]
        elif op == "byte":
            data = data[:i] + bytes([rng.randrange(256)]) + data[i + 1 :]
        else:
            lines = data.split(b"\n")
            k = rng.randrange(len(lines))
            lines.insert(k, lines[k])
            data = b"\n".join(lines)
    return data


# ------------------------------------------------------------------ the commands and their files

#: A valid, fast run of each command: ``{map}``, ``{bench}``, ``{tracker}``, ``{hall}``,
#: ``{harmonics}`` are the case's files, ``{out}`` its output folder (``{out}.csv`` for synth).
BASES = {
    "sweep": ["sweep", "{map}", "--up", "10", "--trials", "20", "--out", "{out}"],
    "design": ["design", "{map}", "--uf-max", "10", "--up", "10,20", "--trials", "20",
               "--out", "{out}"],
    "kinematics": ["kinematics", "--bench", "{bench}", "--trials", "40", "--out", "{out}"],
    "tolerance": ["tolerance", "--target", "5", "--bench", "{bench}", "--check", "40",
                  "--out", "{out}"],
    "coupled": ["coupled", "--bench", "{bench}", "--step", "4", "--z", "0", "--trials", "40",
                "--no-budget", "--out", "{out}"],
    "fig4": ["fig4", "{map}", "--up", "10", "--trials", "20", "--out", "{out}"],
    "compare": ["compare", "--tracker", "{tracker}", "--bench", "{bench}", "--no-budget",
                "--trials", "40", "--out", "{out}"],
    "diagnose": ["diagnose", "--tracker", "{tracker}", "--bench", "{bench}", "--no-report",
                 "--out", "{out}"],
    "synth": ["synth", "tracker", "--bench", "{bench}", "--grid", "2,2,2", "--reps", "2",
              "--out", "{out}.csv"],
    "quality": ["quality", "{map}", "--r-ref", "2", "--up", "10", "--trials", "40",
                "--budget-trials", "40", "--out", "{out}"],
}  # fmt: skip

#: Commands each kind of file is given to: (command, options that replace or extend its base).
FILE_USES = {
    "map": [("sweep", []), ("design", []), ("fig4", []), ("quality", []),
            ("coupled", ["--field", "{map}", "--bench", "{bench}"])],
    "bench": [("kinematics", []), ("tolerance", []), ("coupled", []), ("compare", []),
              ("diagnose", []), ("synth", []),
              ("sweep", ["--mode", "htm", "--bench", "{bench}", "--up", None])],
    "tracker": [("compare", []), ("diagnose", [])],
    "hall": [("compare", ["--hall-map", "{hall}", "--tracker", None, "--reference",
                          "{harmonics}"]),
             ("diagnose", ["--hall-map", "{hall}", "--tracker", None, "--reference",
                           "{harmonics}"])],
    "harmonics": [("coupled", ["--field", "{harmonics}"]),
                  ("synth", ["hall", "--harmonics", "{harmonics}", "--grid", None])],
}  # fmt: skip

#: Values tried for an option: numbers fuzzing met, non-finite and absurd sizes, empty text,
#: lists, ranges, escapes, and paths (``{dir}`` is the case's folder).
OPTION_TOKENS = ["nan", "inf", "-inf", "-1", "0", "1", "-0", "1e14", "1e999", "1e-300", "1e9",
                 "2.5", "", " ", "abc", "1,2", "1,nan,2", "1,2,3", "0,0,0", "2:1:1", "0:50:0",
                 "0:1e9:1e-9", "-5:5:1", "\n", "\x1b[2J", "1_000", "\u0661", "x" * 300,
                 "{dir}", "{dir}/missing.csv", "{dir}/quadrupole.txt", "{dir}/tracker.csv",
                 "{dir}/bench.toml", "/dev/null", "tcp://127.0.0.1:1"]  # fmt: skip


#: Options whose value is a file or folder: a refusal may name the file instead of the option.
FILE_OPTIONS = {"--bench", "--field", "--tracker", "--hall-map", "--reference", "--harmonics",
                "--tolerances",
                "--out"}  # fmt: skip


def _set(argv: list, option: str, value) -> list:
    """``argv`` with ``option`` set to ``value`` (None: removed; a flag: value True)."""
    argv = list(argv)
    if option in argv:
        i = argv.index(option)
        flag = i + 1 >= len(argv) or argv[i + 1].startswith("--")
        del argv[i : i + (1 if flag else 2)]
        if value is None:
            return argv
        argv[i:i] = [option] if value is True else [option, value]
        return argv
    if value is None:
        return argv
    return argv + ([option] if value is True else [option, value])


def _apply(argv: list, changes: list) -> list:
    """``argv`` with ``changes`` (option, value, ... ; a bare word replaces the positional)."""
    i = 0
    while i < len(changes):
        if not str(changes[i]).startswith("--"):
            argv = [argv[0], changes[i], *argv[2:]]  # synth's kind
            i += 1
            continue
        argv = _set(argv, changes[i], changes[i + 1])
        i += 2
    return argv


def command_options() -> dict:
    """Every option of every command, from the parsers: {command: [(option, kind, choices)]},
    kind "flag" or "value"."""
    sys.path.insert(0, str(ROOT))
    from cfm_fem.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    out = {}
    for name, sp in sub.choices.items():
        opts = []
        for a in sp._actions:
            if not a.option_strings or a.option_strings[0] in ("-h", "--help"):
                continue
            kind = "flag" if a.nargs == 0 else "value"
            opts.append((a.option_strings[-1], kind, list(a.choices or [])))
        out[name] = opts
    return out


def bench_table_variants(bench: bytes) -> list[tuple[str, bytes]]:
    """(what, bytes): the bench without one optional table or key, or with an impossible
    reading delay."""
    text = bench.decode()

    def drop_table(t, table):
        out, skip = [], False
        for line in t.splitlines():
            if line.startswith("["):
                skip = line.strip() == f"[{table}]"
            if not skip:
                out.append(line)
        return "\n".join(out) + "\n"

    variants = [(f"no [{t}]", drop_table(text, t)) for t in
                ("grid", "vibration", "reading_delay", "magnet", "assumptions")]  # fmt: skip
    for axis in "xyz":
        variants.append((f"no grid {axis}_mm", re.sub(rf"\n{axis}_mm = .*", "", text, count=1)))
    variants.append(("an error without unit", text.replace('unit = "um"\n', "", 1)))
    variants.append(("no frame stack", re.sub(r"\nstack = .*", "", text, count=1)))
    variants.append(("no magnet translation", re.sub(r"\ntranslation_mm = .*", "", text)))
    variants.append(("vibration without std_um", text.replace("std_um = 2.5", "")))
    delay = 'model = "speed_tau"\nspeed_mm_s = [0.0, 0.0, 10.0]\ntau = {{ {} }}'
    for tau in ('pdf = "uniform", low = -1.0, high = -0.5', 'pdf = "uniform", low = 0.0, '
                'high = 2e-4', 'pdf = "normal", mean = 0.0, std = 1e-4', 'pdf = "uniform", '
                'low = 0.0, high = 0.2, unit = "ms"'):  # fmt: skip
        changed = text.replace('model = "normal"\nstd_um = 1.0', delay.format(tau))
        variants.append((f"reading delay {tau}", changed))
    return [(what, t.encode()) for what, t in variants]


# ------------------------------------------------------------------ cases


def make_cases(n: int, rng: random.Random, seeds_only: bool = False, commands=None,
               kinds=("files", "tables", "options")) -> list[dict]:  # fmt: skip
    """``n`` cases, the kinds in turn: {name, command, files {name: bytes}, argv (with
    ``{dir}``, ``{out}`` and file placeholders), names (what a refusal must name)}."""
    pool = seeds()
    files = {name: data for name, kind, data, _ in pool
             if name in ("quadrupole.txt", "bench.toml", "tracker.csv", "hall.csv",
                         "harmonics.csv")}  # fmt: skip
    placeholders = {"map": "quadrupole.txt", "bench": "bench.toml", "tracker": "tracker.csv",
                    "hall": "hall.csv", "harmonics": "harmonics.csv"}  # fmt: skip
    file_cases = [(seed, cmd, change) for seed in pool for cmd, change in FILE_USES[seed[1]]
                  if commands is None or cmd in commands]  # fmt: skip
    table_cases = [(v, cmd, change) for v in bench_table_variants(files["bench.toml"])
                   for cmd, change in FILE_USES["bench"]
                   if commands is None or cmd in commands]  # fmt: skip
    options = {c: o for c, o in command_options().items() if commands is None or c in commands}
    option_cases = [(c, o) for c, opts in options.items() for o in opts]
    kinds = [k for k in kinds if {"files": file_cases, "tables": table_cases,
                                  "options": option_cases}[k]]  # fmt: skip
    cases = []
    for k in range(n):
        kind = kinds[k % len(kinds)]
        case_files = dict(files)
        names = []
        if kind == "files":
            (name, seed_kind, data, extra), cmd, change = file_cases[(k // len(kinds))
                                                                    % len(file_cases)]  # fmt: skip
            case_files[name] = data if seeds_only else mutate(data, rng)
            argv = _apply(BASES[cmd], change)
            argv = [a.replace("{" + seed_kind + "}", "{dir}/" + name) for a in argv]
            argv += extra if seed_kind == "map" else []
            names = [name]
            label = f"{name} -> {cmd}"
        elif kind == "tables":
            (what, data), cmd, change = table_cases[(k // len(kinds)) % len(table_cases)]
            mutated = k // len(kinds) >= len(table_cases) and not seeds_only
            case_files["bench.toml"] = mutate(data, rng) if mutated else data
            argv = _apply(BASES[cmd], change)
            names = ["bench.toml"]
            label = f"bench {what}{' (mutated)' if mutated else ''} -> {cmd}"
        else:
            cmd, (option, okind, choices) = option_cases[rng.randrange(len(option_cases))]
            if okind == "flag":
                value = True
            elif choices and rng.random() < 0.6:
                value = str(rng.choice(choices))
            else:
                value = rng.choice(OPTION_TOKENS)
            argv = _apply(BASES[cmd], [option, value])
            names = [option]
            if option in FILE_OPTIONS and isinstance(value, str):
                names += [value, repr(value)]  # a blank name is quoted
            label = f"{cmd} {option} {value!r}"
        for key, name in placeholders.items():
            argv = [a.replace("{" + key + "}", "{dir}/" + name) for a in argv]
        cases.append(dict(k=k, label=label, command=cmd, files=case_files, argv=argv,
                          names=names))  # fmt: skip
    return cases


# ------------------------------------------------------------------ running and judging


def _worker(conn) -> None:
    """Run cases sent over ``conn`` with ``cfm_fem.cli.main``; send back (code, stderr)."""
    import os as _os

    from cfm_fem.cli import main

    while True:
        try:
            argv, cwd = conn.recv()
        except EOFError:  # the parent is done
            return
        err = io.StringIO()
        _os.chdir(cwd)  # an output folder given as "" or "." lands in the case's folder
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                code = main(argv)
            except BaseException as exc:  # noqa: BLE001 - a traceback is what we look for
                import traceback

                traceback.print_exception(exc, file=err)
                code = "traceback"
        conn.send((code, err.getvalue()))


class Worker:
    """A process that runs cases; replaced after a hang or a crash."""

    def __init__(self):
        self.conn, child = mp.Pipe()
        self.proc = mp.get_context("spawn").Process(target=_worker, args=(child,), daemon=True)
        self.proc.start()

    def run(self, argv, cwd, timeout):
        self.conn.send((argv, str(cwd)))
        if self.conn.poll(timeout):
            try:
                return self.conn.recv()
            except EOFError:
                pass
        else:
            self.proc.kill()
            self.proc.join()
            return "timeout", ""
        self.proc.join()
        return f"died (exit {self.proc.exitcode})", ""

    def close(self):
        self.proc.kill()
        self.proc.join()


def run_subprocess(argv, cwd, timeout):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    try:
        done = subprocess.run([sys.executable, "-m", "cfm_fem", *argv], capture_output=True,
                              text=True, timeout=timeout, env=env, cwd=cwd)  # fmt: skip
    except subprocess.TimeoutExpired:
        return "timeout", ""
    return done.returncode, done.stderr


_NON_FINITE = {"nan", "inf", "+inf", "-inf", "infinity", "-infinity", "+infinity", "-nan"}


def non_finite_output(paths) -> str | None:
    """The first output file (JSON or CSV) holding NaN or infinity as a number, with the
    token; VTK files are left out (NaN marks a node without statistics there, as documented),
    and so is text that merely mentions NaN."""
    import json

    for path in paths:
        if path.suffix not in (".json", ".csv") or not path.is_file():
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        if path.suffix == ".json":
            found = []
            try:
                json.loads(text, parse_constant=lambda c, seen=found: seen.append(c) or 0.0)
            except ValueError:
                return f"{path.name}: not JSON"
            if found:
                return f"{path.name}: {found[0]}"
            continue
        for line in text.splitlines():
            if line.startswith("#"):
                continue
            bad = [f for f in line.split(",") if f.strip().strip('"').lower() in _NON_FINITE]
            if bad:
                return f"{path.name}: {bad[0].strip()}"
    return None


def _outputs(folder: Path, inputs) -> list:
    return [p for p in folder.rglob("*") if p.is_file() and p.name not in inputs
            and p.name != ".cfm_fem.lock"]  # fmt: skip


def classify(code, err: str, folder: Path, inputs, names) -> str:
    """The outcome of one case (see the module docstring)."""
    from cfm_fem.errors import one_line

    if code == "timeout":
        return "failure: hang"
    if code not in (0, 2) or "Traceback" in err:
        return "failure: traceback"
    if code == 0:
        bad = non_finite_output(_outputs(folder, inputs))
        return f"failure: non-finite output ({bad.split(':')[0]})" if bad else "exit 0"
    lines = [line for line in err.splitlines() if line.startswith("cfm-fem: error:")]
    if len(lines) != 1:
        return "failure: not one error line"
    if _RAW_CONTROL.search(err.replace("\r", "")):
        return "failure: raw control character on stderr"
    if _outputs(folder, inputs):
        return "failure: output left"
    names = [str(n).replace("{dir}", str(folder)) for n in names]
    names = [one_line(n) for n in names if one_line(n).strip()]
    if not any(n in lines[0] for n in names):
        return "failure: message not naming its input"
    return "exit 2"


def run_cases(cases, workers: int = 2, timeout: float = 120.0, keep=None,
              use_subprocess: bool = False, verbose: bool = False, log=sys.stderr):  # fmt: skip
    """Run ``cases``; returns (Counter of (command, outcome), failures)."""
    work = Path(tempfile.mkdtemp(prefix="cfm_fuzz_"))
    counts = collections.Counter()
    failures = []
    lock = threading.Lock()
    queue = list(reversed(cases))
    started = time.monotonic()

    def serve():
        worker = None if use_subprocess else Worker()
        while True:
            with lock:
                if not queue:
                    break
                case = queue.pop()
            folder = work / f"case_{case['k']}"
            folder.mkdir()
            for name, data in case["files"].items():
                (folder / name).write_bytes(data)
            argv = [a.replace("{dir}", str(folder)).replace("{out}", str(folder / "out"))
                    for a in case["argv"]]  # fmt: skip
            if use_subprocess:
                code, err = run_subprocess(argv, folder, timeout)
            else:
                code, err = worker.run(argv, folder, timeout)
                if code == "timeout" or str(code).startswith("died"):
                    worker = Worker()
            outcome = classify(code, err, folder, case["files"], case["names"])
            with lock:
                counts[case["command"], outcome] += 1
                if verbose:
                    tail = err.strip().splitlines()[-1][:160] if err.strip() else ""
                    print(f"{case['label']!r}: {outcome}: {tail}", file=log)
                if outcome.startswith("failure"):
                    if keep is not None:
                        kept = Path(keep) / f"case_{case['k']}"
                        shutil.rmtree(kept, ignore_errors=True)
                        kept.mkdir(parents=True)
                        for name, data in case["files"].items():
                            (kept / name).write_bytes(data)
                        argv = [a.replace(str(folder), str(kept)) for a in argv]
                    failures.append((case["k"], case["label"], outcome, argv,
                                     err.strip().splitlines()[-3:]))  # fmt: skip
                done = sum(counts.values())
                if done % 25 == 0:
                    print(f"{done} cases, {time.monotonic() - started:.0f} s", file=log,
                          flush=True)  # fmt: skip
            shutil.rmtree(folder, ignore_errors=True)
        if worker is not None:
            worker.close()

    threads = [threading.Thread(target=serve) for _ in range(max(workers, 1))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    shutil.rmtree(work, ignore_errors=True)
    return counts, failures


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=500)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--timeout", type=float, default=120.0, help="seconds per case")
    p.add_argument("--keep", default="fuzz_failures", help="folder for failing inputs")
    p.add_argument("--subprocess", action="store_true", help="one interpreter per case")
    p.add_argument("--seeds-only", action="store_true", help="run the seeds unmutated (all ok)")
    p.add_argument("--commands", help="comma-separated commands to fuzz (default: all)")
    p.add_argument("--kinds", default="files,tables,options",
                   help="kinds of case: files, tables, options (default: all)")  # fmt: skip
    p.add_argument("-v", "--verbose", action="store_true", help="print each case's outcome")
    args = p.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    commands = None if args.commands is None else set(args.commands.split(","))
    cases = make_cases(args.cases, random.Random(args.seed), args.seeds_only, commands,
                       tuple(args.kinds.split(",")))  # fmt: skip
    started = time.monotonic()
    counts, failures = run_cases(cases, args.workers, args.timeout, args.keep, args.subprocess,
                                 args.verbose)  # fmt: skip
    print(f"{len(cases)} cases in {time.monotonic() - started:.0f} s (seed {args.seed})")
    outcomes = sorted({o for _, o in counts})
    for command in sorted({c for c, _ in counts}):
        row = ", ".join(f"{o}: {counts[command, o]}" for o in outcomes if counts[command, o])
        print(f"  {command}: {row}")
    total = collections.Counter()
    for (_, o), n in counts.items():
        total[o] += n
    print("  all: " + ", ".join(f"{o}: {n}" for o, n in sorted(total.items())))
    for k, label, outcome, argv, tail in failures:
        print(f"case {k} ({label}): {outcome}\n  reproduce: cfm-fem "
              f"{' '.join(map(repr, argv))}\n  " + "\n  ".join(tail))  # fmt: skip
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
