"""cfm_fem: field-mapping uncertainty of Hall-probe benches from FEM field maps."""

from . import _numba_cache  # noqa: F401 - chooses numba's cache folder before numba loads
from .errors import CfmInputError, CfmInputWarning
from .field import FieldMap

__version__ = "0.1.0"

__all__ = ["CfmInputError", "CfmInputWarning", "FieldMap", "__version__"]
