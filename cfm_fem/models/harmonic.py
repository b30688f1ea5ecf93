"""Local harmonic field model of a 3-D field map: one Maxwell-consistent polynomial per node.

Around each node g the field is modelled as B(x) = sum_j coef[g, j] F_j((x - x_g) / scale_g),
with F_j the gradients of harmonic polynomials (`cfm_fem.models.harmonic_basis`), so div B and
curl B are exactly zero. The coefficients are the least-squares fit to the three components at
the node's k nearest nodes (the node included), weighted from 1 at the node to 1e-4 at the
k-th neighbour (`cfm_fem._kernels.FIT_TAPER`), of the degree 2 .. 5 that the neighbourhood
supports and that predicts left-out neighbours best (`cfm_fem._kernels.harmonic_fit`).

Neighbourhoods are the k nearest nodes ordered by (distance, x, y, z), ties at the k-th
distance broken the same way, so the fit of a node does not depend on the map's row order;
``scale`` is the distance to the k-th nearest node, so the fit's displacements lie in the unit
ball.

Reach: a node's model is used up to half the distance to its k-th nearest node
(`REACH_FRACTION`); displacements beyond it are outside the model.

Unequal steps: on a full grid whose steps along one axis exceed `ANISOTROPY_MAX` times the
finest (an FEM export 1.5 mm apart across the bore and 10 mm along it), the k nearest nodes
all lie in one plane, so the fits describe the field across the plane and guess it along the
coarse axis, and the points between planes lie beyond every reach. With ``metric="grid"``
(`grid_metric`) neighbourhoods, nearness and reach are measured in steps (coordinates scaled
so that every axis's step is the finest): a neighbourhood then spans as many planes along
the coarse axis as across it, which determines the field's derivatives along every axis
alike. Below that ratio the k nearest nodes already span three planes along every axis and
millimetres serve. The fits themselves stay in millimetres (Laplace's equation is not
scale-free per axis).

Fallback: Laplace's equation fails where currents or iron lie inside the neighbourhood, or
the export is noisy; there the node falls back to the linear interpolant (``use`` False). The
rule (`FALLBACK_RULE`), with r the weighted RMS residual over the neighbours' components:

* curl check: r of the harmonic fit of degree 2 exceeds `CURL_RATIO` times r of an
  unconstrained quadratic fit of each component (3 x 10 free coefficients against the
  harmonic 15) of the same neighbourhood, and r of the chosen fit (degree up to 5) is no
  smaller than the unconstrained quadratic's. A harmonic field gives a ratio of about 1 (at
  most 1.47 over the 46,051 nodes of the bundled quadrupole map); a uniform current density
  of 0.8 A/mm^2 (3.2 A/mm^2) in a conductor holding the neighbourhood, on top of the bundled
  map's field, gives at least 4.4 (17). The second condition keeps the one-sided
  neighbourhoods of a grid's edges, where strong high-order terms can lift the degree-2 ratio
  above 3 although the field is harmonic: there the chosen fit beats the quadratic, while a
  current leaves every harmonic fit behind it.
* misfit check: r of the chosen fit exceeds `MISFIT_REL` of the RMS variation of B over the
  neighbourhood (at most 6.5e-4 over the bundled map): a field jump at an iron surface, or
  noise comparable with the field's variation, that the smooth model cannot follow (a
  tangential jump of 0.01 T across a plane through a neighbourhood, in a field of RMS
  variation 0.018 T over it, gives about 0.1).
* or no degree >= ``min_degree`` could be fitted (too few or coplanar neighbours).

Residuals below `ROUNDING_FLOOR` of the RMS field over the neighbourhood are rounding and never
fail a check.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np

from .. import _kernels
from ..errors import CfmInputError
from ..threads import map_blocks
from .harmonic_basis import MAX_DEGREE, field_basis, monomial_exponents, n_basis

__all__ = [
    "HarmonicFit",
    "fit_harmonic",
    "neighbourhoods",
    "fallback_mask",
    "FALLBACK_RULE",
    "REACH_FRACTION",
    "CURL_RATIO",
    "MISFIT_REL",
    "ROUNDING_FLOOR",
    "MIN_NODES",
    "ANISOTROPY_MAX",
    "grid_metric",
    "time_fit",
]

#: Reach of a node's model, as a fraction of the distance to its k-th nearest node.
REACH_FRACTION = 0.5
#: Curl check: harmonic over unconstrained quadratic fit residual above this fails Laplace.
CURL_RATIO = 3.0
#: Misfit check: fit residual over the field's RMS variation in the neighbourhood.
MISFIT_REL = 0.02
#: Residuals below this fraction of the RMS field of the neighbourhood are rounding.
ROUNDING_FLOOR = 1e-9
#: Fewest nodes (and neighbours per fit) the model accepts: the curl check fits 10
#: coefficients per component with at least 2 equations each.
MIN_NODES = 20
#: A full grid with a step beyond this multiple of its finest is measured in steps: the 40
#: nearest nodes of a grid with one step 3.6 times the other two all lie in one plane.
ANISOTROPY_MAX = 3.0

FALLBACK_RULE = (
    f"a node falls back to the linear interpolant when the RMS residual of its harmonic fit "
    f"of degree {_kernels.FIT_CHECK_DEGREE} exceeds {CURL_RATIO:g} times that of an "
    f"unconstrained polynomial fit of the same degree and neighbours and its chosen fit does "
    f"no better than that unconstrained fit (curl), or the residual of "
    f"its chosen fit exceeds {MISFIT_REL:g} of the RMS variation of B over its neighbours "
    f"(misfit), or no fit of the lowest degree is determined; residuals below "
    f"{ROUNDING_FLOOR:g} of the RMS field are rounding"
)

_NBR_MARGIN = 8  # extra candidates per query, to see ties at the k-th distance
_QUERY_CHUNK = 32768  # nodes per neighbour query: bounds the memory of the neighbour arrays
_FIT_BLOCK = 64  # nodes per kernel call on a thread
_EVAL_CHUNK = 16384  # points per chunk of `HarmonicFit.field_at`


@dataclass
class HarmonicFit:
    """Harmonic field models of every node of a map (`fit_harmonic`).

    Attributes
    ----------
    centers : ndarray, shape (n, 3), mm
        The nodes (map frame).
    scale : ndarray, shape (n,), mm
        Length scale: u = (x - centers[g]) / scale[g].
    coef : ndarray, shape (n, NB), float64, T
        Coefficients of the basis fields, NB = n_basis(MAX_DEGREE); zeros past the degree.
    degree : ndarray, shape (n,), int64
        Field degree used, 2 .. 5.
    residual_T : ndarray, shape (n,), T
        RMS residual of the fit over its neighbours' components, weighted as the fit
        (weights normalised to sum 1; NaN if no fit).
    reach_mm : ndarray, shape (n,), mm
        Displacements beyond it are outside the model's reach (measured in the frame of
        ``metric``).
    use : ndarray, shape (n,), bool
        False: Laplace fails here (`FALLBACK_RULE`); the node falls back to linear.
    k : int
        Neighbours per fit.
    fallback_rule : str
        The fallback rule, in words, for outputs.
    metric : ndarray, shape (3,)
        Factors on x, y, z in which neighbourhoods, nearness and reach are measured (ones:
        millimetres; `grid_metric`).
    """

    centers: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    degree: np.ndarray
    residual_T: np.ndarray
    reach_mm: np.ndarray
    use: np.ndarray
    k: int
    fallback_rule: str = field(default=FALLBACK_RULE)
    metric: np.ndarray = field(default_factory=lambda: np.ones(3))

    @cached_property
    def _used(self) -> tuple:
        """Indices of the nodes with ``use``, their centres (times ``metric``) and a k-d tree
        of them: query it with points times ``metric``."""
        import scipy.spatial

        idx = np.flatnonzero(self.use)
        cen = self.centers[idx] * self.metric
        return idx, cen, scipy.spatial.cKDTree(cen)

    def field_at(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Field of the model of the nearest node with ``use`` True, within its reach.

        Of equidistant nodes, the first in (x, y, z) order: the answer does not depend on the
        map's row order.

        Parameters
        ----------
        points : array_like, shape (m, 3), mm

        Returns
        -------
        B : ndarray, shape (m, 3), T
            NaN where ``inside`` is False.
        inside : ndarray, shape (m,), bool
            The nearest usable node's reach holds the point.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full((len(pts), 3), np.nan)
        inside = np.zeros(len(pts), dtype=bool)
        idx, used, tree = self._used
        if idx.size == 0:
            return out, inside
        gmat = field_basis(MAX_DEGREE)
        exps = monomial_exponents(MAX_DEGREE)
        for a in range(0, len(pts), _EVAL_CHUNK):
            p = pts[a : a + _EVAL_CHUNK]
            near, dist = neighbourhoods(tree, used, p * self.metric, 1)
            g = idx[near[:, 0]]
            u = (p - self.centers[g]) / self.scale[g, None]
            ok = dist <= self.reach_mm[g]
            nodes, inv = np.unique(g[ok], return_inverse=True)
            cexp = np.einsum("cmj,nj->ncm", gmat, self.coef[nodes])  # (nodes, 3, M)
            val = np.empty((int(ok.sum()), 3))
            _kernels.poly_points(cexp, inv.astype(np.int64), exps, np.ascontiguousarray(u[ok]),
                                 val)  # fmt: skip
            out[a : a + len(p)][ok] = val
            inside[a : a + len(p)] = ok
        return out, inside


def _check_map(points, B, k, min_degree, max_degree, source):
    """Clean float64 arrays, or `CfmInputError` naming what the harmonic model cannot use."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    B = np.ascontiguousarray(B, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or B.shape != points.shape:
        raise CfmInputError(
            f"the harmonic field model needs points and B of shape (n, 3); got {points.shape} "
            f"and {B.shape}", file=source,
        )  # fmt: skip
    if not (np.isfinite(points).all() and np.isfinite(B).all()):
        raise CfmInputError("the harmonic field model needs finite points and B", file=source)
    if len(points) < MIN_NODES:
        raise CfmInputError(
            f"the harmonic field model needs a 3-D map of at least {MIN_NODES} nodes; "
            f"this one has {len(points)}", file=source,
        )  # fmt: skip
    # thickness of the cloud across its thinnest direction, relative to its extent
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if sv[2] <= 1e-9 * sv[0]:
        raise CfmInputError(
            f"the harmonic field model needs a 3-D map; the {len(points)} nodes lie in one "
            "plane (use the linear field model)", file=source,
        )  # fmt: skip
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < MIN_NODES:
        raise CfmInputError(f"k must be an integer >= {MIN_NODES}; got {k!r}")
    if not 2 <= min_degree <= max_degree <= MAX_DEGREE:
        raise CfmInputError(
            f"degrees must satisfy 2 <= min_degree <= max_degree <= {MAX_DEGREE}; got "
            f"{min_degree} and {max_degree}"
        )
    return points, B


def neighbourhoods(tree, points, centres, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest nodes of each centre, in an order independent of the map's row order.

    Sorted by squared distance, then x, y, z. Where ties at the k-th distance (a grid's
    shells) may run past the queried candidates, the query is repeated with twice as many.

    Parameters
    ----------
    tree : scipy.spatial.cKDTree
        Over ``points``.
    points : ndarray, shape (N, 3), mm
    centres : ndarray, shape (m, 3), mm
    k : int
        <= N.

    Returns
    -------
    nbr : ndarray, shape (m, k), int64
        Indices into ``points``, nearest first.
    scale : ndarray, shape (m,), mm
        Distance to the k-th.
    """
    n = len(points)
    nbr = np.empty((len(centres), k), dtype=np.int64)
    d2k = np.empty(len(centres))
    todo = np.arange(len(centres))
    kq = min(k + _NBR_MARGIN, n)
    while todo.size:
        _, cand = tree.query(centres[todo], kq, workers=numba.get_num_threads())
        cand = cand.reshape(len(todo), kq)
        cen = centres[todo]

        def block(i0, i1, cand=cand, cen=cen):
            return _kernels.canonical_neighbours(points, cen[i0:i1], cand[i0:i1])

        cand, d2 = map_blocks(block, len(todo), _FIT_BLOCK * 16)
        # complete unless the last candidate ties with the k-th (to rounding: the tree's
        # distances may round otherwise)
        done = d2[:, kq - 1] > d2[:, k - 1] * (1.0 + 1e-12) if kq < n else np.ones(todo.size, bool)
        nbr[todo[done]] = cand[done, :k]
        d2k[todo[done]] = d2[done, k - 1]
        todo = todo[~done]
        kq = min(2 * kq, n)
    return nbr, np.sqrt(d2k)


def _canonical(points, centres, cand):
    """Candidates ``cand`` (m, c) of ``centres`` (m, 3) sorted by (squared distance, x, y, z):
    (nbr (m, c), d2). The numpy twin of `cfm_fem._kernels.canonical_neighbours`."""
    p = points[cand]
    d2 = np.sum((p - centres[:, None, :]) ** 2, axis=2)
    order = np.lexsort((p[..., 2], p[..., 1], p[..., 0], d2), axis=-1)
    return np.take_along_axis(cand, order, -1), np.take_along_axis(d2, order, -1)


def fallback_mask(residual_T, flag, checks, misfit_rel: float = MISFIT_REL) -> np.ndarray:
    """``use`` of the fallback rule (`FALLBACK_RULE`) from the kernel's outputs.

    Parameters
    ----------
    residual_T : ndarray, shape (n,), T
    flag : ndarray, shape (n,), int64
    checks : ndarray, shape (n, 4), T
        See `cfm_fem._kernels.harmonic_fit_block`.
    misfit_rel : float
        Bound of the misfit check (`MISFIT_REL`); ``inf``: the curl check alone.

    Returns
    -------
    ndarray, shape (n,), bool
    """
    floor = ROUNDING_FLOOR * checks[:, _kernels.CHECK_LEVEL]
    harm = checks[:, _kernels.CHECK_HARMONIC]
    with np.errstate(invalid="ignore"):
        free = checks[:, _kernels.CHECK_FREE]
        curl = (harm > CURL_RATIO * free) & (residual_T > free) & (harm > floor)
        misfit = (residual_T > misfit_rel * checks[:, _kernels.CHECK_SPREAD]) & (residual_T > floor)
    failed = (flag & _kernels.FIT_FAILED) != 0
    return ~(curl | misfit | failed)


def grid_metric(points) -> np.ndarray:
    """Factors (3,) on x, y, z that make a full grid's steps equal, or ones.

    Ones unless the nodes form a full tensor grid (every combination of the distinct x, y
    and z, once) with a median step along some axis above `ANISOTROPY_MAX` times the
    smallest; then, per axis, the smallest median step over the axis's.

    Parameters
    ----------
    points : ndarray, shape (n, 3), mm

    Returns
    -------
    ndarray, shape (3,)
    """
    pts = np.round(np.asarray(points, dtype=np.float64), 9)
    axes = [np.unique(pts[:, a]) for a in range(3)]
    sizes = [a.size for a in axes]
    if min(sizes) < 2 or int(np.prod(sizes)) != len(pts):
        return np.ones(3)
    if len(np.unique(pts, axis=0)) != len(pts):
        return np.ones(3)
    steps = np.array([np.median(np.diff(a)) for a in axes])
    if steps.max() <= ANISOTROPY_MAX * steps.min():
        return np.ones(3)
    return steps.min() / steps


def fit_harmonic(
    points,
    B,
    *,
    k=40,
    min_degree=2,
    max_degree=MAX_DEGREE,
    source=None,
    metric=None,
    misfit_rel: float = MISFIT_REL,
) -> HarmonicFit:
    """Fit the harmonic field model of every node of a 3-D map.

    Parameters
    ----------
    points : array_like, shape (n, 3), mm
    B : array_like, shape (n, 3), T
    k : int
        Neighbours per fit (the node included); ``min(k, n)`` are used.
    min_degree, max_degree : int
        Field degrees allowed, 2 <= min_degree <= max_degree <= 5. A low ``max_degree`` makes
        the misfit check (`FALLBACK_RULE`) fire where the field needs a higher degree: a
        quadrupole whose strength varies as cos(2 pi z / 40 mm), 500 nodes in a 20 mm cube,
        falls back at 94 % of the nodes with degree 2 only, at none with degrees up to 3.
    source : str, optional
        The map's file, for messages.
    metric : {None, "grid"} or array_like, shape (3,), optional
        Factors on x, y, z in which neighbourhoods and reach are measured: None, millimetres;
        "grid", `grid_metric` of the nodes (module docstring, unequal steps).
    misfit_rel : float
        Bound of the misfit check of the fallback rule; ``inf`` keeps every fit that passes
        the curl check (a reader whose alternative between nodes errs more than a fit that
        follows the field less closely than `MISFIT_REL`).

    Returns
    -------
    HarmonicFit

    Raises
    ------
    CfmInputError
        Fewer than `MIN_NODES` nodes, all nodes in one plane, or bad arguments.

    Notes
    -----
    Neighbours are queried `_QUERY_CHUNK` nodes at a time and fitted in blocks on
    ``numba.get_num_threads()`` threads; the results do not depend on the number of threads,
    the blocks or the row order of the map. Memory: the coefficients, 384 bytes a node, and
    the neighbour search of one chunk (~0.1 GB); a 1,000,000-node map peaks at ~0.8 GB for the
    whole process.
    """
    import scipy.spatial

    points, B = _check_map(points, B, k, min_degree, max_degree, source)
    n = len(points)
    k = int(min(k, n))
    if metric is None:
        metric = np.ones(3)
    elif isinstance(metric, str):
        metric = grid_metric(points)
    metric = np.asarray(metric, dtype=np.float64)
    scaled = bool(np.any(metric != 1.0))
    q = points * metric if scaled else points
    tree = scipy.spatial.cKDTree(q)
    gmat = np.ascontiguousarray(field_basis(max_degree))
    exps = monomial_exponents(max_degree)
    nbf = n_basis(MAX_DEGREE)
    coef = np.zeros((n, nbf))
    scale = np.empty(n)
    degree = np.empty(n, dtype=np.int64)
    resid = np.empty(n)
    use = np.empty(n, dtype=bool)
    reach = np.empty(n)
    for a in range(0, n, _QUERY_CHUNK):
        idx = np.arange(a, min(a + _QUERY_CHUNK, n))
        nbr, sc = neighbourhoods(tree, q, q[idx], k)
        cen = points[idx]
        reach[idx] = REACH_FRACTION * sc
        if scaled:  # the fit's unit ball: the farthest neighbour in millimetres
            sc = np.sqrt(np.max(np.sum((points[nbr] - cen[:, None, :]) ** 2, axis=2), axis=1))

        def block(i0, i1, nbr=nbr, sc=sc, cen=cen):
            return _kernels.harmonic_fit_block(
                cen[i0:i1], sc[i0:i1], nbr[i0:i1], points, B, gmat, exps, min_degree, max_degree
            )

        c, deg, res, flag, checks = map_blocks(block, len(idx), _FIT_BLOCK)
        coef[idx, : c.shape[1]] = c
        scale[idx], degree[idx], resid[idx] = sc, deg, res
        use[idx] = fallback_mask(res, flag, checks, misfit_rel)
    return HarmonicFit(
        centers=points, scale=scale, coef=coef, degree=degree, residual_T=resid,
        reach_mm=reach, use=use, k=k, metric=metric,
    )  # fmt: skip


def time_fit(points, B, *, k=40) -> dict:
    """Time `fit_harmonic` on a map, its kernel compiled beforehand (on the first nodes).

    Parameters
    ----------
    points : array_like, shape (n, 3), mm
    B : array_like, shape (n, 3), T
    k : int

    Returns
    -------
    dict
        ``nodes``, ``k``, ``threads`` (numba's), ``seconds`` (wall time of the fit),
        ``fallback_nodes`` and ``degrees`` (nodes per degree).
    """
    import time

    warm = np.random.default_rng(0).uniform(-1.0, 1.0, (2 * k, 3))  # compiles the kernel
    fit_harmonic(warm, warm, k=k)
    t0 = time.perf_counter()
    fit = fit_harmonic(points, B, k=k)
    seconds = time.perf_counter() - t0
    degrees = np.bincount(fit.degree, minlength=MAX_DEGREE + 1)
    return {
        "nodes": len(points), "k": fit.k, "threads": numba.get_num_threads(),
        "seconds": seconds, "fallback_nodes": int(np.sum(~fit.use)),
        "degrees": {d: int(degrees[d]) for d in range(2, MAX_DEGREE + 1)},
    }  # fmt: skip
