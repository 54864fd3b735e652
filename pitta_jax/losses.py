"""PITTA's losses: depth-refining (eqs. 7-8), edge-guided (eq. 9) and their sum (eq. 10).

Single frame, no batch axis, plain arrays in, jittable (window size, mode and implementation are
static). Public entry points:

  median_filter(x, s)                                    eq. 7     (from `pitta_jax.median`)
  edge_map(x, weight)                                    eqs. 5-6  (from `pitta_jax.edges`)
  depth_refining_loss(depth, panoptic, dynamic_ids, s, mode)          eq. 8
  edge_guided_loss(image, depth, u, v)                                eq. 9
  pitta_loss(image, depth, panoptic, dynamic_ids, s, lam, mode)       eq. 10

`dynamic_ids` are the panoptic segment ids of the frame's dynamic instances, an int array padded
with 0 or -1 (entries <= 0 are unused). N = the number of used entries (an id with no pixel in
the map still counts, exactly as an empty mask would in eq. 8).

The engine, which already holds the per-pixel instance index map, calls
`depth_refining_loss_from_index`.

Depth-refining loss, two implementations with the same value and the same gradient:

- "literal": eq. 8 as written. For each of the N_max table rows, D~_j = D * M_j, its median
  filter D~'_j (stop-gradient), and sum |D~_j - D~'_j| over all pixels; invalid rows add nothing;
  divided by N. Cost grows with N_max.
- "fast" (default): the instances are disjoint, so per pixel only a fixed number of terms of
  sum_j |D~_j - D~'_j| can be nonzero. In a window with c pixels, m of instance k, D~_k holds
  c - m zeros; when the zeros number at least c//2 + 1 both middle order statistics are zeros
  (whatever the signs of the m others: at most m <= (c-1)//2 of them sort before the zeros), so
  D~'_k = 0. A nonzero D~'_k therefore needs m >= ceil(c/2); at most two instances reach that, and
  each then fills a run of >= ceil(c/2) sorted slots of the window's index multiset, which covers
  slot (c-1)//2 or c//2. So at a pixel of instance k0 (0 = none) the terms are:
    j = k0:               |D~_k0 - D~'_k0|                 (carries the gradient)
    j = e (the majority): |0 - D~'_e|                      (constant in D, part of the value)
  with e the instance != k0 found at slot (c-1)//2 or c//2 of the window's sorted indices whose
  count reaches ceil(c/2) (two such instances fill the whole window, so one of them is k0).
  Work, whatever N is: one sorting-network pass over the window's instance indices (candidates
  and their counts), then one pass over each of the two masked maps D~_k0 and D~_e. From
  s = `STACKED_FROM_WINDOW` on, the same with the windows stacked on an array axis: seconds to
  compile instead of minutes, and slower to run.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from pitta_jax import masks as masks_lib
from pitta_jax.edges import edge_map, image_edge_map
from pitta_jax.dtypes import as_float
from pitta_jax.nonsmooth import absolute
from pitta_jax.median import (BLOCK_BYTES, INT_PAD, WINDOW, check_map, check_window,
                              map_row_blocks, mean_of_middles, median_filter, median_of_views,
                              middle_order_statistics, middle_ranks, select_middles, window_views)

Array = jax.Array

# The smallest window s for which the fast L_d keeps its windows stacked on an array axis and
# selects their middle values there (`median.stacked_order_statistics`) instead of unrolling
# them into s*s-term expressions and sorting networks. Unrolled, its value and gradient at
# 640x192 compile in 5.5 s at s = 9 and 8.7 s at s = 11, but s = 13 did not compile in 400 s
# (64x96; 11 GB at s = 17); stacked they compile in 1.1-1.5 s for s = 13-17 and run slower
# (640x192: 1.3-1.6 s at s = 13 and 2.4-2.9 s at s = 17 per frame, against 0.24 s unrolled at
# s = 11). 2 CPU cores.
STACKED_FROM_WINDOW = 13

__all__ = [
    "PittaLoss", "median_filter", "edge_map", "image_edge_map", "depth_refining_loss",
    "depth_refining_loss_from_index", "depth_refining_loss_literal", "depth_refining_loss_fast",
    "edge_guided_loss", "pitta_loss", "pitta_loss_from_index", "combine",
]

IMPLS = ("fast", "literal")
LAMBDA = 0.2   # lambda of eq. 10, the paper's best (Table 4)


class PittaLoss(NamedTuple):
  """Eq. 10 and its parts (scalars)."""
  total: Array  # L = L_d + lambda * L_e
  l_d: Array  # depth-refining loss, eq. 8
  l_e: Array  # edge-guided loss, eq. 9
  n: Array  # number of dynamic instances N (int32)


def _instance_count(n: Array) -> Array:
  """The number of instances N as an int32 scalar; ValueError for any other shape."""
  n = jnp.asarray(n, jnp.int32)
  if n.ndim != 0:
    raise ValueError(f"n (the number of instances N) must be a scalar, got shape {n.shape}")
  return n


def _mean_over_instances(total: Array, n: Array) -> Array:
  """total / N, and 0 when N = 0 (no NaN in the value or the gradient)."""
  n = _instance_count(n)
  safe_n = jnp.maximum(n, 1).astype(total.dtype)
  return jnp.where(n > 0, total / safe_n, jnp.zeros((), total.dtype))


def depth_refining_loss_literal(depth: Array, masks: Array, inst_valid: Array, s: int = WINDOW) -> Array:
  """Depth-refining loss, eq. 8 term by term (the reference implementation).

  `L_d = 1/N sum_j sum_{x,y} |D~_j(x, y) - sg(D~'_j(x, y))|`, D~_j = D * M_j (eq. 4),
  D~'_j = median_filter(D~_j, s) (eq. 7), sg = stop-gradient (pseudo labels are constants).

  Args:
    depth: (H, W) float depth D.
    masks: (N_max, H, W) float32 masks M_j (eq. 3, g_j included), see `masks.instance_masks`.
    inst_valid: (N_max,) bool; invalid rows contribute nothing, N = inst_valid.sum().
    s: odd median window (static).

  Returns:
    scalar float32 L_d (0 when N = 0).
  """
  depth = as_float(depth)
  inst_valid = jnp.asarray(inst_valid, bool)
  masks = jnp.asarray(masks)
  if depth.ndim != 2 or masks.ndim != 3 or masks.shape[1:] != depth.shape or \
      inst_valid.shape != masks.shape[:1]:
    raise ValueError(f"depth (H, W), masks (N_max, H, W) and inst_valid (N_max,) must agree, got "
                     f"{depth.shape}, {masks.shape} and {inst_valid.shape}")

  def one(m):  # m: (H, W)
    masked = depth * m  # D~_j, eq. 4
    pseudo = median_filter(jax.lax.stop_gradient(masked), s)  # D~'_j, eq. 7
    return jnp.sum(absolute(masked - pseudo))

  per_instance = jax.vmap(one)(jnp.asarray(masks, depth.dtype))  # (N_max,)
  total = jnp.sum(jnp.where(inst_valid, per_instance, 0.0))
  return _mean_over_instances(total, jnp.sum(inst_valid))


def _window_of_instance(index: Array, value: Array, key: Array) -> Array:
  """The window of D~_key: the values of instance `key`, 0 at the other pixels, +inf outside
  the image (`index` holds INT_PAD there). Elementwise: views or a stack, key broadcast."""
  return jnp.where(index == key, value, jnp.where(index == INT_PAD, jnp.inf, 0.0))


def _majority_and_pseudo_labels(index_map: Array, cand_lo: Array, cand_hi: Array, count, pseudo,
                                lo_rank: Array) -> tuple[Array, Array, Array]:
  """Per pixel of the fast L_d: the majority instance e != k0 of its window (0 = none) and the
  pseudo labels D~'_k0 and D~'_e (see the module docstring).

  Args:
    index_map: (R, W) the pixels' own instance k0.
    cand_lo, cand_hi: (R, W) the window's sorted instance indices at slots (c-1)//2 and c//2.
    count: key (R, W) -> (R, W) how many of the window's pixels hold that instance.
    pseudo: key (R, W) -> (R, W) the median of the window of D~_key (eq. 7).
    lo_rank: (R, W) the slot (c-1)//2.

  Returns:
    (extra, pseudo_own, pseudo_extra), (R, W) each.
  """
  need = lo_rank + 1  # ceil(c / 2) = (c - 1) // 2 + 1
  ok_lo = (cand_lo > 0) & (cand_lo != index_map) & (count(cand_lo) >= need)
  ok_hi = (cand_hi > 0) & (cand_hi != index_map) & (count(cand_hi) >= need)
  extra = jnp.where(ok_lo, cand_lo, jnp.where(ok_hi, cand_hi, 0))  # (R, W), 0 = none
  # One pass per map (D~_k0, then D~_extra): a single pass over the two stacked as (2, R, W)
  # makes XLA:CPU emit a concatenate fusion that takes twice as long as the whole loss.
  return extra, pseudo(index_map), pseudo(extra)


def depth_refining_loss_fast(depth: Array, index_map: Array, n: Array, s: int,
                             mode: str = "binary", inst_ids: Array | None = None,
                             block_bytes: int = BLOCK_BYTES) -> Array:
  """Depth-refining loss, eq. 8, at a cost independent of N (see the module docstring).

  Same value (up to float summation order) and the same gradient w.r.t. depth as
  `depth_refining_loss_literal`, including the constant terms |0 - D~'_j| just outside each
  instance, for a finite depth map. With a non-finite depth pixel anywhere and N >= 1 the value
  is NaN (eq. 8 taken literally gives NaN or inf: the pixel's D * 0 is NaN in every other
  instance's masked map), so a logged L_d never looks finite for a rejected step; the gradient
  is then unspecified.

  Args:
    depth: (H, W) float depth D.
    index_map: (H, W) int32 instance index, 0 = none, j = instance j (`masks.instance_index_map`);
      an entry above n counts as none.
    n: scalar int, the number of instances N (table rows, with or without pixels).
    s: odd median window (static).
    mode: "binary" (g_j = 1), "segment_id" (g_j = the segment id, `inst_ids` required) or
      "instance_id" (g_j = j), static.
    inst_ids: (N_max,) the instance table's segment ids (row j - 1 = instance j).
    block_bytes: from s = `STACKED_FROM_WINDOW` on, the bound on one block of stacked windows
      (`median.map_row_blocks`; static).

  Returns:
    scalar float32 L_d (0 when N = 0).
  """
  depth = as_float(depth)
  index_map = masks_lib.index_array(index_map)
  if depth.ndim != 2 or depth.shape != index_map.shape:
    raise ValueError(f"depth {depth.shape} and index_map {index_map.shape} must be the same (H, W)")
  check_map(depth, "depth_refining_loss")
  # Eq. 8 sums over j = 1..N: a pixel of a row above n is no instance's, as in the literal loss.
  index_map = jnp.where(index_map <= _instance_count(n), index_map, 0)  # (H, W)
  # D~_k0 at each pixel's own k0; a select, not a product with 0, outside the instances, so
  # that a non-finite depth there (inf * 0 = NaN) does not reach its neighbours' pseudo labels
  gain = masks_lib.pixel_gain(index_map, mode, inst_ids)  # (H, W)
  own_masked = jnp.where(index_map > 0, depth * gain, 0.0)  # (H, W)

  # Majority candidates: the window's sorted instance indices at slots (c-1)//2 and c//2, and
  # pseudo labels D~'_k at each pixel: the median of the window of D~_k (stop-gradient).
  masked_values = jax.lax.stop_gradient(own_masked)
  check_window(s)
  if s >= STACKED_FROM_WINDOW:  # the windows stacked on an array axis, a block of rows at a time
    def block(stacks: list[Array], lo_rank: Array, hi_rank: Array) -> tuple[Array, Array, Array]:
      idx_stack, val_stack = stacks  # (R, W, s*s) each, INT_PAD / inf outside the image

      def count(key: Array) -> Array:
        return jnp.sum((idx_stack == key[..., None]).astype(jnp.int32), axis=-1)  # (R, W)

      def pseudo(key: Array) -> Array:
        window = _window_of_instance(idx_stack, val_stack, key[..., None])  # (R, W, s*s)
        return mean_of_middles(*select_middles(window, lo_rank, hi_rank), lo_rank, hi_rank)
      own_index = idx_stack[..., (s * s) // 2]  # (R, W): the window's centre, the pixel itself
      return _majority_and_pseudo_labels(own_index, *select_middles(idx_stack, lo_rank, hi_rank),
                                         count, pseudo, lo_rank)
    extra, pseudo_own, pseudo_extra = map_row_blocks(
        block, [(index_map, INT_PAD), (masked_values, jnp.inf)], s, block_bytes)
  else:
    idx_views = window_views(index_map, s, INT_PAD)  # s*s x (H, W), INT_PAD outside the image
    val_views = window_views(masked_values, s, jnp.inf)  # s*s x (H, W)

    def count(key: Array) -> Array:
      return sum((v == key).astype(jnp.int32) for v in idx_views)  # (H, W)

    def pseudo(key: Array) -> Array:
      return median_of_views([_window_of_instance(iv, vv, key)
                              for iv, vv in zip(idx_views, val_views)], s)
    extra, pseudo_own, pseudo_extra = _majority_and_pseudo_labels(
        index_map, *middle_order_statistics(idx_views, s), count, pseudo,
        middle_ranks(*index_map.shape, s)[0])

  own_term = jnp.where(index_map > 0, absolute(own_masked - pseudo_own), 0.0)
  extra_term = jnp.where(extra > 0, absolute(pseudo_extra), 0.0)  # |0 - D~'_e|
  l_d = _mean_over_instances(jnp.sum(own_term + extra_term), n)
  return jnp.where(jnp.all(jnp.isfinite(depth)) | (jnp.asarray(n) <= 0), l_d, jnp.nan)


def depth_refining_loss_from_index(depth: Array, index_map: Array, n: Array, *, s: int = WINDOW,
                                   mode: str = "binary", impl: str = "fast",
                                   n_max: int | None = None,
                                   inst_ids: Array | None = None) -> Array:
  """Depth-refining loss, eq. 8, from an instance index map (what the engine holds).

  Args:
    depth: (H, W) float depth.
    index_map: (H, W) int32, 0 or j in 1..n (what `masks.instance_index_map` makes; an entry
      above n is no instance, as a row j > n of the table is invalid).
    n: scalar int N.
    s: odd median window (static).
    mode: "binary", "segment_id" or "instance_id" (static).
    impl: "fast" (default, cost independent of N) or "literal" (eq. 8 term by term).
    n_max: static table size, required by "literal" (rows j > n are invalid); where given, N
      is at most n_max (a larger n counts as n_max, in both implementations).
    inst_ids: (N_max,) the table's segment ids, required by mode "segment_id".

  Returns:
    scalar float32 L_d.
  """
  masks_lib.check_mode(mode)
  if n_max is not None:  # a table of n_max rows holds at most n_max instances
    n_max = masks_lib.table_rows(n_max)
    n = jnp.minimum(_instance_count(n), n_max)
  if impl == "fast":
    return depth_refining_loss_fast(depth, index_map, n, s, mode, inst_ids)
  if impl == "literal":
    if n_max is None:
      raise ValueError("impl='literal' needs the static table size n_max")
    masks = masks_lib.masks_from_index(index_map, n_max, mode, inst_ids)  # (N_max, H, W)
    valid = jnp.arange(1, n_max + 1) <= _instance_count(n)  # (N_max,), rows 1..N of eq. 8
    return depth_refining_loss_literal(depth, masks, valid, s)
  raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")


def depth_refining_loss(depth: Array, panoptic: Array, dynamic_ids: Array, s: int = WINDOW,
                        mode: str = "binary", impl: str = "fast") -> Array:
  """Depth-refining loss, eq. 8, from a panoptic id map.

  Args:
    depth: (H, W) float depth D.
    panoptic: (H, W) int segment id map (0 = void).
    dynamic_ids: (N_max,) int segment ids of the dynamic instances, padded with 0 or -1
      (entries <= 0 unused, anywhere); instance j is the j-th used entry (g_j = j). The used
      ids must be distinct, as a panoptic map's segment ids are (`fast` counts a repeated
      id's pixels once, `literal` once per entry); a concrete table that repeats one is refused.
    s: odd median window (static), default `WINDOW`.
    mode: "binary" (g_j = 1, default), "segment_id" (g_j = the segment id i, eq. 3 as
      written) or "instance_id" (g_j = j); static.
    impl: "fast" (default) or "literal"; static.

  Returns:
    scalar float32 L_d (0 when no entry is used).
  """
  masks_lib.check_mode(mode)
  if impl in IMPLS and jnp.size(dynamic_ids) == 0:  # no instance table: no term (eq. 8)
    depth = as_float(depth)  # the inputs checked as with a table (not hidden by its absence)
    panoptic = masks_lib.segment_id_array(panoptic, "panoptic")
    masks_lib.table_from_dynamic_ids(dynamic_ids)  # its type and rank
    if depth.ndim != 2 or panoptic.shape != depth.shape:
      raise ValueError(f"depth {depth.shape} and panoptic {panoptic.shape} must be the same "
                       f"(H, W)")
    return jnp.zeros((), depth.dtype)
  inst_ids, inst_valid = masks_lib.table_from_dynamic_ids(dynamic_ids)
  if impl == "literal":
    masks = masks_lib.instance_masks(panoptic, inst_ids, inst_valid, mode)  # (N_max, H, W)
    return depth_refining_loss_literal(depth, masks, inst_valid, s)
  if impl == "fast":
    index_map = masks_lib.instance_index_map(panoptic, inst_ids, inst_valid)  # (H, W)
    return depth_refining_loss_fast(depth, index_map, jnp.sum(inst_valid), s, mode, inst_ids)
  raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")


def edge_guided_loss(image: Array, depth: Array, u: Array | float | None = None,
                     v: Array | float | None = None) -> Array:
  """Edge-guided loss, eq. 9: `L_e = sum_{x,y} |dI(x, y) - dD(x, y)|`.

  Args:
    image: (H, W, C) float image (the edge map uses its channel mean, eq. 5).
    depth: (H, W) float depth D (eq. 6).
    u: image weights U: None (= 1), scalar or (H, W).
    v: depth weights V: None (= 1), scalar or (H, W).

  Returns:
    scalar float32 L_e >= 0.
  """
  d_image = image_edge_map(image, u)  # (H, W)
  d_depth = edge_map(depth, v)  # (H, W)
  if d_image.shape != d_depth.shape:
    raise ValueError(f"image {d_image.shape} and depth {d_depth.shape} sizes differ")
  return jnp.sum(absolute(d_image - d_depth))


def pitta_loss(image: Array, depth: Array, panoptic: Array, dynamic_ids: Array, s: int = WINDOW,
               lam: float | Array = LAMBDA, mode: str = "binary", impl: str = "fast",
               u: Array | float | None = None, v: Array | float | None = None) -> PittaLoss:
  """PITTA's total loss, eq. 10: `L = L_d + lambda * L_e`.

  Args:
    image: (H, W, 3) float image in [0, 1].
    depth: (H, W) float predicted depth.
    panoptic: (H, W) int segment id map.
    dynamic_ids: (N_max,) int dynamic segment ids padded with 0 or -1 (see
      `depth_refining_loss`).
    s: odd median window (static), default `WINDOW`.
    lam: lambda >= 0, default `LAMBDA` (the paper's best, Table 4); a float or a traced scalar.
      inf means "L_e only" (Table 4's last column): total = L_e.
    mode: "binary", "segment_id" or "instance_id" (static).
    impl: "fast" or "literal" for L_d (static).
    u, v: edge weights U, V (None = 1).

  Returns:
    PittaLoss(total, l_d, l_e, n).
  """
  l_d = depth_refining_loss(depth, panoptic, dynamic_ids, s, mode, impl)
  l_e = edge_guided_loss(image, depth, u, v)
  n = jnp.sum(masks_lib.table_from_dynamic_ids(dynamic_ids)[1]).astype(jnp.int32)  # N
  return PittaLoss(total=combine(l_d, l_e, lam), l_d=l_d, l_e=l_e, n=n)


def _check_lam(lam: float) -> None:
  """ValueError unless eq. 10's concrete lambda is >= 0 (inf: L_e alone)."""
  if math.isnan(lam) or lam < 0:
    raise ValueError(f"lam must be >= 0 (inf: L_e alone), got {lam}")


def combine(l_d: Array, l_e: Array, lam: float | Array) -> Array:
  """Eq. 10, `L = L_d + lambda * L_e`; lambda = inf means L_e alone (Table 4's last column).

  lam: a Python float or a traced scalar; for a traced inf there is no inf * 0 = NaN in the
  gradient.
  """
  if isinstance(lam, (int, float)):
    _check_lam(lam)
    return l_e if math.isinf(lam) else l_d + lam * l_e
  lam = as_float(lam)  # float64 stays float64 (x64 gradient checks)
  if lam.ndim != 0:  # a (K,) lambda broadcast the loss to (K,)
    raise ValueError(f"lam must be a scalar (vmap over streams for several), got shape "
                     f"{lam.shape}")
  if not isinstance(lam, jax.core.Tracer):  # a concrete array: the Python float's check
    _check_lam(float(lam))
  is_inf = jnp.isinf(lam)
  return jnp.where(is_inf, l_e, l_d + jnp.where(is_inf, 0.0, lam) * l_e)


def pitta_loss_from_index(image: Array, depth: Array, index_map: Array, n: Array, *, s: int,
                          lam: float | Array, mode: str = "binary", impl: str = "fast",
                          n_max: int | None = None, inst_ids: Array | None = None,
                          u: Array | float | None = None,
                          v: Array | float | None = None) -> PittaLoss:
  """Eq. 10 from an instance index map (what the adaptation engine holds per frame).

  Args:
    image: (H, W, 3) float image; depth: (H, W) float depth.
    index_map: (H, W) int32, 0 = no dynamic instance, j = instance j (`masks.instance_index_map`).
    n: scalar int N; other arguments as `pitta_loss` (`n_max` for impl="literal", `inst_ids`
      for mode="segment_id").
  """
  l_d = depth_refining_loss_from_index(depth, index_map, n, s=s, mode=mode, impl=impl,
                                       n_max=n_max, inst_ids=inst_ids)
  l_e = edge_guided_loss(image, depth, u, v)
  return PittaLoss(total=combine(l_d, l_e, lam), l_d=l_d, l_e=l_e,
                   n=jnp.asarray(n, jnp.int32))
