"""Tests of slotlifter_jax.collapse: usage statistics against NumPy references, verdicts on
constructed healthy and collapsed segmentations."""

import chex
import jax
import numpy as np
import pytest
import scipy.stats

from slotlifter_jax import collapse

K = 7
N = 211


def _objects_map(rng, views=3, num_objects=5):
  """Ground-truth labels [views, N], 0 = background, objects 1..num_objects all present."""
  labels = rng.integers(0, num_objects + 1, size=(views, N))
  labels[:, : num_objects + 1] = np.arange(num_objects + 1)  # every object present in every view
  return labels


def _confident(labels, rng, k=K, confidence=0.85):
  """Soft segmentation [..., N, K] with most mass on slot `labels` (background → slot 0)."""
  noise = rng.random(labels.shape + (k,))
  noise *= (1 - confidence) / noise.sum(axis=-1, keepdims=True)
  return noise + confidence * np.eye(k)[labels]


def test_slot_usage_matches_numpy_reference():
  rng = np.random.default_rng(0)
  seg = rng.random((2, 3, N, K)) ** 3  # unnormalised on purpose: the function renormalises
  fg = rng.random((2, 3, N)) < 0.6
  usage = collapse.slot_usage(segmentation=seg, foreground_mask=fg)
  chex.assert_shape(usage.share_per_slot, (2, 3, K))
  chex.assert_shape([usage.largest_share, usage.active_slots, usage.pixel_entropy], (2, 3))
  for idx in np.ndindex(2, 3):
    p = seg[idx] / seg[idx].sum(-1, keepdims=True)
    owners = np.argmax(p[fg[idx]], axis=-1)
    share = np.bincount(owners, minlength=K) / fg[idx].sum()
    np.testing.assert_allclose(usage.share_per_slot[idx], share, atol=1e-6)
    assert usage.largest_share[idx] == pytest.approx(share.max(), abs=1e-6)
    assert usage.active_slots[idx] == np.sum(share >= 0.01)
    ent = scipy.stats.entropy(p[fg[idx]], axis=-1) / np.log(K)
    assert usage.pixel_entropy[idx] == pytest.approx(ent.mean(), abs=1e-5)
    share_entropy = scipy.stats.entropy(share) / np.log(K)
    assert usage.share_entropy[idx] == pytest.approx(share_entropy, abs=1e-5)
    assert usage.foreground_pixels[idx] == fg[idx].sum()


def test_healthy_segmentation_is_not_flagged():
  rng = np.random.default_rng(1)
  labels = _objects_map(rng)
  seg = _confident(labels, rng)
  usage = collapse.slot_usage(segmentation=seg, foreground_mask=labels > 0)
  # Each of the 5 objects owns its own slot.
  np.testing.assert_array_equal(usage.active_slots, [5, 5, 5])
  for view in range(3):
    counts = np.bincount(labels[view][labels[view] > 0], minlength=K)
    np.testing.assert_allclose(usage.share_per_slot[view], counts / counts.sum(), atol=1e-6)
  verdict = collapse.is_collapsed(usage)
  assert not verdict.collapsed
  assert not (verdict.dominant_slot or verdict.too_few_active or verdict.near_uniform)
  assert not collapse.is_collapsed(usage, per_view=True).collapsed.any()


def test_all_foreground_in_one_slot_is_flagged():
  rng = np.random.default_rng(2)
  labels = _objects_map(rng)
  seg = _confident(np.where(labels > 0, 3, 0), rng)  # every object → slot 3
  usage = collapse.slot_usage(segmentation=seg, foreground_mask=labels > 0)
  np.testing.assert_allclose(usage.largest_share, 1.0, atol=1e-6)
  np.testing.assert_array_equal(usage.active_slots, [1, 1, 1])
  verdict = collapse.is_collapsed(usage)
  assert verdict.collapsed and verdict.dominant_slot and verdict.too_few_active
  assert not verdict.near_uniform


def test_uniform_segmentation_is_flagged_even_when_argmax_spreads():
  rng = np.random.default_rng(3)
  labels = _objects_map(rng)
  # 1/K plus tiny noise: the argmax is random, so the shares look healthy; the entropy does not.
  seg = 1.0 / K + 1e-3 * rng.random(labels.shape + (K,))
  usage = collapse.slot_usage(segmentation=seg, foreground_mask=labels > 0)
  assert np.all(usage.largest_share < 0.9) and np.all(usage.active_slots >= 2)
  assert np.all(usage.pixel_entropy > 0.99)
  verdict = collapse.is_collapsed(usage)
  assert verdict.collapsed and verdict.near_uniform
  assert not (verdict.dominant_slot or verdict.too_few_active)
  # Exactly uniform: ties go to slot 0, which then also owns all the foreground.
  exact = collapse.slot_usage(segmentation=np.full((N, K), 1.0 / K))
  assert exact.largest_share == pytest.approx(1.0)
  assert collapse.is_collapsed(exact).dominant_slot


def test_foreground_mask_none_counts_every_pixel():
  rng = np.random.default_rng(4)
  labels = _objects_map(rng)
  seg = _confident(labels, rng)
  usage = collapse.slot_usage(segmentation=seg)
  ones = collapse.slot_usage(segmentation=seg, foreground_mask=np.ones(labels.shape, bool))
  np.testing.assert_allclose(usage.share_per_slot, ones.share_per_slot, atol=1e-7)
  np.testing.assert_array_equal(usage.active_slots, [6, 6, 6])  # background slot counts too


def test_run_verdict_ignores_views_without_foreground():
  rng = np.random.default_rng(5)
  labels = _objects_map(rng, views=4)
  labels[1:] = 0  # empty views: their zero shares must not count as "too few active slots"
  usage = collapse.slot_usage(segmentation=_confident(labels, rng), foreground_mask=labels > 0)
  np.testing.assert_array_equal(usage.foreground_pixels[1:], 0)
  assert not collapse.is_collapsed(usage).collapsed
  per_view = collapse.is_collapsed(usage, per_view=True)
  chex.assert_shape(per_view.collapsed, (4,))
  assert not per_view.collapsed.any()


def test_black_render_detection():
  rng = np.random.default_rng(6)
  target = 0.2 + 0.6 * rng.random((3, N, 3))
  rendered = np.stack([
      np.zeros((N, 3)),  # black render
      np.clip(target[1] + 0.05 * rng.normal(size=(N, 3)), 0, 1),  # fine
      0.01 * rng.random((N, 3)),  # nearly black
  ])
  brightness = collapse.black_render(rendered=rendered, target=target)
  np.testing.assert_array_equal(brightness.black, [True, False, True])
  np.testing.assert_allclose(brightness.target_mean, target.mean(axis=(1, 2)), rtol=1e-6)
  # A dark target is not judged.
  dark = collapse.black_render(rendered=np.zeros((N, 3)), target=np.full((N, 3), 0.02))
  assert not dark.black

  labels = _objects_map(rng)
  usage = collapse.slot_usage(segmentation=_confident(labels, rng), foreground_mask=labels > 0)
  healthy_render = collapse.black_render(rendered=target, target=target)
  assert not collapse.is_collapsed(usage, brightness=healthy_render).collapsed
  black_everywhere = collapse.black_render(rendered=np.zeros_like(target), target=target)
  verdict = collapse.is_collapsed(usage, brightness=black_everywhere)
  assert verdict.collapsed and verdict.black and not verdict.dominant_slot
  per_view = collapse.is_collapsed(usage, brightness=brightness, per_view=True)
  np.testing.assert_array_equal(per_view.collapsed, [True, False, True])


def test_jit_agrees_with_eager():
  rng = np.random.default_rng(7)
  labels = _objects_map(rng)
  seg = _confident(labels, rng)
  fg = labels > 0
  eager = collapse.slot_usage(segmentation=seg, foreground_mask=fg)
  jitted = jax.jit(lambda s, f: collapse.slot_usage(segmentation=s, foreground_mask=f))(seg, fg)
  chex.assert_trees_all_close(eager, jitted, atol=1e-6)
  verdict = jax.jit(collapse.is_collapsed)(jitted)
  assert bool(verdict.collapsed) == bool(collapse.is_collapsed(eager).collapsed)
