"""pitta-jax: PITTA test-time adaptation for monocular depth estimation in JAX/Flax.

Paper: "No Pose Estimation? No Problem: Pose-Agnostic and Instance-Aware Test-Time
Adaptation for Monocular Depth Estimation" (Sung et al.). See docs/method.md for the equations and defaults.
"""

__version__ = "0.1.0"
