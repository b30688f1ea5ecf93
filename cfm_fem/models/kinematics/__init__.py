"""Bench kinematics: the HTM chain of paper eq. 1-10, its Monte Carlo, budget and design.

Modules: `chain` (the exact chain in plain numpy), `geometry` (kernel arguments, error sets and
noise keys from the seed), `monte_carlo` (`run_kinematics`, Table IV), `budget` (uncertainty
budget, design in reverse, GUM check). This namespace re-exports their public names.
"""

from .budget import (
    NOISE_NAME,
    UP_SHARE_MEANING,
    VAR_SHARE_MEANING,
    LinearModel,
    design_tolerances,
    gum_check,
    linear_model,
    uncertainty_budget,
)
from .chain import (
    error_values,
    probe_errors,
    probe_errors_for_bench,
    probe_positions,
    sensitivities,
    squareness_angles,
    travel_directions,
)
from .geometry import KernelGeometry, draw_error_sets, kernel_geometry, noise_keys, point_noise
from .monte_carlo import QUANTITIES, KinematicsResult, pool_table_iv, run_kinematics

__all__ = [
    "squareness_angles",
    "travel_directions",
    "error_values",
    "probe_positions",
    "probe_errors",
    "probe_errors_for_bench",
    "sensitivities",
    "QUANTITIES",
    "KernelGeometry",
    "kernel_geometry",
    "draw_error_sets",
    "noise_keys",
    "point_noise",
    "KinematicsResult",
    "pool_table_iv",
    "run_kinematics",
    "NOISE_NAME",
    "VAR_SHARE_MEANING",
    "UP_SHARE_MEANING",
    "LinearModel",
    "linear_model",
    "uncertainty_budget",
    "design_tolerances",
    "gum_check",
]
