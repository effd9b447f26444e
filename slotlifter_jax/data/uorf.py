"""Readers for the uORF and uOCF folder formats and for our generated folders.

Formats: docs/method.md §3.2 (uORF), §3.3 (uOCF) and §3.5 (generated).

Vocabulary: N views per scene, H×W the stored and h×w the delivered image size.

A split folder `<root>/<subset>_<split>/` holds per view `NNNNN_scSSSS_azAA.png` and beside it
`…_RT.txt` (4×4 cam2world, world units) and, depending on the format, `…_mask.png`,
`…_intrinsics.txt` (normalised K) and `…_depth.npy`. Views group by `scSSSS`, ordered by file name;
the first `num_source_views` views of a scene are its sources (az00 for the paper's sets).

| folder            | intrinsics                  | masks                                        |
|-------------------|-----------------------------|----------------------------------------------|
| uORF (CLEVR-567,  | uORF default at h×w         | test views only; RGB→L, sorted grey levels,  |
|  Room-Chair/-Div.)|                             | background = 2nd-smallest level (→ label 0)  |
| uOCF Room-Texture | `_intrinsics.txt`           | background = smallest level                  |
| uOCF Kitchen-*    | `_intrinsics.txt`           | none: masks=None, never made up              |
| generated (has    | `_intrinsics.txt`           | every view; grey g ↦ label through           |
|  dataset.json)    |                             | dataset.json["mask"]["label_grey_levels"]    |

With the uORF/uOCF rules a view's labels index *its own* sorted grey levels, so label ids are not
consistent across views (ARI does not need them to be); the generated table makes them consistent.

Translations are multiplied by the scene scale (1/7, uORF's nss_scale) into the normalised frame;
depth (generated sets) is camera z and scales the same way. Other PNG suffixes of the uORF tools
(`_mask_for_moving`, `_moved`, …) are not views and are skipped; any other file named like a view is
an error. Everything is validated before any pixel is decoded; nothing is ever written.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from typing import Callable, Optional, Sequence

from absl import logging
import numpy as np

from slotlifter_jax.data import cameras
from slotlifter_jax.data import images
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

# `NNNNN_scSSSS_azAA` (some uORF tools add `_elEE`), then the suffix that says what the file is.
VIEW_NAME = re.compile(r"^(?P<stem>\d+_sc(?P<scene>\d+)_az\d+(?:_el\d+)?)(?P<rest>.*)$")
VIEW_FILE_KINDS = {
    ".png": "image",
    "_RT.txt": "pose",
    "_mask.png": "mask",
    "_intrinsics.txt": "intrinsics",
    "_depth.npy": "depth",
}
# Written by the uORF/uOCF scene-editing tools; they are not views (docs/method.md §3.2).
NOT_VIEW_SUFFIXES = frozenset(f"_{s}.png" for s in (
    "mask_for_moving", "moved", "mask_for_bg", "mask_for_providing_bg", "changed", "providing_bg",
    "depth"))

MANIFEST_NAME = "dataset.json"
MANIFEST_FORMAT = "slotlifter_jax.generated"
SUPPORTED_GENERATOR_MAJOR = 1  # dataset.json "generator_version" 1, "1", "1.x", … is understood
MANIFEST_KEYS = ("format", "generator_version", "family", "split", "seed", "image_size",
                 "views_per_scene", "num_source_views", "scene_scale", "camera", "mask", "scenes")
MASK_KEYS = ("background_label", "label_grey_levels", "max_objects")
# dataset.json's scene_scale and data.scene_scale must agree to this relative tolerance.
SCENE_SCALE_RTOL = 1e-4

# Background rules for masks.
BACKGROUND_SECOND_SMALLEST = "second_smallest"  # uORF sets
BACKGROUND_SMALLEST = "smallest"  # uOCF Room-Texture
GREY_LEVEL_TABLE = "grey_level_table"  # generated sets: dataset.json lists the grey of each label
UOCF_SUBSETS = ("room_texture", "kitchen_matte", "kitchen_shiny")


@dataclasses.dataclass(frozen=True)
class ViewFiles:
  stem: str
  image: str
  pose: str
  mask: Optional[str] = None
  intrinsics: Optional[str] = None
  depth: Optional[str] = None


@dataclasses.dataclass(frozen=True)
class Manifest:
  """A validated dataset.json."""
  path: str
  image_size: tuple[int, int]  # (H, W) on disk
  views_per_scene: int
  scene_scale: float
  grey_levels: tuple[int, ...]  # grey of label l at index l; label 0 is the background
  scenes: dict  # scene name → its entry {"name", "views", "objects", …}


@dataclasses.dataclass(frozen=True)
class FolderRules:
  """How one folder's files are interpreted (see the module table)."""
  normalised_intrinsics: bool  # `_intrinsics.txt` per view; otherwise the uORF default K
  mask_rule: Optional[str]  # a background rule, or None: masks are not read
  masks_on_every_view: bool  # generated sets
  depth: bool  # generated sets: `_depth.npy` per view


def folder_rules(*, data_format: str, subset: str, has_masks: bool,
                 generated: bool) -> FolderRules:
  """The rules for `data.format` ('uorf' | 'uocf'), `data.subset` and a dataset.json's presence."""
  if generated:
    return FolderRules(normalised_intrinsics=True,
                       mask_rule=GREY_LEVEL_TABLE if has_masks else None,
                       masks_on_every_view=True, depth=True)
  if data_format == "uorf":
    if subset in UOCF_SUBSETS:
      raise DataError(f"data.subset={subset!r} is a uOCF set but data.format='uorf': set "
                      f"data.format='uocf' (its masks use another background rule)")
    return FolderRules(normalised_intrinsics=False,
                       mask_rule=BACKGROUND_SECOND_SMALLEST if has_masks else None,
                       masks_on_every_view=False, depth=False)
  if data_format == "uocf":
    no_masks = not has_masks or subset.startswith("kitchen")
    return FolderRules(normalised_intrinsics=True,
                       mask_rule=None if no_masks else BACKGROUND_SMALLEST,
                       masks_on_every_view=False, depth=False)
  raise ValueError(f"folder_rules: data.format must be 'uorf' or 'uocf', got {data_format!r}")


def index_folder(folder: str) -> dict[str, tuple[ViewFiles, ...]]:
  """Scene name (`scSSSS`) → its views ordered by file name, scenes ordered by number.

  Checks the file set only (no decoding): every view image has its pose, every per-view file has its
  image, and no file named like a view has an unknown suffix.
  """
  if not os.path.isdir(folder):
    raise DataError(f"{folder}: split folder does not exist (or is not a folder)")
  by_stem: dict[str, dict[str, str]] = {}
  scene_of: dict[str, str] = {}
  for name in sorted(os.listdir(folder)):
    path = os.path.join(folder, name)
    match = VIEW_NAME.match(name)
    if match is None or not os.path.isfile(path):
      continue  # dataset.json, README, files.csv from the official loader, sub-folders
    rest = match["rest"]
    if rest in NOT_VIEW_SUFFIXES:
      continue
    kind = VIEW_FILE_KINDS.get(rest)
    if kind is None:
      raise DataError(
          f"{path}: named like a view but its suffix {rest!r} is unknown (views use "
          f"{sorted(VIEW_FILE_KINDS)}; skipped: {sorted(NOT_VIEW_SUFFIXES)})")
    by_stem.setdefault(match["stem"], {})[kind] = path
    scene_of[match["stem"]] = "sc" + match["scene"]
  if not by_stem:
    raise DataError(f"{folder}: no views (NNNNN_scSSSS_azAA.png with _RT.txt) in the folder")

  scenes: dict[str, list[ViewFiles]] = {}
  for stem in sorted(by_stem):
    files = by_stem[stem]
    if "image" not in files:
      orphan = sorted(files.values())[0]
      raise DataError(f"{orphan}: has no view image {stem}.png beside it")
    if "pose" not in files:
      raise DataError(f"{files['image']}: view has no pose file {stem}_RT.txt beside it")
    scenes.setdefault(scene_of[stem], []).append(ViewFiles(stem=stem, **files))
  ordered = sorted(scenes, key=lambda s: (int(s[2:]), s))
  return {name: tuple(scenes[name]) for name in ordered}


def _generator_major(version) -> Optional[int]:
  if isinstance(version, bool):
    return None
  if isinstance(version, int):
    return version
  if isinstance(version, str) and re.fullmatch(r"\d+(\.\d+)*", version):
    return int(version.split(".")[0])
  return None


def _positive_int(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool) and value > 0


def read_manifest(path: str, *, split: Optional[str] = None) -> Manifest:
  """Reads and validates a generated folder's dataset.json (keys, format, version, types)."""
  try:
    with open(path, encoding="utf-8") as f:
      raw = json.load(f)
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise DataError(f"{path}: not valid JSON ({e})") from e
  except OSError as e:
    raise DataError(f"{path}: cannot be read ({e})") from e
  if not isinstance(raw, dict):
    raise DataError(f"{path}: top level must be a JSON object, found {type(raw).__name__}")
  missing = [k for k in MANIFEST_KEYS if k not in raw]
  if missing:
    raise DataError(f"{path}: missing keys {missing}")
  if raw["format"] != MANIFEST_FORMAT:
    raise DataError(f"{path}: format is {raw['format']!r}, expected {MANIFEST_FORMAT!r}")
  if _generator_major(raw["generator_version"]) != SUPPORTED_GENERATOR_MAJOR:
    raise DataError(f"{path}: generator_version {raw['generator_version']!r} is not supported "
                    f"(this reader understands major version {SUPPORTED_GENERATOR_MAJOR})")
  if split is not None and raw["split"] != split:
    raise DataError(f"{path}: describes split {raw['split']!r} but was found in the {split!r} "
                    f"folder")
  size = raw["image_size"]
  if not (isinstance(size, list) and len(size) == 2 and all(_positive_int(x) for x in size)):
    raise DataError(f"{path}: image_size must be [H, W] of positive ints, found {size!r}")
  if not _positive_int(raw["views_per_scene"]):
    raise DataError(f"{path}: views_per_scene must be a positive int, found "
                    f"{raw['views_per_scene']!r}")
  scale = raw["scene_scale"]
  if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
    raise DataError(f"{path}: scene_scale must be a positive number, found {scale!r}")
  mask = raw["mask"]
  if not isinstance(mask, dict) or any(k not in mask for k in MASK_KEYS):
    raise DataError(f"{path}: mask must be an object with keys {list(MASK_KEYS)}, found {mask!r}")
  if mask["background_label"] != 0:
    raise DataError(f"{path}: mask.background_label is {mask['background_label']!r}; the "
                    f"readers' contract is background label 0")
  levels = mask["label_grey_levels"]
  if not (isinstance(levels, list) and levels
          and all(isinstance(g, int) and not isinstance(g, bool) and 0 <= g <= 255 for g in levels)
          and len(set(levels)) == len(levels)):
    raise DataError(f"{path}: mask.label_grey_levels must be distinct ints in [0, 255], found "
                    f"{levels!r}")
  if not isinstance(raw["camera"], dict):
    raise DataError(f"{path}: camera must be an object")
  if not isinstance(raw["scenes"], list):
    raise DataError(f"{path}: scenes must be a list")
  scenes = {}
  for i, entry in enumerate(raw["scenes"]):
    if not (isinstance(entry, dict) and isinstance(entry.get("name"), str)
            and isinstance(entry.get("views"), list)
            and all(isinstance(v, str) for v in entry["views"])
            and isinstance(entry.get("objects"), list)
            and all(isinstance(o, dict) and "label" in o and "position" in o
                    for o in entry["objects"])):
      raise DataError(f"{path}: scenes[{i}] must have a string 'name', a list of view stems "
                      f"'views' and a list 'objects' of objects with 'label' and 'position'")
    if entry["name"] in scenes:
      raise DataError(f"{path}: scene {entry['name']!r} is listed twice")
    scenes[entry["name"]] = entry
  return Manifest(path=path, image_size=(size[0], size[1]),
                  views_per_scene=raw["views_per_scene"], scene_scale=float(scale),
                  grey_levels=tuple(levels), scenes=scenes)


def _check_manifest_files(manifest: Manifest, index: dict[str, tuple[ViewFiles, ...]],
                          folder: str) -> None:
  """The scenes and views listed in dataset.json are exactly those on disk, with all their files."""
  for name, views in index.items():
    if name not in manifest.scenes:
      raise DataError(f"{views[0].image}: scene {name} is not listed in {manifest.path}")
  for name, entry in manifest.scenes.items():
    on_disk = {v.stem: v for v in index.get(name, ())}
    for stem in entry["views"]:
      if stem not in on_disk:
        raise DataError(f"{os.path.join(folder, stem + '.png')}: listed in {manifest.path} "
                        f"(scene {name}) but does not exist")
    for stem, view in on_disk.items():
      if stem not in entry["views"]:
        raise DataError(f"{view.image}: view is not listed in {manifest.path} (scene {name})")
    if len(entry["views"]) != manifest.views_per_scene:
      raise DataError(f"{manifest.path}: scene {name} lists {len(entry['views'])} views, "
                      f"views_per_scene is {manifest.views_per_scene}")
    for view in on_disk.values():
      for kind, suffix in (("intrinsics", "_intrinsics.txt"), ("depth", "_depth.npy"),
                           ("mask", "_mask.png")):
        if getattr(view, kind) is None:
          raise DataError(f"{os.path.join(folder, view.stem + suffix)}: missing (a generated "
                          f"folder has it for every view)")


def labels_from_grey(grey: np.ndarray, *, rule: str) -> np.ndarray:
  """[H, W] uint8 grey levels → [H, W] int32 labels by the uORF/uOCF rule (module table).

  Labels index the view's sorted distinct levels; with BACKGROUND_SECOND_SMALLEST labels 0 and 1
  swap so the second-smallest level (the uORF background) becomes 0 and the smallest 1. A view with
  a single level is all background.
  """
  levels = np.unique(grey)  # sorted
  labels = np.searchsorted(levels, grey).astype(np.int32)  # [H, W]
  if rule == BACKGROUND_SECOND_SMALLEST:
    labels = np.where(labels == 0, 1, np.where(labels == 1, 0, labels))
    labels = labels if len(levels) > 1 else np.zeros_like(labels)
  elif rule != BACKGROUND_SMALLEST:
    raise ValueError(f"labels_from_grey: unknown rule {rule!r}")
  return labels.astype(np.int32)


def labels_from_table(grey: np.ndarray, *, grey_levels: Sequence[int], path: str) -> np.ndarray:
  """[H, W] uint8 → [H, W] int32: grey_levels[l] ↦ l exactly; an unlisted grey is a DataError."""
  lookup = np.full(256, -1, dtype=np.int32)
  lookup[np.asarray(grey_levels, dtype=np.int64)] = np.arange(len(grey_levels), dtype=np.int32)
  labels = lookup[grey]  # [H, W]
  if np.any(labels < 0):
    unknown = sorted(int(g) for g in np.unique(grey[labels < 0]))
    raise DataError(f"{path}: grey levels {unknown} are not in dataset.json "
                    f"mask.label_grey_levels {list(grey_levels)}")
  return labels


def _read_depth(path: str, *, stored: tuple[int, int]) -> np.ndarray:
  try:
    depth = np.load(path, allow_pickle=False)
  except (OSError, ValueError) as e:
    raise DataError(f"{path}: unreadable .npy depth ({e})") from e
  if depth.shape != stored or not np.issubdtype(depth.dtype, np.floating):
    raise DataError(f"{path}: depth must be a float [H, W] = {list(stored)} array, found "
                    f"{depth.dtype} {list(depth.shape)}")
  if np.any(np.isnan(depth)) or np.any(depth < 0):
    raise DataError(f"{path}: depth has NaN or negative values")
  return depth.astype(np.float32)


def _check_same_size(path: str, array: np.ndarray, stored: tuple[int, int], what: str) -> None:
  if array.shape[:2] != stored:
    raise DataError(f"{path}: {what} is {array.shape[0]}×{array.shape[1]} but the views of this "
                    f"set are {stored[0]}×{stored[1]} (H×W)")


def _load_scene(name: str, views: tuple[ViewFiles, ...], *, rules: FolderRules,
                stored: tuple[int, int], size: tuple[int, int], scene_scale: float,
                num_source_views: int, official_principal_point: bool,
                manifest: Optional[Manifest]) -> Scene:
  rgbs, poses, ks, masks, has_mask, depths = [], [], [], [], [], []
  for view in views:
    rgb = images.read_rgb(view.image)  # [H, W, 3]
    _check_same_size(view.image, rgb, stored, "the image")
    rgbs.append(images.downsample_area(rgb, size))
    poses.append(cameras.scale_translation(cameras.read_pose(view.pose), scene_scale))
    if rules.normalised_intrinsics:
      path = view.intrinsics or os.path.join(os.path.dirname(view.image),
                                             view.stem + "_intrinsics.txt")
      k_norm = cameras.read_normalised_intrinsics(path)
      if official_principal_point:
        k = cameras.intrinsics_from_normalised(k_norm, height=size[0], width=size[1],
                                               official_principal_point=True)
      else:  # convert at the stored size, where the normalisation is defined, then resize
        k = cameras.scale_intrinsics(
            cameras.intrinsics_from_normalised(k_norm, height=stored[0], width=stored[1]),
            stored=stored, size=size)
    else:
      k = cameras.uorf_intrinsics(height=size[0], width=size[1],
                                  official_principal_point=official_principal_point)
    ks.append(k)
    label = None
    if rules.mask_rule is not None and view.mask is not None:
      if rules.mask_rule == GREY_LEVEL_TABLE:
        grey = images.read_grey_rgb(view.mask)
        _check_same_size(view.mask, grey, stored, "the mask")
        label = labels_from_table(grey, grey_levels=manifest.grey_levels, path=view.mask)
      else:
        grey = images.read_luma(view.mask)
        _check_same_size(view.mask, grey, stored, "the mask")
        # Labels come from the full-resolution levels so that a level lost by the resize cannot
        # shift which level counts as background.
        label = labels_from_grey(grey, rule=rules.mask_rule)
      label = images.resample_nearest(label, size)
    has_mask.append(label is not None)
    masks.append(label if label is not None else np.zeros(size, np.int32))
    if rules.depth:
      depth = _read_depth(view.depth, stored=stored) * np.float32(scene_scale)
      depths.append(images.resample_nearest(depth, size))

  return Scene(
      name=name,
      images=np.stack(rgbs).astype(np.float32),
      cam_to_world=np.stack(poses).astype(np.float32),
      intrinsics=np.stack(ks).astype(np.float32),
      source_indices=tuple(range(num_source_views)),
      masks=np.stack(masks).astype(np.int32) if any(has_mask) else None,
      mask_views=np.array(has_mask, dtype=bool) if any(has_mask) else None,
      depth=np.stack(depths).astype(np.float32) if rules.depth else None,
      objects=list(manifest.scenes[name]["objects"]) if manifest is not None else None,
      view_names=tuple(v.stem for v in views),
  )


def read_uorf_split(folder: str, *, data_format: str, subset: str, scene_scale: float,
                    image_size: images.ImageSize, num_source_views: int, has_masks: bool = True,
                    views_per_scene: Optional[int] = None, split: Optional[str] = None,
                    official_principal_point: bool = False,
                    select: Optional[Callable[[list[str]], list[str]]] = None) -> list[Scene]:
  """All scenes of one split folder (or those `select` keeps from the ordered scene names).

  Args:
    folder: `<root>/<subset>_<split>`.
    data_format: 'uorf' or 'uocf' (a folder with dataset.json is read as a generated folder).
    subset: `data.subset`; picks the uOCF mask rule (Kitchen-* have no masks).
    scene_scale: world → normalised frame factor (1/7); dataset.json must agree.
    image_size: `data.image_size` (0: as stored, n: n×n, or (h, w)); only downsampling.
    num_source_views: V, the first V views of each scene.
    has_masks: False ignores mask files (`data.has_masks`).
    views_per_scene: when given, every scene must have exactly this many views.
    split: when given, dataset.json's "split" must equal it.
    official_principal_point: the official code's principal point (see `cameras`).
    select: picks scenes from the ordered names (the registry's validation hold-out).

  Raises:
    DataError naming the offending file, before any scene is returned.
  """
  index = index_folder(folder)
  manifest_path = os.path.join(folder, MANIFEST_NAME)
  manifest = None
  if os.path.exists(manifest_path):
    manifest = read_manifest(manifest_path, split=split)
    _check_manifest_files(manifest, index, folder)
    if not math.isclose(manifest.scene_scale, scene_scale, rel_tol=SCENE_SCALE_RTOL):
      raise DataError(f"{manifest_path}: scene_scale {manifest.scene_scale} differs from "
                      f"data.scene_scale {scene_scale}")
  rules = folder_rules(data_format=data_format, subset=subset, has_masks=has_masks,
                       generated=manifest is not None)

  counts = {name: len(views) for name, views in index.items()}
  first = next(iter(index))
  for name, count in counts.items():
    if count != counts[first]:
      raise DataError(f"{index[name][0].image}: scene {name} has {count} views but scene "
                      f"{first} has {counts[first]}; every scene of a split needs the same count")
  if views_per_scene is not None and counts[first] != views_per_scene:
    raise DataError(f"{folder}: scenes have {counts[first]} views but data.views_per_scene is "
                    f"{views_per_scene}")
  if num_source_views >= counts[first]:
    raise DataError(f"{folder}: scenes have {counts[first]} views, too few for "
                    f"data.num_source_views={num_source_views} plus a novel view")
  if rules.normalised_intrinsics:
    for views in index.values():
      for view in views:
        if view.intrinsics is None:
          raise DataError(f"{os.path.join(folder, view.stem + '_intrinsics.txt')}: missing "
                          f"(the uOCF format has a normalised K beside every view)")
  if rules.mask_rule is None and any(v.mask for vs in index.values() for v in vs):
    logging.warning("%s: mask files ignored (data.has_masks=False or a Kitchen-* subset)", folder)

  names = list(index) if select is None else list(select(list(index)))
  if not names:
    raise DataError(f"{folder}: no scenes selected")

  stored = images.stored_size(index[names[0]][0].image)
  if manifest is not None and stored != manifest.image_size:
    raise DataError(f"{index[names[0]][0].image}: image is {stored[0]}×{stored[1]} but "
                    f"{manifest.path} says image_size {list(manifest.image_size)}")
  for name in names:
    for view in index[name]:
      here = images.stored_size(view.image)
      if here != stored:
        raise DataError(f"{view.image}: image is {here[0]}×{here[1]} but "
                        f"{index[names[0]][0].image} is {stored[0]}×{stored[1]}; all views of a "
                        f"set must share one size")
  size = images.output_size(requested=image_size, stored=stored, path=folder)
  return [_load_scene(name, index[name], rules=rules, stored=stored, size=size,
                      scene_scale=scene_scale, num_source_views=num_source_views,
                      official_principal_point=official_principal_point, manifest=manifest)
          for name in names]
