"""Losses, eqs. 8-10: the fast and literal L_d against literal NumPy loops (value and gradient),
hand-computed values, and properties."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pitta_jax import losses, masks
from reference_numpy import (channel_mean_loop, depth_refining_grad_loop,
                             depth_refining_loss_loop, edge_guided_loss_loop, laplacian_edge_loop)

SHAPE = (12, 20)
RTOL = 1e-5  # fast vs literal vs loop: float32 sums in different orders


def _ld_value_and_grad(depth, panoptic, dynamic_ids, s, mode, impl):
  f = lambda d: losses.depth_refining_loss(d, panoptic, dynamic_ids, s, mode, impl)
  return jax.value_and_grad(f)(depth)


@pytest.fixture(scope="module")
def ld():
  """(value, grad) of L_d w.r.t. depth; one compilation per (shape, s, mode, impl)."""
  return jax.jit(_ld_value_and_grad, static_argnums=(3, 4, 5))


@pytest.fixture(scope="module")
def total():
  return jax.jit(losses.pitta_loss, static_argnames=("s", "mode", "impl"))


@pytest.fixture(scope="module")
def le():
  return jax.jit(losses.edge_guided_loss)


def random_panoptic(rng, shape, n_ids, block):
  """Segment ids 0..n_ids in blocks of `block` pixels (block 1: every pixel random, so instances
  touch each other everywhere), cut to `shape`."""
  small = rng.integers(0, n_ids + 1, (shape[0] // block + 1, shape[1] // block + 1))
  return np.kron(small, np.ones((block, block), np.int64))[:shape[0], :shape[1]].astype(np.int32)


# Instances 3, 1, 5, 2 and an id absent from the map (9, still counted in N); 0 / -1 = unused.
DYNAMIC_IDS = np.array([3, 1, 0, 5, 9, -1, 2, 0], np.int32)


def assert_ld_matches_loop(ld, depth, pan, dyn, s, mode):
  want_v = depth_refining_loss_loop(depth, pan, dyn, s, mode)
  want_g = depth_refining_grad_loop(depth, pan, dyn, s, mode)
  got = {impl: ld(depth, pan, dyn, s, mode, impl) for impl in losses.IMPLS}
  for impl, (v, g) in got.items():
    np.testing.assert_allclose(float(v), want_v, rtol=RTOL, err_msg=impl)
    np.testing.assert_allclose(np.asarray(g), want_g, rtol=RTOL, atol=1e-7, err_msg=impl)
  (vf, gf), (vl, gl) = got["fast"], got["literal"]
  np.testing.assert_allclose(float(vf), float(vl), rtol=RTOL)
  np.testing.assert_allclose(np.asarray(gf), np.asarray(gl), rtol=RTOL, atol=1e-7)
  return want_v


@pytest.mark.parametrize("s,mode", [(1, "binary"), (3, "binary"), (5, "binary"), (7, "binary"),
                                    (9, "binary"), (3, "instance_id"), (5, "instance_id"),
                                    (3, "segment_id"), (5, "segment_id")])
def test_fast_and_literal_match_loop(ld, s, mode):
  # Reference: literal NumPy loops of eqs. 3, 4, 7, 8 (value) and of the sign formula for the
  # gradient, on random id maps where instances touch (block 1: every pixel random; blocks of
  # 2-3 pixels: larger touching instances), tolerance 1e-5 relative.
  rng = np.random.default_rng(s + {"binary": 10, "instance_id": 20, "segment_id": 30}[mode])
  for block in (1, 2, 3):
    pan = random_panoptic(rng, SHAPE, 6, block)
    depth = rng.uniform(0.5, 80.0, SHAPE).astype(np.float32)
    value = assert_ld_matches_loop(ld, depth, pan, DYNAMIC_IDS, s, mode)
    assert value > 0 or s == 1


@pytest.mark.parametrize("mode", ["binary", "instance_id"])
def test_fast_and_literal_match_loop_on_depths_of_either_sign(ld, mode):
  # Reference: the NumPy loops, as above, on depths in [-40, 40]: eq. 8's |D~' - median| holds
  # for any finite map (the fast form once dropped a |.| that positive depths never need).
  rng = np.random.default_rng({"binary": 40, "instance_id": 50}[mode])
  for s in (3, 5):
    pan = random_panoptic(rng, SHAPE, 6, 2)
    depth = rng.uniform(-40.0, 40.0, SHAPE).astype(np.float32)
    assert_ld_matches_loop(ld, depth, pan, DYNAMIC_IDS, s, mode)


@pytest.mark.parametrize("mode", ["binary", "segment_id"])
def test_fast_loss_of_a_large_window_matches_loop(ld, mode):
  # Reference: literal NumPy loops, as above. From losses.STACKED_FROM_WINDOW on the fast L_d
  # selects from windows stacked on an array axis instead of unrolling them (which took minutes
  # to compile); 16x24 holds interior windows and windows clipped on one or both axes. Instance 3
  # fills the left half but for a patch of instance 1, so that it fills more than half of the
  # windows of pixels outside it (the |0 - D~'_e| terms); the rest is random ids.
  s = losses.STACKED_FROM_WINDOW
  rng = np.random.default_rng(s)
  for block in (1, 2):
    pan = random_panoptic(rng, (16, 24), 6, block)
    pan[:, :13], pan[4:9, 2:6] = 3, 1
    depth = rng.uniform(0.5, 80.0, (16, 24)).astype(np.float32)
    value, grad = ld(depth, pan, DYNAMIC_IDS, s, mode, "fast")
    want = depth_refining_loss_loop(depth, pan, DYNAMIC_IDS, s, mode)
    np.testing.assert_allclose(float(value), want, rtol=RTOL)
    np.testing.assert_allclose(np.asarray(grad),
                               depth_refining_grad_loop(depth, pan, DYNAMIC_IDS, s, mode),
                               rtol=RTOL, atol=1e-7)


@pytest.mark.parametrize("rows", [1, 5])  # 16 rows: 16 blocks, or 4 with one row in the last
def test_fast_loss_in_blocks_of_rows_matches_loop(rows):
  # Reference: the NumPy loops of eq. 8 (an index map is a panoptic map whose ids are the rows).
  # The stacked fast L_d goes through the image a block of rows at a time (bounded memory); the
  # value and the gradient must be those of the whole image's windows.
  s, shape = losses.STACKED_FROM_WINDOW, (16, 24)
  rng = np.random.default_rng(20 + rows)
  index = random_panoptic(rng, shape, 4, 2)
  index[:, :13], index[4:9, 2:6] = 3, 1  # instance 3 fills most windows of its neighbours
  depth = rng.uniform(0.5, 80.0, shape).astype(np.float32)
  ids = np.arange(1, 5, dtype=np.int32)
  block_bytes = rows * shape[1] * s * s * 4
  for mode in ("binary", "segment_id"):
    f = lambda d: losses.depth_refining_loss_fast(  # noqa: E731
        d, jnp.asarray(index), jnp.int32(4), s, mode, jnp.asarray(ids), block_bytes)
    v, g = jax.jit(jax.value_and_grad(f))(jnp.asarray(depth))
    np.testing.assert_allclose(float(v), depth_refining_loss_loop(depth, index, ids, s, mode),
                               rtol=RTOL)
    np.testing.assert_allclose(np.asarray(g), depth_refining_grad_loop(depth, index, ids, s, mode),
                               rtol=RTOL, atol=1e-7)


def test_image_smaller_than_window(ld):
  # Reference: NumPy loops; a 3x4 image with s = 5 (every window is clipped on both axes).
  rng = np.random.default_rng(3)
  pan = random_panoptic(rng, (3, 4), 4, 1)
  depth = rng.uniform(1.0, 10.0, (3, 4)).astype(np.float32)
  assert_ld_matches_loop(ld, depth, pan, np.array([1, 2, 3, 4], np.int32), 5, "binary")


def test_hand_computed_includes_terms_outside_instances(ld):
  # Hand value, 1x3 row, s = 3, instance = pixels 0, 1 (depths 2, 4); pixel 2 background:
  # D~ = [2, 4, 0]; windows {2,4} -> 3, {2,4,0} -> 2, {4,0} -> 2;
  # L_d = |2-3| + |4-2| + |0-2| = 1 + 2 + 2 = 5 (N = 1). The last term lies outside the
  # instance: constant in D but part of eq. 8's value. Gradient: sign(2-3), sign(4-2), 0.
  depth = np.array([[2.0, 4.0, 10.0]], np.float32)
  pan = np.array([[7, 7, 1]], np.int32)
  dyn = np.array([7, 0], np.int32)
  for impl in losses.IMPLS:
    v, g = ld(depth, pan, dyn, 3, "binary", impl)
    assert float(v) == pytest.approx(5.0), impl
    np.testing.assert_array_equal(np.asarray(g), [[-1.0, 1.0, 0.0]])
  # instance_id mode with the instance second in the table (g = 2): D~ = [4, 8, 0] -> windows
  # 6, 4, 4 -> L_d = (2 + 4 + 4) / N, N = 2 (id 5 has no pixel but counts).
  dyn = np.array([5, 7], np.int32)
  for impl in losses.IMPLS:
    v, g = ld(depth, pan, dyn, 3, "instance_id", impl)
    assert float(v) == pytest.approx(10.0 / 2), impl
    np.testing.assert_array_equal(np.asarray(g), [[-1.0, 1.0, 0.0]])  # 1/N * g * sign


def test_no_instances_gives_zero_without_nan(ld):
  # Hand value: N = 0 -> L_d = 0 and a zero (not NaN) gradient, in both implementations.
  depth = np.random.default_rng(0).uniform(1, 5, SHAPE).astype(np.float32)
  pan = random_panoptic(np.random.default_rng(1), SHAPE, 6, 2)
  for dyn in (np.zeros(8, np.int32), np.full(8, -1, np.int32)):
    for impl in losses.IMPLS:
      v, g = ld(depth, pan, dyn, 3, "binary", impl)
      assert float(v) == 0.0
      assert np.all(np.asarray(g) == 0.0)


def test_a_non_finite_depth_is_not_hidden_by_the_fast_loss(ld):
  """Eq. 8 taken literally on a depth with NaN or inf anywhere is not finite (D * 0 is NaN in
  every other instance's masked map): both implementations say so; 'fast' returned a finite
  L_d for a NaN outside the instances. A finite pixel outside every instance keeps a finite
  gradient in 'fast' (inf * 0 had leaked NaN into its neighbours')."""
  rng = np.random.default_rng(3)
  pan = random_panoptic(rng, SHAPE, 6, 3)
  outside = tuple(np.argwhere(~np.isin(pan, DYNAMIC_IDS[DYNAMIC_IDS > 0]))[0])
  inside = tuple(np.argwhere(pan == 3)[0])
  for where in (outside, inside):
    for bad in (np.nan, np.inf):
      depth = rng.uniform(1, 5, SHAPE).astype(np.float32)
      depth[where] = bad
      for impl in losses.IMPLS:
        assert not np.isfinite(float(ld(depth, pan, DYNAMIC_IDS, 3, "binary", impl)[0])), impl
      assert math.isnan(float(ld(depth, pan, DYNAMIC_IDS, 3, "binary", "fast")[0]))
  depth = rng.uniform(1, 5, SHAPE).astype(np.float32)
  depth[outside] = np.nan
  g = np.asarray(ld(depth, pan, DYNAMIC_IDS, 3, "binary", "fast")[1])
  finite_outside = ~np.isin(pan, DYNAMIC_IDS[DYNAMIC_IDS > 0]) & np.isfinite(depth)
  assert np.all(np.isfinite(g[finite_outside]))
  # no instance: no term, whatever the depth (the literal sum over no instance is 0)
  for impl in losses.IMPLS:
    assert float(ld(depth, pan, np.zeros(8, np.int32), 3, "binary", impl)[0]) == 0.0


def test_from_index_matches_public_api(ld):
  # Reference: the public entry point from the panoptic map (same table, same numbers).
  rng = np.random.default_rng(5)
  pan = random_panoptic(rng, SHAPE, 6, 1)
  depth = rng.uniform(1, 5, SHAPE).astype(np.float32)

  @jax.jit
  def from_index(depth, pan, dyn):
    ids, valid = masks.table_from_dynamic_ids(dyn)
    index = masks.instance_index_map(pan, ids, valid)
    return [losses.depth_refining_loss_from_index(depth, index, jnp.sum(valid), s=3,
                                                  mode="instance_id", impl=impl,
                                                  n_max=dyn.shape[0])
            for impl in losses.IMPLS]

  want, _ = ld(depth, pan, DYNAMIC_IDS, 3, "instance_id", "literal")
  for got in from_index(depth, pan, DYNAMIC_IDS):
    np.testing.assert_allclose(float(got), float(want), rtol=RTOL)


@pytest.mark.parametrize("s", [3, losses.STACKED_FROM_WINDOW])
def test_index_entries_above_n_are_no_instance(s):
  # Reference: the NumPy loops of eq. 8 with the instances 1..n only (an index map is a panoptic
  # map whose ids are the rows; rows above n are not in the sum). Both implementations, an index
  # map that also holds rows n + 1 and n + 2 (binary masks, and g = j).
  rng = np.random.default_rng(11)
  shape = (16, 24)
  index = random_panoptic(rng, shape, 5, 2)
  index[:, :12] = np.where(index[:, :12] > 0, 2, 0)  # an instance that fills windows
  depth = rng.uniform(0.5, 80.0, shape).astype(np.float32)
  n = 3
  rows = np.arange(1, n + 1, dtype=np.int32)
  for mode in ("binary", "instance_id"):
    want_v = depth_refining_loss_loop(depth, index, rows, s, mode)
    want_g = depth_refining_grad_loop(depth, index, rows, s, mode)
    for impl in losses.IMPLS:
      f = lambda d: losses.depth_refining_loss_from_index(d, jnp.asarray(index), jnp.int32(n), s=s,
                                                          mode=mode, impl=impl, n_max=5)
      v, g = jax.value_and_grad(f)(jnp.asarray(depth))
      np.testing.assert_allclose(float(v), want_v, rtol=RTOL, err_msg=impl)
      np.testing.assert_allclose(np.asarray(g), want_g, rtol=RTOL, atol=1e-7, err_msg=impl)


def test_a_count_above_the_table_counts_as_the_tables_rows():
  # Reference: the NumPy loop of eq. 8 over the table's rows 1..n_max (a table of n_max rows
  # holds at most n_max instances): n = 5 with 3 rows and n = 3 with 2 rows; the fast loss
  # divided by n and kept index entries above n_max, the literal one did neither.
  rng = np.random.default_rng(5)
  index = random_panoptic(rng, (12, 16), 4, 2)
  depth = rng.uniform(0.5, 80.0, (12, 16)).astype(np.float32)
  for n, n_max in ((5, 3), (3, 2)):
    want = depth_refining_loss_loop(depth, index, np.arange(1, n_max + 1, dtype=np.int32), 3,
                                    "binary")
    for impl in losses.IMPLS:
      got = losses.depth_refining_loss_from_index(jnp.asarray(depth), jnp.asarray(index),
                                                  jnp.int32(n), s=3, impl=impl, n_max=n_max)
      np.testing.assert_allclose(float(got), want, rtol=RTOL, err_msg=f"{impl} n={n}")


def test_an_empty_map_is_refused_naming_its_shape():
  for f in (lambda d: losses.depth_refining_loss(d, jnp.zeros(d.shape, jnp.int32),
                                                 jnp.arange(1, 3, dtype=jnp.int32), 3),
            lambda d: losses.median_filter(d, 3), lambda d: losses.median_filter(d, 17)):
    with pytest.raises(ValueError, match=r"H, W >= 1, got shape \(0, 3\)"):
      f(jnp.zeros((0, 3)))


def test_bad_arguments():
  d, i = jnp.ones((4, 4)), jnp.zeros((4, 4), jnp.int32)
  with pytest.raises(ValueError, match="n_max"):
    losses.depth_refining_loss_from_index(d, i, 1, impl="literal")
  with pytest.raises(ValueError, match="impl"):
    losses.depth_refining_loss_from_index(d, i, 1, impl="slow")
  with pytest.raises(ValueError, match="mode"):
    losses.depth_refining_loss(d, i, jnp.zeros(2, jnp.int32), 3, mode="ids")
  with pytest.raises(ValueError, match="odd"):
    losses.depth_refining_loss(d, i, jnp.zeros(2, jnp.int32), 4)


# --- properties (shape SHAPE, s = 3, binary mode unless stated: one compilation each) --------

panoptic_maps = hnp.arrays(np.int32, SHAPE, elements=st.integers(0, 5))
depth_maps = hnp.arrays(np.float32, SHAPE,
                        elements=st.floats(0.125, 80.0, width=32, allow_subnormal=False))


@settings(max_examples=15, deadline=None)
@given(pan=panoptic_maps, depth=depth_maps, perm=st.permutations(range(5)))
def test_invariant_to_permuting_instances(ld, pan, depth, perm):
  # Property (binary mode): L_d and its gradient do not depend on the order of the instances.
  dyn = np.array([1, 2, 3, 4, 5], np.int32)
  v, g = ld(depth, pan, dyn, 3, "binary", "fast")
  vp, gp = ld(depth, pan, dyn[list(perm)], 3, "binary", "fast")
  np.testing.assert_allclose(float(vp), float(v), rtol=RTOL)
  np.testing.assert_allclose(np.asarray(gp), np.asarray(g), rtol=RTOL)


@settings(max_examples=15, deadline=None)
@given(pan=panoptic_maps, depth=depth_maps, a=st.floats(0.01, 100.0))
def test_positively_homogeneous(ld, pan, depth, a):
  # Property (binary mode): L_d(a D) = a L_d(D) for a > 0 (medians commute with scaling).
  dyn = np.array([1, 2, 3, 4, 5], np.int32)
  v, _ = ld(depth, pan, dyn, 3, "binary", "fast")
  va, _ = ld((np.float32(a) * depth).astype(np.float32), pan, dyn, 3, "binary", "fast")
  np.testing.assert_allclose(float(va), a * float(v), rtol=1e-4, atol=1e-6)


@settings(max_examples=15, deadline=None)
@given(pan=panoptic_maps, depth=depth_maps)
def test_fast_equals_literal_property(ld, pan, depth):
  # Reference: the literal eq. 8 (vmap over the N_max masked maps), value and gradient.
  dyn = np.array([2, 0, 4, 1, 5, -1], np.int32)
  vf, gf = ld(depth, pan, dyn, 3, "binary", "fast")
  vl, gl = ld(depth, pan, dyn, 3, "binary", "literal")
  np.testing.assert_allclose(float(vf), float(vl), rtol=RTOL, atol=1e-6)
  np.testing.assert_allclose(np.asarray(gf), np.asarray(gl), rtol=RTOL)


# --- edge-guided loss and total ----------------------------------------------------------------

def test_edge_guided_loss_matches_loop(le):
  # Reference: literal NumPy loops of eqs. 5, 6, 9, with weights None and (H, W) arrays.
  rng = np.random.default_rng(2)
  image = rng.random(SHAPE + (3,)).astype(np.float32)
  depth = rng.uniform(1, 50, SHAPE).astype(np.float32)
  u, v = rng.random(SHAPE).astype(np.float32), rng.random(SHAPE).astype(np.float32)
  for uu, vv in ((None, None), (u, v), (np.float32(2.0), None)):
    np.testing.assert_allclose(float(le(image, depth, uu, vv)),
                               edge_guided_loss_loop(image, depth, uu, vv), rtol=1e-5)


@settings(max_examples=15, deadline=None)
@given(d=hnp.arrays(np.float32, SHAPE, elements=st.integers(0, 64).map(lambda k: k / 8.0)),
       noise=hnp.arrays(np.float32, SHAPE + (3,), elements=st.integers(-8, 8).map(float)))
def test_edge_guided_loss_properties(le, d, noise):
  # Properties: L_e >= 0; L_e = 0 when the depth's edges equal the image's (an image with three
  # equal channels d against the depth d + 3; up to the rounding of the channel mean and of the
  # added constant, 1e-6 of the edges' sum); against a flat depth, L_e = sum dI (loop reference).
  grey = np.repeat(d[..., None], 3, axis=-1)
  edges_d = float(np.sum(laplacian_edge_loop(d)))
  assert float(le(grey, d + np.float32(3.0))) <= 1e-6 * (1.0 + edges_d)
  image = grey + np.float32(0.25) * noise
  assert float(le(image, d)) >= 0.0
  flat = float(le(image, np.full(SHAPE, 5.0, np.float32)))
  edges_sum = float(np.sum(laplacian_edge_loop(channel_mean_loop(image))))
  np.testing.assert_allclose(flat, edges_sum, rtol=1e-5, atol=1e-5)


def test_pitta_loss_total_and_parts(total):
  # Reference: eq. 10 from the NumPy loops of L_d and L_e; lambda = 0 leaves only L_d,
  # lambda = inf (Table 4's "L_e only") leaves only L_e.
  rng = np.random.default_rng(4)
  image = rng.random(SHAPE + (3,)).astype(np.float32)
  depth = rng.uniform(1, 50, SHAPE).astype(np.float32)
  pan = random_panoptic(rng, SHAPE, 6, 2)
  out = total(image, depth, pan, DYNAMIC_IDS, s=3, lam=0.2)  # lam traced: one compilation
  l_d = depth_refining_loss_loop(depth, pan, DYNAMIC_IDS, 3)
  l_e = edge_guided_loss_loop(image, depth)
  assert int(out.n) == 5
  np.testing.assert_allclose(float(out.l_d), l_d, rtol=RTOL)
  np.testing.assert_allclose(float(out.l_e), l_e, rtol=RTOL)
  np.testing.assert_allclose(float(out.total), l_d + 0.2 * l_e, rtol=RTOL)
  zero = total(image, depth, pan, DYNAMIC_IDS, s=3, lam=0.0)
  assert float(zero.total) == float(zero.l_d)
  only_e = total(image, depth, pan, DYNAMIC_IDS, s=3, lam=math.inf)
  assert float(only_e.total) == float(only_e.l_e)
  # The gradient through a traced lambda = inf is L_e's alone (no inf * 0 = NaN).
  grad = jax.jit(jax.grad(lambda d, lam: losses.pitta_loss(image, d, pan, DYNAMIC_IDS, s=3,
                                                           lam=lam).total))
  g_inf = np.asarray(grad(depth, math.inf))
  assert np.isfinite(g_inf).all()
  g_e = np.asarray(jax.jit(jax.grad(lambda d: losses.edge_guided_loss(image, d)))(depth))
  np.testing.assert_allclose(g_inf, g_e, rtol=1e-6)


@pytest.mark.parametrize("lam, want", [(0.0, 2.0), (0.5, 3.5), (math.inf, 3.0)])
def test_combine_with_a_python_or_a_traced_lambda(lam, want):
  """Eq. 10 by hand, L_d = 2, L_e = 3: 2 + lambda 3, L_e alone at lambda = inf; the same for a
  Python float (the engine's static lambda) and a traced one (the lambda sweep)."""
  l_d, l_e = jnp.float32(2.0), jnp.float32(3.0)
  assert float(losses.combine(l_d, l_e, lam)) == want
  assert float(jax.jit(losses.combine)(l_d, l_e, jnp.float32(lam))) == want


def test_combine_refuses_a_concrete_negative_or_nan_lambda_of_any_type():
  """A NumPy or JAX scalar lambda is checked as a Python float is (np.float32(-1) gave -1)."""
  for lam in (-1.0, np.float32(-1.0), np.array(np.nan), jnp.float32(-0.5)):
    with pytest.raises(ValueError, match="lam must be >= 0"):
      losses.combine(jnp.float32(2.0), jnp.float32(3.0), lam)
  assert float(losses.combine(jnp.float32(2.0), jnp.float32(3.0), np.float32(0.5))) == 3.5


def test_combine_keeps_a_float64_lambda():
  """Eq. 10 with a traced lambda under x64: lambda stays float64 (it was cast to float32, so
  0.1 became 0.10000000149 and a float64 check of the lambda sweep was off by 1e-9)."""
  with jax.enable_x64(True):
    l_d, l_e = jnp.float64(2.0), jnp.float64(3.0)
    got = jax.jit(losses.combine)(l_d, l_e, jnp.float64(0.1))
    assert got.dtype == jnp.float64 and float(got) == 2.0 + 0.1 * 3.0


def test_depth_refining_loss_of_an_empty_instance_table_is_zero():
  """A (0,) dynamic-id table (no instance at all): eq. 8 has no term, 0 with a zero gradient,
  from both forms ('fast' failed on an empty reduction)."""
  depth = jnp.asarray(np.random.default_rng(0).uniform(1, 5, (8, 9)), jnp.float32)
  panoptic, ids = jnp.ones((8, 9), jnp.int32), jnp.zeros((0,), jnp.int32)
  for impl in ("fast", "literal"):
    value, grad = jax.value_and_grad(
        lambda d: losses.depth_refining_loss(d, panoptic, ids, 3, "binary", impl))(depth)
    assert float(value) == 0.0 and not np.any(np.asarray(grad))


def test_shape_mistakes_are_named():
  """Wrong shapes fail with a ValueError that names the argument (they were broadcasting
  TypeErrors, an IndexError, or for a non-scalar n a loss of shape (2,)); one segment id given
  as a scalar is a table of one."""
  depth = jnp.asarray(np.random.default_rng(0).random((6, 7)), jnp.float32)
  pan = np.zeros((6, 7), np.int32)
  pan[1:4, 2:5] = 5
  one = losses.depth_refining_loss(depth, pan, np.int32(5))
  np.testing.assert_allclose(one, losses.depth_refining_loss(depth, pan, np.array([5])))
  with pytest.raises(ValueError, match=r"masks \(N_max, H, W\) .* must agree"):
    losses.depth_refining_loss(depth, pan[:, :6], np.array([5]), impl="literal")
  with pytest.raises(ValueError, match="n .* must be a scalar"):
    losses.depth_refining_loss_from_index(depth, (pan > 0).astype(np.int32), jnp.array([1, 1]))
  with pytest.raises(ValueError, match=r"weights must be a scalar or the map's \(6, 7\)"):
    losses.edge_guided_loss(jnp.ones((6, 7, 3)), depth, u=jnp.ones((3,)))
  with pytest.raises(ValueError, match="positive odd int, got True"):
    losses.depth_refining_loss(depth, pan, np.array([5]), s=True)


def test_literal_loss_from_index_refuses_a_non_scalar_n():
  """N is a scalar for both forms. The fast form refuses an (N_max,) n; the literal one
  compared it row by row with the row numbers, so the table's validity vector passed as n
  (True, True, False) silently kept one instance of two: L_d of instance 1 alone."""
  rng = np.random.default_rng(3)
  depth = jnp.asarray(rng.uniform(1, 5, (6, 7)), jnp.float32)
  index = np.zeros((6, 7), np.int32)
  index[1:4, 1:4], index[2:6, 4:7] = 1, 2
  want = losses.depth_refining_loss_from_index(depth, index, 2, s=3, impl="literal", n_max=3)
  np.testing.assert_allclose(
      want, losses.depth_refining_loss_from_index(depth, index, 2, s=3), rtol=RTOL)
  for impl in losses.IMPLS:
    with pytest.raises(ValueError, match="n .* must be a scalar"):
      losses.depth_refining_loss_from_index(depth, index, jnp.array([True, True, False]), s=3,
                                            impl=impl, n_max=3)


def test_an_empty_instance_table_still_checks_the_inputs():
  """With no dynamic ids (a frame without instances) L_d is 0, but a batched depth, a float
  panoptic map or maps of another size are refused as with a table (they returned 0)."""
  empty = np.zeros((0,), np.int32)
  assert float(losses.depth_refining_loss(jnp.ones((6, 8)), np.zeros((6, 8), np.int32),
                                          empty)) == 0.0
  with pytest.raises(ValueError, match=r"depth \(2, 6, 8\) and panoptic \(6, 8\) must be"):
    losses.depth_refining_loss(jnp.ones((2, 6, 8)), np.zeros((6, 8), np.int32), empty)
  with pytest.raises(ValueError, match=r"depth \(6, 8\) and panoptic \(3, 3\) must be"):
    losses.depth_refining_loss(jnp.ones((6, 8)), np.zeros((3, 3), np.int32), empty)
  with pytest.raises(TypeError, match="panoptic must be an integer array"):
    losses.depth_refining_loss(jnp.ones((6, 8)), np.zeros((6, 8), np.float32), empty)


def test_lambda_and_channel_mistakes_are_named():
  """Eq. 10's lambda is a scalar >= 0 (inf: L_e alone): a negative or NaN Python lambda (which
  maximised L_e or made the loss NaN) and a (K,) array (which broadcast the loss to (K,)) are
  refused; an image without channels is refused by I_bar (an IndexError before); an lr too
  large for a float is the config's own error (an OverflowError before)."""
  from pitta_jax import edges
  from pitta_jax.adapt import AdaptConfig
  l_d, l_e = jnp.float32(1.0), jnp.float32(2.0)
  assert float(losses.combine(l_d, l_e, 0.5)) == 2.0 and float(losses.combine(l_d, l_e,
                                                                              math.inf)) == 2.0
  for lam in (-1.0, math.nan):
    with pytest.raises(ValueError, match="lam must be >= 0"):
      losses.combine(l_d, l_e, lam)
  with pytest.raises(ValueError, match=r"lam must be a scalar .* got shape \(3,\)"):
    losses.combine(l_d, l_e, jnp.ones(3))
  with pytest.raises(ValueError, match=r"channel axis last .* got shape \(4, 4, 0\)"):
    edges.channel_mean(jnp.ones((4, 4, 0)))
  with pytest.raises(ValueError, match="lr must be a finite number"):
    AdaptConfig(lr=10**400)


def test_a_batch_of_dynamic_ids_for_one_frame_is_refused():
  """`dynamic_ids` is one frame's (N_max,) table. A (B, N_max) batch of them (a data loader's
  stack, with one frame's depth) was flattened into one table: the same car listed twice made
  N = 2, and the fast L_d, which counts a repeated id's pixels once, came out half of the frame's
  own (while the literal one counted it twice), without an error. Reference: the literal NumPy
  loop of eq. 8 on the frame's own (N_max,) ids."""
  rng = np.random.default_rng(0)
  depth = rng.uniform(1, 5, (6, 7)).astype(np.float32)
  pan = np.zeros((6, 7), np.int32)
  pan[1:4, 2:6] = 5                                                    # one car, segment 5
  image = rng.random((6, 7, 3)).astype(np.float32)
  ids = np.array([5, 0], np.int32)
  want = depth_refining_loss_loop(depth, pan, ids, 3)
  assert want > 0
  for impl in losses.IMPLS:
    got = losses.pitta_loss(image, depth, pan, ids, 3, lam=0.0, impl=impl)
    np.testing.assert_allclose(float(got.l_d), want, rtol=RTOL)
    assert int(got.n) == 1
  for batch in (np.stack([ids, ids]), np.zeros((2, 0), np.int32)):
    for impl in losses.IMPLS:
      for call in (lambda: losses.depth_refining_loss(depth, pan, batch, 3, impl=impl),
                   lambda: jax.jit(losses.pitta_loss, static_argnames="impl")(
                       image, depth, pan, batch, impl=impl)):
        with pytest.raises(ValueError, match=r"dynamic_ids must be one frame's \(N_max,\) "
                                             rf"segment ids, got shape \(2, {batch.shape[1]}\)"):
          call()
    with pytest.raises(ValueError, match="dynamic_ids must be one frame's"):
      masks.table_from_dynamic_ids(batch)
  # vmapped over a batch of frames, each frame sees its own (N_max,) row
  got = jax.vmap(lambda d, i: losses.pitta_loss(image, d, pan, i, 3, lam=0.0).l_d)(
      np.stack([depth, 2 * depth]), np.stack([ids, ids]))
  np.testing.assert_allclose(np.asarray(got), [want, 2 * want], rtol=RTOL)
