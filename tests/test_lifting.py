"""Tests of slotlifter_jax.lifting against scipy.ndimage and NumPy references."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from slotlifter_jax import lifting
from random_cameras import random_cameras

B, V, R, S, D = 2, 3, 7, 11, 13
H, W, h, w = 13, 17, 5, 9  # (h−1)/(H−1) = 1/3, (w−1)/(W−1) = 1/2


def _scipy_sample(image, pix, mode):
  """map_coordinates per channel; scipy takes (row, col) = (v, u)."""
  coords = np.stack([pix[..., 1].ravel(), pix[..., 0].ravel()])
  out = [ndimage.map_coordinates(image[..., c], coords, order=1, mode=mode, cval=0.0)
         for c in range(image.shape[-1])]
  return np.stack(out, axis=-1).reshape(pix.shape[:-1] + (image.shape[-1],))


def test_bilinear_sample_matches_scipy():
  rng = np.random.default_rng(0)
  image = rng.uniform(size=(h, w, D))
  inside = rng.uniform([0, 0], [w - 1, h - 1], size=(40, 2))
  border = np.array([[0, 0], [w - 1, h - 1], [0, h - 1], [w - 1, 0], [0, 2.5], [w - 1, 1.25],
                     [3.5, 0], [2.25, h - 1], [3, 2]], dtype=np.float64)
  outside = np.concatenate([rng.uniform([-3, -3], [w + 2, h + 2], size=(60, 2)),
                            [[-0.5, 2], [w - 0.5, 1], [2, -0.5], [1, h - 0.5], [-1, 2],
                             [-1e9, 3], [2, 1e9], [-0.25, -0.25]]])
  pix = np.concatenate([inside, border, outside])
  ours = np.asarray(lifting.bilinear_sample(image=jnp.asarray(image, jnp.float32),
                                            pix=jnp.asarray(pix, jnp.float32)))
  chex.assert_shape(ours, (pix.shape[0], D))
  # Everywhere: each tap outside contributes zero ('grid-constant', = torch grid_sample zeros).
  np.testing.assert_allclose(ours, _scipy_sample(image, pix, "grid-constant"), atol=1e-5)
  # Inside and exactly on the border, scipy's 'constant' mode agrees too.
  n_in = len(inside) + len(border)
  np.testing.assert_allclose(ours[:n_in], _scipy_sample(image, pix[:n_in], "constant"), atol=1e-5)
  # The half-pixel band is where the two scipy modes differ: we fade to half of the edge column.
  np.testing.assert_allclose(ours[n_in + 60], 0.5 * image[2, 0], atol=1e-6)
  assert np.all(_scipy_sample(image, pix[n_in + 60:n_in + 61], "constant") == 0.0)


def test_bilinear_sample_integer_pixel_is_exact_and_batched():
  rng = np.random.default_rng(1)
  image = rng.uniform(size=(h, w, 3)).astype(np.float32)
  rows, cols = np.mgrid[0:h, 0:w]
  pix = np.stack([cols, rows], axis=-1).astype(np.float32)  # [h, w, 2]
  out = lifting.bilinear_sample(image=jnp.asarray(image), pix=jnp.asarray(pix))
  chex.assert_shape(out, (h, w, 3))
  np.testing.assert_array_equal(np.asarray(out), image)


def _axis_aligned_camera(centre):
  """cam2world looking down world −z (x right, y down in the image), exactly representable."""
  pose = np.eye(4)
  pose[:3, :3] = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
  pose[:3, 3] = centre
  return pose


def _numpy_lift(points, cams, ks, images, features):
  """Reference: float64 inverse pose, snapping, scipy sampling, RGB then features."""
  nb, nv = cams.shape[:2]
  values = np.zeros(points.shape[:-1] + (nv, 3 + features.shape[-1]))
  valid = np.zeros(points.shape[:-1] + (nv,))
  margin = np.zeros(points.shape[:-1] + (nv,))  # distance to the validity boundary
  for b in range(nb):
    for v in range(nv):
      p_h = np.concatenate([points[b], np.ones(points[b].shape[:-1] + (1,))], axis=-1)
      p_cam = np.einsum("ij,rsj->rsi", np.linalg.inv(cams[b, v]), p_h)[..., :3]
      proj = np.einsum("ij,rsj->rsi", ks[b, v], p_cam)
      with np.errstate(divide="ignore", invalid="ignore"):
        pix = proj[..., :2] / proj[..., 2:]
      size = np.array([W, H])
      ok = (p_cam[..., 2] > 0) & np.all((pix >= -0.5) & (pix <= size - 0.5), axis=-1)
      dist = np.minimum(pix + 0.5, size - 0.5 - pix).min(-1)
      margin[b, :, :, v] = np.where(p_cam[..., 2] > 0, np.abs(dist), -p_cam[..., 2])
      pix = np.clip(np.nan_to_num(pix), 0, size - 1)
      rgb = _scipy_sample(images[b, v], pix, "constant")
      feat = _scipy_sample(features[b, v], pix * (np.array([w, h]) - 1) / (size - 1), "constant")
      values[b, :, :, v] = np.where(ok[..., None], np.concatenate([rgb, feat], -1), 0.0)
      valid[b, :, :, v] = ok
  return values, valid, margin


def _lift(points, cams, ks, images, features):
  f32 = lambda a: jnp.asarray(a, jnp.float32)
  return lifting.project_and_gather(points=f32(points), cam_to_world=f32(cams),
                                    intrinsics=f32(ks), images=f32(images), features=f32(features))


def test_project_and_gather_matches_numpy_reference():
  rng = np.random.default_rng(2)
  cams, ks = random_cameras(rng, B * V, H, W)
  cams, ks = cams.reshape(B, V, 4, 4), ks.reshape(B, V, 3, 3)
  points = rng.uniform(-1.2, 1.2, size=(B, R, S, 3))
  points[0, 0, :3] = cams[0, 0, :3, 3] - 0.5 * cams[0, 0, :3, 2]  # behind view 0 of scene 0
  images = rng.uniform(size=(B, V, H, W, 3))
  features = rng.normal(size=(B, V, h, w, D))
  lifted = _lift(points, cams, ks, images, features)
  chex.assert_shape(lifted.values, (B, R, S, V, 3 + D))
  chex.assert_shape(lifted.valid, (B, R, S, V))
  ref_values, ref_valid, margin = _numpy_lift(points, cams, ks, images, features)
  far_from_edge = margin > 1e-3  # float32 vs float64 may disagree right at the boundary
  assert 0.2 < ref_valid[far_from_edge].mean() < 0.95  # both valid and invalid points are tested
  np.testing.assert_array_equal(np.asarray(lifted.valid)[far_from_edge], ref_valid[far_from_edge])
  np.testing.assert_allclose(np.asarray(lifted.values)[far_from_edge],
                             ref_values[far_from_edge], atol=2e-3)
  invalid = np.asarray(lifted.valid) == 0
  np.testing.assert_array_equal(np.asarray(lifted.values)[invalid], 0.0)
  assert np.all(np.asarray(lifted.valid[0, 0, :3, 0]) == 0)  # behind the camera


def test_point_on_integer_pixel_returns_that_pixel_exactly():
  rng = np.random.default_rng(3)
  # Exactly representable camera: power-of-two focal length, integer principal point, depth 2.
  k = np.array([[16.0, 0, 8.0], [0, 16.0, 6.0], [0, 0, 1.0]])
  cams = np.stack([_axis_aligned_camera([0.5, -0.25, 2.0])] * V)[None]  # [1, V, 4, 4]
  ks = np.stack([k] * V)[None]
  images = rng.uniform(size=(1, V, H, W, 3)).astype(np.float32)
  features = rng.normal(size=(1, V, h, w, D)).astype(np.float32)
  us = np.array([0, 3, 8, 16, 16, 0, 2])  # corners and the principal point included
  vs = np.array([0, 5, 6, 12, 0, 12, 11])
  # Camera looks down −z from z = 2 with y flipped: world x = 0.5 + (u−8)/16·2, y = −0.25 − (v−6)/8.
  x = 0.5 + (us - 8) / 16 * 2.0
  y = -0.25 - (vs - 6) / 16 * 2.0
  points = np.stack([x, y, np.zeros_like(x)], -1)[None, :, None]  # [1, 7, 1, 3], depth 2
  lifted = _lift(points, cams, ks, images, features)
  for v in range(V):
    np.testing.assert_array_equal(np.asarray(lifted.values[0, :, 0, v, :3]), images[0, v, vs, us])
  np.testing.assert_array_equal(np.asarray(lifted.valid), 1.0)
  # Corner pixels map onto corner feature cells (align_corners=True).
  np.testing.assert_allclose(np.asarray(lifted.values[0, 0, 0, 0, 3:]), features[0, 0, 0, 0],
                             atol=1e-6)
  np.testing.assert_allclose(np.asarray(lifted.values[0, 3, 0, 0, 3:]),
                             features[0, 0, h - 1, w - 1], atol=1e-6)


def test_snap_band_and_outside_and_behind():
  k = np.array([[16.0, 0, 8.0], [0, 16.0, 6.0], [0, 0, 1.0]])
  cams = _axis_aligned_camera([0.0, 0.0, 2.0])[None, None]
  ks = k[None, None]
  rng = np.random.default_rng(4)
  images = rng.uniform(0.1, 1, size=(1, 1, H, W, 3))
  features = rng.uniform(0.1, 1, size=(1, 1, h, w, D))
  # Target pixels (u, v): in the snap band left/right/top, just beyond it, and a point behind.
  targets = np.array([[-0.4, 3.0], [W - 0.6, 4.0], [5.0, -0.3], [-0.6, 3.0], [W - 0.4, 4.0],
                      [5.0, H - 0.4]])
  x = (targets[:, 0] - 8) / 16 * 2.0
  y = -(targets[:, 1] - 6) / 16 * 2.0
  points = np.stack([x, y, np.zeros_like(x)], -1)
  points = np.concatenate([points, [[0.0, 0.0, 3.0]]])[None, :, None]  # [1, 7, 1, 3]
  lifted = _lift(points, cams, ks, images, features)
  np.testing.assert_array_equal(np.asarray(lifted.valid[0, :, 0, 0]), [1, 1, 1, 0, 0, 0, 0])
  np.testing.assert_allclose(np.asarray(lifted.values[0, 0, 0, 0, :3]), images[0, 0, 3, 0],
                             atol=1e-6)  # snapped onto column 0
  np.testing.assert_allclose(np.asarray(lifted.values[0, 1, 0, 0, :3]), images[0, 0, 4, W - 1],
                             atol=1e-6)
  np.testing.assert_allclose(np.asarray(lifted.values[0, 2, 0, 0, :3]), images[0, 0, 0, 5],
                             atol=1e-6)
  np.testing.assert_array_equal(np.asarray(lifted.values[0, 3:, 0, 0]), 0.0)


def test_project_and_gather_jit_and_gradients():
  rng = np.random.default_rng(5)
  cams, ks = random_cameras(rng, B * V, H, W)
  args = [jnp.asarray(a, jnp.float32) for a in (
      rng.uniform(-0.5, 0.5, size=(B, R, S, 3)), cams.reshape(B, V, 4, 4), ks.reshape(B, V, 3, 3),
      rng.uniform(size=(B, V, H, W, 3)), rng.normal(size=(B, V, h, w, D)))]

  def f(p, c, k, im, ft):
    return lifting.project_and_gather(points=p, cam_to_world=c, intrinsics=k, images=im,
                                      features=ft)

  eager, jitted = f(*args), jax.jit(f)(*args)
  np.testing.assert_allclose(np.asarray(jitted.values), np.asarray(eager.values), atol=1e-5)
  np.testing.assert_array_equal(np.asarray(jitted.valid), np.asarray(eager.valid))
  grad = jax.grad(lambda ft: f(*args[:4], ft).values.sum())(args[4])
  assert np.all(np.isfinite(np.asarray(grad)))
  # Bilinear weights of a valid point sum to 1 over the feature map taps.
  np.testing.assert_allclose(float(grad.sum()), float(D * eager.valid.sum()), rtol=1e-4)


def _numpy_fuse(values, valid):
  out = np.zeros(values.shape[:-2] + (2 * values.shape[-1],))
  for idx in np.ndindex(values.shape[:-2]):
    wts = valid[idx] / (valid[idx].sum() + 1e-6)
    mean = sum(wts[i] * values[idx][i] for i in range(values.shape[-2]))
    var = sum(wts[i] * (values[idx][i] - mean) ** 2 for i in range(values.shape[-2]))
    out[idx] = np.concatenate([mean, var])
  return out


def test_fuse_views_matches_numpy():
  rng = np.random.default_rng(6)
  values = rng.normal(size=(B, R, S, V, D))
  valid = (rng.uniform(size=(B, R, S, V)) < 0.6).astype(np.float64)
  valid[0, 0, 0] = 0.0  # seen by no view
  valid[0, 0, 1] = 1.0  # seen by all
  fused = lifting.fuse_views(values=jnp.asarray(values, jnp.float32),
                             valid=jnp.asarray(valid, jnp.float32))
  chex.assert_shape(fused, (B, R, S, 2 * D))
  np.testing.assert_allclose(np.asarray(fused), _numpy_fuse(values, valid), rtol=1e-4, atol=1e-5)
  np.testing.assert_array_equal(np.asarray(fused[0, 0, 0]), 0.0)
  single = lifting.fuse_views(values=jnp.asarray(values[..., :1, :], jnp.float32),
                              valid=jnp.asarray(valid[..., :1], jnp.float32))
  chex.assert_shape(single, (B, R, S, D))
  np.testing.assert_allclose(np.asarray(single), values[..., 0, :] * valid[..., :1], rtol=1e-6)


@pytest.mark.parametrize("shared", [True, False])
def test_sample_ray_keep(shared):
  key = jax.random.key(7)
  keep = np.asarray(lifting.sample_ray_keep(key=key, keep_ratio=0.3, shape=(B, 4001),
                                            shared_across_batch=shared))
  chex.assert_shape(keep, (B, 4001))
  assert set(np.unique(keep)) <= {0.0, 1.0}
  assert abs(keep.mean() - 0.3) < 0.03
  assert np.array_equal(keep[0], keep[1]) == shared
  for ratio, expected in ((0.0, 0.0), (1.0, 1.0)):
    np.testing.assert_array_equal(
        np.asarray(lifting.sample_ray_keep(key=key, keep_ratio=ratio, shape=(B, R),
                                           shared_across_batch=shared)), expected)
  jitted = jax.jit(lambda k, r: lifting.sample_ray_keep(key=k, keep_ratio=r, shape=(B, 4001),
                                                       shared_across_batch=shared))(key, 0.3)
  np.testing.assert_array_equal(np.asarray(jitted), keep)


def test_apply_ray_mask():
  rng = np.random.default_rng(8)
  lifted = rng.normal(size=(B, R, S, D))
  keep = (rng.uniform(size=(B, R)) < 0.5).astype(np.float32)
  out = np.asarray(lifting.apply_ray_mask(lifted=jnp.asarray(lifted, jnp.float32),
                                          keep=jnp.asarray(keep)))
  chex.assert_shape(out, (B, R, S, D))
  for b in range(B):
    for r in range(R):
      np.testing.assert_allclose(out[b, r], lifted[b, r] * keep[b, r], rtol=1e-6)
