"""jax.random's threefry draws with the hash unrolled: the same numbers, a fraction of the time
on XLA:CPU.

On CPU, JAX lowers its threefry2x32 hash as a loop over the hash's five blocks of four rounds
(`use_rolled_loops` in jax's threefry module: a smaller program to compile), and XLA:CPU runs
each block as its own pass over the whole array of counters. For the large draws of a step
(CoTTA's noise on 32 views, 12M numbers; its restore masks, one per network parameter) those
passes cost more than the convolutions around them. Written out in full, the hash is one
elementwise expression that XLA fuses into a single kernel: 11.8M 32-bit draws in ~50 ms
instead of ~320 ms on a 2-core Xeon.

`unrolled(key)` gives a key of `UNROLLED_THREEFRY`, a PRNG implementation (`jax.extend.random.
define_prng_impl`) that is JAX's threefry with only `random_bits` replaced. Its bits are those
of JAX's default (partitionable) threefry bit generation for the same key, so
`jax.random.normal(unrolled(key), ...)` equals `jax.random.normal(key, ...)` bit for bit, and
so does every other sampler built on the bits (uniform, bernoulli, choice...). No draw changes;
only the program that computes it.
"""

from __future__ import annotations

import math
import operator

import jax
import jax.extend.random as jex_random
import jax.numpy as jnp
import numpy as np

_THREEFRY = jex_random.threefry_prng_impl
_ROTATIONS = ((13, 15, 26, 6), (17, 29, 16, 24))  # Salmon et al. 2011, Threefry-2x32
_PARITY = 0x1BD11BDA                               # the key schedule's constant


def _rotate_left(x: jax.Array, bits: int) -> jax.Array:
  return (x << np.uint32(bits)) | (x >> np.uint32(32 - bits))


def threefry2x32(k0: jax.Array, k1: jax.Array, x0: jax.Array, x1: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
  """Threefry-2x32 with 20 rounds of the counter pair (x0, x1) (uint32, any shape) under the
  key (k0, k1) (uint32 scalars); all 20 rounds and 6 key injections written out."""
  schedule = (k0, k1, k0 ^ k1 ^ np.uint32(_PARITY))
  x0, x1 = x0 + schedule[0], x1 + schedule[1]
  for block in range(5):
    for r in _ROTATIONS[block % 2]:
      x0 = x0 + x1
      x1 = _rotate_left(x1, r) ^ x0
    x0 = x0 + schedule[(block + 1) % 3]
    x1 = x1 + schedule[(block + 2) % 3] + np.uint32(block + 1)
  return x0, x1


def _random_bits(key: jax.Array, bit_width: int, shape: tuple[int, ...]) -> jax.Array:
  """JAX's partitionable threefry bits: element i (row-major) hashes the counter pair
  (i // 2**32, i % 2**32); 32-bit draws are the two output words xor-ed, 64-bit draws the two
  words side by side, narrower ones the xor truncated. key: (2,) uint32."""
  size = math.prod(shape)
  if size >= 2 ** 32:  # counters with a high word: JAX's own lowering
    return _THREEFRY.random_bits(key, bit_width, shape)
  counters = jax.lax.iota(np.uint32, size).reshape(shape)
  hi, lo = threefry2x32(key[0], key[1], jnp.zeros_like(counters), counters)
  if bit_width == 64:
    return (hi.astype(np.uint64) << np.uint64(32)) | lo.astype(np.uint64)
  return (hi ^ lo).astype({8: np.uint8, 16: np.uint16, 32: np.uint32}[bit_width])


UNROLLED_THREEFRY = jex_random.define_prng_impl(
    key_shape=_THREEFRY.key_shape, seed=_THREEFRY.seed, split=_THREEFRY.split,
    random_bits=_random_bits, fold_in=_THREEFRY.fold_in, name="threefry2x32_unrolled",
    tag="fry_unrolled")


def unrolled(key: jax.Array) -> jax.Array:
  """The same key as an `UNROLLED_THREEFRY` key: a raw (2,) uint32 key (`PRNGKey`) or a typed
  threefry key. Keys of other implementations are returned as they are."""
  if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
    if jax.random.key_impl(key) != jax.random.key_impl(jax.random.key(0, impl="threefry2x32")):
      return key
    key = jax.random.key_data(key)
  return jax.random.wrap_key_data(key, impl=UNROLLED_THREEFRY)


def seed_key(seed: int) -> jax.Array:
  """`jax.random.PRNGKey(seed)` as it is with 64-bit seeds (`jax_enable_x64`), whatever that
  setting: the key (seed >> 32, seed mod 2^32). Without x64, PRNGKey keeps the low 32 bits, so
  seed 2^32 + 7 drew seed 7's numbers; below 2^32 both give PRNGKey's key. `seed` in [0, 2^63)
  (`configs.check_seed`)."""
  from pitta_jax.configs import check_seed
  seed = operator.index(seed)  # NumPy and JAX integer scalars as Python ints; a float: TypeError
  check_seed(seed)
  if seed < 2**32:
    return jax.random.PRNGKey(seed)
  if jax.random.PRNGKey(0).shape != (2,):
    raise ValueError(f"seed {seed}: seeds from 2^32 on need JAX's default threefry PRNG")
  return jnp.asarray(np.array([seed >> 32, seed & 0xFFFFFFFF], np.uint32))
