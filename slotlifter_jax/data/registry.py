"""`load_split(config.data, split)`: the scenes of a split, any data set (docs/method.md §3).

Dispatches on `data.format`:
  'uorf' / 'uocf'  `<root>/<subset>_<split>/` (or `<root>/<subset>/<subset>_<split>/`, the official
                   layout); a folder with dataset.json is one of our generated sets (uorf.py)
  'dtu'            pixelNeRF rs_dtu_4: train = new_train.lst, test = new_val.lst (dtu.py)
  'scannet'        training scenes and the 8 NerfingMVS test scenes (scannet.py)

Validation never looks at the test split (docs/method.md §4): when a set has no validation split on
disk, the last `data.num_val_scenes` training scenes (in name order) are held out as 'val' and
removed from 'train'. DTU and ScanNet evaluation splits come back as one fixed-source Scene per
target (`pipeline.per_target_scenes`), their training split as pooled-source scenes.

Nothing is cached or written: not into the data folders, nor anywhere else.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Optional

from absl import logging

from slotlifter_jax import config_checks
from slotlifter_jax.data import cameras
from slotlifter_jax.data import dtu
from slotlifter_jax.data import pipeline
from slotlifter_jax.data import scannet
from slotlifter_jax.data import uorf
from slotlifter_jax.data.types import DataConfigError
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

# "dev": the embedded sets' development split (data/layout.py says why); real sets have none.
SPLITS = ("train", "val", "dev", "test")


def hold_out(names: list[str], *, split: str, num_val: int, where: str) -> list[str]:
  """Train keeps all but the last `num_val` names, val gets those (num_val 0: no hold-out)."""
  if split == "train" and num_val <= 0:
    return names
  if not 0 < num_val < len(names):
    raise DataError(f"{where}: data.num_val_scenes={num_val} cannot hold out a validation split "
                    f"from {len(names)} training scenes; set it between 1 and {len(names) - 1}")
  return names[:-num_val] if split == "train" else names[-num_val:]


def split_folder(root: str, subset: str, split: str) -> Optional[str]:
  """The uORF-style folder of a split, or None when neither layout has it."""
  for folder in (os.path.join(root, f"{subset}_{split}"),
                 os.path.join(root, subset, f"{subset}_{split}")):
    if os.path.isdir(folder):
      return folder
  return None


def _first(names: list[str], max_scenes: Optional[int]) -> list[str]:
  return names if max_scenes is None else names[:max_scenes]


def _load_uorf(d, split: str, max_scenes: Optional[int]) -> list[Scene]:
  folder = split_folder(d.root, d.subset, split)
  select = None
  if split in ("train", "val") and split_folder(d.root, d.subset, "val") is None:
    folder = split_folder(d.root, d.subset, "train")
    logging.info("%s: no %s_val folder; holding out the last %d training scenes as 'val'",
                 d.root, d.subset, d.num_val_scenes)
    select = functools.partial(hold_out, split=split, num_val=int(d.num_val_scenes), where=folder)
  if folder is None:
    raise DataError(f"{os.path.join(d.root, f'{d.subset}_{split}')}: split folder does not exist "
                    f"(also looked for {os.path.join(d.root, d.subset, f'{d.subset}_{split}')})")
  def pick(names):
    return _first(select(names) if select else names, max_scenes)
  return uorf.read_uorf_split(
      folder, data_format=d.format, subset=d.subset, scene_scale=float(d.scene_scale),
      image_size=d.image_size, num_source_views=int(d.num_source_views),
      has_masks=bool(d.has_masks), views_per_scene=int(d.views_per_scene),
      split="train" if select else split,  # a held-out val lives in the train folder
      official_principal_point=bool(d.get("official_principal_point", False)), select=pick)


def _expand(scenes: list[Scene], d) -> list[Scene]:
  out = []
  for scene in scenes:
    out.extend(pipeline.per_target_scenes(scene, num_source_views=int(d.num_source_views)))
  return out


def _load_dtu(d, split: str, max_scenes: Optional[int]) -> list[Scene]:
  list_path = os.path.join(d.root, dtu.TEST_LIST if split == "test" else dtu.TRAIN_LIST)
  scans = dtu.read_scan_list(list_path)
  if split != "test":
    scans = hold_out(scans, split=split, num_val=int(d.num_val_scenes), where=list_path)
  scenes = dtu.read_dtu_scans(
      d.root, _first(scans, max_scenes), protocol="train" if split == "train" else "eval",
      image_size=d.image_size, scene_scale=float(d.scene_scale),
      num_source_views=int(d.num_source_views))
  return scenes if split == "train" else _expand(scenes, d)


def _load_scannet(d, split: str, max_scenes: Optional[int]) -> list[Scene]:
  if split == "test":
    names, protocol = list(scannet.NERFINGMVS_TEST_SCENES), "test"
  else:
    names = hold_out(scannet.train_scene_names(d.root), split=split,
                     num_val=int(d.num_val_scenes), where=d.root)
    protocol = "train" if split == "train" else "holdout"
  scenes = scannet.read_scannet_scenes(
      d.root, _first(names, max_scenes), protocol=protocol, image_size=d.image_size,
      scene_scale=float(d.scene_scale), num_source_views=int(d.num_source_views),
      has_masks=bool(d.has_masks))
  return scenes if split == "train" else _expand(scenes, d)


def in_source_azimuth_frame(scene: Scene) -> Scene:
  """The scene with its poses in its first source view's azimuth frame
  (`cameras.source_azimuth_frame`); `objects` metadata stays in the stored world frame."""
  if scene.source_pool is not None or not scene.source_indices:
    raise DataError(f"{scene.name}: data.frame='source_azimuth' needs fixed source views "
                    f"(uORF-style sets); this scene draws its sources from a pool")
  try:
    poses = cameras.source_azimuth_frame(scene.cam_to_world, source_idx=scene.source_indices[0])
  except ValueError as e:
    raise DataError(f"{scene.name}: data.frame='source_azimuth': {e}") from e
  return dataclasses.replace(scene, cam_to_world=poses.astype(scene.cam_to_world.dtype))


def load_split(data_config, split: str, *, max_scenes: Optional[int] = None) -> list[Scene]:
  """The scenes of `split` ('train' | 'val' | 'dev' | 'test') of the data set `data_config` describes.

  Args:
    data_config: the `config.data` ConfigDict (format, root, subset, image_size, scene_scale,
      num_source_views, views_per_scene, num_val_scenes, has_masks; optionally
      official_principal_point).
    split: which split.
    max_scenes: keep only the first scenes (quick looks and tests); None keeps all.

  Raises:
    DataError naming the offending file when anything on disk is missing or malformed, and its
    DataConfigError naming the field when data.format or data.frame has no reader.
  """
  if split not in SPLITS:
    raise ValueError(f"load_split: split must be one of {SPLITS}, got {split!r}")
  problem = config_checks.data_problem(data_config)  # data.format and data.frame
  if problem:
    raise DataConfigError(f"load_split: {problem}")
  fmt = data_config.format
  if not data_config.root:
    raise DataError("data.root is empty: point it at a data set, or let embedded.resolve_data "
                    "generate the embedded set first")
  if not os.path.isdir(data_config.root):
    raise DataError(f"{data_config.root}: data.root does not exist (or is not a folder)")
  if split == "dev" and fmt in ("dtu", "scannet"):
    raise DataError(f"{data_config.root}: data.format={fmt!r} has no 'dev' split (only the "
                    f"embedded sets do); use val to choose and test to report")
  frame = data_config.get("frame", "world")
  loader = {"uorf": _load_uorf, "uocf": _load_uorf, "dtu": _load_dtu,
            "scannet": _load_scannet}[fmt]
  scenes = loader(data_config, split, max_scenes)
  if frame == "source_azimuth":
    scenes = [in_source_azimuth_frame(scene) for scene in scenes]
  logging.info("%s %s: %d scenes from %s", fmt, split, len(scenes), data_config.root)
  return scenes
