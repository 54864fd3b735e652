"""Shared test configuration.

Parity tests compare float32 results at 1e-4..1e-5: make XLA use full float32 precision for
matrix products and convolutions on every backend (on GPUs the default may use TF32/bf16 passes).
"""

import jax

jax.config.update("jax_default_matmul_precision", "highest")
