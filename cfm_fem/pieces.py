"""A sweep kept by pieces: the full statistics never sit in memory at once.

`run_sweep_pieces` runs the chunks like `cfm_fem.sweep.run_sweep` but keeps, per node, only
what the summary needs (U_f, the complete flag, the GUM-S1 disagreement flags and the outside
counts: about 21 bytes per node and U_p value instead of about 224); the full statistics of each
chunk go to the chunk store on disk. `piece_result` then rebuilds the full `SweepResult` of one
piece of the mesh at a time, for writing (`cfm_fem.io.sweep_out.write_sweep_pieces`).

What is bounded: the per-node statistics and the output arrays (one piece and one chunk at a
time). What is not: the field map, the interpolation mesh and the node gradients (O(n), needed by
every chunk), and the compact per-node summary arrays above.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .errors import CfmInputError
from .field import FieldMap
from .sweep import (
    HTM_PARTS,
    SweepConfig,
    SweepResult,
    _gum_u,
    chunk_ranges,
    node_gradients,
    prepare_sweep,
)

__all__ = ["CompactSweep", "run_sweep_pieces", "partition", "piece_result"]


@dataclass
class CompactSweep(SweepResult):
    """A `SweepResult` without the full statistics, for `cfm_fem.sweep.summarize`.

    ``uf_units``, ``complete`` and the GUM-S1 flags of ``gum_check`` are kept per node;
    ``stats`` is a read-only view of shape (n, n_col, 4, 6) in which every entry of a node and
    column holds the standard uncertainty of |B| (``stats[..., 3, 1]`` is exact, the other
    entries are not statistics); ``gum_u`` is None. `tests/test_pieces.py` checks that the
    summary equals that of the full result.
    """

    uf: np.ndarray | None = None
    complete_: np.ndarray | None = None
    disagree: np.ndarray | None = None
    #: Mode htm: U_p of each column (RMS over the reachable nodes of the 3-D probe position
    #: error, as `SweepResult.column_up_um` computes it from the full ``positioning``), um.
    up_columns: list[float] | None = None

    def column_up_um(self) -> list[float]:
        """U_p of each column, um (see `cfm_fem.sweep.SweepResult.column_up_um`)."""
        if self.up_columns is not None:
            return list(self.up_columns)
        return super().column_up_um()

    def uf_units(self) -> np.ndarray:
        """U_f per node and column, units, shape (n, n_col)."""
        return self.uf

    def complete(self) -> np.ndarray:
        """Nodes whose every trial stayed inside the map, shape (n, n_col), bool."""
        return self.complete_

    def gum_check(self, column: int | None = None):
        """(None, None, disagree): only the flags are kept, shape (n, n_col, 4), bool."""
        return None, None, (self.disagree if column is None else self.disagree[:, column])


def _sigma_mm(problem):
    """Per-axis standard deviation of the gauss perturbation, shape (1, n_up, 3), mm."""
    return (problem.scales_mm[:, None] * problem.axis_scale[None, :])[None]


def _part_result(compact, nodes, parts) -> SweepResult:
    """Full `SweepResult` of the nodes ``nodes`` from their chunk-result arrays ``parts``."""
    stats, n_out, n_lost, star = parts[:4]
    positioning = parts[4] if len(parts) > 4 and parts[4].shape[1] > 0 else None
    fm = compact.fieldmap
    sub = FieldMap(points=fm.points[nodes], B=fm.B[nodes], source=fm.source)
    grad = compact.gradient[nodes]
    sigma = compact.sigma_mm if positioning is None else positioning[:, :, 1]
    corr = None if positioning is None else positioning[:, :, 2]
    extra = {} if positioning is None else {"positioning": positioning}
    return SweepResult(
        fieldmap=sub,
        mesh=compact.mesh,
        config=compact.config,
        b_ref_T=compact.b_ref_T,
        stats=stats,
        n_outside=n_out,
        n_walk_failed=n_lost,
        linear_in_up=star,
        gradient=grad,
        gum_u=_gum_u(grad, sub.B, compact.b_ref_T, sigma, corr),
        seconds=0.0,
        **extra,
    )


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
        `cfm_fem.resume.ResumableRun.mapper`.
    progress : callable(int), optional

    Returns
    -------
    CompactSweep
        Gives exactly the summary of `run_sweep` on the same inputs.
    """
    t0 = time.perf_counter()
    mesh, problem, b_ref = prepare_sweep(fm, cfg)
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
        gradient=node_gradients(mesh, fm.B),
        gum_u=None,
        seconds=0.0,
        uf=np.full((n, n_col), np.nan),
        complete_=np.zeros((n, n_col), dtype=bool),
        disagree=np.zeros((n, n_col, 4), dtype=bool),
    )
    compact.sigma_mm = None if htm else _sigma_mm(problem)
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


def piece_bounds(n_nodes: int, n_pieces: int) -> np.ndarray:
    """Node ranges of the pieces of `partition`: piece k owns nodes ``bounds[k]:bounds[k + 1]``
    (and holds copies of lower nodes its cells use).

    Returns
    -------
    ndarray, shape (K + 1,), int64
        K = min(n_pieces, n_nodes), at least 1.
    """
    n_pieces = max(1, min(int(n_pieces), int(n_nodes)))
    return np.linspace(0, n_nodes, n_pieces + 1).round().astype(np.int64)


def partition(simplices: np.ndarray, n_nodes: int, n_pieces: int):
    """Split a mesh into pieces by node ranges; each cell goes to the piece of its last node.

    Parameters
    ----------
    simplices : ndarray, shape (m, k), int64
    n_nodes : int
    n_pieces : int
        At most this many pieces (fewer if there are fewer nodes).

    Yields
    ------
    nodes : ndarray, shape (p,), int64
        Sorted node indices of the piece: its own range and the nodes its cells use.
    cells : ndarray, shape (c, k), int64
        The piece's cells in local indices (into ``nodes``).
    """
    bounds = piece_bounds(n_nodes, n_pieces)
    n_pieces = len(bounds) - 1
    owner = np.searchsorted(bounds, simplices.max(axis=1), side="right") - 1
    for k in range(n_pieces):
        own = simplices[owner == k]
        nodes = np.union1d(np.arange(bounds[k], bounds[k + 1]), own.ravel())
        yield nodes, np.searchsorted(nodes, own)


def piece_result(compact: CompactSweep, nodes, parts) -> SweepResult:
    """Full `SweepResult` of the nodes ``nodes`` (a piece) from their chunk-result arrays.

    Parameters
    ----------
    compact : CompactSweep
    nodes : ndarray, shape (p,), int64
    parts : tuple
        The `cfm_fem.sweep.SweepProblem.run_chunk` arrays of those nodes (e.g. from
        `cfm_fem.resume.ResumableRun.gather`).

    Raises
    ------
    CfmInputError
        ``nodes`` is empty (a piece of `partition` never is).
    """
    nodes = np.asarray(nodes)
    if nodes.size == 0:
        raise CfmInputError("nodes is empty; expected the node indices of a piece (at least one)")
    return _part_result(compact, nodes, parts)
