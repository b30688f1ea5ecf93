"""One run at a time per ``--out`` folder (`cfm_fem.io.lock`).

Two runs sharing an output folder corrupted each other: a sweep without ``--resume`` deleted
the whole chunk store on start (the other run's chunks included), its end deleted the store and
the maps its sweep.pvd does not name. A run into a folder another live run holds now stops at
once (exit 2), naming the holder, and leaves every file of the folder as it was.

The lock is flock(2), which belongs to an open file description: a second ``open`` of the lock
file, even in this process, is a second holder. The tests hold it that way (`_hold`).
"""

import fcntl
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cfm_fem.cli import main
from cfm_fem.errors import CfmInputError
from cfm_fem.io.chunk_store import STORE_NAME
from cfm_fem.io.lock import LOCK_NAME, output_lock

ROOT = Path(__file__).resolve().parents[1]
HOLDER = {"pid": 4242, "host": "benchhost", "started": "2025-01-02T03:04:05+00:00",
          "command": "cfm-fem sweep live.csv --out res"}  # fmt: skip
IN_USE = (
    "is in use by another cfm-fem run (pid 4242 on benchhost, started 2025-01-02T03:04:05+00:00: "
    "cfm-fem sweep live.csv --out res); wait for it to finish or choose another --out"
)


@pytest.fixture
def small_map(grid_csv):
    """A 4 x 4 x 4 grid with a linear field (64 nodes: a sweep of it takes well under 1 s)."""
    return grid_csv(4, lambda pts: pts @ np.diag([0.2, -0.2, 0.1]) + [0.0, 0.0, 1.0])


def _sweep(field, out, *extra):
    return main(["sweep", str(field), "--up", "0,1", "--trials", "40", "--out", str(out), *extra])


def _snapshot(root: Path) -> dict:
    """Every file and folder under ``root`` (hidden ones too): bytes and modification time."""
    return {
        p.relative_to(root).as_posix(): (
            (p.read_bytes(), p.stat().st_mtime_ns) if p.is_file() else "folder"
        )
        for p in sorted(root.rglob("*"))
    }


def _hold(out: Path, record: dict | None = HOLDER) -> int:
    """Lock ``out``'s lock file through a descriptor of its own, as another run would."""
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o666)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    if record is not None:
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
    return fd


@pytest.mark.parametrize(
    "layout", [[], ["--resume"], ["--pieces", "2"], ["--slabs", "2"], ["--keep-chunks"]]
)
def test_second_sweep_into_a_folder_in_use_exits_2_and_changes_nothing(
    small_map, tmp_path, capsys, layout
):
    """The live run's chunk store, maps and lock record stay byte for byte."""
    out = tmp_path / "res"
    assert _sweep(small_map, out, "--keep-chunks") == 0  # maps and a chunk store, as mid-run
    (out / "uf_up5um.vtu").write_bytes((out / "uf_up1um.vtu").read_bytes())  # a map of its own
    fd = _hold(out)
    try:
        before = _snapshot(out)
        assert (STORE_NAME + "/manifest.json") in before
        capsys.readouterr()
        rc = _sweep(small_map, out, *layout)
        assert _snapshot(out) == before
        assert rc == 2
        assert capsys.readouterr().err == f"cfm-fem: error: {out} {IN_USE}\n"
        # the option checks still come first: a typo is named, not the folder in use
        assert _sweep(small_map, out, "--chunk-nodes", "0") == 2
        assert "--chunk-nodes must be >= 1" in capsys.readouterr().err
        assert _snapshot(out) == before
    finally:
        os.close(fd)
    assert _sweep(small_map, out) == 0  # free again once its holder closes it


def test_every_command_that_writes_into_out_refuses_a_folder_in_use(tmp_path, capsys):
    out = tmp_path / "res"
    (out / "summary.json").parent.mkdir()
    (out / "summary.json").write_text("{}\n")
    fd = _hold(out)
    try:
        before = _snapshot(out)
        for argv in (
            ["kinematics", "--trials", "20"],
            ["tolerance", "--target", "5"],
        ):
            capsys.readouterr()
            assert main([*argv, "--out", str(out)]) == 2, argv
            assert IN_USE in capsys.readouterr().err, argv
            assert _snapshot(out) == before, argv
    finally:
        os.close(fd)


def test_a_killed_holder_leaves_no_lock(small_map, tmp_path, capsys):
    """The kernel releases the lock of a process that dies (SIGKILL): no stale lock, and the
    next run takes over the file and writes its own record into it."""
    out = tmp_path / "res"
    code = (
        "import sys, time\n"
        "from cfm_fem.io.lock import output_lock\n"
        "with output_lock(sys.argv[1], 'cfm-fem sweep held.csv'):\n"
        "    print('locked', flush=True)\n"
        "    time.sleep(120)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE,
                            env=env, text=True)  # fmt: skip
    try:
        assert proc.stdout.readline() == "locked\n"
        capsys.readouterr()
        assert _sweep(small_map, out) == 2
        err = capsys.readouterr().err
        assert f"in use by another cfm-fem run (pid {proc.pid} on " in err
        assert ": cfm-fem sweep held.csv); wait for it to finish" in err
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing written
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert _sweep(small_map, out) == 0
    record = json.loads((out / LOCK_NAME).read_text())
    assert record["pid"] == os.getpid() and record["command"].startswith("cfm-fem sweep ")


def test_the_lock_file_is_left_by_reruns_and_clean_ups(small_map, tmp_path, capsys):
    """An hour-old lock file (of a finished or killed run) is neither an output, nor a stale
    map, nor a leftover temporary: re-runs (other U_p, pieces, --resume) keep it and say
    nothing of it, and each takes it over."""
    out = tmp_path / "res"
    assert _sweep(small_map, out) == 0
    lock = out / LOCK_NAME
    assert lock.is_file()
    old = time.time() - 7200.0
    os.utime(lock, (old, old))
    capsys.readouterr()
    for extra in (["--up", "2"], ["--pieces", "2"], ["--resume"], ["--slabs", "2"]):
        args = ["sweep", str(small_map), "--trials", "40", "--out", str(out), *extra]
        assert main(args if "--up" in extra else [*args, "--up", "0,1"]) == 0, extra
        assert LOCK_NAME not in capsys.readouterr().err, extra
        assert lock.is_file(), extra
    from cfm_fem.io.sweep_out import remove_earlier_outputs

    os.utime(lock, (old, old))
    assert remove_earlier_outputs(out) == ([], [], [])
    assert lock.is_file()


def test_a_run_that_fails_leaves_no_lock_file_and_no_folder(small_map, tmp_path):
    """The lock file and the folders made for it go again when the run fails, as the outputs
    never appeared."""
    bad = tmp_path / "bad.csv"
    bad.write_text(small_map.read_text().replace("\n1,", "\nx,", 1))
    new = tmp_path / "a" / "b" / "res"
    assert _sweep(bad, new) == 2
    assert not (tmp_path / "a").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _sweep(bad, empty) == 2
    assert not any(empty.iterdir())


def test_python_writers_refuse_a_folder_in_use(tmp_path):
    """`ResumableRun.finish` deleted the store of whatever run used the folder, and
    `run_slab_sweep` replaced its work folder; both now refuse, naming ``out_dir``."""
    from cfm_fem.io.chunk_store import ChunkStore
    from cfm_fem.models.sweep import SweepConfig
    from cfm_fem.workflows.sweep.resume import ResumableRun
    from cfm_fem.workflows.sweep.slabs import run_slab_sweep

    out = tmp_path / "res"
    store = ChunkStore(out)
    store.write_manifest({"key": "live run"})
    store.save(0, 4, {"part0": np.zeros(4)})
    (out / ".cfm_fem_slabs").mkdir()
    (out / ".cfm_fem_slabs" / "manifest.json").write_text("{}\n")
    fd = _hold(out, record=None)  # locked, its record not written yet
    try:
        before = _snapshot(out)
        says = re.escape("is in use by another cfm-fem run (its lock file does not say which)")
        with pytest.raises(CfmInputError, match=r"\(its lock file .*choose another out_dir$"):
            ResumableRun(out, {"run": 2}).finish()
        with pytest.raises(CfmInputError, match=says):
            run_slab_sweep(tmp_path / "map.csv", SweepConfig(up_um=[1.0]), out, n_slabs=2,
                           description={"run": 2})  # fmt: skip
        with pytest.raises(CfmInputError, match=says), output_lock(out):
            pass
        assert _snapshot(out) == before
    finally:
        os.close(fd)
    with output_lock(out) as lock, output_lock(out) as nested:  # re-entrant in one process
        assert lock == out / LOCK_NAME and nested is None
        ResumableRun(out, {"run": 2}).finish()  # shares the lock this process holds
    assert not store.exists()
