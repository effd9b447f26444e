"""Tests of slotlifter_jax.metrics against independent references: sklearn, brute force."""

import itertools
import socket

import chex
import numpy as np
import pytest
import sklearn.metrics

from slotlifter_jax import metrics


def _sk_ari(true, pred):
  return sklearn.metrics.adjusted_rand_score(true, pred)


def _sk_fg_ari(true, pred, background=0):
  keep = true != background
  return np.nan if not keep.any() else _sk_ari(true[keep], pred[keep])


# ------------------------------------------------------------------------------------ ARI


def test_ari_matches_sklearn_on_random_batched_maps():
  rng = np.random.default_rng(0)
  # Arbitrary (negative, large, non-contiguous) label values exercise the relabelling.
  values = np.array([-3, 0, 7, 250, 11])
  true = values[rng.integers(0, 5, size=(2, 3, 97))]
  pred = rng.integers(0, 4, size=(2, 3, 97)) * 13
  got = metrics.ari(true_labels=true, pred_labels=pred)
  got_fg = metrics.fg_ari(true_labels=true, pred_labels=pred)
  chex.assert_shape(got, (2, 3))
  chex.assert_shape(got_fg, (2, 3))
  for idx in np.ndindex(2, 3):
    np.testing.assert_allclose(got[idx], _sk_ari(true[idx], pred[idx]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_fg[idx], _sk_fg_ari(true[idx], pred[idx]), rtol=0, atol=1e-12)


def test_ari_correlated_prediction_matches_sklearn():
  # Mostly-right predictions (ARI far from 0) with a few flipped pixels.
  rng = np.random.default_rng(1)
  true = rng.integers(0, 6, size=(5, 211))
  pred = np.where(rng.random(true.shape) < 0.1, rng.integers(0, 6, size=true.shape), (true + 2) % 6)
  got = metrics.ari(true_labels=true, pred_labels=pred)
  want = [_sk_ari(t, p) for t, p in zip(true, pred)]
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
  assert np.all(got > 0.5)


def test_ari_full_size_view_matches_sklearn():
  # 300×400 (DTU size): pair counts reach n² ≈ 1.4e10 and their products ≈ 2e20 > int64.
  rng = np.random.default_rng(2)
  true = rng.integers(0, 9, size=(300 * 400,))
  pred = np.where(rng.random(true.shape) < 0.3, rng.integers(0, 8, size=true.shape), true % 8)
  np.testing.assert_allclose(
      metrics.ari(true_labels=true, pred_labels=pred), _sk_ari(true, pred), rtol=0, atol=1e-12
  )
  np.testing.assert_allclose(
      metrics.fg_ari(true_labels=true, pred_labels=pred), _sk_fg_ari(true, pred), rtol=0, atol=1e-12
  )


def _adversarial_cases():
  rng = np.random.default_rng(3)
  n = 61
  varied = rng.integers(0, 4, size=n)
  one_pixel = np.zeros(n, int)
  one_pixel[[5, 17, 40]] = [1, 2, 3]  # three one-pixel objects
  return {
      "single_label_both": (np.full(n, 2), np.full(n, 5)),
      "all_background": (np.zeros(n, int), rng.integers(0, 3, size=n)),
      "permutation": (varied, np.array([3, 0, 1, 2])[varied]),
      "pred_constant": (varied, np.zeros(n, int)),
      "true_constant": (np.full(n, 1), varied),
      "pred_all_singletons": (varied, np.arange(n)),
      "both_all_singletons": (np.arange(n), np.arange(n)[::-1].copy()),
      "many_tiny_clusters": (rng.integers(0, 40, size=n), rng.integers(0, 45, size=n)),
      "one_pixel_objects": (one_pixel, rng.integers(0, 3, size=n)),
      "one_pixel_objects_found": (one_pixel, one_pixel + 1),
      "single_pixel_view": (np.array([4]), np.array([1])),
  }


@pytest.mark.parametrize("case", sorted(_adversarial_cases()))
def test_ari_adversarial_cases_match_sklearn(case):
  true, pred = _adversarial_cases()[case]
  got = metrics.ari(true_labels=true, pred_labels=pred)
  assert got.shape == ()
  np.testing.assert_allclose(got, _sk_ari(true, pred), rtol=0, atol=1e-12)
  got_fg = metrics.fg_ari(true_labels=true, pred_labels=pred)
  want_fg = _sk_fg_ari(true, pred)
  if np.isnan(want_fg):
    assert np.isnan(got_fg)
  else:
    np.testing.assert_allclose(got_fg, want_fg, rtol=0, atol=1e-12)


def test_ari_permutation_is_one_and_fg_nan_only_where_no_foreground():
  rng = np.random.default_rng(4)
  true = rng.integers(0, 5, size=(3, 50))
  true[1] = 0  # this view has no foreground
  perm = np.array([4, 2, 0, 1, 3])
  got = metrics.ari(true_labels=true, pred_labels=perm[true])
  np.testing.assert_allclose(got, 1.0)
  fg = metrics.fg_ari(true_labels=true, pred_labels=perm[true])
  assert np.isnan(fg[1]) and np.all(np.isfinite(fg[[0, 2]]))
  np.testing.assert_allclose(fg[[0, 2]], 1.0)


def test_ari_custom_background_label():
  rng = np.random.default_rng(5)
  true = rng.integers(0, 4, size=(2, 73))
  pred = rng.integers(0, 3, size=(2, 73))
  got = metrics.ari(true_labels=true, pred_labels=pred, ignore_background=True, background_label=2)
  want = [_sk_fg_ari(t, p, background=2) for t, p in zip(true, pred)]
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_ari_rejects_mismatched_shapes():
  with pytest.raises(ValueError):
    metrics.ari(true_labels=np.zeros((2, 5), int), pred_labels=np.zeros((2, 6), int))


def test_segmentation_from_render_is_argmax_over_slots():
  rng = np.random.default_rng(6)
  labels = rng.integers(0, 5, size=(2, 7, 11))
  seg = rng.random((2, 7, 11, 5)) * 0.5
  seg += 0.6 * np.eye(5)[labels]  # the labelled slot has the largest weight
  got = metrics.segmentation_from_render(seg)
  chex.assert_shape(got, (2, 7, 11))
  np.testing.assert_array_equal(got, labels)


@pytest.mark.parametrize("image_hw", [(16, 24), (15, 22), (4, 6)])
def test_attention_labels_give_each_pixel_its_nearest_cells_argmax(image_hw):
  rng = np.random.default_rng(3)
  attn = rng.random((5, 4 * 6))  # K = 5 slots over a 4×6 feature map, row-major cells
  labels = metrics.attention_labels(attn, feature_hw=(4, 6), image_hw=image_hw)
  height, width = image_hw
  chex.assert_shape(labels, (height, width))
  for y, x in itertools.product(range(height), range(width)):  # align-corners, by hand
    cy, cx = round(y * 3 / (height - 1)), round(x * 5 / (width - 1))
    assert labels[y, x] == attn[:, cy * 6 + cx].argmax()


# ------------------------------------------------------------------------------------ mBO / mIoU


def _brute_overlap(true, pred, background=0):
  objects = [g for g in np.unique(true) if g != background]
  segments = list(np.unique(pred))
  if not objects:
    return np.nan, np.nan
  iou = np.zeros((len(objects), len(segments)))
  for i, g in enumerate(objects):
    for j, s in enumerate(segments):
      a, b = true == g, pred == s
      iou[i, j] = np.sum(a & b) / np.sum(a | b)
  mbo = iou.max(axis=1).mean()
  # Every injective assignment of objects to segments; objects beyond the segments get nothing.
  slots = segments + [None] * len(objects)
  best = 0.0
  for assignment in itertools.permutations(range(len(slots)), len(objects)):
    total = sum(iou[i, j] for i, j in enumerate(assignment) if j < len(segments))
    best = max(best, total)
  return mbo, best / len(objects)


def test_object_overlap_matches_brute_force():
  rng = np.random.default_rng(7)
  true = rng.integers(0, 5, size=(2, 3, 41))  # up to 4 objects + background
  pred = rng.integers(0, 4, size=(2, 3, 41))  # fewer segments than objects in some views
  true[0, 1] = 0  # no foreground
  true[1, 2] = np.where(true[1, 2] > 2, 0, true[1, 2])  # fewer objects
  got = metrics.object_overlap(true_labels=true, pred_labels=pred)
  chex.assert_shape([got.mbo, got.miou, got.num_objects], (2, 3))
  for idx in np.ndindex(2, 3):
    mbo, miou = _brute_overlap(true[idx], pred[idx])
    if np.isnan(mbo):
      assert np.isnan(got.mbo[idx]) and np.isnan(got.miou[idx]) and got.num_objects[idx] == 0
    else:
      np.testing.assert_allclose(got.mbo[idx], mbo, atol=1e-12)
      np.testing.assert_allclose(got.miou[idx], miou, atol=1e-12)
      assert got.num_objects[idx] == len(set(true[idx].tolist()) - {0})


def test_object_overlap_more_objects_than_segments_counts_zero():
  # 3 equal objects, 1 segment covering everything: each object's best IoU is 10/40, but only one
  # object can be matched, so mIoU = mBO / 3.
  true = np.repeat(np.array([0, 1, 2, 3]), 10)
  pred = np.zeros_like(true)
  got = metrics.object_overlap(true_labels=true, pred_labels=pred)
  mbo, miou = _brute_overlap(true, pred)
  np.testing.assert_allclose([got.mbo, got.miou], [mbo, miou], atol=1e-12)
  np.testing.assert_allclose(got.miou, got.mbo / 3, atol=1e-12)


def test_object_overlap_perfect_segmentation_is_one():
  rng = np.random.default_rng(8)
  true = rng.integers(0, 6, size=(4, 53))
  got = metrics.object_overlap(true_labels=true, pred_labels=(true * 7 + 1) % 11)
  np.testing.assert_allclose(got.mbo, 1.0)
  np.testing.assert_allclose(got.miou, 1.0)


# ------------------------------------------------------------------------------------ active slots


def test_active_slots_on_constructed_map():
  # 2000 pixels, 1000 foreground (objects 1, 2, 5); foreground owned by slots 0: 600, 1: 390,
  # 2: 10 (exactly 1 % → active), background owned by slots 3 and 4 (no foreground → inactive).
  true = np.zeros(2000, int)
  true[:400], true[400:700], true[700:1000] = 1, 2, 5
  pred = np.full(2000, 3)
  pred[:600], pred[600:990], pred[990:1000] = 0, 1, 2
  pred[1500:] = 4
  got = metrics.active_slots(true_labels=true, pred_labels=pred)
  assert got.num_active == 3 and got.num_objects == 3
  # One pixel less for slot 2 (0.9 %): no longer active.
  pred[990] = 1
  got = metrics.active_slots(true_labels=true, pred_labels=pred)
  assert got.num_active == 2
  # A soft segmentation with the same argmax gives the same count; batched shape preserved.
  seg = np.eye(5)[pred] * 0.7 + 0.05
  both = metrics.active_slots(true_labels=np.stack([true, true]), segmentation=np.stack([seg, seg]))
  np.testing.assert_array_equal(both.num_active, [2, 2])
  np.testing.assert_array_equal(both.num_objects, [3, 3])


def test_active_slots_without_foreground_and_bad_arguments():
  got = metrics.active_slots(
      true_labels=np.zeros((2, 9), int), pred_labels=np.arange(18).reshape(2, 9)
  )
  np.testing.assert_array_equal(got.num_active, [0, 0])
  np.testing.assert_array_equal(got.num_objects, [0, 0])
  with pytest.raises(ValueError):
    metrics.active_slots(true_labels=np.zeros(9, int))


# ------------------------------------------------------------------------------------ PSNR


def test_psnr_against_formula():
  target = np.zeros((7, 11, 3))
  np.testing.assert_allclose(metrics.psnr(pred=target + 0.1, target=target), 20.0, atol=1e-12)
  np.testing.assert_allclose(
      metrics.psnr(pred=target + 25.5, target=target, data_range=255.0), 20.0, atol=1e-12
  )
  rng = np.random.default_rng(9)
  pred, target = rng.random((2, 3, 7, 11, 3)), rng.random((2, 3, 7, 11, 3))
  got = metrics.psnr(pred=pred, target=target)
  chex.assert_shape(got, (2, 3))
  for idx in np.ndindex(2, 3):
    mse = np.sum((pred[idx] - target[idx]) ** 2) / pred[idx].size
    np.testing.assert_allclose(got[idx], -10 * np.log10(mse), rtol=1e-12)
  assert metrics.psnr(pred=pred[0, 0], target=pred[0, 0]) == np.inf


# ------------------------------------------------------------------------------------ SSIM


def _brute_valid_ssim(x, y, data_range=1.0, sigma=1.5, radius=5, k1=0.01, k2=0.03):
  """Gaussian SSIM over the positions whose whole 11×11 window lies inside the image."""
  coords = np.arange(-radius, radius + 1)
  g = np.exp(-(coords**2) / (2 * sigma**2))
  window = np.outer(g, g) / np.outer(g, g).sum()
  c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2
  per_channel = []
  for ch in range(x.shape[-1]):
    px = np.lib.stride_tricks.sliding_window_view(x[..., ch], window.shape)  # [h, w, 11, 11]
    py = np.lib.stride_tricks.sliding_window_view(y[..., ch], window.shape)
    mx = np.einsum("hwij,ij->hw", px, window)
    my = np.einsum("hwij,ij->hw", py, window)
    vx = np.einsum("hwij,ij->hw", (px - mx[..., None, None]) ** 2, window)
    vy = np.einsum("hwij,ij->hw", (py - my[..., None, None]) ** 2, window)
    cxy = np.einsum("hwij,ij->hw", (px - mx[..., None, None]) * (py - my[..., None, None]), window)
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    per_channel.append(s.mean())
  return np.mean(per_channel)


def _smooth_pair(rng, h, w):
  # Structured images (not white noise) so that SSIM is far from both 0 and 1.
  base = np.cumsum(np.cumsum(rng.normal(size=(h, w, 3)), axis=0), axis=1)
  base = (base - base.min()) / (base.max() - base.min())
  noisy = np.clip(base + 0.05 * rng.normal(size=base.shape), 0, 1)
  return base, noisy


def test_ssim_matches_brute_force_valid_window():
  rng = np.random.default_rng(10)
  pairs = [_smooth_pair(rng, 37, 29) for _ in range(2)]
  pred = np.stack([p for p, _ in pairs])
  target = np.stack([t for _, t in pairs])
  got = metrics.ssim(pred=pred, target=target)
  chex.assert_shape(got, (2,))
  for i in range(2):
    np.testing.assert_allclose(got[i], _brute_valid_ssim(pred[i], target[i]), rtol=0, atol=1e-10)
  assert np.all((got > 0.2) & (got < 0.99))


def test_ssim_pools_large_images_like_piq():
  # min(H, W) = 384 → f = round(1.5) = 2: SSIM of the 2×2-block means, cropped to even size.
  rng = np.random.default_rng(11)
  pred, target = _smooth_pair(rng, 384, 391)
  got = metrics.ssim(pred=pred, target=target)

  def block_mean(img):
    out = np.zeros((192, 195, 3))
    for i, j in itertools.product(range(2), range(2)):
      out += img[i:384:2, j:390:2]
    return out / 4

  want = _brute_valid_ssim(block_mean(pred), block_mean(target))
  np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
  unpooled = metrics.ssim(pred=pred, target=target, downsample=False)
  assert abs(unpooled - got) > 1e-4  # pooling actually changed the score


def test_ssim_at_protocol_resolution_matches_brute_force():
  # At 128×128 (f = 1, no pooling) the protocol SSIM with the constants of docs/method.md §4,
  # against the brute-force NumPy reference above and nothing else: a reference built on the same
  # library as the implementation would share its mistakes.
  rng = np.random.default_rng(12)
  pred, target = _smooth_pair(rng, 128, 128)
  assert metrics.ssim_pool_factor(128, 128) == 1
  got = metrics.ssim(pred=pred, target=target)
  np.testing.assert_allclose(got, _brute_valid_ssim(pred, target), rtol=0, atol=1e-10)
  assert 0.2 < got < 0.99
  np.testing.assert_allclose(metrics.ssim(pred=pred, target=pred), 1.0, atol=1e-12)


@pytest.mark.parametrize(
    "size, factor",
    [((128, 128), 1), ((300, 400), 1), ((383, 500), 1), ((384, 384), 2), ((480, 640), 2),
     ((640, 640), 2), ((700, 900), 3)],
)
def test_ssim_pool_factor(size, factor):
  # round(min/256): 1.17 → 1, 1.496 → 1, 1.5 → 2 (half to even), 1.875 → 2, 2.5 → 2, 2.73 → 3.
  assert metrics.ssim_pool_factor(*size) == factor


# ------------------------------------------------------------------------------------ LPIPS


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_zero_on_identical_and_grows_with_noise(net):
  rng = np.random.default_rng(13)
  clean = np.stack([_smooth_pair(rng, 64, 64)[0] for _ in range(2)])  # [2, 64, 64, 3]
  chex.assert_shape(clean, (2, 64, 64, 3))
  same = metrics.lpips(pred=clean, target=clean, net=net)
  chex.assert_shape(same, (2,))
  np.testing.assert_allclose(same, 0.0, atol=1e-6)
  noise = rng.normal(size=clean.shape)
  dists = [
      metrics.lpips(pred=np.clip(clean + s * noise, 0, 1), target=clean, net=net)
      for s in (0.02, 0.08, 0.3)
  ]
  assert np.all(dists[0] > 1e-4)
  assert np.all(dists[0] < dists[1]) and np.all(dists[1] < dists[2])


def test_lpips_quirk_feeds_unit_range_unchanged():
  # The quirk on (a, b) equals the correct mapping applied to images whose 2x − 1 is (a, b).
  rng = np.random.default_rng(14)
  a = np.stack([_smooth_pair(rng, 64, 64)[0] for _ in range(2)])
  b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
  quirk = metrics.lpips(pred=a, target=b, official_quirk=True)
  np.testing.assert_allclose(
      quirk, metrics.lpips(pred=(a + 1) / 2, target=(b + 1) / 2), rtol=1e-4, atol=1e-6
  )
  assert np.all(np.abs(quirk - metrics.lpips(pred=a, target=b)) > 1e-4)


def test_lpips_batching_and_no_network_access(monkeypatch):
  def refuse(*args, **kwargs):
    raise AssertionError("LPIPS tried to open a network connection")

  monkeypatch.setattr(socket.socket, "connect", refuse)
  metrics._lpips_network.cache_clear()  # pylint: disable=protected-access
  rng = np.random.default_rng(15)
  a = np.stack([_smooth_pair(rng, 64, 64)[0] for _ in range(3)]).reshape(3, 1, 64, 64, 3)
  b = np.clip(a + 0.1 * rng.normal(size=a.shape), 0, 1)
  whole = metrics.lpips(pred=a, target=b, batch_size=8)
  chex.assert_shape(whole, (3, 1))
  np.testing.assert_allclose(metrics.lpips(pred=a, target=b, batch_size=2), whole, rtol=1e-5)


# ------------------------------------------------------------------------------------ aggregation


def test_summarize_skips_nan():
  values = np.array([0.2, np.nan, 0.5, 0.9, np.nan, 0.4])
  got = metrics.summarize(values)
  kept = np.array([0.2, 0.5, 0.9, 0.4])
  mean = kept.sum() / 4
  stderr = np.sqrt(np.sum((kept - mean) ** 2) / 3) / 2
  np.testing.assert_allclose([got.mean, got.stderr], [mean, stderr], atol=1e-12)
  assert (got.count, got.skipped) == (4, 2)
  one = metrics.summarize([np.nan, 0.3])
  assert one.mean == 0.3 and np.isnan(one.stderr)
  assert np.isnan(metrics.summarize([np.nan]).mean)


def test_per_scene_novel_mean_and_last_view_quirk():
  scenes = [[0.2, 0.4, 0.9], [np.nan, 0.6], [np.nan, np.nan], [0.1, 0.3, np.nan]]
  got = metrics.per_scene_novel_mean(values=scenes)
  np.testing.assert_allclose(got, [0.5, 0.6, np.nan, 0.2], atol=1e-12)
  last = metrics.per_scene_novel_mean(values=scenes, last_novel_only=True)
  np.testing.assert_allclose(last, [0.9, 0.6, np.nan, np.nan], atol=1e-12)
  # Scene mean first, then over scenes — not the mean over all views pooled.
  summary = metrics.summarize(got)
  np.testing.assert_allclose(summary.mean, (0.5 + 0.6 + 0.2) / 3, atol=1e-12)
  assert summary.skipped == 1
