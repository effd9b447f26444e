"""Reader for DTU in pixelNeRF's rs_dtu_4 layout (docs/method.md §3.4).

Vocabulary: N views of a scan (49 in rs_dtu_4), H×W = 300×400 stored, h×w delivered, V sources.

  <root>/new_train.lst, <root>/new_val.lst    one scan name per line (88 / 15 scans)
  <root>/<scan>/image/000000.png …            view i is the image whose stem is the integer i
  <root>/<scan>/cameras.npz                   world_mat_i (4×4 projection) and scale_mat_i

Cameras: P = (world_mat_i @ scale_mat_i)[:3, :4] projects points of the *normalised* frame (the
scale matrix maps the unit sphere around the object into the world), so decomposing P = K[R | t]
gives the pose directly in the normalised frame (the same result as pixelNeRF's "subtract the
translation, divide by the scale" on the world pose). cam_to_world = [R | t]⁻¹, OpenCV convention.
Each view keeps its own decomposed K (the official code averages K over the views of a scan).

Scenes are pooled-source scenes (types.py): training uses every view as a target with sources from
all other views; evaluation uses every 8th view (0, 8, …) as a target with sources from the rest.
Images are delivered in [0, 1]; the model side maps them to [−1, 1].
"""

from __future__ import annotations

import os
import re
import zipfile
from typing import Sequence

import numpy as np

from slotlifter_jax.data import cameras
from slotlifter_jax.data import images
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

TRAIN_LIST = "new_train.lst"
TEST_LIST = "new_val.lst"  # pixelNeRF's held-out scans: our test split (docs/method.md §3.4, §4)
EVAL_TARGET_STRIDE = 8  # evaluation targets: views 0, 8, 16, …
CAMERAS_FILE = "cameras.npz"
IMAGE_DIR = "image"
PROTOCOLS = ("train", "eval")


def read_scan_list(path: str) -> list[str]:
  """Scan names, one per line (blank lines skipped); an empty or missing list is an error."""
  if not os.path.isfile(path):
    raise DataError(f"{path}: scan list does not exist")
  with open(path, encoding="utf-8") as f:
    names = [line.strip() for line in f if line.strip()]
  if not names:
    raise DataError(f"{path}: scan list is empty")
  if len(set(names)) != len(names):
    raise DataError(f"{path}: a scan is listed twice")
  return names


def _view_images(scan_dir: str) -> list[tuple[int, str]]:
  """(view index, path) of the scan's images, ordered by index; names must be integers."""
  folder = os.path.join(scan_dir, IMAGE_DIR)
  if not os.path.isdir(folder):
    raise DataError(f"{folder}: image folder does not exist")
  views = []
  for name in sorted(os.listdir(folder)):
    stem, ext = os.path.splitext(name)
    if ext.lower() not in (".png", ".jpg", ".jpeg"):
      continue
    if not re.fullmatch(r"\d+", stem) or ext != ".png":
      raise DataError(f"{os.path.join(folder, name)}: DTU views are named <index>.png "
                      f"(e.g. 000000.png)")
    views.append((int(stem), os.path.join(folder, name)))
  if not views:
    raise DataError(f"{folder}: no images")
  views.sort()
  if len({i for i, _ in views}) != len(views):
    raise DataError(f"{folder}: two images share a view index")
  return views


def _load_cameras(path: str) -> dict[str, np.ndarray]:
  if not os.path.isfile(path):
    raise DataError(f"{path}: file does not exist")
  try:
    with np.load(path, allow_pickle=False) as npz:
      return {k: np.asarray(npz[k]) for k in npz.files}
  except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
    raise DataError(f"{path}: unreadable .npz ({e})") from e


def camera_from_npz(arrays: dict[str, np.ndarray], view: int, *,
                    path: str) -> tuple[np.ndarray, np.ndarray]:
  """(K [3, 3] at the stored size, cam_to_world [4, 4] in the normalised frame) of one view."""
  mats = {}
  for key in (f"world_mat_{view}", f"scale_mat_{view}"):
    if key not in arrays:
      raise DataError(f"{path}: has no {key!r} for view {view}")
    m = np.asarray(arrays[key], dtype=np.float64)
    if m.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(m)):
      raise DataError(f"{path}: {key!r} must be a finite 4×4 (or 3×4) matrix, found shape "
                      f"{m.shape}")
    mats[key] = m if m.shape == (4, 4) else np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
  scale = mats[f"scale_mat_{view}"]
  if abs(np.linalg.det(scale[:3, :3])) < 1e-12:
    raise DataError(f"{path}: 'scale_mat_{view}' is singular")
  projection = (mats[f"world_mat_{view}"] @ scale)[:3]  # [3, 4], normalised frame → pixels
  if np.linalg.matrix_rank(projection[:, :3]) < 3:
    raise DataError(f"{path}: 'world_mat_{view}' is not a camera projection (rank < 3)")
  parts = cameras.decompose_projection(projection)
  world_to_cam = np.eye(4)
  world_to_cam[:3, :3] = parts.rotation
  world_to_cam[:3, 3] = parts.translation
  cam_to_world = cameras.check_pose(cameras.rigid_inverse(world_to_cam),
                                    source=f"{path} (view {view})")
  return parts.intrinsics, cam_to_world


def eval_split_indices(num_views: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
  """(targets, source pool) of the evaluation protocol: every 8th view, and the rest."""
  targets = tuple(range(0, num_views, EVAL_TARGET_STRIDE))
  return targets, tuple(i for i in range(num_views) if i % EVAL_TARGET_STRIDE)


def read_scan(scan_dir: str, *, protocol: str, image_size: images.ImageSize, scene_scale: float,
              num_source_views: int) -> Scene:
  """One scan as a pooled-source Scene (see the module docstring for the protocols)."""
  if protocol not in PROTOCOLS:
    raise ValueError(f"read_scan: protocol must be one of {PROTOCOLS}, got {protocol!r}")
  if not os.path.isdir(scan_dir):
    raise DataError(f"{scan_dir}: scan folder does not exist")
  views = _view_images(scan_dir)
  npz_path = os.path.join(scan_dir, CAMERAS_FILE)
  arrays = _load_cameras(npz_path)
  stored = images.stored_size(views[0][1])
  for _, path in views:
    here = images.stored_size(path)
    if here != stored:
      raise DataError(f"{path}: image is {here[0]}×{here[1]} but {views[0][1]} is "
                      f"{stored[0]}×{stored[1]} (H×W); all views of a set must share one size")
  size = images.output_size(requested=image_size, stored=stored, path=scan_dir)
  rgbs, ks, poses = [], [], []
  for view, path in views:
    k, pose = camera_from_npz(arrays, view, path=npz_path)
    rgbs.append(images.downsample_area(images.read_rgb(path), size))
    ks.append(cameras.scale_intrinsics(k, stored=stored, size=size))
    poses.append(cameras.scale_translation(pose, scene_scale))
  n = len(views)
  if protocol == "train":
    targets, pool = tuple(range(n)), tuple(range(n))
    needed = num_source_views + 1  # the target itself is never its own source
  else:
    targets, pool = eval_split_indices(n)
    needed = num_source_views
  if len(pool) < needed:
    raise DataError(f"{scan_dir}: {n} views leave {len(pool)} candidate sources, too few for "
                    f"data.num_source_views={num_source_views}")
  return Scene(
      name=os.path.basename(os.path.normpath(scan_dir)),
      images=np.stack(rgbs).astype(np.float32),
      cam_to_world=np.stack(poses).astype(np.float32),
      intrinsics=np.stack(ks).astype(np.float32),
      source_indices=(),
      target_indices=targets,
      source_pool=pool,
      view_names=tuple(os.path.splitext(os.path.basename(p))[0] for _, p in views),
  )


def read_dtu_scans(root: str, scans: Sequence[str], *, protocol: str,
                   image_size: images.ImageSize, scene_scale: float,
                   num_source_views: int) -> list[Scene]:
  """The listed scans of `root`; every scan must share one image size."""
  scenes = [read_scan(os.path.join(root, s), protocol=protocol, image_size=image_size,
                      scene_scale=scene_scale, num_source_views=num_source_views) for s in scans]
  for scan, scene in zip(scans, scenes):
    if scene.image_size != scenes[0].image_size:
      raise DataError(f"{os.path.join(root, scan)}: images are {scene.image_size} but "
                      f"{scans[0]}'s are {scenes[0].image_size}; all scans must share one size")
  return scenes
