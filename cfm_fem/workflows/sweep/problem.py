"""The sweep problem every variant runs: mesh, gradients, kernel arrays and chunked work.

Paper eq. 16: x_meas = x_nom + N(0, U_p) per coordinate; the field is interpolated at x_meas and
B_meas - B_nom collected over the trials, per node, for each component and for |B|.
`prepare_sweep` builds a `SweepProblem`, whose chunks of nodes run independently (in memory,
in pieces, in slabs, resumed or on Dask workers) with the same numbers.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import namedtuple
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from threadpoolctl import threadpool_limits

from ... import _kernels
from ...errors import CfmInputError, check_seed
from ...models.field import FieldMap
from ...models.mesh import (
    SimplexMesh,
    build_mesh,
    coordinate_keys,
    exact_search,
    morton_order,
    no_search,
)
from ...models.sweep import (
    FIELD_MODELS,
    HTM_PARTS,
    OUTSIDE_RULES,
    SweepConfig,
    reference_field,
    up_label,
    uses_adaptive,
    uses_harmonic,
)
from ...threads import check_memory, map_blocks

__all__ = [
    "node_keys",
    "SweepProblem",
    "SweepMesh",
    "HtmTrials",
    "chunk_ranges",
    "serial_map",
    "prepare_sweep",
    "fallback_note",
    "up_too_large",
    "check_options",
    "node_gradients",
    "sweep_gradients",
    "field_fit_info",
    "edge_fit_gradients",
    "with_bench",
]


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


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
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


@threadpool_limits.wrap(limits=1, user_api="blas")  # small matrices: idle BLAS threads spin
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


#: Smallest B_ref, as a share of the map's largest |B|: below it, field errors in units of
#: 1e-4 B_ref reach 1e13 units per tesla of error and overflow for absurd values (1e-300 T).
MIN_B_REF_SHARE = 1e-9


def trial_bytes(n_columns: int, mode: str = "gauss") -> float:
    """Bytes a sweep holds per Monte Carlo trial, whatever the map's size.

    Each kernel thread keeps per node the trials of every U_p column and component (a
    (n_columns, 3, trials) and a (n_columns, trials) array) and some 17 scratch rows of
    ``trials`` values; mode htm also keeps the 21 geometric errors and their chain terms of
    every trial.

    Parameters
    ----------
    n_columns : int
        U_p values (mode gauss) or bench columns (mode htm).
    mode : {'gauss', 'htm'}

    Returns
    -------
    float
        Bytes per trial.
    """
    per_thread = 8.0 * (4 * max(int(n_columns), 1) + 24)
    shared = 8.0 * 2 * 21 if mode == "htm" else 0.0
    return numba.get_num_threads() * per_thread + shared


def check_options(
    trials: int, axis_scale, b_ref_T: float | None, n_columns: int = 1, mode: str = "gauss"
) -> None:
    """The checks of a `SweepConfig` that need no map: the command line runs them before it
    reads the map (which can take minutes), `_check_config` again for a Python caller.

    Raises
    ------
    CfmInputError
        ``trials`` < 20, an axis scale negative, not finite or all 0, ``b_ref_T`` not > 0, or
        more trials than the memory holds (`cfm_fem.threads.check_memory`, `trial_bytes`).
    """
    if trials < 20:
        raise CfmInputError(f"--trials must be at least 20 for a 95 % interval; got {trials}")
    check_memory("--trials", trials, trial_bytes(n_columns, mode), "trials")
    if any(not np.isfinite(a) or a < 0 for a in axis_scale) or max(axis_scale) == 0:
        raise CfmInputError(
            f"--axis-scale (axis_scale) must be finite, >= 0 and not all 0; got {axis_scale}"
        )
    if b_ref_T is not None and not (np.isfinite(b_ref_T) and b_ref_T > 0):
        raise CfmInputError(f"--b-ref (B_ref) must be a positive field in T; got {b_ref_T}")


def _check_config(cfg: SweepConfig, fm: FieldMap, mesh: SimplexMesh):
    if cfg.mode not in ("gauss", "htm"):
        raise CfmInputError(f"--mode must be gauss or htm; got {cfg.mode!r}")
    check_options(cfg.trials, cfg.axis_scale, cfg.b_ref_T, len(cfg.up_um), cfg.mode)
    if not 0.5 < cfg.coverage < 1.0:
        raise CfmInputError(f"coverage must be in (0.5, 1); got {cfg.coverage}")
    if cfg.outside not in OUTSIDE_RULES:
        raise CfmInputError(f"--outside must be exclude or extrapolate; got {cfg.outside!r}")
    if cfg.field_model not in FIELD_MODELS:
        raise CfmInputError(
            f"--field-model must be auto, linear or harmonic; got {cfg.field_model!r}"
        )
    if cfg.field_model == "harmonic" and mesh.dim != 3:
        raise CfmInputError(
            "--field-model harmonic needs a 3-D map (Laplace's equation ties the field's "
            "derivative across the plane of a planar map to nothing it records); use "
            "--field-model linear",
            file=fm.source,
        )
    check_seed(cfg.seed)  # the CLI's rule and message (numba takes the seed as int64)
    if cfg.mode == "htm":
        return
    check_up_distinct(cfg.up_um)
    extent = np.ptp(mesh.coords, axis=0).min()  # smallest in-plane / in-volume extent, mm
    up_max_mm = max(cfg.up_um) * 1e-3 * max(cfg.axis_scale)
    if up_max_mm * 5.0 > extent:
        raise CfmInputError(up_too_large(cfg, extent), file=fm.source)


def up_too_large(cfg: SweepConfig, extent_mm: float) -> str:
    """The refusal of a largest U_p (times the largest --axis-scale) that 5 times exceeds the
    map's smallest extent ``extent_mm``."""
    scale = max(cfg.axis_scale)
    what = f"--up: U_p of {max(cfg.up_um):g} um"
    if scale != 1.0:
        what = f"--up, --axis-scale: U_p of {max(cfg.up_um):g} um times {scale:g}"
    return (
        f"{what} is too large for this map: 5 U_p exceeds its smallest extent of "
        f"{extent_mm:g} mm, so most perturbed points would leave the map"
    )


#: Mesh arrays of the sweep kernels (`SweepProblem.mesh_arrays`), the `SweepProblem` fields of
#: the same names.
SweepMesh = namedtuple("SweepMesh", "coords values simplices transform neighbors start_cells basis")


class HtmTrials(NamedTuple):
    """Per-trial arrays of the mode-htm kernel (`_kernels.htm_sweep`), built by `_htm_arrays`.

    Attributes
    ----------
    rot : ndarray, shape (3, 3)
        Bench frame -> map (magnet) frame.
    q_nodes : ndarray, shape (n, 3), mm
        Commanded axis positions that bring the probe to each node.
    params : ndarray, shape (T, 21)
        Error amplitudes per trial (mm, rad).
    terms : ndarray, shape (T, 21), (1, 21) or (0, 21)
        The collapsed chain of each trial (constant error profiles), else empty.
    nkey, fkey : uint64
        Noise keys of the seed.
    """

    rot: np.ndarray
    q_nodes: np.ndarray
    params: np.ndarray
    terms: np.ndarray
    nkey: np.uint64
    fkey: np.uint64


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
    # field model "harmonic": the per-node fits (`cfm_fem.models.harmonic.HarmonicFit`)
    harmonic: object | None = None
    # mode gauss under the harmonic model: "adaptive" (`harmonic_cv_sweep`) or "plain"
    estimator: str = "plain"

    def search_arrays(self) -> tuple:
        """The kernels' ``search`` argument (`cfm_fem.models.mesh.exact_search`)."""
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
        if self.harmonic is not None:
            return self._run_harmonic(nodes, keys)
        return self._run_linear(nodes, keys)

    def _run_linear(self, nodes, keys):
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

    def _run_harmonic(self, nodes, keys):
        """Nodes whose harmonic fit holds run under it, the others (`HarmonicFit.use` False)
        under the linear interpolant; results in the order of ``nodes``."""
        use = self.harmonic.use[nodes]
        if not use.any():  # no node (or none whose fit holds): the linear interpolant
            return self._run_linear(nodes, keys)
        if use.all():
            return self._harmonic_kernel(nodes, keys)
        parts = (
            self._run_linear(nodes[~use], keys[~use]),
            self._harmonic_kernel(nodes[use], keys[use]),
        )
        out = [np.empty((len(nodes),) + a.shape[1:], dtype=a.dtype) for a in parts[1]]
        for part, sel in zip(parts, (~use, use), strict=True):
            for o, a in zip(out, part, strict=True):
                o[sel] = a
        return tuple(out)

    def _harmonic_kernel(self, nodes, keys):
        from ...models.harmonic_basis import field_basis, monomial_exponents

        fit = self.harmonic
        model = (
            self.coords, fit.coef, fit.degree, fit.scale, fit.reach_mm,
            np.ascontiguousarray(field_basis()), monomial_exponents(),
        )  # fmt: skip
        extrapolate = self.exit_grad is not None and self.exit_grad.shape[0] > 0
        if self.htm is None:
            if self.estimator == "adaptive":
                return self._adaptive_kernel(nodes, keys, model, extrapolate)
            s, o, lost, star = self._plain_harmonic(nodes, keys, model, extrapolate)
            return s, o, lost, star, np.empty((len(nodes), 0, 3, 3))
        h = self.htm
        parts = []
        for use_geo, use_noise in HTM_PARTS.values():
            trials = h["trials"] if use_geo else h["trials"]._replace(terms=h["terms_zero"])

            def block(i0, i1, trials=trials, use_geo=use_geo, use_noise=use_noise):
                return _kernels.harmonic_htm_sweep(
                    nodes[i0:i1], keys[i0:i1], model, self.start_cells, trials, h["geo"],
                    use_geo, use_noise, float(self.coverage), extrapolate,
                )  # fmt: skip

            parts.append(map_blocks(block, len(nodes), 16))
        stats, n_out, n_lost, pos = (np.concatenate(x, axis=1) for x in zip(*parts, strict=True))
        pos = pos.reshape(len(nodes), len(HTM_PARTS), 3, 3)
        return stats, n_out, n_lost, np.zeros(len(nodes), dtype=bool), pos

    def _plain_harmonic(self, nodes, keys, model, extrapolate):
        def block(i0, i1):
            return _kernels.harmonic_gauss_sweep(
                nodes[i0:i1], keys[i0:i1], model, self.axis_scale, self.scales_mm,
                int(self.trials), int(self.seed), float(self.coverage), extrapolate,
            )  # fmt: skip

        return map_blocks(block, len(nodes), 32)

    def _adaptive_kernel(self, nodes, keys, model, extrapolate):
        """`harmonic_cv_sweep` at every node; the nodes one of whose trials left the model's
        reach get the plain Monte Carlo of ``trials`` trials (`harmonic_gauss_sweep`)."""
        from ...models.sweep import ADAPTIVE_PLAN
        from .compile_ahead import model_arrays, wait

        model = model_arrays(*model)
        wait()  # a first run: the kernel compiled beside the fit
        kept = threading.local()  # each thread's work arrays, from one block to the next

        def block(i0, i1):
            buffers = getattr(kept, "buffers", None)
            if buffers is None:
                buffers = _kernels.harmonic_cv_buffers(
                    len(self.scales_mm), float(self.coverage), ADAPTIVE_PLAN
                )
            *out, kept.buffers = _kernels.harmonic_cv_sweep(
                nodes[i0:i1], keys[i0:i1], model, self.axis_scale, self.scales_mm,
                int(self.seed), float(self.coverage), ADAPTIVE_PLAN, buffers,
            )  # fmt: skip
            return tuple(out)

        s, o, lost, star, used = map_blocks(block, len(nodes), 64)
        plain = used == 0
        if plain.any():
            parts = self._plain_harmonic(nodes[plain], keys[plain], model, extrapolate)
            for out, part in zip((s, o, lost, star), parts, strict=True):
                out[plain] = part
        return s, o, lost, star, np.empty((len(nodes), 0, 3, 3))

    def mesh_arrays(self) -> SweepMesh:
        """The mesh arrays the sweep kernels take, as one named tuple."""
        return SweepMesh(*(getattr(self, name) for name in SweepMesh._fields))

    def _run_htm(self, nodes, keys):
        h = self.htm
        search = self.search_arrays()
        mesh = self.mesh_arrays()
        parts = []
        for use_geo, use_noise in HTM_PARTS.values():
            trials = h["trials"] if use_geo else h["trials"]._replace(terms=h["terms_zero"])

            def block(i0, i1, trials=trials, use_geo=use_geo, use_noise=use_noise):
                return _kernels.htm_sweep(
                    nodes[i0:i1], keys[i0:i1], mesh, trials, h["geo"], use_geo, use_noise,
                    float(self.coverage), self.exit_grad, search,
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


def with_bench(cfg: SweepConfig) -> SweepConfig:
    """``cfg`` with the packaged reference bench filled in for mode htm when it names none."""
    if cfg.mode != "htm" or cfg.bench is not None:
        return cfg
    from ...io.bench_toml import read_reference_bench

    return dataclasses.replace(cfg, bench=read_reference_bench())


def prepare_sweep(
    fm: FieldMap, cfg: SweepConfig, mesh: SimplexMesh | None = None, *, lazy: bool = False
):
    """Check the configuration and build the mesh and the `SweepProblem`.

    ``lazy``: under the harmonic field model in mode gauss, the linear kernel's search arrays
    (octant start cells, exact-search buckets) are built only if some node's fit fails and
    that node takes the linear interpolant; else the problem has none (empty start cells) and
    runs the harmonic kernel only. Default: always built (callers that run the linear kernel
    on any node, or hand the arrays on, as the slabs do).

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
    b_ref = reference_field(fm, cfg)
    if b_ref <= 0:
        raise CfmInputError(
            "the map's field is zero everywhere; give B_ref explicitly", file=fm.source
        )
    if b_ref < MIN_B_REF_SHARE * fm.b_max:  # units of 1e-4 B_ref would overflow
        raise CfmInputError(
            f"--b-ref {b_ref:g} T is below {MIN_B_REF_SHARE:g} of the map's largest |B| "
            f"({fm.b_max:.6g} T): its units (1e-4 B_ref) would be meaningless or overflow; "
            "expected the reference field of the magnet, in T",
            file=fm.source,
        )
    deferred = lazy and cfg.mode == "gauss" and uses_harmonic(cfg.field_model, mesh.dim)
    start_cells = None if deferred else _start_cells(mesh)
    htm = None
    if cfg.mode == "htm":
        htm, unreachable = _htm_arrays(cfg, fm)
        if unreachable.all():
            bench = cfg.bench
            where = "the packaged bench" if bench is None else bench.source
            raise CfmInputError(
                f"no node of the map is within the strokes of the bench's axes; check the magnet "
                f"placement in the bench file {where} ([magnet] rotation_deg, translation_mm)",
                file=fm.source,
            )
        if unreachable.any():
            start_cells = start_cells.copy()
            start_cells[unreachable] = -1
            mesh.notes.append(
                f"{int(unreachable.sum())} node(s) lie outside the strokes of the bench's axes: "
                "no statistics (NaN)"
            )
    harmonic = _harmonic_fit(fm, cfg, mesh)
    if start_cells is None and not harmonic.use.all():  # nodes that take the linear model
        start_cells = _start_cells(mesh)
    problem = SweepProblem(
        coords=mesh.coords,
        values=np.ascontiguousarray(fm.B),
        simplices=mesh.simplices,
        transform=mesh.transform,
        neighbors=mesh.neighbors,
        start_cells=(
            np.empty((0, 1 << mesh.dim), dtype=np.int64) if start_cells is None else start_cells
        ),
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
        search=None if start_cells is None else exact_search(mesh),
        keys=node_keys(fm.points),
        harmonic=harmonic,
        estimator="adaptive" if uses_adaptive(cfg, harmonic is not None) else "plain",
    )
    return mesh, problem, b_ref


def _start_cells(mesh: SimplexMesh) -> np.ndarray:
    """The linear kernel's octant start cells of every node (`_kernels.octant_cells`)."""
    eps = 1e-7 * float(np.ptp(mesh.coords, axis=0).max())
    return _kernels.octant_cells(mesh.coords, mesh.node_cell, mesh.transform, mesh.neighbors, eps)


def _harmonic_fit(fm: FieldMap, cfg: SweepConfig, mesh: SimplexMesh):
    """The per-node harmonic fits of field model "harmonic" (else None), with a note of how
    many nodes fall back to the linear interpolant."""
    if not uses_harmonic(cfg.field_model, mesh.dim):
        if cfg.field_model == "auto":
            mesh.notes.append(
                "field model: the linear interpolant (a planar map; the harmonic fits need a "
                "3-D map)"
            )
        return None
    from ...io.fit_cache import cached_fit

    fit, cached = cached_fit(fm.points, fm.B, source=fm.source)
    if cached is not None:
        mesh.notes.append(fit_cache_note(len(fit.use), cached))
    n_lin = int((~fit.use).sum())
    if n_lin:
        mesh.notes.append(fallback_note(n_lin, len(fit.use), fit.fallback_rule))
    return fit


def fit_cache_note(n: int, path) -> str:
    """The note of harmonic fits of ``n`` nodes read from the cache file ``path``."""
    return (
        f"harmonic fits of the {n} nodes read from the cache ({path}; set CFM_FEM_FIT_CACHE=off "
        "to fit afresh)"
    )


def fallback_note(n_linear: int, n: int, rule: str) -> str:
    """The note of the ``n_linear`` nodes of ``n`` whose harmonic fit fails (``rule``)."""
    return (
        f"{n_linear} node(s) of {n} use the linear interpolant: their harmonic fit fails ({rule})"
    )


def field_fit_info(fit) -> dict | None:
    """`SweepResult.field_fit` of the harmonic fits ``fit`` (None: the linear model)."""
    if fit is None:
        return None
    return {
        "degree": np.where(fit.use, fit.degree, 0).astype(np.int64),
        "residual_T": np.asarray(fit.residual_T, dtype=np.float64),
        "neighbours": int(fit.k),
        "fallback_rule": fit.fallback_rule,
        "reach_rule": getattr(fit, "reach_rule", "a trial beyond the node's reach is outside"),
    }


def sweep_gradients(mesh: SimplexMesh, B: np.ndarray, fit=None) -> np.ndarray:
    """Node gradients of the field model (the GUM figure's): `node_gradients` of the linear
    interpolant, or the linear term of each node's harmonic fit where it holds.

    Returns
    -------
    ndarray, shape (n, 3, 3), T/mm, ``[i, c, j] = dB_c/dx_j``
    """
    if fit is not None and fit.use.all():  # no node takes the linear interpolant
        grad = np.empty((len(B), 3, 3))
    else:
        grad = node_gradients(mesh, B)
    if fit is not None:
        from ...models.harmonic_basis import field_basis

        lin = np.ascontiguousarray(field_basis()[:, 1:4, :])  # monomials x, y, z
        use = np.flatnonzero(fit.use)
        for a in range(0, len(use), 1 << 16):
            i = use[a : a + (1 << 16)]
            grad[i] = np.einsum("caj,nj->nca", lin, fit.coef[i]) / fit.scale[i, None, None]
    return grad


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


def _htm_arrays(cfg: SweepConfig, fm: FieldMap):
    """Bench arrays of mode htm for `SweepProblem`, and the nodes the bench cannot reach."""
    from ...io.bench_toml import read_reference_bench  # the packaged default bench
    from ...models.kinematics.geometry import draw_error_sets, kernel_geometry, noise_keys

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
    rot = np.ascontiguousarray(bench.bench_to_magnet_rotation())
    arrays = dict(
        trials=HtmTrials(rot, q, params, terms, nkey, fkey),
        terms_zero=terms_zero,
        geo=g,
        bench_name=bench.name,
    )
    return arrays, bench.outside_stroke(q)
