"""Bad input on disk → DataError naming the file and the problem, raised while loading, and the
folder left byte-for-byte as it was (readers never write)."""

import json
import os

import ml_collections
import numpy as np
from PIL import Image
import pytest

import data_fixtures as fx
from slotlifter_jax.data import registry
from slotlifter_jax.data import scannet
from slotlifter_jax.data import uorf
from slotlifter_jax.data.types import DataError

SIZE = (6, 6)


def _stems(truth, scene="sc0001"):
  return truth["stems"][scene]


def _write_pose(path, pose):
  np.savetxt(path, pose, fmt="%.8f")


# ---- uORF-style folders: each breaker returns the path the message must name -------------------

def image_without_pose(d, t):
  stem = _stems(t)[1]
  os.remove(d / f"{stem}_RT.txt")
  return d / f"{stem}.png"


def pose_without_image(d, t):
  stem = _stems(t)[2]
  os.remove(d / f"{stem}.png")
  os.remove(d / f"{stem}_mask.png")
  return d / f"{stem}_RT.txt"


def mask_without_image(d, t):
  stem = _stems(t)[3]
  os.remove(d / f"{stem}.png")
  os.remove(d / f"{stem}_RT.txt")
  return d / f"{stem}_mask.png"


def unknown_view_like_file(d, t):
  path = d / f"{_stems(t)[0]}_normals.png"
  fx.save_rgb(path, np.zeros(SIZE + (3,), np.uint8))
  return path


def view_with_wrong_extension(d, t):
  path = d / f"{_stems(t)[0]}.jpg"
  Image.fromarray(np.zeros(SIZE + (3,), np.uint8)).save(path)
  return path


def pose_not_4x4(d, t):
  path = d / f"{_stems(t)[1]}_RT.txt"
  _write_pose(path, t["pose"][_stems(t)[1]][:3])
  return path


def pose_not_numeric(d, t):
  path = d / f"{_stems(t)[1]}_RT.txt"
  path.write_text("1 0 0 0\n0 1 zero 0\n0 0 1 0\n0 0 0 1\n")
  return path


def pose_non_finite(d, t):
  path = d / f"{_stems(t)[1]}_RT.txt"
  pose = t["pose"][_stems(t)[1]].copy()
  pose[0, 3] = np.nan
  _write_pose(path, pose)
  return path


def pose_not_orthonormal(d, t):
  path = d / f"{_stems(t)[2]}_RT.txt"
  pose = t["pose"][_stems(t)[2]].copy()
  pose[:3, :3] *= 1.01
  _write_pose(path, pose)
  return path


def pose_is_a_reflection(d, t):
  path = d / f"{_stems(t)[2]}_RT.txt"
  pose = t["pose"][_stems(t)[2]].copy()
  pose[:3, 0] *= -1  # orthonormal, det −1
  _write_pose(path, pose)
  return path


def pose_bad_bottom_row(d, t):
  path = d / f"{_stems(t)[2]}_RT.txt"
  pose = t["pose"][_stems(t)[2]].copy()
  pose[3, 2] = 0.5
  _write_pose(path, pose)
  return path


def image_of_another_size(d, t):
  path = d / f"{_stems(t)[2]}.png"
  fx.save_rgb(path, np.zeros((SIZE[0] + 1, SIZE[1]), np.uint8)[..., None].repeat(3, -1))
  return path


def mask_of_another_size(d, t):
  path = d / f"{_stems(t)[2]}_mask.png"
  fx.save_rgb(path, np.zeros((SIZE[0], SIZE[1] + 2, 3), np.uint8))
  return path


def empty_folder(d, t):
  for name in os.listdir(d):
    os.remove(d / name)
  return d


def corrupt_png(d, t):
  path = d / f"{_stems(t)[3]}.png"
  path.write_bytes(b"\x89PNG\r\n\x1a\n this is not image data")
  return path


def truncated_png(d, t):
  path = d / f"{_stems(t)[3]}.png"
  fx.save_rgb(path, np.random.default_rng(0).integers(0, 256, SIZE + (3,), dtype=np.uint8))
  data = path.read_bytes()
  path.write_bytes(data[:len(data) // 2])
  return path


def corrupt_mask_png(d, t):
  path = d / f"{_stems(t)[0]}_mask.png"
  path.write_bytes(b"garbage")
  return path


def scenes_with_different_view_counts(d, t):
  stem = _stems(t)[3]
  for suffix in (".png", "_RT.txt", "_mask.png"):
    os.remove(d / f"{stem}{suffix}")
  return d / f"{_stems(t)[0]}.png"


def uocf_missing_intrinsics(d, t):
  for stems in t["stems"].values():
    for stem in stems:
      np.savetxt(d / f"{stem}_intrinsics.txt", [[1.09375, 0, 0], [0, 1.458333, 0], [0, 0, 1]])
  path = d / f"{_stems(t)[1]}_intrinsics.txt"
  os.remove(path)
  return path


def uocf_bad_intrinsics(d, t):
  uocf_missing_intrinsics(d, t)
  path = d / f"{_stems(t)[1]}_intrinsics.txt"
  np.savetxt(path, np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1]]))
  return path


UORF_CASES = {
    "image_without_pose": (image_without_pose, {}),
    "pose_without_image": (pose_without_image, {}),
    "mask_without_image": (mask_without_image, {}),
    "unknown_view_like_file": (unknown_view_like_file, {}),
    "view_with_wrong_extension": (view_with_wrong_extension, {}),
    "pose_not_4x4": (pose_not_4x4, {}),
    "pose_not_numeric": (pose_not_numeric, {}),
    "pose_non_finite": (pose_non_finite, {}),
    "pose_not_orthonormal": (pose_not_orthonormal, {}),
    "pose_is_a_reflection": (pose_is_a_reflection, {}),
    "pose_bad_bottom_row": (pose_bad_bottom_row, {}),
    "image_of_another_size": (image_of_another_size, {}),
    "mask_of_another_size": (mask_of_another_size, {}),
    "empty_folder": (empty_folder, {}),
    "corrupt_png": (corrupt_png, {}),
    "truncated_png": (truncated_png, {}),
    "corrupt_mask_png": (corrupt_mask_png, {}),
    "scenes_with_different_view_counts": (scenes_with_different_view_counts, {}),
    "views_per_scene_differs_from_config": (lambda d, t: d, {"views_per_scene": 5}),
    "uocf_missing_intrinsics": (uocf_missing_intrinsics,
                                {"data_format": "uocf", "subset": "room_texture"}),
    "uocf_bad_intrinsics": (uocf_bad_intrinsics,
                            {"data_format": "uocf", "subset": "room_texture"}),
    "image_size_larger_than_stored": (lambda d, t: d, {"image_size": SIZE[0] + 2}),
}


def _read_uorf(folder, **kw):
  args = dict(data_format="uorf", subset="clevr_567", scene_scale=1 / 7, image_size=0,
              num_source_views=1)
  args.update(kw)
  return uorf.read_uorf_split(str(folder), **args)


def _expect_data_error(root, load, named):
  before = fx.folder_hash(root)
  with pytest.raises(DataError) as err:
    load()
  assert str(named) in str(err.value), str(err.value)
  assert fx.folder_hash(root) == before
  return str(err.value)


@pytest.mark.parametrize("case", sorted(UORF_CASES))
def test_uorf_folder(tmp_path, case):
  folder = tmp_path / "clevr_567_test"
  truth = fx.write_uorf_split(folder, num_scenes=2, views=4, size=SIZE, masks=True)
  breaker, kwargs = UORF_CASES[case]
  named = breaker(folder, truth)
  _expect_data_error(tmp_path, lambda: _read_uorf(folder, **kwargs), named)


def test_missing_folder(tmp_path):
  folder = tmp_path / "clevr_567_test"
  message = _expect_data_error(tmp_path, lambda: _read_uorf(folder), folder)
  assert "does not exist" in message


def test_missing_split_folder_in_registry(tmp_path):
  d = ml_collections.ConfigDict(dict(
      format="uorf", root=str(tmp_path), subset="clevr_567", scene_scale=1 / 7, image_size=0,
      num_source_views=1, views_per_scene=4, num_val_scenes=1, has_masks=True))
  _expect_data_error(tmp_path, lambda: registry.load_split(d, "test"),
                     tmp_path / "clevr_567_test")


# ---- generated folders (dataset.json) ------------------------------------------------------------

def _edit_manifest(d, edit):
  path = d / "dataset.json"
  manifest = json.loads(path.read_text())
  edit(manifest)
  path.write_text(json.dumps(manifest))
  return path


def bad_json(d, t):
  path = d / "dataset.json"
  path.write_text('{"format": "slotlifter_jax.generated", ')
  return path


def wrong_format(d, t):
  return _edit_manifest(d, lambda m: m.update(format="uorf"))


def wrong_version(d, t):
  return _edit_manifest(d, lambda m: m.update(generator_version=2))


def missing_keys(d, t):
  return _edit_manifest(d, lambda m: m.pop("mask"))


def wrong_split(d, t):
  return _edit_manifest(d, lambda m: m.update(split="train"))


def listed_view_missing(d, t):
  _edit_manifest(d, lambda m: m["scenes"][1]["views"].append("99999_sc0001_az09"))
  return d / "99999_sc0001_az09.png"


def view_not_listed(d, t):
  stem = t["manifest"]["scenes"][0]["views"][2]
  _edit_manifest(d, lambda m: m["scenes"][0]["views"].remove(stem))
  return d / f"{stem}.png"


def scene_not_listed(d, t):
  _edit_manifest(d, lambda m: m["scenes"].pop(1))
  return d / f"{_stems(t)[0]}.png"


def image_size_mismatch(d, t):
  return _edit_manifest(d, lambda m: m.update(image_size=[SIZE[0] * 2, SIZE[1] * 2]))


def scene_scale_mismatch(d, t):
  return _edit_manifest(d, lambda m: m.update(scene_scale=0.1))


def grey_level_not_in_table(d, t):
  path = d / f"{_stems(t)[1]}_mask.png"
  grey = np.full(SIZE, 99, np.uint8)
  fx.save_rgb(path, np.repeat(grey[..., None], 3, -1))
  return path


def mask_not_grey(d, t):
  path = d / f"{_stems(t)[1]}_mask.png"
  rgb = np.zeros(SIZE + (3,), np.uint8)
  rgb[2, 3] = (17, 0, 17)
  fx.save_rgb(path, rgb)
  return path


def missing_depth(d, t):
  path = d / f"{_stems(t)[2]}_depth.npy"
  os.remove(path)
  return path


def depth_of_another_shape(d, t):
  path = d / f"{_stems(t)[2]}_depth.npy"
  np.save(path, np.ones((SIZE[0], SIZE[1] + 1), np.float32))
  return path


def missing_mask(d, t):
  path = d / f"{_stems(t)[0]}_mask.png"
  os.remove(path)
  return path


GENERATED_CASES = {f.__name__: f for f in (
    bad_json, wrong_format, wrong_version, missing_keys, wrong_split, listed_view_missing,
    view_not_listed, scene_not_listed, image_size_mismatch, scene_scale_mismatch,
    grey_level_not_in_table, mask_not_grey, missing_depth, depth_of_another_shape, missing_mask)}


@pytest.mark.parametrize("case", sorted(GENERATED_CASES))
def test_generated_folder(tmp_path, case):
  folder = tmp_path / "clevr_567_val"
  truth = fx.write_generated_split(folder, split="val", num_scenes=2, views=4, size=SIZE)
  named = GENERATED_CASES[case](folder, truth)
  _expect_data_error(tmp_path, lambda: _read_uorf(folder, split="val"), named)


# ---- DTU ----------------------------------------------------------------------------------------

def _dtu_root(tmp_path):
  for i, scan in enumerate(("scan1", "scan4")):
    fx.write_dtu_scan(tmp_path, scan, num_views=9, size=(4, 5), seed=i)
  (tmp_path / "new_train.lst").write_text("scan1\nscan4\n")
  return ml_collections.ConfigDict(dict(
      format="dtu", root=str(tmp_path), subset="", scene_scale=1.0, image_size=0,
      num_source_views=3, views_per_scene=4, num_val_scenes=0, has_masks=False))


def _npz_without(path, key):
  arrays = dict(np.load(path))
  arrays.pop(key)
  np.savez(path, **arrays)


def dtu_missing_world_mat(root):
  path = root / "scan4" / "cameras.npz"
  _npz_without(path, "world_mat_3")
  return path


def dtu_missing_scale_mat(root):
  path = root / "scan1" / "cameras.npz"
  _npz_without(path, "scale_mat_0")
  return path


def dtu_corrupt_npz(root):
  path = root / "scan1" / "cameras.npz"
  path.write_bytes(b"PK\x03\x04 broken")
  return path


def dtu_missing_list(root):
  path = root / "new_train.lst"
  os.remove(path)
  return path


def dtu_missing_scan(root):
  (root / "new_train.lst").write_text("scan1\nscan4\nscan7\n")
  return root / "scan7"


def dtu_misnamed_image(root):
  path = root / "scan1" / "image" / "left.png"
  fx.save_rgb(path, np.zeros((4, 5, 3), np.uint8))
  return path


def dtu_image_of_another_size(root):
  path = root / "scan4" / "image" / "000002.png"
  fx.save_rgb(path, np.zeros((5, 5, 3), np.uint8))
  return path


DTU_CASES = {f.__name__: f for f in (
    dtu_missing_world_mat, dtu_missing_scale_mat, dtu_corrupt_npz, dtu_missing_list,
    dtu_missing_scan, dtu_misnamed_image, dtu_image_of_another_size)}


@pytest.mark.parametrize("case", sorted(DTU_CASES))
def test_dtu(tmp_path, case):
  d = _dtu_root(tmp_path)
  named = DTU_CASES[case](tmp_path)
  _expect_data_error(tmp_path, lambda: registry.load_split(d, "train"), named)


# ---- ScanNet -------------------------------------------------------------------------------------

def _scannet_scene(tmp_path):
  fx.write_scannet_scene(tmp_path, "scene0079_00", frames=(0, 10, 20, 30, 40), size=(6, 8),
                         test_split=((0, 10, 30), (20, 40)))
  return tmp_path / "scene0079_00"


def scannet_missing_pose(scene):
  path = scene / "pose" / "30.txt"
  os.remove(path)
  return path


def scannet_pose_not_rigid(scene):
  path = scene / "pose" / "10.txt"
  np.savetxt(path, np.diag([2.0, 1.0, 1.0, 1.0]))
  return path


def scannet_missing_instance(scene):
  path = scene / "instance" / "40.png"
  os.remove(path)
  return path


def scannet_listed_frame_missing(scene):
  (scene / "test.txt").write_text("20\n40\n50\n")
  return scene / "color_480640" / "50.jpg"


def scannet_missing_intrinsics(scene):
  path = scene / "intrinsic" / "intrinsic_color.txt"
  os.remove(path)
  return path


def scannet_missing_test_list(scene):
  path = scene / "test.txt"
  os.remove(path)
  return path


def scannet_all_targets_nonfinite(scene):
  for f in (20, 40):
    np.savetxt(scene / "pose" / f"{f}.txt", np.full((4, 4), np.inf))
  return scene


SCANNET_CASES = {f.__name__: f for f in (
    scannet_missing_pose, scannet_pose_not_rigid, scannet_missing_instance,
    scannet_listed_frame_missing, scannet_missing_intrinsics, scannet_missing_test_list,
    scannet_all_targets_nonfinite)}


@pytest.mark.parametrize("case", sorted(SCANNET_CASES))
def test_scannet(tmp_path, case):
  scene = _scannet_scene(tmp_path)
  named = SCANNET_CASES[case](scene)
  _expect_data_error(
      tmp_path, lambda: scannet.read_scene(str(scene), protocol="test", image_size=0,
                                           scene_scale=1.0, num_source_views=2), named)


def test_valid_folders_load_and_stay_unchanged(tmp_path):
  """The positive control: the fixtures above load without error when nothing is broken."""
  folder = tmp_path / "u" / "clevr_567_test"
  fx.write_uorf_split(folder, num_scenes=2, views=4, size=SIZE, masks=True)
  assert len(_read_uorf(folder)) == 2
  folder = tmp_path / "g" / "clevr_567_val"
  fx.write_generated_split(folder, split="val", num_scenes=2, views=4, size=SIZE)
  assert len(_read_uorf(folder, split="val")) == 2
  d = _dtu_root(tmp_path / "d")
  assert len(registry.load_split(d, "train")) == 2
  scene = _scannet_scene(tmp_path / "s")
  assert scannet.read_scene(str(scene), protocol="test", image_size=0, scene_scale=1.0,
                            num_source_views=2).target_indices == (3, 4)
