"""Small data-set folders in the real on-disk formats (docs/method.md §3), written with PIL / NumPy.

Each writer returns the ground truth it wrote (uint8 pixels, world-unit poses, K, label maps), so a
test can compare a reader's output with values that never went through the code under test.
"""

from __future__ import annotations

import hashlib
import json
import math
import os

import numpy as np
from PIL import Image


def folder_hash(root) -> str:
  """SHA-256 over every file's relative path, size and bytes (and every folder's name)."""
  h = hashlib.sha256()
  for dirpath, dirnames, filenames in sorted(os.walk(root)):
    dirnames.sort()
    h.update(("D:" + os.path.relpath(dirpath, root)).encode())
    for name in sorted(filenames):
      path = os.path.join(dirpath, name)
      with open(path, "rb") as f:
        data = f.read()
      h.update(f"F:{os.path.relpath(path, root)}:{len(data)}".encode())
      h.update(data)
  return h.hexdigest()


def look_at(eye, target=(0.0, 0.0, 0.0)) -> np.ndarray:
  """OpenCV cam2world (x right, y down, z forward) looking from `eye` at `target`, world z up."""
  eye = np.asarray(eye, np.float64)
  forward = np.asarray(target, np.float64) - eye
  forward /= np.linalg.norm(forward)
  right = np.cross(forward, [0.0, 0.0, 1.0])
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  pose = np.eye(4)
  pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
  return pose


def orbit_pose(azimuth_deg: float, *, radius: float = 12.4, elevation_deg: float = 40.0):
  az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
  eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
  return look_at(eye)


def save_rgb(path, rgb: np.ndarray) -> None:
  Image.fromarray(np.asarray(rgb, np.uint8), "RGB").save(path)


def write_uorf_split(folder, *, num_scenes=2, views=4, size=(6, 6), masks=False,
                     intrinsics=False, mask_greys=(30, 64, 120, 200), seed=0,
                     first_scene=0) -> dict:
  """A uORF (or, with `intrinsics`, uOCF) split folder; masks use the given grey levels.

  Returns {"stems": {scene: [stems]}, "rgb": {stem: uint8}, "pose": {stem: world 4×4},
  "grey": {stem: uint8 grey map}, "k_norm": normalised K written (or None)}.
  """
  rng = np.random.default_rng(seed)
  os.makedirs(folder, exist_ok=True)
  height, width = size
  truth = {"stems": {}, "rgb": {}, "pose": {}, "grey": {}, "k_norm": None}
  k_norm = np.array([[1.09375, 0.0, -1.0 / width], [0.0, 1.458333, -1.0 / height],
                     [0.0, 0.0, 1.0]])
  index = 0
  for s in range(first_scene, first_scene + num_scenes):
    name = f"sc{s:04d}"
    truth["stems"][name] = []
    for v in range(views):
      stem = f"{index:05d}_{name}_az{v:02d}"
      index += 1
      rgb = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
      save_rgb(os.path.join(folder, stem + ".png"), rgb)
      pose = orbit_pose(rng.uniform(0, 360), elevation_deg=rng.uniform(30, 50))
      np.savetxt(os.path.join(folder, stem + "_RT.txt"), pose, fmt="%.8f")
      if masks:
        grey = np.asarray(mask_greys, np.uint8)[rng.integers(0, len(mask_greys), size=size)]
        grey[0, :len(mask_greys)] = mask_greys  # every level present in every mask
        save_rgb(os.path.join(folder, stem + "_mask.png"), np.repeat(grey[..., None], 3, -1))
        truth["grey"][stem] = grey
      if intrinsics:
        np.savetxt(os.path.join(folder, stem + "_intrinsics.txt"), k_norm, fmt="%.10f")
        truth["k_norm"] = k_norm
      truth["stems"][name].append(stem)
      truth["rgb"][stem] = rgb
      truth["pose"][stem] = pose
  return truth


GREY_LEVELS = [0, 17, 34, 51]  # label l ↦ grey 17·l, as our generator draws masks


def write_generated_split(folder, *, split="train", num_scenes=2, views=4, size=(6, 6),
                          seed=0) -> dict:
  """A folder in our generator's contract: uORF files + intrinsics, depth, masks, dataset.json."""
  truth = write_uorf_split(folder, num_scenes=num_scenes, views=views, size=size, masks=False,
                           intrinsics=True, seed=seed)
  rng = np.random.default_rng(seed + 1)
  truth["labels"], truth["depth"] = {}, {}
  scenes = []
  for name, stems in truth["stems"].items():
    for stem in stems:
      labels = rng.integers(0, len(GREY_LEVELS), size=size)
      grey = np.asarray(GREY_LEVELS, np.uint8)[labels]
      save_rgb(os.path.join(folder, stem + "_mask.png"), np.repeat(grey[..., None], 3, -1))
      depth = rng.uniform(8.0, 16.0, size=size).astype(np.float32)
      np.save(os.path.join(folder, stem + "_depth.npy"), depth)
      truth["labels"][stem], truth["depth"][stem] = labels, depth
    scenes.append({"name": name, "views": list(stems),
                   "objects": [{"label": l, "shape": "cube", "position": [float(l), 0.5, 0.35]}
                               for l in range(1, len(GREY_LEVELS))]})
  manifest = {
      "format": "slotlifter_jax.generated", "generator_version": 1, "family": "clevr",
      "split": split, "seed": seed, "image_size": list(size), "views_per_scene": views,
      "num_source_views": 1, "scene_scale": 1.0 / 7.0,
      "camera": {"convention": "opencv_cam2world"},
      "mask": {"background_label": 0, "label_grey_levels": GREY_LEVELS,
               "max_objects": len(GREY_LEVELS) - 1},
      "scenes": scenes,
  }
  with open(os.path.join(folder, "dataset.json"), "w") as f:
    json.dump(manifest, f, indent=1)
  truth["manifest"] = manifest
  return truth


def random_rotation(rng) -> np.ndarray:
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q @ np.diag(np.sign(np.diag(r)))
  return q if np.linalg.det(q) > 0 else -q


def write_dtu_scan(root, scan, *, num_views=10, size=(6, 8), seed=0, negative_view=1) -> dict:
  """A rs_dtu_4 scan: image/NNNNNN.png and cameras.npz built from known K, R, t and a scale matrix.

  Returns the normalised-frame truth: K [N, 3, 3] and cam_to_world [N, 4, 4].
  """
  rng = np.random.default_rng(seed)
  height, width = size
  os.makedirs(os.path.join(root, scan, "image"), exist_ok=True)
  scale, centre = 1.7, np.array([0.3, -0.2, 5.0])
  scale_mat = np.eye(4)
  scale_mat[:3, :3] *= scale
  scale_mat[:3, 3] = centre
  arrays, ks, poses, rgbs = {}, [], [], []
  for i in range(num_views):
    k = np.array([[rng.uniform(7, 9), rng.uniform(-0.01, 0.01), rng.uniform(3, 4)],
                  [0.0, rng.uniform(7, 9), rng.uniform(2, 3)], [0.0, 0.0, 1.0]])
    cam_to_world_norm = orbit_pose(rng.uniform(0, 360), radius=rng.uniform(2, 3),
                                   elevation_deg=rng.uniform(10, 60))
    # World frame = scale·(normalised frame) + centre: same rotation, moved and scaled centre.
    cam_to_world_world = cam_to_world_norm.copy()
    cam_to_world_world[:3, 3] = scale * cam_to_world_norm[:3, 3] + centre
    world_to_cam = np.linalg.inv(cam_to_world_world)
    k4 = np.eye(4)
    k4[:3, :3] = k
    world_mat = k4 @ world_to_cam
    if i == negative_view:
      world_mat = -2.5 * world_mat  # same camera, negative overall scale
    arrays[f"world_mat_{i}"] = world_mat
    arrays[f"scale_mat_{i}"] = scale_mat
    arrays[f"camera_mat_{i}"] = k4  # IDR files carry extra keys; readers ignore them
    rgb = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    save_rgb(os.path.join(root, scan, "image", f"{i:06d}.png"), rgb)
    ks.append(k)
    poses.append(cam_to_world_norm)
    rgbs.append(rgb)
  np.savez(os.path.join(root, scan, "cameras.npz"), **arrays)
  return {"k": np.stack(ks), "cam_to_world": np.stack(poses), "rgb": np.stack(rgbs)}


NATIVE_K = np.array([[1170.2, 0.0, 647.8], [0.0, 1170.2, 483.8], [0.0, 0.0, 1.0]])


def write_scannet_scene(root, name, *, frames=(0, 10, 20, 100), size=(6, 8), seed=0,
                        bad_frames=(), test_split=None) -> dict:
  """A ScanNet scene folder; `bad_frames` get a -inf pose; `test_split` = (pool, targets)."""
  rng = np.random.default_rng(seed)
  height, width = size
  scene = os.path.join(root, name)
  for sub in ("color_480640", "pose", "intrinsic", "instance"):
    os.makedirs(os.path.join(scene, sub), exist_ok=True)
  k4 = np.eye(4)
  k4[:3, :3] = NATIVE_K
  np.savetxt(os.path.join(scene, "intrinsic", "intrinsic_color.txt"), k4, fmt="%.6f")
  truth = {"pose": {}, "instance": {}}
  for f in frames:
    rgb = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(os.path.join(scene, "color_480640", f"{f}.jpg"), quality=95)
    pose = look_at(rng.uniform(-2, 2, size=3) + [0, 0, 1.5], target=rng.uniform(-1, 1, size=3))
    if f in bad_frames:
      pose = np.full((4, 4), -np.inf)
    np.savetxt(os.path.join(scene, "pose", f"{f}.txt"), pose, fmt="%.8f")
    instance = rng.integers(0, 40, size=size).astype(np.uint16)
    Image.fromarray(instance.astype(np.uint8)).save(os.path.join(scene, "instance", f"{f}.png"))
    truth["pose"][str(f)] = pose
    truth["instance"][str(f)] = instance
  if test_split is not None:
    pool, targets = test_split
    with open(os.path.join(scene, "train.txt"), "w") as fh:
      fh.write("\n".join(f"{f}.jpg" for f in pool) + "\n")
    with open(os.path.join(scene, "test.txt"), "w") as fh:
      fh.write("\n".join(str(f) for f in targets) + "\n")
  return truth


def write_eval(folder, rows, *, differs=None, step=100, parameters=None):
  """An evaluation folder as --mode=eval writes it: per_scene.csv rows, metrics.json."""
  os.makedirs(folder)
  names = sorted({k for r in rows.values() for k in r})
  with open(os.path.join(folder, "per_scene.csv"), "w") as f:
    f.write(",".join(["index", "scene", "num_views"] + names) + "\n")
    for i, (scene, r) in enumerate(rows.items()):
      f.write(",".join([str(i), scene, "4"] + [repr(float(r.get(k, math.nan))) for k in names])
              + "\n")
  with open(os.path.join(folder, "metrics.json"), "w") as f:
    meta = {"checkpoint": {"step": step}, "differs_from_training": differs or {}}
    if parameters:  # written since --params; older evaluations lack it
      meta["parameters"] = parameters
    json.dump(meta, f)
  return str(folder)
