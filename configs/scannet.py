"""ScanNet (NerfingMVS test split): 480×640 frames, 4 nearest source views, coarse + fine passes.

Paper settings (docs/method.md §1–3): K = 8, D = 32, 64 + 64 samples, near/far [0.1, 10.0] metres,
colours in [−1, 1], no locality constraint; 1 target view × 1024 rays per step. Reference: PSNR
28.36 (docs/method.md §5).
Run: python -m slotlifter_jax.main --config=configs/scannet.py --config.data.root=/path/to/scannet --workdir=DIR
"""

from slotlifter_jax import defaults


def get_config(variant: str = ""):
  c = defaults.base_config()
  c.data.format = "scannet"
  c.data.subset = ""
  c.data.image_size = 0  # as on disk (480×640)
  c.data.num_source_views = 4
  c.data.num_val_scenes = 10  # held out of the training scenes
  c.data.scene_scale = 1.0
  c.model.num_slots = 8
  c.model.feature_dim = 32
  c.model.colour_range = "signed"
  c.render.near, c.render.far = 0.1, 10.0
  c.render.num_samples = 64
  c.render.num_fine_samples = 64
  c.train.batch_scenes = 1
  c.train.grad_accum_chunks = 1
  c.train.locality_steps = 0
  return defaults.apply_variant(c, variant)
