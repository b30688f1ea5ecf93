"""Nothing lost: a killed sweep resumes to the numbers of an uninterrupted run; provenance."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv
from conftest import curved_field, grid_nodes, write_map_csv

from cfm_fem.cli import main
from cfm_fem.io._atomic import TEMPORARY_AGE_S
from cfm_fem.io.chunk_store import STORE_NAME, ChunkStore
from cfm_fem.io.sweep_out import read_provenance


def _write_map(path, n):
    pts = grid_nodes(n)
    return write_map_csv(path, pts, curved_field(pts))


@pytest.fixture(scope="module")
def big_map(tmp_path_factory):
    return _write_map(tmp_path_factory.mktemp("big") / "map.csv", 12)  # 1728 nodes


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    return _write_map(tmp_path_factory.mktemp("small") / "map.csv", 6)  # 216 nodes


def _chunks(out):
    store = out / STORE_NAME
    return sorted(store.glob("chunk_*.npz")) if store.is_dir() else []


def _same_outputs(a, b, ups):
    sa = json.loads((a / "summary.json").read_text())
    sb = json.loads((b / "summary.json").read_text())
    for key in ("uf_units", "uf_nodes", "outside_fraction", "walk_failed_fraction"):
        assert sa[key] == sb[key], key
    assert sa["gum_disagree_fraction"] == sb["gum_disagree_fraction"]
    for up in ups:
        pa = pv.read(a / f"uf_up{up}um.vtu").point_data
        pb = pv.read(b / f"uf_up{up}um.vtu").point_data
        assert set(pa) == set(pb)
        for name in pa:
            np.testing.assert_array_equal(pa[name], pb[name], err_msg=name)
    return sa, sb


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_numbers(big_map, tmp_path, capsys):
    args = ["sweep", str(big_map), "--up", "0:40:20", "--trials", "4000", "--seed", "9",
            "--chunk-nodes", "24"]  # fmt: skip
    n_chunks = -(-1728 // 24)
    killed = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cfm_fem", *args, "--out", str(killed)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=dict(os.environ, NUMBA_NUM_THREADS="1"),
    )
    try:
        deadline = time.monotonic() + 120
        while len(_chunks(killed)) < 4 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    done_before = len(_chunks(killed))
    assert 4 <= done_before < n_chunks, done_before  # killed mid-way
    assert not (killed / "summary.json").exists()
    assert not list(killed.glob("*.vtu"))
    # SIGKILL may cut a write short: its hidden temporary file stays, never a chunk file
    for partial in (killed / STORE_NAME).glob(".*"):
        assert partial.name.startswith((".chunk_", ".manifest.json.")), partial.name
    for chunk in _chunks(killed):
        with np.load(chunk) as z:  # every chunk file is complete
            assert z["n_parts"] > 0, chunk.name

    assert main([*args, "--out", str(killed), "--resume"]) == 0
    err = capsys.readouterr().err
    loaded = int(err.split("resumed: ")[1].split(" chunk")[0])
    assert loaded >= done_before - 1  # a chunk renamed at the kill may count either way
    assert not (killed / STORE_NAME).exists()  # removed after success

    clean = tmp_path / "clean"
    assert main([*args, "--out", str(clean)]) == 0
    sa, sb = _same_outputs(killed, clean, (0, 20, 40))
    assert sa["provenance"]["resumed_chunks"] == loaded
    print(f"\nresume test: killed after {done_before}/{n_chunks} chunks, resumed {loaded}, "
          "outputs identical to the uninterrupted run")  # fmt: skip


def test_resume_refuses_a_store_of_another_run(small_map, tmp_path, capsys):
    out = tmp_path / "o"
    base = ["sweep", str(small_map), "--up", "0:20:10", "--seed", "1", "--chunk-nodes", "50"]
    assert main([*base, "--trials", "200", "--out", str(out), "--keep-chunks"]) == 0
    before = sorted(p.name for p in (out / STORE_NAME).iterdir())
    (out / "summary.json").unlink()
    capsys.readouterr()
    assert main([*base, "--trials", "300", "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and STORE_NAME in err
    assert "trials: 200 in the store, 300 now" in err and "Traceback" not in err
    assert sorted(p.name for p in (out / STORE_NAME).iterdir()) == before  # untouched
    assert not (out / "summary.json").exists()
    # same options resume from the complete store without computing anything
    assert main([*base, "--trials", "200", "--out", str(out), "--resume"]) == 0
    assert "resumed: 5 chunk(s) read from" in capsys.readouterr().err
    # without --resume a stale store is replaced, not reused
    assert main([*base, "--trials", "300", "--out", str(out), "--keep-chunks"]) == 0
    manifest = json.loads((out / STORE_NAME / "manifest.json").read_text())
    assert manifest["run"]["trials"] == 300


def test_damaged_chunk_file_is_recomputed(small_map, tmp_path, capsys):
    base = ["sweep", str(small_map), "--up", "10", "--trials", "200", "--chunk-nodes", "50"]
    out = tmp_path / "o"
    assert main([*base, "--out", str(out), "--keep-chunks"]) == 0
    chunk = _chunks(out)[2]
    chunk.write_bytes(chunk.read_bytes()[:100])  # truncated
    _chunks(out)[0].unlink()  # missing
    assert main([*base, "--out", str(tmp_path / "r"), "--keep-chunks"]) == 0
    (out / "summary.json").unlink()
    capsys.readouterr()
    assert main([*base, "--out", str(out), "--resume"]) == 0
    err = capsys.readouterr().err
    assert "3 chunk(s) read" in err and "2 computed" in err and "1 unreadable" in err
    _same_outputs(out, tmp_path / "r", (10,))


def test_every_output_records_what_produced_it(small_map, tmp_path):
    out = tmp_path / "o"
    assert main(["sweep", str(small_map), "--up", "10", "--trials", "100", "--seed", "4",
                 "--out", str(out)]) == 0  # fmt: skip
    prov = json.loads((out / "summary.json").read_text())["provenance"]
    assert prov["inputs"]["field"]["sha256"] and prov["cfm_fem_version"]
    assert prov["seed"] == 4 and prov["trials"] == 100
    assert prov["command_line"].startswith("cfm-fem sweep") and "--seed 4" in prov["command_line"]
    vtu = pv.read(out / "uf_up10um.vtu")
    assert read_provenance(vtu.field_data) == prov

    kin = tmp_path / "k"
    assert main(["kinematics", "--trials", "500", "--seed", "2", "--out", str(kin)]) == 0
    kprov = json.loads((kin / "summary.json").read_text())["provenance"]
    assert kprov["seed"] == 2 and kprov["trials"] == 500 and kprov["bench_name"]
    assert kprov["inputs"]["bench"] == _packaged_bench()  # no --bench: the packaged one
    assert kprov["command_line"].startswith("cfm-fem kinematics") and kprov["cfm_fem_version"]
    csv_line = next(
        ln for ln in (kin / "points.csv").read_text().splitlines() if ln.startswith("# provenance:")
    )
    assert json.loads(csv_line.removeprefix("# provenance: ")) == kprov
    assert read_provenance(pv.read(kin / "points.vtu").field_data) == kprov


def test_ctrl_c_keeps_the_chunks_and_says_how_to_resume(big_map, tmp_path):
    out = tmp_path / "o"
    proc = subprocess.Popen(
        [sys.executable, "-m", "cfm_fem", "sweep", str(big_map), "--up", "20", "--trials",
         "4000", "--chunk-nodes", "24", "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, NUMBA_NUM_THREADS="1"),
        # A shell starts background jobs with SIGINT ignored, and a child inherits that (Python
        # then never installs its Ctrl-C handler): the sweep must get Ctrl-C as from a terminal
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while len(_chunks(out)) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 1, err
    assert "Traceback" not in err
    assert "run the same command with --resume to continue" in err
    assert _chunks(out) and not (out / "summary.json").exists()


def test_resume_removes_the_temporary_file_of_a_killed_write(small_map, tmp_path, capsys):
    out = tmp_path / "o"
    base = ["sweep", str(small_map), "--up", "0:20:10", "--seed", "2", "--chunk-nodes", "50"]
    assert main([*base, "--trials", "200", "--out", str(out), "--keep-chunks"]) == 0
    store = out / STORE_NAME
    partial = store / ".chunk_50_100.npz.k1ll3d_0.npz"  # `atomic_path`'s name: 8 random chars
    partial.write_bytes(b"PK\x03\x04 cut short")
    old = time.time() - 2 * TEMPORARY_AGE_S
    os.utime(partial, (old, old))
    (store / "chunk_50_100.npz").unlink()  # the chunk whose write was killed
    # another run's write still in progress, and a file that is no temporary of the store
    young = store / ".chunk_0_50.npz.wr1t1ng0.npz"
    young.write_bytes(b"PK\x03\x04 being written")
    other = store / ".nfs000000000001"
    other.write_bytes(b"not ours")
    os.utime(other, (old, old))
    capsys.readouterr()
    assert main([*base, "--trials", "200", "--out", str(out), "--resume", "--keep-chunks"]) == 0
    assert "resumed: 4 chunk(s) read from" in capsys.readouterr().err
    assert not partial.exists()
    assert (store / "chunk_50_100.npz").exists()
    assert young.exists() and other.exists()


def test_remove_partial_removes_only_old_temporaries_of_the_store(tmp_path):
    store = ChunkStore(tmp_path)
    store.write_manifest({"key": "k"})
    old = time.time() - TEMPORARY_AGE_S - 60
    names = {
        ".chunk_0_50.npz.a1b2c3d4.npz": old,  # removed: a killed chunk write
        ".manifest.json.zz_9zz_9.json": old,  # removed: a killed manifest write
        ".chunk_0_50.npz.e5f6g7h8.npz": None,  # kept: young, may be in flight
        ".chunk_0_50.npz.short.npz": old,  # kept: not a name `atomic_path` gives
        ".notes.txt.a1b2c3d4.txt": old,  # kept: a temporary, but of no store file
        ".hidden": old,  # kept: no temporary
    }
    for name, t in names.items():
        (store.path / name).write_bytes(b"x")
        if t is not None:
            os.utime(store.path / name, (t, t))
    assert store.remove_partial() == 2
    left = sorted(p.name for p in store.path.iterdir())
    assert left == sorted([*list(names)[2:], "manifest.json"])
    assert store.remove_partial(min_age_s=0.0) == 1  # the young one, once old enough
    assert store.read_manifest() == {"key": "k"}


def _packaged_bench():
    """Provenance entry expected for the packaged reference bench."""
    ref = resources.files("cfm_fem.data").joinpath("cfm_reference_bench.toml")
    sha = hashlib.sha256(ref.read_bytes()).hexdigest()
    return {"path": str(ref), "sha256": sha, "packaged_default": True}


def test_the_packaged_bench_is_recorded_and_keyed_like_a_copy_of_it(small_map, tmp_path, capsys):
    """Mode htm without --bench names the packaged bench (path, hash) in the provenance and the
    summary; a run given a copy of that file has the same key: it resumes from the store of the
    default run, with the same numbers."""
    from cfm_fem.io.bench_toml import read_reference_bench

    packaged = _packaged_bench()
    base = ["sweep", str(small_map), "--mode", "htm", "--trials", "40", "--seed", "3",
            "--chunk-nodes", "50"]  # fmt: skip
    out = tmp_path / "o"
    assert main([*base, "--out", str(out), "--keep-chunks"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["provenance"]["inputs"]["bench"] == packaged
    assert s["bench"] == {"name": read_reference_bench().name, "source": packaged["path"]}
    manifest = json.loads((out / STORE_NAME / "manifest.json").read_text())
    assert manifest["run"]["bench_sha256"] == packaged["sha256"]

    copy = tmp_path / "copy.toml"
    copy.write_bytes(Path(packaged["path"]).read_bytes())
    (out / "summary.json").unlink()
    capsys.readouterr()
    assert main([*base, "--bench", str(copy), "--out", str(out), "--resume"]) == 0
    assert "resumed: 5 chunk(s) read from" in capsys.readouterr().err  # nothing recomputed
    c = json.loads((out / "summary.json").read_text())
    assert c["provenance"]["inputs"]["bench"] == dict(
        packaged, path=str(copy), packaged_default=False
    )
    assert c["provenance"]["run_key"] == s["provenance"]["run_key"]
    assert c["bench"] == {"name": s["bench"]["name"], "source": str(copy)}
    for key in ("uf_units", "uf_nodes", "outside_fraction", "up_um"):
        assert c[key] == s[key], key

    sl = tmp_path / "sl"  # out of core: the same record
    assert main([*base, "--slabs", "2", "--out", str(sl)]) == 0
    s_sl = json.loads((sl / "summary.json").read_text())
    assert s_sl["provenance"]["inputs"]["bench"] == packaged and s_sl["bench"] == s["bench"]

    g = tmp_path / "g"  # mode gauss uses no bench: none recorded
    assert main(["sweep", str(small_map), "--up", "10", "--trials", "40", "--out", str(g)]) == 0
    s_g = json.loads((g / "summary.json").read_text())
    assert "bench" not in s_g["provenance"]["inputs"] and s_g["bench"] is None


def test_resume_refuses_the_store_of_another_comsol_solution(tmp_path, capsys):
    """The COMSOL solution read (--solution) is part of the run's key: the chunks of I0=100 are
    not mixed into a run of I0=200 of the same file."""
    ax = np.arange(5.0)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    B = np.c_[0.03 * pts[:, 0] ** 2, -0.02 * pts[:, 1] * pts[:, 2], 1.0 + 0.1 * pts[:, 2]]
    names = ["X", "Y", "Z"] + [f"mf.B{a} (T) @ I0={i}" for i in (100, 200) for a in "xyz"]
    rows = "".join(" ".join(f"{v:.17g}" for v in r) + "\n" for r in np.c_[pts, B, 2.0 * B])
    path = tmp_path / "two_solutions.txt"
    path.write_text("% Length unit: mm\n% " + "  ".join(names) + "\n" + rows)
    out = tmp_path / "o"
    base = ["sweep", str(path), "--up", "0:20:10", "--trials", "200", "--chunk-nodes", "50"]
    assert main([*base, "--solution", "I0=100", "--out", str(out), "--keep-chunks"]) == 0
    manifest = json.loads((out / STORE_NAME / "manifest.json").read_text())
    assert manifest["run"]["read_options"]["solution"] == "I0=100"
    capsys.readouterr()
    assert main([*base, "--solution", "I0=200", "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert 'read_options.solution: "I0=100" in the store, "I0=200" now' in err, err
    assert main([*base, "--solution", "I0=100", "--out", str(out), "--resume"]) == 0
    assert "resumed: 3 chunk(s) read from" in capsys.readouterr().err


def test_code_fingerprint_reads_files_that_exist():
    """Every entry of CODE_MODULES is a file of the package or a folder of .py files: an entry
    left behind by a move would hash "<absent>" and let a store outlive the code it came from."""
    from importlib import resources

    from cfm_fem.workflows.sweep.resume import CODE_MODULES

    root = resources.files("cfm_fem")
    for entry in CODE_MODULES:
        path = root.joinpath(entry)
        if entry.endswith("/"):
            assert any(f.name.endswith(".py") for f in path.iterdir()), entry
        else:
            assert path.is_file(), entry
