"""A sweep kept by pieces: the full statistics never sit in memory at once.

`run_sweep_pieces` runs the chunks like `cfm_fem.workflows.sweep.in_memory.run_sweep` but keeps, per
node, only what the summary needs (U_f, the complete flag, the GUM-S1 disagreement flags and the
outside counts: about 21 bytes per node and U_p value instead of about 224); the full statistics of
each chunk go to the chunk store on disk. `piece_result` then rebuilds the full `SweepResult` of one
piece of the mesh at a time, for writing (`cfm_fem.io.sweep_out.write_sweep_pieces`).

What is bounded: the per-node statistics and the output arrays (one piece and one chunk at a
time). What is not: the field map, the interpolation mesh and the node gradients (O(n), needed by
every chunk), and the compact per-node summary arrays above.
"""

from __future__ import annotations

import time

import numpy as np

from ...models.field import FieldMap
from ...models.sweep import HTM_PARTS, CompactSweep, SweepConfig, _part_result
from .problem import chunk_ranges, field_fit_info, prepare_sweep, sweep_gradients, with_bench

__all__ = ["run_sweep_pieces"]


def run_sweep_pieces(fm: FieldMap, cfg: SweepConfig, mapper, progress=None) -> CompactSweep:
    """Run a sweep keeping only the per-node summary quantities in memory.

    Parameters
    ----------
    fm : FieldMap
    cfg : SweepConfig
        Mode ``gauss`` or ``htm`` (then the per-node probe-error mean and standard deviation
        are not kept, only |mean|^2 + |std|^2 per node and column, for the U_p of each column).
    mapper : callable(problem, chunks) -> iterable of ((start, stop), result)
        Must keep the full chunk results somewhere `piece_result` can read them back, e.g.
        `cfm_fem.workflows.sweep.resume.ResumableRun.mapper`.
    progress : callable(int), optional

    Returns
    -------
    CompactSweep
        Gives exactly the summary of `run_sweep` on the same inputs.
    """
    t0 = time.perf_counter()
    cfg = with_bench(cfg)
    mesh, problem, b_ref = prepare_sweep(fm, cfg, lazy=True)
    n = fm.n_nodes
    htm = cfg.mode == "htm"
    n_col = len(HTM_PARTS) if htm else len(cfg.up_um)
    compact = CompactSweep(
        fieldmap=fm,
        mesh=mesh,
        config=cfg,
        b_ref_T=b_ref,
        stats=None,
        n_outside=np.zeros((n, n_col), dtype=np.int32),
        n_walk_failed=np.zeros((n, n_col), dtype=np.int32),
        linear_in_up=np.zeros(n, dtype=bool),
        gradient=sweep_gradients(mesh, fm.B, problem.harmonic),
        gum_u=None,
        seconds=0.0,
        uf=np.full((n, n_col), np.nan),
        complete_=np.zeros((n, n_col), dtype=bool),
        disagree=np.zeros((n, n_col, 4), dtype=bool),
        field_fit=field_fit_info(problem.harmonic),
    )
    u_abs = np.full((n, n_col), np.nan)
    # htm: |mean|^2 + |std|^2 of the probe error per node and column, mm^2 (8 bytes per node
    # and column, kept so that the column U_p equals SweepResult.column_up_um bit for bit)
    e2 = np.full((n, n_col), np.nan) if htm else None
    done = np.zeros(n, dtype=bool)
    for (a, b), parts in mapper(problem, chunk_ranges(n, cfg.chunk_nodes)):
        part = _part_result(compact, np.arange(a, b), parts)
        u_abs[a:b] = part.stats[:, :, 3, 1]
        compact.uf[a:b] = part.uf_units()
        compact.complete_[a:b] = part.complete()
        compact.disagree[a:b] = part.gum_check()[2]
        compact.n_outside[a:b] = part.n_outside
        compact.n_walk_failed[a:b] = part.n_walk_failed
        compact.linear_in_up[a:b] = part.linear_in_up
        if htm:
            pos = part.positioning  # (k, n_col, 3, 3): mean, std (mm), correlations
            e2[a:b] = (pos[:, :, 0] ** 2).sum(-1) + (pos[:, :, 1] ** 2).sum(-1)
        done[a:b] = True
        if progress is not None:
            progress(b - a)
    if not done.all():
        raise RuntimeError(f"{int((~done).sum())} nodes were not computed by the chunk mapper")
    compact.stats = np.lib.stride_tricks.as_strided(
        u_abs, shape=(n, n_col, 4, 6), strides=u_abs.strides + (0, 0), writeable=False
    )
    if htm:
        compact.up_columns = [float(np.sqrt(np.nanmean(e2[:, k])) * 1e3) for k in range(n_col)]
    compact.seconds = time.perf_counter() - t0
    return compact
