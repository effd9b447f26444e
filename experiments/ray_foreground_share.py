"""Share of training rays that land on objects, per ray-sampling mode (data/pipeline.py).

  python experiments/ray_foreground_share.py [--config=configs/clevr.py:paper_cpu] [--scenes=20] \
      [--set=data.room_objects=boxes ...]

Draws 50 training batches from the validation scenes (they have ground-truth masks; the sampler
never looks at them) and prints the fraction of rays whose pixel is foreground, for uniform,
contrast and (sets with a floor at z = 0) floor-parallax sampling at a few mixes, next to the
foreground share of the pixels.
Then, per object and view, how many times more likely contrast sampling (mix 0.5) is to draw one
of the object's pixels than uniform sampling, for grey objects (colour saturation < 0.05, the
ones that look like the grey floor) and coloured ones.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common  # noqa: E402
from slotlifter_jax.data import embedded  # noqa: E402
from slotlifter_jax.data import pipeline  # noqa: E402
from slotlifter_jax.data import registry  # noqa: E402


def object_oversampling(images: np.ndarray, masks: np.ndarray, *, mix: float) -> dict:
  """{"grey": [...], "coloured": [...]}: per object and view, the mean over the object's pixels of
  contrast sampling's probability relative to uniform's 1 / (H·W). An object is grey when its mean
  colour's channels differ by < 0.05. images [N, H, W, 3] in [0, 1], masks [N, H, W] (0 background)."""
  pixels = images.shape[1] * images.shape[2]
  ratio = pixels * pipeline.mix_with_uniform(pipeline.contrast_weights(images), mix)  # [N, H·W]
  labels = masks.reshape(len(images), -1)
  colours = images.reshape(len(images), -1, 3)
  factors = {"grey": [], "coloured": []}
  for view in range(len(images)):
    for obj in np.unique(labels[view][labels[view] > 0]):
      on = labels[view] == obj
      mean_colour = colours[view][on].mean(axis=0)
      kind = "grey" if mean_colour.max() - mean_colour.min() < 0.05 else "coloured"
      factors[kind].append(float(ratio[view][on].mean()))
  return factors


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/clevr.py:paper_cpu")
  parser.add_argument("--scenes", type=int, default=20)
  parser.add_argument("--batches", type=int, default=50)
  parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                      help="a dotted config override, e.g. data.object_scale=0.6 (repeatable)")
  args = parser.parse_args()
  try:
    overrides = study_common.parse_set_overrides(args.set)
    config = study_common.apply_overrides(study_common.load_config(args.config), overrides)
  except study_common.StudyError as e:
    parser.error(str(e))
  config = embedded.resolve_data(config)
  scenes = registry.load_split(config.data, "val", max_scenes=args.scenes)
  print(f"{len(scenes)} val scenes of {config.data.root}: foreground share of pixels "
        f"{np.mean([(s.masks > 0).mean() for s in scenes]):.3f}")
  modes = [("uniform", 0.0), ("contrast", 0.5), ("contrast", 0.8)]
  if config.data.format in ("uorf", "uocf"):  # a floor at z = 0
    modes += [("floor_parallax", 0.5), ("floor_parallax", 0.8)]
  for mode, mix in modes:
    sampler = pipeline.BatchSampler(
        scenes, batch_scenes=config.train.batch_scenes, rays_per_scene=config.train.rays_per_scene,
        num_source_views=config.data.num_source_views, novel_ray_prob=config.data.novel_ray_prob,
        seed=0, ray_sampling=mode, contrast_mix=mix)
    shares = []
    for step in range(args.batches):
      draw = sampler.draw(step)
      for b, s in enumerate(draw.scene_index):
        labels = scenes[s].masks[draw.ray_views[b], draw.ray_rows[b], draw.ray_cols[b]]
        shares.append((labels > 0).mean())
    print(f"ray_sampling={mode:14s} contrast_mix={mix:.1f}: foreground share of rays "
          f"{np.mean(shares):.3f}")
  factors = {"grey": [], "coloured": []}
  for scene in scenes:
    for kind, values in object_oversampling(scene.images, scene.masks, mix=0.5).items():
      factors[kind] += values
  for kind, values in factors.items():
    if not values:
      print(f"contrast_mix=0.5, {kind:8s} objects: none in these scenes")
      continue
    print(f"contrast_mix=0.5, {kind:8s} objects: pixels drawn {np.median(values):.2f}x as often as "
          f"under uniform sampling (median over {len(values)} object views, 10th percentile "
          f"{np.percentile(values, 10):.2f}x)")


if __name__ == "__main__":
  main()
