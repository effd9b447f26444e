"""Tests of the embedded data-set generator (docs/method.md §3.5) against independent NumPy code.

The references (generator_refs.py) never call the ray caster: primitives are described by exact
signed distance functions written from dataset.json's `parts`, cameras are read back from the
written text files, and visibility is decided by NumPy sphere tracing of those SDFs. The easier
CLEVR sets' options are tested in test_generator_objects.py.
"""

import hashlib
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from generator_refs import SIZES, check_views, generate_small, inside_part, part_sdf, read_splits
from slotlifter_jax.data import generator


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


@pytest.fixture(scope="module")
def clevr_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("clevr")
  generate_small(root, "clevr")
  return root


@pytest.fixture(scope="module")
def room_root(tmp_path_factory):
  root = tmp_path_factory.mktemp("room")
  generate_small(root, "room", num_val=0, num_test=0)
  return root


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
  generate_small(tmp_path, "clevr", num_workers=2)
  first, second = _hash_tree(clevr_root), _hash_tree(tmp_path)
  assert len(first) == 4 + (2 + 1 + 1 + 1) * 4 * 5  # 4 dataset.json + 5 files per view
  assert first == second


def test_layout_and_metadata(clevr_root):
  splits = read_splits(clevr_root)
  assert [os.path.basename(p) for p, _ in splits] == [
      "clevr_567_dev", "clevr_567_test", "clevr_567_train", "clevr_567_val"]
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


def test_clevr_views_consistent_with_geometry(clevr_root):
  check_views(clevr_root, "clevr")


def test_room_views_consistent_with_geometry(room_root):
  check_views(room_root, "room")
  (path, meta), = [s for s in read_splits(room_root) if s[0].endswith("_train")]
  assert os.path.basename(path) == "room_chair_train"
  for scene in meta["scenes"]:
    assert 1 <= len(scene["objects"]) <= 4
    for o in scene["objects"]:
      assert o["shape"] == "chair" and len(o["parts"]) == 6
      legs = o["parts"][2:]
      assert all(p["centre"][2] == pytest.approx(p["half_size"][2]) for p in legs)  # on floor


def test_mask_png_grey_levels_survive_pil_l_conversion(clevr_root):
  path, meta = read_splits(clevr_root)[1]
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
  summary = generate_small(clevr_root, "clevr")  # same parameters: nothing to do
  assert all(s.get("kept_existing") for s in summary["splits"].values())
  with pytest.raises(FileExistsError):
    generate_small(clevr_root, "clevr", seed=12)
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


def test_worker_renders_on_cpu_when_jax_platforms_names_only_a_gpu():
  """A training process started with JAX_PLATFORMS=cuda hands that variable to the pool's
  workers; their initializer must still put them on the CPU. Here no GPU exists, so a worker left
  on "cuda" cannot start a backend at all."""
  code = ("from slotlifter_jax.data import writer; writer._worker_init(); import jax; "
          "print(jax.devices()[0].platform)")
  env = dict(os.environ, JAX_PLATFORMS="cuda")
  out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=120)
  assert out.returncode == 0, out.stderr[-2000:]
  assert out.stdout.split()[-1] == "cpu"


def test_scene_without_cpu_backend_renders_on_default_device(monkeypatch):
  """Where JAX_PLATFORMS leaves no CPU backend, asking for one raises; the scene is then rendered
  on the default device, the same scene (here the default device is the CPU)."""
  kw = dict(family="clevr", views=2, image_size=16)
  reference = generator.generate_scene(np.random.default_rng(3), **kw)
  real = jax.local_devices

  def no_cpu(*args, backend=None, **kwargs):
    if backend == "cpu":
      raise RuntimeError("Unknown backend cpu. Available backends are ['cuda']")
    return real(*args, backend=backend, **kwargs)

  monkeypatch.setattr(jax, "local_devices", no_cpu)
  scene = generator.generate_scene(np.random.default_rng(3), **kw)
  for name in ("rgb", "label", "depth", "cam_to_world"):
    np.testing.assert_array_equal(getattr(scene, name), getattr(reference, name))
