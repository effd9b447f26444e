"""Tests for `model.locality_attention`: source-view cells whose ray never enters the locality box go
to slot attention's first slot only (docs/method.md §1.4)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import geometry
from slotlifter_jax import model as model_lib
from slotlifter_jax import slot_attention as sa

jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


def _key(seed):
  return jax.random.key(seed, impl="rbg")


def _marched_misses(origins, dirs, near, far, half, num=100_001):
  """Brute force: does any of `num` points on each segment [near, far] lie in the closed cube?"""
  t = np.linspace(near, far, num)
  points = origins[:, None] + t[None, :, None] * dirs[:, None]  # [n, num, 3]
  return ~np.any(np.all(np.abs(points) <= half, axis=-1), axis=-1)


def test_ray_misses_box_against_a_dense_march_and_hand_cases():
  half, near, far = 0.64, 0.5, 4.0
  rng = np.random.default_rng(0)
  n = 96
  origins = rng.uniform(-2.5, 2.5, size=(n, 3))
  dirs = rng.normal(size=(n, 3))
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
  got = np.asarray(geometry.ray_misses_box(origins=jnp.asarray(origins, jnp.float32),
                                           directions=jnp.asarray(dirs, jnp.float32),
                                           near=near, far=far, half_size=half))
  want = _marched_misses(origins, dirs, near, far, half)
  # A march can only miss a grazing hit, so a disagreement must be one the exact test calls a hit
  # while the march saw none; with 100 001 points none of these random rays grazes.
  np.testing.assert_array_equal(got, want)
  assert want.any() and (~want).any()

  # Hand cases, directions along an axis (two components exactly 0: the parallel-slab branch).
  o = jnp.asarray([[-3.0, 0.0, 0.0],   # straight through the centre: hits
                   [-3.0, 0.7, 0.0],   # parallel to x, outside the y slab: misses
                   [-3.0, 0.64, 0.0],  # on the face y = 0.64 (closed cube): hits
                   [-3.0, 0.0, 0.0]])  # through the centre but stops before the box
  d = jnp.asarray([[1.0, 0.0, 0.0]] * 4)
  fars = jnp.asarray([4.0, 4.0, 4.0, 2.3])  # the box starts at t = 3 − 0.64 = 2.36
  got = geometry.ray_misses_box(origins=o, directions=d, near=0.0, far=fars, half_size=half)
  np.testing.assert_array_equal(np.asarray(got), [False, True, False, True])


def test_background_only_inputs_go_to_the_first_slot_in_every_iteration():
  b, n, d, k = 2, 19, 7, 4
  rng = np.random.default_rng(1)
  logits = jnp.asarray(rng.normal(size=(b, k, n)) * 3, jnp.float32)
  only = jnp.asarray(rng.uniform(size=(b, n)) < 0.4)
  masked = sa.background_only_logits(logits, only)
  attn = np.asarray(jax.nn.softmax(masked, axis=1))
  sel = np.asarray(only)
  np.testing.assert_array_equal(attn[:, 0][sel], 1.0)
  np.testing.assert_array_equal(attn[:, 1:].transpose(0, 2, 1)[sel], 0.0)
  # Elsewhere the logits are untouched, for every slot including the first.
  np.testing.assert_array_equal(np.asarray(masked).transpose(0, 2, 1)[~sel],
                                np.asarray(logits).transpose(0, 2, 1)[~sel])

  module = sa.SlotAttention(num_slots=k, slot_dim=16, mlp_dim=32)
  inputs = jax.random.normal(_key(0), (b, n, d))
  params = jit(module.init)(_key(1), inputs)
  free = jit(lambda p, x: module.apply(p, x))(params, inputs)
  held = jit(lambda p, x, m: module.apply(p, x, background_only=m))(params, inputs, only)
  np.testing.assert_array_equal(np.asarray(held.attn)[:, 0][sel], 1.0)
  assert np.asarray(free.attn)[:, 0][sel].max() < 0.99
  # The held inputs change the first slot's update, so the slots differ.
  assert np.abs(np.asarray(held.slots) - np.asarray(free.slots)).max() > 1e-3


def _look_down_camera(height):
  """OpenCV camera at (0, 0, height) looking straight down (camera z = world −z)."""
  c2w = np.eye(4)
  c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])
  c2w[:3, 3] = [0.0, 0.0, height]
  return c2w


def test_background_cells_are_the_cells_whose_sampled_segment_misses_the_box():
  """A camera 3 above the box's centre: its centre cells see the box, its corners only the floor
  outside it. Each cell's ray is built here from K⁻¹ and the pose and marched in NumPy."""
  image, feat, near, far = (20, 28), (5, 7), 1.0, 6.0
  model = model_lib.SlotLifter(
      feature_dim=5, encoder_stem_width=8, encoder_widths=(8, 8, 8), encoder_blocks=(1, 1, 1),
      num_slots=3, slot_dim=8, slot_mlp_dim=8, point_dim=8, num_blocks=1, ffn_dim=8,
      self_attn_dim=8, colour_hidden=8, num_samples=4, near=near, far=far,
      locality_attention=True)
  c2w = _look_down_camera(3.0)
  focal = 9.0
  intr = np.array([[focal, 0, (image[1] - 1) / 2], [0, focal, (image[0] - 1) / 2], [0, 0, 1.0]])
  cells = model.apply({}, source_cam_to_world=jnp.asarray(c2w[None, None], jnp.float32),
                      source_intrinsics=jnp.asarray(intr[None, None], jnp.float32),
                      image_size=image, feature_size=feat, method=model.background_cells)
  assert cells.shape == (1, 1) + feat
  want = np.zeros(feat, bool)
  for i in range(feat[0]):
    for j in range(feat[1]):
      u, v = j * (image[1] - 1) / (feat[1] - 1), i * (image[0] - 1) / (feat[0] - 1)
      d_cam = np.array([(u - intr[0, 2]) / focal, (v - intr[1, 2]) / focal, 1.0])
      d = c2w[:3, :3] @ d_cam
      d /= np.linalg.norm(d)
      want[i, j] = _marched_misses(c2w[None, :3, 3], d[None], near, far, 0.64)[0]
  np.testing.assert_array_equal(np.asarray(cells[0, 0]), want)
  assert want.any() and (~want).any() and not want[feat[0] // 2, feat[1] // 2]


@pytest.mark.parametrize("locality", [True, False])
def test_encode_gives_background_cells_to_the_first_slot_while_locality_holds(locality):
  image, near, far = (16, 16), 1.0, 6.0
  model = model_lib.SlotLifter(
      feature_dim=5, encoder_stem_width=8, encoder_widths=(8, 8, 8), encoder_blocks=(1, 1, 1),
      num_slots=3, slot_dim=8, slot_mlp_dim=8, point_dim=8, num_blocks=1, ffn_dim=8,
      self_attn_dim=8, colour_hidden=8, num_samples=4, near=near, far=far,
      locality_attention=True)
  c2w = jnp.asarray(_look_down_camera(3.0)[None, None], jnp.float32)
  intr = jnp.asarray([[[[12.0, 0, 7.5], [0, 12.0, 7.5], [0, 0, 1]]]], jnp.float32)
  images = jax.random.uniform(_key(2), (1, 1) + image + (3,))
  sources = dict(source_images=images, source_cam_to_world=c2w, source_intrinsics=intr)
  variables = jit(lambda: model.init(_key(0), **sources, train=False, method=model.encode))()
  encoded = jit(lambda loc: model.apply(variables, **sources, locality=loc, train=False,
                                        method=model.encode))(locality)
  cells = model.apply({}, source_cam_to_world=c2w, source_intrinsics=intr, image_size=image,
                      feature_size=encoded.features.shape[2:4], method=model.background_cells)
  sel = np.asarray(cells).reshape(-1)
  assert sel.any() and (~sel).any()
  first = np.asarray(encoded.slot_attn)[0, 0]  # [V·h·w]
  if locality:
    np.testing.assert_array_equal(first[sel], 1.0)
  else:
    assert first[sel].max() < 0.99


def test_the_config_switch_reaches_the_model_and_is_off_by_default():
  from slotlifter_jax import defaults
  config = defaults.base_config()
  assert model_lib.build_model(config).locality_attention is False
  config.model.locality_attention = True
  assert model_lib.build_model(config).locality_attention is True


def test_attention_locality_starts_at_its_step_and_ends_with_the_constraint():
  from slotlifter_jax import schedules
  on = lambda t: bool(schedules.attention_locality_on(t, locality_steps=20_000, start=6000))
  assert [on(t) for t in (0, 5999, 6000, 19_999, 20_000)] == [False, False, True, True, False]
  assert bool(schedules.attention_locality_on(0, locality_steps=20_000, start=0))
  assert not bool(schedules.attention_locality_on(0, locality_steps=0, start=0))


def test_the_train_step_hands_slot_attention_its_own_switch():
  """The gradient function's loss with the locality constraint on in the decoder: slot attention
  held (`attention_locality` on) differs from free, and free equals a model without
  `locality_attention`, so the switch reaches slot attention and nothing else."""
  from slotlifter_jax import defaults
  from slotlifter_jax import schedules
  from slotlifter_jax import train_step as step_lib
  config = defaults.base_config()
  defaults.smoke(config)
  config.model.locality_attention = True
  s, b, r = config.data.image_size, 1, 16
  c2w = _look_down_camera(3.0).astype(np.float32)
  intr = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]], np.float32)
  rng = np.random.default_rng(3)
  dirs = rng.normal(size=(b, r, 3)) * [0.2, 0.2, 0.0] + [0, 0, -1]
  batch = dict(
      source_images=rng.uniform(size=(b, 1, s, s, 3)).astype(np.float32),
      source_cam_to_world=np.broadcast_to(c2w, (b, 1, 4, 4)).copy(),
      source_intrinsics=np.broadcast_to(intr, (b, 1, 3, 3)).copy(),
      ray_origins=np.broadcast_to(c2w[:3, 3], (b, r, 3)).astype(np.float32).copy(),
      ray_directions=(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).astype(np.float32),
      target_rgb=rng.uniform(size=(b, r, 3)).astype(np.float32))
  held_model = model_lib.build_model(config)
  config.model.locality_attention = False
  plain_model = model_lib.build_model(config)
  cells = held_model.apply({}, source_cam_to_world=jnp.asarray(batch["source_cam_to_world"]),
                           source_intrinsics=jnp.asarray(batch["source_intrinsics"]),
                           image_size=(s, s), feature_size=(s // 4, s // 4),
                           method=held_model.background_cells)
  assert np.asarray(cells).any()
  params = step_lib.init_state(held_model, config, batch, _key(0)).params
  sched = dict(schedules.all_schedules(0, config.train), locality=jnp.asarray(True))
  loss = lambda model, held: float(jit(step_lib.make_grad_fn(model, config))(
      params, batch, _key(1), dict(sched, attention_locality=jnp.asarray(held)))[0][0])
  free = loss(held_model, False)
  # Equal up to float32 rounding: the two models compile to different programs.
  np.testing.assert_allclose(free, loss(plain_model, False), rtol=1e-6)
  assert abs(loss(held_model, True) - free) > 1e-4 * free
