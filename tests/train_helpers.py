"""What the training tests share: the smoke config, a batch of the pipeline's shapes, and the
parameters a run folder's last checkpoint holds. Not a test module: tests/test_*.py import it (and
so do subprocesses that put tests/ on sys.path)."""

import importlib.util
import os

import jax
import numpy as np

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import model as model_lib
from slotlifter_jax import train_step as step_lib

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_config(name="clevr", variant="smoke"):
  spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, "configs", f"{name}.py"))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


def fake_batch(config, *, seed=0, num_scenes=None):
  """A batch of the pipeline's shapes whose rays hit the region the source camera sees."""
  rng = np.random.default_rng(seed)
  b = num_scenes or config.train.batch_scenes
  v, r, s = config.data.num_source_views, config.train.rays_per_scene, config.data.image_size
  cam = np.eye(4, dtype=np.float32)
  cam[:3, 3] = [0.0, 0.0, -1.8]  # looking down +z at the origin
  intr = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]], np.float32)
  dirs = rng.normal(size=(b, r, 3)).astype(np.float32) * [0.2, 0.2, 0.0] + [0, 0, 1]
  return dict(
      source_images=rng.uniform(size=(b, v, s, s, 3)).astype(np.float32),
      source_cam_to_world=np.broadcast_to(cam, (b, v, 4, 4)).copy(),
      source_intrinsics=np.broadcast_to(intr, (b, v, 3, 3)).copy(),
      ray_origins=np.broadcast_to(cam[:3, 3], (b, r, 3)).astype(np.float32).copy(),
      ray_directions=(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).astype(np.float32),
      target_rgb=rng.uniform(size=(b, r, 3)).astype(np.float32),
  )


def final_params(workdir, config):
  model = model_lib.build_model(config)
  device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  abstract = step_lib.state_shapes(model, config, fake_batch(config), sharding=device)
  manager = ckpt_lib.Checkpoints(workdir)
  state = manager.restore(abstract)
  manager.close()
  return int(state.step), state.params


def load_config_with(config):
  return config.copy_and_resolve_references()
