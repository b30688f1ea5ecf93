"""2-D multipole field of an accelerator magnet (paper eq. 11), feed-down and roll.

Conventions (European, as in the paper and at CERN):

* ``n = 1`` is the dipole, ``n = 2`` the quadrupole, ``n = 3`` the sextupole, ...
* the field in the magnet's transverse plane is the complex function

      F(z) = B_y + i B_x = sum_{n=1}^{N} (B_n + i A_n) (z / R_ref)^(n-1),   z = x + i y,

  with ``B_n`` the normal and ``A_n`` the skew coefficient, both in T at the reference radius
  ``R_ref``. Coordinates are in mm, fields in T, angles in rad. The model is 2-D: ``B_z = 0`` and
  nothing depends on ``z`` (no fringe field).
* Arrays of coefficients are indexed from 0: ``normal[0]`` is ``B_1``, ``normal[n-1]`` is ``B_n``.

The raw functions (``multipole_field``, ``multipole_gradient``, ``feed_down``, ``roll``) work on
plain arrays; `Multipole` bundles the coefficients with ``R_ref`` and the main order and points at
them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from math import comb

import numpy as np

from ..errors import CfmInputError

__all__ = [
    "Multipole",
    "multipole_field",
    "multipole_gradient",
    "feed_down",
    "roll",
    "UNIT",
]

#: One "unit" of a harmonic is 1e-4 of the main harmonic.
UNIT = 1e-4


# --- raw functions -------------------------------------------------------------------------------


def _complex_coefficients(normal, skew) -> np.ndarray:
    normal = np.atleast_1d(np.asarray(normal, dtype=np.float64))
    skew = np.atleast_1d(np.asarray(skew, dtype=np.float64))
    if normal.ndim != 1 or normal.shape != skew.shape or normal.size == 0:
        raise CfmInputError(
            "normal and skew coefficients must be 1-D arrays of the same non-zero length; "
            f"instead received shapes {normal.shape} and {skew.shape}"
        )
    return normal + 1j * skew


def _complex_position(points, r_ref: float) -> tuple[np.ndarray, np.ndarray]:
    """(points as float array, w = (x + i y) / R_ref)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 0 or pts.shape[-1] not in (2, 3):
        raise CfmInputError(
            f"points must have shape (..., 2) or (..., 3) in mm; instead received {pts.shape}"
        )
    return pts, (pts[..., 0] + 1j * pts[..., 1]) / r_ref


def _horner(c: np.ndarray, w: np.ndarray) -> np.ndarray:
    """sum_k c[k] w**k, evaluated by Horner's scheme (stable and cheap for N ~ 20)."""
    f = np.full(w.shape, c[-1], dtype=np.complex128)
    for ck in c[-2::-1]:
        f = f * w + ck
    return f


def multipole_field(points, normal, skew, r_ref: float) -> np.ndarray:
    """Flux density of a 2-D multipole expansion (paper eq. 11).

    Parameters
    ----------
    points : array_like, shape (..., 3) or (..., 2), mm
        Positions in the magnet frame; a third coordinate (z, along the magnet) is ignored.
    normal, skew : array_like, shape (N,), T
        ``B_n`` and ``A_n`` at ``r_ref`` for n = 1..N (index 0 is the dipole).
    r_ref : float, mm
        Reference radius.

    Returns
    -------
    ndarray, shape (..., 3), T
        (B_x, B_y, B_z) with B_z = 0.
    """
    c = _complex_coefficients(normal, skew)
    pts, w = _complex_position(points, float(r_ref))
    f = _horner(c, w)  # B_y + i B_x
    out = np.zeros(pts.shape[:-1] + (3,))
    out[..., 0] = f.imag
    out[..., 1] = f.real
    return out


def multipole_gradient(points, normal, skew, r_ref: float) -> np.ndarray:
    """Analytic field gradient of a 2-D multipole expansion (GUM sensitivity coefficients).

    F(z) = B_y + i B_x is analytic in z, so with G = dF/dz
    (= sum_n (n-1)(B_n + i A_n) z^(n-2) / R_ref^(n-1)):

        dB_y/dx = Re G,   dB_x/dx = Im G,   dB_y/dy = -Im G,   dB_x/dy = Re G.

    The matrix is symmetric (curl B = 0) and traceless (div B = 0); all z terms vanish.

    Parameters
    ----------
    points : array_like, shape (..., 3) or (..., 2), mm
    normal, skew : array_like, shape (N,), T
    r_ref : float, mm

    Returns
    -------
    ndarray, shape (..., 3, 3), T/mm
        ``J[..., i, j] = dB_i / dx_j`` with i, j over (x, y, z).
    """
    c = _complex_coefficients(normal, skew)
    pts, w = _complex_position(points, float(r_ref))
    out = np.zeros(pts.shape[:-1] + (3, 3))
    if c.size < 2:
        return out
    dc = c[1:] * np.arange(1, c.size)  # coefficients of dF/dw
    g = _horner(dc, w) / float(r_ref)
    out[..., 0, 0] = g.imag
    out[..., 0, 1] = g.real
    out[..., 1, 0] = g.real
    out[..., 1, 1] = -g.imag
    return out


def feed_down(normal, skew, r_ref: float, dx: float, dy: float) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of the same field expanded about the point (dx, dy) instead of the origin.

    With d = dx + i dy and C_n = B_n + i A_n, the exact binomial re-expansion of
    F(z' + d) in powers of z' / R_ref is

        C'_k = sum_{n >= k} C_n binom(n-1, k-1) (d / R_ref)^(n-k).

    This is the textbook feed-down: a quadrupole seen from a centre displaced by +dx gives a
    dipole B'_1 = B_2 dx / R_ref. No order is lost or added (N stays N).

    Parameters
    ----------
    normal, skew : array_like, shape (N,), T at ``r_ref``
    r_ref : float, mm
    dx, dy : float, mm
        New expansion centre, in the frame of the given expansion.

    Returns
    -------
    normal, skew : ndarray, shape (N,), T at ``r_ref``
    """
    c = _complex_coefficients(normal, skew)
    delta = complex(dx, dy) / float(r_ref)
    n = c.size
    # T[k, m] = binom(m, k) delta^(m-k) for 0-based k <= m (binom(n-1, k-1) in 1-based orders).
    t = np.zeros((n, n), dtype=np.complex128)
    for k in range(n):
        for m in range(k, n):
            t[k, m] = comb(m, k) * delta ** (m - k)
    cn = t @ c
    return cn.real.copy(), cn.imag.copy()


def roll(normal, skew, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of the magnet turned by ``angle`` about its own axis (normal/skew exchange).

    The magnet is rotated by ``angle`` rad counter-clockwise in the (x, y) plane seen from +z (from
    +x towards +y): B_new(r) = Rot(angle) B_old(Rot(-angle) r). In complex form this is

        C'_n = C_n exp(-i n angle),

    so a normal 2n-pole turned by +pi/(2n) becomes a skew 2n-pole with A'_n = -B_n (and by
    -pi/(2n) one with A'_n = +B_n).

    Parameters
    ----------
    normal, skew : array_like, shape (N,), T
    angle : float, rad

    Returns
    -------
    normal, skew : ndarray, shape (N,), T
    """
    c = _complex_coefficients(normal, skew)
    orders = np.arange(1, c.size + 1)
    cn = c * np.exp(-1j * orders * float(angle))
    return cn.real.copy(), cn.imag.copy()


# --- the model object ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Multipole:
    """A 2-D multipole field: coefficients in T at a reference radius in mm.

    Attributes
    ----------
    normal, skew : ndarray, shape (N,), float64, T
        ``B_n`` and ``A_n`` at ``r_ref`` for n = 1..N (index 0 is the dipole, European numbering).
    r_ref : float, mm
        Reference radius at which the coefficients are given.
    main : int
        Order of the main harmonic (1 dipole, 2 quadrupole, ...). Defaults to the order with the
        largest |B_n + i A_n|.
    source : str
        Where the coefficients came from (file name or "<memory>"), for messages and outputs.

    Notes
    -----
    ``b_ref`` = |B_main + i A_main| is the reference field of "units" (field errors in units of
    1e-4 B_ref, as in magnet measurement): the modulus of the main harmonic at R_ref, which a roll
    leaves unchanged.
    """

    normal: np.ndarray
    skew: np.ndarray
    r_ref: float
    main: int | None = None
    source: str = "<memory>"

    def __post_init__(self):
        c = _complex_coefficients(self.normal, self.skew)
        if not np.all(np.isfinite(c)):
            raise CfmInputError("multipole coefficients must be finite numbers")
        r_ref = float(self.r_ref)
        if not (np.isfinite(r_ref) and r_ref > 0):
            raise CfmInputError(f"r_ref must be a positive length in mm; instead received {r_ref}")
        main = int(np.argmax(np.abs(c))) + 1 if self.main is None else int(self.main)
        if not 1 <= main <= c.size:
            raise CfmInputError(f"main order must be in 1..{c.size}; instead received {main}")
        normal, skew = c.real.copy(), c.imag.copy()
        normal.flags.writeable = False
        skew.flags.writeable = False
        object.__setattr__(self, "normal", normal)
        object.__setattr__(self, "skew", skew)
        object.__setattr__(self, "r_ref", r_ref)
        object.__setattr__(self, "main", main)

    # construction ------------------------------------------------------------------------------

    @classmethod
    def from_units(
        cls,
        main_n: int,
        main_T: float,
        normal_units,
        skew_units,
        r_ref: float,
        *,
        source: str = "<memory>",
    ) -> Multipole:
        """Build from harmonics in units of 1e-4 of the main harmonic.

        Parameters
        ----------
        main_n : int
            Order of the main harmonic (2 for a quadrupole).
        main_T : float, T
            Main normal coefficient B_main at ``r_ref`` (signed; units are relative to it, so
            B_n = 1e-4 * b_n * main_T).
        normal_units, skew_units : array_like, shape (N,), units
            b_n and a_n for n = 1..N. The normal entry at ``main_n`` is the main harmonic itself
            and must be written as 1e4 or 0; the skew entry at ``main_n`` is in units like the rest.
        r_ref : float, mm

        Returns
        -------
        Multipole
        """
        b = np.atleast_1d(np.asarray(normal_units, dtype=np.float64)).copy()
        a = np.atleast_1d(np.asarray(skew_units, dtype=np.float64))
        main_n = int(main_n)
        if not 1 <= main_n <= b.size:
            raise CfmInputError(f"main_n must be in 1..{b.size}; instead received {main_n}")
        if not (np.isfinite(main_T) and main_T != 0):
            raise CfmInputError(f"main_T must be a non-zero field in T; instead received {main_T}")
        if b[main_n - 1] not in (0.0, 1.0 / UNIT):
            raise CfmInputError(
                f"the normal entry of the main order {main_n} must be 10000 units (or 0 for "
                f"'given by main_T'); instead received {b[main_n - 1]}"
            )
        b[main_n - 1] = 1.0 / UNIT
        return cls(b * UNIT * main_T, a * UNIT * main_T, r_ref, main_n, source)

    # derived quantities ------------------------------------------------------------------------

    @property
    def n_orders(self) -> int:
        """N, the highest order of the expansion."""
        return int(self.normal.size)

    @property
    def coefficients(self) -> np.ndarray:
        """C_n = B_n + i A_n, shape (N,), complex128, T at ``r_ref``."""
        return self.normal + 1j * self.skew

    @property
    def b_ref(self) -> float:
        """|B_main + i A_main| in T: the reference field of 'units'."""
        return float(abs(self.coefficients[self.main - 1]))

    def in_units(self) -> tuple[np.ndarray, np.ndarray]:
        """(b_n, a_n) in units of 1e-4 of ``b_ref``, shape (N,) each."""
        return self.normal / (UNIT * self.b_ref), self.skew / (UNIT * self.b_ref)

    # field -------------------------------------------------------------------------------------

    def field(self, points) -> np.ndarray:
        """(B_x, B_y, 0) in T at ``points`` (shape (..., 3) or (..., 2), mm): shape (..., 3)."""
        return multipole_field(points, self.normal, self.skew, self.r_ref)

    def gradient(self, points) -> np.ndarray:
        """dB_i/dx_j in T/mm at ``points`` (mm): shape (..., 3, 3); see `multipole_gradient`."""
        return multipole_gradient(points, self.normal, self.skew, self.r_ref)

    # transformations ---------------------------------------------------------------------------

    def about(self, dx: float, dy: float) -> Multipole:
        """The same field expanded about (dx, dy) mm of the current frame (`feed_down`)."""
        b, a = feed_down(self.normal, self.skew, self.r_ref, dx, dy)
        return replace(self, normal=b, skew=a)

    def moved(self, dx: float, dy: float) -> Multipole:
        """The magnet displaced by (dx, dy) mm in the measurement frame.

        B_new(x, y) = B_old(x - dx, y - dy); a quadrupole moved by +dx shows a dipole
        B_1 = -B_2 dx / R_ref about the old centre.
        """
        return self.about(-dx, -dy)

    def rolled(self, angle: float) -> Multipole:
        """The magnet turned by ``angle`` rad about its own axis, counter-clockwise from +x to +y
        (`roll`). To misalign a magnet by a roll and an offset, roll first, then move:
        ``m.rolled(psi).moved(dx, dy)``."""
        b, a = roll(self.normal, self.skew, angle)
        return replace(self, normal=b, skew=a)

    def rescaled(self, r_ref: float) -> Multipole:
        """The same field with coefficients given at another reference radius (mm).

        C_n(r_new) = C_n(r_old) (r_new / r_old)^(n-1). To *relabel* R_ref instead (for example to
        try another assumption for a table that does not state it), use
        ``dataclasses.replace(m, r_ref=...)``.
        """
        scale = (float(r_ref) / self.r_ref) ** np.arange(self.n_orders)
        return replace(self, normal=self.normal * scale, skew=self.skew * scale, r_ref=r_ref)
