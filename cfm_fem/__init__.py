"""cfm_fem: field-mapping uncertainty of Hall-probe benches from FEM field maps."""

from .errors import CfmInputError, CfmInputWarning
from .models.field import FieldMap

__version__ = "0.1.0"

__all__ = ["CfmInputError", "CfmInputWarning", "FieldMap", "__version__"]
