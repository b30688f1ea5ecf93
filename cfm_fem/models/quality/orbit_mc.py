"""Uncertainty of a dipole's deflection: the orbit through the map a bench measures.

A measured map holds at node j the reading B_j + dB_j, dB_j the reading error of the trial (the
node read at its place moved by the bench, through the probe). The orbit of `track` runs through
the model between the map's nodes, which is linear in the node values (the linear interpolant;
each node's harmonic fit at its degree), so the error field along the orbit is a linear image
of the dB_j, and to first order in it the exit direction moves by

    dt_end = k sum_s w_s t_s x dB(r_s),      k = q / (1000 B rho),

over the field readings of the orbit's Runge-Kutta stages r_s, with their directions t_s and
their weights w_s in the steps (h / 6, h / 3, h / 3, h / 6).
`orbit_response` builds that linear map once: the nodes whose readings the orbit uses and the
matrix (3, 3 u) from their errors to dt_end. `deflection_deviations` draws the readings of those
nodes trial by trial as the field-quality Monte Carlo does (`cfm_fem.models.quality.uncertainty`:
the same displacements of trial t and the same probe draw) and returns the deviation of the
deflection of each trial.

First order: the orbit's own move (a change of the field it samples of the order of the field
gradient times the move) and the turn of dt within the magnet (of the order of the deflection
times dt) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.spatial

from ... import _kernels
from ...errors import CfmInputError
from ..harmonic import HarmonicFit, neighbourhoods
from ..harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents
from ..interpolation import LinearInterpolator, interpolate_points
from .sampling import LocalField

__all__ = ["OrbitField", "OrbitResponse", "orbit_response", "deflection_deviations"]

#: Unit readings fitted per kernel call when the harmonic fits' linear maps are built.
_UNIT_BLOCK = 4096


@dataclass
class OrbitResponse:
    """Linear map from the reading errors of the nodes an orbit uses to its exit direction.

    Attributes
    ----------
    nodes : ndarray, shape (u,), int64
        Indices of the map's nodes whose readings the orbit's field uses.
    matrix : ndarray, shape (3, 3 u), 1 / T
        dt_end = matrix @ dB, dB the errors (T) of those nodes, node after node, (x, y, z).
    exit_tangent : ndarray, shape (3,)
        Unit exit direction of the nominal orbit.
    """

    nodes: np.ndarray
    matrix: np.ndarray
    exit_tangent: np.ndarray


def _exit_tangent(orbit) -> np.ndarray:
    """Unit exit direction of an orbit of `track`, from its deflection components."""
    ax, ay = orbit["deflection_x_mrad"] * 1e-3, orbit["deflection_y_mrad"] * 1e-3
    t = np.array([np.tan(ax), np.tan(ay), 1.0])
    return t / np.linalg.norm(t)


def _cross_matrix(t) -> np.ndarray:
    """[t]_x (n, 3, 3): [t]_x v = t x v."""
    out = np.zeros(t.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -t[..., 2], t[..., 1]
    out[..., 1, 0], out[..., 1, 2] = t[..., 2], -t[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -t[..., 1], t[..., 0]
    return out


def _linear_weights(interp: LinearInterpolator, path):
    """(nodes (n, d+1), weights (n, d+1)) of the linear interpolant at the orbit's points."""
    mesh = interp.mesh
    _, inside = interp.field_at(path)
    if not inside.all():
        raise CfmInputError("the trajectory leaves the linear interpolant of the map")
    local = np.ascontiguousarray(mesh.to_local(path))
    tree = scipy.spatial.cKDTree(mesh.coords)
    _, near = tree.query(local)
    ones = np.ones((len(mesh.coords), 1))
    _, cell = interpolate_points(mesh, ones, local, mesh.node_cell[near])
    if np.any(cell < 0):  # a walk blocked by the border: the interpolant's own search
        bad = np.flatnonzero(cell < 0)
        cell[bad] = interp._cells_around(local[bad])
    tr = mesh.transform[cell]  # (n, d+1, d)
    d = mesh.dim
    lam = np.einsum("nij,nj->ni", tr[:, :d], local - tr[:, d])
    lam = np.column_stack([lam, 1.0 - lam.sum(axis=1)])
    return mesh.simplices[cell], lam


def _harmonic_maps(fit: HarmonicFit, g):
    """Linear maps P (len(g), NB, 3 k) of the nodes g's fits (at their degrees) from their
    neighbours' values, and the neighbours (len(g), k)."""
    pts = fit.centers
    tree = scipy.spatial.cKDTree(pts)
    nbr, scale = neighbourhoods(tree, pts, pts[g], fit.k)
    k = fit.k
    gmat = np.ascontiguousarray(field_basis(MAX_DEGREE))
    exps = monomial_exponents(MAX_DEGREE)
    nb = gmat.shape[2]
    maps = np.zeros((len(g), nb, 3 * k))
    # one fit per (node, unit reading): the neighbours' points, one of them reading a unit
    # component, the others zero
    unit = np.zeros((3 * k, k, 3))
    unit.reshape(3 * k, 3 * k)[np.arange(3 * k), np.arange(3 * k)] = 1.0
    for deg in np.unique(fit.degree[g]):
        sel = np.flatnonzero(fit.degree[g] == deg)
        per = max(1, _UNIT_BLOCK // (3 * k))
        for a in range(0, sel.size, per):
            s = sel[a : a + per]
            m = s.size * 3 * k
            p_ext = np.repeat(pts[nbr[s]], 3 * k, axis=0).reshape(m * k, 3)
            b_ext = np.tile(unit.reshape(-1, 3), (s.size, 1))
            nbr_ext = np.arange(m * k, dtype=np.int64).reshape(m, k)
            cen = np.repeat(pts[g[s]], 3 * k, axis=0)
            sc = np.repeat(scale[s], 3 * k)
            coef = _kernels.harmonic_fit_block(cen, sc, nbr_ext, p_ext, b_ext, gmat, exps,
                                               int(deg), int(deg))[0]  # fmt: skip
            nd = coef.shape[1]  # basis fields up to the degree; zero past it
            maps[s, :nd] = coef.reshape(s.size, 3 * k, nd).transpose(0, 2, 1)
    return maps, nbr


def _harmonic_weights(fit: HarmonicFit, path):
    """(nodes (n, 3 k) as node indices (n, k), weights (n, 3, 3 k)) of the harmonic model at
    the orbit's points: the field there from the values of the neighbours of its node."""
    idx, used, tree = fit._used
    near, dist = neighbourhoods(tree, used, path, 1)
    g_all = idx[near[:, 0]]
    if np.any(dist > fit.reach_mm[g_all]):
        raise CfmInputError("the trajectory leaves the harmonic model of the map")
    g, which = np.unique(g_all, return_inverse=True)
    maps, nbr = _harmonic_maps(fit, g)
    gmat = field_basis(MAX_DEGREE)
    exps = monomial_exponents(MAX_DEGREE)
    u = (path - fit.centers[g_all]) / fit.scale[g_all, None]
    mono = np.prod(u[:, None, :] ** exps[None], axis=-1)  # (n, M)
    basis = np.einsum("cmb,nm->ncb", gmat, mono)  # (n, 3, NB)
    return nbr[which], np.einsum("ncb,nbq->ncq", basis, maps[which])


class OrbitField:
    """The field an orbit reads: a node's harmonic model where its reach holds the point, the
    linear interpolant of the map elsewhere (where the planes of a map lie further apart than
    twice the reach of their nodes' models, or a node falls back to linear).

    Parameters
    ----------
    fit : HarmonicFit
    fieldmap : FieldMap
        The map ``fit`` was fitted to (its linear interpolant is built when first needed).

    Attributes
    ----------
    reads, linear_reads : int
        Points read, and those read from the linear interpolant.
    """

    def __init__(self, fit: HarmonicFit, fieldmap):
        self.fit, self.fieldmap = fit, fieldmap
        self._linear = None
        self.reads = self.linear_reads = 0

    @property
    def linear(self) -> LinearInterpolator:
        if self._linear is None:
            self._linear = LinearInterpolator(self.fieldmap)
        return self._linear

    def field_at(self, points):
        """``(B (m, 3) T, inside (m,))`` at ``points`` (m, 3) mm."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        b, inside = self.fit.field_at(pts)
        miss = np.flatnonzero(~inside)
        if miss.size:
            b[miss], inside[miss] = self.linear.field_at(pts[miss])
        self.reads += len(pts)
        self.linear_reads += int(miss.size)
        return b, inside


def _assemble(parts, orbit) -> OrbitResponse:
    """`OrbitResponse` from (nodes (n, w), per-stage maps (n, 3, 3 w)) of groups of stages."""
    nodes = np.concatenate([p[0].ravel() for p in parts])
    uniq, inv = np.unique(nodes, return_inverse=True)
    matrix = np.zeros((3, 3 * uniq.size))
    at = 0
    for nd, per_point in parts:
        j = inv[at : at + nd.size].reshape(nd.shape)
        at += nd.size
        cols = (3 * j[..., None] + np.arange(3)).reshape(len(nd), -1)
        for c in range(3):
            np.add.at(matrix[c], cols.ravel(), per_point[:, c, :].ravel())
    return OrbitResponse(uniq.astype(np.int64), matrix, _exit_tangent(orbit))


def orbit_response(model, orbit: dict) -> OrbitResponse:
    """The linear map of the module docstring for an orbit of `track` through ``model``.

    Parameters
    ----------
    model : HarmonicFit, LinearInterpolator or OrbitField
        The field the orbit ran through.
    orbit : dict
        `track` output: the field is read at its Runge-Kutta stages (``stages``), weighted as
        the steps weight them (``stage_weights_mm``).

    Returns
    -------
    OrbitResponse
    """
    path, tangent = orbit["stages"][:, :3], orbit["stages"][:, 3:]
    k = orbit["charge"] / (1000.0 * orbit["rigidity_Tm"])
    cross = _cross_matrix(tangent) * (k * orbit["stage_weights_mm"])[:, None, None]  # (n, 3, 3)
    if isinstance(model, OrbitField):
        harmonic = model.fit.field_at(path)[1]
        fit, linear = model.fit, model.linear if not harmonic.all() else None
    elif isinstance(model, HarmonicFit):
        harmonic, fit, linear = np.ones(len(path), dtype=bool), model, None
    elif isinstance(model, LinearInterpolator):
        harmonic, fit, linear = np.zeros(len(path), dtype=bool), None, model
    else:
        raise CfmInputError("the deflection's uncertainty needs the harmonic or linear model")
    parts = []
    if harmonic.any():
        nodes, wts = _harmonic_weights(fit, path[harmonic])  # (n, k), (n, 3, 3 k)
        parts.append((nodes, np.einsum("nij,njq->niq", cross[harmonic], wts)))
    if not harmonic.all():
        nodes, lam = _linear_weights(linear, path[~harmonic])  # (n, d+1)
        wts = np.einsum("nv,ij->nivj", lam, np.eye(3)).reshape(len(nodes), 3, -1)
        parts.append((nodes, np.einsum("nij,njq->niq", cross[~harmonic], wts)))
    return _assemble(parts, orbit)


def deflection_deviations(resp: OrbitResponse, model, node_points, node_values, read,
                          trials: int, chunk: int) -> np.ndarray:  # fmt: skip
    """Deflection of each trial's measured map minus the nominal one, mrad.

    Parameters
    ----------
    resp : OrbitResponse
    model : object
        The model between nodes (readings at displaced nodes, `LocalField`).
    node_points, node_values : ndarray, shape (n, 3), mm and T
        The map's nodes and values.
    read : callable
        ``read(local, t0, m) -> B (m, u, 3)``: readings of trials t0 .. t0 + m - 1 at the
        nodes of ``local`` (`LocalField` over ``resp.nodes``), displaced and through the probe.
    trials : int
    chunk : int
        Trials at a time.

    Returns
    -------
    ndarray, shape (trials,), mrad
        NaN where a reading left the model.
    """
    local = LocalField(model, node_points[resp.nodes], node_values[resp.nodes])
    t0_dir = resp.exit_tangent
    theta0 = np.arccos(np.clip(t0_dir[2], -1.0, 1.0))
    out = np.empty(trials)
    for t0 in range(0, trials, chunk):
        m = min(chunk, trials - t0)
        db = read(local, t0, m) - node_values[resp.nodes][None]  # (m, u, 3)
        t = t0_dir[None] + db.reshape(m, -1) @ resp.matrix.T
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        out[t0 : t0 + m] = (np.arccos(np.clip(t[:, 2], -1.0, 1.0)) - theta0) * 1e3
    return out
