"""The sweep in memory: every node's statistics of a map held at once (`run_sweep`)."""

from __future__ import annotations

import time

import numpy as np

from ...models.field import FieldMap
from ...models.mesh import SimplexMesh
from ...models.sweep import HTM_PARTS, SweepConfig, assemble_result
from .problem import (
    chunk_ranges,
    field_fit_info,
    prepare_sweep,
    serial_map,
    sweep_gradients,
    with_bench,
)

__all__ = ["run_sweep"]


def run_sweep(
    fm: FieldMap,
    cfg: SweepConfig,
    progress=None,
    mesh: SimplexMesh | None = None,
    map_chunks=None,
):
    """Run the Monte Carlo sweep over ``cfg.up_um`` for every node of ``fm``.

    Parameters
    ----------
    fm : FieldMap
    cfg : SweepConfig
    progress : callable(int), optional
        Called with the number of nodes finished after each chunk.
    mesh : SimplexMesh, optional
        Reuse a mesh built earlier (it must belong to ``fm``: `prepare_sweep` refuses one of
        another node count).
    map_chunks : callable(problem, chunks) -> iterable of ((start, stop), result), optional
        Runs the chunks (in any order, anywhere: a Dask cluster, a resumable store); default
        `serial_map`. Results are identical whatever runs them.

    Returns
    -------
    SweepResult
    """
    t0 = time.perf_counter()
    cfg = with_bench(cfg)
    mesh, problem, b_ref = prepare_sweep(fm, cfg, mesh, lazy=True)
    n = fm.n_nodes
    n_col = len(HTM_PARTS) if cfg.mode == "htm" else len(cfg.up_um)
    stats = np.full((n, n_col, 4, 6), np.nan)
    n_out = np.zeros((n, n_col), dtype=np.int64)
    n_lost = np.zeros((n, n_col), dtype=np.int64)
    star = np.zeros(n, dtype=bool)
    positioning = np.full((n, n_col, 3, 3), np.nan) if cfg.mode == "htm" else None
    done = np.zeros(n, dtype=bool)
    mapper = serial_map if map_chunks is None else map_chunks
    for (a, b), (s, o, lost, st, pos) in mapper(problem, chunk_ranges(n, cfg.chunk_nodes)):
        stats[a:b], n_out[a:b], n_lost[a:b], star[a:b] = s, o, lost, st
        if positioning is not None:
            positioning[a:b] = pos
        done[a:b] = True
        if progress is not None:
            progress(b - a)
    if not done.all():
        raise RuntimeError(f"{int((~done).sum())} nodes were not computed by the chunk mapper")
    fit = problem.harmonic
    # the kernels' own arrays (octant start cells, exact-search buckets and face excess: 0.4 GB
    # on a 1e6-node non-convex map) are done with: freed before the gradients' temporaries
    del problem
    gradient = sweep_gradients(mesh, fm.B, fit)
    parts = (stats, n_out, n_lost, star, positioning)
    return assemble_result(
        fm, mesh, cfg, b_ref, parts, gradient,
        seconds=time.perf_counter() - t0, field_fit=field_fit_info(fit),
    )  # fmt: skip
