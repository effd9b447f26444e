"""Tests of the embedded data-set generator (docs/method.md §3.5) against independent NumPy code.

The references here never call the ray caster: primitives are described by exact signed distance
functions written from dataset.json's `parts`, cameras are read back from the written text files,
and visibility is decided by NumPy sphere tracing of those SDFs.
"""

import hashlib
import json
import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from slotlifter_jax.data import generator

# World-unit tolerance for "this point lies on that surface": float32 ray casting at distances of
# 8–25 units is good to ~1e-5; the smallest object is 0.35, so 2e-3 still tells surfaces apart.
SURFACE_TOL = 2e-3
SIZES = {"clevr": 48, "room": 40}  # odd-looking, distinct sizes so H/W mix-ups fail


# ---------------------------------------------------------------------------------------------
# Independent references: SDFs, inside tests, pinhole cameras
# ---------------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------------
# Ray–primitive intersections against brute-force ray marching
# ---------------------------------------------------------------------------------------------


def _scene_with(parts):
  objs = []
  for i, part in enumerate(parts):
    prim = generator.Primitive(part["kind"], tuple(part["centre"]), tuple(part["half_size"]),
                               part["yaw"])
    m = generator.Material(rgb=(100, 100, 100), rgb2=(100, 100, 100))
    objs.append(generator.SceneObject(
        label=i + 1, shape="cube", colour="gray", material_name="rubber", size="large",
        position=prim.centre, yaw=prim.yaw, bounding_radius=1.0, parts=(prim,), material=m))
  light = generator.Light((0.0, 0.0, 1.0), (1.0, 1.0, 1.0))
  spec = generator.SceneSpec(family="clevr", objects=tuple(objs), lights=(light,) * 3,
                             ambient=(0.1, 0.1, 0.1), floor=objs[0].material, walls=None)
  return generator.scene_arrays(spec)


PARTS = [
    {"kind": "box", "centre": [0.3, -0.2, 0.5], "half_size": [0.7, 0.35, 0.5], "yaw": 0.6},
    {"kind": "sphere", "centre": [-0.4, 0.5, 0.35], "half_size": [0.45] * 3, "yaw": 0.0},
    {"kind": "cylinder", "centre": [0.1, 0.2, -0.1], "half_size": [0.4, 0.4, 0.6], "yaw": 1.3},
]


@pytest.mark.parametrize("part", PARTS, ids=[p["kind"] for p in PARTS])
def test_intersection_matches_ray_marching(part):
  rng = np.random.default_rng(3)
  num_rays = 29
  origins = rng.normal(size=(num_rays, 3))
  origins = 4.0 * origins / np.linalg.norm(origins, axis=-1, keepdims=True) + part["centre"]
  # Aim at points around the primitive: some rays hit, some miss.
  reach = 1.3 * max(part["half_size"])
  targets = np.asarray(part["centre"]) + rng.uniform(-reach, reach, size=(num_rays, 3))
  directions = (targets - origins) * rng.uniform(0.5, 2.0, size=(num_rays, 1))  # not unit
  scene = _scene_with([part])
  t = np.asarray(generator.intersect_primitives(
      origins=jnp.asarray(origins, jnp.float32), directions=jnp.asarray(directions, jnp.float32),
      scene=scene))[:, 0]
  step = 2e-4
  ts = np.arange(0.0, 8.0 / np.linalg.norm(directions, axis=-1).min(), step)  # [S]
  points = origins[:, None, :] + ts[None, :, None] * directions[:, None, :]  # [R, S, 3]
  inside = inside_part(part, points)
  first = np.where(inside.any(-1), ts[np.argmax(inside, axis=-1)], np.inf)
  assert 3 <= np.isfinite(first).sum() <= num_rays - 3  # both hits and misses are exercised
  np.testing.assert_array_equal(np.isfinite(t), np.isfinite(first))
  hit = np.isfinite(first)
  np.testing.assert_allclose(t[hit], first[hit], atol=step + 1e-4)


@pytest.mark.parametrize("part", PARTS, ids=[p["kind"] for p in PARTS])
def test_normals_match_sdf_gradient(part):
  rng = np.random.default_rng(5)
  num_rays = 11
  origins = np.asarray(part["centre"]) + rng.normal(size=(num_rays, 3)) * 0.1 + [3.0, 1.0, 2.5]
  targets = np.asarray(part["centre"]) + rng.uniform(-0.2, 0.2, size=(num_rays, 3))
  directions = targets - origins
  scene = _scene_with([part])
  o, d = jnp.asarray(origins, jnp.float32), jnp.asarray(directions, jnp.float32)
  opts = generator.RenderOptions(walls=False)
  hit = generator.trace(origins=o, directions=d, scene=scene, options=opts)
  assert np.all(np.asarray(hit.surface) == 0)  # the primitive, not the floor
  normals = np.asarray(generator.surface_normals(origins=o, directions=d, hit=hit, scene=scene,
                                                 options=opts))
  points = origins + np.asarray(hit.t)[:, None] * directions
  np.testing.assert_allclose(part_sdf(part, points), 0.0, atol=1e-4)
  eps = 1e-4
  grad = np.stack([(part_sdf(part, points + eps * e) - part_sdf(part, points - eps * e)) / (2 * eps)
                   for e in np.eye(3)], -1)
  np.testing.assert_allclose(normals, grad / np.linalg.norm(grad, axis=-1, keepdims=True),
                             atol=2e-3)


def test_staged_render_matches_single_function_shading():
  """render_views runs compiled stages; shade() is the same maths as one function."""
  rng = generator.scene_rng(seed=2, family="clevr", split="train", index=0)
  spec = generator.sample_clevr_layout(rng)
  scene = generator.scene_arrays(spec)
  cams = np.stack([generator.camera_to_world(c) for c in generator.sample_cameras(rng, 2)])
  size, options = 21, generator.render_options("clevr", supersample=1)
  k = generator.uorf_intrinsics(size)
  out = generator.render_views(scene, cam_to_world=jnp.asarray(cams, jnp.float32),
                               intrinsics=jnp.asarray(k, jnp.float32), image_size=size,
                               options=options)
  origins, dirs = generator.camera_rays(
      cam_to_world=jnp.asarray(cams, jnp.float32), intrinsics=jnp.asarray(k, jnp.float32),
      image_size=size, offsets=jnp.zeros((1, 2), jnp.float32))
  o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
  hit = generator.trace(origins=o, directions=d, scene=scene, options=options)
  radiance = generator.shade(origins=o, directions=d, hit=hit, scene=scene, options=options,
                             shadows=True, bounce=True)
  expected = np.clip(np.asarray(radiance), 0, 1) ** (1 / generator.GAMMA)
  np.testing.assert_allclose(np.asarray(out.rgb).reshape(-1, 3), expected, atol=1e-5)
  # Shadows are there: without them the flat, untextured floor under directional lights would be
  # almost uniform (only its faint highlight varies).
  floor = np.asarray(radiance)[np.asarray(hit.surface) == scene.centre.shape[0]].sum(-1)
  assert floor.max() - floor.min() > 0.1
  np.testing.assert_array_equal(np.asarray(out.depth).ravel(), np.asarray(hit.t))


# ---------------------------------------------------------------------------------------------
# Generated data sets
# ---------------------------------------------------------------------------------------------


def _generate(root, family, **kw):
  args = dict(family=family, num_train=2, num_val=1, num_test=1, views=4,
              image_size=SIZES[family], seed=11, num_workers=1, progress=False)
  args.update(kw)
  return generator.generate_dataset(str(root), **args)


@pytest.fixture(scope="module")
def clevr_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("clevr")
  _generate(root, "clevr")
  return root


@pytest.fixture(scope="module")
def room_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("room")
  _generate(root, "room", num_val=0, num_test=0)
  return root


def _splits(root):
  out = []
  for name in sorted(os.listdir(root)):
    with open(os.path.join(root, name, "dataset.json")) as f:
      out.append((os.path.join(root, name), json.load(f)))
  return out


def _hash_tree(root):
  digests = {}
  for dirpath, _, files in os.walk(root):
    for name in files:
      path = os.path.join(dirpath, name)
      with open(path, "rb") as f:
        digests[os.path.relpath(path, root)] = hashlib.sha256(f.read()).hexdigest()
  return digests


def test_deterministic_and_independent_of_workers(clevr_root, tmp_path):
  # Two worker processes render the scenes in another order: the bytes must not change.
  _generate(tmp_path, "clevr", num_workers=2)
  first, second = _hash_tree(clevr_root), _hash_tree(tmp_path)
  assert len(first) == 3 + (2 + 1 + 1) * 4 * 5  # 3 dataset.json + 5 files per view
  assert first == second


def test_layout_and_metadata(clevr_root):
  splits = _splits(clevr_root)
  assert [os.path.basename(p) for p, _ in splits] == [
      "clevr_567_test", "clevr_567_train", "clevr_567_val"]
  seen = set()
  for path, meta in splits:
    h = w = SIZES["clevr"]
    assert meta["format"] == "slotlifter_jax.generated" and meta["generator_version"] == 1
    assert meta["image_size"] == [h, w] and meta["views_per_scene"] == 4
    assert meta["num_source_views"] == 1 and meta["scene_scale"] == pytest.approx(1 / 7)
    assert meta["camera"]["convention"] == "opencv_cam2world"
    assert meta["mask"]["label_grey_levels"][0] == 0
    assert sorted(meta["mask"]["label_grey_levels"]) == meta["mask"]["label_grey_levels"]
    files = sorted(os.listdir(path))
    assert "dataset.json" in files and not any(f.endswith(".partial") for f in files)
    for i, scene in enumerate(meta["scenes"]):
      assert scene["name"] not in seen  # scene names are unique over the splits
      seen.add(scene["name"])
      for a, stem in enumerate(scene["views"]):
        assert stem == f"{i * 4 + a:05d}_{scene['name']}_az{a:02d}"
        for suffix in (".png", "_RT.txt", "_intrinsics.txt", "_depth.npy", "_mask.png"):
          assert stem + suffix in files
        img = Image.open(os.path.join(path, stem + ".png"))
        assert img.mode == "RGB" and img.size == (w, h)
      objs = scene["objects"]
      assert 5 <= len(objs) <= 7
      assert [o["label"] for o in objs] == list(range(1, len(objs) + 1))
      for o in objs:
        assert o["colour"] in generator.CLEVR_COLOURS and o["material"] in ("rubber", "metal")
        assert o["shape"] in ("cube", "sphere", "cylinder")
        assert o["position"][2] == pytest.approx(o["radius"])  # resting on the ground
        assert max(abs(o["position"][0]), abs(o["position"][1])) <= 3.0
      for a in range(len(objs)):  # no interpenetration: bounding circles keep the 0.25 gap
        for b in range(a):
          gap = np.hypot(objs[a]["position"][0] - objs[b]["position"][0],
                         objs[a]["position"][1] - objs[b]["position"][1])
          assert gap >= objs[a]["bounding_radius"] + objs[b]["bounding_radius"] + 0.25 - 1e-9
      for cam in scene["cameras"]:
        assert abs(cam["radius"] - 12.4) <= 0.2 and abs(cam["elevation_deg"] - 40) <= 2


def _check_views(root, family):
  """Every pixel: its back-projected depth lies on the surface its mask label names."""
  checked_centres = visible_centres = 0
  for path, meta in _splits(root):
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


def test_clevr_views_consistent_with_geometry(clevr_root):
  _check_views(clevr_root, "clevr")


def test_room_views_consistent_with_geometry(room_root):
  _check_views(room_root, "room")
  (path, meta), = [s for s in _splits(room_root) if s[0].endswith("_train")]
  assert os.path.basename(path) == "room_chair_train"
  for scene in meta["scenes"]:
    assert 1 <= len(scene["objects"]) <= 4
    for o in scene["objects"]:
      assert o["shape"] == "chair" and len(o["parts"]) == 6
      legs = o["parts"][2:]
      assert all(p["centre"][2] == pytest.approx(p["half_size"][2]) for p in legs)  # on floor


def test_mask_png_grey_levels_survive_pil_l_conversion(clevr_root):
  path, meta = _splits(clevr_root)[1]
  stem = os.path.join(path, meta["scenes"][0]["views"][0])
  rgb = np.asarray(Image.open(stem + "_mask.png"))
  assert rgb.ndim == 3 and rgb.shape[-1] == 3
  assert np.all(rgb[..., 0] == rgb[..., 1]) and np.all(rgb[..., 1] == rgb[..., 2])
  grey = np.asarray(Image.open(stem + "_mask.png").convert("L"))
  np.testing.assert_array_equal(grey, rgb[..., 0])
  assert set(np.unique(grey)) <= set(meta["mask"]["label_grey_levels"])
  assert grey.min() == meta["mask"]["label_grey_levels"][0]  # background is the smallest level


def test_eight_views_have_four_sources(tmp_path):
  summary = generator.generate_dataset(
      str(tmp_path), family="clevr", num_train=1, num_val=0, num_test=0, views=8, image_size=17,
      seed=1, num_workers=1, progress=False)
  with open(os.path.join(summary["splits"]["train"]["path"], "dataset.json")) as f:
    meta = json.load(f)
  assert meta["views_per_scene"] == 8 and meta["num_source_views"] == 4
  assert [v[-4:] for v in meta["scenes"][0]["views"]] == [f"az{a:02d}" for a in range(8)]


def test_existing_split_is_kept_not_overwritten(clevr_root):
  before = _hash_tree(clevr_root)
  summary = _generate(clevr_root, "clevr")  # same parameters: nothing to do
  assert all(s.get("kept_existing") for s in summary["splits"].values())
  with pytest.raises(FileExistsError):
    _generate(clevr_root, "clevr", seed=12)
  assert _hash_tree(clevr_root) == before


def test_cli_refuses_to_overwrite(tmp_path):
  split = tmp_path / "clevr_567_train"
  split.mkdir()
  (split / "keep.txt").write_text("user data")
  cmd = [sys.executable, "-m", "slotlifter_jax.data.generate", "--family=clevr",
         f"--out={tmp_path}", "--num_train=1", "--num_val=0", "--num_test=0", "--image_size=16",
         "--num_workers=1", "--noprogress"]
  result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
  assert result.returncode != 0
  assert "exists" in result.stderr + result.stdout
  assert sorted(os.listdir(split)) == ["keep.txt"]
  assert not (tmp_path / "clevr_567_val").exists()


# ---------------------------------------------------------------------------------------------
# Easier CLEVR sets: min_objects / max_objects / object_scale
# ---------------------------------------------------------------------------------------------

# sha256 of `_scene_digest(generate_scene(default_rng(0), family="clevr", views=2, image_size=16))`
# computed with the generator before these options existed: the default draws must not change.
DEFAULT_SCENE_DIGEST = "7d31b5c718f938860003e8a40d0d7f51e0dce6d85e345af8f06a437795d856f1"
# The model's locality box (defaults.py: model.locality_box = 0.64 in the scene frame) in world
# units: 0.64 / scene_scale.
LOCALITY_BOX_WORLD = 0.64 / generator.SCENE_SCALE


def _rounded(x):
  """Floats to 9 significant digits, so the digest does not hang on a libm's last bit."""
  if isinstance(x, float):
    return float(f"{x:.9g}")
  if isinstance(x, dict):
    return {k: _rounded(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_rounded(v) for v in x]
  return x


def _scene_digest(scene):
  """What the random draws decide: objects, cameras, lights and the number of layouts drawn."""
  d = {"objects": [o.to_json() for o in scene.spec.objects],
       "cameras": [c.to_json() for c in scene.cameras],
       "lights": [{"direction": l.direction, "intensity": l.intensity} for l in scene.spec.lights],
       "attempts": scene.attempts}
  return hashlib.sha256(json.dumps(_rounded(d), sort_keys=True).encode()).hexdigest()


def test_default_object_options_leave_output_unchanged():
  kw = dict(family="clevr", views=2, image_size=16)
  default = generator.generate_scene(np.random.default_rng(0), **kw)
  assert _scene_digest(default) == DEFAULT_SCENE_DIGEST
  explicit = generator.generate_scene(np.random.default_rng(0), min_objects=5, max_objects=7,
                                      object_scale=1.0, **kw)
  for name in ("rgb", "label", "depth", "cam_to_world"):
    np.testing.assert_array_equal(getattr(explicit, name), getattr(default, name))
  assert explicit.spec == default.spec and explicit.attempts == default.attempts


def test_object_count_is_respected():
  for i in range(40):  # layouts only: cheap
    rng = np.random.default_rng(i)
    assert len(generator.sample_clevr_layout(rng, min_objects=2, max_objects=2).objects) == 2
    n = len(generator.sample_room_layout(rng, min_objects=1, max_objects=2).objects)
    assert 1 <= n <= 2


def test_scaled_objects_fit_on_floor_apart_and_inside_locality_box():
  scale = generator.MAX_OBJECT_SCALE  # the worst case
  counts = set()
  for i in range(100):
    spec = generator.sample_clevr_layout(np.random.default_rng(i), min_objects=1, max_objects=3,
                                         object_scale=scale)
    objs = [o.to_json() for o in spec.objects]
    counts.add(len(objs))
    for o in objs:
      (part,) = o["parts"]
      r = generator.CLEVR_SIZES[o["size"]] * scale
      assert o["radius"] == pytest.approx(r) and part["half_size"] == pytest.approx([r] * 3)
      assert o["position"][2] == pytest.approx(r)  # resting on the floor
      x, y, top = abs(o["position"][0]), abs(o["position"][1]), 2 * r
      # Inside the default scenes' footprint, and well inside the locality box.
      assert max(x, y) + o["bounding_radius"] <= generator.CLEVR_FOOTPRINT + 1e-9
      assert max(x, y) + o["bounding_radius"] <= LOCALITY_BOX_WORLD - 0.4
      assert top <= LOCALITY_BOX_WORLD - 1.0
    for a in range(len(objs)):
      for b in range(a):
        gap = np.hypot(objs[a]["position"][0] - objs[b]["position"][0],
                       objs[a]["position"][1] - objs[b]["position"][1])
        assert gap >= objs[a]["bounding_radius"] + objs[b]["bounding_radius"] + generator.MIN_GAP
  assert counts == {1, 2, 3}


def test_easy_set_has_two_objects_each_1p6_times_the_default_size(tmp_path):
  _generate(tmp_path, "clevr", num_train=2, num_val=0, num_test=0, views=2, image_size=24,
            min_objects=2, max_objects=2, object_scale=1.6)
  (path, meta), = [s for s in _splits(tmp_path) if s[0].endswith("_train")]
  assert meta["objects"] == {"min_objects": 2, "max_objects": 2, "object_scale": 1.6}
  for scene in meta["scenes"]:
    objs = scene["objects"]
    assert [o["label"] for o in objs] == [1, 2]
    for o in objs:
      assert o["radius"] == pytest.approx(1.6 * generator.CLEVR_SIZES[o["size"]])
      shape_factor = np.sqrt(2.0) if o["shape"] == "cube" else 1.0
      assert o["bounding_radius"] == pytest.approx(o["radius"] * shape_factor)
    # The source view shows both objects, each with its own label.
    labels = read_labels(os.path.join(path, scene["views"][0]), meta["mask"]["label_grey_levels"])
    assert set(np.unique(labels)) == {0, 1, 2}
  _check_views(tmp_path, "clevr")  # depths and masks agree with the (larger) geometry
  # The default set records no object options, so its dataset.json is unchanged.
  assert "objects" not in generator._split_header(
      family="clevr", split="train", seed=0, views=4, image_size=16, num_scenes=1, supersample=2,
      min_objects=5, max_objects=7)


def test_existing_split_with_other_object_options_is_not_kept(tmp_path):
  kw = dict(num_train=1, num_val=0, num_test=0, views=1, image_size=16)
  _generate(tmp_path, "clevr", min_objects=1, max_objects=1, **kw)
  with pytest.raises(FileExistsError):  # the default set's header lacks "objects": no match
    _generate(tmp_path, "clevr", **kw)


def test_bad_object_options_name_the_field():
  cases = [("clevr", dict(min_objects=4, max_objects=3), "min_objects"),
           ("clevr", dict(max_objects=8), "max_objects"),
           ("clevr", dict(object_scale=0.0), "object_scale"),
           ("clevr", dict(object_scale=2.5), "object_scale"),
           ("room", dict(object_scale=1.6), "object_scale")]
  for family, kw, field in cases:
    with pytest.raises(ValueError, match=field) as info:
      generator.check_object_options(family, **kw)
    assert info.value.field == field


def test_cache_name_changes_only_for_non_default_object_options():
  import ml_collections
  from slotlifter_jax import defaults
  from slotlifter_jax.data import embedded
  d = defaults.base_config().data
  default_name = os.path.basename(embedded.dataset_dir(d, seed=0))
  assert default_name == "clevr-v1-128px-4v-1000-100-100-s0"  # the name before the options
  old = d.to_dict()  # a config saved before the fields existed
  for k in ("min_objects", "max_objects", "object_scale"):
    del old[k]
  assert os.path.basename(embedded.dataset_dir(ml_collections.ConfigDict(old), seed=0)) == (
      default_name)
  d.min_objects, d.max_objects = 5, 7  # explicit defaults: the same set, the same folder
  assert os.path.basename(embedded.dataset_dir(d, seed=0)) == default_name
  d.min_objects, d.max_objects, d.object_scale = 1, 3, 1.6
  assert os.path.basename(embedded.dataset_dir(d, seed=0)) == default_name + "-o1-3-x1.6"


def test_cli_rejects_min_objects_above_max_objects(tmp_path):
  cmd = [sys.executable, "-m", "slotlifter_jax.data.generate", "--family=clevr",
         f"--out={tmp_path}", "--min_objects=3", "--max_objects=2", "--noprogress"]
  result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
  assert result.returncode != 0
  last = result.stderr.strip().splitlines()[-1]
  assert last.startswith("error: --min_objects") and "max_objects" in last
  assert not os.listdir(tmp_path)
