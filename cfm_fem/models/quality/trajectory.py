"""Trajectory of a charged particle through a field map (dipoles): deflection and sagitta.

The orbit r(s) (arc length s in mm) of a particle of magnetic rigidity B rho (T m) and charge
sign q obeys

    d r / d s = t,      d t / d s = q t x B(r) / (1000 B rho),

integrated by the classical fourth-order Runge-Kutta method with a fixed step in s. The particle
enters at (x0, y0, z_start) moving along +z; the integration stops where z reaches z_end (the
last step is cut to land on it). With B_y > 0 a positive particle bends towards -x.

Deflection: the angle between the exit and entry directions; its components in the x-z and y-z
planes are signed (positive towards +x, +y). Sagitta: the largest distance of the orbit from the
chord joining its entry and exit points.
"""

from __future__ import annotations

import numpy as np

from ...errors import CfmInputError

__all__ = ["PARTICLE_MASS_GEV", "rigidity_from_energy", "track", "C_LIGHT"]

#: Rest energies, GeV.
PARTICLE_MASS_GEV = {"electron": 0.51099895e-3, "proton": 0.93827208816}
#: Speed of light in units of 1e9 m/s: B rho [T m] = p [GeV/c] / C_LIGHT.
C_LIGHT = 0.299792458


def rigidity_from_energy(kinetic_gev: float, particle: str = "electron") -> float:
    """Magnetic rigidity B rho (T m) of a particle of kinetic energy ``kinetic_gev`` (GeV)."""
    if particle not in PARTICLE_MASS_GEV:
        raise CfmInputError(
            f"particle must be one of {', '.join(PARTICLE_MASS_GEV)}; got {particle!r}"
        )
    if not (np.isfinite(kinetic_gev) and kinetic_gev > 0):
        raise CfmInputError(f"--energy must be a positive energy in GeV; got {kinetic_gev}")
    m = PARTICLE_MASS_GEV[particle]
    return float(np.sqrt(kinetic_gev * (kinetic_gev + 2 * m)) / C_LIGHT)


def track(field_at, rigidity_Tm: float, z_start: float, z_end: float, *, step_mm: float = 0.5,
          x0: float = 0.0, y0: float = 0.0, charge: int = 1) -> dict:  # fmt: skip
    """Orbit through a field (module docstring).

    Parameters
    ----------
    field_at : callable
        ``field_at(points (m, 3) mm) -> (B (m, 3) T, inside (m,) bool)``.
    rigidity_Tm : float, T m
    z_start, z_end : float, mm
        Entry and exit planes, z_start < z_end.
    step_mm : float, mm
        Runge-Kutta step in arc length.
    x0, y0 : float, mm
        Entry point.
    charge : {1, -1}

    Returns
    -------
    dict
        ``path_mm`` (n, 3), ``stages`` (4 (n - 1), 6) (position, mm, and direction at which
        each Runge-Kutta stage reads the field), ``stage_weights_mm`` (4 (n - 1),) (their
        weights h / 6, h / 3, h / 3, h / 6 in the step), ``charge``, ``deflection_mrad``,
        ``deflection_x_mrad``, ``deflection_y_mrad``, ``sagitta_mm``, ``exit_mm`` (3,),
        ``step_mm``, ``rigidity_Tm``.

    Raises
    ------
    CfmInputError
        A bad argument, or the orbit leaves the field (``inside`` False) before z_end.
    """
    if not (np.isfinite(rigidity_Tm) and rigidity_Tm > 0):
        raise CfmInputError(f"--rigidity must be a positive rigidity in T m; got {rigidity_Tm}")
    if not (step_mm > 0 and z_end > z_start):
        raise CfmInputError("the trajectory needs step > 0 mm and z_end > z_start")
    k = charge / (1000.0 * rigidity_Tm)  # 1 / (B rho) in 1 / (T mm)

    def deriv(state):
        if not np.all(np.isfinite(state)):  # a step far longer than the radius of curvature
            raise CfmInputError(
                f"--rigidity {rigidity_Tm:g} T m bends the orbit on a radius far below the "
                f"{step_mm:g} mm step; expected a rigidity the map's field bends by degrees"
            )
        b, inside = field_at(state[None, :3])
        if not inside[0]:
            raise CfmInputError(
                f"the trajectory leaves the field map at {np.round(state[:3], 4).tolist()} mm "
                "before its exit plane; give a larger rigidity or a map that holds the orbit"
            )
        t = state[3:]
        return np.concatenate([t, k * np.cross(t, b[0])])

    s = np.array([x0, y0, z_start, 0.0, 0.0, 1.0])
    path, stages, weights = [s[:3].copy()], [], []
    max_steps = int(10 * (z_end - z_start) / step_mm) + 10
    for _ in range(max_steps):
        h = step_mm
        if s[2] + h * s[5] > z_end:  # land on the exit plane (t_z > 0 in a map's dipole)
            h = (z_end - s[2]) / s[5]
        k1 = deriv(s1 := s)
        k2 = deriv(s2 := s + 0.5 * h * k1)
        k3 = deriv(s3 := s + 0.5 * h * k2)
        k4 = deriv(s4 := s + h * k3)
        stages += [s1, s2, s3, s4]
        weights += [h / 6.0, h / 3.0, h / 3.0, h / 6.0]
        s = s + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        s[3:] /= np.linalg.norm(s[3:])
        path.append(s[:3].copy())
        if s[2] >= z_end - 1e-9 * max(1.0, abs(z_end)):
            break
        if s[5] <= 0:
            raise CfmInputError("the particle turns back inside the map: rigidity too small")
    path = np.array(path)
    t_end = s[3:]
    chord = path[-1] - path[0]
    chord /= np.linalg.norm(chord)
    rel = path - path[0]
    dist = np.linalg.norm(rel - np.outer(rel @ chord, chord), axis=1)
    return {
        "path_mm": path,
        "stages": np.array(stages),
        "stage_weights_mm": np.array(weights),
        "charge": int(charge),
        "deflection_mrad": float(np.arccos(np.clip(t_end[2], -1.0, 1.0)) * 1e3),
        "deflection_x_mrad": float(np.arctan2(t_end[0], t_end[2]) * 1e3),
        "deflection_y_mrad": float(np.arctan2(t_end[1], t_end[2]) * 1e3),
        "sagitta_mm": float(dist.max()),
        "exit_mm": path[-1],
        "step_mm": float(step_mm),
        "rigidity_Tm": float(rigidity_Tm),
    }
