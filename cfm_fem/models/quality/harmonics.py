"""Circular harmonics of a field map, plane by plane, and the field quality they give.

Conventions of `cfm_fem.models.multipole`: European n (1 dipole, 2 quadrupole, ...) and

    F(w) = B_y + i B_x = sum_n C_n (w / R_ref)^(n-1),   C_n = B_n + i A_n,   w = x + i y,

about the line x = y = 0 of the map frame, lengths in mm, fields in T.

A `ScanPlan` is the set of points where the field is read: the nodes of each z plane of a map
inside the largest disk about the axis that the plane covers (`plan_from_nodes`), or points on a
circle in each of a series of planes, read from the model between nodes (`plan_on_circles`).
Every plane holds the same (x, y) points, so the plane fits are linear operators.

Two fits of a plane, both least squares on (B_x, B_y) at its points, solved at the radius of the
sampled disk (well conditioned):

* the **2-D fit** (`ScanPlan.pinv`): the 2-D multipole expansion, orders 1 .. `ScanPlan.n_orders`,
  rescaled to R_ref by (R_ref / r)^(n-1). Its integral over z is the fit of the integrated
  field, which is a 2-D potential field when the map holds the whole magnet: the integrated
  harmonics. Orders the points cannot determine (condition number above `MAX_CONDITION`) are
  not fitted and reported as NaN.
* the **circle fit** (`ScanPlan.pinv_circle`): in a plane of a 3-D field, (B_x, B_y) is the
  in-plane gradient of the scalar potential, which holds besides the 2-D multipoles r^m e^(i m
  theta) the pseudo-multipoles r^(2k) r^m e^(i m theta), k >= 1, of the z derivatives of the
  multipoles: -r^2 C_n'' / (4 n) is the first, large in the ends and the centre of a short
  magnet. The fit takes the 2-D multipoles and the first pseudo-multipoles (k = 1, m = 0 ..
  `PSEUDO_ORDERS`) and returns C_n on the circle r = R_ref: the coefficient of e^(i (n-1)
  theta) of F on that circle. The plane harmonics (`planes.csv`) and the main harmonic in the
  plane of the magnetic length are these.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from math import comb

import numpy as np
import scipy.spatial

from ...errors import CfmInputError

__all__ = [
    "N_HARMONICS",
    "MAX_CONDITION",
    "ScanPlan",
    "plan_from_nodes",
    "plan_on_circles",
    "node_planes",
    "inscribed_radius",
    "fit_planes",
    "QualityNumbers",
    "quality_numbers",
    "centre_from_harmonics",
    "length_plane_value",
    "analyse",
    "PSEUDO_ORDERS",
]

#: Harmonics reported: n = 1 .. N_HARMONICS.
N_HARMONICS = 15
#: Largest condition number of a plane's least-squares fit; fewer orders are fitted above it.
MAX_CONDITION = 1e8
#: Fewest planes a map needs for an integral over z.
MIN_PLANES = 2
#: Highest order m of the pseudo-multipoles r^2 r^m e^(i m theta) of the circle fit.
PSEUDO_ORDERS = 8
#: Points of the circle r = R_ref on which the circle fit's polynomials are Fourier-analysed
#: (exact for polynomials of degree below it).
_CIRCLE_POINTS = 64


@dataclass
class ScanPlan:
    """Where the field is read for the harmonics, and the fit that turns readings into them.

    Attributes
    ----------
    points : ndarray, shape (n, 3), mm
        Scan points, plane after plane, the same (x, y) order in each plane.
    z : ndarray, shape (P,), mm
        Plane positions, increasing.
    per_plane : int
        Points per plane k (n = P k).
    r_fit_mm : float, mm
        Radius of the sampled disk (nodes) or of the circle.
    r_ref_mm : float, mm
    n_orders : int
        Orders fitted (the rest are NaN).
    pinv : ndarray, shape (2 n_orders, 2 k)
        2-D fit: [B_1..B_N, A_1..A_N] at R_ref from [B_y of the k points, B_x of the k points].
    weights_mm : ndarray, shape (P,), mm
        Trapezoid weights of the planes: integral over z = sum of weights x plane values.
    sampling : {"nodes", "circles"}
    condition : float
        Condition number of the fit (at r_fit).
    pinv_circle : ndarray, shape (2 n_orders, 2 k)
        Circle fit: [B_1..B_N, A_1..A_N] on the circle r = R_ref from the same readings.
    pseudo_orders : int or None
        Highest order m of the circle fit's pseudo-multipoles (-1: none fit the points); None
        on circles, where the circle fit is the circle's own Fourier analysis, scaled to R_ref
        as a 2-D field.
    notes : list of str
    """

    points: np.ndarray
    z: np.ndarray
    per_plane: int
    r_fit_mm: float
    r_ref_mm: float
    n_orders: int
    pinv: np.ndarray
    weights_mm: np.ndarray
    sampling: str
    condition: float
    pinv_circle: np.ndarray
    pseudo_orders: int | None
    notes: list = field(default_factory=list)

    @property
    def n_planes(self) -> int:
        return int(self.z.size)

    def describe(self) -> str:
        if self.sampling == "nodes":
            what = f"the map's nodes inside r <= {self.r_fit_mm:.6g} mm"
        else:
            what = f"{self.per_plane} points on the circle r = {self.r_fit_mm:.6g} mm"
        return (
            f"{self.n_planes} planes z = {self.z[0]:.6g} .. {self.z[-1]:.6g} mm, {what} "
            f"({self.per_plane} per plane); orders 1..{self.n_orders} fitted"
        )


def _design(xy, r_fit, n_orders) -> np.ndarray:
    """Matrix (2k, 2N) taking [B_1..B_N, A_1..A_N] at radius r_fit to [B_y; B_x] at xy (k, 2)."""
    w = (xy[:, 0] + 1j * xy[:, 1]) / r_fit
    p = w[:, None] ** np.arange(n_orders)[None, :]  # (k, N)
    top = np.hstack([p.real, -p.imag])  # B_y = sum B_n Re p - A_n Im p
    bottom = np.hstack([p.imag, p.real])  # B_x = sum B_n Im p + A_n Re p
    return np.vstack([top, bottom])


def _operator(xy, r_fit, r_ref, n_max=N_HARMONICS):
    """(pinv (2N, 2k) at r_ref, N, condition) with the most orders N <= n_max the points fix."""
    for n in range(min(n_max, len(xy)), 0, -1):
        a = _design(xy, r_fit, n)
        s = np.linalg.svd(a, compute_uv=False)
        cond = s[0] / s[-1] if s[-1] > 0 else np.inf
        if cond <= MAX_CONDITION:
            scale = (r_ref / r_fit) ** np.arange(n)
            return np.linalg.pinv(a) * np.tile(scale, 2)[:, None], n, float(cond)
    raise CfmInputError(
        f"the {len(xy)} points of a plane inside r <= {r_fit:g} mm cannot determine even a "
        "dipole; expected points around the axis x = y = 0"
    )


def _potential_columns(xy, r_fit, n_orders, pseudo_orders) -> np.ndarray:
    """Matrix (2k, M) taking the circle fit's coefficients to [B_y; B_x] at xy (k, 2).

    Columns: the 2-D multipoles of `_design` (F = (w / r_fit)^(n-1), n = 1 .. n_orders), then
    the in-plane gradients of the potentials Re(c rho^2 u^m), u = w / r_fit, rho = |u|, c = 1
    and i (1 only for m = 0), m = 0 .. pseudo_orders.
    """
    u = (xy[:, 0] + 1j * xy[:, 1]) / r_fit
    rho2 = np.abs(u) ** 2
    cols = [_design(xy, r_fit, n_orders)]
    for m in range(pseudo_orders + 1):
        um = u**m
        dm = m * rho2 * u ** max(m - 1, 0)  # d/dx of rho^2 u^m = 2 x um + dm, d/dy 2 y um + i dm
        gx, gy = 2 * u.real * um + dm, 2 * u.imag * um + 1j * dm
        for c in (1.0, 1j) if m > 0 else (1.0,):
            cols.append(np.concatenate([(c * gy).real, (c * gx).real])[:, None])
    return np.hstack(cols)


def _circle_operator(xy, r_fit, r_ref, n_orders):
    """(pinv_circle (2N, 2k), pseudo-multipole orders) of the circle fit at the points xy (k,
    2): the most orders m <= `PSEUDO_ORDERS` whose fit stays within `MAX_CONDITION` (-1: none)."""
    th = 2 * np.pi * np.arange(_CIRCLE_POINTS) / _CIRCLE_POINTS
    ring = r_ref * np.column_stack([np.cos(th), np.sin(th)])
    fourier = np.exp(-1j * np.outer(np.arange(n_orders), th)) / _CIRCLE_POINTS  # (N, 64)
    for m in range(PSEUDO_ORDERS, -2, -1):
        a = _potential_columns(xy, r_fit, n_orders, m)
        s = np.linalg.svd(a, compute_uv=False) if a.shape[1] <= a.shape[0] else [1.0, 0.0]
        if s[-1] > 0 and s[0] / s[-1] <= MAX_CONDITION:
            on_ring = _potential_columns(ring, r_fit, n_orders, m)  # (128, M)
            c = fourier @ (on_ring[:_CIRCLE_POINTS] + 1j * on_ring[_CIRCLE_POINTS:])  # (N, M)
            return np.vstack([c.real, c.imag]) @ np.linalg.pinv(a), m
    raise AssertionError("the 2-D fit alone is within MAX_CONDITION")  # _operator checked it


def _trapezoid_weights(z) -> np.ndarray:
    dz = np.diff(z)
    w = np.zeros(z.size)
    w[:-1] += 0.5 * dz
    w[1:] += 0.5 * dz
    return w


def inscribed_radius(xy) -> float:
    """Radius of the largest disk about the origin inside the convex hull of ``xy`` (k, 2), mm;
    0 when the origin is outside (or on) the hull."""
    try:
        hull = scipy.spatial.ConvexHull(xy)
    except scipy.spatial.QhullError:
        return 0.0
    # facets a . p + b <= 0 inside, |a| = 1: distance of the origin to a facet is -b
    return float(max(0.0, np.min(-hull.equations[:, 2])))


def node_planes(points, tol_mm: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """z planes of a map's nodes: (z values (P,), plane index of each node (n,))."""
    z = np.asarray(points, dtype=np.float64)[:, 2]
    order = np.argsort(z, kind="stable")
    zs = z[order]
    new = np.r_[True, np.diff(zs) > tol_mm]
    group = np.cumsum(new) - 1
    index = np.empty(z.size, dtype=np.int64)
    index[order] = group
    return zs[new], index


def plan_from_nodes(points, r_ref_mm: float, *, r_fit_mm: float | None = None,
                    source: str = "<map>") -> ScanPlan:  # fmt: skip
    """Scan plan of a map whose nodes lie in z planes on one (x, y) pattern.

    Parameters
    ----------
    points : array_like, shape (n, 3), mm
        The map's nodes.
    r_ref_mm : float, mm
    r_fit_mm : float, optional, mm
        Radius of the disk whose nodes are fitted; default the largest disk about the axis
        inside the (x, y) pattern of every plane.
    source : str
        For messages.

    Returns
    -------
    ScanPlan

    Raises
    ------
    CfmInputError
        Fewer than `MIN_PLANES` planes holding the common pattern, the axis outside the map, or
        too few nodes in the disk.
    """
    pts = np.asarray(points, dtype=np.float64)
    zp, index = node_planes(pts)
    counts = np.bincount(index, minlength=zp.size)
    if zp.size < MIN_PLANES or np.median(counts) < 3:  # scattered nodes: no planes
        raise CfmInputError(
            f"the map's nodes do not lie in z planes sharing one (x, y) pattern ({zp.size} "
            "distinct z values); use the circle sampling of the model between nodes",
            file=source,
        )
    key = np.round(pts[:, :2], 9)[np.argsort(index, kind="stable")]
    # (x, y) pattern shared by the planes: the pattern of the most common kind of plane
    sets = [frozenset(map(tuple, k)) for k in np.split(key, np.cumsum(counts)[:-1])]
    common = Counter(sets).most_common(1)[0][0]
    keep = np.array([s >= common for s in sets])
    if keep.sum() < MIN_PLANES or len(common) < 3:
        raise CfmInputError(
            f"the map's nodes do not lie in z planes sharing one (x, y) pattern ({zp.size} "
            "distinct z values); use the circle sampling of the model between nodes",
            file=source,
        )
    xy = np.array(sorted(common))
    r_in = inscribed_radius(xy)
    r_fit = r_in if r_fit_mm is None else float(r_fit_mm)
    if not r_fit > 0:
        raise CfmInputError(
            "the line x = y = 0 is not inside the map's (x, y) pattern; harmonics are taken "
            "about it",
            file=source,
        )
    disk = xy[np.hypot(xy[:, 0], xy[:, 1]) <= r_fit * (1 + 1e-9)]
    pinv, n, cond = _operator(disk, r_fit, r_ref_mm)
    pinv_circle, pseudo = _circle_operator(disk, r_fit, r_ref_mm, n)
    z = zp[keep]
    notes = []
    if (~keep).any():
        notes.append(f"{int((~keep).sum())} z plane(s) without the common (x, y) pattern left out")
    if r_fit_mm is not None and r_fit > r_in * (1 + 1e-9):
        notes.append(f"fit radius {r_fit:g} mm exceeds the disk the map covers ({r_in:.6g} mm)")
    scan = np.column_stack([np.tile(disk, (z.size, 1)), np.repeat(z, len(disk))])
    return ScanPlan(scan, z, len(disk), r_fit, float(r_ref_mm), n, pinv,
                    _trapezoid_weights(z), "nodes", cond, pinv_circle, pseudo,
                    notes)  # fmt: skip


def plan_on_circles(z, r_mm: float, r_ref_mm: float, n_angles: int = 64) -> ScanPlan:
    """Scan plan of points on a circle of radius ``r_mm`` in each plane ``z``.

    Parameters
    ----------
    z : array_like, shape (P,), mm
        Plane positions, increasing, at least `MIN_PLANES`.
    r_mm : float, mm
    r_ref_mm : float, mm
    n_angles : int
        Points per circle, equally spaced from angle 0; at least 2 `N_HARMONICS` + 1 for all
        orders.

    Returns
    -------
    ScanPlan
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 1 or z.size < MIN_PLANES or np.any(np.diff(z) <= 0):
        raise CfmInputError(f"planes must be at least {MIN_PLANES} increasing z values in mm")
    if not (r_mm > 0 and n_angles >= 3):
        raise CfmInputError(f"the circle needs r > 0 mm and >= 3 points; got {r_mm}, {n_angles}")
    th = 2 * np.pi * np.arange(n_angles) / n_angles
    xy = np.column_stack([r_mm * np.cos(th), r_mm * np.sin(th)])
    pinv, n, cond = _operator(xy, r_mm, r_ref_mm, min(N_HARMONICS, (n_angles - 1) // 2))
    scan = np.column_stack([np.tile(xy, (z.size, 1)), np.repeat(z, n_angles)])
    return ScanPlan(scan, z, n_angles, float(r_mm), float(r_ref_mm), n, pinv,
                    _trapezoid_weights(z), "circles", cond, pinv, None, [])  # fmt: skip


def fit_planes(plan: ScanPlan, B, *, on_circle: bool = False, planes=None) -> np.ndarray:
    """Harmonics of planes from the field at the scan points.

    Parameters
    ----------
    plan : ScanPlan
    B : ndarray, shape (..., n, 3), T
        Field at ``plan.points`` (any leading shape, e.g. trials).
    on_circle : bool
        False: the 2-D fit (whose integral over z is the integrated harmonics); True: the
        circle fit, C_n on the circle r = R_ref (module docstring).
    planes : array_like of int, optional
        Indices of the planes to fit; default all.

    Returns
    -------
    ndarray, shape (..., P, N_HARMONICS), complex, T at R_ref
        C_n = B_n + i A_n; NaN past ``plan.n_orders``. P: the planes asked for.
    """
    B = np.asarray(B, dtype=np.float64)
    lead = B.shape[:-2]
    k, n = plan.per_plane, plan.n_orders
    b = B.reshape(lead + (plan.n_planes, k, 3))
    if planes is not None:
        b = b[..., np.asarray(planes, dtype=np.int64), :, :]
    n_planes = b.shape[-3]
    op = plan.pinv_circle if on_circle else plan.pinv
    rows = int(np.prod(lead + (n_planes,)))
    by = np.ascontiguousarray(b[..., 1]).reshape(rows, k)
    bx = np.ascontiguousarray(b[..., 0]).reshape(rows, k)
    coef = by @ op[:, :k].T + bx @ op[:, k:].T  # (rows, 2N), [B_y, B_x] columns
    coef = coef.reshape(lead + (n_planes, 2 * n))
    out = np.full(lead + (n_planes, N_HARMONICS), np.nan + 0j)
    out[..., :n] = coef[..., :n] + 1j * coef[..., n:]
    return out


def length_plane_value(plan: ScanPlan, B, main_order: int, z_length: float) -> np.ndarray:
    """Main harmonic on the circle r = R_ref in the plane z_length (circle fit of the two planes
    around it, linear between them).

    Parameters
    ----------
    plan : ScanPlan
    B : ndarray, shape (..., n, 3), T
        Field at ``plan.points``.
    main_order : int
    z_length : float, mm
        Inside the planes' range.

    Returns
    -------
    ndarray, shape (...), complex, T
    """
    z = plan.z
    j = int(np.clip(np.searchsorted(z, z_length), 1, z.size - 1))
    t = (z_length - z[j - 1]) / (z[j] - z[j - 1])
    c = fit_planes(plan, B, on_circle=True, planes=[j - 1, j])[..., main_order - 1]
    return (1 - t) * c[..., 0] + t * c[..., 1]


def analyse(plan: ScanPlan, B, main_order: int, z_length: float) -> QualityNumbers:
    """`quality_numbers` of the field ``B`` (..., n, 3) T at the scan points."""
    return quality_numbers(fit_planes(plan, B), plan, main_order,
                           length_plane_value(plan, B, main_order, z_length))  # fmt: skip


# --------------------------------------------------------------------------- field quality


@dataclass
class QualityNumbers:
    """Field quality of one map (or of each Monte Carlo trial: every array gets a leading axis).

    Attributes
    ----------
    integrated : ndarray, shape (..., N_HARMONICS), complex, T mm
        Integral over z of C_n = B_n + i A_n at R_ref.
    b_units, a_units : ndarray, shape (..., N_HARMONICS)
        1e4 B_n / |C_N| and 1e4 A_n / |C_N| of the integrals (N the main order).
    centre_mm : ndarray, shape (..., 2), mm
        Point about which the integrated harmonic of order N - 1 vanishes (NaN for a dipole).
    roll_mrad : ndarray, shape (...), mrad
        -atan2(A_N, B_N) / N of the integrated main harmonic.
    length_mm : ndarray, shape (...), mm
        Magnetic length: integral of the main harmonic over its value on the circle r = R_ref in
        the length plane, both projected on the phase of the integral (for a magnet without
        roll, integral B_N over B_N on that circle).
    main_integral_Tmm : ndarray, shape (...), T mm
        |integral of C_N| at R_ref.
    """

    integrated: np.ndarray
    b_units: np.ndarray
    a_units: np.ndarray
    centre_mm: np.ndarray
    roll_mrad: np.ndarray
    length_mm: np.ndarray
    main_integral_Tmm: np.ndarray

    def vector(self) -> np.ndarray:
        """The scalars of a trial in one row, shape (..., 2 N_HARMONICS + 5):
        b_1..b_15, a_1..a_15, centre x, centre y, roll, length, main integral."""
        return np.concatenate(
            [self.b_units, self.a_units, self.centre_mm,
             np.stack([self.roll_mrad, self.length_mm, self.main_integral_Tmm], axis=-1)],
            axis=-1,
        )  # fmt: skip


#: Names of the columns of `QualityNumbers.vector`.
VECTOR_NAMES = (
    [f"b{n}" for n in range(1, N_HARMONICS + 1)]
    + [f"a{n}" for n in range(1, N_HARMONICS + 1)]
    + ["centre_x", "centre_y", "roll", "length", "main_integral"]
)


def centre_from_harmonics(c, main_order: int, r_ref_mm: float, iterations: int = 30):
    """Point d = x + i y about which the harmonic of order N - 1 of ``c`` vanishes (feed-down).

    Solves sum_{n >= N-1} C_n binom(n-1, N-2) (d / R_ref)^(n-N+1) = 0 by Newton's method from
    the first-order root -C_{N-1} R_ref / ((N-1) C_N). NaN coefficients count as zero.

    Parameters
    ----------
    c : ndarray, shape (..., N_HARMONICS), complex, any unit
    main_order : int
        N >= 2.
    r_ref_mm : float, mm

    Returns
    -------
    ndarray, shape (...), complex, mm
    """
    big = main_order
    c = np.nan_to_num(np.asarray(c, dtype=np.complex128))
    shape = c.shape[:-1]
    c = c.reshape(-1, c.shape[-1])
    orders = np.arange(big - 1, c.shape[-1] + 1)  # n = N-1 .. 15
    coef = np.stack(
        [c[..., n - 1] * comb(n - 1, big - 2) for n in orders], axis=-1
    )  # coefficients of (d/R)^(n-N+1), powers 0, 1, ...
    powers = np.arange(orders.size)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = -coef[..., 0] / coef[..., 1]
        moving = np.isfinite(u)
        for _ in range(iterations):  # each value stops on its own: no dependence on the others
            if not moving.any():
                break
            um = u[moving]
            cm = coef[moving]
            f = np.sum(cm * um[:, None] ** powers, axis=-1)
            df = np.sum(cm[:, 1:] * powers[1:] * um[:, None] ** (powers[1:] - 1), axis=-1)
            step = f / df
            u[moving] = um - step
            idx = np.flatnonzero(moving)
            moving[idx[~np.isfinite(step) | (np.abs(step) <= 1e-15 * (1 + np.abs(um)))]] = False
    return (u * r_ref_mm).reshape(shape)


def quality_numbers(planes, plan: ScanPlan, main_order: int, central) -> QualityNumbers:
    """Integrated harmonics, centre, roll and magnetic length from plane harmonics.

    Parameters
    ----------
    planes : ndarray, shape (..., P, N_HARMONICS), complex, T at R_ref
        `fit_planes` output (2-D fit).
    plan : ScanPlan
    main_order : int
        N, 1 .. plan.n_orders.
    central : ndarray, shape (...), complex, T
        Main harmonic on the circle r = R_ref in the plane of the magnetic length
        (`length_plane_value`).

    Returns
    -------
    QualityNumbers
    """
    integ = np.einsum("...pn,p->...n", planes, plan.weights_mm)
    cm = integ[..., main_order - 1]
    mod = np.abs(cm)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = 1e4 * integ / mod[..., None]
        roll = -np.angle(cm) / main_order * 1e3
        phase = np.exp(-1j * np.angle(cm))
        length = mod / (central * phase).real
    if main_order >= 2:
        d = centre_from_harmonics(integ, main_order, plan.r_ref_mm)
        centre = np.stack([d.real, d.imag], axis=-1)
    else:
        centre = np.full(cm.shape + (2,), np.nan)
    return QualityNumbers(integ, rel.real, rel.imag, centre, roll, length, mod)


def main_order_of(integrated) -> int:
    """Order n of the largest |integral of C_n| (the main harmonic)."""
    a = np.abs(np.nan_to_num(np.asarray(integrated)))
    return int(np.argmax(a)) + 1
