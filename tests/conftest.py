"""Shared test configuration.

Parity tests compare float32 results at 1e-4..1e-5: make XLA use full float32 precision for
matrix products and convolutions on every backend (on GPUs the default may use TF32/bf16 passes).

The suite runs in pytest-xdist workers (`-n 2 --dist loadfile` in pyproject.toml: each test
file in one worker, so its module fixtures and compiled functions are built once). Each worker
is pinned to its own share of the CPUs before JAX starts its thread pools: two workers that
both size their XLA and PyTorch pools for every core only contend (measured on 2 cores:
unpinned, 22% more CPU time for a 14% shorter run), and the heaviest files go first.
"""

import os
from pathlib import Path

# Every process of the suite, the commands the tests start as subprocesses included, traces
# with full float32 precision: the precision is part of the compiled program, so a subprocess
# and the test that started it then share XLA's persistent compilation cache (a command killed
# and resumed in-process compiles its step once, not twice).
os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
# With the persistent cache on, JAX also points XLA's GPU autotuning cache at a path inside the
# configured cache directory, and that path string enters every executable's cache key: a test
# or command that names the same cache by another path (its own $PITTA_JAX_CACHE) would miss.
# The suite does not use that GPU-only cache; without it the keys depend on the program alone.
os.environ["JAX_PERSISTENT_CACHE_ENABLE_XLA_CACHES"] = "none"
# The suite is compile-bound, and most of a compile is XLA:CPU turning fusions into machine code.
# The tests check values, not speed: compile with LLVM at -O0, no loop unrolling and no SLP
# vectorisation, and with XLA's older LLVM-IR fusion emitters instead of its MLIR-based ones
# (none of which reassociates floating-point arithmetic). Measured on 2 vCPUs (2026-12-02/03,
# Ada-Depth's float64 step at 64x96, one core each, pairs run side by side): -O1 and the two
# LLVM options 103 -> 80 s, the step no slower (2.69 vs 2.78 s); the older emitters on top
# 116-138 -> 85-111 s (three pairs). -O0 rather than -O1 (2026-12-07, the whole suite each way):
# 1160 -> 1115 s of test time, and less once the few programs that run many steps take -O1 back
# (tests/xla_options.py). Placed first, so that flags of the caller's own XLA_FLAGS (the last of
# a repeated flag wins) override them.
TEST_CODEGEN_FLAGS = ("--xla_backend_optimization_level=0 --xla_backend_extra_options="
                      "xla_cpu_disable_loop_unrolling,xla_cpu_disable_slp_vectorizer "
                      "--xla_cpu_use_fusion_emitters=false")
# XLA aborts the process on a flag it does not know, and these are XLA's, not JAX's API: another
# jaxlib may rename or drop one. One subprocess (started once per run: its verdict is passed on
# to the xdist workers and the tests' subprocesses through the environment) tries them first;
# without them the suite is slower, not wrong.
_PROBED = "PITTA_JAX_TEST_CODEGEN_FLAGS"


def _codegen_flags() -> str:
  """TEST_CODEGEN_FLAGS when this jaxlib accepts them, else ""."""
  if _PROBED not in os.environ:
    import subprocess
    import sys
    env = {**os.environ, "XLA_FLAGS": TEST_CODEGEN_FLAGS, "JAX_PLATFORMS": "cpu"}
    code = "import jax; jax.numpy.zeros(1).block_until_ready()"
    try:
      ok = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          timeout=300).returncode == 0
    except (OSError, subprocess.SubprocessError):
      ok = False
    os.environ[_PROBED] = TEST_CODEGEN_FLAGS if ok else ""
  return os.environ[_PROBED]


if not os.environ.get("XLA_FLAGS", "").startswith(TEST_CODEGEN_FLAGS):  # not yet (xdist workers)
  os.environ["XLA_FLAGS"] = f"{_codegen_flags()} {os.environ.get('XLA_FLAGS', '')}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402


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

# The same two settings for this process, in case a plugin imported JAX before this file ran.
jax.config.update("jax_default_matmul_precision", "highest")
jax.config.update("jax_persistent_cache_enable_xla_caches", "none")

# The heaviest files (single-process seconds on 2 cores, 2026-12-01), started first so that
# the two workers finish together instead of one running the last big file alone. test_streams
# compiles one of test_adapt's programs: three files apart, it finds it in the shared XLA cache
# instead of compiling it at the same time in the other worker.
HEAVY_FIRST = ("test_experiments.py", "test_cli.py", "test_adadepth.py", "test_adapt.py",
               "test_faults.py", "test_comoda.py", "test_streams.py",
               "test_monodepth2_parity.py", "test_methods_cli.py", "test_networks_adapt.py")


def pytest_collection_modifyitems(config, items):
  """Heavy files first (a stable sort: every file keeps its own test order)."""
  rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
  items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def _suite_xla_cache(tmp_path_factory) -> Path:
  """One directory of persisted XLA executables for the whole run, shared by the xdist workers
  (their base temporary directories are siblings), this run's alone outside xdist."""
  base = tmp_path_factory.getbasetemp()
  path = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "xla-cache"
  path.mkdir(exist_ok=True)
  return path


@pytest.fixture(scope="session", autouse=True)
def _private_cache_root(tmp_path_factory):
  """Every test's cache root ($PITTA_JAX_CACHE: source models, ActMAD statistics, the XLA
  executables the commands persist) is this session's temporary directory, never the user's
  ~/.cache; a test that needs its own sets it again (monkeypatch).

  Every compile of a second or more is persisted from the first test on (JAX fixes its cache
  directory at the first compile that finds one set), in one directory that the root's `xla`
  links to: a program that two test files, two workers, or a test and the command it starts as
  a subprocess compile is compiled once. Executables are keyed by their program, compile
  options and JAX version, so sharing them changes no result."""
  from pitta_jax.source_model import CACHE_ENV, enable_compilation_cache
  root = tmp_path_factory.mktemp("pitta_jax_cache")
  (root / "xla").symlink_to(_suite_xla_cache(tmp_path_factory), target_is_directory=True)
  mp = pytest.MonkeyPatch()
  mp.setenv(CACHE_ENV, str(root))
  enable_compilation_cache()  # as the commands do: root/xla, their minimum compile time
  yield
  mp.undo()
