"""Independent references for the generator's tests: exact signed distance functions written from
dataset.json's `parts`, cameras read back from the written text files, NumPy sphere tracing of
those SDFs, and a per-pixel check of written views against them. None of it calls the ray caster.
"""

import json
import os

import numpy as np
import pytest
from PIL import Image

from slotlifter_jax.data import generator

# World-unit tolerance for "this point lies on that surface": float32 ray casting at distances of
# 8–25 units is good to ~1e-5; the smallest object is 0.35, so 2e-3 still tells surfaces apart.
SURFACE_TOL = 2e-3
SIZES = {"clevr": 48, "room": 40}  # odd-looking, distinct sizes so H/W mix-ups fail


def _to_local(points, centre, yaw):
  p = np.asarray(points, np.float64) - np.asarray(centre, np.float64)
  c, s = np.cos(yaw), np.sin(yaw)
  return np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1], p[..., 2]], -1)


def part_sdf(part, points):
  """Exact Euclidean signed distance to one primitive: [..., 3] → [...]."""
  q = _to_local(points, part["centre"], part["yaw"])
  h = np.asarray(part["half_size"], np.float64)
  if part["kind"] == "sphere":
    return np.linalg.norm(q, axis=-1) - h[0]
  if part["kind"] == "box":
    e = np.abs(q) - h
    return np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(-1), 0.0)
  assert part["kind"] == "cylinder"
  e = np.stack([np.linalg.norm(q[..., :2], axis=-1) - h[0], np.abs(q[..., 2]) - h[2]], -1)
  return np.linalg.norm(np.maximum(e, 0.0), axis=-1) + np.minimum(e.max(-1), 0.0)


def object_sdf(obj, points):
  return np.min([part_sdf(p, points) for p in obj["parts"]], axis=0)


def inside_part(part, points):
  return part_sdf(part, points) <= 0.0


def read_camera(stem):
  """cam2world [4, 4] and pixel K [3, 3] from the written text files (uOCF normalised K)."""
  c2w = np.loadtxt(stem + "_RT.txt")
  kn = np.loadtxt(stem + "_intrinsics.txt")
  h, w = np.load(stem + "_depth.npy").shape
  k = np.array([[kn[0, 0] * w, 0, (kn[0, 2] + 1) * w / 2],
                [0, kn[1, 1] * h, (kn[1, 2] + 1) * h / 2], [0, 0, 1]])
  return c2w, k


def pixel_rays(c2w, k, us, vs):
  """World ray origins and camera-z-normalised directions through pixel coordinates."""
  d_cam = np.stack([(us - k[0, 2]) / k[0, 0], (vs - k[1, 2]) / k[1, 1], np.ones_like(us)], -1)
  return np.broadcast_to(c2w[:3, 3], d_cam.shape), d_cam @ c2w[:3, :3].T


def read_labels(stem, grey_levels):
  grey = np.asarray(Image.open(stem + "_mask.png").convert("L"))
  lut = np.full(256, -1)
  lut[np.asarray(grey_levels)] = np.arange(len(grey_levels))
  return lut[grey]


def background_sdf(points, wall_half):
  d = points[..., 2]  # floor z = 0
  if wall_half is not None:  # inner faces of the walls, seen from inside the room
    d = np.minimum(d, wall_half - np.max(np.abs(points[..., :2]), axis=-1))
  return d


def sphere_trace(origins, directions, objects, wall_half, t_far=60.0):
  """First hit along rays by sphere tracing the exact SDFs: (t in camera-z units, label or 0).

  Starts outside the room (walls are one-sided in the renderer), so the walls only count once the
  ray is inside the square |x|, |y| ≤ wall_half.
  """
  dn = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
  t = np.zeros(origins.shape[:-1])
  if wall_half is not None:  # enter the room first
    with np.errstate(divide="ignore", invalid="ignore"):
      lo = np.max(np.minimum((-wall_half - origins[..., :2]) / dn[..., :2],
                             (wall_half - origins[..., :2]) / dn[..., :2]), axis=-1)
    t = np.maximum(lo, 0.0) + 1e-3  # past the (one-sided, invisible) near wall
  owner_labels = np.array([o["label"] for o in objects] + [0])  # the last entry: background
  label = np.full(t.shape, -1)
  for _ in range(2000):
    p = origins + t[..., None] * dn
    dists = np.stack([object_sdf(o, p) for o in objects] + [background_sdf(p, wall_half)])
    d = dists.min(axis=0)
    label = np.where((d < 1e-6) & (label < 0), owner_labels[dists.argmin(axis=0)], label)
    t = np.where(label < 0, t + np.maximum(d, 0.0), t)
    if np.all((label >= 0) | (t > t_far)):
      break
  z = t / np.linalg.norm(directions, axis=-1)  # camera-z depth (directions have z_cam = 1)
  return z, label


def generate_small(root, family, **kw):
  """A small set (2/1/1 scenes, 4 views, SIZES[family] pixels) written to `root`; `kw` overrides."""
  args = dict(family=family, num_train=2, num_val=1, num_test=1, views=4,
              image_size=SIZES[family], seed=11, num_workers=1, progress=False)
  args.update(kw)
  return generator.generate_dataset(str(root), **args)


def read_splits(root):
  """[(split folder, its dataset.json)] in name order."""
  out = []
  for name in sorted(os.listdir(root)):
    with open(os.path.join(root, name, "dataset.json")) as f:
      out.append((os.path.join(root, name), json.load(f)))
  return out


def check_views(root, family):
  """Every pixel: its back-projected depth lies on the surface its mask label names."""
  checked_centres = visible_centres = 0
  for path, meta in read_splits(root):
    levels = meta["mask"]["label_grey_levels"]
    wall_half = meta["background"]["wall_half_size"]
    threshold = generator.min_visible_pixels(meta["image_size"][0])
    for scene in meta["scenes"]:
      objs = scene["objects"]
      for a, stem in enumerate(scene["views"]):
        stem = os.path.join(path, stem)
        c2w, k = read_camera(stem)
        # The camera looks at the origin from the recorded distance.
        cam = scene["cameras"][a]
        assert np.linalg.norm(c2w[:3, 3]) == pytest.approx(cam["radius"], abs=1e-6)
        np.testing.assert_allclose(c2w[:3, 2], -c2w[:3, 3] / np.linalg.norm(c2w[:3, 3]),
                                   atol=1e-6)
        assert c2w[2, 1] < 0  # image "down" (y) points down in the world (z up)
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-8)
        labels = read_labels(stem, levels)
        assert labels.min() >= 0  # every grey level is one of the recorded ones
        assert set(np.unique(labels)) <= {0} | {o["label"] for o in objs}
        depth = np.load(stem + "_depth.npy")
        assert depth.dtype == np.float32 and depth.min() > 0
        h, w = depth.shape
        vs, us = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64),
                             indexing="ij")
        origins, dirs = pixel_rays(c2w, k, us, vs)
        points = origins + depth[..., None] * dirs  # [H, W, 3]
        sdfs = np.stack([object_sdf(o, points) for o in objs])  # [O, H, W]
        for o, sdf in zip(objs, sdfs):
          on = labels == o["label"]
          assert np.all(np.abs(sdf[on]) < SURFACE_TOL), (stem, o["label"])
        bg = labels == 0
        assert np.all(np.abs(background_sdf(points[bg], wall_half)) < SURFACE_TOL)
        assert np.all(sdfs[:, bg] > -SURFACE_TOL)
        if a == 0:  # every object is visible in the source view
          counts = np.bincount(labels.ravel(), minlength=len(objs) + 1)
          assert np.all(counts[1:] >= threshold), counts
        # Project each object's centre; if sphere tracing finds that object first along the
        # pixel-centre ray (it is not occluded there), the mask must name it and the depth
        # must match the traced one.
        centres = np.array([o["position"] for o in objs])
        cam_pts = (centres - c2w[:3, 3]) @ c2w[:3, :3]
        u = np.rint(k[0, 0] * cam_pts[:, 0] / cam_pts[:, 2] + k[0, 2]).astype(int)
        v = np.rint(k[1, 1] * cam_pts[:, 1] / cam_pts[:, 2] + k[1, 2]).astype(int)
        inside = (cam_pts[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        o_r, d_r = pixel_rays(c2w, k, u[inside].astype(float), v[inside].astype(float))
        z, first = sphere_trace(o_r, d_r, objs, wall_half)
        seen_objs = [o for o, ok in zip(objs, inside) if ok]
        for obj, ui, vi, zi, fi in zip(seen_objs, u[inside], v[inside], z, first):
          checked_centres += 1
          if fi == obj["label"]:
            visible_centres += 1
            assert labels[vi, ui] == obj["label"], (stem, obj["label"])
            assert depth[vi, ui] == pytest.approx(zi, abs=SURFACE_TOL)
  # The centre check is not vacuous: most objects are seen at their own centre pixel.
  assert visible_centres >= 0.5 * checked_centres > 0
