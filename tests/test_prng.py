"""`prng`: the unrolled threefry against the published Threefry-2x32 answers and against
jax.random's own samplers (the same key must give the same numbers)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax import prng


# Random123's known-answer vectors for Threefry-2x32, 20 rounds (kat_vectors):
# (key0, key1), (counter0, counter1) -> (out0, out1)
KAT = [((0x00000000, 0x00000000), (0x00000000, 0x00000000), (0x6B200159, 0x99BA4EFE)),
       ((0xFFFFFFFF, 0xFFFFFFFF), (0xFFFFFFFF, 0xFFFFFFFF), (0x1CB996FC, 0xBB002BE7)),
       ((0x13198A2E, 0x03707344), (0x243F6A88, 0x85A308D3), (0xC4923A9C, 0x483DF7A0))]


@pytest.mark.parametrize("key,counter,expected", KAT)
def test_threefry2x32_known_answers(key, counter, expected):
  u = lambda v: jnp.asarray(v, jnp.uint32)
  out = jax.jit(prng.threefry2x32)(u(key[0]), u(key[1]), u([counter[0]]), u([counter[1]]))
  assert [int(o[0]) for o in out] == list(expected)


SAMPLERS = {
    "normal f32": lambda k: jax.random.normal(k, (3, 5, 7)),
    "normal f64": lambda k: jax.random.normal(k, (4, 9), jnp.float64),
    "uniform": lambda k: jax.random.uniform(k, (1001,), minval=-2.0, maxval=3.0),
    "bernoulli": lambda k: jax.random.bernoulli(k, 0.01, (4099,)),
    "randint": lambda k: jax.random.randint(k, (33,), 0, 1000),
    "permutation": lambda k: jax.random.permutation(k, 17),
    "bits u8": lambda k: jax.random.bits(k, (65,), jnp.uint8),
    "bits u16": lambda k: jax.random.bits(k, (65,), jnp.uint16),
    "bits u64": lambda k: jax.random.bits(k, (65,), jnp.uint64),
}


@pytest.mark.parametrize("name", sorted(SAMPLERS))
def test_same_draws_as_jax_random(name):
  draw, seed = SAMPLERS[name], 1000 * sorted(SAMPLERS).index(name)
  with jax.enable_x64(True):  # float64 and uint64 as asked
    _check_same_draws(draw, seed)


def _check_same_draws(draw, seed):
  raw, typed = jax.random.PRNGKey(seed), jax.random.key(seed)
  expected = np.asarray(draw(raw))
  np.testing.assert_array_equal(np.asarray(jax.jit(lambda k: draw(prng.unrolled(k)))(raw)),
                                expected)
  np.testing.assert_array_equal(np.asarray(draw(prng.unrolled(typed))), expected)


def test_split_fold_in_and_vmap_unchanged():
  """Keys split and folded from an unrolled key, and unrolled keys under vmap, draw as
  jax.random's."""
  key = jax.random.PRNGKey(3)
  keys = jax.random.split(jax.random.fold_in(key, 11), 5)
  expected = np.asarray(jax.vmap(lambda k: jax.random.normal(k, (8,)))(keys))
  derived = jax.random.split(jax.random.fold_in(prng.unrolled(key), 11), 5)
  np.testing.assert_array_equal(
      np.asarray(jax.jit(jax.vmap(lambda k: jax.random.normal(k, (8,))))(derived)), expected)
  np.testing.assert_array_equal(
      np.asarray(jax.vmap(lambda k: jax.random.normal(prng.unrolled(k), (8,)))(keys)), expected)


def test_other_implementations_pass_through():
  key = jax.random.key(0, impl="rbg")
  assert prng.unrolled(key) is key


def test_seeds_from_2_32_on_are_keys_of_their_own():
  """prng.seed_key (the engine's, the streams' and the source model's key of a seed) is
  jax.random.PRNGKey's key with 64-bit seeds whether or not x64 is on: without x64 PRNGKey kept
  the low 32 bits, so seed 2^32 + 7 ran exactly as seed 7. Seeds below 2^32 keep PRNGKey's own
  key; a negative seed (init_streams took one unchecked) is refused."""
  from pitta_jax.prng import seed_key
  for seed in (0, 7, 2**32 - 1):
    np.testing.assert_array_equal(seed_key(seed), jax.random.PRNGKey(seed))
  assert not np.array_equal(seed_key(2**32 + 7), seed_key(7))
  for seed in (jnp.int32(3), np.int64(3)):  # (init_streams(seeds=jnp.arange(K)))
    np.testing.assert_array_equal(seed_key(seed), jax.random.PRNGKey(3))
  assert not np.array_equal(seed_key(2**40), seed_key(0))
  with jax.enable_x64(True):
    for seed in (2**32, 2**32 + 7, 2**62 + 5):
      np.testing.assert_array_equal(seed_key(seed), jax.random.PRNGKey(seed))
  with pytest.raises(ValueError, match=r"seed must be in \[0, 2\^63\), got -5"):
    seed_key(-5)
