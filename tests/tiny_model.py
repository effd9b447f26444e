"""A tiny SlotLifter and its inputs, shared by the model's test files (test_model.py,
test_model_options.py): the same shapes and keys in both, and each configuration initialised once
per process (compilation dominates their run time)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from random_cameras import random_cameras

from slotlifter_jax import model as model_lib

B, H, W, R, S, K = 2, 20, 28, 11, 7, 5
D = 13
STREAMS = ("dropout", "noise", "sample", "mask")
# The model is indifferent to the key implementation; 'rbg' keys compile several times faster than
# threefry on XLA:CPU (initialising the tiny model: ~7 s instead of ~32 s), which keeps the
# model's test files fast.
KEY_IMPL = "rbg"
# Compilation dominates these files' run time and the programs are tiny: skip XLA's backend
# optimisations (about half the compile time) for the jitted calls made here.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


def tiny(**kw):
  args = dict(feature_dim=D, encoder_stem_width=8, encoder_widths=(8, 12, 16),
              encoder_blocks=(1, 1, 1), num_slots=K, slot_dim=24, slot_mlp_dim=32, point_dim=16,
              num_blocks=2, ffn_dim=24, self_attn_dim=8, colour_hidden=16, num_samples=S,
              near=1.0, far=3.0)
  args.update(kw)
  return model_lib.SlotLifter(**args)


def make_inputs(num_views, seed=0, num_rays=R):
  """Source views around the origin and rays from another camera through points near the origin."""
  rng = np.random.default_rng(seed)
  cams, ks = random_cameras(rng, B * (num_views + 1), H, W)
  cams = cams.reshape(B, num_views + 1, 4, 4)
  ks = ks.reshape(B, num_views + 1, 3, 3)
  origins = np.broadcast_to(cams[:, -1, None, :3, 3], (B, num_rays, 3))
  targets = rng.uniform(-0.5, 0.5, size=(B, num_rays, 3))
  dirs = targets - origins
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return dict(source_images=f32(rng.uniform(0, 1, size=(B, num_views, H, W, 3))),
              source_cam_to_world=f32(cams[:, :num_views]),
              source_intrinsics=f32(ks[:, :num_views]),
              ray_origins=f32(origins), ray_directions=f32(dirs))


def key(seed):
  return jax.random.key(seed, impl=KEY_IMPL)


def rngs(seed):
  return {s: jax.random.fold_in(key(seed), i) for i, s in enumerate(STREAMS)}


def init(model, inputs):
  return jit(lambda: model.init(key(0), **inputs, train=False))()


def sources(inputs):
  return {k: v for k, v in inputs.items() if k.startswith("source_")}


# Two tiny configurations cover V = 1 and V = 2, with and without a fine pass.
CONFIGS = {"v1": dict(num_views=1, num_fine=0), "v2_fine": dict(num_views=2, num_fine=5)}


@functools.lru_cache(maxsize=None)
def setup(name):
  cfg = CONFIGS[name]
  model = tiny(num_fine_samples=cfg["num_fine"])
  inputs = make_inputs(cfg["num_views"])
  return model, inputs, init(model, inputs)
