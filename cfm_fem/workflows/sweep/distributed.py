"""Dask backend: sweep chunks and kinematics point blocks on a cluster.

Results do not depend on where they are computed: a sweep chunk's statistics depend only on its
node range (counter-based random numbers keyed by seed and node), so `dask_chunk_map` yields
exactly the chunks `cfm_fem.workflows.sweep.problem.serial_map` would, in completion order, and
`run_sweep` merges them into bit-identical arrays. Kinematics points are likewise independent of
each other (each point's statistics use its own noise stream and its own windows), see
`run_kinematics_dask`.

Dask is an optional dependency (``pip install cfm_fem[dask]``); it is imported only here and
only when a cluster is asked for.
"""

from __future__ import annotations

import contextlib
import os

import numpy as np

from ...errors import CfmInputError

__all__ = [
    "backend_description",
    "check_scale_out",
    "dask_client",
    "dask_chunk_map",
    "check_workers",
    "run_kinematics_dask",
]


#: Seconds to wait for a ``--scheduler`` before giving up.
CONNECT_TIMEOUT_S = 20


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise CfmInputError(
            "--scheduler and --workers need Dask: pip install 'cfm_fem[dask]'"
        ) from None
    return distributed


#: Most local Dask worker processes per CPU: more only compete for the CPUs and the memory.
MAX_WORKERS_PER_CPU = 4


def backend_description(scheduler: str | None = None, workers: int | None = None) -> str:
    """Where a run's trials ran, for the provenance: a Dask scheduler, a local cluster of
    ``workers`` processes, or this process."""
    if scheduler:
        return f"dask scheduler {scheduler}"
    if workers:
        return f"dask LocalCluster, {workers} worker process(es)"
    return "this process (numba threads)"


def check_scale_out(scheduler: str | None = None, workers: int | None = None) -> None:
    """The checks of `dask_client` that need no cluster, for a command to run before any work.

    Raises
    ------
    CfmInputError
        Both given, ``workers < 1``, or Dask missing.
    """
    if scheduler is None and workers is None:
        return
    if scheduler is not None and workers is not None:
        raise CfmInputError("give either --scheduler or --workers, not both")
    if workers is not None and workers < 1:
        raise CfmInputError(f"--workers must be >= 1; got {workers}")
    most = MAX_WORKERS_PER_CPU * (os.cpu_count() or 1)
    if workers is not None and workers > most:
        raise CfmInputError(
            f"--workers must be at most {most} ({MAX_WORKERS_PER_CPU} per CPU of this machine; "
            f"each is a process with its own copy of the map); got {workers}"
        )
    _import_distributed()


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None):
    """A Dask client: to a running scheduler, or to a local cluster started for the run.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler, e.g. ``tcp://10.0.0.5:8786``.
    workers : int, optional
        Start a `distributed.LocalCluster` with this many worker processes (one thread each:
        the numba kernels are the parallel part). Closed on exit.

    Yields
    ------
    distributed.Client or None
        None when neither is given (run in this process).

    Raises
    ------
    CfmInputError
        Both given, ``workers < 1``, Dask missing, or the scheduler cannot be reached.
    """
    if scheduler is None and workers is None:
        yield None
        return
    check_scale_out(scheduler, workers)
    distributed = _import_distributed()
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            try:
                client = distributed.Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise CfmInputError(
                    f"--scheduler: cannot reach the Dask scheduler {scheduler!r}: {exc}; "
                    "expected the address "
                    "of a running scheduler such as tcp://HOST:8786"
                ) from None
        else:
            try:
                cluster = stack.enter_context(
                    distributed.LocalCluster(
                        n_workers=int(workers),
                        threads_per_worker=1,
                        processes=True,
                        dashboard_address=None,
                        host="127.0.0.1",
                    )
                )
            except (OSError, RuntimeError, TimeoutError) as exc:  # "Nanny failed to start"
                raise CfmInputError(
                    f"--workers {workers}: Dask could not start a local cluster of {workers} "
                    f"worker process(es) ({exc}); expected fewer workers, or the memory and "
                    "process limits for them"
                ) from None
            client = distributed.Client(cluster)
        stack.enter_context(client)
        yield client


def _run_chunk(problem, start, stop):
    return problem.run_chunk(start, stop)


def _fingerprint():
    from .resume import code_fingerprint

    return code_fingerprint()


def check_workers(client) -> None:
    """Refuse workers that run other cfm_fem code than this process (other numbers).

    Raises
    ------
    CfmInputError
        A worker cannot import cfm_fem, or its number-deciding sources differ from ours.
    """
    from .resume import code_fingerprint

    mine = code_fingerprint()
    try:
        theirs = client.run(_fingerprint)
    except Exception as exc:  # ModuleNotFoundError on the worker, comm errors, ...
        raise CfmInputError(
            f"the Dask workers cannot run cfm_fem ({type(exc).__name__}: {exc}); install the "
            "same cfm_fem version in the workers' environment"
        ) from None
    other = sorted(addr for addr, fp in theirs.items() if fp != mine)
    if other:
        raise CfmInputError(
            f"{len(other)} Dask worker(s) run other cfm_fem code than this process (first: "
            f"{other[0]}); install the same cfm_fem version on the workers so that the numbers "
            "are those of a single-process run"
        )


def dask_chunk_map(client):
    """Chunk mapper for `cfm_fem.workflows.sweep.in_memory.run_sweep` that runs the chunks on
    ``client``'s cluster.

    The workers are first checked to run the same cfm_fem code (`check_workers`); the
    `SweepProblem` is then scattered once to every worker (broadcast); each chunk is one task;
    results are yielded as they complete and released on the cluster at once.

    Parameters
    ----------
    client : distributed.Client

    Returns
    -------
    callable(problem, chunks) -> iterator of ((start, stop), result)
    """
    distributed = _import_distributed()

    def run(problem, chunks):
        chunks = [(int(a), int(b)) for a, b in chunks]
        if not chunks:
            return
        check_workers(client)
        shared = client.scatter(problem, broadcast=True, hash=False)
        futures = {
            client.submit(_run_chunk, shared, a, b, pure=False, key=f"cfm-sweep-chunk-{a}-{b}"): (
                a,
                b,
            )
            for a, b in chunks
        }
        try:
            for future, result in distributed.as_completed(futures, with_results=True):
                yield futures.pop(future), result
                future.release()
        finally:
            for future in futures:
                future.cancel()
            shared.release()

    return run


def _kinematics_block(bench, trials, seed, q, index, exact):
    from ...models.kinematics.monte_carlo import run_kinematics

    return run_kinematics(bench, trials=trials, seed=seed, q_cmd=q, point_index=index, exact=exact)


def run_kinematics_dask(client, bench, trials, seed, *, exact=True, block_points=64, progress=None):
    """`run_kinematics` over blocks of scan points on a Dask cluster; same numbers as one process.

    Every point's statistics (pilot windows, shifted sums per trial block, exact order
    statistics) use only that point's samples, and its noise stream is keyed by its index in
    the full grid (``point_index``), so a block of points gives the rows of the full run
    bit for bit; the Table IV pooling is then done on the merged per-point arrays.

    Parameters
    ----------
    client : distributed.Client
    bench : Bench
    trials, seed : int
    exact : bool
        Exact interval ends on the generic path, as `run_kinematics` (the reference bench's
        are exact either way).
    block_points : int
        Points per task.
    progress : callable(int), optional
        Called with the number of points finished.

    Returns
    -------
    KinematicsResult

    """
    from ...models.kinematics.monte_carlo import KinematicsResult, pool_table_iv

    distributed = _import_distributed()
    check_workers(client)
    q = np.ascontiguousarray(bench.grid_points())
    npts = len(q)
    blocks = [(a, min(a + block_points, npts)) for a in range(0, npts, block_points)]
    shared = client.scatter(bench, broadcast=True, hash=False)
    futures = {
        client.submit(
            _kinematics_block,
            shared,
            int(trials),
            int(seed),
            q[a:b],
            np.arange(a, b, dtype=np.int64),
            bool(exact),
            pure=False,
        ): (a, b)
        for a, b in blocks
    }
    parts = {}
    for future, res in distributed.as_completed(futures, with_results=True):
        a, b = futures[future]
        parts[a] = res
        future.release()
        if progress is not None:
            progress(b - a)
    shared.release()
    ordered = [parts[a] for a, _ in blocks]

    def cat(name):
        return np.concatenate([getattr(r, name) for r in ordered])

    mean, std = cat("mean"), cat("std")
    notes = list(dict.fromkeys(n for r in ordered for n in r.notes))
    notes.append(f"computed on Dask in {len(blocks)} blocks of up to {block_points} points")
    seconds = {}
    for r in ordered:
        for k, v in r.seconds.items():
            seconds[f"{k}_worker_sum"] = seconds.get(f"{k}_worker_sum", 0.0) + v
    first = ordered[0]
    return KinematicsResult(
        q_cmd=cat("q_cmd"),
        nominal=cat("nominal"),
        mean=mean,
        std=std,
        low=cat("low"),
        high=cat("high"),
        trials=first.trials,
        seed=first.seed,
        pooled=pool_table_iv(mean, std),
        seconds=seconds,
        interval_method=first.interval_method,
        p=first.p,
        notes=notes,
        adaptive=None,
    )
