"""Priors and plausible ranges of the catalogued effects' parameters, and the columns an
effect adds to the model with them: the pieces every effect module shares."""

from __future__ import annotations

import numpy as np

from .calibrate import Columns

__all__ = ["WIDE", "PLAUSIBLE", "bounds_for", "effect_columns"]

WIDE = 1e6  # prior std of effect parameters (display units): effectively none, keeps cov finite


#: Physically plausible range of each parameter, display units: effect -> [(name prefix,
#: low, high, why)]; the first matching prefix applies. Generous on purpose: they reject fits that
#: need an unphysical value, not unusual benches.
PLAUSIBLE = {
    "thermal_drift": [
        ("drift_", -50.0, 50.0, "an axis drifting by more than 50 um/h (um/K) is not thermal"),
        ("scale_drift_", -100.0, 100.0, "screw/frame expansion beyond 100 ppm/h (ppm/K)"),
    ],
    "reversal": [("backlash_", -200.0, 200.0, "backlash beyond 0.2 mm on a precision stage")],
    "reading_delay": [
        ("tau", 0.0, 200.0, "a reading delay is positive (read late) and below 0.2 s"),
    ],
    "position_dependent_geometric": [
        ("eps", -1000.0, 1000.0, "angular error beyond 1 mrad over the stroke"),
        ("delta", -1000.0, 1000.0, "straightness/scale error beyond 1 mm over the stroke"),
    ],
    "arm_deflection": [
        ("sag_", 0.0, 500.0, "a load deflection sags downwards (gravity), below 0.5 mm"),
    ],
    "parameter_bias": [
        ("delta", -500.0, 500.0, "a constant axis error beyond 0.5 mm"),
        ("eps", -2000.0, 2000.0, "an angular error beyond 2 mrad"),
        ("alpha", -2000.0, 2000.0, "a squareness error beyond 2 mrad"),
    ],
    "probe_misalignment": [("m_", -50.0, 50.0, "a probe tilted by more than 50 mrad (3 deg)")],
    "sensor_offset": [
        ("d_", -1000.0, 1000.0, "Hall elements more than 1 mm apart"),
        ("e_", -1000.0, 1000.0, "a Hall element more than 1 mm from the others"),
        ("centroid_", -2000.0, 2000.0, "Hall elements 2 mm off the probe's reference point"),
    ],
    "magnet_misalignment": [
        ("magnet_d", -10000.0, 10000.0, "a magnet 10 mm off its survey or nominal placement"),
        ("magnet_", -10000.0, 10000.0, "a magnet rotated 10 mrad off its survey"),
    ],
    "planar_hall": [
        # high-mobility plates (InSb, InAs) carry planar terms of tens of % at 1 T
        ("k_", -1.0, 1.0, "a planar Hall term as large as the Hall signal at 1 T"),
    ],
    "hall_offset_gain": [
        ("offset_", -1000.0, 1000.0, "a Hall offset beyond 1 mT after zeroing"),
        ("gain_", -5.0, 5.0, "a Hall gain error beyond 5 %"),
    ],
    "magnet_temperature": [
        ("beta", -2500.0, 2500.0, "a field temperature coefficient beyond ferrite's 0.2 %/K"),
    ],
    "fringe_field_3d": [
        ("amplitude", 0.0, 2.0, "a magnet end takes the field from its body value to zero"),
        ("d", -1e4, 1e4, "an end or fringe length moved by more than 10 m"),
    ],
    "sensor_volume_averaging": [
        ("dw_", -1042.0, 1042.0, "differences of a^2/24 with a sensitive size a <= 5 mm"),
    ],
    "step_event": [
        ("step_", -2000.0, 2000.0, "a jump of the probe position beyond 2 mm"),
        ("offset_step_", -2000.0, 2000.0, "a jump of a Hall offset beyond 2 mT"),
    ],
}


def bounds_for(effect: str, names) -> tuple[np.ndarray, list]:
    """Plausible [low, high] (display units) and the reason of each parameter of ``effect``.

    Parameters
    ----------
    effect : str
    names : sequence of str

    Returns
    -------
    bounds : ndarray, shape (len(names), 2)
    why : list of str
    """
    out = np.tile([-np.inf, np.inf], (len(names), 1))
    why = [""] * len(names)
    for i, nm in enumerate(names):
        for prefix, lo, hi, reason in PLAUSIBLE.get(effect, []):
            if nm.startswith(prefix):
                out[i] = lo, hi
                why[i] = reason
                break
    return out, why


def effect_columns(J, names, units, group, std=WIDE):
    """The columns of an effect's new parameters: signatures ``J`` (n, 3, p), no prior to speak
    of (`WIDE`), and the plausible bounds of the effect ``group`` (`bounds_for`)."""
    p = J.shape[-1]
    bounds, _ = bounds_for(group, names)
    return Columns(J, names, units, np.zeros(p), np.full(p, float(std)), group, bounds=bounds)
