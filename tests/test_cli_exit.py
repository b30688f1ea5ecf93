"""The ``cfm-fem`` program ends by its exit handlers and flushed streams, with main's code."""

import subprocess
import sys

import pytest

PROGRAM = """
import atexit, sys
from pathlib import Path
flag = Path(sys.argv.pop(1))
atexit.register(lambda: flag.write_text("exit handlers ran"))
from cfm_fem.cli import run
run()
"""


@pytest.mark.parametrize(
    ("argv", "code", "stream", "text"),
    [
        (["--version"], 0, "stdout", "cfm-fem "),
        (["sweep", "no_such_map.vtu", "--up", "10", "--out", "o"], 2, "stderr", "no_such_map"),
    ],
)
def test_program_runs_exit_handlers_flushes_and_keeps_the_code(tmp_path, argv, code, stream, text):
    """Through pipes (block-buffered streams) the whole message arrives, the exit handlers
    registered before the command run, and the exit code is the command's."""
    flag = tmp_path / "flag.txt"
    done = subprocess.run(
        [sys.executable, "-c", PROGRAM, str(flag), *argv], capture_output=True, text=True,
        cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert done.returncode == code, done.stderr
    assert text in getattr(done, stream)
    assert getattr(done, stream).endswith("\n")
    assert flag.read_text() == "exit handlers ran"


def test_module_entry_is_the_program(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "cfm_fem", "sweep", "missing.vtu", "--up", "10", "--out", "o"],
        capture_output=True, text=True, cwd=tmp_path, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    assert "missing.vtu" in done.stderr
