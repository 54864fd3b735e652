"""A per-program XLA option for tests whose program runs for longer than it compiles.

The suite compiles everything at LLVM -O0 (tests/conftest.py): most of its programs run once or
twice, and a compile at -O0 takes about two thirds of the time of one at -O1. A test that builds
one large step and runs it many times, or that compares two forms of one computation to within
float32 rounding, compiles that program at -O1 instead (`jax.jit(..., compiler_options=
RUN_OPTIMIZED)`, or the second argument of `make_chunk_runner`). Measured on 2 vCPUs (AMD EPYC
Zen 4 guest without AVX-512, 2026-12-07, the whole suite at -O1 and then at -O0, per-test
durations): 1160 -> 1115 s of test time in all, but Ada-Depth's file 112 -> 150 s (its parity
setup 70 -> 48 s, the frames of its reproducibility test 17 -> 48 s) and CoMoDa's 46 -> 78 s
(its float64 parity chunk 31 -> 63 s), and two of conv_vjp's comparisons with JAX's own
convolution rule at 1e-6 differed by 1.0e-6 and 1.2e-6 (-O0 contracts no multiply-add into an
FMA); those programs take RUN_OPTIMIZED. Values differ only by rounding, and every test keeps
its tolerance. (Before 2026-12-07 the suite compiled at -O1 and the opposite option, -O0 per
program, was taken by the parity tests that compile for far longer than they run.)
"""

RUN_OPTIMIZED = {"xla_backend_optimization_level": 1}  # jax.jit(..., compiler_options=...)
