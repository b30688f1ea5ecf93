"""Description of a Cartesian field-mapping bench: stacked axes, the 21 geometric errors, dynamics.

Everything is in internal units: lengths in mm, angles in rad, times in s. Bench files
(:mod:`cfm_fem.io.bench_toml`) carry their own units and are converted once, on reading.

The 21 geometric errors (paper section II-A, Fig. 2, Table II), in the order of ``ERROR_NAMES``:
for each axis ``a`` in x, y, z: ``delta_x(a)``, ``delta_y(a)``, ``delta_z(a)`` (translations of
the carriage of axis ``a`` along bench x, y, z: one positioning and two straightness errors) and
``eps_x(a)``, ``eps_y(a)``, ``eps_z(a)`` (rotations of that carriage about x, y, z: roll, pitch and
yaw in some order), then the three squareness errors ``alpha_xy``, ``alpha_xz``, ``alpha_yz``.

Each error is ``A * P(q / stroke)``: an amplitude ``A`` drawn once per Monte Carlo trial from its
PDF (common to all points, as on a real bench) times a fixed polynomial profile ``P`` of the
normalised axis position (default ``P = 1``: a position-independent error, as in the paper).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import CfmInputError
from .mc import Pdf

__all__ = [
    "AXES",
    "ERROR_NAMES",
    "ERROR_IS_ANGLE",
    "ERROR_DESCRIPTIONS",
    "error_index",
    "ErrorSpec",
    "Axis",
    "Grid",
    "ReadingDelay",
    "MagnetPlacement",
    "Bench",
]

AXES = ("x", "y", "z")

# Written out for readability: the order is the contract of draw_error_sets and the kernels.
ERROR_NAMES: tuple[str, ...] = (
    "delta_x(x)", "delta_y(x)", "delta_z(x)", "eps_x(x)", "eps_y(x)", "eps_z(x)",
    "delta_x(y)", "delta_y(y)", "delta_z(y)", "eps_x(y)", "eps_y(y)", "eps_z(y)",
    "delta_x(z)", "delta_y(z)", "delta_z(z)", "eps_x(z)", "eps_y(z)", "eps_z(z)",
    "alpha_xy", "alpha_xz", "alpha_yz",
)  # fmt: skip

#: True for the 12 angular errors (rad inside the code), False for the 9 translations (mm).
ERROR_IS_ANGLE = np.array([name.startswith(("eps", "alpha")) for name in ERROR_NAMES], dtype=bool)

_ROLE = {  # Table II names: (axis of motion, direction) -> name
    ("x", "x"): "roll", ("x", "y"): "yaw", ("x", "z"): "pitch",
    ("y", "x"): "pitch", ("y", "y"): "roll", ("y", "z"): "yaw",
    ("z", "x"): "pitch", ("z", "y"): "yaw", ("z", "z"): "roll",
}  # fmt: skip


def _describe(name: str) -> str:
    if name.startswith("alpha"):
        a, b = name[-2], name[-1]
        return f"squareness of the {a.upper()} and {b.upper()} travel directions"
    kind, c, a = name[0], name.split("_")[1][0], name[-2]
    if kind == "d":
        what = "linear positioning" if c == a else f"straightness in {c.upper()}"
        return f"{what} error of the {a.upper()} axis"
    return f"{_ROLE[(a, c)]} error of the {a.upper()} axis (rotation about {c})"


#: Human description of each error (Table II wording).
ERROR_DESCRIPTIONS = {name: _describe(name) for name in ERROR_NAMES}


def error_index(name: str) -> int:
    """Column of ``name`` (e.g. ``'eps_y(z)'``) in ``ERROR_NAMES``."""
    try:
        return ERROR_NAMES.index(name)
    except ValueError:
        raise CfmInputError(
            f"unknown geometric error '{name}'; expected one of {', '.join(ERROR_NAMES)}"
        ) from None


@dataclass(frozen=True)
class ErrorSpec:
    """One of the 21 geometric errors.

    Attributes
    ----------
    name : str
        One of ``ERROR_NAMES``.
    pdf : Pdf
        PDF of the amplitude in internal units (mm or rad).
    profile : tuple of float
        Polynomial coefficients c_0, c_1, ... of P(u) = sum c_k u**k, u = q / stroke in [0, 1],
        dimensionless. ``(1.0,)`` is a position-independent error. Squareness takes no profile.
    unit : str
        Unit used to show it (``'um'`` or ``'urad'``), as in the bench file.
    note : str
        Where the PDF comes from (``'Table II'``, a metrology report, ...).
    """

    name: str
    pdf: Pdf
    profile: tuple = (1.0,)
    unit: str = "um"
    note: str = ""

    @property
    def is_angle(self) -> bool:
        return self.name.startswith(("eps", "alpha"))

    @property
    def position_dependent(self) -> bool:
        return any(c != 0.0 for c in self.profile[1:])


@dataclass(frozen=True)
class Axis:
    """A prismatic axis: its stroke and where its base sits on the carriage below it.

    Attributes
    ----------
    name : str
        ``'x'``, ``'y'`` or ``'z'``: the bench direction it moves along.
    stroke_mm : float
        Travel; commanded positions run over [0, stroke].
    mount_offset_mm : ndarray, shape (3,), mm
        Origin of this axis' frame in the frame of the carriage below it (the foundation for the
        first axis) at zero travel. Lever arm for the angular errors of the axes below.
    """

    name: str
    stroke_mm: float
    mount_offset_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class Grid:
    """Commanded scan grid: ``linspace(start, stop, num)`` per axis, in mm of axis travel."""

    x: tuple = (0.0, 150.0, 9)
    y: tuple = (0.0, 150.0, 8)
    z: tuple = (0.0, 800.0, 13)

    def axis_values(self, axis: str) -> np.ndarray:
        start, stop, num = getattr(self, axis)
        return np.linspace(float(start), float(stop), int(num))

    def points(self) -> np.ndarray:
        """Commanded axis positions, shape (nx*ny*nz, 3), mm; x varies slowest, z fastest."""
        gx, gy, gz = (self.axis_values(a) for a in AXES)
        return np.stack(np.meshgrid(gx, gy, gz, indexing="ij"), axis=-1).reshape(-1, 3)


@dataclass(frozen=True)
class ReadingDelay:
    """Position reading delay (paper eq. 9).

    ``model='normal'``: an axis-position error N(0, std_mm**2) per axis, point and trial.
    ``model='speed_tau'``: Delta q = speed_mm_s * tau with tau drawn per point and trial from
    ``tau_pdf`` (s); the same tau for the three axes of one reading.
    """

    model: str = "normal"
    std_mm: np.ndarray = field(default_factory=lambda: np.full(3, 1.0e-3))
    speed_mm_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tau_pdf: Pdf | None = None


@dataclass(frozen=True)
class MagnetPlacement:
    """Pose of the magnet (map) frame in the bench frame: p_bench = R p_magnet + t.

    ``rotation_rad`` holds (phi, theta, psi), the zyx angles of paper eq. 4.
    ``survey_std_mm`` and ``survey_std_rad``: the 1-sigma uncertainty of that pose after the
    survey (translation per axis, mm; rotation per axis, rad), the prior of a diagnosis's
    magnet-to-bench registration; None where the bench file does not state it.
    """

    rotation_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    translation_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    survey_std_mm: float | None = None
    survey_std_rad: float | None = None


@dataclass(frozen=True)
class Bench:
    """A three-axis Cartesian bench (paper section II-A; the shipped CFM reference bench, whose
    geometry the paper does not give, is `cfm_fem.io.bench_toml.read_reference_bench`).

    Attributes
    ----------
    name : str
    stack : tuple of str
        Axis names from the foundation up, e.g. ``('z', 'x', 'y')``.
    axes : dict of str -> Axis
    tool_offset_mm : ndarray, shape (3,), mm
        Probe position in the frame of the top carriage.
    errors : tuple of ErrorSpec
        The 21 errors in ``ERROR_NAMES`` order.
    vibration_std_mm : ndarray, shape (3,), mm
        Std of the zero-mean normal vibration per axis, drawn per point and trial (paper 2.5 um).
    delay : ReadingDelay
    magnet : MagnetPlacement
    grid : Grid
    assumptions : tuple of str
        Every modelling choice, printed in every output.
    source : str
        File it was read from.
    """

    name: str
    stack: tuple
    axes: dict
    tool_offset_mm: np.ndarray
    errors: tuple
    vibration_std_mm: np.ndarray = field(default_factory=lambda: np.full(3, 2.5e-3))
    delay: ReadingDelay = field(default_factory=ReadingDelay)
    magnet: MagnetPlacement = field(default_factory=MagnetPlacement)
    grid: Grid = field(default_factory=Grid)
    assumptions: tuple = ()
    source: str = "<memory>"

    def __post_init__(self):
        self.validate()

    # -- checks ------------------------------------------------------------------------------
    def validate(self) -> None:
        """Raise CfmInputError (naming the bench key) for anything the model cannot use."""
        stack = tuple(self.stack)
        if sorted(stack) != sorted(AXES):
            raise CfmInputError(
                "frame.stack must list x, y and z once each (foundation first); "
                f"found {list(stack)}"
            )
        for a in AXES:
            if a not in self.axes:
                raise CfmInputError(f"axes.{a} is missing; a bench needs axes x, y and z")
            ax = self.axes[a]
            if not (np.isfinite(ax.stroke_mm) and ax.stroke_mm > 0):
                raise CfmInputError(f"axes.{a}.stroke_mm must be > 0; found {ax.stroke_mm}")
            if np.shape(ax.mount_offset_mm) != (3,):
                raise CfmInputError(f"axes.{a}.mount_offset_mm must be 3 numbers")
        if np.shape(self.tool_offset_mm) != (3,) or not np.all(np.isfinite(self.tool_offset_mm)):
            raise CfmInputError("frame.tool_offset_mm must be 3 finite numbers (mm)")
        names = tuple(e.name for e in self.errors)
        if names != ERROR_NAMES:
            missing = [n for n in ERROR_NAMES if n not in names]
            raise CfmInputError(
                "the bench must give all 21 geometric errors"
                + (f"; missing {', '.join(missing)}" if missing else " in the standard order")
            )
        for e in self.errors:
            e.pdf.kernel_code()  # raises for PDFs the kernels cannot sample
            if e.name.startswith("alpha") and e.position_dependent:
                raise CfmInputError(f"errors.{e.name}: squareness takes no position profile")
            if len(e.profile) == 0 or not np.all(np.isfinite(e.profile)):
                raise CfmInputError(f"errors.{e.name}.profile must be a list of finite numbers")
        if np.any(np.asarray(self.vibration_std_mm) < 0):
            raise CfmInputError("vibration.std_um must be >= 0")
        if self.delay.model not in ("normal", "speed_tau"):
            raise CfmInputError(
                f"reading_delay.model must be 'normal' or 'speed_tau'; found '{self.delay.model}'"
            )
        if self.delay.model == "normal" and np.any(np.asarray(self.delay.std_mm) < 0):
            raise CfmInputError("reading_delay.std_um must be >= 0")
        if self.delay.model == "speed_tau":
            if self.delay.tau_pdf is None:
                raise CfmInputError("reading_delay.tau is required with model = 'speed_tau'")
            self.delay.tau_pdf.kernel_code()
        for a in AXES:
            start, stop, num = getattr(self.grid, a)
            lo, hi = min(start, stop), max(start, stop)
            if int(num) < 1:
                raise CfmInputError(f"grid.{a}_mm.num must be >= 1; found {num}")
            if lo < 0 or hi > self.axes[a].stroke_mm + 1e-9:
                raise CfmInputError(
                    f"grid.{a}_mm must stay within the stroke [0, {self.axes[a].stroke_mm:g}] mm; "
                    f"found [{start:g}, {stop:g}]"
                )

    # -- derived arrays ----------------------------------------------------------------------
    @property
    def stack_indices(self) -> np.ndarray:
        """Bench axis index (0=x, 1=y, 2=z) of the 1st, 2nd, 3rd body from the foundation."""
        return np.array([AXES.index(a) for a in self.stack], dtype=np.int64)

    @property
    def strokes_mm(self) -> np.ndarray:
        """Stroke per bench axis (x, y, z), mm."""
        return np.array([self.axes[a].stroke_mm for a in AXES], dtype=np.float64)

    @property
    def mounts_mm(self) -> np.ndarray:
        """Mount offsets in stack order, shape (3, 3), mm."""
        return np.array([self.axes[a].mount_offset_mm for a in self.stack], dtype=np.float64)

    @property
    def profiles(self) -> np.ndarray:
        """Profile coefficients, shape (21, n_coef), zero padded."""
        n = max(len(e.profile) for e in self.errors)
        out = np.zeros((len(self.errors), n))
        for k, e in enumerate(self.errors):
            out[k, : len(e.profile)] = e.profile
        return out

    @property
    def position_dependent(self) -> bool:
        return any(e.position_dependent for e in self.errors)

    @property
    def pdfs(self) -> tuple:
        return tuple(e.pdf for e in self.errors)

    def error_means(self) -> np.ndarray:
        """Mean of each amplitude, shape (21,), mm or rad."""
        return np.array([e.pdf.mean for e in self.errors])

    def error_stds(self) -> np.ndarray:
        """Standard deviation of each amplitude, shape (21,), mm or rad."""
        return np.array([e.pdf.std for e in self.errors])

    def noise_std_mm(self) -> np.ndarray:
        """Std of the per-point axis-position noise (vibration and, if normal, delay), (3,), mm."""
        v = np.asarray(self.vibration_std_mm, dtype=np.float64) ** 2
        if self.delay.model == "normal":
            v = v + np.asarray(self.delay.std_mm, dtype=np.float64) ** 2
        return np.sqrt(v)

    def grid_points(self) -> np.ndarray:
        """Commanded axis positions of the scan grid, shape (n, 3), mm."""
        return self.grid.points()

    def nominal_probe_mm(self, q_cmd) -> np.ndarray:
        """Nominal probe position in the bench frame for commanded positions, (n, 3), mm.

        The bench frame is the foundation frame: at zero travel the first axis' frame sits at
        its mount offset; nominal probe = sum of mount offsets + q + tool offset.
        """
        return np.asarray(q_cmd, dtype=np.float64) + self.mounts_mm.sum(0) + self.tool_offset_mm

    def axis_positions_for(self, points_magnet_mm) -> np.ndarray:
        """Commanded axis positions that bring the probe to map points given in the magnet frame.

        Parameters
        ----------
        points_magnet_mm : ndarray, shape (n, 3), mm

        Returns
        -------
        ndarray, shape (n, 3), mm
            (q_x, q_y, q_z); may fall outside the strokes (check with ``outside_stroke``).
        """
        from .rotations import rotation_zyx  # local: kinematics imports bench

        p = np.asarray(points_magnet_mm, dtype=np.float64)
        r = rotation_zyx(*self.magnet.rotation_rad)
        p_bench = p @ r.T + self.magnet.translation_mm
        return p_bench - self.mounts_mm.sum(0) - self.tool_offset_mm

    def bench_to_magnet_rotation(self) -> np.ndarray:
        """Rotation (3, 3) that takes a bench-frame vector (a probe error) into the magnet frame."""
        from .rotations import rotation_zyx

        return rotation_zyx(*self.magnet.rotation_rad).T

    def outside_stroke(self, q_cmd) -> np.ndarray:
        """Boolean (n,): commanded positions outside [0, stroke] on some axis."""
        q = np.asarray(q_cmd, dtype=np.float64)
        return np.any((q < -1e-9) | (q > self.strokes_mm + 1e-9), axis=1)

    def axis_positions_within_strokes(self, points_magnet_mm, check: str) -> np.ndarray:
        """`axis_positions_for` of scan points, refusing a point beyond the strokes.

        Parameters
        ----------
        points_magnet_mm : ndarray, shape (n, 3), mm
        check : str
            What the user should check, for the message (e.g. the scan options).

        Returns
        -------
        ndarray, shape (n, 3), mm
        """
        pts = np.asarray(points_magnet_mm, dtype=np.float64)
        q = np.ascontiguousarray(self.axis_positions_for(pts))
        out = self.outside_stroke(q)
        if out.any():
            i = int(np.argmax(out))
            raise CfmInputError(
                f"scan point {i} at {np.round(pts[i], 6).tolist()} mm (magnet frame) needs axis "
                f"positions {np.round(q[i], 3).tolist()} mm, outside the strokes "
                f"{self.strokes_mm.tolist()}; check {check} and [magnet] translation_mm of the "
                f"bench {self.source}"
            )
        return q

    def with_errors(self, errors) -> Bench:
        """A copy with other error specs (used by the tolerance design)."""
        return replace(self, errors=tuple(errors))

    def scaled_errors(self, factors) -> Bench:
        """A copy with every error amplitude scaled: error k becomes factors[k] * error k."""
        factors = np.broadcast_to(np.asarray(factors, dtype=np.float64), (len(self.errors),))
        return self.with_errors(
            replace(e, pdf=e.pdf.scaled(f)) for e, f in zip(self.errors, factors, strict=True)
        )
