"""torchcal: robot calibration on torch tensors."""
from .params import ParamSet
from .robot import Robot
from .tree import Marker

__version__ = "0.1.0"
__all__ = ["Robot", "ParamSet", "Marker", "__version__"]
