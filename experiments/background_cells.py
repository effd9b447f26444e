"""How much of the source view `model.locality_attention` hands to slot attention's first slot.

  python experiments/background_cells.py [--config=configs/clevr.py:scene] [--scenes=100]

For each validation scene, the source-view feature cells whose ray never enters the locality box
over its sampled interval (`SlotLifter.background_cells`, docs/method.md §1.4). Prints their share
of the cells and, from the ground-truth masks at each cell's nearest pixel, the share of them that
show an object: the locality constraint gives such a cell's object to slot 1, which is what it does
in 3D to an object that reaches outside the box.
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common  # noqa: E402
from slotlifter_jax import model as model_lib  # noqa: E402
from slotlifter_jax.data import embedded  # noqa: E402
from slotlifter_jax.data import registry  # noqa: E402
from slotlifter_jax.rendering import views as views_lib  # noqa: E402


def feature_size(model, sources: dict) -> tuple[int, int]:
  """The (h, w) of the encoder's feature maps for these source views, from shapes alone."""
  encoded = jax.eval_shape(lambda: model.init_with_output(
      jax.random.key(0), **sources, train=False, method=model.encode)[0])
  return tuple(encoded.features.shape[2:4])


def cell_pixels(size: int, cells: int) -> np.ndarray:
  """The nearest pixel row (or column) of each feature cell (align-corners convention)."""
  return np.rint(np.linspace(0.0, size - 1.0, cells)).astype(int)


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/clevr.py:scene")
  parser.add_argument("--scenes", type=int, default=100)
  args = parser.parse_args()
  config = embedded.resolve_data(study_common.load_config(args.config))
  scenes = registry.load_split(config.data, "val", max_scenes=args.scenes)
  model = model_lib.build_model(config)
  signed = config.model.colour_range == "signed"
  shares, on_objects = [], []
  sizes = {}  # image (H, W) → feature (h, w): traced once per image size, not once per scene
  for scene in scenes:
    idx = np.asarray(scene.source_indices)
    height, width = scene.images.shape[1:3]
    sources = views_lib.scene_sources(scene, signed=signed)
    if (height, width) not in sizes:
      sizes[height, width] = feature_size(model, sources)
    h, w = sizes[height, width]
    cells = np.asarray(model.apply(
        {}, source_cam_to_world=sources["source_cam_to_world"],
        source_intrinsics=sources["source_intrinsics"], image_size=(height, width),
        feature_size=(h, w), method=model.background_cells))[0]  # [V, h, w]
    rows, cols = cell_pixels(height, h), cell_pixels(width, w)
    labels = scene.masks[idx][:, rows][:, :, cols]  # [V, h, w]
    shares.append(cells.mean())
    on_objects.append((labels[cells] > 0).mean() if cells.any() else 0.0)
  print(f"{len(scenes)} val scenes of {config.data.root}, frame {config.data.frame!r}: "
        f"background cells {np.mean(shares):.3f} of the source view's cells "
        f"(min {np.min(shares):.3f}, max {np.max(shares):.3f}); of those, "
        f"{np.mean(on_objects):.4f} show an object (max {np.max(on_objects):.3f} in one scene)")


if __name__ == "__main__":
  main()
