"""Evaluation's and the pictures' pure functions on made-up renderings (no model): which views
reach the metrics, how per-scene results aggregate, and the orbit cameras, against sklearn/NumPy
references and closed forms. The eval and render modes end to end are in test_evaluate.py; the
metric functions themselves (ARI, SSIM, LPIPS, mBO, …) in test_metrics.py.
"""

import dataclasses
import math
import os

import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from data_fixtures import look_at
from slotlifter_jax import evaluate
from slotlifter_jax import geometry
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import pictures
from slotlifter_jax.rendering import views as views_lib
from train_helpers import load_config

# ---------------------------------------------------------------------------------------------
# scene_metrics on made-up renderings (no model)
# ---------------------------------------------------------------------------------------------

H, W, K = 5, 7, 3


def _toy_scene(rng):
  """5 views: 0 source; 1-4 novel; view 2 has no ground-truth mask; view 4 shows no foreground."""
  n = 5
  masks = rng.integers(0, 4, size=(n, H, W)).astype(np.int32)
  masks[4] = 0
  return Scene(name="toy", images=rng.uniform(size=(n, H, W, 3)).astype(np.float32),
               cam_to_world=np.broadcast_to(np.eye(4, dtype=np.float32), (n, 4, 4)).copy(),
               intrinsics=np.broadcast_to(np.eye(3, dtype=np.float32), (n, 3, 3)).copy(),
               source_indices=(0,), masks=masks,
               mask_views=np.array([True, True, False, True, True]))


def _toy_render(rng, n):
  seg = rng.uniform(size=(n, H, W, K)).astype(np.float32)
  return views_lib.RenderedViews(
      colour=rng.uniform(size=(n, H, W, 3)).astype(np.float32),
      depth=np.zeros((n, H, W), np.float32), segmentation=seg / seg.sum(-1, keepdims=True),
      slots=np.zeros((K, 2), np.float32), slot_attn=np.zeros((K, 4), np.float32),
      source_labels=rng.integers(0, K, size=(1, H, W)).astype(np.int32))


def _psnr(a, b):
  return 10 * np.log10(1.0 / np.mean((np.float64(a) - np.float64(b)) ** 2))


def _fg_ari(true, pred):
  fg = true != 0
  return adjusted_rand_score(true[fg], pred[fg])


@pytest.mark.parametrize("height,width,chunk", [(6, 5, 8), (6, 5, 64), (4, 4, 16)])
def test_render_cameras_covers_every_pixel_once_in_order(height, width, chunk):
  """Chunks (padded, or one exact chunk for a view smaller than `chunk`) give every pixel its own
  ray's result in row-major order, against geometry.pixel_rays on all pixels at once."""
  cams = np.stack([look_at(np.array([2.0, 0.5, 1.0])), look_at(np.array([0.3, -2.0, 1.5]))])
  intr = np.array([[4.0, 0, (width - 1) / 2], [0, 4.0, (height - 1) / 2], [0, 0, 1]], np.float32)
  sizes = []

  def fn(origins, directions):  # [1, c, 3] each → per-ray values
    sizes.append(origins.shape[1])
    return origins + 2.0 * directions, directions[..., 0]

  points, first = views_lib.render_cameras(
      fn, cam_to_world=cams, intrinsics=[intr, intr], height=height, width=width, chunk=chunk)
  n = height * width
  assert points.shape == (2, n, 3) and first.shape == (2, n)
  assert set(sizes) == {min(chunk, n)}  # one compiled shape; no padding beyond the view
  pix = geometry.image_pixels(height, width).reshape(-1, 2)
  for c in range(2):
    rays = geometry.pixel_rays(cam_to_world=jnp.asarray(cams[c], jnp.float32),
                               intrinsics=jnp.asarray(intr), pix=pix)
    np.testing.assert_allclose(points[c], rays.origins + 2.0 * rays.directions, atol=1e-6)
    np.testing.assert_allclose(first[c], rays.directions[:, 0], atol=1e-6)


@pytest.mark.parametrize("supersample", [2, 3])
def test_render_cameras_supersample_is_the_footprint_mean(supersample):
  """With S×S rays per pixel each result is their mean: for a value u² of the ray's image
  column, the mean over the grid's columns c + δ is c² + (S² − 1)/(12 S²), δ at the cells'
  centres (the variance of S equally spaced points of spacing 1/S)."""
  cam = look_at(np.array([2.0, 0.5, 1.0]))
  height, width = 3, 4
  intr = np.array([[4.0, 0, 1.5], [0, 4.0, 1.0], [0, 0, 1]], np.float32)

  def column_squared(origins, directions):  # the image column the ray goes through, squared
    d_cam = jnp.einsum("ji,crj->cri", jnp.asarray(cam[:3, :3], jnp.float32), directions)
    u = intr[0, 0] * d_cam[..., 0] / d_cam[..., 2] + intr[0, 2]
    return (u ** 2,)

  (got,) = views_lib.render_cameras(column_squared, cam_to_world=cam[None], intrinsics=[intr],
                                    height=height, width=width, chunk=5, supersample=supersample)
  columns = np.tile(np.arange(width, dtype=np.float64), height)  # row-major
  expected = columns ** 2 + (supersample ** 2 - 1) / (12 * supersample ** 2)
  np.testing.assert_allclose(got[0], expected, atol=1e-4)


def test_scene_metrics_splits_views_and_skips_as_the_protocol_says():
  rng = np.random.default_rng(0)
  scene = _toy_scene(rng)
  rendered = _toy_render(rng, scene.num_views)
  out = evaluate.scene_metrics(rendered, scene, range(scene.num_views))
  true = scene.masks.reshape(5, -1)
  pred = np.argmax(rendered.segmentation, -1).reshape(5, -1)

  assert out["psnr_source"] == pytest.approx(_psnr(rendered.colour[0], scene.images[0]))
  assert out["psnr_novel"] == pytest.approx(
      np.mean([_psnr(rendered.colour[v], scene.images[v]) for v in (1, 2, 3, 4)]))
  assert out["ari"] == pytest.approx(adjusted_rand_score(true[0], pred[0]))
  assert out["fg_ari"] == pytest.approx(_fg_ari(true[0], pred[0]))
  # The slot attention's own grouping of the source view, not the rendered one.
  assert out["attn_fg_ari"] == pytest.approx(
      _fg_ari(true[0], rendered.source_labels[0].ravel()))
  assert out["attn_fg_ari"] != pytest.approx(out["fg_ari"])
  assert out["attn_ari"] == pytest.approx(
      adjusted_rand_score(true[0], rendered.source_labels[0].ravel()))
  # View 2 has no mask: left out of every segmentation metric; view 4 has no foreground: left
  # out of FG-ARI only.
  assert out["nv_ari"] == pytest.approx(
      np.mean([adjusted_rand_score(true[v], pred[v]) for v in (1, 3, 4)]))
  assert out["nv_fg_ari"] == pytest.approx(np.mean([_fg_ari(true[v], pred[v]) for v in (1, 3)]))
  for k in ("mbo", "miou", "nv_mbo", "nv_miou"):
    assert 0.0 <= out[k] <= 1.0
  assert "ssim" not in out and "lpips" not in out  # image_metrics off

  # Active slots: the scene's masked views pooled; a slot counts with ≥ 1 % of the foreground.
  views = [0, 1, 3, 4]
  t, p = true[views].ravel(), pred[views].ravel()
  owned = np.array([np.sum((t != 0) & (p == k)) for k in range(K)])
  assert out["active_slots"] == np.sum((owned > 0) & (owned >= 0.01 * np.sum(t != 0)))
  assert out["num_objects"] == len(set(t[t != 0].tolist()))
  assert out["slot_excess"] == out["active_slots"] - out["num_objects"]


def test_fg_ari_on_views_with_two_objects_leaves_out_single_object_views():
  """One visible object: FG-ARI is 0 for any split of it (sklearn's convention) whatever the split
  looks like, so `fg_ari_multi` skips such views; views with two objects score as FG-ARI."""
  rng = np.random.default_rng(5)
  scene = _toy_scene(rng)
  masks = np.zeros((5, H, W), np.int32)
  masks[0, :2, :] = 1  # source: one object only
  masks[1, :2, :], masks[1, 3:, :] = 1, 2  # novel 1: two objects
  masks[3, :2, :] = 2  # novel 3: one object
  scene = Scene(**{**scene.__dict__, "masks": masks})
  # The rendering splits every object's pixels in two columns' halves: slot 0 | slot 1.
  seg = np.zeros((5, H, W, K), np.float32)
  seg[..., :3, 0], seg[..., 3:, 1] = 1.0, 1.0
  rendered = dataclasses.replace(_toy_render(rng, 5), segmentation=seg)
  out = evaluate.scene_metrics(rendered, scene, range(5))
  true, pred = masks.reshape(5, -1), np.argmax(seg, -1).reshape(5, -1)
  assert out["fg_ari"] == pytest.approx(0.0)  # a split single object: exactly 0
  assert np.isnan(out["fg_ari_multi"])
  assert out["nv_fg_ari_multi"] == pytest.approx(_fg_ari(true[1], pred[1]))
  assert out["nv_fg_ari"] == pytest.approx(np.mean([_fg_ari(true[v], pred[v]) for v in (1, 3)]))


def test_scene_metrics_quirk_and_missing_masks():
  rng = np.random.default_rng(1)
  scene = _toy_scene(rng)
  rendered = _toy_render(rng, scene.num_views)
  true = scene.masks.reshape(5, -1)
  pred = np.argmax(rendered.segmentation, -1).reshape(5, -1)
  quirk = evaluate.scene_metrics(rendered, scene, range(5), nv_ari_last_view=True)
  assert quirk["nv_ari"] == pytest.approx(adjusted_rand_score(true[4], pred[4]))
  assert math.isnan(quirk["nv_fg_ari"])  # the last novel view has no foreground
  plain = evaluate.scene_metrics(rendered, scene, range(5))
  assert quirk["nv_mbo"] == plain["nv_mbo"]  # the uORF rule is for NV-ARI only

  no_masks = evaluate.scene_metrics(rendered, Scene(**{**scene.__dict__, "masks": None,
                                                        "mask_views": None}), range(5))
  assert set(no_masks) == {"psnr_source", "psnr_novel"}


def test_scene_metrics_rejects_source_labels_of_other_sources():
  rng = np.random.default_rng(2)
  scene = _toy_scene(rng)
  rendered = _toy_render(rng, scene.num_views)
  two = rendered.replace(source_labels=np.zeros((2, H, W), np.int32))
  with pytest.raises(ValueError, match="toy: 2 source views rendered, but the scene names 1"):
    evaluate.scene_metrics(two, scene, range(scene.num_views))


def test_mean_over_scenes_skips_nan():
  got = evaluate.mean_over_scenes([{"a": 1.0, "b": math.nan}, {"a": 3.0}, {"a": 5.0, "b": 2.0}])
  assert got["a"] == 3.0 and got["b"] == 2.0


def test_lpips_network_by_data_set():
  assert evaluate.lpips_net_for(load_config("clevr")) == "alex"
  assert evaluate.lpips_net_for(load_config("dtu")) == "vgg"
  assert evaluate.lpips_net_for(load_config("scannet")) == "vgg"


# ---------------------------------------------------------------------------------------------
# Orbit cameras and per-slot densities (pure functions)
# ---------------------------------------------------------------------------------------------


def test_panel_row_labels_and_checkpoint_name():
  rng = np.random.default_rng(0)
  scene = _toy_scene(rng)
  assert pictures.view_labels(scene) == ["source", "novel 1", "novel 2", "novel 3", "novel 4"]
  two = dataclasses.replace(scene, source_indices=(2, 0))
  assert pictures.view_labels(two) == ["source 2", "novel 1", "source 1", "novel 2", "novel 3"]
  assert pictures.checkpoint_name(os.path.join("run", "checkpoints", "best", "40")) == "best"
  assert pictures.checkpoint_name("run/checkpoints/latest/7/") == "latest"


def test_orbit_circles_z_axis_looking_at_origin():
  source = look_at([3.0, -5.0, 4.0])  # the test fixtures' own look-at, not the library's
  poses = pictures.orbit_cam_to_world(source_cam_to_world=source, num_frames=7)
  assert poses.shape == (7, 4, 4)
  np.testing.assert_allclose(poses[0], source, atol=1e-9)
  eyes = poses[:, :3, 3]
  np.testing.assert_allclose(eyes[:, 2], 4.0, atol=1e-9)
  np.testing.assert_allclose(np.hypot(eyes[:, 0], eyes[:, 1]), math.hypot(3.0, -5.0), atol=1e-9)
  azimuth = np.unwrap(np.arctan2(eyes[:, 1], eyes[:, 0]))
  np.testing.assert_allclose(np.diff(azimuth), 2 * np.pi / 7, atol=1e-9)
  for pose in poses:
    rot = pose[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-9)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    origin_cam = np.linalg.inv(pose) @ np.array([0.0, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(origin_cam[:2], 0.0, atol=1e-9)  # on the optical axis
    assert origin_cam[2] > 0  # in front of the camera
    assert rot[2, 1] < 0  # the camera's y (down) points against world z (up)
