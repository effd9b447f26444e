"""Adaptive full-view rendering (slotlifter_jax.rendering.adaptive, issue #7): the window choice
against brute-force NumPy references, the window δ of volume_render, windowed compositing of an
analytic field against the whole grid, and the model's adaptive renderer against the plain
SceneRenderer.
Odd, distinct sizes throughout (H 29 × W 31, S 11 / 41, 7 rays …) so swapped axes fail."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from data_fixtures import orbit_pose
from slotlifter_jax import model as model_lib
from slotlifter_jax import train_step as step_lib
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import adaptive
from slotlifter_jax.rendering import views as views_lib
from slotlifter_jax.rendering import volume
from train_helpers import load_config

NEAR, FAR = 6.0 / 7.0, 20.0 / 7.0
SCALE = 25.0


# ---------------------------------------------------------------------------------------------
# 1. Window choice against brute force
# ---------------------------------------------------------------------------------------------


def _random_profiles(rng, shape, s):
  """Render-weight-like profiles [*shape, S], Σ ≤ 1: peaked, spread, sparse, zero and faint."""
  kind = rng.integers(0, 5, size=shape)
  centre = rng.uniform(0, s, size=shape + (1,))
  width = rng.uniform(0.3, 3.0, size=shape + (1,))
  peaked = np.exp(-0.5 * ((np.arange(s) - centre) / width) ** 2)
  spread = rng.uniform(size=shape + (s,))
  sparse = spread * (rng.uniform(size=shape + (s,)) < 0.25)
  w = np.where((kind == 0)[..., None], peaked, np.where((kind == 1)[..., None], spread, sparse))
  w = w / np.maximum(w.sum(-1, keepdims=True), 1e-12)
  opacity = rng.uniform(0.3, 1.0, size=shape)
  opacity = np.where(kind == 3, 0.0, np.where(kind == 4, 0.004, opacity))  # empty, faint (< ε)
  return (w * opacity[..., None]).astype(np.float32)


def _brute_range(w, eps):
  """Smallest [lo, hi) leaving out ≤ eps, first on ties (float64 on the float32 weights)."""
  w = np.float64(w)
  total, s = w.sum(), len(w)
  if total <= eps:
    return 0, 0
  for length in range(0, s + 1):
    for lo in range(0, s - length + 1):
      if total - w[lo:lo + length].sum() <= eps:
        return lo, lo + length
  raise AssertionError("unreachable: the whole ray leaves out nothing")


@pytest.mark.parametrize("eps", [0.01, 0.1])
def test_significant_range_matches_brute_force(eps):
  rng = np.random.default_rng(1)
  b, r, s = 3, 7, 11
  w = _random_profiles(rng, (b, r), s)
  got = jax.jit(adaptive.significant_range)(weights=w, eps=eps)
  chex.assert_shape([got.lo, got.hi], (b, r))
  for idx in np.ndindex(b, r):
    assert (int(got.lo[idx]), int(got.hi[idx])) == _brute_range(w[idx], eps), idx
    # The property that matters: at most ε of the ray's weight lies outside its range.
    assert w[idx].sum() - w[idx][got.lo[idx]:got.hi[idx]].sum() <= eps + 1e-6


def _brute_window(lo, hi, window, s):
  """(start, overflow) by the rule in words: cover the hull, centred when shorter; the hull
  reaches the grid's end when some but not all neighbours are transparent."""
  ranges = [(a, b) for a, b in zip(lo, hi) if b > a]
  if not ranges:
    return 0, 0
  h_lo, h_hi = min(a for a, _ in ranges), max(b for _, b in ranges)
  if len(ranges) < len(lo):
    h_hi = s
  length = h_hi - h_lo
  if length > window:
    return min(h_lo, s - window), length - window
  slack = window - length
  return int(np.clip(h_lo - slack // 2, 0, s - window)), 0


@pytest.mark.parametrize("window", [1, 4, 11])
def test_choose_windows_covers_the_neighbours_ranges(window):
  rng = np.random.default_rng(2)
  s, n_pix, n = 11, 37, 4
  w = _random_profiles(rng, (n_pix, n), s)
  sig = adaptive.significant_range(weights=w, eps=0.01)
  lo, hi = np.asarray(sig.lo), np.asarray(sig.hi)  # [37, 4]
  got = adaptive.choose_windows(lo=lo, hi=hi, window=window, num_samples=s)
  chex.assert_shape([got.start, got.overflow], (n_pix,))
  start, overflow = np.asarray(got.start), np.asarray(got.overflow)
  for p in range(n_pix):
    assert (start[p], overflow[p]) == _brute_window(lo[p], hi[p], window, s), p
    assert 0 <= start[p] <= s - window
    nonempty = hi[p] > lo[p]
    if overflow[p] == 0:  # coverage: every proposal's (1 − ε) range inside the window
      assert np.all(start[p] <= lo[p][nonempty]) and np.all(hi[p][nonempty] <= start[p] + window)
    else:  # the front of the hull is kept
      assert start[p] == min(lo[p][nonempty].min(), s - window)


def test_proposal_raster_encloses_every_pixel():
  h, w, stride = 29, 31, 4
  raster = adaptive.proposal_raster(height=h, width=w, stride=stride)
  assert np.array_equal(adaptive.proposal_lines(h, stride), [0, 4, 8, 12, 16, 20, 24, 28])
  assert np.array_equal(adaptive.proposal_lines(w, stride), [0, 4, 8, 12, 16, 20, 24, 28, 30])
  assert len(raster.proposals) + len(raster.others) == h * w
  assert not set(raster.proposals) & set(raster.others)
  py, px = np.divmod(raster.proposals[raster.corners], w)  # [n2, 4] corner pixel coordinates
  y, x = np.divmod(raster.others, w)
  # The corners bound the pixel, within one stride, in both axes.
  assert np.all(py[:, :2] <= y[:, None]) and np.all(py[:, 2:] >= y[:, None])
  assert np.all(px[:, ::2] <= x[:, None]) and np.all(px[:, 1::2] >= x[:, None])
  assert np.all(py[:, 2:] - py[:, :2] <= stride) and np.all(px[:, 1::2] - px[:, ::2] <= stride)


# ---------------------------------------------------------------------------------------------
# 4. volume_render's last δ
# ---------------------------------------------------------------------------------------------


def test_volume_render_last_delta_default_and_window():
  rng = np.random.default_rng(3)
  b, r, s, k, wn = 2, 7, 13, 5, 5
  z = np.broadcast_to(np.float32(NEAR + (FAR - NEAR) / s * np.arange(s)), (b, r, s))
  start = rng.integers(0, s - wn + 1, size=(b, r))
  start[0, 0], start[0, 1] = 0, s - wn  # both grid ends
  inside = (np.arange(s) >= start[..., None]) & (np.arange(s) < start[..., None] + wn)
  # Semi-transparent (optical depth ~0.2 a sample), so the last sample of a window matters.
  density = np.where(inside, rng.exponential(0.05, size=(b, r, s)), 0.0).astype(np.float32)
  colour = rng.uniform(size=(b, r, s, 3)).astype(np.float32)
  slot_w = rng.dirichlet(np.ones(k + 1), size=(b, r, s)).astype(np.float32)
  full = volume.volume_render(density=density, z=z, colour=colour, slot_weights=slot_w,
                              far=FAR, density_scale=SCALE)
  # Default unchanged: None and an explicit zero last δ are the old function.
  for last in (None, np.zeros((b, r), np.float32)):
    same = volume.volume_render(density=density, z=z, colour=colour, slot_weights=slot_w,
                                far=FAR, density_scale=SCALE, last_delta=last)
    for a, c in zip(jax.tree.leaves(full), jax.tree.leaves(same)):
      np.testing.assert_array_equal(a, c)

  take = lambda x: np.take_along_axis(x, (start[..., None] + np.arange(wn)).reshape(
      (b, r, wn) + (1,) * (x.ndim - 3)), axis=2)
  win = adaptive.window_depths(z_grid=jnp.asarray(z), start=jnp.asarray(start), window=wn)
  np.testing.assert_array_equal(win.z, take(z))
  expect_delta = np.where(start + wn < s, (FAR - NEAR) / s, 0.0)
  np.testing.assert_allclose(win.last_delta, expect_delta, rtol=1e-5)
  part = volume.volume_render(density=take(density), z=win.z, colour=take(colour),
                              slot_weights=take(slot_w), far=FAR, density_scale=SCALE,
                              last_delta=win.last_delta)
  for name in ("colour", "depth", "segmentation", "opacity"):
    np.testing.assert_allclose(getattr(part, name), getattr(full, name), atol=1e-6, err_msg=name)
  np.testing.assert_allclose(part.weights, take(np.asarray(full.weights)), atol=1e-6)
  # Without the grid δ the window's last sample would be transparent: the argument matters.
  wrong = volume.volume_render(density=take(density), z=win.z, colour=take(colour),
                               slot_weights=take(slot_w), far=FAR, density_scale=SCALE)
  assert np.abs(np.asarray(wrong.opacity) - np.asarray(full.opacity)).max() > 1e-2


# ---------------------------------------------------------------------------------------------
# 3. Windowed compositing of an analytic field
# ---------------------------------------------------------------------------------------------

SPHERE_RADIUS, SHELL_WIDTH, SHELL_DENSITY = 0.45, 0.04, 4.0


def _shell_field(origins, directions, z, last_delta):
  """A per-sample-independent field: density a narrow Gaussian shell around a sphere at the
  origin, colour and 4 slot weights smooth functions of position."""
  p = origins[..., None, :] + directions[..., None, :] * z[..., :, None]  # [B, R, S', 3]
  radius = jnp.linalg.norm(p, axis=-1)
  density = SHELL_DENSITY * jnp.exp(-0.5 * ((radius - SPHERE_RADIUS) / SHELL_WIDTH) ** 2)
  colour = 0.5 + 0.5 * jnp.sin(3.0 * p + jnp.array([0.0, 1.0, 2.0]))
  slot_w = jax.nn.softmax(4.0 * jnp.concatenate([p, jnp.zeros_like(p[..., :1])], -1), -1)
  out = volume.volume_render(density=density, z=z, colour=colour, slot_weights=slot_w, far=FAR,
                             density_scale=SCALE, last_delta=last_delta)
  return (out.colour, out.depth, out.segmentation), out.weights


def _shell_view(*, fallback, window=13, stride=4, eps=0.01, s=41, h=29, w=31):
  grid = adaptive.SampleGrid(near=NEAR, far=FAR, num_samples=s)
  settings = adaptive.AdaptiveSettings(stride=stride, window=window, mass_eps=eps,
                                       fallback=fallback, num_samples=s, chunk=1024)
  proposal_fn = jax.jit(lambda o, d: adaptive.proposal_pass(
      _shell_field, origins=o, directions=d, grid=grid, mass_eps=eps))
  window_fn = jax.jit(lambda o, d, i0: adaptive.window_pass(
      _shell_field, origins=o, directions=d, start=i0, grid=grid, window=window))
  c2w = orbit_pose(30.0, radius=12.4 / 7.0).astype(np.float32)
  k = np.array([[0.8 * w, 0, (w - 1) / 2], [0, 0.8 * w, (h - 1) / 2], [0, 0, 1]], np.float32)
  origins, directions = adaptive.camera_rays(cam_to_world=c2w, intrinsics=k, height=h, width=w)
  outputs, diag = adaptive.render_view(proposal_fn=proposal_fn, window_fn=window_fn,
                                       origins=origins, directions=directions, height=h,
                                       width=w, settings=settings)
  # The plain path: every pixel on the whole grid, through the same compiled proposal function.
  chunk = adaptive.balanced_chunk(len(adaptive.proposal_raster(
      height=h, width=w, stride=stride).proposals), settings.chunk)
  plain = adaptive.run_chunks(proposal_fn, [origins, directions], chunk)[:3]
  return outputs, plain, diag


@pytest.mark.parametrize("fallback", [True, False])
def test_windowed_compositing_matches_the_whole_grid(fallback):
  (colour, depth, seg), (p_colour, p_depth, p_seg), diag = _shell_view(fallback=fallback)
  h, w = diag.proposal.shape
  chex.assert_shape([colour, p_colour], (h * w, 3))
  prop = diag.proposal.reshape(-1)
  # The scene is non-trivial: the sphere fills part of the view, some windows overflow.
  hit = np.asarray(p_depth) < FAR - 0.1
  assert 0.2 < hit.mean() < 0.8
  assert diag.overflow_fraction > 0.0
  # A small view where the silhouette is a large share (23 % overflow): still < 2/3 of the work.
  assert diag.work_fraction < (0.65 if fallback else 0.4)
  # Pass 1 pixels are the plain path's, bit for bit (same compiled function and chunk shape);
  # the fallback's are the same function at another chunk shape, equal to float rounding.
  fell_back = diag.fallback.reshape(-1)
  assert fell_back.any() == fallback
  for a, c in ((colour, p_colour), (depth, p_depth), (seg, p_seg)):
    np.testing.assert_array_equal(a[prop], np.asarray(c)[prop])
    np.testing.assert_allclose(a[fell_back], np.asarray(c)[fell_back], rtol=1e-5, atol=1e-6)
  # Windowed pixels: the shell is opaque (peak α ≈ 1) and smooth, so the neighbours' ranges hold
  # the pixel's weight up to ~ε = 0.01. Measured: max colour error 9.5e-3, depth 1.4e-2 (both
  # with and without the fallback: the front window of an overflowing rim pixel holds its front
  # surface).
  err = np.abs(colour - np.asarray(p_colour)).max(-1)
  assert err.max() < 0.02 and err.mean() < 1e-3
  np.testing.assert_allclose(depth, p_depth, atol=0.03)
  # Segmentation where there is something to segment (transparent pixels normalise ~0 masses).
  same = np.argmax(seg, -1) == np.argmax(np.asarray(p_seg), -1)
  assert same[hit].all()


# ---------------------------------------------------------------------------------------------
# 2. The model's adaptive renderer against SceneRenderer
# ---------------------------------------------------------------------------------------------

H, W = 29, 31


@pytest.fixture(scope="module")
def smoke_model():
  """The smoke config (8 samples) at 29×31, random init, and a scene of three orbit views."""
  config = load_config()
  config.data.image_size = H
  rng = np.random.default_rng(4)
  c2w = np.stack([orbit_pose(a) for a in (10.0, 130.0, 250.0)]).astype(np.float32)
  c2w[:, :3, 3] *= 1.0 / 7.0  # the normalised scene frame
  k = np.array([[1.09375 * W, 0, (W - 1) / 2], [0, 1.458333 * H, (H - 1) / 2], [0, 0, 1]],
               np.float32)
  scene = Scene(name="smoke", images=rng.uniform(size=(3, H, W, 3)).astype(np.float32),
                cam_to_world=c2w, intrinsics=np.repeat(k[None], 3, 0), source_indices=(0,))
  model = model_lib.build_model(config)
  inputs = step_lib.init_batch(scene)
  inputs.pop("target_rgb")
  params = jax.jit(lambda: model.init(jax.random.key(0), **inputs, train=False))()["params"]
  plain = views_lib.SceneRenderer(model, config).render(params, scene, [0, 1, 2])
  return config, model, params, scene, plain


def _adaptive(config, **render_overrides):
  config = config.copy_and_resolve_references()
  config.render.adaptive = True
  for key, value in render_overrides.items():
    config.render[key] = value
  return config


def test_whole_grid_window_equals_the_plain_renderer(smoke_model):
  config, model, params, scene, plain = smoke_model
  s = config.render.num_samples
  cfg = _adaptive(config, adaptive_window=s, adaptive_stride=3)
  renderer = adaptive.make_scene_renderer(model, cfg)
  assert isinstance(renderer, adaptive.AdaptiveSceneRenderer)
  got, diags = renderer.render_with_diagnostics(params, scene, [0, 1, 2])
  chex.assert_shape(got.colour, (3, H, W, 3))
  for name in ("colour", "depth", "segmentation", "slots"):
    np.testing.assert_allclose(getattr(got, name), getattr(plain, name), atol=1e-5, err_msg=name)
  np.testing.assert_array_equal(got.source_labels, plain.source_labels)
  for d in diags:
    assert d.overflow_fraction == 0.0 and not d.fallback.any()
    assert (d.window_start[~d.proposal] == 0).all()  # W = S: the only window
  # The plain renderer's result type and call, also through `render`.
  same = renderer.render(params, scene, [1])
  np.testing.assert_array_equal(same.colour[0], got.colour[1])


def test_source_labels_are_the_slot_attention_of_the_source_view(smoke_model):
  _, _, _, scene, plain = smoke_model
  chex.assert_shape(plain.source_labels, (1, H, W))
  h, w = (H + 3) // 4, (W + 3) // 4  # the encoder's stride 4, odd sizes rounded up
  assert plain.slot_attn.shape[1] == h * w
  cells = plain.slot_attn.reshape(-1, h, w).argmax(0)  # [h, w]
  # The corners map to the corner cells (align-corners), and every label is a cell's argmax.
  assert plain.source_labels[0, 0, 0] == cells[0, 0]
  assert plain.source_labels[0, -1, -1] == cells[-1, -1]
  assert set(np.unique(plain.source_labels)) <= set(np.unique(cells))


def test_fallback_renders_overflowing_pixels_on_the_whole_grid(smoke_model):
  """ε = 0 on a random-init model (density spread along the rays): many ranges overflow a 2-sample
  window; those pixels go through pass 3 and equal the plain path, as do the proposals."""
  config, model, params, scene, plain = smoke_model
  cfg = _adaptive(config, adaptive_window=2, adaptive_stride=4, adaptive_mass_eps=0.0)
  got, diags = adaptive.AdaptiveSceneRenderer(model, cfg).render_with_diagnostics(
      params, scene, [2])
  d = diags[0]
  assert d.fallback.any() and not (d.fallback & d.proposal).any()
  assert np.array_equal(d.fallback, d.overflow > 0)
  exact = d.proposal | d.fallback
  for name in ("colour", "depth", "segmentation"):
    np.testing.assert_allclose(getattr(got, name)[0][exact], getattr(plain, name)[2][exact],
                               atol=1e-5, err_msg=name)


def test_adaptive_refuses_fine_pass_and_bad_settings(smoke_model):
  config, model, params, scene, _ = smoke_model
  fine = _adaptive(config)
  fine.render.num_fine_samples = 4
  with pytest.raises(ValueError, match="fine pass"):
    adaptive.AdaptiveSceneRenderer(model_lib.build_model(fine), fine)
  with pytest.raises(ValueError, match="fine pass"):
    model_lib.build_model(fine).apply(
        {"params": params}, None, source_images=None, source_cam_to_world=None,
        source_intrinsics=None, ray_origins=None, ray_directions=None, z=None,
        method=model_lib.SlotLifter.render_at_depths)
  with pytest.raises(ValueError, match="adaptive_window"):
    adaptive.AdaptiveSceneRenderer(model, _adaptive(config, adaptive_window=99))
  assert isinstance(adaptive.make_scene_renderer(model, config), views_lib.SceneRenderer)


def test_pictures_slot_renderer_switches_to_adaptive(smoke_model):
  """The render mode's SlotRenderer with render.adaptive and W = S: the plain panel outputs,
  per-slot renderings included."""
  from slotlifter_jax.rendering import pictures
  config, model, params, scene, _ = smoke_model
  cams, intr = scene.cam_to_world[1:], scene.intrinsics[1:]
  plain = pictures.SlotRenderer(model, config).render(params, scene, cam_to_world=cams,
                                                      intrinsics=intr)
  cfg = _adaptive(config, adaptive_window=config.render.num_samples, adaptive_stride=5)
  renderer = pictures.SlotRenderer(model, cfg)
  assert renderer.adaptive is not None
  got = renderer.render(params, scene, cam_to_world=cams, intrinsics=intr)
  for name in ("colour", "depth", "segmentation", "slot_colour"):
    np.testing.assert_allclose(getattr(got, name), getattr(plain, name), atol=1e-5, err_msg=name)
