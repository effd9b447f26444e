"""The device-side batch sampler, the curriculum, and steps run in blocks under lax.scan."""

import importlib.util
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import model as model_lib
from slotlifter_jax import train_step as step_lib
from slotlifter_jax.data import device_sampler
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def make_scenes(n, *, views=4, size=8, num_objects=None, seed=0):
  """Scenes with PNG-like colours (multiples of 1/255) and distinct random cameras."""
  rng = np.random.default_rng(seed)
  scenes = []
  for i in range(n):
    c2w = np.tile(np.eye(4, dtype=np.float32), (views, 1, 1))
    for v in range(views):
      q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
      c2w[v, :3, :3] = q
      c2w[v, :3, 3] = rng.normal(size=3)
    k = np.array([[size, 0.1, size / 2], [0, size * 1.1, size / 2 - 0.5], [0, 0, 1]], np.float32)
    images = rng.integers(0, 256, size=(views, size, size, 3)).astype(np.float32) / 255.0
    objects = None if num_objects is None else [{}] * num_objects[i]
    scenes.append(Scene(name=f"s{i}", images=images, cam_to_world=c2w,
                        intrinsics=np.repeat(k[None], views, 0), source_indices=(i % views,),
                        objects=objects))
  return scenes


DRAW = dict(batch_scenes=3, rays_per_scene=20, novel_ray_prob=0.75)


def test_batch_is_the_drawn_pixels_rays_and_sources():
  scenes = make_scenes(5)
  dev = device_sampler.to_device_scenes(scenes, num_source_views=1)
  assert dev.images.dtype == jnp.uint8  # lossless for PNG-like colours
  for seed in range(4):
    b = device_sampler.debug_draw(dev, jax.random.key(seed), with_draw=True, **DRAW)
    assert len(set(b["scene_index"].tolist())) == 3  # distinct scenes
    for i, s in enumerate(b["scene_index"]):
      scene = scenes[s]
      views, rows, cols = b["ray_views"][i], b["ray_rows"][i], b["ray_cols"][i]
      flat = views * 64 + rows * 8 + cols
      assert len(set(flat.tolist())) == 20  # pixels never repeat within a scene
      if b["novel_only"][i]:
        assert not np.any(views == scene.source_indices[0])
      # uint8 / 255 on the device may differ from NumPy's float32 division by one ulp (XLA may
      # multiply by the reciprocal).
      np.testing.assert_allclose(b["target_rgb"][i], scene.images[views, rows, cols], atol=1e-7)
      # Reference rays: R·K⁻¹[u, v, 1] with a general float64 inverse, normalised.
      c2w = scene.cam_to_world[views].astype(np.float64)  # [R, 4, 4]
      pix_h = np.stack([cols, rows, np.ones_like(cols)], axis=-1).astype(np.float64)  # [R, 3]
      d_cam = np.einsum("rij,rj->ri", np.linalg.inv(scene.intrinsics[views].astype(np.float64)),
                        pix_h)
      d = np.einsum("rij,rj->ri", c2w[:, :3, :3], d_cam)
      d /= np.linalg.norm(d, axis=-1, keepdims=True)
      np.testing.assert_allclose(b["ray_origins"][i], c2w[:, :3, 3], atol=1e-6)
      np.testing.assert_allclose(b["ray_directions"][i], d, atol=1e-5)
      src = list(scene.source_indices)
      np.testing.assert_allclose(b["source_images"][i], scene.images[src], atol=1e-7)
      np.testing.assert_array_equal(b["source_cam_to_world"][i], scene.cam_to_world[src])
      np.testing.assert_array_equal(b["source_intrinsics"][i], scene.intrinsics[src])


def test_draws_follow_the_host_samplers_distribution():
  """Novel-only with probability 0.75, every candidate (view, pixel) equally likely."""
  scenes = make_scenes(4, views=2, size=4)
  dev = device_sampler.to_device_scenes(scenes, num_source_views=1)
  draw = jax.jit(jax.vmap(lambda k: device_sampler.sample_batch(
      dev, k, batch_scenes=4, rays_per_scene=4, novel_ray_prob=0.75, with_draw=True)))
  out = jax.tree.map(np.asarray, draw(jax.random.split(jax.random.key(0), 4000)))
  novel = out["novel_only"].ravel()  # 16 000 Bernoulli(0.75) draws: std of the mean 0.0034
  assert abs(novel.mean() - 0.75) < 0.015
  # Rays of all-view draws: source and novel view equally likely (half each).
  idx = out["scene_index"]
  src = np.array([s.source_indices[0] for s in scenes])[idx]  # [N, B]
  on_source = (out["ray_views"] == src[..., None])[~out["novel_only"]]
  assert abs(on_source.mean() - 0.5) < 0.02
  # The 16 pixels of a view, uniform: chi-square with 15 degrees of freedom, p ≈ 1e-4 bound.
  pix = (out["ray_rows"] * 4 + out["ray_cols"]).ravel()
  counts = np.bincount(pix, minlength=16)
  expected = pix.size / 16
  assert np.sum((counts - expected) ** 2 / expected) < 45.0


def test_curriculum_limits_the_scenes_drawn():
  scenes = make_scenes(6, num_objects=[1, 3, 1, 5, 2, 7])
  dev = device_sampler.to_device_scenes(scenes, num_source_views=1)
  stages = ((0, 1), (100, 3), (200, 7))
  assert [int(device_sampler.curriculum_limit(t, stages)) for t in (0, 99, 100, 250)] == [1, 1, 3, 7]
  assert int(device_sampler.curriculum_limit(5, ())) == np.iinfo(np.int32).max
  counts = np.array([1, 3, 1, 5, 2, 7])
  for limit, allowed in ((1, {0, 2}), (3, {0, 1, 2, 4})):
    seen = set()
    for seed in range(30):
      b = device_sampler.debug_draw(dev, jax.random.key(seed), batch_scenes=2, rays_per_scene=4,
                                    novel_ray_prob=0.5, max_objects=limit)
      seen |= set(b["scene_index"].tolist())
    assert seen == allowed, (limit, seen, counts)
  assert device_sampler.check_curriculum([[0, 1], [100, 3]], scenes) == ((0, 1), (100, 3))
  with pytest.raises(DataError, match="no training scene has at most 0 objects"):
    device_sampler.check_curriculum([[0, 0]], scenes)
  with pytest.raises(ValueError, match="not increasing"):
    device_sampler.check_curriculum([[100, 1], [0, 3]], scenes)


def test_object_count_from_metadata_or_masks():
  scene = make_scenes(1)[0]
  assert device_sampler.scene_object_count(scene) == -1
  masks = np.zeros((4, 8, 8), np.int32)
  masks[0, :2, :2], masks[1, 5:, 5:], masks[2, 0, 7] = 1, 3, 2
  import dataclasses
  assert device_sampler.scene_object_count(dataclasses.replace(scene, masks=masks)) == 3
  assert device_sampler.scene_object_count(dataclasses.replace(scene, objects=[{}, {}])) == 2


def test_device_split_refuses_scenes_it_cannot_draw_from():
  scenes = make_scenes(2)
  import dataclasses
  with pytest.raises(DataError, match="scene s1: pooled sources"):
    device_sampler.to_device_scenes([scenes[0], dataclasses.replace(scenes[1], source_pool=(0, 1))],
                                    num_source_views=1)
  with pytest.raises(DataError, match="scene s0: 1 source views"):
    device_sampler.to_device_scenes(scenes, num_source_views=2)
  resized = dataclasses.replace(scenes[1], images=scenes[1].images * 0.999)
  dev = device_sampler.to_device_scenes([scenes[0], resized], num_source_views=1)
  assert dev.images.dtype == jnp.float32  # not PNG levels: kept exact as float32


def load_smoke():
  spec = importlib.util.spec_from_file_location("clevr", os.path.join(REPO, "configs", "clevr.py"))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  config = module.get_config("smoke")
  config.data.sampler = "device"
  config.data.image_size = 8
  return config


def test_a_block_of_steps_trains_on_the_same_batches_as_single_dispatches():
  """4 steps as one scanned block and as 4 dispatches of the step, from one init.

  The two are not bit-identical: XLA fuses a scanned step differently, and Lion moves a weight by
  ±lr whatever its gradient's size, so a weight whose gradient is ~0 can take the other sign. Such
  flips change the loss only to second order, while another batch, order or key changes it at first
  order (a few per cent here). So every step's loss must agree to 1e-3, and the block must have
  moved the weights (a block that skipped its updates would leave them at the init)."""
  config = load_smoke()
  dev = device_sampler.to_device_scenes(make_scenes(4), num_source_views=1)
  model = model_lib.build_model(config)
  key, data_key = jax.random.key(1), jax.random.key(2)
  draw = dict(batch_scenes=config.train.batch_scenes, rays_per_scene=config.train.rays_per_scene,
              novel_ray_prob=config.data.novel_ray_prob)
  batches = [device_sampler.sample_batch(dev, jax.random.fold_in(data_key, t), **draw)
             for t in range(4)]
  init = step_lib.init_state(model, config, jax.tree.map(np.asarray, batches[0]),
                             jax.random.key(0))
  copy = lambda: jax.tree.map(jnp.copy, init)  # both runs donate their state
  block4 = step_lib.make_train_block(model, config, key=key, data_key=data_key, num_steps=4)
  single = step_lib.make_train_step(model, config, key=key)
  a, metrics = block4(copy(), dev)
  c, losses = copy(), []
  for batch in batches:
    c, m = single(c, batch)
    losses.append(float(m["loss"]))
  assert int(a.step) == int(c.step) == 4
  assert len(set(np.round(losses, 4))) == 4  # four different batches
  np.testing.assert_allclose(np.asarray(metrics["loss"]), losses, rtol=1e-3)
  flat = lambda s: np.concatenate([np.asarray(x).ravel() for x in jax.tree.leaves(s.params)])
  assert (np.abs(flat(a) - flat(init)) > 0.5 * config.train.base_lr).mean() > 0.25
