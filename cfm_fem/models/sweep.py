"""The positioning-uncertainty sweep as data: its configuration, per-node result and summary.

Paper eq. 16: x_meas = x_nom + N(0, U_p) per coordinate (mode gauss), or the probe error of
the bench model (mode htm); B_meas - B_nom is collected over the trials, per node, for each
component and for |B|. The workflows that run it are in `cfm_fem.workflows.sweep`; a result
split into node-range pieces (`partition`, `piece_result`) is what the piecewise writers use.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .. import _kernels
from ..errors import CfmInputError
from .field import FieldMap
from .mc import numerical_tolerance
from .mesh import SimplexMesh
from .node_weights import node_volumes, volume_rule, weighted_percentiles
from .region import region_mask

__all__ = [
    "HTM_PARTS",
    "OUTSIDE_RULES",
    "FIELD_MODELS",
    "ESTIMATORS",
    "ADAPTIVE_PLAN",
    "ADAPTIVE_PRECISION",
    "uses_adaptive",
    "uses_harmonic",
    "field_model_summary",
    "harmonic_summary",
    "SweepConfig",
    "COMPONENTS",
    "STAT_NAMES",
    "up_label",
    "SweepResult",
    "summarize",
    "reference_field",
    "b_ref_rule",
    "uf_percentiles",
    "CompactSweep",
    "piece_bounds",
    "partition",
    "piece_result",
]

#: Columns of a mode-htm sweep: (include the 21 geometric errors, include vibration and delay).
HTM_PARTS = {
    "htm_total": (True, True),
    "htm_geometric": (True, False),
    "htm_vibration_delay": (False, True),
}


#: Field models between the nodes (`SweepConfig.field_model`). "auto": the harmonic fits on a
#: 3-D map (each node keeps the linear interpolant where its fit finds Laplace's equation
#: violated), the linear interpolant on a planar map, whose records tie the field's derivative
#: across the plane to nothing.
FIELD_MODELS = ("auto", "linear", "harmonic")


#: Estimators of the statistics (`SweepConfig.estimator`). "plain": Monte Carlo with
#: ``trials`` trials per node; "adaptive": under the harmonic model in mode gauss, the
#: control-variate estimator (`cfm_fem._kernels.harmonic_cv`), with `ADAPTIVE_PLAN`.
ESTIMATORS = ("plain", "adaptive")

#: The adaptive estimator's plan: pilot trials per node, most trials per node, and the standard
#: error of each end of |B|'s 95 % interval it stops at, relative to U_f: 0.7 %, so that U_f
#: lies within +-1.4 % of its exact value at 95 % (`ADAPTIVE_PRECISION`).
ADAPTIVE_PLAN = (256, 64000, 0.007)

#: The stated precision of the adaptive estimator's U_f: relative half-width at 95 %.
ADAPTIVE_PRECISION = 0.014

#: Most U_p values of a sweep the adaptive estimator runs (each thread keeps every trial of a
#: node at each of them: 2 MB per U_p value at the most trials); more run plain.
ADAPTIVE_MAX_COLUMNS = 16


def uses_adaptive(cfg, harmonic: bool) -> bool:
    """Whether a sweep with configuration ``cfg`` runs the adaptive estimator at its harmonic
    nodes (``harmonic``: the run fits the harmonic models): estimator "adaptive", mode gauss,
    at most `ADAPTIVE_MAX_COLUMNS` U_p values."""
    return (
        cfg.estimator == "adaptive"
        and cfg.mode == "gauss"
        and harmonic
        and len(cfg.up_um) <= ADAPTIVE_MAX_COLUMNS
    )


def uses_harmonic(field_model: str, dim: int) -> bool:
    """Whether field model ``field_model`` fits the per-node harmonic models on a map of
    dimension ``dim`` (2: planar, 3: volume)."""
    return field_model == "harmonic" or (field_model == "auto" and dim == 3)


#: What happens to a trial whose perturbed position leaves the map (`SweepConfig.outside`).
OUTSIDE_RULES = {
    "exclude": "left out of the node's statistics (counted in outside_fraction); the node is "
    "incomplete and not in the U_f percentiles",
    "extrapolate": "given the node's first-order Taylor expansion B + grad B . delta (grad B: a "
    "least-squares fit over the edges of its cells, weighted by 1/length^2; counted in "
    "outside_fraction); the node keeps all its trials",
}


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
        Bench model for mode ``htm`` (`cfm_fem.models.bench.Bench`); None means the reference bench.
    chunk_nodes : int
        Nodes per chunk (progress granularity and memory; results do not depend on it).
    outside : {"exclude", "extrapolate"}
        Trials whose perturbed position leaves the map: left out of the node's statistics
        (the node is then incomplete), or given the node's first-order Taylor expansion
        B + grad B . delta (`edge_fit_gradients`). Counted in ``n_outside`` either way.
    hull_slivers : {"remove", "keep"}
        Delaunay maps: remove the flat cells of the convex hull (default) or keep them
        (`cfm_fem.models.mesh.hull_sliver_cells`); trials in a removed cell are outside. Kept,
        they put U_f and the gradient (so the GUM figure) of the nodes on the hull far off.
    field_model : {"auto", "linear", "harmonic"}
        The field between nodes: the piecewise-linear interpolant of the mesh, or per node the
        local harmonic fit (`cfm_fem.models.harmonic`; 3-D maps), with the linear interpolant
        where the fit finds Laplace's equation violated; "auto" (default): the harmonic fits on a
        3-D map, the linear interpolant on a planar one (`uses_harmonic`).
    region : cfm_fem.models.region.Region or None
        Region of interest: the U_f percentiles of the summary are over its nodes, and the
        default B_ref is the largest |B| over them (`reference_field`); None: the whole map.
    estimator : {"plain", "adaptive"}
        `ESTIMATORS`: "adaptive" takes, at the nodes under a harmonic model in mode gauss, as
        many trials as U_f's precision needs (`ADAPTIVE_PLAN`); every other node (and any
        node one of whose trials leaves its model's reach) gets ``trials`` plain trials.
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
    field_model: str = "auto"
    region: object | None = None
    estimator: str = "plain"


def _bench_named(cfg) -> dict | None:
    """Name and file of the bench of mode htm (the workflows set the packaged reference bench
    when none is given, `cfm_fem.workflows.sweep.problem.with_bench`)."""
    if cfg.mode != "htm":
        return None
    return {"name": cfg.bench.name, "source": str(cfg.bench.source)}


#: Layout of the component axis: the three components and |B|.
COMPONENTS = _kernels.COMPONENTS


STAT_NAMES = _kernels.STAT_NAMES


#: 97.5 % quantile of the standard normal: the GUM 95 % half-width is Z95 * u.
Z95 = 1.959963984540054


def up_label(up_um: float) -> str:
    """Column name of a U_p value, ``up<U_p>um`` (6 significant digits): it names the map
    (``uf_up20um.vtu``) and the summary column."""
    return f"up{up_um:g}um"


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
    field_fit : dict or None
        Field model "harmonic": per node ``degree`` (n,) int64, the polynomial degree of its
        harmonic fit (0 where the node uses the linear interpolant), and ``residual_T`` (n,),
        the fit's RMS residual over its neighbours' field values, T. None: linear.
    node_volume_mm3 : ndarray, shape (n,), mm^3, or None
        Volume each node stands for (`node_volumes`); None: from the mesh on first use.
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
    field_fit: dict | None = None
    node_volume_mm3: np.ndarray | None = None

    def node_volumes(self) -> np.ndarray:
        """Volume each node stands for, shape (n,), mm^3 (`node_weights.node_volumes` of the
        mesh, made on first use; a piece of a result carries its nodes' share of the whole)."""
        if self.node_volume_mm3 is None:
            self.node_volume_mm3 = node_volumes(self.mesh)[0]
        return self.node_volume_mm3

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


def gauss_sigma_mm(up_um, axis_scale) -> np.ndarray:
    """Per-axis standard deviation of the gauss perturbation, shape (1, n_up, 3), mm.

    Parameters
    ----------
    up_um : sequence of float, length n_up, um
    axis_scale : sequence of float, length 3
        Per-axis multiplier of U_p (`SweepConfig.axis_scale`).
    """
    scales = np.asarray(up_um, dtype=np.float64) * 1e-3
    return (scales[:, None] * np.asarray(axis_scale, dtype=np.float64)[None, :])[None]


def assemble_result(fieldmap, mesh, config, b_ref_T, parts, gradient, **extra) -> SweepResult:
    """The `SweepResult` of a map or of part of one, from its chunk-result arrays and node
    gradients: the one place a result is put together, its GUM figures computed here.

    Parameters
    ----------
    fieldmap : FieldMap
        The nodes of the result (a whole map, a piece or a slab's own nodes).
    mesh : SimplexMesh or None
    config : SweepConfig
    b_ref_T : float
        B_ref of the whole run, T.
    parts : tuple
        (stats (n, n_col, 4, 6) T, n_outside (n, n_col), n_walk_failed (n, n_col),
        linear_in_up (n,)[, positioning]) as
        `cfm_fem.workflows.sweep.problem.SweepProblem.run_chunk` returns them; positioning
        (n, n_col, 3, 3) in mode htm, None or of shape (n, 0, 3, 3) in mode gauss.
    gradient : ndarray, shape (n, 3, 3), T/mm
    **extra
        The optional fields of `SweepResult`: ``n_left_out``, ``field_fit``,
        ``node_volume_mm3``, ``seconds`` (default 0).

    Returns
    -------
    SweepResult
        ``gum_u`` from the gradient and, in mode gauss, U_p of each column times
        ``config.axis_scale``; in mode htm the standard deviations and correlations of each
        node's probe error.
    """
    stats, n_out, n_lost, star = parts[:4]
    pos = parts[4] if len(parts) > 4 else None
    if pos is not None and pos.shape[1] == 0:
        pos = None
    if pos is None:
        gum_u = _gum_u(
            gradient, fieldmap.B, b_ref_T, gauss_sigma_mm(config.up_um, config.axis_scale)
        )
    else:
        gum_u = _gum_u(gradient, fieldmap.B, b_ref_T, pos[:, :, 1], pos[:, :, 2])
    extra.setdefault("seconds", 0.0)
    return SweepResult(
        fieldmap=fieldmap,
        mesh=mesh,
        config=config,
        b_ref_T=b_ref_T,
        stats=stats,
        n_outside=n_out,
        n_walk_failed=n_lost,
        linear_in_up=star,
        gradient=gradient,
        gum_u=gum_u,
        positioning=pos,
        **extra,
    )


def _gum_mean(gradient, B, b_ref, mean_mm):
    """Linearised systematic error g . mean per node, column and component, shape
    (n, n_col, 4), T; ``mean_mm`` (n, n_col, 3): mean probe position error per map axis."""
    return np.einsum("ncj,nkj->nkc", _gradients4(gradient, B, b_ref), mean_mm)


#: How the U_f percentiles of summary.json weigh the nodes (`summarize`).
WEIGHTING = (
    "volume: each node weighs the volume it stands for (its dual cell, node_volume_rule); p<q> "
    "is the smallest U_f such that the nodes at or below it hold q % of the volume of the "
    "region's nodes with a U_f figure; max is the largest node value. uf_units_per_node counts "
    "every node once"
)


def b_ref_rule(cfg) -> str:
    """How B_ref was set (`reference_field`), for summary.json."""
    if cfg.b_ref_T is not None:
        return "given by the user"
    if cfg.region is None:
        return "max |B| over the map nodes"
    return "max |B| over the map nodes in the region of interest"


def reference_field(fm: FieldMap, cfg) -> float:
    """B_ref of a run, T: ``cfg.b_ref_T`` when given, else the largest |B| over the map's
    nodes in ``cfg.region`` (every node without a region), whatever the file format.

    Raises
    ------
    CfmInputError
        The region holds no node of the map.
    """
    if cfg.b_ref_T is not None:
        return float(cfg.b_ref_T)
    if cfg.region is None:
        return fm.b_max
    inside = cfg.region.mask(fm.points)
    if not inside.any():
        raise CfmInputError(
            f"--region ({cfg.region.describe()}) holds none of the {fm.n_nodes} nodes of the map",
            file=fm.source,
        )
    return float(np.sqrt((fm.B[inside] ** 2).sum(axis=1)).max())


def uf_percentiles(uf, counted, volumes):
    """U_f percentiles p50, p95, p99 and max per column, weighted by node volume and per node.

    Parameters
    ----------
    uf : ndarray, shape (n, n_col), units
    counted : ndarray, shape (n, n_col), bool
        Nodes that enter each column's figures (a U_f figure, in the region).
    volumes : ndarray, shape (n,), mm^3

    Returns
    -------
    weighted, per_node : dict of str -> list of float or None
        One entry per column; None where no node counts.
    counted : ndarray, shape (n, n_col), bool
    """
    names = (("p50", 50), ("p95", 95), ("p99", 99))
    weighted = {"p50": [], "p95": [], "p99": [], "max": []}
    per_node = {"p50": [], "p95": [], "p99": [], "max": []}
    for k in range(uf.shape[1]):
        vals = uf[counted[:, k], k]
        w = weighted_percentiles(vals, volumes[counted[:, k]], [q for _, q in names])
        for (name, q), v in zip(names, w, strict=True):
            weighted[name].append(v)
            per_node[name].append(float(np.percentile(vals, q)) if vals.size else None)
        top = float(vals.max()) if vals.size else None
        weighted["max"].append(top)
        per_node["max"].append(top)
    return weighted, per_node, counted


def _estimator_summary(res: SweepResult, processed) -> dict:
    """``estimator``, ``estimator_rule`` and ``uf_relative_mc_std`` of the summary: nodes that
    took the plain Monte Carlo under the adaptive estimator are those on the linear
    interpolant and those with a trial beyond their model's reach (counted outside)."""
    cfg = res.config
    plain_std = float(1.363 / np.sqrt(cfg.trials))
    if not uses_adaptive(cfg, res.field_fit is not None):
        return {"estimator": "plain", "estimator_rule": f"plain Monte Carlo, {cfg.trials} trials "
                "per node", "uf_relative_mc_std": plain_std}  # fmt: skip
    pilot, most, rel_se = ADAPTIVE_PLAN
    plain = (res.field_fit["degree"] == 0) | (res.n_outside > 0).any(axis=1)
    n_plain = int((plain & processed).sum())
    rule = (
        f"adaptive control-variate estimator at the nodes under a harmonic model: {pilot} to "
        f"{most} trials per node, until the standard error of each end of U_f's interval is "
        f"at most {100 * rel_se:g} % of U_f; {n_plain} node(s) on plain Monte Carlo of "
        f"{cfg.trials} trials (on the linear interpolant, or a trial beyond the model's reach)"
    )
    return {"estimator": "adaptive", "estimator_rule": rule,
            "uf_relative_mc_std": max(rel_se, plain_std) if n_plain else rel_se}  # fmt: skip


def summarize(res: SweepResult) -> dict:
    """The ``summary.json`` content plus the context a reader needs.

    Stable keys (other tools read them): ``b_ref_T``, ``trials``, ``seed``, ``seconds`` (one
    number for the run) and, one entry per U_p value, ``up_um``, ``uf_units`` (``p50``, ``p95``,
    ``p99``, ``max`` over nodes) and ``outside_fraction``. U_f of a node is the 95 % expanded
    uncertainty of |B|: the larger of |lower| and |upper| of the probabilistically symmetric
    95 % interval of B_meas - B_nom, in units of 1e-4 B_ref.

    U_f percentiles are taken over the nodes of the region of interest (``config.region``; the
    whole map without one) whose every trial has a value (``uf_nodes`` counts them): by default
    those whose every trial stayed inside the map, as nodes near the map's border lose trials
    and are reported through ``outside_fraction`` instead of being summarised from a truncated
    sample; with ``outside="extrapolate"`` every node, the trials that left the map taking the
    node's first-order Taylor expansion. Each node weighs the volume it stands for
    (`cfm_fem.models.node_weights.node_volumes`), so the node density does not move them;
    ``uf_units_per_node`` gives the same percentiles with every node counted once.
    """
    cfg = res.config
    n_col = res.stats.shape[1]
    uf = res.uf_units()
    complete = res.complete()
    # nodes that were simulated (htm: reachable by the bench; all: in some cell)
    processed = (res.n_outside + res.n_walk_failed > 0).any(axis=1) | np.isfinite(
        res.stats[:, :, 3, 1]
    ).any(axis=1)
    if res.node_volume_mm3 is None:  # kept: the maps are written from the same figures
        res.node_volume_mm3, rule = node_volumes(res.mesh)
    else:  # a part of a map (a slab's own nodes) carries its share of the whole
        rule = volume_rule(res.mesh)
    volumes = res.node_volume_mm3
    inside = region_mask(res.fieldmap.points, cfg.region)
    pct, per_node, counted = uf_percentiles(uf, complete & inside[:, None], volumes)
    n_samples = max(int(processed.sum()), 1) * cfg.trials
    dis_frac, dis_nodes = [], []
    for k in range(n_col):  # one column at a time: no map-sized temporaries for every column
        disagree = res.gum_check(k)[2][complete[:, k]]
        dis_frac.append(
            {name: float(disagree[:, c].mean()) if len(disagree) else None
             for c, name in enumerate(COMPONENTS)}
        )  # fmt: skip
        dis_nodes.append({name: int(disagree[:, c].sum()) for c, name in enumerate(COMPONENTS)})
    notes = list(res.fieldmap.notes) + list(res.mesh.notes)
    if res.mesh.dim == 2:
        notes.append(
            "planar map: perturbations are projected into the plane of the map; the out-of-plane "
            "component of U_p is not covered (the field off the plane is unknown)"
        )
    return {
        "b_ref_T": res.b_ref_T,
        "b_ref_rule": b_ref_rule(cfg),
        "trials": cfg.trials,
        "seed": cfg.seed,
        "up_um": res.column_up_um(),
        "columns": res.labels,
        "uf_units": pct,
        "uf_units_per_node": per_node,
        "statistics_weighting": WEIGHTING,
        "node_volume_rule": rule,
        "region": None if cfg.region is None else cfg.region.to_json(),
        "region_description": "the whole map" if cfg.region is None else cfg.region.describe(),
        "region_nodes": int(inside.sum()),
        "region_volume_mm3": float(volumes[inside].sum()),
        "uf_volume_fraction": [
            float(volumes[counted[:, k]].sum() / volumes[inside].sum())
            if volumes[inside].sum() > 0
            else None
            for k in range(n_col)
        ],
        "uf_nodes": [int(counted[:, k].sum()) for k in range(n_col)],
        "nodes": int(res.fieldmap.n_nodes),
        "processed_nodes": int(processed.sum()),  # in some cell (gauss) / reachable (htm)
        "outside_fraction": [float(res.n_outside[:, k].sum() / n_samples) for k in range(n_col)],
        "outside": cfg.outside,
        "outside_rule": OUTSIDE_RULES[cfg.outside],
        "walk_failed_fraction": [
            float(res.n_walk_failed[:, k].sum() / n_samples) for k in range(n_col)
        ],
        **_estimator_summary(res, processed),
        "gum_disagree_fraction": dis_frac,
        "gum_disagree_nodes": dis_nodes,
        "linear_in_up_fraction": float(res.linear_in_up[processed].mean())
        if processed.any()
        else None,
        "seconds": res.seconds,
        "definitions": {
            "U_f": "95 % expanded uncertainty of |B| per node: max(|low|, |high|) of the "
            "probabilistically symmetric 95 % interval of |B|(x_meas) - |B|(x_nom), in units of "
            "1e-4 B_ref",
            "uf_relative_mc_std": "relative standard error of one node's U_f: plain Monte Carlo, "
            "the normal-theory figure of the finite trial count sqrt(p(1-p)/N) / (phi(z) z), "
            "p = 0.025; adaptive estimator, the standard error it runs each node to (the larger "
            "of the two where some nodes ran plain)",
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
        **field_model_summary(res),
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


def field_model_summary(res: SweepResult) -> dict:
    """``field_model`` and, for the harmonic model, what its fits did (summary.json)."""
    ff = res.field_fit
    if ff is None:
        return {"field_model": "linear"}
    deg = np.asarray(ff["degree"])
    pts = res.fieldmap.points[deg == 0]
    box = [pts.min(axis=0).tolist(), pts.max(axis=0).tolist()] if len(pts) else None
    return harmonic_summary(deg, res.to_units(np.asarray(ff["residual_T"])), box, ff)


def harmonic_summary(degree, residual_units, fallback_box, info) -> dict:
    """summary.json entries of the harmonic field model.

    Parameters
    ----------
    degree : ndarray, shape (n,), int
        Degree of each node's fit, 0 where the node uses the linear interpolant.
    residual_units : ndarray, shape (n,)
        RMS residual of each node's fit, units.
    fallback_box : [min (3,), max (3,)] or None
        Box of the nodes on the linear interpolant, mm.
    info : dict
        ``neighbours``, ``fallback_rule``, ``reach_rule`` (`SweepResult.field_fit`).
    """
    degree = np.asarray(degree)
    fit = degree > 0
    resid = np.asarray(residual_units)[fit]
    return {
        "field_model": "harmonic",
        "harmonic": {
            "neighbours": int(info["neighbours"]),
            "nodes_by_degree": {str(d): int((degree == d).sum()) for d in np.unique(degree[fit])},
            "residual_units": {
                name: float(np.percentile(resid, q)) if resid.size else None
                for name, q in (("p50", 50), ("p95", 95), ("max", 100))
            },
            "linear_fallback_nodes": int((~fit).sum()),
            "linear_fallback_box_mm": (
                None if fallback_box is None else {"min": fallback_box[0], "max": fallback_box[1]}
            ),
            "fallback_rule": info["fallback_rule"],
            "reach_rule": info["reach_rule"],
        },
    }


@dataclass
class CompactSweep(SweepResult):
    """A `SweepResult` without the full statistics, for `cfm_fem.models.sweep.summarize`.

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
        """U_p of each column, um (see `cfm_fem.models.sweep.SweepResult.column_up_um`)."""
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


def _part_result(compact, nodes, parts) -> SweepResult:
    """Full `SweepResult` of the nodes ``nodes`` from their chunk-result arrays ``parts``."""
    fm = compact.fieldmap
    sub = FieldMap(points=fm.points[nodes], B=fm.B[nodes], source=fm.source)
    extra = {"node_volume_mm3": compact.node_volumes()[nodes]}
    if compact.field_fit is not None:
        extra["field_fit"] = {
            key: v[nodes] if isinstance(v, np.ndarray) else v
            for key, v in compact.field_fit.items()
        }
    return assemble_result(
        sub,
        compact.mesh,
        compact.config,
        compact.b_ref_T,
        parts,
        compact.gradient[nodes],
        **extra,
    )


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
        The `cfm_fem.workflows.sweep.problem.SweepProblem.run_chunk` arrays of those nodes (e.g.
        from `cfm_fem.workflows.sweep.resume.ResumableRun.gather`).

    Raises
    ------
    CfmInputError
        ``nodes`` is empty (a piece of `partition` never is).
    """
    nodes = np.asarray(nodes)
    if nodes.size == 0:
        raise CfmInputError("nodes is empty; expected the node indices of a piece (at least one)")
    return _part_result(compact, nodes, parts)
