"""Hall probe model S_P (paper section II-B and Table I): what the probe reads for a true field.

Two models share one measurement equation. For each reading

    B_meas_i = g_i * (n_i . B_true) + o_i,        i = x, y, z

with g_i the gain of sensing element i (1 when exact), n_i its unit sensing direction in the probe
frame (e_i when exact) and o_i its offset in T (0 when exact).

``model="paper"`` (the default, the paper's S_HP)
    One factor common to the three components, uniform with standard deviation
    ``instrumental_std`` (0.15 %) centred on 1, i.e. U(1 - sqrt(3) s, 1 + sqrt(3) s). No offset,
    no misalignment.

``model="table1"`` (each line of Table I, SENIS 3-D probe, turned into a PDF; our assumptions)
    * Tolerance of sensitivity 0.02 %: a bound, so a gain error U(-0.02 %, +0.02 %), independent
      per element.
    * Non-linearity 0.05 %: the data sheet gives neither its shape nor whether it is of reading or
      of full scale. We read it, like the paper's 0.15 %, relative to the reading, and take the
      deviation from linear as U(-0.05 %, +0.05 %) of the reading per element (GUM type B,
      rectangular). Drawn once per probe it acts like a further gain error; its field dependence is
      unknown and not modelled.
    * Offset at zero field +-1 mT: U(-1 mT, +1 mT) per element, in T. This is the uncompensated
      figure; after a zero-gauss-chamber calibration set ``offset_T`` to the residual.
    * Mutual orthogonality of axes 35 mrad: three small angles, each U(-35, +35) mrad. The x
      element defines the probe frame, the y element lies in the probe's x-y plane tilted by g_xy
      towards x, the z element is tilted by g_xz towards x and g_yz towards y:

          n_x = (1, 0, 0)
          n_y = (sin g_xy, cos g_xy, 0)
          n_z = (sin g_xz, sin g_yz, sqrt(1 - sin^2 g_xz - sin^2 g_yz))

      so the x-y and x-z angles are exactly 90 deg - g_xy and 90 deg - g_xz, the y-z angle
      90 deg - g_yz to first order. A field along x thus reads sin(g_xy) B_x in the y channel.
    * Instrumental uncertainty 0.15 %: a gain factor uniform with standard deviation
      ``instrumental_std``, independent per element (each element has its own channel). The
      manufacturer's figure probably already contains the tolerance and non-linearity; keeping
      them separate costs 0.1532 % instead of 0.15 % in quadrature and lets each be switched off.

    The element gain is g_i = (1 + tolerance_i)(1 + nonlinearity_i) s_i.

Every parameter can be set to 0 to switch its term off; with all zero the probe is exact.
The random draws come from an explicit `numpy.random.Generator` in a fixed order (see
`HallProbe.sample`), so one seed gives the same numbers everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CfmInputError

__all__ = ["HallProbe", "ProbeDraws", "apply_probe", "sample_s_hp", "sensing_directions"]

_SQRT3 = float(np.sqrt(3.0))
MODELS = ("paper", "table1")


def sample_s_hp(rng: np.random.Generator, size=(), std: float = 1.5e-3) -> np.ndarray:
    """Draw the paper's Hall-probe factor S_HP: uniform, mean 1, standard deviation ``std``.

    Parameters
    ----------
    rng : numpy.random.Generator
    size : int or tuple of int
        Shape of the result.
    std : float
        Relative standard deviation (0.15 % in the paper). The half-width is sqrt(3) std.

    Returns
    -------
    ndarray, shape ``size``, dimensionless
    """
    half = _SQRT3 * std
    return rng.uniform(1.0 - half, 1.0 + half, size=size)


def sensing_directions(g_xy, g_xz, g_yz) -> np.ndarray:
    """Unit sensing directions of the three elements from the non-orthogonality angles.

    Parameters
    ----------
    g_xy, g_xz, g_yz : array_like, rad, broadcastable to a common shape (...)
        Tilt of the y element towards x, of the z element towards x and towards y.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        Rows n_x, n_y, n_z (see the module docstring); the identity when all angles are 0.
    """
    g_xy, g_xz, g_yz = np.broadcast_arrays(
        *(np.asarray(g, dtype=np.float64) for g in (g_xy, g_xz, g_yz))
    )
    s_xz, s_yz = np.sin(g_xz), np.sin(g_yz)
    n = np.zeros(g_xy.shape + (3, 3))
    n[..., 0, 0] = 1.0
    n[..., 1, 0] = np.sin(g_xy)
    n[..., 1, 1] = np.cos(g_xy)
    n[..., 2, 0] = s_xz
    n[..., 2, 1] = s_yz
    n[..., 2, 2] = np.sqrt(1.0 - s_xz**2 - s_yz**2)
    return n


@dataclass(frozen=True, eq=False)
class ProbeDraws:
    """One or many realisations of a probe's errors (leading shape ``...``, broadcast on use).

    Attributes
    ----------
    gain : ndarray, shape (..., 3)
        Multiplicative factor of each element (1 = exact).
    offset_T : ndarray, shape (..., 3), T
        Additive offset of each element.
    directions : ndarray, shape (..., 3, 3)
        Row i is the unit sensing direction of element i in the probe frame.
    """

    gain: np.ndarray
    offset_T: np.ndarray
    directions: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        return self.gain.shape[:-1]


def apply_probe(B_true, draws: ProbeDraws) -> np.ndarray:
    """Reading of a probe with the given errors: B_meas_i = gain_i (n_i . B) + offset_i.

    Parameters
    ----------
    B_true : array_like, shape (..., 3), T
        True flux density in the probe frame.
    draws : ProbeDraws
        Its leading shape broadcasts against that of ``B_true``: shape () is one probe for all
        readings, the shape of ``B_true[..., 0]`` is one draw per reading.

    Returns
    -------
    ndarray, shape broadcast(...) + (3,), T
    """
    b = np.asarray(B_true, dtype=np.float64)
    if b.ndim == 0 or b.shape[-1] != 3:
        raise CfmInputError(f"B_true must have shape (..., 3) in T; instead received {b.shape}")
    mixed = (draws.directions @ b[..., None])[..., 0]
    return draws.gain * mixed + draws.offset_T


@dataclass(frozen=True)
class HallProbe:
    """A 3-D Hall probe described by Table I of the paper (SENIS 3-D S-Hall probe).

    Attributes
    ----------
    model : {"paper", "table1"}
        "paper": the single S_HP factor; "table1": each data-sheet line as a PDF (module docstring).
    instrumental_std : float
        Relative standard deviation of the uniform instrumental factor (Table I: 0.15 %).
    sensitivity_tolerance : float
        Relative half-width of the gain tolerance (Table I: 0.02 %). "table1" only.
    nonlinearity : float
        Relative half-width of the non-linearity, of reading (Table I: 0.05 %). "table1" only.
    offset_T : float, T
        Half-width of the zero-field offset (Table I: 1 mT). "table1" only.
    orthogonality_rad : float, rad
        Half-width of each non-orthogonality angle (Table I: 35 mrad). "table1" only.
    """

    model: str = "paper"
    instrumental_std: float = 1.5e-3
    sensitivity_tolerance: float = 2e-4
    nonlinearity: float = 5e-4
    offset_T: float = 1e-3
    orthogonality_rad: float = 35e-3

    def __post_init__(self):
        if self.model not in MODELS:
            raise CfmInputError(
                f"probe model must be one of {MODELS}; instead received {self.model!r}"
            )
        for name in (
            "instrumental_std",
            "sensitivity_tolerance",
            "nonlinearity",
            "offset_T",
            "orthogonality_rad",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise CfmInputError(
                    f"probe {name} must be a finite number >= 0; instead received {v}"
                )
        if (
            _SQRT3 * self.instrumental_std >= 1
            or max(self.sensitivity_tolerance, self.nonlinearity) >= 1
        ):
            raise CfmInputError("probe relative errors must be well below 1")
        if np.sqrt(2.0) * np.sin(self.orthogonality_rad) >= 1:
            raise CfmInputError(
                f"orthogonality_rad must be below pi/4; instead received {self.orthogonality_rad}"
            )

    @classmethod
    def exact(cls, model: str = "paper") -> HallProbe:
        """A probe with every error switched off (reads the true field)."""
        return cls(model, 0.0, 0.0, 0.0, 0.0, 0.0)

    def sample(self, rng: np.random.Generator, size=()) -> ProbeDraws:
        """Draw probe errors with an explicit generator (plain numpy).

        Parameters
        ----------
        rng : numpy.random.Generator
        size : int or tuple of int
            Leading shape of the draws: () for one probe, (n,) for one per reading, ...

        Returns
        -------
        ProbeDraws

        Notes
        -----
        Order of draws, fixed for reproducibility. "paper": S_HP, shape ``size``. "table1":
        instrumental factors, tolerance, non-linearity (each ``size + (3,)``), offsets
        (``size + (3,)``), then the angles g_xy, g_xz, g_yz (``size + (3,)``, last axis in that
        order). Terms switched off still consume their draws, so switching one term off does not
        change the others.
        """
        size = (size,) if np.isscalar(size) else tuple(size)
        if self.model == "paper":
            s = sample_s_hp(rng, size, self.instrumental_std)
            gain = np.repeat(s[..., None], 3, axis=-1)
            offset = np.zeros(size + (3,))
            directions = np.broadcast_to(np.eye(3), size + (3, 3)).copy()
            return ProbeDraws(gain, offset, directions)
        vec = size + (3,)
        s = sample_s_hp(rng, vec, self.instrumental_std)
        tol = rng.uniform(-1.0, 1.0, vec) * self.sensitivity_tolerance
        nl = rng.uniform(-1.0, 1.0, vec) * self.nonlinearity
        offset = rng.uniform(-1.0, 1.0, vec) * self.offset_T
        angles = rng.uniform(-1.0, 1.0, vec) * self.orthogonality_rad
        directions = sensing_directions(angles[..., 0], angles[..., 1], angles[..., 2])
        return ProbeDraws((1.0 + tol) * (1.0 + nl) * s, offset, directions)

    def measure(
        self, B_true, rng: np.random.Generator | int | None = None, *, draws=None
    ) -> np.ndarray:
        """What the probe reads for the true field.

        Parameters
        ----------
        B_true : array_like, shape (..., 3), T
            True flux density in the probe frame.
        rng : numpy.random.Generator or int, optional
            Draw fresh errors, independent for every reading (size ``B_true.shape[:-1]``). An int is
            a seed for `numpy.random.default_rng`.
        draws : ProbeDraws, optional
            Use these errors instead (for example one probe for a whole map: ``self.sample(rng)``).

        Returns
        -------
        ndarray, shape (..., 3), T
        """
        if (rng is None) == (draws is None):
            raise CfmInputError("give exactly one of rng or draws to HallProbe.measure")
        b = np.asarray(B_true, dtype=np.float64)
        if draws is None:
            if b.ndim == 0 or b.shape[-1] != 3:
                raise CfmInputError(
                    f"B_true must have shape (..., 3) in T; instead received {b.shape}"
                )
            draws = self.sample(np.random.default_rng(rng), b.shape[:-1])
        return apply_probe(b, draws)

    def assumptions(self) -> list[str]:
        """One line per error term, saying how the figure became a PDF (for reports)."""
        pct = 100.0
        if self.model == "paper":
            return [
                f"Hall probe S_HP (paper): one factor for all components, uniform, mean 1, "
                f"std {self.instrumental_std * pct:.3g} %"
            ]
        inst, tol, nl = (
            pct * v for v in (self.instrumental_std, self.sensitivity_tolerance, self.nonlinearity)
        )
        return [
            f"instrumental factor per element: uniform, mean 1, std {inst:.3g} %",
            f"sensitivity tolerance per element: uniform +-{tol:.3g} %",
            f"non-linearity per element: uniform +-{nl:.3g} % of reading",
            f"offset per element: uniform +-{self.offset_T * 1e3:.3g} mT",
            f"non-orthogonality angles g_xy, g_xz, g_yz: uniform "
            f"+-{self.orthogonality_rad * 1e3:.3g} mrad, x element defines the probe frame",
        ]
