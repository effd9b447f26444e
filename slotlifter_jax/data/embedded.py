"""The embedded default data set: generated once into a cache folder when no data root is given.

The cache key holds every argument of the generator, so a config that asks for another size or
seed gets its own folder, and a finished folder is never regenerated or modified. The object
options (data.min_objects, data.max_objects, data.object_scale) add a suffix such as `-o1-3-x1.6`
only when they differ from the family's default, so the default sets keep their folder names.
Generation writes each split to a temporary folder and renames it into place, so an interrupted run
leaves nothing that looks complete.
"""

from __future__ import annotations

import os

import ml_collections
from absl import logging

# layout is the generator's JAX-free part, so this import stays light; the generator itself is
# imported inside the functions below, only when a set is generated.
from slotlifter_jax.data.layout import SUBSETS


def cache_root() -> str:
  """$SLOTLIFTER_DATA_CACHE, else $XDG_CACHE_HOME/slotlifter_jax, else ~/.cache/slotlifter_jax."""
  if os.environ.get("SLOTLIFTER_DATA_CACHE"):
    return os.environ["SLOTLIFTER_DATA_CACHE"]
  base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
  return os.path.join(base, "slotlifter_jax")


def object_options(data_config) -> dict:
  """min_objects, max_objects, object_scale, plain_background, plain_objects, no_walls,
  room_objects, grey_floor of a data config; configs saved before these fields existed get the
  defaults (0, 0, 1.0, False ×3, "chairs", False)."""
  d = data_config
  return {"min_objects": int(d.get("min_objects", 0)), "max_objects": int(d.get("max_objects", 0)),
          "object_scale": float(d.get("object_scale", 1.0)),
          "plain_background": bool(d.get("plain_background", False)),
          "plain_objects": bool(d.get("plain_objects", False)),
          "no_walls": bool(d.get("no_walls", False)),
          "room_objects": str(d.get("room_objects", "chairs")),
          "grey_floor": bool(d.get("grey_floor", False))}


def num_dev_scenes(data_config) -> int:
  """Scenes of the development split (layout.SPLITS); configs saved before it existed: as many as
  the test split."""
  return int(data_config.get("num_dev_scenes", data_config.num_test_scenes))


def dataset_dir(data_config, *, seed: int) -> str:
  from slotlifter_jax.data import generator  # heavy imports only when generating
  d = data_config
  # The name counts the four splits: folders made before the held-out split existed hold three
  # splits (their test scenes are today's dev scenes) and are never reused or modified.
  name = (f"{d.family}-v{generator.GENERATOR_VERSION}-{d.image_size}px-{d.views_per_scene}v-"
          f"{d.num_train_scenes}-{d.num_val_scenes}-{num_dev_scenes(d)}-{d.num_test_scenes}"
          f"-s{seed}")
  objects = object_options(d)
  generator.check_object_options(d.family, **objects)
  if not generator.is_default_objects(d.family, **objects):
    lo, hi = generator.object_count_range(d.family, objects["min_objects"],
                                          objects["max_objects"], objects["room_objects"])
    name += f"-o{lo}-{hi}-x{objects['object_scale']!r}"
    if objects["plain_background"]:
      name += "-plainbg"
    if objects["plain_objects"]:
      name += "-plainobj"
    if objects["no_walls"]:
      name += "-nowalls"
    if objects["room_objects"] != "chairs":
      name += "-" + objects["room_objects"]
    if objects["grey_floor"]:
      name += "-greyfloor"
  return os.path.join(cache_root(), name)


def ensure_dataset(data_config, *, seed: int = 0) -> str:
  """Returns the root of the embedded set described by `data_config`, generating it if absent."""
  from slotlifter_jax.data import generator
  d = data_config
  root = dataset_dir(d, seed=seed)
  subset = SUBSETS[d.family]
  splits = {"train": d.num_train_scenes, "val": d.num_val_scenes, "dev": num_dev_scenes(d),
            "test": d.num_test_scenes}
  if all(os.path.exists(os.path.join(root, f"{subset}_{s}", "dataset.json")) for s in splits):
    return root
  logging.info("embedded %s set not found: generating it into %s (once)", d.family, root)
  generator.generate_dataset(
      root, family=d.family, num_train=d.num_train_scenes, num_val=d.num_val_scenes,
      num_test=d.num_test_scenes, num_dev=num_dev_scenes(d), views=d.views_per_scene, image_size=d.image_size, seed=seed,
      progress=True, **object_options(d))
  return root


def resolve_data(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
  """Fills data.root with the embedded default set (generated once) when the config leaves it empty.

  Training, evaluation and the experiments all call this before loading a split; it lives with the
  data rather than in train.py so that evaluating a run does not import the training loop.
  """
  if not config.data.root:
    with config.unlocked():
      config.data.root = ensure_dataset(config.data, seed=config.data.get("seed", 0))
  return config
