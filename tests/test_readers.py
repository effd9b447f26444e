"""Readers on small fixtures in the real formats (docs/method.md §3), against the values written."""

import logging
import os

import chex
import ml_collections
import numpy as np
from PIL import Image
import pytest
from scipy.spatial.transform import Rotation

import data_fixtures as fx
from slotlifter_jax.data import cameras
from slotlifter_jax.data import dtu
from slotlifter_jax.data import images
from slotlifter_jax.data import registry
from slotlifter_jax.data import scannet
from slotlifter_jax.data import uorf

SCALE = 1.0 / 7.0


def read(folder, **kw):
  args = dict(data_format="uorf", subset="clevr_567", scene_scale=SCALE, image_size=0,
              num_source_views=1)
  args.update(kw)
  return uorf.read_uorf_split(str(folder), **args)


def data_config(**kw):
  d = ml_collections.ConfigDict(dict(
      format="uorf", root="", subset="clevr_567", scene_scale=SCALE, image_size=0,
      num_source_views=1, views_per_scene=4, num_val_scenes=1, has_masks=True))
  d.update(kw)
  return d


def expected_pose(world_pose):
  out = world_pose.copy()
  out[:3, 3] *= SCALE
  return out


def test_uorf_views_poses_and_default_intrinsics(tmp_path):
  folder = tmp_path / "clevr_567_train"
  truth = fx.write_uorf_split(folder, num_scenes=3, views=4, size=(7, 7))
  before = fx.folder_hash(folder)
  scenes = read(folder)
  assert fx.folder_hash(folder) == before
  assert [s.name for s in scenes] == ["sc0000", "sc0001", "sc0002"]
  for scene in scenes:
    stems = truth["stems"][scene.name]
    assert scene.view_names == tuple(stems)
    chex.assert_shape(scene.images, (4, 7, 7, 3))
    np.testing.assert_allclose(scene.images, np.stack([truth["rgb"][s] for s in stems]) / 255.0,
                               atol=1e-7)
    np.testing.assert_allclose(scene.cam_to_world,
                               np.stack([expected_pose(truth["pose"][s]) for s in stems]),
                               atol=1e-6)
    # uORF camera at 7×7 (docs/method.md §3.1): fx = 1.09375·W, fy = 1.458333·H, image centre.
    k = np.array([[1.09375 * 7, 0, 3.0], [0, 1.4583333 * 7, 3.0], [0, 0, 1]])
    np.testing.assert_allclose(scene.intrinsics, np.broadcast_to(k, (4, 3, 3)), rtol=1e-6)
    assert scene.source_indices == (0,)
    assert scene.novel_indices == (1, 2, 3)
    assert scene.masks is None and scene.depth is None and scene.objects is None


def test_official_principal_point_flag(tmp_path):
  folder = tmp_path / "clevr_567_train"
  fx.write_uorf_split(folder, num_scenes=1, size=(16, 16))
  k = read(folder, official_principal_point=True)[0].intrinsics[0]
  assert k[0, 2] == pytest.approx(16 / 2 - 16 / 512) and k[1, 2] == pytest.approx(16 / 2 - 16 / 512)
  # At 128 this is the official 63.75 = W/2 − 0.25.
  assert cameras.uorf_intrinsics(height=128, width=128,
                                 official_principal_point=True)[0, 2] == pytest.approx(63.75)


def test_look_at_cam_to_world_sees_the_target_upright():
  rng = np.random.default_rng(0)
  k = cameras.uorf_intrinsics(height=64, width=64)
  for _ in range(20):
    eye, target = rng.uniform(-10, 10, size=3), rng.uniform(-1, 1, size=3)
    pose = cameras.look_at_cam_to_world(eye, target)
    cameras.check_pose(pose, source="look_at")  # rigid, det +1, bottom row (0, 0, 0, 1)
    np.testing.assert_allclose(pose[:3, 3], eye)
    assert pose[2, 0] == pytest.approx(0.0, abs=1e-12)  # camera x (right) is horizontal
    world_to_cam = cameras.rigid_inverse(pose)

    def project(point):
      p = world_to_cam[:3, :3] @ point + world_to_cam[:3, 3]
      return (k @ p)[:2] / p[2], p[2]

    # The target lies on the optical axis (the principal point) at its distance, in front.
    pix, depth = project(target)
    np.testing.assert_allclose(pix, [31.5, 31.5], atol=1e-9)
    assert depth == pytest.approx(np.linalg.norm(target - eye))
    # World up is up in the image: a point above the target has a smaller row.
    assert project(target + [0.0, 0.0, 0.5])[0][1] < 31.5
  # The default target is the origin.
  np.testing.assert_allclose(cameras.look_at_cam_to_world(np.array([3.0, -2.0, 4.0])),
                             cameras.look_at_cam_to_world(np.array([3.0, -2.0, 4.0]), np.zeros(3)))


def test_uorf_background_is_second_smallest_grey(tmp_path):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_uorf_split(folder, num_scenes=1, size=(7, 7), masks=True,
                              mask_greys=(30, 64, 120, 200))
  scene = read(folder)[0]
  rule = {30: 1, 64: 0, 120: 2, 200: 3}  # second-smallest → 0, smallest → 1, others keep rank
  for i, stem in enumerate(truth["stems"]["sc0000"]):
    expected = np.vectorize(rule.get)(truth["grey"][stem])
    np.testing.assert_array_equal(scene.masks[i], expected)
  assert scene.masks.dtype == np.int32 and scene.mask_views.all()


def test_room_texture_background_is_smallest_grey(tmp_path):
  folder = tmp_path / "room_texture_test"
  truth = fx.write_uorf_split(folder, num_scenes=1, size=(7, 7), masks=True, intrinsics=True,
                              mask_greys=(10, 80, 150))
  scene = read(folder, data_format="uocf", subset="room_texture")[0]
  rule = {10: 0, 80: 1, 150: 2}
  for i, stem in enumerate(truth["stems"]["sc0000"]):
    np.testing.assert_array_equal(scene.masks[i], np.vectorize(rule.get)(truth["grey"][stem]))
  # Normalised K (f' = f/W, c' = 2c/W − 1) back in pixels: the written c' = −1/W is (W − 1)/2.
  np.testing.assert_allclose(scene.intrinsics[0], [[1.09375 * 7, 0, 3], [0, 1.458333 * 7, 3],
                                                   [0, 0, 1]], rtol=1e-6)


def test_coloured_uorf_masks_go_through_pil_luma(tmp_path):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_uorf_split(folder, num_scenes=1, views=2, size=(5, 5))
  # Luma: blue 29 < red 76 < green 150 < white 255, so red (second smallest) is the background.
  colours = np.array([[0, 0, 255], [255, 0, 0], [0, 255, 0], [255, 255, 255]], np.uint8)
  want = np.array([1, 0, 2, 3])
  rng = np.random.default_rng(3)
  picks = {}
  for stem in truth["stems"]["sc0000"]:
    pick = rng.integers(0, 4, size=(5, 5))
    pick[0, :4] = np.arange(4)
    fx.save_rgb(folder / f"{stem}_mask.png", colours[pick])
    picks[stem] = pick
  scene = read(folder)[0]
  for i, stem in enumerate(truth["stems"]["sc0000"]):
    np.testing.assert_array_equal(scene.masks[i], want[picks[stem]])


def test_masks_only_on_some_views_are_marked(tmp_path):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_uorf_split(folder, num_scenes=1, size=(7, 7), masks=True)
  os.remove(folder / f"{truth['stems']['sc0000'][0]}_mask.png")
  scene = read(folder)[0]
  np.testing.assert_array_equal(scene.mask_views, [False, True, True, True])


def test_kitchen_sets_have_no_masks(tmp_path):
  folder = tmp_path / "kitchen_matte_test"
  fx.write_uorf_split(folder, num_scenes=1, size=(7, 7), masks=True, intrinsics=True)
  scene = read(folder, data_format="uocf", subset="kitchen_matte")[0]
  assert scene.masks is None and scene.mask_views is None
  assert read(folder, data_format="uocf", subset="room_texture", has_masks=False)[0].masks is None


def test_ignored_suffixes_are_not_views(tmp_path):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_uorf_split(folder, num_scenes=2, size=(7, 7), masks=True)
  plain = read(folder)
  stem = truth["stems"]["sc0001"][2]
  for suffix in ("_mask_for_moving", "_moved", "_mask_for_bg", "_mask_for_providing_bg",
                 "_changed", "_providing_bg", "_depth"):
    fx.save_rgb(folder / f"{stem}{suffix}.png", np.zeros((3, 5, 3), np.uint8))  # other size too
  (folder / "files.csv").write_text("written by the official loader\n")
  (folder / "README").write_text("not a view\n")
  with_extras = read(folder)
  assert [s.view_names for s in with_extras] == [s.view_names for s in plain]
  for a, b in zip(plain, with_extras):
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.masks, b.masks)


def test_generated_folder(tmp_path):
  folder = tmp_path / "clevr_567_val"
  truth = fx.write_generated_split(folder, split="val", num_scenes=2, views=5, size=(7, 7))
  before = fx.folder_hash(folder)
  scenes = read(folder, views_per_scene=5, split="val")
  assert fx.folder_hash(folder) == before
  for scene, entry in zip(scenes, truth["manifest"]["scenes"]):
    stems = entry["views"]
    assert scene.name == entry["name"] and scene.view_names == tuple(stems)
    # Grey 17·l is label l in every view (a table, not a per-view ranking).
    np.testing.assert_array_equal(scene.masks, np.stack([truth["labels"][s] for s in stems]))
    assert scene.mask_views.all()
    np.testing.assert_allclose(scene.depth, np.stack([truth["depth"][s] for s in stems]) * SCALE,
                               rtol=1e-6)
    assert scene.objects == entry["objects"]
    np.testing.assert_allclose(scene.intrinsics[0], [[1.09375 * 7, 0, 3], [0, 1.458333 * 7, 3],
                                                     [0, 0, 1]], rtol=1e-6)


def test_resize_uorf_box_filter_nearest_masks_and_depth(tmp_path):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_generated_split(folder, split="test", num_scenes=1, size=(8, 8))
  scene = read(folder, image_size=4)[0]
  for i, stem in enumerate(truth["stems"]["sc0000"]):
    rgb = truth["rgb"][stem] / 255.0
    blocks = rgb.reshape(4, 2, 4, 2, 3).mean(axis=(1, 3))  # 2×2 box filter
    np.testing.assert_allclose(scene.images[i], blocks, atol=1e-6)
    # Nearest: the sample under each output centre is input pixel 2i + 1 (centre at 2i + ½).
    np.testing.assert_array_equal(scene.masks[i], truth["labels"][stem][1::2, 1::2])
    np.testing.assert_allclose(scene.depth[i], truth["depth"][stem][1::2, 1::2] * SCALE,
                               rtol=1e-6)
  np.testing.assert_allclose(scene.intrinsics[0], [[1.09375 * 4, 0, 1.5], [0, 1.458333 * 4, 1.5],
                                                   [0, 0, 1]], rtol=1e-6)


def test_resize_keeps_a_projected_point_on_its_scaled_pixel(tmp_path):
  """The f×f block around a 3D point's projection becomes the pixel the point now projects to."""
  for data_format, stored, size in (("uorf", 12, 6), ("uocf", 12, 4)):
    f = stored // size
    folder = tmp_path / f"{data_format}_{size}" / "clevr_567_train"
    truth = fx.write_uorf_split(folder, num_scenes=1, size=(stored, stored),
                                intrinsics=data_format == "uocf")
    c = (stored - 1) / 2  # the uORF camera, which the fixture's uOCF file also encodes
    k = np.array([[1.09375 * stored, 0, c], [0, 1.458333 * stored, c], [0, 0, 1]])
    points, pixels = [], []
    for i, stem in enumerate(truth["stems"]["sc0000"]):
      row, col = i % size, (2 * i + 1) % size  # the output pixel this view's point should hit
      u, v = f * col + (f - 1) / 2, f * row + (f - 1) / 2  # centre of its f×f input block
      pose = truth["pose"][stem]
      ray = pose[:3, :3] @ np.linalg.solve(k, [u, v, 1.0])
      points.append(pose[:3, 3] + 11.0 * ray)  # world point that projects to (u, v)
      pixels.append((col, row))
      img = np.zeros((stored, stored, 3), np.uint8)
      img[f * row:f * row + f, f * col:f * col + f] = 255
      fx.save_rgb(folder / f"{stem}.png", img)
    scene = read(folder, data_format=data_format,
                 subset="room_texture" if data_format == "uocf" else "clevr_567",
                 image_size=size)[0]
    for i, (point, (col, row)) in enumerate(zip(points, pixels)):
      want = np.zeros((size, size, 3), np.float32)
      want[row, col] = 1.0
      np.testing.assert_allclose(scene.images[i], want, atol=1e-6)
      cam = cameras.rigid_inverse(scene.cam_to_world[i].astype(np.float64)) @ np.append(
          point * SCALE, 1.0)
      projected = (scene.intrinsics[i].astype(np.float64) @ cam[:3])[:2] / cam[2]
      np.testing.assert_allclose(projected, [col, row], atol=1e-4)


def test_area_downsampling_and_nearest_indices_against_brute_force():
  rng = np.random.default_rng(0)
  for (hi, wi), (ho, wo) in (((12, 15), (5, 6)), ((9, 9), (3, 3)), ((7, 10), (7, 4))):
    img = rng.uniform(size=(hi, wi, 2))
    # Split every input pixel into ho × wo equal sub-pixels: each output cell is then exactly
    # hi × wi whole sub-pixels, so the area mean is a plain block mean.
    fine = np.repeat(np.repeat(img, ho, axis=0), wo, axis=1)  # [hi·ho, wi·wo, 2]
    brute = fine.reshape(ho, hi, wo, wi, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(images.downsample_area(img, (ho, wo)), brute, atol=1e-12)
    np.testing.assert_allclose(images.downsample_area(img[..., 0], (ho, wo)), brute[..., 0],
                               atol=1e-12)
    centres = (np.arange(ho) + 0.5) * hi / ho  # output centres in input edge coordinates
    np.testing.assert_array_equal(images.nearest_indices(hi, ho),
                                  np.minimum(np.floor(centres + 1e-9), hi - 1).astype(int))


def test_dtu_cameras_recovered_from_npz(tmp_path):
  truth = fx.write_dtu_scan(tmp_path, "scan1", num_views=10, size=(6, 8))
  before = fx.folder_hash(tmp_path)
  scene = dtu.read_scan(str(tmp_path / "scan1"), protocol="train", image_size=0, scene_scale=1.0,
                        num_source_views=3)
  assert fx.folder_hash(tmp_path) == before
  np.testing.assert_allclose(scene.intrinsics, truth["k"], rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(scene.cam_to_world, truth["cam_to_world"], atol=1e-5)
  np.testing.assert_allclose(scene.images, truth["rgb"] / 255.0, atol=1e-7)
  assert scene.target_indices == tuple(range(10)) and scene.source_pool == tuple(range(10))
  assert scene.source_indices == ()
  evaluation = dtu.read_scan(str(tmp_path / "scan1"), protocol="eval", image_size=0,
                             scene_scale=1.0, num_source_views=3)
  assert evaluation.target_indices == (0, 8)
  assert evaluation.source_pool == (1, 2, 3, 4, 5, 6, 7, 9)


def test_decompose_projection_signs():
  rng = np.random.default_rng(0)
  for scale in (1.0, -3.0, 0.01):
    k = np.array([[500.0, 0.3, 200.0], [0.0, 480.0, 150.0], [0.0, 0.0, 1.0]])
    r = fx.random_rotation(rng)
    t = rng.normal(size=3)
    parts = cameras.decompose_projection(scale * k @ np.c_[r, t])
    np.testing.assert_allclose(parts.intrinsics, k, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(parts.rotation, r, atol=1e-9)
    np.testing.assert_allclose(parts.translation, t, atol=1e-9)


def _mix_distance(poses, target):
  """0.5·angle + 0.5·centre distance with scipy's rotation magnitude (independent reference)."""
  out = []
  for p in poses:
    angle = Rotation.from_matrix(poses[target][:3, :3].T @ p[:3, :3]).magnitude()
    out.append(0.5 * angle + 0.5 * np.linalg.norm(p[:3, 3] - poses[target][:3, 3]))
  return np.array(out)


def test_dtu_registry_splits_and_per_target_sources(tmp_path):
  for i, scan in enumerate(("scan1", "scan4", "scan9", "scan12")):
    fx.write_dtu_scan(tmp_path, scan, num_views=10, size=(6, 8), seed=i)
  (tmp_path / "new_train.lst").write_text("scan1\nscan4\n\nscan9\n")
  (tmp_path / "new_val.lst").write_text("scan12\n")
  before = fx.folder_hash(tmp_path)
  d = data_config(format="dtu", root=str(tmp_path), num_source_views=3, scene_scale=1.0,
                  num_val_scenes=1)
  train = registry.load_split(d, "train")
  val = registry.load_split(d, "val")
  test = registry.load_split(d, "test")
  assert fx.folder_hash(tmp_path) == before
  assert [s.name for s in train] == ["scan1", "scan4"]
  assert [s.name for s in val] == ["scan9/000000", "scan9/000008"]
  assert [s.name for s in test] == ["scan12/000000", "scan12/000008"]
  full = dtu.read_scan(str(tmp_path / "scan12"), protocol="eval", image_size=0, scene_scale=1.0,
                       num_source_views=3)
  for scene, target in zip(test, (0, 8)):
    assert scene.num_views == 4 and scene.source_indices == (0, 1, 2)
    assert scene.novel_indices == (3,)
    dist = _mix_distance(full.cam_to_world.astype(np.float64), target)
    pool = [i for i in range(10) if i % 8]
    nearest = sorted(pool, key=lambda i: dist[i])[:3]
    np.testing.assert_array_equal(scene.images, full.images[nearest + [target]])


def test_scannet_scene_frames_poses_intrinsics(tmp_path, caplog):
  truth = fx.write_scannet_scene(tmp_path, "scene0001_00", frames=(0, 5, 10, 20, 100), size=(6, 8),
                                 bad_frames=(20,))
  before = fx.folder_hash(tmp_path)
  with caplog.at_level(logging.WARNING):
    scene = scannet.read_scene(str(tmp_path / "scene0001_00"), protocol="train", image_size=0,
                               scene_scale=1.0, num_source_views=2)
  assert fx.folder_hash(tmp_path) == before
  assert scene.view_names == ("0", "5", "10", "100")  # numeric order, the -inf pose skipped
  assert any("20.txt" in r.getMessage() for r in caplog.records)
  np.testing.assert_allclose(scene.cam_to_world,
                             np.stack([truth["pose"][f] for f in scene.view_names]), atol=1e-6)
  sx, sy = 8 / 1296, 6 / 968  # native colour camera → stored frames, pixel centres at integers
  k = fx.NATIVE_K
  want = np.array([[k[0, 0] * sx, 0, (k[0, 2] + 0.5) * sx - 0.5],
                   [0, k[1, 1] * sy, (k[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
  np.testing.assert_allclose(scene.intrinsics, np.broadcast_to(want, (4, 3, 3)), rtol=1e-5)
  jpg = np.asarray(Image.open(tmp_path / "scene0001_00" / "color_480640" / "100.jpg")) / 255.0
  np.testing.assert_allclose(scene.images[3], jpg, atol=1e-6)
  assert scene.masks is None and scene.target_indices == (0, 1, 2, 3)


def test_scannet_test_scene_targets_and_instances(tmp_path):
  truth = fx.write_scannet_scene(tmp_path, "scene0079_00", frames=(0, 10, 20, 30, 40, 50),
                                 size=(6, 8), test_split=((0, 20, 30, 50), (10, 40)))
  scene = scannet.read_scene(str(tmp_path / "scene0079_00"), protocol="test", image_size=0,
                             scene_scale=1.0, num_source_views=2)
  assert scene.view_names == ("0", "20", "30", "50", "10", "40")
  assert scene.target_indices == (4, 5) and scene.source_pool == (0, 1, 2, 3)
  np.testing.assert_array_equal(scene.mask_views, [False] * 4 + [True] * 2)
  np.testing.assert_array_equal(scene.masks[4], truth["instance"]["10"])
  np.testing.assert_array_equal(scene.masks[5], truth["instance"]["40"])


def test_scannet_registry_train_val_test(tmp_path):
  for i in range(3):
    fx.write_scannet_scene(tmp_path, f"scene01{i:02d}_00", frames=(0, 1, 2, 3, 4, 5, 6, 7, 8),
                           size=(6, 8), seed=i)
  for i, name in enumerate(scannet.NERFINGMVS_TEST_SCENES):
    fx.write_scannet_scene(tmp_path, name, frames=(0, 1, 2, 3), size=(6, 8), seed=10 + i,
                           test_split=((0, 1, 3), (2,)))
  before = fx.folder_hash(tmp_path)
  d = data_config(format="scannet", root=str(tmp_path), num_source_views=2, scene_scale=1.0,
                  num_val_scenes=1)
  train = registry.load_split(d, "train")
  val = registry.load_split(d, "val")
  test = registry.load_split(d, "test")
  assert fx.folder_hash(tmp_path) == before
  assert [s.name for s in train] == ["scene0100_00", "scene0101_00"]
  assert [s.name for s in val] == ["scene0102_00/0", "scene0102_00/8"]  # every 8th frame
  assert [s.name for s in test] == [f"{n}/2" for n in scannet.NERFINGMVS_TEST_SCENES]
  assert all(s.num_views == 3 and s.mask_views.tolist() == [False, False, True] for s in test)


def test_registry_uorf_holds_out_validation_scenes(tmp_path):
  fx.write_uorf_split(tmp_path / "room_chair" / "room_chair_train", num_scenes=4, size=(7, 7))
  fx.write_uorf_split(tmp_path / "room_chair" / "room_chair_test", num_scenes=2, size=(7, 7),
                      masks=True, first_scene=4)
  before = fx.folder_hash(tmp_path)
  d = data_config(root=str(tmp_path), subset="room_chair", num_val_scenes=1)
  assert [s.name for s in registry.load_split(d, "train")] == ["sc0000", "sc0001", "sc0002"]
  assert [s.name for s in registry.load_split(d, "val")] == ["sc0003"]
  test = registry.load_split(d, "test")
  assert [s.name for s in test] == ["sc0004", "sc0005"] and test[0].masks is not None
  assert [s.name for s in registry.load_split(d, "train", max_scenes=2)] == ["sc0000", "sc0001"]
  assert fx.folder_hash(tmp_path) == before


@pytest.mark.slow  # renders with JAX: ~10 s idle, ~30 s on a busy 2-core host
def test_registry_reads_a_real_generator_folder(tmp_path):
  generator = pytest.importorskip("slotlifter_jax.data.generator")
  generator.generate_dataset(str(tmp_path), family="clevr", num_train=1, num_val=1, num_test=1,
                             views=3, image_size=8, seed=0, num_workers=1, progress=False,
                             supersample=1)
  before = fx.folder_hash(tmp_path)
  d = data_config(root=str(tmp_path), views_per_scene=3, image_size=8)
  for split in ("train", "val", "test"):
    (scene,) = registry.load_split(d, split)
    assert scene.masks is not None and scene.depth is not None and scene.objects
    assert scene.masks.max() <= len(scene.objects)
    chex.assert_shape(scene.images, (3, 8, 8, 3))
  assert fx.folder_hash(tmp_path) == before


def _project(pose, k, point):
  """Pixel of a world point in a cam2world pose (a NumPy pinhole, independent of the readers)."""
  cam = np.linalg.inv(pose) @ np.append(point, 1.0)
  uvw = k @ cam[:3]
  return uvw[:2] / uvw[2]


def test_source_azimuth_frame_turns_scene_so_source_sits_at_azimuth_zero(tmp_path):
  truth = fx.write_uorf_split(tmp_path / "clevr_567_train", num_scenes=3, views=4, size=(6, 6))
  world = registry.load_split(data_config(root=str(tmp_path)), "train")
  turned = registry.load_split(data_config(root=str(tmp_path), frame="source_azimuth"), "train")
  assert len(world) == len(turned) == 2
  for a, b in zip(world, turned):
    stems = truth["stems"][a.name]
    centre = truth["pose"][stems[0]][:3, 3] * SCALE
    azimuth = np.arctan2(centre[1], centre[0])
    # The source camera now stands at azimuth 0, at its own radius and height.
    src = b.cam_to_world[0, :3, 3].astype(np.float64)
    np.testing.assert_allclose(src, [np.hypot(centre[0], centre[1]), 0.0, centre[2]], atol=1e-5)
    # Every view turned by the same rotation about z (scipy's, an independent reference) ...
    turn = Rotation.from_euler("z", -azimuth).as_matrix()
    for v, stem in enumerate(stems):
      expected = expected_pose(truth["pose"][stem])
      expected[:3, :] = turn @ expected[:3, :]
      np.testing.assert_allclose(b.cam_to_world[v], expected, atol=1e-5)
    # ... so a point turned with the scene lands on the same pixel of every view.
    point = np.array([0.2, -0.1, 0.05])
    for v in range(a.num_views):
      np.testing.assert_allclose(
          _project(b.cam_to_world[v].astype(np.float64), b.intrinsics[v], turn @ point),
          _project(a.cam_to_world[v].astype(np.float64), a.intrinsics[v], point), atol=1e-4)
    np.testing.assert_array_equal(a.images, b.images)


def test_source_azimuth_frame_rejects_pooled_sources_and_unknown_frames(tmp_path):
  for i, scan in enumerate(("scan1", "scan4", "scan9")):
    fx.write_dtu_scan(tmp_path, scan, num_views=10, size=(6, 8), seed=i)
  (tmp_path / "new_train.lst").write_text("scan1\nscan4\nscan9\n")
  (tmp_path / "new_val.lst").write_text("scan9\n")
  d = data_config(format="dtu", root=str(tmp_path), num_source_views=3, scene_scale=1.0,
                  frame="source_azimuth")
  with pytest.raises(registry.DataError, match=r"scan1: data.frame='source_azimuth' needs fixed"):
    registry.load_split(d, "train")
  d.frame = "camera"
  with pytest.raises(registry.DataError, match=r"data.frame must be one of .*'camera'"):
    registry.load_split(d, "train")


def test_source_azimuth_frame_names_a_scene_whose_source_has_no_azimuth(tmp_path):
  truth = fx.write_uorf_split(tmp_path / "clevr_567_train", num_scenes=3, views=4, size=(6, 6))
  stem = truth["stems"]["sc0001"][0]  # sc0001's source view: straight above the scene's centre
  overhead = np.eye(4)  # camera-to-world, built by hand: look_at cannot look along its up axis z
  overhead[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down
  overhead[:3, 3] = [0.0, 0.0, 12.4]
  np.savetxt(tmp_path / "clevr_567_train" / f"{stem}_RT.txt", overhead, fmt="%.8f")
  with pytest.raises(registry.DataError, match=r"sc0001: data.frame='source_azimuth': view 0"):
    registry.load_split(data_config(root=str(tmp_path), frame="source_azimuth"), "train")
