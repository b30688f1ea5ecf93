"""Bench-model sweep (mode htm): probe errors from the 21-error HTM chain plus vibration/delay."""

from __future__ import annotations

import numba as nb
import numpy as np

from .htm import probe_error_mm
from .interpolate import _interp_in, walk_block3
from .kinematics_passes import _chain
from .locate import MAX_STAR, OUTSIDE, WALK_FAILED, locate, locate_exact, settle_walk
from .options import JIT
from .order_stats import coverage_count, sample_stats
from .rng import _delay_tau, normals_by_key, trial_key
from .star import STAR_HASH, build_star, star_find
from .sweep import _abs_change, sweep_outputs


@nb.njit(inline="always", **JIT)
def _probe_points(
    g, qg, gk, n_trials, z, tkeys, params, terms, zero, use_geometric, use_noise, geo, rot,
    basis, coords, start_cells, dq, e, dm, s1, s2, sx, pts, starts,
):  # fmt: skip
    """Probe error of every trial at node g (bench model, `htm_sweep`), rotated into the map:
    the perturbed points ``pts`` (n_trials, d), their start cells (by octant), and the sums
    s1, s2 and cross sums sx (xy, xz, yz) of the map-frame errors, mm."""
    d = coords.shape[1]
    stack, mounts, tool = geo.stack, geo.mounts, geo.tool
    strokes, profiles = geo.strokes, geo.profiles
    sig, speed, tau_code, tau_par = geo.sig, geo.speed, geo.tau_code, geo.tau_par
    for t in range(n_trials):
        for a in range(3):
            dq[a] = sig[a] * z[a, t]
        if use_noise and tau_code >= 0:  # eq. 9 delay, as in axis_noise_mm
            tau = _delay_tau(tkeys[t], gk, tau_code, tau_par)
            for a in range(3):
                dq[a] += speed[a] * tau
        if terms.shape[0] > 0:
            tt = t if use_geometric else 0
            e[0], e[1], e[2], _norm = _chain(terms, tt, qg[0], qg[1], qg[2], dq[0], dq[1], dq[2])
        else:
            prm = params[t] if use_geometric else zero
            probe_error_mm(prm, qg, dq, stack, mounts, tool, strokes, profiles, e)
        octant = 0
        for a in range(3):
            dm[a] = rot[a, 0] * e[0] + rot[a, 1] * e[1] + rot[a, 2] * e[2]
            s1[a] += dm[a]
            s2[a] += dm[a] * dm[a]
        sx[0] += dm[0] * dm[1]
        sx[1] += dm[0] * dm[2]
        sx[2] += dm[1] * dm[2]
        for a in range(d):
            acc = 0.0
            for c in range(3):
                acc += basis[c, a] * dm[c]
            pts[t, a] = coords[g, a] + acc
            if acc < 0.0:
                octant |= 1 << a
        starts[t] = start_cells[g, octant]


@nb.njit(inline="always", **JIT)
def _place_exits(
    g, n_trials, pts, starts, cells, bary, coords, values, simplices, transform, neighbors,
    start_cells, search, scells, lmat, dmat, nbr, htab, delta,
):  # fmt: skip
    """Non-convex mesh: trials that left it near node g are placed in its star (built at the
    first such exit, `build_star`, `star_find`), the others by `locate_exact`."""
    d = coords.shape[1]
    reach = search[1]
    n_star = -2  # the star of g, built at the first exit near g
    for t in range(n_trials):
        if cells[t] != OUTSIDE:
            continue
        n2 = 0.0
        for a in range(d):
            n2 += (pts[t, a] - coords[g, a]) ** 2
        if n2 < reach[g] ** 2:  # nearer to g than any other cell: in its star or out
            if n_star == -2:
                n_star = build_star(g, start_cells[g, 0], simplices, transform, neighbors,
                                    values, scells, lmat, dmat, nbr, htab)  # fmt: skip
            if n_star > 0:
                cells[t] = star_find(pts[t], g, coords, transform, scells, n_star, lmat,
                                     delta, bary[t])  # fmt: skip
                continue
        cells[t] = locate_exact(pts[t], starts[t], transform, neighbors, bary[t], search)


@nb.njit(inline="always", **JIT)
def _trial_errors(
    i, g, n_trials, pts, cells, bary, coords, values, simplices, transform, search, exit_grad,
    b0, abs0, bi, comp, absb, n_out,
):  # fmt: skip
    """Field errors of the placed trials of node g (row i): components into comp[:, :nv] and
    |B| changes into absb[:nv] (outside trials counted in ``n_out``, left out or given the
    node's Taylor expansion). Returns nv."""
    d = coords.shape[1]
    nv = 0
    for t in range(n_trials):
        s = cells[t]
        if s == WALK_FAILED:  # rare: a walk that cycled (non-Delaunay meshes only)
            s = settle_walk(pts[t], transform, search, bary[t])
        if s == OUTSIDE:
            n_out[i, 0] += 1
            if exit_grad.shape[0] == 0:
                continue
            for c in range(3):  # the Taylor expansion at the node
                e0 = 0.0
                for a in range(d):
                    e0 += exit_grad[g, c, a] * (pts[t, a] - coords[g, a])
                comp[c, nv] = e0
        else:
            _interp_in(s, bary[t], simplices, values, bi)
            for c in range(3):
                comp[c, nv] = bi[c] - b0[c]
        absb[nv] = _abs_change(b0, comp[0, nv], comp[1, nv], comp[2, nv], abs0)
        nv += 1
    return nv


@nb.njit(inline="always", **JIT)
def _position_moments(n_trials, s1, s2, sx, pos_i):
    """Mean (row 0), standard deviation (row 1) and correlations xy, xz, yz (row 2) of the
    map-frame probe errors from their sums, into ``pos_i`` (3, 3)."""

    bessel = n_trials / max(n_trials - 1, 1)
    for a in range(3):
        mean = s1[a] / n_trials
        pos_i[0, a] = mean
        pos_i[1, a] = np.sqrt(max(s2[a] / n_trials - mean * mean, 0.0) * bessel)
    for j in range(3):
        a, b = (0, 0, 1)[j], (1, 2, 2)[j]
        sd = pos_i[1, a] * pos_i[1, b]
        cov = (sx[j] / n_trials - pos_i[0, a] * pos_i[0, b]) * bessel
        pos_i[2, j] = min(max(cov / sd, -1.0), 1.0) if sd > 0.0 else 0.0


@nb.njit(**JIT)
def htm_buffers(k_nodes, params, nkey, d):
    """Work arrays of the mode-htm kernels: probe-error moments per node (NaN), a zero error
    set, 3-vectors dq, e, dm, the trials' noise keys, normals z and their flags ok, the probe
    points (n_trials, d) and their start cells."""
    n_trials = params.shape[0]
    tkeys = np.empty(n_trials, dtype=np.uint64)
    for t in range(n_trials):
        tkeys[t] = trial_key(nkey, t)
    return (
        np.full((k_nodes, 3, 3), np.nan),
        np.zeros(params.shape[1]),
        np.zeros(3),
        np.empty(3),
        np.empty(3),
        tkeys,
        np.zeros((3, n_trials)),
        np.empty(n_trials, dtype=np.bool_),
        np.empty((n_trials, d)),
        np.empty(n_trials, dtype=np.int64),
    )


@nb.njit(**JIT)
def htm_sweep(nodes, keys, mesh, trials, geo, use_geometric, use_noise, p, exit_grad, search):
    """Monte Carlo of B(x + E_p) - B(x) with E_p from the bench model, statistics per node.

    Trial t uses error amplitudes ``params[t]`` for every node (a real bench has one set of
    geometric errors per scan) and the per-(trial, node) vibration and delay of
    `axis_noise_mm` (the node's key as the point index), so maps are reproducible from the seed.

    Parameters
    ----------
    nodes : ndarray, shape (k,), int64
    keys : ndarray, shape (k,), int64
        Noise-stream id (point index) of each node: its index in the whole map, as in
        `gauss_sweep`.
    mesh : SweepMesh
        Named tuple (coords, values, simplices, transform, neighbors, start_cells, basis), the
        mesh arrays of `gauss_sweep` (`cfm_fem.workflows.sweep.problem.SweepMesh`).
    trials : HtmTrials
        Named tuple (`cfm_fem.workflows.sweep.problem.HtmTrials`) of

        - rot : ndarray, shape (3, 3): bench frame -> map (magnet) frame;
        - q_nodes : ndarray, shape (n, 3), mm: commanded axis positions that bring the probe to
          each node;
        - params : ndarray, shape (T, 21): error amplitudes per trial
          (`cfm_fem.models.kinematics.geometry.draw_error_sets`);
        - terms : ndarray, shape (T, 21) or (1, 21) or (0, 21): when the bench's error profiles
          are constant, `trial_terms` of ``params`` (or of one row of zeros when
          ``use_geometric`` is False), and each sample costs the 18 multiply-adds of the
          collapsed chain (`_chain`) instead of the 18 sines and cosines of `probe_error_mm`:
          the same probe error up to rounding. Empty: `probe_error_mm`;
        - nkey, fkey : uint64: noise keys, as in `axis_noise_mm`.
    geo : KernelGeometry
        Bench geometry (`probe_error_mm`) and noise model (`axis_noise_mm`),
        `cfm_fem.models.kinematics.geometry.kernel_geometry`.
    use_geometric, use_noise : bool
        Include the 21 geometric errors / the vibration and delay (to split the two parts).
    p : float
        Coverage probability.
    exit_grad : ndarray, shape (n, 3, d) or (0, 3, d), T/mm
        As in `gauss_sweep`: trials that leave the mesh left out (empty) or given the node's
        first-order Taylor expansion; counted in ``n_out`` either way.
    search : tuple
        As in `gauss_sweep`. A trial that leaves the mesh where that is no proof is placed by
        `star_find` when nearer to its node than any other cell (`node_reach`), else by
        `locate_exact`.

    Returns
    -------
    stats : ndarray, shape (k, 1, 4, 6), T
    n_out, n_lost : ndarray, shape (k, 1), int64
        As `gauss_sweep` (n_lost: 0, failed walks are settled by `settle_walk`).
    pos : ndarray, shape (k, 3, 3)
        Over all trials, per map axis: mean (row 0, mm) and standard deviation (row 1, mm) of
        the probe error, and (row 2) its correlation coefficients xy, xz, yz (0 where an
        axis does not vary): the linearised (GUM) figure needs the covariance, as the
        geometric errors move the probe along several axes at once.
    """
    coords, values, simplices, transform, neighbors, start_cells, basis = mesh
    rot, q_nodes, params, terms, nkey, fkey = trials
    k_nodes = nodes.shape[0]
    n_trials = params.shape[0]
    d = coords.shape[1]
    stats, n_out, n_lost, _ = sweep_outputs(k_nodes, 1)
    comp = np.empty((3, n_trials))
    absb = np.empty(n_trials)
    scratch = np.empty(n_trials)
    bi = np.empty(3)
    # per node, all trials at once: the noise by the block generator (`axis_noise_mm`'s
    # numbers), then the probe points, then their walks (`walk_block3` in 3-D)
    pos, zero, dq, e, dm, tkeys, z, ok, pts, starts = htm_buffers(k_nodes, params, nkey, d)
    cells = np.empty(n_trials, dtype=np.int64)
    act = np.empty(n_trials, dtype=np.int64)
    bary = np.empty((n_trials, d + 1))
    excess = search[0]
    scells = np.empty(MAX_STAR, dtype=np.int64)  # star tables (`build_star`), non-convex mesh
    lmat = np.empty((MAX_STAR, d, d))
    dmat = np.empty((MAX_STAR, 3, d))
    nbr = np.empty((MAX_STAR, d), dtype=np.int64)
    htab = np.full((3, STAR_HASH), -1, dtype=np.int64)
    delta = np.empty(d)
    for i in range(k_nodes):
        g = nodes[i]
        if start_cells[g, 0] < 0:
            continue
        b0 = values[g]
        abs0 = np.sqrt(b0[0] ** 2 + b0[1] ** 2 + b0[2] ** 2)
        gk = keys[i]
        if use_noise:
            normals_by_key(tkeys, fkey, gk, n_trials, z, ok)
        s1 = np.zeros(3)
        s2 = np.zeros(3)
        sx = np.zeros(3)  # cross sums xy, xz, yz
        qg = q_nodes[g]
        _probe_points(
            g, qg, gk, n_trials, z, tkeys, params, terms, zero, use_geometric, use_noise, geo,
            rot, basis, coords, start_cells, dq, e, dm, s1, s2, sx, pts, starts,
        )  # fmt: skip
        if d == 3:
            walk_block3(pts, 0, n_trials, starts, transform, neighbors, cells, act, bary)
        else:
            for t in range(n_trials):
                cells[t] = locate(pts[t], starts[t], transform, neighbors, bary[t])
        if excess.shape[0] > 0:  # non-convex mesh: is an exit a proof?
            _place_exits(
                g, n_trials, pts, starts, cells, bary, coords, values, simplices, transform,
                neighbors, start_cells, search, scells, lmat, dmat, nbr, htab, delta,
            )  # fmt: skip
        nv = _trial_errors(
            i, g, n_trials, pts, cells, bary, coords, values, simplices, transform, search,
            exit_grad, b0, abs0, bi, comp, absb, n_out,
        )  # fmt: skip
        _position_moments(n_trials, s1, s2, sx, pos[i])
        q = coverage_count(nv, p) if nv > 1 else 1
        for c in range(3):
            sample_stats(comp[c], nv, q, stats[i, 0, c], scratch)
        sample_stats(absb, nv, q, stats[i, 0, 3], scratch)
    return stats, n_out, n_lost, pos
