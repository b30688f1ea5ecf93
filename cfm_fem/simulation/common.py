"""Pieces shared by the tracker and Hall simulations: random streams, temperature, sizes."""

from __future__ import annotations

import numpy as np

__all__ = [
    "streams",
    "reading_streams",
    "temperature",
    "speeds_for",
    "circle_harmonics",
    "SPEED_CYCLE",
    "TEMP_NOISE_K",
]

#: Speed of each repetition, cycled: stop-and-go, then on the fly at 10, 5 and 20 mm/s.
SPEED_CYCLE = (0.0, 10.0, 5.0, 20.0)
TEMP_NOISE_K = 0.005  # temperature sensor noise


def streams(seed: int, names) -> dict:
    """One independent generator per named part of a simulation, all from ``seed``: adding a
    part or an effect does not change the draws of the others."""
    children = np.random.SeedSequence(int(seed)).spawn(len(names))
    return {nm: np.random.default_rng(c) for nm, c in zip(names, children, strict=True)}


#: The streams a replica draws afresh: the axes' vibration and reading error, the white noise.
READING_NOISE = ("vib", "noise")


def reading_streams(cfg: dict, names) -> dict:
    """:func:`streams` of a configuration, with the readings' noise of its replica.

    Replica 0 (``cfg.get("replica", 0)``) is the configuration as drawn. Replica k > 0 keeps
    every other draw (magnet, bench, scan, survey, gains, temperatures, the concealed effect)
    and draws the streams of :data:`READING_NOISE` from the seed sequence ``(seed, k)``: the
    same recording with other noise, whose spread of fitted parameters is the one their
    stated std must match.
    """
    rng = streams(cfg["seed"], names)
    k = int(cfg.get("replica", 0))
    if k < 0:
        raise ValueError(f"replica must be >= 0; found {k}")
    if k:
        fresh = [nm for nm in names if nm in READING_NOISE]
        children = np.random.SeedSequence([int(cfg["seed"]), k]).spawn(len(fresh))
        rng |= {nm: np.random.default_rng(c) for nm, c in zip(fresh, children, strict=True)}
    return rng


def temperature(t_s, rng: np.random.Generator):
    """Hall temperature (degC): a slow rise plus a daily swing of random phase.

    Returns
    -------
    true : ndarray, shape (n,), degC
    logged : ndarray, shape (n,), degC
        ``true`` plus sensor noise.
    """
    t_h = np.asarray(t_s, dtype=float) / 3600.0
    phase = rng.uniform(0.0, 2.0 * np.pi)
    rise = rng.uniform(0.05, 0.15)  # K/h
    true = 20.0 + rise * t_h + 0.3 * (np.sin(2.0 * np.pi * t_h / 24.0 + phase) - np.sin(phase))
    return true, true + rng.normal(0.0, TEMP_NOISE_K, len(t_h))


def speeds_for(n_reps: int, cycle=SPEED_CYCLE) -> list:
    """Speed of each repetition (mm/s, 0 = stop-and-go)."""
    return [float(cycle[r % len(cycle)]) for r in range(n_reps)]


def circle_harmonics(field, r_ref_mm: float, n_max: int, z_mm: float) -> np.ndarray:
    """2-D multipole coefficients of ``field(points (m, 3) mm) -> B (m, 3) T`` on a circle of
    radius ``r_ref_mm`` at ``z_mm``: B_y + i B_x = sum_n (B_n + i A_n) ((x + i y) / r_ref)^(n - 1)
    (Fourier analysis, 256 points).

    Returns
    -------
    ndarray, shape (n_max, 3)
        Rows (n, B_n, A_n), T at r_ref.
    """
    m = 256
    th = 2.0 * np.pi * np.arange(m) / m
    p = np.stack([r_ref_mm * np.cos(th), r_ref_mm * np.sin(th), np.full(m, z_mm)], -1)
    b = field(p)
    c = np.fft.fft(b[:, 1] + 1j * b[:, 0]) / m  # coefficient of e^{i k th}, k = n - 1
    n = np.arange(1, n_max + 1)
    return np.stack([n, c[n - 1].real, c[n - 1].imag], -1)
