"""``cfm-fem sweep`` as one function, `run_sweep`, behind both the command line and
`cfm_fem.api.run_sweep`: check the options, choose the bench of mode htm, then run the sweep in
memory (`in_memory`), by pieces (`pieces`), out of core (`slabs`), resumable (`resume`) or on
Dask workers (`distributed`), and, given an output folder, write the maps, ``summary.json``, the
per-node table and the report.

Messages for the user (what was removed, resumed, kept) go to ``log``; nothing here prints.
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass, field
from importlib import import_module
from pathlib import Path

from ...errors import CfmInputError
from ..inputs import bench_provenance, choose_bench, field_map
from ..results import SweepMaps
from .distributed import backend_description

#: Most U_p values one sweep accepts (a typo such as 0:50:0.001 would otherwise ask for 50,001
#: maps and exhaust the memory before anything is computed).
MAX_UP_VALUES = 1000

__all__ = ["SweepRun", "run_sweep", "check_options", "check_mode_options", "parse_size"]


@dataclass
class SweepRun(SweepMaps):
    """A sweep: its `SweepMaps` (``result`` None when it ran out of core, slab by slab) and
    what it wrote.

    Attributes
    ----------
    summary : dict
        ``summary.json``.
    written : list of Path
        Files written (empty without an output folder).
    """

    written: list = field(default_factory=list)


def parse_size(text) -> float:
    """A memory size, ``'2G'``, ``'500M'``, ``'1.5GB'``, ``'800000000'`` or a number, in
    bytes."""
    if isinstance(text, (int, float)):
        value = float(text)
        if not (value > 0 and value < float("inf")):
            raise CfmInputError(f"--max-memory must be a positive size in bytes; got {text!r}")
        return value
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    mult = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}.get(t[-1:], 1)
    try:
        v = float(t[:-1] if t[-1:] in "KMGT" else t) * mult
    except ValueError:
        v = -1.0
    if not (v > 0 and v < float("inf")):
        raise CfmInputError(f"--max-memory must be a size such as 2G or 500M; got {text!r}")
    return v


def check_mode_options(mode: str, bench=None, up_given: bool = False, axis_scale=None) -> None:
    """Refuse a bench in mode gauss, and U_p values (``up_given``) or an axis scale in mode
    htm."""
    if bench is not None and mode != "htm":  # gauss draws N(0, U_p): no bench in it
        raise CfmInputError(
            "--bench is used by --mode htm only (mode gauss has no bench model); "
            "add --mode htm or leave out --bench"
        )
    given = [o for o, v in (("--up", up_given), ("--axis-scale", axis_scale)) if v]
    if given and mode == "htm":  # htm draws the probe error from the bench: no U_p in it
        raise CfmInputError(
            f"{' and '.join(given)} {'is' if len(given) == 1 else 'are'} used by --mode gauss "
            "only (--mode htm draws the probe error from the bench model); leave "
            f"{'it' if len(given) == 1 else 'them'} out"
        )


def check_up_values(up_um, option: str = "--up") -> None:
    """Refuse U_p values that are not finite, negative, more than `MAX_UP_VALUES` or the same
    map twice."""
    import math

    from .problem import check_up_distinct

    values = list(up_um)
    if not values or any(not math.isfinite(v) or v < 0 for v in values):
        shown = ", ".join(f"{v:g}" for v in values)
        raise CfmInputError(f"{option} values must be finite and >= 0 um; got {shown or 'none'}")
    if len(values) > MAX_UP_VALUES:
        raise CfmInputError(f"{option} gives {len(values)} U_p values; expected at most "
                            f"{MAX_UP_VALUES}")  # fmt: skip
    check_up_distinct(values, option)


def check_options(*, up_um, trials: int, seed: int, mode: str = "gauss", bench=None,
                  axis_scale=None, b_ref_T=None, chunk_nodes: int = 20000, pieces=None,
                  scheduler=None, workers=None, slabs=None, max_memory=None, region=None,
                  table=None, up_given: bool = True) -> None:  # fmt: skip
    """Every check of the options that needs no file read, before the map is read (minutes for
    a large one) and before any output.

    Raises
    ------
    CfmInputError
        A bench or ``--up`` / ``--axis-scale`` in the wrong mode, a bad count, trial number,
        seed, axis scale, B_ref, Dask option, slab option or table format.
    """
    from ...errors import check_seed
    from .distributed import check_scale_out
    from .problem import check_options as check_config

    check_mode_options(mode, bench, up_given, axis_scale)
    check_seed(seed)
    check_up_values(up_um)
    if chunk_nodes < 1:
        raise CfmInputError(f"--chunk-nodes must be >= 1; got {chunk_nodes}")
    if pieces is not None and pieces < 1:
        raise CfmInputError(f"--pieces must be >= 1; got {pieces}")
    trials = DEFAULT_TRIALS if trials is None else trials
    check_config(trials, axis_scale or (1.0, 1.0, 1.0), b_ref_T, len(up_um), mode)
    check_scale_out(scheduler, workers)
    if slabs is not None or max_memory is not None:
        _check_slab_options(slabs, max_memory, pieces, region)
    if table is not None:
        from ...io.sweep_table import check_table_format

        check_table_format(table)


def _check_slab_options(slabs, max_memory, pieces, region) -> None:
    """The checks of ``--slabs`` / ``--max-memory`` that need no file, before any output."""
    if slabs is not None and slabs < 1:
        raise CfmInputError(f"--slabs must be >= 1; got {slabs}")
    if max_memory:
        parse_size(max_memory)
    if pieces:
        raise CfmInputError("--slabs/--max-memory cannot be combined with --pieces (slabs are "
                            "written as pieces already)")  # fmt: skip
    if region is not None:
        raise CfmInputError("--region cannot be combined with --slabs/--max-memory (the "
                            "out-of-core run summarises every node); leave one out")  # fmt: skip


def _say(log, text: str) -> None:
    if log is not None:
        log(text)


@dataclass
class _Job:
    """The options of one sweep, as `run_sweep` received them."""

    field: object
    cfg: object
    bench_spec: object
    reader: dict
    out_dir: object
    pieces: object
    resume: bool
    keep_chunks: bool
    scheduler: object
    workers: object
    slabs: object
    max_memory: object
    table: object
    report: bool
    command_line: object
    progress: object
    on_start: object
    log: object
    bench_sentence: object


#: Plain trials per node when ``trials`` is not given (the adaptive estimator's nodes aside).
DEFAULT_TRIALS = 10_000


def run_sweep(field, up_um=(0, 10, 20, 30, 40, 50), *, trials: int | None = None, seed: int = 0,
              mode: str = "gauss", bench=None, axis_scale=None, b_ref_T=None,
              interpolation: str = "auto", chunk_nodes: int = 20000, outside: str = "exclude",
              hull_slivers: str = "remove", field_model: str = "auto", region=None, reader=None,
              out_dir=None, pieces=None, resume: bool = False, keep_chunks: bool = False,
              scheduler=None, workers=None, slabs=None, max_memory=None, table=None,
              report: bool = True, command_line=None, progress=None, on_start=None,
              log=None) -> SweepRun:  # fmt: skip
    """U_f maps of a field map for a sweep of U_p (``cfm-fem sweep``).

    Parameters
    ----------
    field : path-like or FieldMap
    up_um : sequence of float, um
        U_p values (mode gauss).
    trials : int or None
        Plain Monte Carlo with this many trials per node and U_p. None (default): the adaptive
        estimator at the nodes under a harmonic model in mode gauss (`SweepConfig.estimator`),
        `DEFAULT_TRIALS` plain trials at the others.
    seed : int
    mode : {"gauss", "htm"}
    bench : Bench, path-like or None
        Mode htm: the bench (None: the packaged CFM reference bench).
    axis_scale, b_ref_T, interpolation, chunk_nodes, outside, hull_slivers, field_model
        `cfm_fem.models.sweep.SweepConfig` fields.
    region : Region or str, optional
        Region of interest (``"cylinder:7,-30:30"``).
    reader : dict, optional
        Keyword arguments of `cfm_fem.io.read_field`.
    out_dir : path-like, optional
        Write the outputs there; needed by ``pieces``, ``resume``, ``slabs``, ``max_memory``
        and ``table``. The caller holds its lock (`cfm_fem.io.lock.output_lock`).
    pieces, resume, keep_chunks, scheduler, workers, slabs, max_memory, table, report
        As the command line's options.
    command_line : str, optional
        For the provenance.
    progress : callable(int), optional
        Called with the nodes finished.
    on_start : callable(str, int or None, str), optional
        Called once the map is read: a line naming the run, the nodes to come, ``"nodes"``.
    log : callable(str), optional
        Messages for the user (outputs of an earlier run removed, chunks resumed or kept).

    Returns
    -------
    SweepRun
    """
    from ...models.region import parse_region
    from ...models.sweep import SweepConfig

    up = [float(u) for u in up_um]
    estimator = "adaptive" if trials is None else "plain"
    trials = DEFAULT_TRIALS if trials is None else trials
    if isinstance(region, str):
        region = parse_region(region)
    check_options(up_um=up, trials=trials, seed=seed, mode=mode, bench=bench,
                  axis_scale=axis_scale, b_ref_T=b_ref_T, chunk_nodes=chunk_nodes, pieces=pieces,
                  scheduler=scheduler, workers=workers, slabs=slabs, max_memory=max_memory,
                  region=region, table=table, up_given=False)  # fmt: skip
    needs_out = [o for o, v in (("pieces", pieces), ("resume", resume), ("slabs", slabs),
                                ("max_memory", max_memory), ("table", table)) if v]  # fmt: skip
    if out_dir is None and needs_out:
        raise CfmInputError(f"{', '.join(needs_out)} need an output folder (out_dir=)")
    model, sentence = choose_bench(bench) if mode == "htm" else (None, None)
    cfg = SweepConfig(up_um=up, trials=int(trials), seed=int(seed),
                      axis_scale=tuple(axis_scale or (1.0, 1.0, 1.0)), b_ref_T=b_ref_T,
                      interpolation=interpolation, mode=mode, bench=model,
                      chunk_nodes=chunk_nodes, outside=outside, hull_slivers=hull_slivers,
                      field_model=field_model, region=region,
                      estimator=estimator)  # fmt: skip
    job = _Job(field, cfg, bench, dict(reader or {}), out_dir, pieces, resume, keep_chunks,
               scheduler, workers, slabs, max_memory, table, report, command_line, progress,
               on_start, log, sentence)  # fmt: skip
    if out_dir is None:
        return _in_memory(job)
    fm = None
    if slabs is not None or max_memory is not None:  # out of core
        done, fm = _run_slabs(job)  # fm: a map that is not 3-D, read while staging
        if done is not None:
            return done
        job.pieces = job.pieces or slabs or 8  # read whole: statistics still by pieces
    return _on_disk(job, fm)


def _trials(cfg) -> str:
    """'10000 trials per node', or the adaptive estimator's range."""
    if cfg.estimator == "adaptive" and cfg.mode == "gauss":
        from ...models.sweep import ADAPTIVE_PLAN

        return (f"{ADAPTIVE_PLAN[0]} to {ADAPTIVE_PLAN[1]} trials per node as U_f's precision "
                f"needs ({cfg.trials} where the plain Monte Carlo runs)")  # fmt: skip
    return f"{cfg.trials} trials per node"


def _what(job) -> str:
    cfg = job.cfg
    if cfg.mode == "gauss":
        return f"U_p = {', '.join(f'{u:g}' for u in cfg.up_um)} um"
    return "mode htm: " + job.bench_sentence


def _in_memory(job) -> SweepRun:
    """The sweep in memory, nothing written."""
    from ...models.sweep import summarize
    from .in_memory import run_sweep as run

    fm = field_map(job.field, job.reader)
    _started(job, fm)
    with _dask(job) as mapper:
        res = run(fm, job.cfg, progress=job.progress, map_chunks=mapper)
    return SweepRun(res, summarize(res))


def _started(job, fm) -> None:
    if job.on_start is not None:
        cfg = job.cfg
        job.on_start(f"{fm.n_nodes} nodes from {fm.source}; {_what(job)}; {_trials(cfg)}, "
                     f"seed {cfg.seed}", fm.n_nodes, "nodes")  # fmt: skip


class _dask:
    """Context of the chunk mapper: None in this process, else the Dask client's."""

    def __init__(self, job, runner=None):
        self.job, self.runner, self.cm = job, runner, None

    def __enter__(self):
        from .distributed import dask_chunk_map, dask_client

        self.cm = dask_client(self.job.scheduler, self.job.workers)
        client = self.cm.__enter__()
        mapper = None if client is None else dask_chunk_map(client)
        return mapper if self.runner is None else self.runner.mapper(mapper)

    def __exit__(self, *exc):
        return self.cm.__exit__(*exc)


def _provenance(job, bench_entry, **extra) -> dict:
    from ...io.provenance import provenance

    field = job.field if not hasattr(job.field, "points") else None
    prov = provenance({"field": field, "bench": bench_entry}, job.command_line)
    prov.update(seed=job.cfg.seed, trials=job.cfg.trials, **extra)
    return prov


def _field_sha(field):
    from ...io.provenance import file_sha256

    return file_sha256(field) if not hasattr(field, "points") else None


def _on_disk(job, fm) -> SweepRun:
    """The sweep in this process or on Dask, resumable, written into ``job.out_dir``."""
    from concurrent import futures

    import numba

    from ...errors import interrupted
    from ...io.sweep_out import encode_shared, write_sweep, write_sweep_pieces
    from .in_memory import run_sweep as run
    from .pieces import run_sweep_pieces
    from .problem import chunk_ranges
    from .resume import ResumableRun, describe_sweep

    cfg, out = job.cfg, job.out_dir
    if fm is None:
        fm = field_map(job.field, job.reader)
    _started(job, fm)
    # the bench used, the packaged one included: a default-bench run and one given a copy of
    # the same file have the same key (same numbers), and both name the file they used
    bench_entry = bench_provenance(job.bench_spec) if cfg.mode == "htm" else None
    bench_sha = bench_entry and bench_entry.get("sha256")
    description = describe_sweep(cfg, _field_sha(job.field), job.reader, bench_sha)
    runner = ResumableRun(out, description, resume=job.resume)
    runner.check()  # a store made by another run: refuse before any work
    if not job.resume and runner.store.completed():
        _say(job.log, f"{len(runner.store.completed())} chunk(s) of an earlier run in "
                      f"{runner.store.path} are discarded (add --resume to continue that run "
                      "instead)")  # fmt: skip
    try:
        with _dask(job, runner) as mapper:
            if job.pieces:
                res = run_sweep_pieces(fm, cfg, mapper, progress=job.progress)
            else:
                res = run(fm, cfg, progress=_preloading_report(job), map_chunks=mapper)
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted(exc):
            raise
        if runner.store.completed():
            _say(job.log, f"{len(runner.store.completed())} finished chunk(s) kept in "
                          f"{runner.store.path}; run the same command with --resume to "
                          "continue")  # fmt: skip
        raise KeyboardInterrupt from None  # numba wraps a Ctrl-C in a SystemError
    if job.resume:
        rejected = (f" ({runner.rejected} unreadable chunk file(s) recomputed)"
                    if runner.rejected else "")  # fmt: skip
        _say(job.log, f"resumed: {runner.loaded} chunk(s) read from {runner.store.path}, "
                      f"{runner.computed} computed{rejected}")  # fmt: skip
    prov = _provenance(job, bench_entry, run_key=runner.key,
                       backend=backend_description(job.scheduler, job.workers),
                       resumed_chunks=runner.loaded)  # fmt: skip
    res.mesh = res.mesh.for_output()  # point location is done: its arrays are freed here
    drawn = None  # the report's files, when drawn beside the maps
    if job.pieces:
        chunks = chunk_ranges(fm.n_nodes, cfg.chunk_nodes)
        summary = write_sweep_pieces(out, res, job.pieces,
                                     lambda nodes: runner.gather(nodes, chunks), prov,
                                     remove_stale=False)  # fmt: skip
    else:
        # the maps' shared arrays first: their compressing threads would wait for the GIL
        # that the figures' thread holds
        encoded = encode_shared(res)
        summary, drawing = _report_ahead(job, res, prov)
        # the figures' thread takes one core of the map writers' until it is done
        writers = None if drawing is None else max(1, numba.get_num_threads() - 1)
        try:
            summary = write_sweep(out, res, prov, remove_stale=False, summary=summary,
                                  writers=writers, widen_after=drawing,
                                  encoded=encoded)  # fmt: skip
        except BaseException:  # the write's error, once the figures' thread has ended
            if drawing is not None:
                futures.wait([drawing])
            raise
        drawn = drawing and drawing.result()
    _remove_stale_maps(out, job.log)  # the new outputs are complete: now the old maps can go
    written = _finish(job, runner, res, drawn)
    return SweepRun(res, summary, written)


def _preloading_report(job):
    """``job.progress``, which also starts importing the report's modules on a thread once the
    first chunk is done, when the run writes a report.

    Importing matplotlib takes about 0.35 s and holds the GIL. While the kernels run, the
    GIL is free (numba releases it) and the import only shares a core with them; after
    them, it would delay the figures' thread, the last to finish."""
    if not job.report:
        return job.progress
    started = []

    def progress(n_done):
        if not started:
            started.append(threading.Thread(target=_import_report, name="cfm_fem report import",
                                            daemon=True))  # fmt: skip
            started[0].start()
        if job.progress is not None:
            job.progress(n_done)

    return progress


def _import_report() -> None:
    """Import the report's drawing modules; a failure is left to the drawing itself."""
    with contextlib.suppress(Exception):
        import_module("...report.sweep", __package__)


def _report_ahead(job, res, prov):
    """The summary `write_sweep` writes, and (when the run writes a report) a future of the
    report's files drawn from it on a thread, beside the map writers (`draw_sweep_report`):
    matplotlib holds the GIL, VTK writes without it."""
    import json
    from concurrent.futures import ThreadPoolExecutor

    from ...io._atomic import json_text
    from ...models.sweep import summarize

    summary = summarize(res)
    if not job.report:
        return summary, None
    document = json.loads(json_text({**summary, "provenance": prov}))  # as read back

    def draw():
        from ...report.sweep import draw_sweep_report  # matplotlib: loaded only when used

        return draw_sweep_report(document, res)

    pool = ThreadPoolExecutor(1)
    drawing = pool.submit(draw)
    pool.shutdown(wait=False)  # the thread ends with its one task
    return summary, drawing


def _run_slabs(job):
    """Dispatch of ``slabs`` / ``max_memory``: (the run, None), or (None, the map or None)
    when the map must be run in memory (a map that is not 3-D comes back as read while
    staging: the file is read, and its warnings given, once)."""
    from ...errors import interrupted
    from ...io.streaming import is_streamable
    from .distributed import dask_chunk_map, dask_client
    from .resume import describe_sweep
    from .slabs import SLAB_WORK, run_slab_sweep

    cfg, out, reader = job.cfg, job.out_dir, job.reader
    budget = parse_size(job.max_memory) if job.max_memory else None
    kind = None if hasattr(job.field, "points") else is_streamable(job.field, reader.get("fmt"))
    if kind is not None:  # the streaming readers bypass read_field: refuse its way
        from ...io import check_solution

        check_solution(job.field, kind, reader.get("solution"))
    if kind is None:
        _say(job.log, f"{job.field} is not a plain or Opera table: it is read whole (not "
                      "streamed) and the statistics are written as pieces")  # fmt: skip
        return None, None
    bench_entry = bench_provenance(job.bench_spec) if cfg.mode == "htm" else None
    prov = _provenance(job, bench_entry, backend="this process, slabs (out of core)")
    if job.on_start is not None:
        job.on_start(f"streaming {job.field} ({kind}) into slabs; {_what(job)}; {_trials(cfg)}, "
                     f"seed {cfg.seed}", None, "nodes")  # fmt: skip
    description = describe_sweep(cfg, _field_sha(job.field), reader,
                                 bench_entry and bench_entry["sha256"])  # fmt: skip
    description.update(slabs=job.slabs, max_memory=job.max_memory)
    flat = []  # a map that is not 3-D, as staged (run in memory, not read again)
    total = None if job.on_start is None else (lambda n: job.on_start(None, n, "nodes"))
    try:
        with dask_client(job.scheduler, job.workers) as client:
            if client is not None:  # the workers map the staged rows in DIR: a shared folder
                where = backend_description(job.scheduler, job.workers)
                prov["backend"] = where + ", slabs (out of core)"
            summary = run_slab_sweep(
                job.field, cfg, out, n_slabs=job.slabs, max_memory=budget, fmt=kind,
                length_unit=reader.get("length_unit"), field_unit=reader.get("field_unit"),
                zero_rows=reader.get("zero_rows", "warn"), provenance=prov,
                log=lambda m: _say(job.log, m), progress=job.progress, progress_total=total,
                description=description, resume=job.resume, keep=job.keep_chunks,
                map_chunks=None if client is None else dask_chunk_map(client),
                flat_map=flat.append,
                remove_stale=False,  # removed below, and named
            )  # fmt: skip
    except (KeyboardInterrupt, SystemError) as exc:
        if not interrupted(exc):
            raise
        store = Path(out) / SLAB_WORK
        done = len(list(store.glob("results/slab*/done.json")))
        if done:
            _say(job.log, f"{done} finished slab(s) kept in {store}; run the same command "
                          "with --resume to continue")  # fmt: skip
        raise KeyboardInterrupt from None  # numba wraps a Ctrl-C in a SystemError
    if summary is None:
        _say(job.log, "the map is not 3-D: run in memory")
        return None, (flat[0] if flat else None)
    _remove_stale_maps(out, job.log)  # the new outputs are complete: now the old maps can go
    written = _finish(job)
    return SweepRun(None, summary, written), None


def _remove_stale_maps(out, log) -> None:
    """After a successful run: remove the maps of an earlier run in ``out`` that this run does
    not use (`cfm_fem.io.sweep_out.remove_stale_maps`: only files a sweep wrote), and the
    temporaries a killed run left (`cfm_fem.io.sweep_out.remove_leftover_temporaries`), and
    say so. The writers leave these to it (``remove_stale=False``): it names them."""
    from ...io.sweep_out import remove_earlier_outputs

    temps, removed, kept = remove_earlier_outputs(out)
    if temps:
        shown = ", ".join(temps[:3]) + (", ..." if len(temps) > 3 else "")
        _say(log, f"removed {len(temps)} leftover temporary file(s) of an interrupted run from "
                  f"{out}: {shown}")  # fmt: skip
    if removed:
        pieces, items = {}, []
        for r in removed:
            top, _, rest = r.partition("/")
            if not rest and not r.endswith("/"):
                items.append(top)
            elif rest:
                pieces[top] = pieces.get(top, 0) + 1
        for top, n in pieces.items():
            gone = f"{top}/" in removed
            items.append(f"{top}/ ({n} piece(s){', folder removed' if gone else ''})")
        n_files = sum(not r.endswith("/") for r in removed)
        listed = ", ".join(items)
        _say(log, f"removed {n_files} map file(s) of an earlier run from {out} that are not "
                  f"part of this run (sweep.pvd does not name them): {listed}")  # fmt: skip
    if kept:
        _say(log, f"note: left in {out}: {', '.join(kept)}: named like a map, but not part of "
                  "this run and not written by cfm-fem sweep")  # fmt: skip


def _finish(job, runner=None, result=None, drawn=None) -> list:
    """The per-node table, the report, once the maps, ``sweep.pvd`` and ``summary.json`` are
    written; the chunk store of ``runner`` goes after every output, so a run stopped before
    then resumes from it. ``result``: the sweep's result in memory, the report's figures drawn
    from it; ``drawn``: the report's files, drawn already (`_report_ahead`). Returns the files
    written."""
    from ...io.sweep_table import remove_stale_table, write_sweep_table

    out = Path(job.out_dir)
    gone = remove_stale_table(out, job.table)
    if gone:
        _say(job.log, f"removed {', '.join(gone)} of an earlier run from {out} (this run "
                      "writes no such table)")  # fmt: skip
    if job.table is not None:
        write_sweep_table(out, job.table)
    written = []
    if job.report:
        from ...report.sweep import write_sweep_report  # matplotlib: loaded only when used

        written = list(write_sweep_report(out, result=result, drawn=drawn) or [])
    if runner is not None:
        runner.finish(keep=job.keep_chunks)
    return written
