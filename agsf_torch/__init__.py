"""agsf-torch: batched Gaussian sum filters (classic and FPKE-adaptive) for attitude estimation."""

from . import models, rotations
from .mixture import GaussianMixture

__all__ = ["GaussianMixture", "models", "rotations", "filters"]
__version__ = "0.1.0"


def __getattr__(name):  # lazy subpackages
    if name == "filters":
        from . import filters

        return filters
    raise AttributeError(name)
