"""Positioning-uncertainty sweep: per-node field uncertainty U_f of a map for a list of U_p values.

Paper eq. 16: x_meas = x_nom + N(0, U_p) per coordinate; the field is interpolated at x_meas and
B_meas - B_nom collected over the trials, per node, for each component and for |B|.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import _kernels
from .errors import CfmInputError, check_seed
from .field import FieldMap
from .interpolation import (
    SimplexMesh,
    build_mesh,
    coordinate_keys,
    exact_search,
    morton_order,
    no_search,
)
from .mc import numerical_tolerance
from .threads import map_blocks

__all__ = [
    "SweepProblem",
    "node_keys",
    "chunk_ranges",
    "serial_map",
    "prepare_sweep",
    "SweepConfig",
    "SweepResult",
    "run_sweep",
    "check_options",
    "summarize",
    "node_gradients",
    "edge_fit_gradients",
]

COMPONENTS = _kernels.COMPONENTS
STAT_NAMES = _kernels.STAT_NAMES
#: Columns of a mode-htm sweep: (include the 21 geometric errors, include vibration and delay).
HTM_PARTS = {
    "htm_total": (True, True),
    "htm_geometric": (True, False),
    "htm_vibration_delay": (False, True),
}
#: What happens to a trial whose perturbed position leaves the map (`SweepConfig.outside`).
OUTSIDE_RULES = {
    "exclude": "left out of the node's statistics (counted in outside_fraction); the node is "
    "incomplete and not in the U_f percentiles",
    "extrapolate": "given the node's first-order Taylor expansion B + grad B . delta (grad B: a "
    "least-squares fit over the edges of its cells, weighted by 1/length^2; counted in "
    "outside_fraction); the node keeps all its trials",
}
#: 97.5 % quantile of the standard normal: the GUM 95 % half-width is Z95 * u.
Z95 = 1.959963984540054


def up_label(up_um: float) -> str:
    """Column name of a U_p value, ``up<U_p>um`` (6 significant digits): it names the map
    (``uf_up20um.vtu``) and the summary column."""
    return f"up{up_um:g}um"


def check_up_distinct(up_um, option: str = "up_um") -> None:
    """Refuse U_p values that name the same map twice (``10,10``, or ``10,10.0000001``, which
    differ beyond the 6 digits of the name): the second map would overwrite the first.
    ``option`` names where they came from, for the message."""
    seen = {}
    for u in up_um:
        label = up_label(u)
        if label in seen:
            raise CfmInputError(
                f"{option}: U_p = {u:g} um appears twice ({seen[label]!r} and {u!r} both name "
                f"the map uf_{label}.vtu); expected distinct values"
            )
        seen[label] = u


@dataclass
class SweepConfig:
    """What to run.

    Attributes
    ----------
    up_um : list of float
        U_p values, um (standard deviation of each coordinate, paper eq. 16).
    trials : int
        Monte Carlo trials per node and U_p value.
    seed : int
    axis_scale : tuple of 3 float
        Per-axis multiplier of U_p (x, y, z); (1, 1, 1) is isotropic.
    b_ref_T : float or None
        Reference field for "units" (1e-4 B_ref); default max |B| over the map nodes.
    coverage : float
        Coverage probability of the intervals.
    interpolation : {"auto", "native", "grid", "delaunay"}
    mode : {"gauss", "htm"}
    bench : Bench or None
        Bench model for mode ``htm`` (`cfm_fem.bench.Bench`); None means the reference bench.
    chunk_nodes : int
        Nodes per chunk (progress granularity and memory; results do not depend on it).
    outside : {"exclude", "extrapolate"}
        Trials whose perturbed position leaves the map: left out of the node's statistics
        (the node is then incomplete), or given the node's first-order Taylor expansion
        B + grad B . delta (`edge_fit_gradients`). Counted in ``n_outside`` either way.
    hull_slivers : {"remove", "keep"}
        Delaunay maps: remove the flat cells of the convex hull (default) or keep them
        (`cfm_fem.interpolation.hull_sliver_cells`); trials in a removed cell are outside. Kept,
        they put U_f and the gradient (so the GUM figure) of the nodes on the hull far off.
    """

    up_um: list[float] = field(default_factory=lambda: [0.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    trials: int = 2000
    seed: int = 0
    axis_scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    b_ref_T: float | None = None
    coverage: float = 0.95
    interpolation: str = "auto"
    mode: str = "gauss"
    bench: object | None = None
    chunk_nodes: int = 20000
    outside: str = "exclude"
    hull_slivers: str = "remove"


@dataclass
class SweepResult:
    """Per-node statistics of a sweep.

    Attributes
    ----------
    fieldmap : FieldMap
    mesh : SimplexMesh
    config : SweepConfig
    b_ref_T : float
    stats : ndarray, shape (n, n_up, 4, 6), T
        Error B_meas - B_nom per node, U_p value, component (Bx, By, Bz, |B|) and statistic
        (mean, std, symmetric low/high, shortest low/high).
    n_outside : ndarray, shape (n, n_up), int64
    n_walk_failed : ndarray, shape (n, n_up), int64
        Trials without a value because their walk did not end: 0 (a walk that cycles, on a
        non-Delaunay native mesh, is settled by an exact search: `_kernels.settle_walk`).
    linear_in_up : ndarray, shape (n,), bool
        Every trial stayed in a cell incident to the node.
    gradient : ndarray, shape (n, 3, 3), T/mm
        ``gradient[i, c, j] = dB_c/dx_j`` at node i (volume-weighted over incident cells).
    gum_u : ndarray, shape (n, n_up, 4), T
        Linearised (GUM) standard uncertainty sqrt(g^T Sigma g), g the gradient of the
        component: Sigma = diag(U_p,j^2) in mode gauss; in mode htm the covariance of the
        node's probe error (its geometric part moves the probe along several axes at once).
    seconds : float
        Wall time of `run_sweep` (mesh, every chunk, gradients), all U_p values together.
    positioning : ndarray, shape (n, 3, 3, 3), or None
        Mode htm, per column (total, geometric, vibration and delay) and map axis: mean (mm),
        standard deviation (mm) and correlation coefficients xy, xz, yz of the probe position
        error (rows 0, 1, 2).
    n_left_out : ndarray, shape (n, n_up), int64, or None
        Trials whose position left the map and that are not in the statistics. None: all of
        ``n_outside`` with ``outside="exclude"``, none with ``"extrapolate"`` (the out-of-core
        run leaves out, also then, the trials of nodes whose walks reached a slab's halo).
    """

    fieldmap: FieldMap
    mesh: SimplexMesh
    config: SweepConfig
    b_ref_T: float
    stats: np.ndarray
    n_outside: np.ndarray
    n_walk_failed: np.ndarray
    linear_in_up: np.ndarray
    gradient: np.ndarray
    gum_u: np.ndarray
    seconds: float
    positioning: np.ndarray | None = None
    n_left_out: np.ndarray | None = None

    @property
    def gum_mean(self) -> np.ndarray:
        """Linearised (GUM) systematic error g . E[E_p] per node, column and component,
        shape (n, n_col, 4), T: zero in mode gauss, the gradient times the node's mean probe
        error in mode htm."""
        if self.positioning is None:
            return np.zeros(self.gum_u.shape)
        return _gum_mean(self.gradient, self.fieldmap.B, self.b_ref_T, self.positioning[:, :, 0])

    def left_out(self, cols=slice(None)) -> np.ndarray:
        """`n_left_out` (or its default) for the columns ``cols``, shape (n, ...)."""
        if self.n_left_out is not None:
            return self.n_left_out[:, cols]
        if self.config.outside == "extrapolate":
            return np.zeros_like(self.n_outside[:, cols])
        return self.n_outside[:, cols]

    @property
    def labels(self) -> list[str]:
        """Name of each column: ``up<U_p>um`` (gauss) or the `HTM_PARTS` names (htm)."""
        if self.config.mode == "htm":
            return list(HTM_PARTS)
        return [up_label(u) for u in self.config.up_um]

    def column_up_um(self) -> list[float]:
        """U_p of each column, um: the sweep values (gauss), or for htm the RMS over the
        reachable nodes of sqrt(|mean|^2 + |std|^2) of the 3-D probe position error."""
        if self.positioning is None:
            return [float(u) for u in self.config.up_um]
        m, sd = self.positioning[:, :, 0], self.positioning[:, :, 1]  # (n, n_col, 3)
        e2 = (m**2).sum(-1) + (sd**2).sum(-1)
        return [float(np.sqrt(np.nanmean(e2[:, k])) * 1e3) for k in range(e2.shape[1])]

    def to_units(self, x):
        """Convert T to units of 1e-4 B_ref."""
        return np.asarray(x) / self.b_ref_T * 1e4

    def expanded_95(self, column: int | None = None) -> np.ndarray:
        """Symmetric 95 % expanded uncertainty max(|low|, |high|), T.

        Shape (n, n_col, 4), or (n, 4) for one ``column`` (less memory on large maps).
        """
        st = self.stats if column is None else self.stats[:, column]
        return np.maximum(np.abs(st[..., 2]), np.abs(st[..., 3]))

    def uf_units(self) -> np.ndarray:
        """U_f of each node: 95 % expanded uncertainty of |B| in units, shape (n, n_up)."""
        st = self.stats[:, :, 3]  # |B| only: `expanded_95` of every component took 0.6 GB
        # of temporaries on a 1e6-node map with 6 U_p values, the peak of the run
        return self.to_units(np.maximum(np.abs(st[..., 2]), np.abs(st[..., 3])))

    def complete(self) -> np.ndarray:
        """Nodes whose every trial has a value (stayed inside the map, or was extrapolated with
        ``outside="extrapolate"``), shape (n, n_up), bool."""
        return (
            (self.left_out() == 0) & (self.n_walk_failed == 0) & np.isfinite(self.stats[..., 3, 1])
        )

    def gum_check(self, column: int | None = None):
        """GUM-S1 section 8 comparison of the GUM interval y +- Z95*u_GUM with Monte Carlo
        (y = `gum_mean`: 0 in mode gauss).

        The tolerance is delta (JCGM 101 7.9.2, two significant digits of u), widened to three
        times the Monte Carlo standard error of a 2.5 % quantile where that is larger (fixed
        trial counts cannot resolve differences below their own noise).

        Returns
        -------
        d_max : ndarray, shape (n, n_col, 4), T
            max(d_low, d_high); shape (n, 4) for one ``column``.
        tol : ndarray, same shape, T
        disagree : ndarray, same shape, bool
        """
        cols = slice(None) if column is None else column
        st = self.stats[:, cols]
        gum_u = self.gum_u[:, cols]
        u_mc = st[..., 1]
        lo, hi = st[..., 2], st[..., 3]
        U = Z95 * gum_u
        y = self.gum_mean[:, cols]
        d_max = np.maximum(np.abs(y - U - lo), np.abs(y + U - hi))
        n = self.config.trials - self.left_out(cols) - self.n_walk_failed[:, cols]
        # standard error of the 2.5 % quantile of a normal: sqrt(p(1-p)/N) / phi(z)
        se = np.sqrt(0.025 * 0.975 / np.maximum(n, 1))[..., None] / 0.05844 * u_mc
        tol = np.maximum(numerical_tolerance(u_mc), 3.0 * se)
        with np.errstate(invalid="ignore"):
            # where the linearisation does not exist (|B| = 0) the GUM cannot give the result
            disagree = (d_max > tol) | (np.isnan(gum_u) & np.isfinite(u_mc) & (u_mc > 0))
        return d_max, tol, disagree


def node_gradients(mesh: SimplexMesh, B: np.ndarray) -> np.ndarray:
    """Gradient of the piecewise-linear field at each node, volume-weighted over incident cells.

    Parameters
    ----------
    mesh : SimplexMesh
    B : ndarray, shape (n, 3), T

    Returns
    -------
    ndarray, shape (n, 3, 3), T/mm
        ``[i, c, j] = dB_c/dx_j`` in the map frame (zero along the normal of a planar map).
    """
    acc, wsum = _kernels.cell_gradient_sums(
        mesh.simplices, mesh.transform, np.ascontiguousarray(B, dtype=np.float64), len(mesh.coords)
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        acc /= wsum[:, None, None]
    return acc @ mesh.basis.T  # local -> map frame


def edge_fit_gradients(mesh: SimplexMesh, B: np.ndarray, cells_per_block: int = 1 << 18):
    """Gradient at each node by a least-squares fit of B_j - B_i = G (x_j - x_i) over the edges
    of its cells, each edge weighted by 1/|x_j - x_i|^2 (and counted once per cell); mesh frame.

    Exact for a linear field. Unlike the cell average of `node_gradients` it does not lean on
    the shape of the cells: a flat cell (the Delaunay hull of scattered nodes has many) has a
    gradient far off the field's, but its edges still sample the field. Cells are taken in
    blocks of ``cells_per_block``: memory O(nodes + block).

    Returns
    -------
    ndarray, shape (n, 3, d), T/mm
        NaN at nodes whose edges do not span d dimensions (nodes in no cell).
    """
    d, n = mesh.dim, len(mesh.coords)
    B = np.asarray(B, dtype=np.float64)
    i, j = np.triu_indices(d + 1, 1)
    normal = np.zeros((n, d, d))
    rhs = np.zeros((n, d, 3))
    for c0 in range(0, len(mesh.simplices), cells_per_block):
        simp = mesh.simplices[c0 : c0 + cells_per_block]
        a, b = simp[:, i].ravel(), simp[:, j].ravel()
        dx = mesh.coords[b] - mesh.coords[a]  # (m, d)
        df = B[b] - B[a]  # (m, 3)
        w = 1.0 / np.einsum("mk,mk->m", dx, dx)
        for k in range(d):  # both ends: (x_j - x_i) and (B_j - B_i) flip sign together
            for m in range(d):
                v = w * dx[:, k] * dx[:, m]
                normal[:, k, m] += np.bincount(a, v, n) + np.bincount(b, v, n)
            for c in range(3):
                v = w * dx[:, k] * df[:, c]
                rhs[:, k, c] += np.bincount(a, v, n) + np.bincount(b, v, n)
    scale = np.trace(normal, axis1=1, axis2=2)
    ok = np.abs(np.linalg.det(normal)) > 1e-12 * np.maximum(scale, 1e-300) ** d
    grad = np.full((n, 3, d), np.nan)
    grad[ok] = np.linalg.solve(normal[ok], rhs[ok]).transpose(0, 2, 1)
    return grad


def _gradients4(gradient, B, b_ref):
    """Gradients of Bx, By, Bz and |B| per node, shape (n, 4, 3), T/mm (|B|'s NaN where
    |B| < 1e-12 ``b_ref``: not differentiable there). ``b_ref`` (T) is the run's B_ref, not the
    largest |B| of ``B``, so that a slab or piece of the map marks the nodes the whole map does."""
    absb = np.sqrt((B**2).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        grad_abs = np.einsum("nc,ncj->nj", B, gradient) / absb[:, None]
    grad_abs[absb < 1e-12 * max(b_ref, 1e-300)] = np.nan
    return np.concatenate([gradient, grad_abs[:, None, :]], axis=1)


def _gum_u(gradient, B, b_ref, sigma_mm, corr=None, block: int = 1 << 16):
    """Linearised standard uncertainty per node, column and component; shape (n, n_col, 4).

    ``b_ref``: B_ref of the run, T (`_gradients4`). ``sigma_mm`` (1 or n, n_col, 3): standard
    deviation of the probe position per map axis;
    ``corr`` (n, n_col, 3), optional: its correlation coefficients xy, xz, yz (mode htm).
    Nodes are taken ``block`` at a time (each node's arithmetic is the same whatever the
    block): the temporaries of the whole map at once took 0.7 GB on a 1e6-node map with 6
    columns, the peak of the run.
    """
    g4 = _gradients4(gradient, B, b_ref)
    n = len(B)
    sig_all = np.broadcast_to(sigma_mm, (n, *sigma_mm.shape[1:]))
    out = np.empty((n, sigma_mm.shape[1], 4))
    for i0 in range(0, n, block):
        g, sig = g4[i0 : i0 + block], sig_all[i0 : i0 + block]
        var = np.einsum("ncj,nkj->nkc", g**2, sig**2)
        if corr is not None:  # + 2 sum_{a<b} g_a g_b rho_ab sigma_a sigma_b
            for j, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
                w = corr[i0 : i0 + block, :, j] * sig[:, :, a] * sig[:, :, b]  # (k, n_col)
                var = var + 2.0 * (g[:, None, :, a] * g[:, None, :, b]) * w[:, :, None]
        np.sqrt(np.maximum(var, 0.0), out=out[i0 : i0 + block])
    return out


def _gum_mean(gradient, B, b_ref, mean_mm):
    """Linearised systematic error g . mean per node, column and component, shape
    (n, n_col, 4), T; ``mean_mm`` (n, n_col, 3): mean probe position error per map axis."""
    return np.einsum("ncj,nkj->nkc", _gradients4(gradient, B, b_ref), mean_mm)


def check_options(trials: int, axis_scale, b_ref_T: float | None) -> None:
    """The checks of a `SweepConfig` that need no map: the command line runs them before it
    reads the map (which can take minutes), `_check_config` again for a Python caller.

    Raises
    ------
    CfmInputError
        ``trials`` < 20, an axis scale negative, not finite or all 0, ``b_ref_T`` not > 0.
    """
    if trials < 20:
        raise CfmInputError(f"--trials must be at least 20 for a 95 % interval; got {trials}")
    if any(not np.isfinite(a) or a < 0 for a in axis_scale) or max(axis_scale) == 0:
        raise CfmInputError(f"axis scale must be finite, >= 0 and not all 0; got {axis_scale}")
    if b_ref_T is not None and not (np.isfinite(b_ref_T) and b_ref_T > 0):
        raise CfmInputError(f"B_ref must be a positive field in T; got {b_ref_T}")


def _check_config(cfg: SweepConfig, fm: FieldMap, mesh: SimplexMesh):
    if cfg.mode not in ("gauss", "htm"):
        raise CfmInputError(f"--mode must be gauss or htm; got {cfg.mode!r}")
    check_options(cfg.trials, cfg.axis_scale, cfg.b_ref_T)
    if not 0.5 < cfg.coverage < 1.0:
        raise CfmInputError(f"coverage must be in (0.5, 1); got {cfg.coverage}")
    if cfg.outside not in OUTSIDE_RULES:
        raise CfmInputError(f"--outside must be exclude or extrapolate; got {cfg.outside!r}")
    check_seed(cfg.seed)  # the CLI's rule and message (numba takes the seed as int64)
    if cfg.mode == "htm":
        return
    check_up_distinct(cfg.up_um)
    extent = np.ptp(mesh.coords, axis=0).min()  # smallest in-plane / in-volume extent, mm
    up_max_mm = max(cfg.up_um) * 1e-3 * max(cfg.axis_scale)
    if up_max_mm * 5.0 > extent:
        raise CfmInputError(
            f"U_p of {max(cfg.up_um):g} um is too large for this map: 5 U_p exceeds its smallest "
            f"extent of {extent:g} mm, so most perturbed points would leave the map",
            file=fm.source,
        )


@dataclass
class SweepProblem:
    """Everything needed to run any chunk of nodes of a sweep: read-only and picklable.

    A chunk's result depends only on the node indices, never on which process computes it or in
    which order, so chunks can be spread over threads, processes or a Dask cluster and merged
    exactly (see `run_sweep`'s ``map_chunks``).
    """

    coords: np.ndarray
    values: np.ndarray
    simplices: np.ndarray
    transform: np.ndarray
    neighbors: np.ndarray
    start_cells: np.ndarray
    basis: np.ndarray
    axis_scale: np.ndarray
    scales_mm: np.ndarray
    trials: int
    seed: int
    coverage: float
    htm: dict | None = None  # mode htm: bench arrays (see `_htm_arrays`)
    # outside="extrapolate": `edge_fit_gradients` (n, 3, d), mesh frame; else (0, 3, d)
    exit_grad: np.ndarray | None = None
    # non-convex mesh: face excess and cell buckets (`exact_search`); None: convex (empty)
    search: tuple | None = None
    # random-stream key of each node (`node_keys`); None: the node's row
    keys: np.ndarray | None = None

    def search_arrays(self) -> tuple:
        """The kernels' ``search`` argument (`cfm_fem.interpolation.exact_search`)."""
        return no_search(self.coords.shape[1]) if self.search is None else self.search

    def run_chunk(self, start: int, stop: int):
        """Statistics of nodes ``start .. stop-1``.

        Returns
        -------
        stats : ndarray, shape (k, n_col, 4, 6), T
            n_col = number of U_p values (gauss) or 3 (htm: total, geometric, vibration+delay).
        n_outside, n_walk_failed : ndarray, shape (k, n_col), int64
        linear_in_up : ndarray, shape (k,), bool
        positioning : ndarray, shape (k, n_col, 3, 3) (htm) or (k, 0, 3, 3) (gauss)
            Mean (mm), standard deviation (mm) and correlations xy, xz, yz of the probe
            position error per map axis (`SweepResult.positioning`).
        """
        return self.run_nodes(np.arange(start, stop, dtype=np.int64))

    def run_nodes(self, nodes, keys=None):
        """Statistics of any list of nodes, in that order (see `run_chunk`).

        Parameters
        ----------
        nodes : ndarray, shape (k,), int64
            Rows of this problem's arrays.
        keys : ndarray, shape (k,), int64, optional
            Random-stream id of each node (default: the problem's `node_keys` of these nodes,
            or ``nodes`` if it has none).
        """
        nodes = np.asarray(nodes, dtype=np.int64)
        if keys is None:
            keys = nodes if self.keys is None else self.keys[nodes]
        keys = np.asarray(keys, dtype=np.int64)
        if self.htm is not None:
            return self._run_htm(nodes, keys)
        # visit the nodes along a Z-order curve (neighbours share cells that are then in cache);
        # each node's numbers depend on its key only, so the order changes no result
        order = morton_order(self.coords[nodes])
        nodes, keys = nodes[order], keys[order]
        search = self.search_arrays()

        def block(i0, i1):
            return _kernels.gauss_sweep(
                nodes[i0:i1], keys[i0:i1], self.coords, self.values, self.simplices,
                self.transform, self.neighbors, self.start_cells, self.basis, self.axis_scale,
                self.scales_mm, int(self.trials), int(self.seed), float(self.coverage),
                self.exit_grad, search,
            )  # fmt: skip

        s, o, lost, star = map_blocks(block, len(nodes), 32)
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        return s[back], o[back], lost[back], star[back], np.empty((len(nodes), 0, 3, 3))

    def _run_htm(self, nodes, keys):
        h = self.htm
        search = self.search_arrays()
        parts = []
        for geo, noise in HTM_PARTS.values():

            def block(i0, i1, geo=geo, noise=noise):
                return _kernels.htm_sweep(
                    nodes[i0:i1], keys[i0:i1], self.coords, self.values, self.simplices,
                    self.transform, self.neighbors, self.start_cells, self.basis, h["rot"],
                    h["q_nodes"], h["params"], h["terms" if geo else "terms_zero"], geo, noise,
                    h["nkey"], h["fkey"], h["sig"], h["speed"], h["tau_code"], h["tau_par"],
                    h["stack"], h["mounts"], h["tool"],
                    h["strokes"], h["profiles"], float(self.coverage), self.exit_grad, search,
                )  # fmt: skip

            parts.append(map_blocks(block, len(nodes), 16))
        stats, n_out, n_lost, pos = (np.concatenate(x, axis=1) for x in zip(*parts, strict=True))
        pos = pos.reshape(len(nodes), len(HTM_PARTS), 3, 3)
        return stats, n_out, n_lost, np.zeros(len(nodes), dtype=bool), pos


def chunk_ranges(n: int, chunk_nodes: int) -> list[tuple[int, int]]:
    """Node ranges [start, stop) of at most ``chunk_nodes`` nodes covering 0 .. n-1."""
    return [(a, min(a + chunk_nodes, n)) for a in range(0, n, chunk_nodes)]


def serial_map(problem: SweepProblem, chunks):
    """Run chunks one after the other in this process (numba threads inside each chunk)."""
    for a, b in chunks:
        yield (a, b), problem.run_chunk(a, b)


def prepare_sweep(fm: FieldMap, cfg: SweepConfig, mesh: SimplexMesh | None = None):
    """Check the configuration and build the mesh and the `SweepProblem`.

    Returns
    -------
    mesh : SimplexMesh
    problem : SweepProblem
    b_ref : float, T

    Raises
    ------
    CfmInputError
        A map without nodes (a `FieldMap` made without `FieldMap.from_arrays`), a ``mesh``
        whose node count is not the map's, or a bad ``cfg`` (`check_options` and more).
    """
    if fm.n_nodes == 0:  # a mesh given: build_mesh, which refuses it, is not called
        raise CfmInputError(
            "the map has 0 node(s); expected at least 4 non-coplanar nodes (or 3 in a plane)",
            file=fm.source,
        )
    if mesh is not None and len(mesh.coords) != fm.n_nodes:
        raise CfmInputError(
            f"the mesh has {len(mesh.coords)} node(s) and the map {fm.n_nodes}; give the mesh "
            "built for this map (`build_mesh`), or none",
            file=fm.source,
        )
    mesh = build_mesh(fm, cfg.interpolation, cfg.hull_slivers) if mesh is None else mesh
    _check_config(cfg, fm, mesh)
    b_ref = fm.b_max if cfg.b_ref_T is None else float(cfg.b_ref_T)
    if b_ref <= 0:
        raise CfmInputError(
            "the map's field is zero everywhere; give B_ref explicitly", file=fm.source
        )
    eps = 1e-7 * float(np.ptp(mesh.coords, axis=0).max())
    start_cells = _kernels.octant_cells(
        mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, eps
    )
    htm = None
    if cfg.mode == "htm":
        htm, unreachable = _htm_arrays(cfg, fm)
        if unreachable.all():
            raise CfmInputError(
                "no node of the map is within the strokes of the bench's axes; check the magnet "
                "placement in the bench file ([magnet] rotation_deg, translation_mm)",
                file=fm.source,
            )
        if unreachable.any():
            start_cells = start_cells.copy()
            start_cells[unreachable] = -1
            mesh.notes.append(
                f"{int(unreachable.sum())} node(s) lie outside the strokes of the bench's axes: "
                "no statistics (NaN)"
            )
    problem = SweepProblem(
        coords=mesh.coords,
        values=np.ascontiguousarray(fm.B),
        simplices=mesh.simplices,
        transform=mesh.transform,
        neighbors=mesh.neighbors,
        start_cells=start_cells,
        basis=np.ascontiguousarray(mesh.basis),
        axis_scale=np.asarray(cfg.axis_scale, dtype=np.float64),
        scales_mm=np.asarray(cfg.up_um, dtype=np.float64) * 1e-3,
        trials=int(cfg.trials),
        seed=int(cfg.seed),
        coverage=float(cfg.coverage),
        htm=htm,
        exit_grad=(
            np.ascontiguousarray(edge_fit_gradients(mesh, fm.B))
            if cfg.outside == "extrapolate"
            else np.empty((0, 3, mesh.dim))
        ),
        search=exact_search(mesh),
        keys=node_keys(fm.points),
    )
    return mesh, problem, b_ref


def node_keys(points) -> np.ndarray:
    """Random-stream key of each node: a hash of its coordinates (`coordinate_keys`), so a node
    gets the same numbers whatever the order of the map's rows and in any part of the map.

    Parameters
    ----------
    points : ndarray, shape (n, 3), mm

    Returns
    -------
    ndarray, shape (n,), int64, >= 0
    """
    return (coordinate_keys(np.asarray(points, dtype=np.float64)) >> np.uint64(1)).astype(np.int64)


def _bench_named(cfg) -> dict | None:
    """Name and file of the bench of mode htm (the packaged reference bench when none is set)."""
    if cfg.mode != "htm":
        return None
    from .io.bench_toml import read_reference_bench

    bench = cfg.bench if cfg.bench is not None else read_reference_bench()
    return {"name": bench.name, "source": str(bench.source)}


def _htm_arrays(cfg: SweepConfig, fm: FieldMap):
    """Bench arrays of mode htm for `SweepProblem`, and the nodes the bench cannot reach."""
    from .io.bench_toml import read_reference_bench  # the packaged default bench
    from .kinematics import draw_error_sets, kernel_geometry, noise_keys

    bench = cfg.bench if cfg.bench is not None else read_reference_bench()
    q = np.ascontiguousarray(bench.axis_positions_for(fm.points))
    g = kernel_geometry(bench)
    nkey, fkey = noise_keys(cfg.seed)
    params = np.ascontiguousarray(draw_error_sets(bench, cfg.trials, cfg.seed))
    # constant error profiles: the chain collapses exactly to 21 numbers per trial
    n_terms = (len(params), 1) if g.linear else (0, 0)
    terms, terms_zero = np.empty((n_terms[0], 21)), np.empty((n_terms[1], 21))
    _kernels.trial_terms(params[: n_terms[0]], g.stack, g.mounts, g.tool, terms)
    _kernels.trial_terms(np.zeros((n_terms[1], 21)), g.stack, g.mounts, g.tool, terms_zero)
    arrays = dict(
        rot=np.ascontiguousarray(bench.bench_to_magnet_rotation()),
        q_nodes=q,
        params=params,
        terms=terms,
        terms_zero=terms_zero,
        nkey=nkey,
        fkey=fkey,
        sig=g.sig,
        speed=g.speed,
        tau_code=g.tau_code,
        tau_par=g.tau_par,
        stack=g.stack,
        mounts=g.mounts,
        tool=g.tool,
        strokes=g.strokes,
        profiles=g.profiles,
        bench_name=bench.name,
    )
    return arrays, bench.outside_stroke(q)


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
    mesh, problem, b_ref = prepare_sweep(fm, cfg, mesh)
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
    sigma_mm = problem.scales_mm[:, None] * problem.axis_scale[None, :]  # (n_up, 3)
    # the kernels' own arrays (octant start cells, exact-search buckets and face excess: 0.4 GB
    # on a 1e6-node non-convex map) are done with: freed before the gradients' temporaries
    del problem
    gradient = node_gradients(mesh, fm.B)
    if positioning is None:
        gum_u = _gum_u(gradient, fm.B, b_ref, sigma_mm[None])
    else:
        gum_u = _gum_u(gradient, fm.B, b_ref, positioning[:, :, 1], positioning[:, :, 2])
    return SweepResult(
        fieldmap=fm,
        mesh=mesh,
        config=cfg,
        b_ref_T=b_ref,
        stats=stats,
        n_outside=n_out,
        n_walk_failed=n_lost,
        linear_in_up=star,
        gradient=gradient,
        gum_u=gum_u,
        seconds=time.perf_counter() - t0,
        positioning=positioning,
    )


def summarize(res: SweepResult) -> dict:
    """The ``summary.json`` content plus the context a reader needs.

    Stable keys (other tools read them): ``b_ref_T``, ``trials``, ``seed``, ``seconds`` (one
    number for the run) and, one entry per U_p value, ``up_um``, ``uf_units`` (``p50``, ``p95``,
    ``p99``, ``max`` over nodes) and ``outside_fraction``. U_f of a node is the 95 % expanded
    uncertainty of |B|: the larger of |lower| and |upper| of the probabilistically symmetric
    95 % interval of B_meas - B_nom, in units of 1e-4 B_ref.

    U_f percentiles are taken over the nodes whose every trial has a value (``uf_nodes`` counts
    them): by default those whose every trial stayed inside the map, as nodes near the map's
    border lose trials and are reported through ``outside_fraction`` instead of being summarised
    from a truncated sample; with ``outside="extrapolate"`` every node, the trials that left the
    map taking the node's first-order Taylor expansion.
    """
    cfg = res.config
    n_col = res.stats.shape[1]
    uf = res.uf_units()
    complete = res.complete()
    # nodes that were simulated (htm: reachable by the bench; all: in some cell)
    processed = (res.n_outside + res.n_walk_failed > 0).any(axis=1) | np.isfinite(
        res.stats[:, :, 3, 1]
    ).any(axis=1)
    pct = {"p50": [], "p95": [], "p99": [], "max": []}
    for k in range(n_col):
        vals = uf[complete[:, k], k]
        for name, q in (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100)):
            pct[name].append(float(np.percentile(vals, q)) if vals.size else None)
    n_samples = max(int(processed.sum()), 1) * cfg.trials
    dis_frac = []
    for k in range(n_col):  # one column at a time: no map-sized temporaries for every column
        disagree = res.gum_check(k)[2][complete[:, k]]
        dis_frac.append(
            {name: float(disagree[:, c].mean()) if len(disagree) else None
             for c, name in enumerate(COMPONENTS)}
        )  # fmt: skip
    notes = list(res.fieldmap.notes) + list(res.mesh.notes)
    if res.mesh.dim == 2:
        notes.append(
            "planar map: perturbations are projected into the plane of the map; the out-of-plane "
            "component of U_p is not covered (the field off the plane is unknown)"
        )
    return {
        "b_ref_T": res.b_ref_T,
        "b_ref_rule": "max |B| over the map nodes" if cfg.b_ref_T is None else "given by the user",
        "trials": cfg.trials,
        "seed": cfg.seed,
        "up_um": res.column_up_um(),
        "columns": res.labels,
        "uf_units": pct,
        "uf_nodes": [int(complete[:, k].sum()) for k in range(n_col)],
        "nodes": int(res.fieldmap.n_nodes),
        "processed_nodes": int(processed.sum()),  # in some cell (gauss) / reachable (htm)
        "outside_fraction": [float(res.n_outside[:, k].sum() / n_samples) for k in range(n_col)],
        "outside": cfg.outside,
        "outside_rule": OUTSIDE_RULES[cfg.outside],
        "walk_failed_fraction": [
            float(res.n_walk_failed[:, k].sum() / n_samples) for k in range(n_col)
        ],
        "uf_relative_mc_std": float(1.363 / np.sqrt(cfg.trials)),
        "gum_disagree_fraction": dis_frac,
        "linear_in_up_fraction": float(res.linear_in_up[processed].mean())
        if processed.any()
        else None,
        "seconds": res.seconds,
        "definitions": {
            "U_f": "95 % expanded uncertainty of |B| per node: max(|low|, |high|) of the "
            "probabilistically symmetric 95 % interval of |B|(x_meas) - |B|(x_nom), in units of "
            "1e-4 B_ref",
            "uf_relative_mc_std": "normal-theory relative standard error of one node's U_f from "
            "the finite trial count: sqrt(p(1-p)/N) / (phi(z) z), p = 0.025",
            "gum_disagree": "GUM-S1 section 8: |y_GUM +- 1.96 u_GUM - MC interval end| > "
            "max(delta, 3 MC standard errors), u_GUM = sqrt(g^T Sigma g) with g the gradient and "
            "Sigma the covariance of the probe position error (diag(U_p,j^2) in mode gauss); "
            "y_GUM = g . mean probe error (0 in mode gauss)",
        },
        "mode": cfg.mode,
        # mode htm: the bench model used (its file's hash: provenance.inputs.bench); None: gauss
        "bench": _bench_named(cfg),
        "axis_scale": list(cfg.axis_scale),
        "coverage": cfg.coverage,
        "interpolation": res.mesh.description,
        "perturbation": (
            "x_meas = x_nom + N(0, U_p) per coordinate (paper eq. 16); the same standard normals "
            "serve every U_p value of the sweep (common random numbers)"
            if cfg.mode == "gauss"
            else "x_meas = x_nom + E_p, E_p from the bench model (paper eq. 10): one draw of the "
            "21 geometric errors per trial common to all nodes, vibration and reading delay per "
            "node; columns: total, geometric errors only, vibration and delay only; up_um is the "
            "RMS over nodes of the 3-D positioning error sqrt(|mean|^2 + |std|^2)"
        ),
        "notes": notes,
        "source": res.fieldmap.source,
    }
