"""What a perfect one-ray-per-pixel renderer scores against the embedded set's anti-aliased images.

  python experiments/aliasing_ceiling.py [--config=configs/clevr.py:scene] [--scenes=100]
      [--out=experiments/results/aliasing_ceiling_clevr64.json]

The embedded generator colours each pixel with the mean of 2×2 rays inside it (anti-aliasing), as
renderers of the paper's sets do. A model that casts one ray through each pixel's centre can at
best reproduce the true scene along that ray. This script renders the test split's true scenes
again with the generator's own ray caster at one ray per pixel (the same layouts, cameras and
shading; only the pixel footprint differs), takes that as the rendering and scores it with the
evaluation's own code (`evaluate.scene_metrics`, ground-truth masks as the segmentation), so its
novel-view PSNR and region split are the ceiling of the plain renderer on this set and read as
the eval's keys do. It also scores S×S rays per pixel for S = 2 (the set itself: infinite PSNR,
a check that the regenerated scenes are the files on disk) and S = 4, the ceiling of a renderer
that averages 4×4 rays (`render.supersample=4`) against the set's 2×2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import warnings

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common  # noqa: E402
from slotlifter_jax import evaluate  # noqa: E402
from slotlifter_jax.data import embedded  # noqa: E402
from slotlifter_jax.data import registry  # noqa: E402
from slotlifter_jax.data import writer  # noqa: E402
from slotlifter_jax.rendering import views as views_lib  # noqa: E402

KEYS = ("psnr_novel", "psnr_novel_fg", "psnr_novel_bg", "psnr_novel_border", "psnr_novel_bg_far",
        "fg_pixel_share", "fg_error_share", "border_pixel_share", "border_error_share")
DATASET_SUPERSAMPLE = 2  # writer.generate_dataset's default, which the embedded sets use


def _as_rendering(rgb: np.ndarray, labels: np.ndarray, num_slots: int) -> views_lib.RenderedViews:
  """A generator rendering [n, H, W, 3] uint8 as the model's output: the true masks as the
  segmentation, so only the colour is being scored."""
  seg = np.eye(num_slots, dtype=np.float32)[labels]  # [n, H, W, K]
  n, h, w = labels.shape
  return views_lib.RenderedViews(
      colour=rgb.astype(np.float32) / 255.0, depth=np.zeros((n, h, w), np.float32),
      segmentation=seg, slots=np.zeros((num_slots, 1), np.float32),
      slot_attn=np.zeros((num_slots, 1), np.float32),
      source_labels=np.zeros((1, h, w), np.int32))


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/clevr.py:scene")
  parser.add_argument("--scenes", type=int, default=100)
  parser.add_argument("--supersample", default="1,2,4",
                      help="rays per pixel side of the renderings to score (comma-separated)")
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  config = study_common.load_config(args.config)
  if config.data.root:
    raise SystemExit(f"error: --config={args.config}: data.root is set; only the embedded set "
                     f"(data.root empty) can be rendered again")
  config = embedded.resolve_data(config)
  d = config.data
  scenes = registry.load_split(d, "test", max_scenes=args.scenes)
  per_side = [int(s) for s in args.supersample.split(",")]
  objects = dict(min_objects=d.min_objects, max_objects=d.max_objects,
                 object_scale=d.object_scale)
  rows = {s: [] for s in per_side}
  t0 = time.perf_counter()
  for index, scene in enumerate(scenes):
    views = list(range(scene.num_views))
    for s in per_side:
      rng = writer.scene_rng(seed=d.get("seed", 0), family=d.family, split="test", index=index)
      again = writer.generate_scene(rng, family=d.family, views=scene.num_views,
                                    image_size=d.image_size, supersample=s, **objects)
      if s == DATASET_SUPERSAMPLE and not np.array_equal(again.rgb,
                                                         np.round(scene.images * 255.0)):
        raise SystemExit(f"error: test scene {index} regenerated differs from {config.data.root}")
      rendering = _as_rendering(again.rgb, scene.masks, int(scene.masks.max()) + 1)
      with warnings.catch_warnings():  # identical images: SSIM and PSNR of zero error
        warnings.simplefilter("ignore", RuntimeWarning)
        rows[s].append(evaluate.scene_metrics(rendering, scene, views, image_metrics=True))
  result = {"config": args.config, "data_root": config.data.root, "scenes": len(scenes),
            "dataset_supersample": DATASET_SUPERSAMPLE, "seconds": time.perf_counter() - t0,
            "renderings": {}}
  for s in per_side:
    with warnings.catch_warnings():  # the set's own footprint: infinite PSNRs, no error shares
      warnings.simplefilter("ignore", RuntimeWarning)
      means = {k: float(np.nanmean([r[k] for r in rows[s]])) for k in KEYS if k in rows[s][0]}
    # JSON has no infinity: null marks a value with no error behind it (the set's own footprint).
    result["renderings"][f"{s}x{s}"] = {k: v if np.isfinite(v) else None for k, v in means.items()}
    print(f"{s}×{s} rays per pixel: " + ", ".join(f"{k} {v:.3f}" for k, v in means.items()))
  if args.out:
    with open(args.out, "w") as f:
      json.dump(result, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
