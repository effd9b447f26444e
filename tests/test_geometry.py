"""Tests of slotlifter_jax.geometry against NumPy references (float64 inverses, loops)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import geometry
from random_cameras import random_cameras

B, R, S, H, W = 2, 7, 11, 13, 17


def _homogeneous_pixels(pix):
  return np.concatenate([pix, np.ones(pix.shape[:-1] + (1,))], axis=-1)


def test_image_pixels_grid():
  pix = geometry.image_pixels(H, W)
  chex.assert_shape(pix, (H, W, 2))
  rows, cols = np.mgrid[0:H, 0:W]
  np.testing.assert_array_equal(np.asarray(pix[..., 0]), cols)  # u = x = column
  np.testing.assert_array_equal(np.asarray(pix[..., 1]), rows)  # v = y = row


def test_pixel_rays_match_numpy_inverse_and_broadcast():
  rng = np.random.default_rng(0)
  cams, ks = random_cameras(rng, B, H, W)
  pix = rng.uniform(-2, W + 2, size=(B, R, 2))
  rays = geometry.pixel_rays(cam_to_world=jnp.asarray(cams[:, None], jnp.float32),
                             intrinsics=jnp.asarray(ks[:, None], jnp.float32),
                             pix=jnp.asarray(pix, jnp.float32))
  chex.assert_shape([rays.origins, rays.directions], (B, R, 3))
  # Reference: d ∝ R·K⁻¹·[u, v, 1] with a general float64 inverse.
  d_cam = np.einsum("bij,brj->bri", np.linalg.inv(ks), _homogeneous_pixels(pix))
  d = np.einsum("bij,brj->bri", cams[:, :3, :3], d_cam)
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  np.testing.assert_allclose(np.asarray(rays.directions), d, atol=1e-5)
  np.testing.assert_allclose(np.asarray(rays.origins),
                             np.broadcast_to(cams[:, None, :3, 3], (B, R, 3)), atol=1e-6)
  np.testing.assert_allclose(np.linalg.norm(np.asarray(rays.directions), axis=-1), 1.0, atol=1e-6)


def test_pixel_rays_in_numpy_stay_on_the_host_in_float64():
  """xp=np (the host batch pipeline's call): NumPy arrays in float64, no JAX arrays, and the same
  rays as the float64 general-inverse reference to float64 rounding."""
  rng = np.random.default_rng(3)
  cams, ks = random_cameras(rng, B, H, W)
  pix = rng.uniform(-2, W + 2, size=(B, R, 2))
  rays = geometry.pixel_rays(cam_to_world=cams[:, None], intrinsics=ks[:, None], pix=pix, xp=np)
  assert type(rays.directions) is np.ndarray and type(rays.origins) is np.ndarray
  assert rays.directions.dtype == np.float64
  chex.assert_shape([rays.origins, rays.directions], (B, R, 3))
  d_cam = np.einsum("bij,brj->bri", np.linalg.inv(ks), _homogeneous_pixels(pix))
  d = np.einsum("bij,brj->bri", cams[:, :3, :3], d_cam)
  d /= np.linalg.norm(d, axis=-1, keepdims=True)
  np.testing.assert_allclose(rays.directions, d, atol=1e-12)
  np.testing.assert_array_equal(rays.origins, np.broadcast_to(cams[:, None, :3, 3], (B, R, 3)))


def test_principal_point_ray_is_camera_forward():
  rng = np.random.default_rng(1)
  cams, ks = random_cameras(rng, 1, 128, 128)
  centre = jnp.array([(128 - 1) / 2, (128 - 1) / 2])
  rays = geometry.pixel_rays(cam_to_world=jnp.asarray(cams[0], jnp.float32),
                             intrinsics=jnp.asarray(ks[0], jnp.float32), pix=centre)
  np.testing.assert_allclose(np.asarray(rays.directions), cams[0, :3, 2], atol=1e-6)


def test_world_to_cam_matches_general_inverse_and_round_trips():
  rng = np.random.default_rng(2)
  cams, _ = random_cameras(rng, B, H, W)
  points = rng.normal(size=(B, R, S, 3))
  cam = jnp.asarray(cams[:, None, None], jnp.float32)  # [B, 1, 1, 4, 4]
  p_cam = geometry.world_to_cam(points=jnp.asarray(points, jnp.float32), cam_to_world=cam)
  chex.assert_shape(p_cam, (B, R, S, 3))
  ref = np.einsum("bij,brsj->brsi", np.linalg.inv(cams),
                  np.concatenate([points, np.ones((B, R, S, 1))], axis=-1))[..., :3]
  np.testing.assert_allclose(np.asarray(p_cam), ref, atol=1e-5)
  back = geometry.cam_to_world_points(points_cam=p_cam, cam_to_world=cam)
  np.testing.assert_allclose(np.asarray(back), points, atol=1e-5)


def test_cam_to_pix_matches_numpy():
  rng = np.random.default_rng(3)
  _, ks = random_cameras(rng, B, H, W)
  p_cam = rng.normal(size=(B, R, 3)) + np.array([0, 0, 3.0])
  pix, depth = geometry.cam_to_pix(points_cam=jnp.asarray(p_cam, jnp.float32),
                                   intrinsics=jnp.asarray(ks[:, None], jnp.float32))
  chex.assert_shape(pix, (B, R, 2))
  chex.assert_shape(depth, (B, R))
  proj = np.einsum("bij,brj->bri", ks, p_cam)
  np.testing.assert_allclose(np.asarray(pix), proj[..., :2] / proj[..., 2:], rtol=1e-5, atol=1e-4)
  np.testing.assert_allclose(np.asarray(depth), p_cam[..., 2], rtol=1e-6)


def test_cam_to_pix_behind_and_on_camera_plane_is_finite():
  k = jnp.asarray([[100.0, 0, 8], [0, 100.0, 6], [0, 0, 1]])
  p_cam = jnp.array([[0.3, -0.2, -1.0], [0.3, -0.2, 0.0], [1e-3, 0.0, 1e-12]])
  pix, depth = geometry.cam_to_pix(points_cam=p_cam, intrinsics=k)
  assert np.all(np.isfinite(np.asarray(pix)))
  assert np.all(np.abs(np.asarray(pix)) <= geometry.PIX_LIMIT)
  np.testing.assert_array_equal(np.asarray(depth) > 0, [False, False, True])


def test_back_projected_point_projects_to_its_pixel_and_depth():
  """Pixel → ray → point o + t·d → pixel again, for random cameras and sub-pixel coordinates."""
  rng = np.random.default_rng(4)
  cams, ks = random_cameras(rng, B, H, W)
  pix = rng.uniform(0, [W - 1, H - 1], size=(B, R, 2))
  t = rng.uniform(0.5, 3.0, size=(B, R, S))
  cam, k = jnp.asarray(cams[:, None], jnp.float32), jnp.asarray(ks[:, None], jnp.float32)
  rays = geometry.pixel_rays(cam_to_world=cam, intrinsics=k, pix=jnp.asarray(pix, jnp.float32))
  points = geometry.points_along_rays(origins=rays.origins, directions=rays.directions,
                                      z=jnp.asarray(t, jnp.float32))
  chex.assert_shape(points, (B, R, S, 3))
  proj = geometry.world_to_pix(points=points, cam_to_world=cam[:, :, None],
                               intrinsics=k[:, :, None])
  chex.assert_shape(proj.pix, (B, R, S, 2))
  np.testing.assert_allclose(np.asarray(proj.pix),
                             np.broadcast_to(pix[:, :, None], (B, R, S, 2)), atol=2e-3)
  # Camera-z depth of o + t·d is t / |K⁻¹[u, v, 1]| (d is the unit version of that z = 1 vector).
  norm = np.linalg.norm(np.einsum("bij,brj->bri", np.linalg.inv(ks), _homogeneous_pixels(pix)),
                        axis=-1)
  np.testing.assert_allclose(np.asarray(proj.depth), t / norm[..., None], rtol=1e-5)


def test_points_along_rays_values():
  rng = np.random.default_rng(5)
  o, d, z = rng.normal(size=(B, R, 3)), rng.normal(size=(B, R, 3)), rng.uniform(size=(B, R, S))
  pts = geometry.points_along_rays(origins=jnp.asarray(o), directions=jnp.asarray(d),
                                   z=jnp.asarray(z))
  chex.assert_shape(pts, (B, R, S, 3))
  for s in range(S):
    np.testing.assert_allclose(np.asarray(pts[:, :, s]), o + z[:, :, s, None] * d, rtol=1e-5,
                               atol=1e-6)


@pytest.mark.parametrize("endpoint", [False, True])
def test_stratified_depths_eval_grid(endpoint):
  near, far = 6 / 7, 20 / 7
  z = geometry.stratified_depths(near=near, far=far, num_samples=S, batch_shape=(B, R),
                                 endpoint=endpoint)
  chex.assert_shape(z, (B, R, S))
  ref = np.linspace(near, far, S, endpoint=endpoint)
  np.testing.assert_allclose(np.asarray(z), np.broadcast_to(ref, (B, R, S)), rtol=1e-6)


def test_stratified_depths_training_jitter():
  near = np.array([0.1, 0.5])[:, None]  # per-scene near/far broadcast to [B, R]
  far = np.array([5.0, 2.0])[:, None]
  z = geometry.stratified_depths(near=near, far=far, num_samples=S, batch_shape=(B, R),
                                 key=jax.random.key(0))
  z = np.asarray(z)
  chex.assert_shape(z, (B, R, S))
  assert np.all(z >= near[..., None] - 1e-6) and np.all(z <= far[..., None] + 1e-6)
  assert np.all(np.diff(z, axis=-1) > 0)
  grid = np.asarray(geometry.stratified_depths(near=near, far=far, num_samples=S,
                                               batch_shape=(B, R)))
  shift = z - grid  # one jitter per ray: the same shift for every sample of a ray
  np.testing.assert_allclose(shift, np.broadcast_to(shift[..., :1], shift.shape), atol=1e-5)
  step = (far - near) / S
  assert np.all(shift[..., 0] >= 0) and np.all(shift[..., 0] < step + 1e-6)
  assert len(np.unique(np.round(shift[..., 0] / step, 5))) == B * R  # different rays, different u


def _numpy_inverse_cdf(bins, weights, u):
  """Reference: invert the piecewise-linear cdf of (weights + eps) with np.interp, ray by ray."""
  out = np.zeros(u.shape)
  for idx in np.ndindex(weights.shape[:-1]):
    w = weights[idx] + geometry.PDF_EPS
    cdf = np.concatenate([[0.0], np.cumsum(w) / np.sum(w)])
    out[idx] = np.interp(u[idx], cdf, bins[idx])
  return out


def test_sample_pdf_deterministic_matches_numpy_inverse_cdf():
  rng = np.random.default_rng(6)
  num_new = 9
  bins = np.sort(rng.uniform(0, 4, size=(B, R, S + 1)), axis=-1)
  weights = rng.uniform(size=(B, R, S)) ** 3
  weights[0, 0] = 0.0  # an empty ray: uniform in the bins
  z = geometry.sample_pdf(bins=jnp.asarray(bins, jnp.float32), weights=jnp.asarray(weights,
                          jnp.float32), num_samples=num_new)
  chex.assert_shape(z, (B, R, num_new))
  u = np.broadcast_to(np.linspace(0, 1, num_new), (B, R, num_new))
  np.testing.assert_allclose(np.asarray(z), _numpy_inverse_cdf(bins, weights, u), atol=1e-4)
  assert np.all(np.diff(np.asarray(z), axis=-1) >= 0)
  assert np.all(np.asarray(z) >= bins[..., :1] - 1e-6)
  assert np.all(np.asarray(z) <= bins[..., -1:] + 1e-6)


def test_sample_pdf_one_hot_and_random_distribution():
  num_new = 64
  bins = jnp.broadcast_to(jnp.linspace(1.0, 2.0, S + 1), (B, R, S + 1))
  hot = 4
  weights = jax.nn.one_hot(jnp.full((B, R), hot), S)
  z = np.asarray(geometry.sample_pdf(bins=bins, weights=weights, num_samples=num_new,
                                     key=jax.random.key(1)))
  chex.assert_shape(z, (B, R, num_new))
  assert np.all(np.diff(z, axis=-1) >= 0)
  lo, hi = float(bins[0, 0, hot]), float(bins[0, 0, hot + 1])
  # The 1e-5 floor leaves (S−1)·1e-5 of the mass elsewhere: at most a stray sample in B·R·64.
  inside = (z >= lo - 1e-6) & (z <= hi + 1e-6)
  assert inside.mean() > 0.999
  # Random samples follow a non-trivial pdf: compare bin frequencies with the weights.
  w = np.arange(1, S + 1, dtype=np.float64)
  many = np.asarray(geometry.sample_pdf(bins=jnp.linspace(0.0, 1.0, S + 1)[None],
                                        weights=jnp.asarray(w)[None], num_samples=20000,
                                        key=jax.random.key(2)))[0]
  freq = np.histogram(many, bins=np.linspace(0, 1, S + 1))[0] / many.size
  np.testing.assert_allclose(freq, w / w.sum(), atol=0.01)


def test_sample_pdf_stops_gradients():
  bins = jnp.linspace(0.0, 1.0, S + 1)
  grad = jax.grad(lambda w: geometry.sample_pdf(bins=bins, weights=w, num_samples=5).sum())(
      jnp.linspace(0.1, 1.0, S))
  np.testing.assert_array_equal(np.asarray(grad), 0.0)


def test_fine_depths_sorted_superset():
  rng = np.random.default_rng(7)
  z = np.sort(rng.uniform(1, 3, size=(B, R, S)), axis=-1)
  weights = rng.uniform(size=(B, R, S))
  out = np.asarray(geometry.fine_depths(z=jnp.asarray(z, jnp.float32),
                                        weights=jnp.asarray(weights, jnp.float32), num_samples=5))
  chex.assert_shape(out, (B, R, S + 5))
  assert np.all(np.diff(out, axis=-1) >= 0)
  for idx in np.ndindex(B, R):  # every coarse depth is still there
    assert np.all(np.min(np.abs(out[idx][:, None] - z[idx][None]), axis=0) < 1e-6)
  mids = 0.5 * (z[..., 1:] + z[..., :-1])
  assert np.all(out >= np.minimum(z[..., :1], mids[..., :1]) - 1e-6)


def test_positional_encoding_order_and_values():
  rng = np.random.default_rng(8)
  x = rng.uniform(-2, 2, size=(B, R, 3))
  pe = np.asarray(geometry.positional_encoding(jnp.asarray(x, jnp.float32)))
  chex.assert_shape(pe, (B, R, 60))
  ref = np.zeros((B, R, 60))
  for c in range(3):
    for k in range(10):
      ref[..., c * 10 + k] = np.sin(2.0**k * x[..., c])
      ref[..., 30 + c * 10 + k] = np.cos(2.0**k * x[..., c])
  np.testing.assert_allclose(pe, ref, atol=2e-4)  # float32 argument up to 2^9·2
  chex.assert_shape(geometry.positional_encoding(jnp.zeros((5, 2)), num_freqs=4), (5, 16))


def test_jit_and_vmap_agree():
  rng = np.random.default_rng(9)
  cams, ks = random_cameras(rng, B, H, W)
  cams, ks = jnp.asarray(cams, jnp.float32), jnp.asarray(ks, jnp.float32)
  points = jnp.asarray(rng.normal(size=(B, R, 3)), jnp.float32)

  def project(p, c, k):
    return geometry.world_to_pix(points=p, cam_to_world=c, intrinsics=k)

  eager = project(points, cams[:, None], ks[:, None])
  jitted = jax.jit(project)(points, cams[:, None], ks[:, None])
  mapped = jax.vmap(project)(points, cams, ks)
  for other in (jitted, mapped):
    np.testing.assert_allclose(np.asarray(other.pix), np.asarray(eager.pix), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(other.depth), np.asarray(eager.depth), rtol=1e-6)
  pix = geometry.image_pixels(H, W)
  rays = geometry.pixel_rays(cam_to_world=cams[0], intrinsics=ks[0], pix=pix)
  rays_jit = jax.jit(lambda c, k, p: geometry.pixel_rays(cam_to_world=c, intrinsics=k, pix=p))(
      cams[0], ks[0], pix)
  chex.assert_shape(rays.directions, (H, W, 3))
  np.testing.assert_allclose(np.asarray(rays_jit.directions), np.asarray(rays.directions),
                             atol=1e-6)
  z_key = jax.random.key(3)
  strat = lambda k: geometry.stratified_depths(near=0.1, far=5.0, num_samples=S,
                                               batch_shape=(B, R), key=k)
  np.testing.assert_allclose(np.asarray(jax.jit(strat)(z_key)), np.asarray(strat(z_key)),
                             rtol=1e-6)


def test_slab_interval_against_a_dense_march():
  """Each ray's [near, far] ∩ {z_min ≤ z ≤ z_max}, found by marching 200 001 points per ray."""
  rng = np.random.default_rng(3)
  n = 64
  origins = rng.uniform(-1, 1, size=(n, 3)) + [0, 0, 1.2]
  dirs = rng.normal(size=(n, 3))
  dirs[:4, 2] = 0.0  # parallel to the slab: two inside it, two above it
  origins[:2, 2], origins[2:4, 2] = 0.1, 2.0
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
  near, far, z_min, z_max = 0.5, 3.0, -0.05, 0.45
  lo, hi = geometry.slab_interval(origins=jnp.asarray(origins, jnp.float32),
                                  directions=jnp.asarray(dirs, jnp.float32), near=near, far=far,
                                  z_min=z_min, z_max=z_max)
  t = np.linspace(near, far, 200_001)
  step = t[1] - t[0]
  for i in range(n):
    z = origins[i, 2] + t * dirs[i, 2]
    inside = t[(z >= z_min) & (z <= z_max)]
    if inside.size < 2:  # misses the slab: the whole interval, as without bounds
      assert (float(lo[i]), float(hi[i])) == pytest.approx((near, far))
    else:
      assert float(lo[i]) == pytest.approx(inside[0], abs=2 * step + 1e-5)
      assert float(hi[i]) == pytest.approx(inside[-1], abs=2 * step + 1e-5)


def test_samples_in_a_slab_render_its_closed_form_opacity():
  """Constant σ inside the slab, zero outside: with all S evaluation samples inside the ray's slab
  segment of length L (Δ = L/S, the last δ is 0), the opacity is exactly 1 − exp(−25σ(S−1)Δ).
  On the unbounded grid only the few samples that land in the slab would see the density."""
  from slotlifter_jax.rendering import volume
  origins = jnp.array([[0.0, 0.0, 1.2], [0.3, -0.2, 1.0]], jnp.float32)
  dirs = jnp.array([[0.0, 0.6, -0.8], [0.48, 0.0, -0.6]], jnp.float32)
  dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
  z_min, z_max, sigma, s = 0.0, 0.4, 0.3, 16
  lo, hi = geometry.slab_interval(origins=origins, directions=dirs, near=0.2, far=3.0,
                                  z_min=z_min, z_max=z_max)
  z = geometry.stratified_depths(near=lo, far=hi, num_samples=s, batch_shape=(2,))
  height = origins[:, None, 2] + z * dirs[:, None, 2]
  assert bool(jnp.all((height >= z_min - 1e-5) & (height <= z_max + 1e-5)))
  density = jnp.where((height >= z_min) & (height <= z_max), sigma, 0.0)
  out = volume.volume_render(density=density, z=z, colour=jnp.ones(z.shape + (3,)),
                             slot_weights=None, far=3.0)
  length = (z_max - z_min) / np.abs(np.asarray(dirs[:, 2]))  # both rays cross the whole slab
  expected = 1.0 - np.exp(-25.0 * sigma * (s - 1) * length / s)
  np.testing.assert_allclose(np.asarray(out.opacity), expected, rtol=1e-5)


@pytest.mark.parametrize("per_side", [1, 2, 3, 4])
def test_subpixel_offsets_are_the_cell_centres_of_the_pixel(per_side):
  offsets = geometry.subpixel_offsets(per_side)
  assert offsets.shape == (per_side ** 2, 2)
  # Each offset is the centre of its own cell of side 1/S inside [-1/2, 1/2]².
  cells = np.floor((offsets + 0.5) * per_side).astype(int)
  assert len({tuple(c) for c in cells}) == per_side ** 2
  np.testing.assert_allclose(offsets, (cells + 0.5) / per_side - 0.5, atol=1e-7)
  if per_side == 2:
    np.testing.assert_array_equal(np.sort(offsets[:, 0]), [-0.25, -0.25, 0.25, 0.25])


def test_subpixel_offsets_refuse_an_empty_grid():
  with pytest.raises(ValueError, match="≥ 1"):
    geometry.subpixel_offsets(0)
