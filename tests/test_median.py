"""Median filter, eq. 7: against a literal NumPy loop (exact float32), hand values, properties."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pitta_jax import median as median_lib
from reference_numpy import median_filter_loop

SHAPE = (7, 9)  # the hypothesis tests' shape (one compilation per window size)


@pytest.fixture(scope="module")
def mf():
  return jax.jit(median_lib.median_filter, static_argnums=1)


def int_maps(shape=SHAPE, lo=-3, hi=3):
  """Small-integer float32 maps: many ties, and exact arithmetic in the properties."""
  return hnp.arrays(np.float32, shape, elements=st.integers(lo, hi).map(float))


@pytest.mark.parametrize("n", range(1, 11))
def test_network_sorts_all_binary_inputs(n):
  # Reference: the 0-1 principle (a comparator network sorts every input iff it sorts all 0/1
  # inputs), checked exhaustively against Python's sorted().
  pairs = median_lib._batcher_pairs(n)
  for bits in itertools.product((0, 1), repeat=n):
    v = list(bits)
    for i, j in pairs:
      if v[i] > v[j]:
        v[i], v[j] = v[j], v[i]
    assert v == sorted(v), bits


@pytest.mark.parametrize("n", [25, 49, 81, 121, 169, 225])
def test_network_sorts_random_inputs(n):
  # Reference: Python's sorted() on random inputs with ties, for the 5x5 to 15x15 windows (the
  # networks on 81 wires and more pad to 128 and 256 wires).
  rng = np.random.default_rng(n)
  pairs = median_lib._batcher_pairs(n)
  for _ in range(300):
    v = rng.integers(0, 6, n).tolist()
    want = sorted(v)
    for i, j in pairs:
      if v[i] > v[j]:
        v[i], v[j] = v[j], v[i]
    assert v == want


@pytest.mark.parametrize("n", [9, 25, 49, 81, 121, 169, 225])
def test_selection_network_gives_the_needed_slots(n):
  # Reference: Python's sorted() on random inputs with ties. The pruned network (min-only and
  # max-only comparators) must leave the sorted values on the slots it was asked for: the middle
  # slots of every window count a filter of n = s * s wires meets, at the border and inside.
  rng = np.random.default_rng(n)
  s = int(round(n ** 0.5))
  counts = median_lib.window_counts(s + 3, s + 4, s)
  ranks = tuple(sorted(set(((counts - 1) // 2).ravel().tolist())
                      | set((counts // 2).ravel().tolist())))
  network = median_lib._selection_network(n, ranks)
  for _ in range(100):
    v = rng.integers(0, 6, n).tolist()
    want = sorted(v)
    for i, j, need_min, need_max in network:
      lo, hi = min(v[i], v[j]), max(v[i], v[j])
      v[i] = lo if need_min else v[i]
      v[j] = hi if need_max else v[j]
    assert [v[k] for k in ranks] == [want[k] for k in ranks]


def test_window_counts_match_loop():
  # Reference: counting the pixels of eq. 7's window with loops.
  for h, w, s in [(5, 8, 3), (4, 3, 5), (2, 2, 7), (9, 6, 5)]:
    r = s // 2
    rows = [min(i + r, h - 1) - max(i - r, 0) + 1 for i in range(h)]
    cols = [min(j + r, w - 1) - max(j - r, 0) + 1 for j in range(w)]
    want = np.array([[rows[i] * cols[j] for j in range(w)] for i in range(h)])
    np.testing.assert_array_equal(median_lib.window_counts(h, w, s), want)
  lo, hi = jax.jit(median_lib.middle_ranks, static_argnums=(0, 1, 2))(h, w, s)
  np.testing.assert_array_equal(lo, (want - 1) // 2)
  np.testing.assert_array_equal(hi, want // 2)


@pytest.mark.parametrize("s", [1, 3, 5, 7, median_lib.SORT_FROM_WINDOW])  # network; stacked
@pytest.mark.parametrize("shape", [(12, 20), (3, 4), (2, 9), (1, 1), (19, 23)])
def test_equals_numpy_loop_exactly(mf, s, shape):
  # Reference: literal NumPy loop of eq. 7 (np.median per window); float32 equality, on real
  # values and on small integers (ties, even counts at the border, images smaller than s).
  rng = np.random.default_rng(s * 100 + shape[0])
  for x in (rng.standard_normal(shape).astype(np.float32),
            rng.integers(-2, 3, shape).astype(np.float32) * np.float32(0.1),
            (rng.random(shape) * 80).astype(np.float32)):
    got = np.asarray(mf(x, s))
    want = median_filter_loop(x, s)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("s", [9, 11])
def test_larger_networks_equal_numpy_loop(mf, s):
  # Reference: the NumPy loop, as above, for the selection networks between the 7x7 and the
  # stacked form (81 and 121 wires); 19x23 holds interior windows and windows clipped on both
  # axes. (13 and 15 take 6-11 s to compile; their networks are checked in pure Python above.)
  rng = np.random.default_rng(s)
  for x in (rng.standard_normal((19, 23)).astype(np.float32),
            rng.integers(-2, 3, (19, 23)).astype(np.float32) * np.float32(0.1)):
    np.testing.assert_array_equal(np.asarray(mf(x, s)), median_filter_loop(x, s))


# One row a block, and 6 rows a block (19 rows: the fourth block holds one row of the image).
@pytest.mark.parametrize("rows", [1, 6])
def test_stacked_blocks_of_rows_equal_numpy_loop(rows):
  # Reference: the NumPy loop of eq. 7. The stacked form goes through the image a block of rows
  # at a time (bounded memory); each pixel must still see its whole-image window and slots, on
  # blocks that cut through windows and a last block that reaches below the image.
  s, shape = median_lib.SORT_FROM_WINDOW, (19, 23)
  block_bytes = rows * shape[1] * s * s * 4
  assert median_lib.block_rows(*shape, s, 4, block_bytes) == rows
  f = jax.jit(median_lib.median_filter, static_argnums=(1, 2))
  rng = np.random.default_rng(rows)
  for x in (rng.standard_normal(shape).astype(np.float32),
            rng.integers(-2, 3, shape).astype(np.float32) * np.float32(0.1)):
    np.testing.assert_array_equal(np.asarray(f(x, s, block_bytes)), median_filter_loop(x, s))


@pytest.mark.parametrize("rows", [1, 19])  # 19 blocks of one row; the whole map in one
def test_stacked_median_gradient_reaches_the_middle_values(rows):
  # Reference: per pixel, by a loop, the window's middle element(s) under np.argsort: distinct
  # values, so the cotangent w of an odd window goes to its median element, and w / 2 to each of
  # the two middle elements of an even one (the mean of eq. 7's even count).
  s, (h, w) = median_lib.SORT_FROM_WINDOW, (19, 23)
  r = s // 2
  rng = np.random.default_rng(7)
  x = rng.permutation(h * w).reshape(h, w).astype(np.float32) / 7
  cot = rng.standard_normal((h, w)).astype(np.float32)
  block_bytes = rows * w * s * s * 4
  f = lambda v: jnp.sum(median_lib.median_filter(v, s, block_bytes) * cot)  # noqa: E731
  got = np.asarray(jax.jit(jax.grad(f))(jnp.asarray(x)))
  want = np.zeros((h, w), np.float64)
  for i in range(h):
    for j in range(w):
      rows_i = np.arange(max(i - r, 0), min(i + r, h - 1) + 1)
      cols_j = np.arange(max(j - r, 0), min(j + r, w - 1) + 1)
      cells = [(a, b) for a in rows_i for b in cols_j]
      order = np.argsort([x[a, b] for a, b in cells])
      c = len(cells)
      middles = {order[(c - 1) // 2], order[c // 2]}
      for k in middles:
        want[cells[k]] += cot[i, j] / len(middles)
  np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("s", [3, 5, median_lib.SORT_FROM_WINDOW])  # network; stacked
def test_gradient_at_ties_reaches_one_element_per_slot_as_torch_sort(s):
  # Reference: PyTorch autograd of eq. 7 as a PyTorch user writes it, per pixel the border-shrunk
  # window's torch.sort and the mean of its two middle values: each middle slot's cotangent goes
  # to one element (the one the sort's index names). On maps of three values (ties everywhere)
  # each Jacobian row must then have torch's nonzero entries (one 1, or two halves) and, per
  # distinct value of the window, the same total; which of several tied elements receives it is
  # each implementation's choice. min/max comparators would split a tie's share between them.
  h, w = 6, 7
  r = s // 2
  x = np.random.default_rng(s).integers(0, 3, (h, w)).astype(np.float32)
  got = np.asarray(jax.jit(jax.jacrev(lambda v: median_lib.median_filter(v, s)))(x))
  got = got.reshape(h * w, h * w)
  xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
  flat = x.reshape(-1)
  for i in range(h):
    for j in range(w):
      window = xt[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].reshape(-1)
      ordered = torch.sort(window).values
      c = window.numel()
      (want,) = torch.autograd.grad((ordered[(c - 1) // 2] + ordered[c // 2]) / 2, xt)
      want = want.numpy().reshape(-1)
      row = got[i * w + j]
      np.testing.assert_array_equal(np.sort(row[row != 0]), np.sort(want[want != 0]))
      for value in np.unique(flat):
        assert row[flat == value].sum() == want[flat == value].sum(), (i, j, value)


def test_stacked_working_memory_is_bounded_by_blocks():
  # Hand bound: at 192x640 and s = 31 one stack of the windows is 192 * 640 * 961 * 4 bytes =
  # 472 MB, and the selection holds several arrays of that size; in blocks of at most
  # BLOCK_BYTES the compiled program's temporaries must stay within a few blocks.
  s, shape = 31, (192, 640)
  compiled = jax.jit(median_lib.median_filter, static_argnums=1).lower(
      jnp.zeros(shape, jnp.float32), s).compile()
  stats = compiled.memory_analysis()
  assert stats.temp_size_in_bytes < 8 * median_lib.BLOCK_BYTES < shape[0] * shape[1] * s * s * 4


def test_hand_computed_even_counts(mf):
  # Hand values: 2x2 map with s = 3, every window is the whole map {1, 2, 3, 10}: median =
  # (2 + 3) / 2 = 2.5 (mean of the two middle values, not 2 or 3, and not the mean 4).
  x = np.array([[1, 2], [3, 10]], np.float32)
  np.testing.assert_array_equal(np.asarray(mf(x, 3)), np.full((2, 2), 2.5, np.float32))
  # 1x4 row, s = 3: windows {1,5}, {1,5,2}, {5,2,8}, {2,8} -> 3, 2, 5, 5.
  x = np.array([[1, 5, 2, 8]], np.float32)
  np.testing.assert_array_equal(np.asarray(mf(x, 3)), [[3, 2, 5, 5]])


def test_identity_for_window_one(mf):
  # Hand value: a 1x1 window is the pixel itself.
  x = np.random.default_rng(0).standard_normal((12, 20)).astype(np.float32)
  np.testing.assert_array_equal(np.asarray(mf(x, 1)), x)


@pytest.mark.parametrize("s", [0, 2, 4, -1, 3.0])
def test_rejects_bad_window(s):
  with pytest.raises(ValueError, match="odd"):
    median_lib.median_filter(jnp.zeros((4, 4)), s)


def test_a_traced_window_is_named_as_such():
  """s passed to a jitted filter as an ordinary argument: the message says to make it static
  (it printed the tracer as the bad value)."""
  with pytest.raises(ValueError, match=r"not a traced value: pass it as a static argument"):
    jax.jit(median_lib.median_filter)(jnp.zeros((4, 4)), 3)


def test_a_bad_or_traced_block_bound_is_named():
  """block_bytes bounds the stacked windows of s >= SORT_FROM_WINDOW and sets the block shape,
  so it is static: traced, it failed in a TracerBoolConversionError inside block_rows."""
  s = median_lib.SORT_FROM_WINDOW
  with pytest.raises(ValueError, match=r"block_bytes must be a Python int, not a traced value"):
    jax.jit(median_lib.median_filter, static_argnums=1)(jnp.zeros((4, 4)), s, 1 << 20)
  for bad in (0, -5, 2.5, True):
    with pytest.raises(ValueError, match="block_bytes must be a positive int"):
      median_lib.median_filter(jnp.zeros((4, 4)), s, bad)


def test_rejects_non_2d():
  with pytest.raises(ValueError, match="H, W"):
    median_lib.median_filter(jnp.zeros((4, 4, 3)), 3)


@settings(max_examples=25, deadline=None)
@given(x=int_maps(), s=st.sampled_from([3, 5]))
def test_matches_loop_property(mf, x, s):
  # Reference: literal NumPy loop, exact, on tie-heavy integer maps.
  np.testing.assert_array_equal(np.asarray(mf(x, s)), median_filter_loop(x, s))


@settings(max_examples=20, deadline=None)
@given(x=int_maps(), s=st.sampled_from([3, 5]))
def test_commutes_with_increasing_maps(mf, x, s):
  # Property: order statistics commute with strictly increasing maps f. Where the count is odd
  # the median is an order statistic, so med(f(x)) = f(med(x)) for any such f (here x**3 + x,
  # exact on small ints); everywhere, with even counts too, for the affine f(x) = 4x - 3.
  counts = median_lib.window_counts(*x.shape, s)
  odd = counts % 2 == 1
  f = lambda v: v ** 3 + v
  got = np.asarray(mf(f(x), s))
  want = f(np.asarray(mf(x, s)))
  np.testing.assert_array_equal(got[odd], want[odd])
  np.testing.assert_array_equal(np.asarray(mf(4 * x - 3, s)), 4 * np.asarray(mf(x, s)) - 3)


@settings(max_examples=20, deadline=None)
@given(x=hnp.arrays(np.float32, SHAPE,
                    elements=st.floats(-100, 100, width=32, allow_subnormal=False)),
       s=st.sampled_from([3, 5]))
def test_commutes_with_flips_and_transpose(mf, x, s):
  # Property: the window is symmetric, so flipping/transposing the map flips/transposes the
  # result exactly.
  y = np.asarray(mf(x, s))
  np.testing.assert_array_equal(np.asarray(mf(x[::-1], s)), y[::-1])
  np.testing.assert_array_equal(np.asarray(mf(x[:, ::-1], s)), y[:, ::-1])
  np.testing.assert_array_equal(np.asarray(mf(np.ascontiguousarray(x.T), s)), y.T)


@settings(max_examples=10, deadline=None)
@given(c=st.floats(-1e3, 1e3, width=32, allow_subnormal=False), s=st.sampled_from([3, 5]))
def test_constant_map_is_fixed(mf, c, s):
  # Property: the median of equal values is that value. (Subnormals excluded: XLA on CPU
  # flushes them to zero.)
  x = np.full(SHAPE, c, np.float32)
  np.testing.assert_array_equal(np.asarray(mf(x, s)), x)


@pytest.fixture(scope="module")
def stacked():
  return jax.jit(median_lib.stacked_order_statistics, static_argnums=1)


def _count_3x3(i: int, j: int, h: int, w: int) -> int:
  """Pixels of the border-shrunk 3x3 window at (i, j) of an h x w map, counted by hand."""
  return (min(i + 1, h - 1) - max(i - 1, 0) + 1) * (min(j + 1, w - 1) - max(j - 1, 0) + 1)


@settings(max_examples=25, deadline=None)
@given(x=hnp.arrays(np.float32, (4, 5, 9), elements=st.one_of(
    st.sampled_from([0.0, -0.0, np.inf, -np.inf, 1.0, -1.0]),
    st.floats(width=32, allow_nan=False))))
def test_stacked_order_statistics_pick_the_sorted_slots(stacked, x):
  # Reference: NumPy's stable argsort along the window axis and the border-shrunk window's
  # middle slots (c - 1) // 2 and c // 2 counted by hand; any float32 but NaN (ties, signed
  # zeros, infinities, subnormals, both signs), which the bisection over order keys must place
  # as jnp.sort does. XLA:CPU compares subnormals as zeros (its jnp.sort leaves them tied with
  # 0.0 and -0.0), so the reference orders them as zeros too; the element expected at a slot is
  # the one a stable sort puts there, compared with == (-0.0 == 0.0, a subnormal != 0.0).
  s = 3
  as_xla_compares = np.where(np.abs(x) < np.finfo(np.float32).tiny, np.float32(0), x)
  order = np.argsort(as_xla_compares, axis=-1, kind="stable")
  ordered = np.take_along_axis(x, order, axis=-1)
  lower, upper = (np.asarray(a) for a in stacked(jnp.asarray(x), s))
  for i in range(4):
    for j in range(5):
      c = _count_3x3(i, j, 4, 5)
      assert lower[i, j] == ordered[i, j, (c - 1) // 2] and upper[i, j] == ordered[i, j, c // 2]


@pytest.mark.parametrize("s", [1, 3, 7])
def test_stacked_windows_hold_each_view_in_order(s):
  # Reference: a NumPy loop over the pixels and offsets of the padded map (slot dy * s + dx holds
  # x(i + dy - r, j + dx - r), the pad value outside), on an integer map (INT_PAD outside); the
  # map padded and stacked as a block of `map_row_blocks` is.
  x = np.arange(5 * 6, dtype=np.int32).reshape(5, 6) * 7 % 11
  r = s // 2
  padded = np.pad(x, r, constant_values=median_lib.INT_PAD)
  want = np.zeros((5, 6, s * s), np.int32)
  for i in range(5):
    for j in range(6):
      for dy in range(s):
        for dx in range(s):
          want[i, j, dy * s + dx] = padded[i + dy, j + dx]
  padded_jax = median_lib._padded(jnp.asarray(x), s, median_lib.INT_PAD)
  np.testing.assert_array_equal(np.asarray(median_lib.stack_windows(padded_jax, s, 5, 6)), want)


def test_stacked_order_statistics_gradient_is_a_stable_sorts():
  # Reference: NumPy's stable argsort per window; the gradient of sum(w_lo * lower + w_hi *
  # upper) reaches the element a stable sort puts at each middle slot. Half-integer values:
  # ties everywhere, signed zeros among them.
  rng = np.random.default_rng(4)
  x = (rng.integers(-3, 4, (4, 5, 9)) * 0.5).astype(np.float32)
  x[x == 0] *= rng.choice([-1.0, 1.0], size=int((x == 0).sum())).astype(np.float32)
  w_lo, w_hi = rng.standard_normal((2, 4, 5)).astype(np.float32)
  f = lambda v: sum(jnp.sum(a * b) for a, b in  # noqa: E731
                    zip(median_lib.stacked_order_statistics(v, 3), (w_lo, w_hi)))
  got = np.asarray(jax.grad(f)(jnp.asarray(x)))
  want = np.zeros_like(x)
  for i in range(4):
    for j in range(5):
      c = _count_3x3(i, j, 4, 5)
      order = np.argsort(x[i, j], kind="stable")
      want[i, j, order[(c - 1) // 2]] += w_lo[i, j]
      want[i, j, order[c // 2]] += w_hi[i, j]
  np.testing.assert_array_equal(got, want)
