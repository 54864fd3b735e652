"""Median filter with a window that shrinks at the image border (paper eq. 7).

`D~'(x, y) = median{ D~(p, q) : p in [max(x-r, 0), min(x+r, H-1)],
                                q in [max(y-r, 0), min(y+r, W-1)] }`, r = s // 2.

No padding: at the border the window holds fewer pixels, c(x, y) = rows(x) * cols(y). The median
of an even count is the mean of the two middle values, `(a + b) / 2` in float32 (NumPy's
convention), so the result equals a literal `np.median` loop bit for bit (but for the sign of
a zero: NumPy's median of -0.0 values may be +0.0, which compares equal).

How: the s*s shifted views of the map, padded with +inf, go through a Batcher odd-even merge
sorting network made of elementwise compare-exchanges (XLA fuses it into one loop over the
pixels). The padding sorts last, so the c valid values of a window occupy the first c sorted
slots and the two middle ones sit at (c-1)//2 and c//2, with c a function of the position. Only
the comparators that feed the slots needed somewhere are kept (124 of them for s = 5, 352 for
s = 7), and a select chain picks each pixel's slots. A network is exact: it permutes the values,
so ties come out as they are. Each comparator moves whole elements (a select on b < a, not
min/max), so the gradient of a slot reaches one element of the window, as through a sort
(`torch.sort`, `torch.median`), also at ties; which of several tied elements is the network's
choice, as it is torch's. About 0.7-0.9 ms at 640x192 with s = 5 on 2 CPU cores, where
`jnp.sort` along the window axis takes about 250 ms.

From s = `SORT_FROM_WINDOW` on, the windows are stacked on an array axis instead and their two
middle values selected there (`stacked_order_statistics`: by bisection over the values' order
keys, exact): the network's compile time doubles with every step of s (at 640x192, 2 CPU cores:
s = 11 2.1 s, 13 6.6 s, 15 12.6 s, and minutes beyond), the stacked form's stays near 1 s
(s = 17-31; `stack_windows` takes 2s slices of the map), while it runs far slower (s = 11: 28 ms
as a network; s = 17: 1.4-1.6 s, against 3.8-4.7 s for `jnp.sort` of the stacked windows,
interleaved). The same values either way (both return elements of the window), and a gradient
that reaches one element per slot either way (here the one a stable sort puts there). The
stacked windows take s*s times the map's memory, so they are built and selected from a block of
rows at a time (`map_row_blocks`, `BLOCK_BYTES` per block): at 640x192, s = 31, the median
filter's working memory is 100 MB instead of 3.2 GB for the whole image's stack, and it runs
faster (s = 17: 0.97 against 1.31 s, s = 31: 3.2 against 4.5 s, best of 4, interleaved; 4 MB
blocks ran within 10-20% of 16 MB, 64 MB blocks slower).
`map_row_blocks` and `select_middles` serve callers that keep the windows stacked (the fast L_d
from `losses.STACKED_FROM_WINDOW` on).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from pitta_jax.dtypes import as_float, static_int

Array = jax.Array

WINDOW = 5  # the window s of eq. 7; not stated in the paper (see docs/method.md)

# The smallest window whose windows are stacked and selected from (`stacked_order_statistics`)
# rather than put through a sorting network (see the docstring).
SORT_FROM_WINDOW = 17

# Padding for integer maps: sorts after every real value.
INT_PAD = np.iinfo(np.int32).max

# The most bytes that one block of stacked windows (rows x W x s*s elements of one map) holds:
# the stacked forms go through the image in blocks of rows (`map_row_blocks`), so that their
# memory stays bounded whatever the image and the window (one stack of a 640x192 map takes
# 142 MB at s = 17 and 472 MB at s = 31, and the selection holds several arrays of that size).
# Per map: under `jax.vmap` (the literal L_d's instances, many streams) each mapped map holds
# its own block.
BLOCK_BYTES = 16 << 20


def _batcher_pairs(n: int) -> tuple[tuple[int, int], ...]:
  """Comparators (i, j), i < j, of Batcher's odd-even merge sort on 2**k >= n wires.

  Comparators touching a wire >= n are dropped: with +inf on those wires they never move a
  value (the larger value always goes to the higher wire), so the network still sorts n wires.
  """
  size = 1
  while size < n:
    size *= 2
  pairs = []
  p = 1
  while p < size:
    k = p
    while k >= 1:
      for j in range(k % p, size - k, 2 * k):
        for i in range(min(k, size - j - k)):
          if (i + j) // (2 * p) == (i + j + k) // (2 * p):
            lo, hi = i + j, i + j + k
            if hi < n:
              pairs.append((lo, hi))
      k //= 2
    p *= 2
  return tuple(pairs)


def _selection_network(n: int, ranks: tuple[int, ...]) -> tuple[tuple[int, int, bool, bool], ...]:
  """The sorting network on n wires pruned to the comparators that the output `ranks` need.

  Returns (i, j, need_min, need_max) per kept comparator, in order; a comparator whose output
  wire is not needed later computes only the other output.
  """
  needed = set(ranks)
  kept = []
  for i, j in reversed(_batcher_pairs(n)):
    need_min, need_max = i in needed, j in needed
    if need_min or need_max:
      kept.append((i, j, need_min, need_max))
      needed.update((i, j))
  return tuple(reversed(kept))


def window_counts(h: int, w: int, s: int) -> np.ndarray:
  """Number of pixels c(x, y) in the border-shrunk window of eq. 7.  # (h, w) int32"""
  r = s // 2
  rows = np.minimum(np.arange(h) + r, h - 1) - np.maximum(np.arange(h) - r, 0) + 1  # (h,)
  cols = np.minimum(np.arange(w) + r, w - 1) - np.maximum(np.arange(w) - r, 0) + 1  # (w,)
  return (rows[:, None] * cols[None, :]).astype(np.int32)


def check_window(s: int) -> None:
  """Refuse a window size s that is not a positive odd int (a static argument)."""
  if static_int(s, "s", "window size", "a positive odd int") < 1 or s % 2 == 0:
    raise ValueError(f"window size s must be a positive odd int, got {s!r}")


def _padded(x: Array, s: int, pad_value, below: int = 0) -> Array:
  """x padded with `pad_value` by r = s // 2 on every side, and `below` more rows at the bottom
  (a last block of `map_row_blocks`): the map both window forms slice.
  # (H + 2r + below, W + 2r)"""
  r = s // 2
  return jnp.pad(x, ((r, r + below), (r, r)), constant_values=pad_value)


def window_views(x: Array, s: int, pad_value) -> list[Array]:
  """The s*s shifted views of x, padded with `pad_value` outside the image.

  View number dy * s + dx holds x(i + dy - r, j + dx - r) at (i, j).

  Args:
    x: (H, W) map.
    s: odd window size.
    pad_value: value of the out-of-image pixels (+inf for a median, `INT_PAD` for ints).

  Returns:
    s*s arrays of shape (H, W).
  """
  check_window(s)
  padded = _padded(x, s, pad_value)
  h, w = x.shape
  return [padded[dy:dy + h, dx:dx + w] for dy in range(s) for dx in range(s)]


def stack_windows(padded: Array, s: int, h: int, w: int) -> Array:
  """The s x s windows of the h x w pixels whose windows fill `padded` (h + s - 1, w + s - 1),
  stacked on a last axis: the view dy * s + dx of `window_views` at [i, j, dy * s + dx].

  One array instead of s*s: what `select_middles` selects from, and what elementwise work over
  the window (a count, a mask) stays one broadcast expression on, whatever s. Built from s row
  slices and s column slices of the padded map (2s slices, not s*s: the program grows with s,
  not s*s).  # (h, w, s*s)
  """
  rows = jnp.stack([padded[dy:dy + h] for dy in range(s)], axis=1)  # (h, s, w + s - 1)
  cells = jnp.stack([rows[..., dx:dx + w] for dx in range(s)], axis=-1)  # (h, s, w, s)
  return jnp.moveaxis(cells, 1, 2).reshape(h, w, s * s)  # [i, j, dy * s + dx]


def block_rows(h: int, w: int, s: int, itemsize: int, block_bytes: int = BLOCK_BYTES) -> int:
  """Rows per block of `map_row_blocks`: as many as keep one block's stack of windows within
  `block_bytes` (a static positive int: ValueError naming it otherwise; at least one row, at
  most h)."""
  if static_int(block_bytes, "block_bytes", "the block bound", "a positive int") < 1:
    raise ValueError(f"the block bound block_bytes must be a positive int, got {block_bytes!r}")
  return int(max(1, min(h, block_bytes // (w * s * s * itemsize))))


def map_row_blocks(fn, maps: list[tuple[Array, object]], s: int,
                   block_bytes: int = BLOCK_BYTES):
  """fn applied to the stacked windows of blocks of rows, one block after another.

  Each map is padded with its value (+inf, `INT_PAD`) and cut into blocks of R rows
  (`block_rows`, from `block_bytes` and the widest element); fn gets the block's window stacks
  (R, W, s*s) in the order of `maps`, and the per-pixel middle slots of eq. 7's border-shrunk
  windows (`middle_ranks` at the block's rows of the whole image), and returns a tuple of
  (R, W) arrays that depend only on the pixel's own window. The blocks go through `lax.map`, so
  the program holds one block's stacks at a time, and the results are cut back to (H, W). A
  gradient flows through, as through `lax.scan`. The last block reaches below the image; its
  rows below the image are computed from the padding and what rows lie above, and dropped.

  Args:
    fn: (stacks, lo_rank, hi_rank) -> tuple of (R, W) arrays.
    maps: (x, pad_value) pairs, x (H, W) each, all of one shape.
    s: odd window size (static).
    block_bytes: the bound on one block's stack of one map (static).

  Returns:
    fn's tuple, each (H, W).
  """
  check_window(s)
  h, w = maps[0][0].shape
  r = s // 2
  rows = block_rows(h, w, s, max(x.dtype.itemsize for x, _ in maps), block_bytes)
  blocks = -(-h // rows)
  padded = [_padded(x, s, pad, blocks * rows - h)
            for x, pad in maps]  # (blocks * R + 2r, W + 2r) each

  def block(top: Array):
    stacks = [stack_windows(jax.lax.dynamic_slice_in_dim(p, top, rows + 2 * r), s, rows, w)
              for p in padded]  # (R, W, s*s) each
    return tuple(fn(stacks, *middle_ranks(h, w, s, top, rows)))

  if blocks == 1:
    return tuple(out[:h] for out in block(0))
  outs = jax.lax.map(block, jnp.arange(blocks, dtype=jnp.int32) * rows)  # (blocks, R, W) each
  return tuple(out.reshape(blocks * rows, *out.shape[2:])[:h] for out in outs)


def middle_ranks(h: int, w: int, s: int, top: Array | int = 0,
                 n_rows: int | None = None) -> tuple[Array, Array]:
  """Per pixel, the sorted slots of the window's two middle values.

  Built from iotas inside the traced function (no (H, W) constants in the program). `top` and
  `n_rows` pick rows top .. top + n_rows - 1 of the h x w image (a block of `map_row_blocks`;
  rows below the image get the last row's slots).

  Returns:
    ((c-1)//2, c//2), (n_rows, W) int32 each (n_rows = h by default), c = c(x, y) the window's
    pixel count.
  """
  r = s // 2
  i = jnp.arange(h if n_rows is None else n_rows, dtype=jnp.int32)
  i = jnp.minimum(top + i, h - 1)[:, None]  # (H, 1)
  j = jnp.arange(w, dtype=jnp.int32)[None, :]  # (1, W)
  rows = jnp.minimum(i + r, h - 1) - jnp.maximum(i - r, 0) + 1  # (H, 1)
  cols = jnp.minimum(j + r, w - 1) - jnp.maximum(j - r, 0) + 1  # (1, W)
  c = rows * cols  # (H, W)
  return (c - 1) // 2, c // 2


def middle_order_statistics(views: list[Array], s: int) -> tuple[Array, Array]:
  """Per pixel, the sorted values at slots (c-1)//2 and c//2 of its border-shrunk window.

  Args:
    views: the s*s views of `window_views`, (..., H, W) each (leading axes = several maps
      filtered in one pass), the out-of-image slots holding a value that sorts after every real
      one (+inf, `INT_PAD`).
    s: the odd window size.

  Returns:
    (lower, upper): the lower and upper middle values, (..., H, W) each (equal when c is odd).
  """
  h, w = views[0].shape[-2:]
  if s >= SORT_FROM_WINDOW:
    return stacked_order_statistics(jnp.stack(views, axis=-1), s)
  counts = window_counts(h, w, s)  # static, for the set of slots needed
  ranks = sorted(set(np.unique((counts - 1) // 2).tolist()) | set(np.unique(counts // 2).tolist()))
  wires = list(views)
  for i, j, need_min, need_max in _selection_network(len(wires), tuple(ranks)):
    a, b = wires[i], wires[j]
    # A compare-exchange that moves whole elements: jnp.minimum/maximum would split a tie's
    # gradient between the two, where a sort (torch.sort, torch.median) gives each slot one.
    swap = b < a
    if need_min:
      wires[i] = jnp.where(swap, b, a)
    if need_max:
      wires[j] = jnp.where(swap, a, b)
  lo_rank, hi_rank = middle_ranks(h, w, s)
  # A select chain, not a stack + gather: XLA would fuse a stack of the network outputs into one
  # loop that recomputes the whole network for every stacked slot.
  lower, upper = wires[ranks[-1]], wires[ranks[-1]]
  for k in ranks[:-1]:
    lower = jnp.where(lo_rank == k, wires[k], lower)
    upper = jnp.where(hi_rank == k, wires[k], upper)
  return lower, upper


def stacked_order_statistics(stack: Array, s: int) -> tuple[Array, Array]:
  """`middle_order_statistics` of windows stacked on the last axis (`stack_windows`).

  stack: (..., H, W, s*s) of a whole image, the out-of-image slots sorting last. Returns
  (lower, upper), (..., H, W) each; see `select_middles`.
  """
  return select_middles(stack, *middle_ranks(*stack.shape[-3:-1], s))


def select_middles(stack: Array, lo_rank: Array, hi_rank: Array) -> tuple[Array, Array]:
  """The elements at sorted slots lo_rank and hi_rank (H, W) of windows stacked on the last
  axis (..., H, W, n), the out-of-image slots sorting last.

  Compile time does not grow with s (a sorting network's does). A float window's two middle
  values are found by bisection (`_select_pair`: the median filter at s = 17, 640x192, 2 CPU
  cores, 2.5-3x faster than with a sort), an integer window's by jnp.sort along the window axis
  (at s = 13, 0.37 s against 0.60 for the bisection's 32 steps on a few distinct indices). Both
  return the elements a stable sort puts at the two slots: the same values and gradients.
  Returns (lower, upper), (..., H, W) each.
  """
  lo_rank, hi_rank = (jnp.broadcast_to(r, stack.shape[:-1]) for r in (lo_rank, hi_rank))
  if jnp.issubdtype(stack.dtype, jnp.floating):
    return _select_pair(stack, lo_rank, hi_rank)
  ordered = jnp.sort(stack, axis=-1)  # (..., H, W, n)
  lower, upper = (jnp.take_along_axis(ordered, rank[..., None], axis=-1)[..., 0]
                  for rank in (lo_rank, hi_rank))
  return lower, upper


def _order_keys(x: Array) -> Array:
  """Floats as integers of the same width in the same order, as `jnp.sort` orders them but NaN
  (-0.0 and +0.0 equal): the sign bit set flips the magnitude bits, so that a larger negative
  float is a smaller integer."""
  kind = jnp.int32 if x.dtype.itemsize == 4 else jnp.int64
  bits = jax.lax.bitcast_convert_type(jnp.where(x == 0, jnp.zeros_like(x), x), kind)
  return jnp.where(bits < 0, bits ^ jnp.iinfo(kind).max, bits)


def _select_pair(stack: Array, rank_a: Array, rank_b: Array) -> tuple[Array, Array]:
  """The elements at 0-based sorted slots rank_a and rank_b (..., H, W) of each float window
  (..., H, W, n), by bisection over the windows' order keys: the smallest key K whose count of
  window keys <= K exceeds the rank is that slot's key, exactly. One pass over the windows per
  bit (32 for float32), counting for both slots, instead of a sort of every window. The
  element itself is then taken from `stack` (`_element_at_slot`), so a gradient reaches it as
  through a sort."""
  keys = _order_keys(jax.lax.stop_gradient(stack))  # (..., H, W, n)
  kind = jnp.iinfo(keys.dtype)
  low = jnp.full(stack.shape[:-1], kind.min, keys.dtype)
  high = jnp.full(stack.shape[:-1], kind.max, keys.dtype)

  def narrow(low: Array, high: Array, rank: Array) -> tuple[Array, Array]:
    mid = (low >> 1) + (high >> 1) + (low & high & 1)  # floor((low + high) / 2), no overflow
    enough = jnp.sum((keys <= mid[..., None]).astype(jnp.int32), axis=-1) > rank
    return jnp.where(enough, low, mid + 1), jnp.where(enough, mid, high)

  def step(_, bounds):
    low_a, high_a, low_b, high_b = bounds
    return (*narrow(low_a, high_a, rank_a), *narrow(low_b, high_b, rank_b))
  key_a, _, key_b, _ = jax.lax.fori_loop(0, kind.bits, step, (low, high, low, high))
  return (_element_at_slot(stack, keys, key_a, rank_a),
          _element_at_slot(stack, keys, key_b, rank_b))


def _element_at_slot(stack: Array, keys: Array, key: Array, rank: Array) -> Array:
  """The element of each window that a stable sort puts at slot `rank`, whose key is `key`:
  among the window's elements of that key, the (rank - #smaller keys)-th in window order.
  Taken from `stack`, so differentiable as a sort's slot.  # (..., H, W)"""
  equal = keys == key[..., None]  # (..., H, W, n)
  nth = rank - jnp.sum((keys < key[..., None]).astype(jnp.int32), axis=-1)  # (..., H, W)
  seen = jnp.cumsum(equal.astype(jnp.int32), axis=-1)
  at = jnp.argmax(equal & (seen == (nth + 1)[..., None]), axis=-1)  # (..., H, W)
  return jnp.take_along_axis(stack, at[..., None], axis=-1)[..., 0]


def median_of_middles(lower: Array, upper: Array, s: int) -> Array:
  """The median (eq. 7) from a window's two middle values (..., H, W): NumPy's convention, the
  mean of the two in the input's float type for an even count, the value itself for an odd one."""
  return mean_of_middles(lower, upper, *middle_ranks(*lower.shape[-2:], s))


def mean_of_middles(lower: Array, upper: Array, lo_rank: Array, hi_rank: Array) -> Array:
  """`median_of_middles` with the slots given (a block of `map_row_blocks`).  # (..., R, W)"""
  return jnp.where(lo_rank != hi_rank, (lower + upper) / 2, lower)


def median_of_views(views: list[Array], s: int) -> Array:
  """Median (eq. 7) of the border-shrunk windows given as +inf-padded views (`window_views`)."""
  return median_of_middles(*middle_order_statistics(views, s), s)


def check_map(x: Array, what: str) -> None:
  """ValueError unless `x` is an (H, W) map of at least one pixel (an empty one has no window)."""
  if x.ndim != 2 or 0 in x.shape:
    raise ValueError(f"{what} expects an (H, W) map with H, W >= 1, got shape {x.shape}")


def median_filter(x: Array, s: int = WINDOW, block_bytes: int = BLOCK_BYTES) -> Array:
  """Median filter with a border-shrunk window, paper eq. 7.

  Equals a loop of `np.median(x[max(i-r,0):min(i+r,H-1)+1, max(j-r,0):min(j+r,W-1)+1])` over
  the pixels exactly (float32), including even counts at the border (mean of the two middle
  values) and windows larger than the image. Not differentiated in PITTA (pseudo labels are
  stop-gradient); differentiated, each middle value's cotangent reaches one element of its
  window (half each for an even count's two), ties included, as through torch.sort.

  Args:
    x: (H, W) float map (float32, or float64 kept: `dtypes.as_float`). NaN: unspecified.
      Subnormal values may be flushed to zero (XLA's CPU and GPU backends do), unlike NumPy.
    s: odd window size (static), r = s // 2; s = 1 is the identity.
    block_bytes: from s = `SORT_FROM_WINDOW` on, the bound on one block of stacked windows
      (`map_row_blocks`; static).

  Returns:
    (H, W) filtered map of x's float type.
  """
  check_window(s)
  x = as_float(x)
  check_map(x, "median_filter")
  if s >= SORT_FROM_WINDOW:  # the windows stacked on an array axis, a block of rows at a time
    def block(stacks: list[Array], lo_rank: Array, hi_rank: Array) -> tuple[Array]:
      return (mean_of_middles(*select_middles(stacks[0], lo_rank, hi_rank), lo_rank, hi_rank),)
    return map_row_blocks(block, [(x, jnp.inf)], s, block_bytes)[0]
  return median_of_views(window_views(x, s, jnp.inf), s)
