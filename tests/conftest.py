"""Shared test configuration.

Parity tests compare float32 results at 1e-4..1e-5: make XLA use full float32 precision for
matrix products and convolutions on every backend (on GPUs the default may use TF32/bf16 passes).

The suite runs in pytest-xdist workers (`-n 2 --dist loadfile` in pyproject.toml: each test
file in one worker, so its module fixtures and compiled functions are built once). Each worker
is pinned to its own share of the CPUs before JAX starts its thread pools: two workers that
both size their XLA and PyTorch pools for every core only contend (measured on 2 cores:
unpinned, 22% more CPU time for a 14% shorter run).
"""

import os

import jax


def _pin_xdist_worker() -> None:
  """Worker i of n keeps CPUs i, i + n, ... of those this process may use (no-op outside xdist,
  with one worker, or with fewer CPUs than workers)."""
  worker = os.environ.get("PYTEST_XDIST_WORKER", "")  # "gw0", "gw1", ...
  count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
  if not worker.startswith("gw") or count < 2 or not hasattr(os, "sched_setaffinity"):
    return
  cpus = sorted(os.sched_getaffinity(0))
  if len(cpus) < count:
    return
  os.sched_setaffinity(0, cpus[int(worker[2:]) % count::count])


_pin_xdist_worker()

jax.config.update("jax_default_matmul_precision", "highest")
