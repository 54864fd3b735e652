"""SGDepth (Klingner et al. 2020), depth path: `SGDepthNet` and its `SPEC`."""

from pitta_jax.models.sgdepth.network import SGDepthNet
from pitta_jax.models.sgdepth.spec import SPEC

__all__ = ["SGDepthNet", "SPEC"]
