"""Reader for ScanNet as SlotLifter uses it (docs/method.md §3.4).

Vocabulary: N frames of a scene, H×W = 480×640 stored, h×w delivered, V sources.

  <root>/sceneXXXX_XX/color_480640/<frame>.jpg     colour frames (640×480)
  <root>/sceneXXXX_XX/pose/<frame>.txt             4×4 cam2world, metres, OpenCV convention
  <root>/sceneXXXX_XX/intrinsic/intrinsic_color.txt  4×4 K of the native 1296×968 colour camera
  <root>/sceneXXXX_XX/sampled_frames.json          optional: the frames a training scene uses
  <root>/train.lst                                 optional: training scene names, one per line
  test scenes (the 8 NerfingMVS scenes) also have
  <root>/sceneXXXX_XX/train.txt, test.txt          source-pool frames and target frames
  <root>/sceneXXXX_XX/instance/<frame>.png         instance ids of the targets, 0 = background

Training scenes are the names in train.lst, or else every `sceneXXXX_XX` folder that is not a test
scene; their frames are those in sampled_frames.json (as the official loader uses), or else every
colour frame. The native K is rescaled to the stored colour size with the pixel-centre convention
(c' = (c + ½)·s − ½, f' = f·s; the official code multiplies by s, a quarter pixel away).

Scenes are pooled-source scenes (types.py) with three protocols: 'train' (every frame a target,
sources from all others), 'holdout' (validation scenes held out of training: every 8th frame a
target, sources from the rest, no masks) and 'test' (targets from test.txt with instance masks,
sources from train.txt). Frames whose pose has non-finite values (ScanNet marks lost tracking with
-inf) are skipped with a warning; any other bad pose is an error.
"""

from __future__ import annotations

import json
import os
import re
from typing import Optional, Sequence

from absl import logging
import numpy as np

from slotlifter_jax.data import cameras
from slotlifter_jax.data import images
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

NERFINGMVS_TEST_SCENES = ("scene0000_01", "scene0079_00", "scene0158_00", "scene0316_00",
                          "scene0521_00", "scene0553_00", "scene0616_00", "scene0653_00")
COLOR_DIR = "color_480640"
POSE_DIR = "pose"
INSTANCE_DIR = "instance"
INTRINSIC_FILE = os.path.join("intrinsic", "intrinsic_color.txt")
NATIVE_COLOR_SIZE = (968, 1296)  # (H, W) the colour intrinsics refer to
TRAIN_SCENE_LIST = "train.lst"
SAMPLED_FRAMES = "sampled_frames.json"
EVAL_TARGET_STRIDE = 8  # 'holdout' protocol: frames 0, 8, 16, … are targets
SCENE_NAME = re.compile(r"^scene\d{4}_\d{2}$")
PROTOCOLS = ("train", "holdout", "test")


def _frame_key(name: str):
  return (0, int(name), name) if name.isdigit() else (1, 0, name)


def train_scene_names(root: str) -> list[str]:
  """Training scenes: `<root>/train.lst` when present, else every non-test scene folder."""
  if not os.path.isdir(root):
    raise DataError(f"{root}: ScanNet root does not exist")
  listed = os.path.join(root, TRAIN_SCENE_LIST)
  if os.path.isfile(listed):
    with open(listed, encoding="utf-8") as f:
      names = [line.strip() for line in f if line.strip()]
    if not names:
      raise DataError(f"{listed}: scene list is empty")
    return names
  names = sorted(n for n in os.listdir(root) if SCENE_NAME.match(n)
                 and os.path.isdir(os.path.join(root, n)) and n not in NERFINGMVS_TEST_SCENES)
  if not names:
    raise DataError(f"{root}: no training scene folders (sceneXXXX_XX) and no {TRAIN_SCENE_LIST}")
  return names


def _read_frame_list(path: str) -> list[str]:
  if not os.path.isfile(path):
    raise DataError(f"{path}: frame list does not exist")
  with open(path, encoding="utf-8") as f:
    names = [os.path.splitext(line.strip())[0] for line in f if line.strip()]
  if not names:
    raise DataError(f"{path}: frame list is empty")
  return names


def _all_frames(scene_dir: str) -> list[str]:
  sampled = os.path.join(scene_dir, SAMPLED_FRAMES)
  if os.path.isfile(sampled):
    try:
      with open(sampled, encoding="utf-8") as f:
        frames = json.load(f)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
      raise DataError(f"{sampled}: not valid JSON ({e})") from e
    if not (isinstance(frames, list) and frames and all(isinstance(x, (str, int)) for x in frames)):
      raise DataError(f"{sampled}: must be a non-empty list of frame names")
    return sorted({os.path.splitext(str(x))[0] for x in frames}, key=_frame_key)
  folder = os.path.join(scene_dir, COLOR_DIR)
  if not os.path.isdir(folder):
    raise DataError(f"{folder}: colour folder does not exist")
  frames = [os.path.splitext(n)[0] for n in os.listdir(folder) if n.lower().endswith(".jpg")]
  if not frames:
    raise DataError(f"{folder}: no .jpg frames")
  return sorted(frames, key=_frame_key)


def _read_pose_or_none(path: str) -> Optional[np.ndarray]:
  """The frame's cam2world, or None (with a warning) when it has non-finite values."""
  pose = cameras.load_text_matrix(path, shapes=((4, 4),))
  if not np.all(np.isfinite(pose)):
    logging.warning("%s: pose has non-finite values (lost tracking); frame skipped", path)
    return None
  return cameras.check_pose(pose, source=path)


def read_native_intrinsics(path: str) -> np.ndarray:
  """[3, 3] K of the native colour camera from intrinsic_color.txt (4×4)."""
  k = cameras.read_matrix(path, shape=(4, 4))[:3, :3]
  if k[0, 0] <= 0 or k[1, 1] <= 0 or np.any(k[2] != np.array([0.0, 0.0, 1.0])):
    raise DataError(f"{path}: not a pinhole K (need fx, fy > 0 and third row [0 0 1])")
  return k


def read_scene(scene_dir: str, *, protocol: str, image_size: images.ImageSize,
               scene_scale: float, num_source_views: int, has_masks: bool = True) -> Scene:
  """One ScanNet scene as a pooled-source Scene (protocols in the module docstring)."""
  if protocol not in PROTOCOLS:
    raise ValueError(f"read_scene: protocol must be one of {PROTOCOLS}, got {protocol!r}")
  if not os.path.isdir(scene_dir):
    raise DataError(f"{scene_dir}: scene folder does not exist")
  if protocol == "test":
    pool_frames = _read_frame_list(os.path.join(scene_dir, "train.txt"))
    target_frames = _read_frame_list(os.path.join(scene_dir, "test.txt"))
    frames = list(dict.fromkeys(pool_frames + target_frames))  # union, order kept
  else:
    frames = _all_frames(scene_dir)

  kept, poses = [], []
  for frame in frames:
    jpg = os.path.join(scene_dir, COLOR_DIR, frame + ".jpg")
    if not os.path.isfile(jpg):
      raise DataError(f"{jpg}: colour frame does not exist")
    pose = _read_pose_or_none(os.path.join(scene_dir, POSE_DIR, frame + ".txt"))
    if pose is not None:
      kept.append(frame)
      poses.append(cameras.scale_translation(pose, scene_scale))
  if not kept:
    raise DataError(f"{scene_dir}: no frame with a finite pose")
  position = {f: i for i, f in enumerate(kept)}
  if protocol == "test":
    targets = tuple(position[f] for f in target_frames if f in position)
    pool = tuple(position[f] for f in pool_frames if f in position)
    needed = num_source_views
  elif protocol == "holdout":
    targets = tuple(range(0, len(kept), EVAL_TARGET_STRIDE))
    pool = tuple(i for i in range(len(kept)) if i % EVAL_TARGET_STRIDE)
    needed = num_source_views
  else:
    targets = pool = tuple(range(len(kept)))
    needed = num_source_views + 1
  if not targets or len(pool) < needed:
    raise DataError(f"{scene_dir}: {len(targets)} target frames and {len(pool)} candidate "
                    f"sources (finite poses), too few for data.num_source_views="
                    f"{num_source_views}")

  jpgs = [os.path.join(scene_dir, COLOR_DIR, f + ".jpg") for f in kept]
  stored = images.stored_size(jpgs[0])
  for path in jpgs:
    here = images.stored_size(path)
    if here != stored:
      raise DataError(f"{path}: image is {here[0]}×{here[1]} but {jpgs[0]} is "
                      f"{stored[0]}×{stored[1]} (H×W); all frames must share one size")
  size = images.output_size(requested=image_size, stored=stored, path=scene_dir)
  native_k = read_native_intrinsics(os.path.join(scene_dir, INTRINSIC_FILE))
  k = cameras.scale_intrinsics(
      cameras.scale_intrinsics(native_k, stored=NATIVE_COLOR_SIZE, size=stored),
      stored=stored, size=size)
  rgbs = np.stack([images.downsample_area(images.read_rgb(p), size) for p in jpgs])

  masks = mask_views = None
  if protocol == "test" and has_masks:
    masks = np.zeros((len(kept),) + size, np.int32)
    mask_views = np.zeros(len(kept), bool)
    for t in targets:
      path = os.path.join(scene_dir, INSTANCE_DIR, kept[t] + ".png")
      labels = images.read_labels(path)  # [H', W'] instance ids, 0 = background
      if not np.isclose(labels.shape[0] * stored[1], labels.shape[1] * stored[0], rtol=1e-2):
        raise DataError(f"{path}: instance image is {labels.shape} (H, W), not the aspect ratio "
                        f"of the colour frames {stored}")
      # The official loader resizes instance images with nearest-neighbour to the image size.
      masks[t] = images.resample_nearest(labels, size)
      mask_views[t] = True
  return Scene(
      name=os.path.basename(os.path.normpath(scene_dir)),
      images=rgbs.astype(np.float32),
      cam_to_world=np.stack(poses).astype(np.float32),
      intrinsics=np.broadcast_to(k, (len(kept), 3, 3)).astype(np.float32),
      source_indices=(),
      masks=masks,
      mask_views=mask_views,
      target_indices=targets,
      source_pool=pool,
      view_names=tuple(kept),
  )


def read_scannet_scenes(root: str, names: Sequence[str], *, protocol: str,
                        image_size: images.ImageSize, scene_scale: float, num_source_views: int,
                        has_masks: bool = True) -> list[Scene]:
  """The named scenes of `root`; every scene must share one image size."""
  scenes = [read_scene(os.path.join(root, n), protocol=protocol, image_size=image_size,
                       scene_scale=scene_scale, num_source_views=num_source_views,
                       has_masks=has_masks) for n in names]
  for name, scene in zip(names, scenes):
    if scene.image_size != scenes[0].image_size:
      raise DataError(f"{os.path.join(root, name)}: frames are {scene.image_size} but "
                      f"{names[0]}'s are {scenes[0].image_size}; all scenes must share one size")
  return scenes
