"""Command line for the embedded default data set (docs/method.md §3.5).

  python -m slotlifter_jax.data.generate --family=clevr --out=DIR --num_train=1000 --num_val=100 \
      --num_dev=100 --num_test=100 --views=4 --image_size=128 --seed=0

writes DIR/clevr_567_{train,val,dev,test} (room: DIR/room_chair_*) in the uORF folder format; see
`generator.generate_dataset` for the layout. With --preview=PATH it instead writes one small PNG
grid of a few training scenes (per scene a row of views and a row of their instance masks):

  python -m slotlifter_jax.data.generate --family=clevr --preview=docs/data_clevr.png

--min_objects, --max_objects and --object_scale (both modes) select an easier set, e.g. 1–3 CLEVR
objects at 1.6× their size: a rung between a single object and the default 5–7 for locating
where a model stops working. The defaults write exactly the default set.

Shapes: N views per scene, H×W image size.
"""

from __future__ import annotations

import json

from absl import app
from absl import flags
import numpy as np
from PIL import Image

from slotlifter_jax.data import generator

FLAGS = flags.FLAGS
flags.DEFINE_enum("family", "clevr", list(generator.FAMILIES), "Scene family.")
flags.DEFINE_string("out", None, "Output root; splits go to OUT/<subset>_<split>.")
flags.DEFINE_integer("num_train", 1000, "Training scenes.")
flags.DEFINE_integer("num_val", 100, "Validation scenes.")
flags.DEFINE_integer("num_dev", 100, "Development scenes (the former test split's stream).")
flags.DEFINE_integer("num_test", 100, "Held-out test scenes (a stream no choice has read).")
flags.DEFINE_integer("views", 4, "Views per scene (8: the first 4 are source views).")
flags.DEFINE_integer("image_size", 128, "Square image size H = W in pixels.")
flags.DEFINE_integer("seed", 0, "Base seed; scene s of split x is seeded by (seed, family, x, s).")
flags.DEFINE_integer("supersample", 2, "Colour uses supersample² rays per pixel (anti-aliasing).")
flags.DEFINE_integer("num_workers", None, "Worker processes (default: one per CPU core).")
flags.DEFINE_bool("overwrite", False, "Replace existing non-empty split folders.")
flags.DEFINE_bool("progress", True, "Show a progress bar.")
flags.DEFINE_string("preview", None, "Write a preview grid PNG to this path instead of a data set.")
flags.DEFINE_integer("preview_scenes", 3, "Scenes in the preview grid.")
flags.DEFINE_integer("min_objects", 0, "Fewest objects per scene (0: the family's default, "
                     "clevr 5, room 1).")
flags.DEFINE_integer("max_objects", 0, "Most objects per scene (0: the family's default, "
                     "clevr 7, room 4).")
flags.DEFINE_float("object_scale", 1.0, "Factor on every object's size, in (0, 2] (room: (0, 1]).")
flags.DEFINE_bool("plain_background", False, "room only: the same scenes with untextured floor "
                  "and walls.")
flags.DEFINE_bool("plain_objects", False, "room only: the same scenes with untextured chairs.")
flags.DEFINE_bool("no_walls", False, "room only: the same scenes without walls.")
flags.DEFINE_string("room_objects", "chairs", "room only: the same scenes with chairs, solid "
                    "chairs (legs filled in) or boxes (one box of a chair's footprint and "
                    "height), or the room holding CLEVR's objects (min/max_objects then count "
                    "them, default 5-7): one of chairs, solid, boxes, clevr.")
flags.DEFINE_bool("grey_floor", False, "room only: the same scenes on the clevr family's grey "
                  "floor.")

# Label colours for previews only (the data set's masks are grey levels).
PREVIEW_PALETTE = np.array([
    (0, 0, 0), (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
    (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212),
    (0, 128, 128), (220, 190, 255), (170, 110, 40), (255, 250, 200), (128, 0, 0)], np.uint8)
PREVIEW_GAP = 2  # pixels of white between tiles


def preview_grid(*, family: str, num_scenes: int = 3, views: int = 4, image_size: int = 128,
                 seed: int = 0, supersample: int = 2, min_objects: int = 0, max_objects: int = 0,
                 object_scale: float = 1.0, plain_background: bool = False,
                 plain_objects: bool = False, no_walls: bool = False,
                 room_objects: str = "chairs", grey_floor: bool = False) -> np.ndarray:
  """[rows·H, N·W, 3] uint8: per training scene, its N views and below them their masks."""
  rows = []
  for s in range(num_scenes):
    rng = generator.scene_rng(seed=seed, family=family, split="train", index=s)
    scene = generator.generate_scene(rng, family=family, views=views, image_size=image_size,
                                     supersample=supersample, min_objects=min_objects,
                                     max_objects=max_objects, object_scale=object_scale,
                                     plain_background=plain_background,
                                     plain_objects=plain_objects, no_walls=no_walls,
                                     room_objects=room_objects, grey_floor=grey_floor)
    rows.append(list(scene.rgb))
    rows.append([PREVIEW_PALETTE[lab % len(PREVIEW_PALETTE)] for lab in scene.label])
  h = w = image_size
  g = PREVIEW_GAP
  grid = np.full((len(rows) * (h + g) - g, views * (w + g) - g, 3), 255, np.uint8)
  for r, row in enumerate(rows):
    for c, tile in enumerate(row):
      grid[r * (h + g):r * (h + g) + h, c * (w + g):c * (w + g) + w] = tile
  return grid


def main(argv):
  del argv
  objects = dict(min_objects=FLAGS.min_objects, max_objects=FLAGS.max_objects,
                 object_scale=FLAGS.object_scale, plain_background=FLAGS.plain_background,
                 plain_objects=FLAGS.plain_objects, no_walls=FLAGS.no_walls,
                 room_objects=FLAGS.room_objects, grey_floor=FLAGS.grey_floor)
  try:
    generator.check_object_options(FLAGS.family, **objects)
  except generator.ObjectOptionError as e:
    # One line on stderr naming the flag (absl's usage errors print the whole help text first).
    raise SystemExit(f"error: --{e.field}: {e}") from None
  if FLAGS.preview:
    grid = preview_grid(family=FLAGS.family, num_scenes=FLAGS.preview_scenes, views=FLAGS.views,
                        image_size=FLAGS.image_size, seed=FLAGS.seed,
                        supersample=FLAGS.supersample, **objects)
    Image.fromarray(grid).save(FLAGS.preview, format="PNG", optimize=True)
    print(f"wrote {FLAGS.preview} ({grid.shape[1]}×{grid.shape[0]})")
    return
  if not FLAGS.out:
    raise app.UsageError("--out is required (or --preview=PATH)")
  try:
    summary = generator.generate_dataset(
        FLAGS.out, family=FLAGS.family, num_train=FLAGS.num_train, num_val=FLAGS.num_val,
        num_test=FLAGS.num_test, num_dev=FLAGS.num_dev, views=FLAGS.views,
        image_size=FLAGS.image_size, seed=FLAGS.seed,
        num_workers=FLAGS.num_workers, progress=FLAGS.progress, overwrite=FLAGS.overwrite,
        supersample=FLAGS.supersample, **objects)
  except FileExistsError as e:
    raise app.UsageError(str(e)) from e
  print(json.dumps(summary, indent=1, sort_keys=True))


if __name__ == "__main__":
  app.run(main)
