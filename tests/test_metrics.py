"""Depth metrics (MonoDepth2 protocol): hand-computed cases and a per-pixel NumPy loop."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pitta_jax import metrics
from reference_numpy import depth_metrics_literal


def test_metric_names_order():
  # Hand value: MonoDepth2's order of compute_errors' outputs.
  assert metrics.METRIC_NAMES == ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def test_hand_computed_2x2_without_scaling():
  # gt [[1, 2], [4, 0]] (0 is invalid), pred [[1, 1], [5, 9]]: valid pairs (1,1), (2,1), (4,5).
  # abs_rel  = (0 + 1/2 + 1/4) / 3 = 0.25
  # sq_rel   = (0 + 1/2 + 1/4) / 3 = 0.25          ((2-1)^2/2, (4-5)^2/4)
  # rmse     = sqrt((0 + 1 + 1) / 3) = sqrt(2/3)
  # rmse_log = sqrt((0 + ln(2)^2 + ln(5/4)^2) / 3)
  # thresh   = 1, 2, 1.25 -> a1 (< 1.25) = 1/3, a2 (< 1.5625) = 2/3, a3 (< 1.953125) = 2/3
  gt = np.array([[1, 2], [4, 0]], np.float32)
  pred = np.array([[1, 1], [5, 9]], np.float32)
  got = metrics.depth_metrics(pred, gt, median_scaling=False)
  want = dict(abs_rel=0.25, sq_rel=0.25, rmse=math.sqrt(2 / 3),
              rmse_log=math.sqrt((math.log(2) ** 2 + math.log(1.25) ** 2) / 3),
              a1=1 / 3, a2=2 / 3, a3=2 / 3)
  for k in metrics.METRIC_NAMES:
    assert got[k] == pytest.approx(want[k], rel=1e-12), k


def test_hand_computed_2x2_with_scaling_and_clamp():
  # Same gt; pred [[1, 1], [5, 9]] scaled by median(gt_valid) / median(pred_valid) = 2 / 1:
  # pred (2, 2, 10); with max_depth = 8 the clamp makes it (2, 2, 8) (gt 4 < 8 stays valid).
  # abs_rel = (1/1 + 0 + 4/4) / 3 = 2/3; sq_rel = (1 + 0 + 16/4) / 3 = 5/3;
  # rmse = sqrt((1 + 0 + 16) / 3); rmse_log = sqrt((ln 2^2 + 0 + ln 2^2) / 3);
  # thresh = 2, 1, 2 -> a1 = a2 = a3 = 1/3.
  gt = np.array([[1, 2], [4, 0]], np.float32)
  pred = np.array([[1, 1], [5, 9]], np.float32)
  got = metrics.depth_metrics(pred, gt, max_depth=8.0)
  want = dict(abs_rel=2 / 3, sq_rel=5 / 3, rmse=math.sqrt(17 / 3),
              rmse_log=math.sqrt(2 * math.log(2) ** 2 / 3), a1=1 / 3, a2=1 / 3, a3=1 / 3)
  for k in metrics.METRIC_NAMES:
    assert got[k] == pytest.approx(want[k], rel=1e-12), k


@pytest.mark.parametrize("median_scaling", [True, False])
@pytest.mark.parametrize("clamp", [True, False])
def test_matches_per_pixel_loop(median_scaling, clamp):
  # Reference: MonoDepth2's protocol and formulas written per pixel (depth_metrics_literal).
  rng = np.random.default_rng(int(median_scaling) * 2 + int(clamp))
  gt = rng.uniform(0.5, 90.0, (15, 24)).astype(np.float32)
  gt[rng.random(gt.shape) < 0.3] = 0.0  # invalid pixels
  pred = (gt * rng.uniform(0.5, 1.6, gt.shape) + 0.3).astype(np.float32)
  got = metrics.depth_metrics(pred, gt, median_scaling=median_scaling, clamp=clamp)
  want = depth_metrics_literal(pred, gt, median_scaling=median_scaling, clamp=clamp)
  for k in metrics.METRIC_NAMES:
    np.testing.assert_allclose(got[k], want[k], rtol=1e-10, err_msg=k)


def test_resizes_prediction_bilinear():
  # Reference: MonoDepth2's evaluate_depth.py (pred_disp = cv2.resize(pred_disp, (W, H)), then
  # pred_depth = 1 / pred_disp) then the loop; resize="depth" resizes the depth itself; and a
  # hand value: a constant prediction 2 on any grid stays 2, against gt 4 -> abs_rel 0.5, a1 = 0.
  rng = np.random.default_rng(7)
  gt = rng.uniform(1.0, 50.0, (12, 20)).astype(np.float32)
  pred = rng.uniform(1.0, 50.0, (6, 10)).astype(np.float32)
  pred_disp = cv2.resize(1.0 / pred, (20, 12), interpolation=cv2.INTER_LINEAR)
  for got, resized in ((metrics.depth_metrics(pred, gt), 1.0 / pred_disp),
                       (metrics.depth_metrics((1.0 / pred).astype(np.float32), gt,
                                              pred_is_disparity=True), 1.0 / pred_disp),
                       (metrics.depth_metrics(pred, gt, resize="depth"),
                        cv2.resize(pred, (20, 12), interpolation=cv2.INTER_LINEAR))):
    want = depth_metrics_literal(resized, gt)
    for k in metrics.METRIC_NAMES:
      np.testing.assert_allclose(got[k], want[k], rtol=1e-6, err_msg=k)
  with pytest.raises(ValueError, match="resize must be"):
    metrics.depth_metrics(pred, gt, resize="nearest")
  const = metrics.depth_metrics(np.full((3, 5), 2.0, np.float32), np.full((6, 10), 4.0),
                                median_scaling=False)
  assert const["abs_rel"] == pytest.approx(0.5)
  assert const["a1"] == 0.0


def test_disparity_input_matches_depth_input():
  # Reference: MonoDepth2's order (resize the disparity, then invert) on a same-size map is just
  # depth = 1 / disparity.
  rng = np.random.default_rng(8)
  gt = rng.uniform(1.0, 50.0, (8, 12)).astype(np.float32)
  depth = rng.uniform(1.0, 50.0, (8, 12)).astype(np.float32)
  a = metrics.depth_metrics(depth, gt)
  b = metrics.depth_metrics((1.0 / depth).astype(np.float32), gt, pred_is_disparity=True)
  for k in metrics.METRIC_NAMES:
    np.testing.assert_allclose(a[k], b[k], rtol=1e-6, err_msg=k)


def test_positive_ground_truth_scores_beyond_the_cap():
  """MonoDepth2's eigen_benchmark protocol (mask = gt > 0; pred still clamped to [1e-3, 80]):
  a pixel with gt 90 m counts, hand value |90 - 80| / 90 averaged with an exact pixel."""
  gt = np.array([[10.0, 90.0]])
  pred = np.array([[10.0, 95.0]])
  capped = metrics.depth_metrics(pred, gt, median_scaling=False)
  positive = metrics.depth_metrics(pred, gt, median_scaling=False, valid_gt="positive")
  assert capped["abs_rel"] == 0.0
  assert positive["abs_rel"] == pytest.approx((10.0 / 90.0) / 2)
  with pytest.raises(ValueError, match="valid_gt must be"):
    metrics.depth_metrics(pred, gt, valid_gt="all")
  # an infinite ground truth (a .npy map's "no return") is no measurement: not scored
  with_inf = metrics.depth_metrics(np.array([[10.0, 95.0, 20.0]]), np.array([[10.0, 90.0, np.inf]]),
                                   median_scaling=False, valid_gt="positive")
  assert with_inf == positive


def test_valid_pixels_are_found_in_the_ground_truths_float_type():
  """evaluate_depth.py compares its float32 ground truth with MIN_DEPTH in float32: a pixel of
  exactly float32(1e-3) is not above 1e-3 there (it is in float64: 1.0000000475e-3). Hand
  value: that pixel is not scored, so a perfect prediction elsewhere gives abs_rel 0; a float64
  map of the same values scores it (|1 - 1e-3| / 1e-3 halved by the other, exact pixel)."""
  gt = np.array([[1.0, 0.001]], np.float32)
  pred = np.ones((1, 2), np.float32)
  assert not (gt > 1e-3)[0, 1]  # NumPy's own float32 comparison, as upstream's mask
  assert metrics.depth_metrics(pred, gt, median_scaling=False)["abs_rel"] == 0.0
  f64 = metrics.depth_metrics(pred, gt.astype(np.float64), median_scaling=False)["abs_rel"]
  assert f64 == pytest.approx((1.0 - 0.001) / float(np.float32(0.001)) / 2)


def test_garg_crop():
  # Hand values for KITTI's 375x1242: rows int(0.40810811*375) = 153 .. int(0.99189189*375) =
  # 371, cols int(0.03594771*1242) = 44 .. int(0.96405229*1242) = 1197.
  mask = metrics.garg_crop_mask(375, 1242)
  assert mask.sum() == (371 - 153) * (1197 - 44)
  assert mask[153, 44] and mask[370, 1196]
  assert not mask[152, 44] and not mask[371, 44] and not mask[153, 43] and not mask[153, 1197]
  # Errors only outside the crop do not count.
  gt = np.full((375, 1242), 10.0, np.float32)
  pred = gt.copy()
  pred[:150] = 30.0
  assert metrics.depth_metrics(pred, gt, garg_crop=True, median_scaling=False)["abs_rel"] == 0.0
  assert metrics.depth_metrics(pred, gt, garg_crop=False, median_scaling=False)["abs_rel"] > 0.0


def test_clear_errors():
  gt = np.ones((4, 4), np.float32)
  with pytest.raises(ValueError, match="pred must be a 2-D"):
    metrics.depth_metrics(np.ones((1, 4, 4)), gt)
  with pytest.raises(ValueError, match="gt must be a 2-D"):
    metrics.depth_metrics(np.ones((4, 4)), np.ones(4))
  with pytest.raises(ValueError, match="NaN"):
    metrics.depth_metrics(np.full((4, 4), np.nan), gt)
  with pytest.raises(ValueError, match="no valid"):
    metrics.depth_metrics(np.ones((4, 4)), np.zeros((4, 4)))
  with pytest.raises(ValueError, match="no valid"):
    metrics.depth_metrics(np.ones((4, 4)), np.full((4, 4), 100.0))  # all beyond max_depth
  with pytest.raises(ValueError, match="positive"):
    metrics.depth_metrics(-np.ones((4, 4)), gt, median_scaling=False, clamp=False)
  # a zero depth resized as disparity (inf) spreads: the prediction's median is 0, and the
  # message told a caller that already clamps to "use clamp=True"
  with pytest.raises(ValueError, match=r"^the prediction's median on the valid pixels is 0\.0: "
                                       r"median scaling needs a positive finite one"):
    metrics.depth_metrics(np.array([[0.0, 1.0]], np.float32), np.full((2, 4), 10.0, np.float32))
  # an infinite median: the ratio is 0 and inf * 0 NaN, which no clamp fixes (it was told to
  # "use clamp=True")
  inf_pred = np.full((4, 4), np.inf)
  inf_pred[0, 0] = 5.0
  with pytest.raises(ValueError, match=r"^the prediction's median on the valid pixels is inf: "
                                       r"median scaling needs a positive finite one"):
    metrics.depth_metrics(inf_pred, gt, clamp=True)


def test_mean_metrics():
  # Hand value: the mean over frames of each metric.
  a = {k: 1.0 for k in metrics.METRIC_NAMES}
  b = {k: 3.0 for k in metrics.METRIC_NAMES}
  b["a1"] = 0.0
  m = metrics.mean_metrics([a, b])
  assert m["abs_rel"] == 2.0 and m["a1"] == 0.5
  # three frames, one far off: the mean (3.0), not the median (2.0) or a pairwise mean
  c = {k: 6.0 for k in metrics.METRIC_NAMES}
  b = {k: 2.0 for k in metrics.METRIC_NAMES}
  assert metrics.mean_metrics([a, b, c])["abs_rel"] == 3.0
  assert tuple(m) == metrics.METRIC_NAMES
  with pytest.raises(ValueError, match="at least one"):
    metrics.mean_metrics([])
  with pytest.raises(ValueError, match="lacks"):
    metrics.mean_metrics([{"abs_rel": 1.0}])


def test_scale_shift_alignment_recovers_an_affine_inverse_depth():
  # Reference: a prediction that is an exact affine map of the inverse ground truth must score
  # 0 after scale-shift alignment (what a relative-depth network is evaluated with), and the
  # closed form must equal NumPy's least squares written out here.
  rng = np.random.default_rng(3)
  gt = rng.uniform(2.0, 60.0, size=(20, 30))
  pred_inv = 3.0 * (1.0 / gt) + 0.25  # relative inverse depth, affine in 1/gt
  got = metrics.depth_metrics(1.0 / pred_inv, gt, alignment="scale_shift")
  assert got["abs_rel"] < 1e-6 and got["a1"] == 1.0  # pred is cast to float32 inside
  a = np.stack([pred_inv.ravel(), np.ones(pred_inv.size)], 1)
  s, t = np.linalg.inv(a.T @ a) @ a.T @ (1.0 / gt.ravel())  # normal equations
  np.testing.assert_allclose(metrics.scale_shift_inverse(pred_inv.ravel(), 1.0 / gt.ravel()),
                             s * pred_inv.ravel() + t, rtol=1e-10)
  with pytest.raises(ValueError, match="alignment must be"):
    metrics.depth_metrics(1.0 / pred_inv, gt, alignment="mean")


def test_stereo_alignment_is_monodepth2s_fixed_factor():
  """MonoDepth2's evaluate_depth.py with --eval_stereo: pred_depth *= 5.4, no median scaling.
  Hand values: pred 1 and 2 m become 5.4 and 10.8 m against gt 5 and 12 m."""
  m = metrics.depth_metrics(np.array([[1.0, 2.0]]), np.array([[5.0, 12.0]]), alignment="stereo")
  assert m["abs_rel"] == pytest.approx((0.4 / 5 + 1.2 / 12) / 2)
  assert m["rmse"] == pytest.approx(math.sqrt((0.4 ** 2 + 1.2 ** 2) / 2))


def test_weights_trained_with_stereo_pairs_are_evaluated_as_monodepth2_does():
  from types import SimpleNamespace
  from pitta_jax.run import model_alignment
  spec = SimpleNamespace(alignment="median")
  assert model_alignment(SimpleNamespace(spec=spec, config={"use_stereo": True})) == "stereo"
  assert model_alignment(SimpleNamespace(spec=spec, config={"use_stereo": False})) == "median"
  assert model_alignment(SimpleNamespace(spec=spec, config={})) == "median"
  relative = SimpleNamespace(alignment="scale_shift")
  assert model_alignment(SimpleNamespace(spec=relative, config={"use_stereo": True})) == \
      "scale_shift"


def test_scale_shift_floors_a_negative_fitted_inverse_depth_at_max_depth():
  """The fitted inverse depth of the far pixel is negative (-0.0076): floored at 1 / 80, it
  scores as 80 m (against gt 70), not as a clamped 1e-3 m. Reference: the least squares and the
  7 metrics written out here."""
  gt = np.array([[2.0, 4.0, 8.0, 70.0]])
  pred_inv = np.array([0.6, 0.35, 0.225, 0.05])
  a = np.stack([pred_inv, np.ones(4)], 1)
  s, t = np.linalg.lstsq(a, 1.0 / gt.ravel(), rcond=None)[0]
  fitted = s * pred_inv + t
  assert fitted[3] < 0
  want = 1.0 / np.maximum(fitted, 1.0 / 80.0)
  assert want[3] == 80.0
  got = metrics.depth_metrics(1.0 / pred_inv[None].astype(np.float32), gt,
                              alignment="scale_shift")
  np.testing.assert_allclose(got["abs_rel"], np.mean(np.abs(gt.ravel() - want) / gt.ravel()),
                             rtol=1e-5)
  assert got["a1"] == np.mean(np.maximum(gt.ravel() / want, want / gt.ravel()) < 1.25) == 1.0


def test_mean_metrics_does_not_hide_a_nan_frame():
  # A frame whose metrics are NaN (a null read back from a results file) makes the mean NaN, as
  # MonoDepth2's np.mean would: it is not left out.
  ok = {k: 0.1 for k in metrics.METRIC_NAMES}
  bad = {k: float("nan") for k in metrics.METRIC_NAMES}
  assert math.isnan(metrics.mean_metrics([ok, bad])["abs_rel"])


def test_positive_ground_truth_leaves_out_zeros():
  # valid_gt="positive" scores gt > 0 only: the 0 (no measurement) pixel is not a pixel at
  # inf relative error. Hand value: the two measured pixels, |12 - 10| / 10 and 0, mean 0.1.
  gt = np.array([[10.0, 0.0, 20.0]])
  pred = np.array([[12.0, 5.0, 20.0]])
  got = metrics.depth_metrics(pred, gt, median_scaling=False, valid_gt="positive")
  assert got["abs_rel"] == pytest.approx(0.1)


def test_the_depth_range_flags_say_what_the_mask_and_the_clamp_do():
  """--eval.max-depth's help called it a "cap of ground truth": ground truth beyond it is left
  out (MonoDepth2's `gt < MAX_DEPTH` mask), not capped; only the prediction is clamped. Hand
  values: gt 100 m is not scored (capped to 80 it would add an error), pred 100 m is clamped."""
  import argparse
  from pitta_jax.config_cli import add_config_arguments
  from pitta_jax.run import EvalConfig
  gt = np.array([[10.0, 100.0]])
  pred = np.array([[12.0, 100.0]])
  m = metrics.depth_metrics(pred, gt, median_scaling=False)
  assert m["abs_rel"] == pytest.approx(0.2)  # the 100 m pixel is not scored
  m = metrics.depth_metrics(np.array([[100.0]]), np.array([[50.0]]), median_scaling=False)
  assert m["abs_rel"] == pytest.approx(30 / 50)  # the prediction clamped to 80
  p = argparse.ArgumentParser()
  add_config_arguments(p, EvalConfig, "eval", "eval")
  helps = {a.dest: " ".join(a.help.split()) for a in p._actions if a.help}
  text = {k: v for k, v in helps.items() if k.endswith(("min_depth", "max_depth"))}
  assert len(text) == 2 and not any("cap of ground truth" in v for v in text.values())
  assert all("not scored" in v and "clamped" in v for v in text.values())


def test_a_min_depth_of_zero_is_refused_before_any_frame():
  """--eval.min-depth 0 was accepted, and a prediction of 0 on a valid pixel, clamped "up" to
  0, then stopped the run mid-way with the metrics' ValueError: the clamp needs a positive
  lower bound (MonoDepth2's 1e-3), so the configuration is refused before any work."""
  from pitta_jax.run import EvalConfig
  for bad in (0.0, -1.0):
    with pytest.raises(ValueError, match=r"need 0 < min_depth < max_depth < inf, got "
                                          rf"min_depth={bad} "):
      EvalConfig(min_depth=bad)
  assert EvalConfig(min_depth=0.1).min_depth == 0.1
