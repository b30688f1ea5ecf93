"""Fuzz the command line with mutated inputs and count what happens.

Seeds: the bundled maps (``meshes/``), the real files of ``../shared/data/`` (when present; large
ones cut to their first lines so that each case runs in about a second), the packaged bench and a
tracker recording. Each case mutates one seed (bytes replaced, inserted or deleted, numbers
replaced by tokens fuzzing met, the end cut off, lines repeated) and runs the matching command
(``sweep`` for a map, ``kinematics --bench`` for a bench, ``compare --tracker`` for a
recording) with a timeout. Outcomes:

- ``ok``: exit 0;
- ``refused``: exit 2 with one ``cfm-fem: error:`` line, no traceback, no raw control character
  on stderr and no output folder left;
- anything else is a failure, printed with a reproducer (the input is kept in ``--keep``).

Cases run in worker processes that call ``cfm_fem.cli.main`` (no interpreter start per case); a
worker that hangs past the timeout or dies (a crash) is replaced and the case counted as a
failure. ``--subprocess`` runs each case as its own ``python -m cfm_fem`` instead.

    python scripts/fuzz_inputs.py --cases 500 --workers 2 --seed 1
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


def seeds() -> list[tuple[str, str, bytes, list[str]]]:
    """(name, command, bytes, extra options) of each seed."""
    out = [
        ("quadrupole.txt", "sweep", _head(ROOT / "meshes" / "quadrupole_comsol.txt", 400), []),
        ("quadrupole.table", "sweep", _head(ROOT / "meshes" / "quadrupole_opera.table", 700), []),
    ]
    real = [("emphatic/mfMapMeasured_5mm.txt", 600, []),
            ("emphatic/CylinderGrid_Section1_231025-112209.txt", 300, ["--length-unit", "mm"]),
            ("emphatic/EMPHATIC_body_scan_5280148.csv", 300, ["--length-unit", "in"]),
            ("cctpy/test_opera_field_table.table", 20_000, [])]  # fmt: skip
    for rel, lines, extra in real:
        if (DATA / rel).is_file():
            out.append((Path(rel).name, "sweep", _head(DATA / rel, lines), extra))
    bench = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml").read_bytes()
    out.append(("bench.toml", "kinematics", bench, []))
    rows = "".join(
        f"{i // 2},{i % 2},{(i // 2) * 10}.0,20.0,{(i // 2) * 50}.0,{(i // 2) * 10}.0021,"
        f"-39.9978,{(i // 2) * 50 + 500}.0013\n"
        for i in range(24)
    )
    head = "point_id,rep,x_cmd,y_cmd,z_cmd,x_meas,y_meas,z_meas\n"
    out.append(("tracker.csv", "compare", (head + rows).encode(), []))
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


def argv_for(command: str, path: Path, out: Path, extra) -> list[str]:
    base = ["--trials", "20", "--out", str(out)]
    if command == "sweep":
        return ["sweep", str(path), "--up", "10", *extra, *base]
    if command == "kinematics":
        return ["kinematics", "--bench", str(path), *base]
    return ["compare", "--tracker", str(path), "--no-budget", *base]


def _worker(conn) -> None:
    """Run cases sent over ``conn`` with ``cfm_fem.cli.main``; send back (code, stderr)."""
    from cfm_fem.cli import main

    while True:
        try:
            argv = conn.recv()
        except EOFError:  # the parent is done
            return
        err = io.StringIO()
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

    def run(self, argv, timeout):
        self.conn.send(argv)
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


def run_subprocess(argv, timeout):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    try:
        done = subprocess.run([sys.executable, "-m", "cfm_fem", *argv], capture_output=True,
                              text=True, timeout=timeout, env=env)  # fmt: skip
    except subprocess.TimeoutExpired:
        return "timeout", ""
    return done.returncode, done.stderr


def classify(code, err: str, out: Path) -> str:
    if code == 0:
        return "ok"
    if code != 2:
        return f"failure: exit {code}"
    if "Traceback" in err:
        return "failure: traceback"
    if err.count("cfm-fem: error:") != 1:
        return "failure: not one error line"
    if _RAW_CONTROL.search(err.replace("\r", "")):
        return "failure: raw control character on stderr"
    if out.exists() and any(p.name != ".cfm_fem.lock" for p in out.iterdir()):
        return "failure: output left"
    return "refused"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=500)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--timeout", type=float, default=120.0, help="seconds per case")
    p.add_argument("--keep", default="fuzz_failures", help="folder for failing inputs")
    p.add_argument("--subprocess", action="store_true", help="one interpreter per case")
    p.add_argument("--seeds-only", action="store_true", help="run the seeds unmutated (all ok)")
    p.add_argument("-v", "--verbose", action="store_true", help="print each refusal's message")
    args = p.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    rng = random.Random(args.seed)
    pool = seeds()
    cases = []
    for k in range(args.cases):
        name, command, data, extra = pool[k % len(pool)]
        cases.append((k, name, command, data if args.seeds_only else mutate(data, rng), extra))
    work = Path(tempfile.mkdtemp(prefix="cfm_fuzz_"))
    counts = collections.Counter()
    failures = []
    lock = threading.Lock()
    queue = list(reversed(cases))
    started = time.monotonic()

    def serve():
        worker = None if args.subprocess else Worker()
        while True:
            with lock:
                if not queue:
                    break
                k, name, command, data, extra = queue.pop()
            folder = work / f"case_{k}"
            folder.mkdir()
            path = folder / name
            path.write_bytes(data)
            out = folder / "out"
            argv = argv_for(command, path, out, extra)
            if args.subprocess:
                code, err = run_subprocess(argv, args.timeout)
            else:
                code, err = worker.run(argv, args.timeout)
                if code == "timeout" or str(code).startswith("died"):
                    worker = Worker()
            outcome = classify(code, err, out)
            with lock:
                counts[outcome] += 1
                if args.verbose and outcome == "refused":
                    print(f"{name}: {err.strip().splitlines()[-1][:160]}", file=sys.stderr)
                if outcome.startswith("failure"):
                    keep = Path(args.keep) / f"case_{k}"
                    keep.mkdir(parents=True, exist_ok=True)
                    shutil.copy(path, keep / name)
                    argv = [str(keep / name) if a == str(path) else a for a in argv]
                    failures.append((k, outcome, argv, err.strip().splitlines()[-3:]))
                done = sum(counts.values())
                if done % 50 == 0:
                    print(f"{done} cases, {time.monotonic() - started:.0f} s: {dict(counts)}",
                          file=sys.stderr, flush=True)  # fmt: skip
            shutil.rmtree(folder, ignore_errors=True)

    threads = [threading.Thread(target=serve) for _ in range(max(args.workers, 1))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    shutil.rmtree(work, ignore_errors=True)
    print(f"{len(cases)} cases in {time.monotonic() - started:.0f} s (seed {args.seed})")
    for outcome, n in sorted(counts.items()):
        print(f"  {outcome}: {n}")
    for k, outcome, argv, tail in failures:
        print(f"case {k}: {outcome}\n  reproduce: cfm-fem {' '.join(argv)}\n  " + "\n  ".join(tail))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
