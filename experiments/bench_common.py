"""The benchmark configurations and batches shared by bench.py and profile_step.py (no flags, no
JAX import at module level)."""

from __future__ import annotations

import os
import sys

# The CPU's model and vector extensions, which every benchmark records (slotlifter_jax/provenance.py).
from slotlifter_jax.provenance import CPU_EXTENSIONS, cpu_info  # noqa: F401

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_SCENE_DEVICE = {"data.sampler": "device", "data.ray_sampling": "uniform"}
CONFIGS = {
    "A": dict(variant="", overrides={"data.image_size": 128, "render.num_samples": 96,
                                     "train.batch_scenes": 2, "train.rays_per_scene": 1024,
                                     "train.grad_accum_chunks": 1}),
    "A_lowmem": dict(variant="", overrides={"data.image_size": 128, "render.num_samples": 96,
                                            "train.batch_scenes": 2, "train.rays_per_scene": 1024,
                                            "model.remat_scan": True, "train.grad_accum_chunks": 2,
                                            "train.ray_chunks": 2}),
    "paper_batch": dict(variant="", overrides={"data.image_size": 128, "render.num_samples": 96,
                                               "train.batch_scenes": 4, "train.rays_per_scene": 1024,
                                               "train.grad_accum_chunks": 2}),
    "B": dict(variant="", overrides={"data.image_size": 64, "render.num_samples": 32,
                                     "train.batch_scenes": 2, "train.rays_per_scene": 256,
                                     "train.grad_accum_chunks": 1}),
    "paper_cpu": dict(variant="paper_cpu", overrides={}),
    # The scene-sized model (host batches, one step per dispatch).
    "scene": dict(variant="scene", overrides={}),
    # scene with its batch drawn inside the jitted step (data.sampler=device).
    # (The device sampler draws uniform rays only.)
    "scene_device": dict(variant="scene", overrides=_SCENE_DEVICE),
    # scene_device with 10 steps per dispatch under lax.scan, timed per step (XLA:CPU compiles a
    # loop body's conv gradients poorly: slower, not faster).
    "scene_scan10": dict(variant="scene", overrides={**_SCENE_DEVICE, "train.steps_per_dispatch": 10}),
    # scene with a half-size feature map (model.encoder_output_stride = 2; slotlifter_jax/encoder.py).
    "scene_stride2": dict(variant="scene", overrides={"model.encoder_output_stride": 2}),
    # scene with 8 samples per ray instead of 16 (the pareto grid's `samples8`, experiments/pareto.py).
    "scene_samples8": dict(variant="scene", overrides={"render.num_samples": 8}),
    # paper_cpu and scene with the decoder's products folded (model.fold_products; decoder.py).
    "paper_cpu_fold": dict(variant="paper_cpu", overrides={"model.fold_products": True}),
    "scene_fold": dict(variant="scene", overrides={"model.fold_products": True}),
}


def config(name: str, dtype: str | None = None):
  """The ml_collections config of benchmark configuration `name` (configs/clevr.py + overrides);
  `dtype` sets `model.dtype` ("float32" | "bfloat16", model.py "Numerics"), None keeps the
  configuration's own (float32)."""
  sys.path.insert(0, os.path.join(REPO, "configs"))
  import clevr  # configs/clevr.py
  spec = CONFIGS[name]
  config = clevr.get_config(spec["variant"])
  for path, value in spec["overrides"].items():
    section, field = path.split(".")
    config[section][field] = value
  if dtype is not None:
    config.model.dtype = dtype
  config.train.log_every = 10**9
  return config


def scenes(n: int, image_size: int, seed: int):
  """n generated clevr scenes in the normalised scene frame (as the reader would return them)."""
  import numpy as np
  from slotlifter_jax.data import generator
  from slotlifter_jax.data.types import Scene
  scale = 1.0 / 7.0
  scenes = []
  for i in range(n):
    g = generator.generate_scene(np.random.default_rng([seed, i]), family="clevr", views=4,
                                 image_size=image_size)
    c2w = g.cam_to_world.astype(np.float32).copy()
    c2w[:, :3, 3] *= scale
    scenes.append(Scene(name=f"bench{i}", images=g.rgb.astype(np.float32) / 255.0,
                        cam_to_world=c2w, intrinsics=np.repeat(g.intrinsics[None], 4, 0).astype(np.float32),
                        source_indices=(0,)))
  return scenes


def setup_step(name: str, num_batches: int, train_scenes=None, dtype: str | None = None):
  """Everything `slotlifter_jax.train` builds for a step, for configuration `name` (with
  `model.dtype = dtype` unless None).

  Returns (config, model, state, batches, train_step): `num_batches` batches already on the mesh
  (rays of `train_scenes`, default freshly generated ones), the replicated initial state and the
  jitted, state-donating step. For a configuration with `data.sampler = "device"`, `train_step`
  is the jitted block of `train.steps_per_dispatch` steps and every entry of `batches` is the
  device-resident training split it draws from.
  """
  import jax
  from slotlifter_jax import model as model_lib
  from slotlifter_jax import train_step as step_lib
  from slotlifter_jax.data import device_sampler
  from slotlifter_jax.data import pipeline
  cfg = config(name, dtype)
  c = cfg.train
  if train_scenes is None:
    train_scenes = scenes(c.batch_scenes, cfg.data.image_size, seed=0)
  sampler = pipeline.BatchSampler(train_scenes,
                                  batch_scenes=c.batch_scenes, rays_per_scene=c.rays_per_scene,
                                  num_source_views=1, novel_ray_prob=cfg.data.novel_ray_prob, seed=0)
  mesh = step_lib.make_mesh()
  model = model_lib.build_model(cfg)
  key = jax.random.key(cfg.seed, impl=c.prng_impl)
  state = step_lib.init_state(model, cfg, sampler.batch(0), jax.random.fold_in(key, 0))
  replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
  state = jax.device_put(state, replicated)
  if cfg.data.sampler == "device":
    split = jax.device_put(device_sampler.to_device_scenes(train_scenes, num_source_views=1),
                           replicated)
    batches = [split] * num_batches
    train_step = step_lib.make_train_block(
        model, cfg, key=jax.random.fold_in(key, 1), data_key=jax.random.fold_in(key, 2),
        num_steps=int(c.steps_per_dispatch), mesh=mesh)
  else:
    batches = [step_lib.shard_batch(sampler.batch(i), mesh) for i in range(num_batches)]
    train_step = step_lib.make_train_step(model, cfg, key=jax.random.fold_in(key, 1), mesh=mesh)
  return cfg, model, state, batches, train_step


def device_peak_bytes(device) -> int | None:
  """The most bytes `device`'s allocator has held in this process (`peak_bytes_in_use` of
  `Device.memory_stats()`, which GPU and TPU backends keep), or None where the backend keeps no
  such count: XLA:CPU returns no statistics, and the CPU figure is the process's peak RSS."""
  stats = device.memory_stats() if hasattr(device, "memory_stats") else None
  if not stats or stats.get("peak_bytes_in_use") is None:
    return None
  return int(stats["peak_bytes_in_use"])

