"""The reference bench of the simulator: Table II draws and its own HTM chain.

Written from the paper (La Marca et al., IEEE TIM, eq. 1-10 and Table II) and the bench geometry
of the design notes (section 5), apart from the tool's kinematics, so that a diagnosis can be
tested against a bench model it did not write.

Frames. Bench (foundation) frame: z along the magnet axis, y up, x horizontal. Stack from the
foundation: the Z carriage (800 mm), the X carriage on it (150 mm), the Y carriage on that
(150 mm); the probe sits at ``TOOL_MM`` = (0, -60, 500) mm in the Y carriage frame. Every mount
offset is zero. Body ``a`` of the stack is placed in its parent by the HTM

    M_a = Trans(q_a d_a + delta(a)) . Rot(eps(a)),

``delta(a)`` = (delta_x(a), delta_y(a), delta_z(a)) and ``Rot`` = Rz Ry Rx of
(eps_x(a), eps_y(a), eps_z(a)) (paper eq. 4, right-handed: a positive angle turns the carriage
counter-clockwise about the bench axis seen from its positive end). ``d_a`` is the travel
direction: the upper axis of each squareness pair leans towards the positive direction of the
lower one, so that ``alpha_ab > 0`` closes the angle between +a and +b to 90 deg - alpha_ab.
The probe is P = M_z M_x M_y [tool; 1]; its error is P - (q + tool).

Error names, units and Table II PDFs: ``TABLE_II`` (um for translations, urad for angles).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "NAMES",
    "TABLE_II",
    "STACK",
    "STROKES_MM",
    "TOOL_MM",
    "MAGNET_ORIGIN_MM",
    "VIBRATION_UM",
    "READING_UM",
    "axis_noise",
    "draw_errors",
    "rotation",
    "travel_directions",
    "probe_position",
]

#: The 21 errors (spelling of the diagnosis reports): 6 per axis, then the squareness.
NAMES = tuple(
    [f"{kind}_{c}({a})" for a in "xyz" for kind in ("delta", "eps") for c in "xyz"]
    + ["alpha_xy", "alpha_xz", "alpha_yz"]
)

#: Table II of the paper: ('uniform', low, high) or ('normal', mean, std), um or urad.
TABLE_II = {
    "delta_x(x)": ("uniform", -1.5, 1.5), "delta_y(x)": ("uniform", -2.5, 2.5),
    "delta_z(x)": ("uniform", -2.5, 2.5), "eps_x(x)": ("uniform", -18.5, 18.5),
    "eps_y(x)": ("uniform", -10.0, 10.0), "eps_z(x)": ("uniform", -18.5, 18.5),
    "delta_x(y)": ("uniform", -2.5, 2.5), "delta_y(y)": ("uniform", -1.5, 1.5),
    "delta_z(y)": ("uniform", -2.5, 2.5), "eps_x(y)": ("uniform", -18.5, 18.5),
    "eps_y(y)": ("uniform", -18.5, 18.5), "eps_z(y)": ("uniform", -10.0, 10.0),
    "delta_x(z)": ("normal", 5.5, 7.8), "delta_y(z)": ("normal", 3.2, 6.1),
    "delta_z(z)": ("normal", 8.4, 9.6), "eps_x(z)": ("normal", 15.1, 18.0),
    "eps_y(z)": ("normal", 15.3, 15.4), "eps_z(z)": ("normal", 10.2, 16.5),
    "alpha_xy": ("normal", 32.3, 12.8), "alpha_xz": ("normal", 51.4, 11.0),
    "alpha_yz": ("normal", 16.5, 7.2),
}  # fmt: skip

STACK = ("z", "x", "y")  # foundation first
STROKES_MM = {"x": 150.0, "y": 150.0, "z": 800.0}
TOOL_MM = np.array([0.0, -60.0, 500.0])
#: Nominal magnet centre in the bench frame: the magnet axis at mid-stroke of X and Y, its centre
#: at mid-stroke of Z (design notes, section 5): map point p sits at axis travel p + (75, 75, 400).
MAGNET_ORIGIN_MM = np.array([75.0, 15.0, 900.0])
VIBRATION_UM = 2.5  # per axis, per reading (paper)
READING_UM = 1.0  # position reading error per axis and reading (paper, eq. 10)


def draw_errors(rng: np.random.Generator) -> dict:
    """One bench: the 21 error amplitudes drawn from Table II.

    Returns
    -------
    dict
        name -> value, um or urad.
    """
    out = {}
    for name in NAMES:
        kind, a, b = TABLE_II[name]
        out[name] = float(rng.uniform(a, b) if kind == "uniform" else rng.normal(a, b))
    return out


def axis_noise(rng: np.random.Generator, n: int) -> np.ndarray:
    """Vibration and position-reading error of the axes (paper eq. 10), shape (n, 3), mm."""
    vib = rng.normal(0.0, VIBRATION_UM * 1e-3, (n, 3))
    return vib + rng.normal(0.0, READING_UM * 1e-3, (n, 3))


def rotation(ex, ey, ez) -> np.ndarray:
    """Rz(ez) Ry(ey) Rx(ex), exact, for angles in rad of shape (n,) (or scalars).

    Returns
    -------
    ndarray, shape (n, 3, 3)
    """
    ex, ey, ez = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (ex, ey, ez))
    ex, ey, ez = np.broadcast_arrays(ex, ey, ez)
    one, zero = np.ones_like(ex), np.zeros_like(ex)

    def mat(rows):
        return np.stack([np.stack(r, -1) for r in rows], -2)

    rx = mat([[one, zero, zero], [zero, np.cos(ex), -np.sin(ex)], [zero, np.sin(ex), np.cos(ex)]])
    ry = mat([[np.cos(ey), zero, np.sin(ey)], [zero, one, zero], [-np.sin(ey), zero, np.cos(ey)]])
    rz = mat([[np.cos(ez), -np.sin(ez), zero], [np.sin(ez), np.cos(ez), zero], [zero, zero, one]])
    return rz @ ry @ rx


def travel_directions(alpha_xy: float, alpha_xz: float, alpha_yz: float) -> dict:
    """Unit travel direction of each axis in its parent frame (squareness in rad).

    Z is the foundation axis (bench z). X rides on Z: it leans towards +z by alpha_xz. Y rides on
    X: it leans towards +x by alpha_xy and towards +z by alpha_yz.
    """
    dx = np.array([np.cos(alpha_xz), 0.0, np.sin(alpha_xz)])
    dy = np.array([np.sin(alpha_xy), 1.0, np.sin(alpha_yz)])
    dy[1] = np.sqrt(1.0 - dy[0] ** 2 - dy[2] ** 2)
    return {"x": dx, "y": dy, "z": np.array([0.0, 0.0, 1.0])}


def _value(errors, name, n):
    v = np.asarray(errors.get(name, 0.0), dtype=float)
    return np.broadcast_to(v, (n,))


def probe_position(q_mm, errors: dict, tool_mm=TOOL_MM) -> np.ndarray:
    """Actual probe position in the bench frame.

    Parameters
    ----------
    q_mm : ndarray, shape (n, 3), mm
        Actual travel of the x, y and z axes (command plus any axis-position disturbance).
    errors : dict
        name -> value in um or urad: a scalar (position-independent) or an array of shape (n,)
        (an error function evaluated at each reading). Missing names are zero.
    tool_mm : ndarray, shape (3,), mm

    Returns
    -------
    ndarray, shape (n, 3), mm
    """
    q = np.atleast_2d(np.asarray(q_mm, dtype=float))
    n = len(q)
    sq = [float(errors.get(k, 0.0)) * 1e-6 for k in ("alpha_xy", "alpha_xz", "alpha_yz")]
    d = travel_directions(*sq)
    v = np.broadcast_to(np.asarray(tool_mm, dtype=float), (n, 3)).copy()
    for a in reversed(STACK):  # innermost body first: P = M_z (M_x (M_y tool))
        k = "xyz".index(a)
        eps = [_value(errors, f"eps_{c}({a})", n) * 1e-6 for c in "xyz"]
        delta = np.stack([_value(errors, f"delta_{c}({a})", n) * 1e-3 for c in "xyz"], -1)
        v = np.einsum("nij,nj->ni", rotation(*eps), v) + q[:, k : k + 1] * d[a] + delta
    return v
