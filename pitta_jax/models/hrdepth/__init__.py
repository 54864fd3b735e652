"""HR-Depth (Lyu et al. 2021): `HRDepthNet` and its `SPEC`."""

from pitta_jax.models.hrdepth.network import HRDepthNet
from pitta_jax.models.hrdepth.spec import SPEC

__all__ = ["HRDepthNet", "SPEC"]
