"""Share of training rays that land on objects, per ray-sampling mode (data/pipeline.py).

  python experiments/ray_foreground_share.py [--config=configs/clevr.py:quick] [--scenes=20]

Draws 50 training batches from the validation scenes (they have ground-truth masks; the sampler
never looks at them) and prints the fraction of rays whose pixel is foreground, for uniform
sampling and contrast sampling at a few mixes, next to the foreground share of the pixels.
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


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/clevr.py:quick")
  parser.add_argument("--scenes", type=int, default=20)
  parser.add_argument("--batches", type=int, default=50)
  args = parser.parse_args()
  config = embedded.resolve_data(study_common.load_config(args.config))
  scenes = registry.load_split(config.data, "val", max_scenes=args.scenes)
  print(f"{len(scenes)} val scenes of {config.data.root}: foreground share of pixels "
        f"{np.mean([(s.masks > 0).mean() for s in scenes]):.3f}")
  for mode, mix in [("uniform", 0.0), ("contrast", 0.5), ("contrast", 0.8)]:
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
    print(f"ray_sampling={mode:8s} contrast_mix={mix:.1f}: foreground share of rays "
          f"{np.mean(shares):.3f}")


if __name__ == "__main__":
  main()
