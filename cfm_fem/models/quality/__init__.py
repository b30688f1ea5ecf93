"""Field quality from a field map: circular harmonics per plane and integrated, magnetic centre,
roll, magnetic length (`harmonics`), read at displaced points from the model between nodes
(`sampling`), with their uncertainty from a bench by Monte Carlo (`uncertainty`)."""

from .harmonics import (
    N_HARMONICS,
    VECTOR_NAMES,
    QualityNumbers,
    ScanPlan,
    analyse,
    centre_from_harmonics,
    fit_planes,
    length_plane_value,
    main_order_of,
    plan_from_nodes,
    plan_on_circles,
    quality_numbers,
)
from .sampling import LocalField
from .uncertainty import McQuality, Sources, budget_groups, run_quality_mc

__all__ = [
    "N_HARMONICS",
    "VECTOR_NAMES",
    "QualityNumbers",
    "ScanPlan",
    "centre_from_harmonics",
    "fit_planes",
    "length_plane_value",
    "analyse",
    "main_order_of",
    "plan_from_nodes",
    "plan_on_circles",
    "quality_numbers",
    "LocalField",
    "McQuality",
    "Sources",
    "budget_groups",
    "run_quality_mc",
]
