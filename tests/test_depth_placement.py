"""experiments/depth_placement.py: projection, depth conversion and a scene's figures against
closed forms and a brute-force reference on a floor seen from two cameras."""

import math
import os
import sys

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

import data_fixtures as fx

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import depth_placement  # noqa: E402

SIZE = 32


def _intrinsics(f=30.0):
  return np.array([[f, 0.0, (SIZE - 1) / 2], [0.0, f, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])


def _floor(pose, k):
  """Closed-form camera depth of the floor z = 0 (inf where the ray misses it) and each pixel's
  floor point [H, W, 3]."""
  v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
  cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
  d = cam @ pose[:3, :3].T  # camera z = 1
  o = pose[:3, 3]
  depth = np.where(d[..., 2] < 0, -o[2] / np.minimum(d[..., 2], -1e-12), np.inf)
  return depth, o + depth[..., None] * d


def test_project_hand_computed():
  pose = np.eye(4)
  pose[:3, 3] = [1.0, 2.0, 3.0]  # camera at (1, 2, 3) looking along +z, no rotation
  k = np.array([[10.0, 0.0, 4.0], [0.0, 20.0, 5.0], [0.0, 0.0, 1.0]])
  points = np.array([[3.0, 1.0, 5.0, 1.0], [1.0, 2.0, 1.0, 1.0]])  # camera (2, −1, 2), (0, 0, −2)
  uv, ahead = depth_placement.project(points, cam_to_world=pose, intrinsics=k)
  np.testing.assert_allclose(uv[0], [10.0 * 2 / 2 + 4.0, 20.0 * -1 / 2 + 5.0])
  assert ahead.tolist() == [True, False]


def test_camera_z_of_a_3_4_5_ray():
  k = np.array([[4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [0.0, 0.0, 1.0]])
  distance = np.full((1, 4), 5.0)
  # Pixel u = 3 has the ray (0.75, 0, 1), of length 1.25: distance 5 is camera z 4; u = 0 is 5.
  z = depth_placement.camera_z(distance, k)
  np.testing.assert_allclose(z[0, [0, 3]], [5.0, 4.0])


def test_nearest_rounds_and_clamps():
  labels = np.arange(12).reshape(3, 4)
  uv = np.array([[0.4, 0.6], [2.6, 1.4], [-3.0, 9.0]])
  assert depth_placement.nearest(labels, uv).tolist() == [labels[1, 0], labels[1, 3], labels[2, 0]]


def test_region_ari_equals_sklearn_on_the_region():
  rng = np.random.default_rng(0)
  true, pred = rng.integers(0, 3, (6, 7)), rng.integers(0, 4, (6, 7))
  region = rng.random((6, 7)) < 0.6
  assert depth_placement.region_ari(true, pred, region) == pytest.approx(
      adjusted_rand_score(true[region], pred[region]))
  assert math.isnan(depth_placement.region_ari(true, pred, np.zeros((6, 7), bool)))


def _scene(scale=1.0):
  k = _intrinsics()
  poses = [fx.orbit_pose(az, radius=6.0, elevation_deg=40.0) for az in (0.0, 35.0)]
  depth, points = zip(*[_floor(p, k) for p in poses])
  depth = np.stack(depth)
  masks = np.stack([(pt[..., 0] > 0.3).astype(np.int32) for pt in points])  # a half-plane "object"
  # The model's distance along the unit ray: the true one times `scale`.
  v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
  norm = np.hypot(np.hypot((u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1]), 1.0)
  distance = np.where(np.isfinite(depth), depth, 50.0) * norm * scale
  return dict(images=np.zeros((2, SIZE, SIZE, 3)), masks=masks, depth=depth,
              cam_to_world=np.stack(poses), intrinsics=np.stack([k, k]), source=0, novel=[1],
              colour=np.zeros((2, SIZE, SIZE, 3)), rendered_distance=distance,
              labels=masks.copy()), points


def test_true_depth_places_every_seen_pixel_exactly():
  kwargs, _ = _scene()
  out = depth_placement.scene_placement(**kwargs)
  assert 0.2 < out["pixel_share_seen"] < 1.0
  for r in depth_placement.REGIONS:
    assert out[f"displacement_px_{r}"] == pytest.approx(0.0, abs=1e-6)
    assert out[f"relative_depth_error_{r}"] == pytest.approx(0.0, abs=1e-9)


def test_scaled_depth_reads_its_relative_error():
  kwargs, _ = _scene(scale=1.1)
  out = depth_placement.scene_placement(**kwargs)
  assert out["relative_depth_error_seen"] == pytest.approx(0.1, rel=1e-6)
  assert out["displacement_px_seen"] > 0.5


def test_transported_split_against_brute_force():
  kwargs, points = _scene()
  k, poses = kwargs["intrinsics"][0], kwargs["cam_to_world"]
  out = depth_placement.scene_placement(**kwargs)
  # Brute force: each novel pixel's floor point into the source camera, by the pinhole model.
  cam = (points[1] - poses[0][:3, 3]) @ poses[0][:3, :3]
  u = k[0, 0] * cam[..., 0] / cam[..., 2] + k[0, 2]
  v = k[1, 1] * cam[..., 1] / cam[..., 2] + k[1, 2]
  finite = np.isfinite(kwargs["depth"][1])
  inside = finite & (cam[..., 2] > 0) & (u >= 0) & (u <= SIZE - 1) & (v >= 0) & (v <= SIZE - 1)
  carried = kwargs["labels"][0][np.clip(np.rint(v[inside]), 0, SIZE - 1).astype(int),
                                np.clip(np.rint(u[inside]), 0, SIZE - 1).astype(int)]
  expected = adjusted_rand_score(kwargs["masks"][1][inside], carried)
  assert out["nv_ari_seen_transported"] == pytest.approx(expected)
  # The model's own labels are the true masks: its seen and unseen ARIs are 1 wherever the
  # region holds both labels.
  assert out["nv_ari_seen"] == pytest.approx(1.0)


def test_depth_bias_is_signed_and_read_on_the_source_view_too():
  kwargs, _ = _scene(scale=0.9)
  out = depth_placement.scene_placement(**kwargs)
  for key in ("depth_bias_seen", "depth_bias_seen_bg", "depth_bias_seen_fg",
              "depth_bias_source_bg", "depth_bias_source_fg"):
    assert out[key] == pytest.approx(-0.1, rel=1e-6), key
  assert out["relative_depth_error_seen_fg"] == pytest.approx(0.1, rel=1e-6)


def test_opacity_is_averaged_per_region_of_the_novel_and_source_views():
  kwargs, _ = _scene()
  opacity = np.zeros((2, SIZE, SIZE))
  opacity[0] = np.where(kwargs["masks"][0] > 0, 0.2, 0.6)  # source: objects 0.2, background 0.6
  opacity[1] = np.where(kwargs["masks"][1] > 0, 0.3, 0.9)
  out = depth_placement.scene_placement(**kwargs, opacity=opacity)
  assert out["opacity_source_fg"] == pytest.approx(0.2)
  assert out["opacity_source_bg"] == pytest.approx(0.6)
  assert out["opacity_seen_fg"] == pytest.approx(0.3)
  assert out["opacity_seen_bg"] == pytest.approx(0.9)
  assert "opacity_seen_bg" not in depth_placement.scene_placement(**kwargs)


@pytest.mark.slow
def test_command_line_on_a_trained_smoke_run_agrees_with_the_evaluation(tmp_path):
  """The script end to end: its file reads the validation split, and its PSNR of the seen pixels
  is the evaluation's `psnr_novel_seen`, computed by evaluate.scene_metrics on the same renders."""
  import json

  from slotlifter_jax import evaluate
  from slotlifter_jax import train
  from slotlifter_jax.rendering import views as views_lib
  from train_helpers import load_config

  workdir, out = tmp_path / "run", tmp_path / "placement.json"
  train.train_and_evaluate(load_config(), str(workdir))  # smoke: 6 steps
  depth_placement.main([f"--workdir={workdir}", "--scenes=2", "--checkpoint=latest",
                        "--params=trained", f"--out={out}"])
  record = json.loads(out.read_text())
  assert record["split"] == "val" and record["scenes"] == 2 and record["step"] == 6
  assert np.isfinite(record["log_density_scale"])
  for key in ("opacity_source_bg", "opacity_seen_bg"):
    assert 0.0 <= record["means"][key] <= 1.0, key

  args = type("Args", (), dict(workdir=str(workdir), split="val", scenes=2,
                               checkpoint="latest"))()
  from experiments import diagnose_slots
  run = diagnose_slots.load_run(args, params="trained")
  renderer = views_lib.SceneRenderer(run.model, run.config)
  for row, scene in zip(record["per_scene"], run.scenes):
    views = list(range(scene.num_views))
    expected = evaluate.scene_metrics(renderer.render(run.params, scene, views), scene, views,
                                      image_metrics=True)
    assert row["psnr_seen"] == pytest.approx(expected["psnr_novel_seen"], abs=1e-4)
