"""cfm_fem: field-mapping uncertainty of Hall-probe benches from FEM field maps.

The command line is ``cfm-fem``; from Python, the same runs with the same defaults
(`cfm_fem.api`, docs/api.md)::

    import cfm_fem
    maps = cfm_fem.run_sweep("map.vtu", up_um=[10, 20])
    maps.uf("absB", up_um=20)  # U_f per node, units of 1e-4 B_ref
"""

from . import _numba_cache  # noqa: F401 - chooses numba's cache folder before numba loads
from .api import (
    read_bench,
    read_map,
    read_recording,
    run_compare,
    run_coupled,
    run_design,
    run_design_quality,
    run_diagnose,
    run_fig4,
    run_kinematics,
    run_quality,
    run_sweep,
    run_tolerance,
)
from .errors import CfmInputError, CfmInputWarning
from .models.field import FieldMap

__version__ = "0.1.0"

__all__ = [
    "CfmInputError",
    "CfmInputWarning",
    "FieldMap",
    "__version__",
    "read_bench",
    "read_map",
    "read_recording",
    "run_compare",
    "run_coupled",
    "run_design",
    "run_design_quality",
    "run_diagnose",
    "run_fig4",
    "run_kinematics",
    "run_quality",
    "run_sweep",
    "run_tolerance",
]
