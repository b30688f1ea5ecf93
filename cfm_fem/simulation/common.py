"""Pieces shared by the tracker and Hall simulations: random streams, temperature, sizes."""

from __future__ import annotations

import numpy as np

__all__ = ["streams", "temperature", "speeds_for", "SPEED_CYCLE", "TEMP_NOISE_K"]

#: Speed of each repetition, cycled: stop-and-go, then on the fly at 10, 5 and 20 mm/s.
SPEED_CYCLE = (0.0, 10.0, 5.0, 20.0)
TEMP_NOISE_K = 0.005  # temperature sensor noise


def streams(seed: int, names) -> dict:
    """One independent generator per named part of a simulation, all from ``seed``: adding a
    part or an effect does not change the draws of the others."""
    children = np.random.SeedSequence(int(seed)).spawn(len(names))
    return {nm: np.random.default_rng(c) for nm, c in zip(names, children, strict=True)}


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
