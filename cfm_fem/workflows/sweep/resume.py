"""Resumable sweeps: finished chunks are kept on disk and reused only by the identical run.

A run is identified by a key: the SHA-256 of everything that determines a chunk's numbers
(`describe_sweep`): the input file's bytes, the reader options, U_p values, trials, seed, axis
scale, interpolation, field model, coverage, mode, bench file, chunk size, the cfm_fem version
and a hash of the source of the modules that compute the numbers. Chunk results depend only on
their node range (`cfm_fem.workflows.sweep.problem.SweepProblem`), so loading the finished chunks
and computing the rest gives bit-identical statistics to an uninterrupted run.

Every sweep writes its chunks to the store as they finish (`ResumableRun.mapper`); ``--resume``
reuses those of a run with the same key and refuses, naming what differs, a store made by a
different run. The store is deleted after the outputs are written (unless kept on request).
"""

from __future__ import annotations

import hashlib
import json
from concurrent.futures import ThreadPoolExecutor
from importlib import resources

import numpy as np

from ...errors import CfmInputError
from ...io.chunk_store import ChunkStore
from ...io.lock import output_lock
from .problem import serial_map

__all__ = ["CODE_MODULES", "code_fingerprint", "describe_sweep", "run_key", "ResumableRun"]

#: Source files whose code decides the numbers of a chunk (readers included: they turn the file
#: into mm and T); a folder stands for every ``.py`` file in it. A change in any of them
#: invalidates a store.
CODE_MODULES = (
    "_kernels/",
    "workflows/sweep/problem.py",
    "models/sweep.py",
    "models/mesh.py",
    "models/interpolation.py",
    "models/harmonic.py",
    "models/harmonic_basis.py",
    "models/field.py",
    "units.py",
    "io/__init__.py",
    "io/_parse.py",
    "io/comsol.py",
    "io/comsol_sections.py",  # the sectionwise layout and the choice of a COMSOL solution
    "io/opera.py",
    "io/table.py",
    "io/meshfile.py",
    # mode htm: the bench model
    "models/kinematics/",
    "models/rotations.py",
    "models/bench.py",
    "models/mc.py",
    "io/bench_toml.py",
    "data/cfm_reference_bench.toml",
)


def code_fingerprint() -> str:
    """SHA-256 over the source of `CODE_MODULES`, hex."""
    h = hashlib.sha256()
    root = resources.files("cfm_fem")
    for entry in CODE_MODULES:
        folder = root.joinpath(entry)
        names = (
            sorted(entry + f.name for f in folder.iterdir() if f.name.endswith(".py"))
            if entry.endswith("/")
            else [entry]
        )
        for name in names:
            h.update(name.encode())
            f = root.joinpath(name)
            h.update(f.read_bytes() if f.is_file() else b"<absent>")
    return h.hexdigest()


def describe_sweep(cfg, field_sha256: str, read_options: dict, bench_sha256=None) -> dict:
    """Everything that determines the chunk results of a sweep, as plain JSON values.

    Parameters
    ----------
    cfg : SweepConfig
    field_sha256 : str
        Hash of the field-map file's bytes.
    read_options : dict
        Reader options (format, units, zero-row rule, COMSOL solution) that change how the file
        is read.
    bench_sha256 : str or None
        Hash of the bench file of mode htm, the packaged reference bench included when no file
        is given (`cfm_fem.io.provenance.bench_input`): a run on the default bench and one on a
        copy of the same file then share a key. None in mode gauss (no bench).

    Returns
    -------
    dict
        B_ref is left out on purpose: it only scales the outputs, not the chunk statistics (T).
    """
    import numba

    from ... import __version__

    return {
        "field_sha256": field_sha256,
        "read_options": {k: read_options[k] for k in sorted(read_options)},
        "bench_sha256": bench_sha256,
        "up_um": [float(u) for u in cfg.up_um],
        "trials": int(cfg.trials),
        "estimator": cfg.estimator,
        "seed": int(cfg.seed),
        "axis_scale": [float(a) for a in cfg.axis_scale],
        "interpolation": cfg.interpolation,
        "coverage": float(cfg.coverage),
        "mode": cfg.mode,
        "outside": cfg.outside,
        "hull_slivers": cfg.hull_slivers,
        "field_model": cfg.field_model,
        "chunk_nodes": int(cfg.chunk_nodes),
        "cfm_fem_version": __version__,
        "code_sha256": code_fingerprint(),
        "numpy": np.__version__,
        "numba": numba.__version__,
    }


def run_key(description: dict) -> str:
    """SHA-256 of the canonical JSON of a run description, hex."""
    text = json.dumps(description, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


class ResumableRun:
    """The chunk store of one sweep and the chunk mapper that fills and reuses it.

    Parameters
    ----------
    out_dir : path-like
        Output folder (the store lives in ``out_dir/.cfm_fem_chunks``).
    description : dict
        From `describe_sweep`.
    resume : bool
        Reuse the finished chunks of an identical earlier run. Without it an existing store is
        replaced.

    The mapper and `finish` remove the store: each holds the lock of ``out_dir``
    (`cfm_fem.io.lock.output_lock`; shared with a caller that holds it, as ``cfm-fem sweep``
    does for the whole run), so they refuse, with a `CfmInputError`, to remove the store of
    another run writing into ``out_dir`` at the same time. Hold the lock around the whole run
    to keep another run out between the chunks and `finish` too.

    Attributes
    ----------
    loaded, computed : int
        Chunks taken from the store and chunks computed in this run (after the mapper ran).
    rejected : int
        Chunk files of the same run that could not be used (unreadable, wrong shape) and were
        computed again.
    """

    def __init__(self, out_dir, description: dict, resume: bool = False):
        self.out_dir = out_dir
        self.store = ChunkStore(out_dir)
        self.description = description
        self.key = run_key(description)
        self.resume = bool(resume)
        self.loaded = 0
        self.computed = 0
        self.rejected = 0

    def check(self) -> list[tuple[int, int]]:
        """Before any work: refuse to resume from a store made by another run.

        Returns
        -------
        list of (start, stop)
            Chunk files present that belong to this run (empty without ``resume``).

        Raises
        ------
        CfmInputError
            ``resume`` is set and the store was made with other inputs, options or code; the
            message names what differs and nothing is changed on disk.
        """
        if not (self.resume and self.store.exists()):
            return []
        manifest = self.store.read_manifest()
        if manifest is None:
            if not self.store.completed():
                return []  # killed before the first chunk: nothing to reuse, nothing to refuse
            raise CfmInputError(
                "cannot resume: the chunk store has no readable manifest.json, so it cannot be "
                "told which run made it; run without --resume to start again",
                file=self.store.path,
            )
        if manifest.get("key") != self.key:
            raise CfmInputError(
                "cannot resume: the chunk store was made by a different run ("
                + _differences(manifest.get("run", {}), self.description)
                + "); use the same input and options, or run without --resume to start again "
                "(the store is then replaced)",
                file=self.store.path,
            )
        return self.store.completed()

    def mapper(self, inner=None):
        """Chunk mapper for `cfm_fem.workflows.sweep.in_memory.run_sweep` that stores every finished
        chunk.

        Parameters
        ----------
        inner : callable(problem, chunks) -> iterable of ((start, stop), result), optional
            Runs the chunks that are not in the store (default
            `cfm_fem.workflows.sweep.problem.serial_map`; e.g.
            `cfm_fem.workflows.sweep.distributed.dask_chunk_map`).
        """
        inner = serial_map if inner is None else inner

        def run(problem, chunks):
            with output_lock(self.out_dir, option="out_dir"):  # the store is removed below
                yield from self._map(problem, chunks, inner)

        return run

    def _map(self, problem, chunks, inner):
        """The body of `mapper`'s chunk mapper."""
        chunks = [(int(a), int(b)) for a, b in chunks]
        present = set(self.check())
        if self.resume:
            # temporaries of writes cut short by a kill, once an hour old (a younger one
            # may be another run's, still being written)
            self.store.remove_partial()
        else:
            self.store.remove()
        self.store.write_manifest({"key": self.key, "run": self.description})
        todo = []
        for a, b in chunks:
            result = self._load(a, b, problem) if (a, b) in present else None
            if result is None:
                todo.append((a, b))
                continue
            self.loaded += 1
            yield (a, b), result
        # each chunk's file is written on a thread while the next chunk runs (an error there
        # is raised here once the chunks are done; an interrupted run waits for the files
        # under way, which then count as finished)
        with ThreadPoolExecutor(1) as saver:
            saving = []
            for (a, b), result in inner(problem, todo):
                parts = {f"part{j}": np.asarray(x) for j, x in enumerate(result)}
                parts.update(n_parts=len(result), key=self.key)
                saving.append(saver.submit(self.store.save, a, b, parts))
                self.computed += 1
                yield (a, b), result
            for done in saving:
                done.result()

    def _load(self, a, b, problem=None):
        """The result tuple of chunk (a, b) from its file, or None if it cannot be used."""
        arrays = self.store.load(a, b)
        parts = _parts(arrays, self.key)
        if parts is None or any(x.ndim == 0 or x.shape[0] != b - a for x in parts):
            self.rejected += 1
            return None
        return parts

    def gather(self, nodes, chunks):
        """Statistics of the nodes ``nodes`` read back from the stored chunks, one at a time.

        Parameters
        ----------
        nodes : ndarray, shape (p,), int64, sorted
        chunks : list of (start, stop)
            The chunk ranges of the run (`cfm_fem.workflows.sweep.problem.chunk_ranges`).

        Returns
        -------
        tuple
            The chunk result arrays (`cfm_fem.workflows.sweep.problem.SweepProblem.run_chunk`) of
            those nodes, ``p`` rows each.
        """
        nodes = np.asarray(nodes, dtype=np.int64)
        out = None
        for a, b in chunks:
            lo, hi = np.searchsorted(nodes, [a, b])
            if lo == hi:
                continue
            parts = _parts(self.store.load(a, b), self.key)
            if parts is None:
                raise RuntimeError(f"chunk {a}..{b - 1} is missing from {self.store.path}")
            if out is None:
                out = [np.empty((len(nodes),) + x.shape[1:], x.dtype) for x in parts]
            for dst, x in zip(out, parts, strict=True):
                dst[lo:hi] = x[nodes[lo:hi] - a]
        return tuple(out)

    def finish(self, keep: bool = False) -> None:
        """After the outputs are written: delete the store unless ``keep``."""
        if not keep:
            with output_lock(self.out_dir, option="out_dir"):  # never another run's store
                self.store.remove()


def _parts(arrays, key):
    """The result tuple stored in a chunk file's arrays, or None (missing, other run)."""
    if arrays is None or str(arrays.get("key", "")) != key or "n_parts" not in arrays:
        return None
    n = int(arrays["n_parts"])
    if any(f"part{j}" not in arrays for j in range(n)):
        return None
    return tuple(arrays[f"part{j}"] for j in range(n))


def _differences(old: dict, new: dict, prefix: str = "") -> str:
    """'trials: 400 in the store, 500 now; seed: ...' for the keys that differ; within a dict
    on both sides, its keys that differ ('read_options.solution: ...')."""
    diffs = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k), new.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            diffs.append(_differences(a, b, f"{prefix}{k}."))
        else:
            diffs.append(f"{prefix}{k}: {_short(a)} in the store, {_short(b)} now")
    return "; ".join(diffs) or "the run keys differ"


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 70 else text[:67] + "..."
