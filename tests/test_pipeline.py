"""The batch pipeline (docs/method.md §2): shapes, determinism from (seed, step), ray geometry, the
75 % rule, nearest-source selection and the prefetch thread."""

import os
import sys
import threading
import time

import chex
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import data_fixtures as fx
from slotlifter_jax import config_checks
from slotlifter_jax.data import cameras
from slotlifter_jax.data import pipeline
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from experiments import ray_foreground_share  # noqa: E402

H, W = 5, 7


def make_scene(name, *, views=4, seed=0, pooled=False, size=(H, W)):
  rng = np.random.default_rng(seed)
  poses = np.stack([fx.orbit_pose(rng.uniform(0, 360), radius=rng.uniform(10, 14),
                                  elevation_deg=rng.uniform(20, 60)) for _ in range(views)])
  poses[:, :3, 3] /= 7.0
  k = np.array([[1.09375 * size[1], 0.2, (size[1] - 1) / 2],
                [0, 1.458333 * size[0], (size[0] - 1) / 2], [0, 0, 1]])
  common = dict(name=name, images=rng.uniform(size=(views,) + size + (3,)).astype(np.float32),
                cam_to_world=poses.astype(np.float32),
                intrinsics=np.broadcast_to(k, (views, 3, 3)).astype(np.float32))
  if pooled:
    return Scene(**common, source_indices=(), target_indices=tuple(range(views)),
                 source_pool=tuple(range(views)))
  return Scene(**common, source_indices=(0,))


def sampler_for(scenes, *, b=2, r=13, v=1, p=0.75, seed=3):
  return pipeline.BatchSampler(scenes, batch_scenes=b, rays_per_scene=r, num_source_views=v,
                               novel_ray_prob=p, seed=seed)


def view_of_ray(scene, origin):
  """The view whose camera centre is the ray origin (each view has its own centre)."""
  d = np.linalg.norm(scene.cam_to_world[:, :3, 3] - origin, axis=-1)
  assert d.min() < 1e-6
  return int(np.argmin(d))


def test_shapes_and_dtypes():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  batch = sampler_for(scenes, b=2, r=13).batch(0)
  assert set(batch) == set(pipeline.BATCH_KEYS)
  chex.assert_shape(batch["source_images"], (2, 1, H, W, 3))
  chex.assert_shape(batch["source_cam_to_world"], (2, 1, 4, 4))
  chex.assert_shape(batch["source_intrinsics"], (2, 1, 3, 3))
  chex.assert_shape([batch["ray_origins"], batch["ray_directions"], batch["target_rgb"]],
                    (2, 13, 3))
  chex.assert_shape(batch["scene_index"], (2,))
  for k, v in batch.items():
    assert v.dtype == (np.int32 if k == "scene_index" else np.float32), k
  np.testing.assert_allclose(np.linalg.norm(batch["ray_directions"], axis=-1), 1.0, rtol=1e-6)
  assert len(set(batch["scene_index"].tolist())) == 2  # no scene twice when there are enough
  for b, s in enumerate(batch["scene_index"]):
    np.testing.assert_array_equal(batch["source_images"][b, 0], scenes[s].images[0])


def test_reproducible_from_seed_and_step_alone():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(5)]
  a, b = sampler_for(scenes), sampler_for(scenes)
  for _ in range(3):
    a.batch(1)  # history must not matter
  for step in (0, 7, 123456):
    x, y = a.batch(step), b.batch(step)
    for k in x:
      np.testing.assert_array_equal(x[k], y[k])
  assert not np.array_equal(a.batch(7)["ray_directions"], a.batch(8)["ray_directions"])
  assert not np.array_equal(a.batch(7)["ray_directions"],
                            sampler_for(scenes, seed=4).batch(7)["ray_directions"])


@pytest.mark.parametrize("pooled", [False, True])
def test_a_process_share_of_a_batch_is_those_rows_of_the_whole_batch(pooled):
  """Each process of a multi-process run gathers only its rows (slotlifter_jax/multihost.py); the
  draw is the whole batch's, so the shares put together are the single-process batch."""
  scenes = [make_scene(f"s{i}", seed=i, pooled=pooled) for i in range(5)]
  sampler = sampler_for(scenes, b=4)
  for step in (0, 9):
    whole = sampler.batch(step)
    for rows in ([0, 1], [2, 3], [1], [3, 0]):
      part = sampler.batch(step, np.array(rows))
      assert set(part) == set(whole)
      for k in whole:
        np.testing.assert_array_equal(part[k], whole[k][rows], err_msg=k)


def test_rays_pass_through_their_pixel_and_carry_its_colour():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  sampler = sampler_for(scenes, b=3, r=29)
  for step in range(4):
    batch = sampler.batch(step)
    for b, s in enumerate(batch["scene_index"]):
      scene = scenes[s]
      for origin, direction, rgb in zip(batch["ray_origins"][b], batch["ray_directions"][b],
                                        batch["target_rgb"][b]):
        view = view_of_ray(scene, origin)
        point = origin.astype(np.float64) + 2.3 * direction  # any point along the ray
        cam = np.linalg.inv(scene.cam_to_world[view].astype(np.float64)) @ np.append(point, 1)
        u, v = (scene.intrinsics[view].astype(np.float64) @ cam[:3])[:2] / cam[2]
        col, row = int(round(u)), int(round(v))
        assert abs(u - col) < 1e-4 and abs(v - row) < 1e-4  # pixel centres at integers
        np.testing.assert_array_equal(rgb, scene.images[view, row, col])


def test_no_pixel_twice_within_a_scene():
  scenes = [make_scene("s0", views=2)]
  sampler = sampler_for(scenes, b=1, r=H * W - 1, p=0.0)  # nearly every pixel of both views
  for step in range(5):
    batch = sampler.batch(step)
    rays = np.concatenate([batch["ray_origins"][0], batch["ray_directions"][0]], axis=-1)
    assert len(np.unique(np.round(rays, 5), axis=0)) == H * W - 1
  novel_only = sampler_for(scenes, b=1, r=H * W, p=1.0).batch(0)  # every pixel of view 1
  rays = np.concatenate([novel_only["ray_origins"][0], novel_only["ray_directions"][0]], axis=-1)
  assert len(np.unique(np.round(rays, 5), axis=0)) == H * W


def test_novel_views_only_in_three_quarters_of_draws():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(4)]
  sampler = sampler_for(scenes, b=4, r=31)  # (3/4)^31 ≈ 1e-4: all-novel by chance is negligible
  novel_only, from_source = [], []
  for step in range(150):
    batch = sampler.batch(step)
    for b, s in enumerate(batch["scene_index"]):
      views = np.array([view_of_ray(scenes[s], o) for o in batch["ray_origins"][b]])
      novel_only.append(np.all(views != 0))
      from_source.append(np.mean(views == 0))
  frac = np.mean(novel_only)
  sigma = np.sqrt(0.75 * 0.25 / len(novel_only))
  assert abs(frac - 0.75) < 4 * sigma, frac
  # In the other draws, rays come from all 4 views: about a quarter from the source view.
  mixed = np.array(from_source)[~np.array(novel_only)]
  assert abs(mixed.mean() - 0.25) < 0.05


def _brute_force_nearest(poses, target, pool, n):
  dist = {}
  for i in pool:
    if i == target:
      continue
    angle = Rotation.from_matrix(poses[target][:3, :3].T @ poses[i][:3, :3]).magnitude()
    dist[i] = 0.5 * angle + 0.5 * np.linalg.norm(poses[i][:3, 3] - poses[target][:3, 3])
  return sorted(dist, key=dist.get)[:n]


def test_nearest_sources_against_brute_force():
  poses = make_scene("s", views=11, seed=5).cam_to_world.astype(np.float64)
  pool = (0, 2, 3, 5, 6, 7, 9, 10)
  for target in range(11):
    got = cameras.nearest_sources(cam_to_world=poses, target_idx=target, pool=pool, n=3)
    assert list(got) == _brute_force_nearest(poses, target, pool, 3)
  with pytest.raises(ValueError):
    cameras.nearest_sources(cam_to_world=poses, target_idx=0, pool=(0, 1), n=2)


def test_pooled_scenes_take_targets_and_nearest_sources():
  scenes = [make_scene(f"p{i}", views=9, seed=i, pooled=True) for i in range(2)]
  sampler = sampler_for(scenes, b=3, r=17, v=3)
  for step in range(6):
    batch = sampler.batch(step)
    chex.assert_shape(batch["source_images"], (3, 3, H, W, 3))
    for b, s in enumerate(batch["scene_index"]):
      scene = scenes[s]
      views = {view_of_ray(scene, o) for o in batch["ray_origins"][b]}
      assert len(views) == 1  # one target view per batch element
      (target,) = views
      want = _brute_force_nearest(scene.cam_to_world.astype(np.float64), target, range(9), 3)
      np.testing.assert_array_equal(batch["source_cam_to_world"][b], scene.cam_to_world[want])
      np.testing.assert_array_equal(batch["source_images"][b], scene.images[want])


def test_per_target_scenes():
  scene = make_scene("scan", views=10, seed=2, pooled=True)
  scene = Scene(**{**scene.__dict__, "target_indices": (0, 8),
                   "source_pool": (1, 2, 3, 4, 5, 6, 7, 9),
                   "view_names": tuple(f"{i:06d}" for i in range(10))})
  out = pipeline.per_target_scenes(scene, num_source_views=3)
  assert [s.name for s in out] == ["scan/000000", "scan/000008"]
  for s, target in zip(out, (0, 8)):
    want = _brute_force_nearest(scene.cam_to_world.astype(np.float64), target,
                                scene.source_pool, 3)
    np.testing.assert_array_equal(s.images, scene.images[want + [target]])
    assert s.source_indices == (0, 1, 2) and s.novel_indices == (3,) and s.source_pool is None
  fixed = make_scene("fixed")
  assert pipeline.per_target_scenes(fixed, num_source_views=1) == [fixed]


def test_sampler_rejects_inconsistent_scenes():
  with pytest.raises(DataError, match="s1"):
    sampler_for([make_scene("s0"), make_scene("s1", size=(H + 2, W))])
  with pytest.raises(DataError, match="pixels"):
    sampler_for([make_scene("s0", views=2)], r=H * W + 1, p=1.0)


def test_prefetch_preserves_order_and_matches_direct_batches():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  sampler = sampler_for(scenes)
  with pipeline.prefetch((sampler.batch(s) for s in range(5, 11)), size=2) as it:
    got = list(it)
  assert len(got) == 6
  for step, batch in zip(range(5, 11), got):
    for k, v in sampler.batch(step).items():
      np.testing.assert_array_equal(batch[k], v)


def test_prefetch_stops_cleanly_and_reraises():
  produced = []

  def endless():
    i = 0
    while True:
      produced.append(i)
      yield i
      i += 1

  it = pipeline.prefetch(endless(), size=2)
  assert [next(it) for _ in range(3)] == [0, 1, 2]
  it.close()
  assert not it.alive
  n = len(produced)
  time.sleep(0.2)
  assert len(produced) == n  # nothing more is built after close
  with pytest.raises(StopIteration):
    next(it)

  def failing():
    yield 1
    raise RuntimeError("broken batch")

  it = pipeline.prefetch(failing())
  assert next(it) == 1
  with pytest.raises(RuntimeError, match="broken batch"):
    next(it)
  it.close()
  assert not any(t.name == "batch-prefetch" and t.is_alive() for t in threading.enumerate())


def test_weighted_choice_matches_sequential_sampling_without_replacement():
  # Reference: draw one index at a time with probability ∝ p among those not yet drawn. The
  # probability that index i is drawn first and j second is p_i·p_j/(1 − p_i); compare the
  # empirical frequencies of the ordered pair with those of the Gumbel top-k draw (k = 2).
  probs = np.array([0.5, 0.2, 0.15, 0.1, 0.05])
  rng = np.random.default_rng(0)
  n = 40_000
  counts = np.zeros(len(probs))  # how often each index is among the two drawn
  for _ in range(n):
    counts[pipeline.weighted_choice_without_replacement(rng, probs=probs, size=2)] += 1
  p_second = np.array([sum(probs[j] * probs[i] / (1 - probs[j]) for j in range(len(probs)) if j != i)
                       for i in range(len(probs))])
  np.testing.assert_allclose(counts / n, probs + p_second, atol=0.01)
  picks = pipeline.weighted_choice_without_replacement(rng, probs=np.array([0.0, 1.0, 0.0, 1.0]),
                                                       size=2)
  assert sorted(picks.tolist()) == [1, 3]  # zero-probability entries only after all others


def test_contrast_sampling_favours_pixels_far_from_the_median_colour():
  # A grey view with a 2×3 red patch: contrast sampling puts about `mix` of the rays (plus the
  # uniform share of the patch's pixels) on the patch; uniform sampling puts 6/35 there.
  scene = make_scene("patch", views=2)
  images = np.full_like(scene.images, 0.5)
  images[:, 1:3, 2:5] = (0.9, 0.1, 0.1)
  scene = Scene(name="patch", images=images, cam_to_world=scene.cam_to_world,
                intrinsics=scene.intrinsics, source_indices=(0,))
  on_patch = {}
  for mode, mix in [("uniform", 0.5), ("contrast", 0.5), ("contrast", 0.9)]:
    sampler = pipeline.BatchSampler([scene], batch_scenes=1, rays_per_scene=5, num_source_views=1,
                                    novel_ray_prob=0.0, seed=1, ray_sampling=mode, contrast_mix=mix)
    draws = [sampler.draw(t) for t in range(400)]
    on_patch[(mode, mix)] = np.mean([
        ((1 <= d.ray_rows) & (d.ray_rows < 3) & (2 <= d.ray_cols) & (d.ray_cols < 5)).mean()
        for d in draws])
    d = draws[-1]
    assert len({(v, r, c) for v, r, c in zip(d.ray_views[0], d.ray_rows[0], d.ray_cols[0])}) == 5
  assert abs(on_patch[("uniform", 0.5)] - 6 / 35) < 0.03
  assert on_patch[("contrast", 0.5)] > 0.45
  assert on_patch[("contrast", 0.9)] > on_patch[("contrast", 0.5)] + 0.1
  with pytest.raises(ValueError, match="ray_sampling"):
    pipeline.BatchSampler([scene], batch_scenes=1, rays_per_scene=5, num_source_views=1,
                          novel_ray_prob=0.0, seed=1, ray_sampling="edges")


def test_object_oversampling_against_a_hand_computed_case():
  """experiments/ray_foreground_share.py's per-object factor. View 0: a light grey pixel (label 1)
  on a mid-grey floor of 3 pixels; the median is the floor, so all contrast is on the object:
  probability 0.5/4 + 0.5·1 = 2.5× uniform's 1/4. View 1: two red pixels (label 2) and two floor
  pixels; the median lies halfway, every pixel is 0.2·√3 from it, so the red object is drawn as
  often as under uniform sampling (1.0×)."""
  floor, light, red = (0.5, 0.5, 0.5), (0.9, 0.9, 0.9), (0.9, 0.1, 0.1)
  images = np.array([[[floor, floor, floor, light]], [[floor, floor, red, red]]])  # [2, 1, 4, 3]
  masks = np.array([[[0, 0, 0, 1]], [[0, 0, 2, 2]]])
  factors = ray_foreground_share.object_oversampling(images, masks, mix=0.5)
  np.testing.assert_allclose(factors["grey"], [2.5])
  np.testing.assert_allclose(factors["coloured"], [1.0])


def test_uniform_sampling_is_unchanged_by_the_contrast_option():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  a = sampler_for(scenes).draw(5)
  b = pipeline.BatchSampler(scenes, batch_scenes=2, rays_per_scene=13, num_source_views=1,
                            novel_ray_prob=0.75, seed=3, ray_sampling="uniform",
                            contrast_mix=0.9).draw(5)
  for field in ("scene_index", "ray_views", "ray_rows", "ray_cols"):
    np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_stage_value_is_the_last_stage_started():
  stages = ((0, 2), (10, 5), (30, 7))
  assert [pipeline.stage_value(t, stages, 9) for t in (0, 9, 10, 29, 30, 10**6)] == [2, 2, 5, 5, 7, 7]
  assert [pipeline.stage_value(t, ((10, 5),), 9) for t in (0, 9, 10)] == [9, 9, 5]
  assert pipeline.stage_value(3, (), 9) == 9


def _assert_same_batch(x, y):
  assert set(x) == set(y)
  for k in x:
    np.testing.assert_array_equal(x[k], y[k], err_msg=k)


@pytest.mark.parametrize("ray_sampling", ["uniform", "contrast"])
def test_scene_stages_draw_as_a_sampler_of_the_first_scenes(ray_sampling):
  """Until a stage starts, a staged sampler's batches are those of a sampler over the first
  num_scenes scenes; afterwards those of a sampler over all of them (so a run is a prefix of the
  same run with a later stage added)."""
  scenes = [make_scene(f"s{i}", seed=i) for i in range(6)]
  kw = dict(batch_scenes=2, rays_per_scene=13, num_source_views=1, novel_ray_prob=0.75, seed=3,
            ray_sampling=ray_sampling)
  staged = pipeline.BatchSampler(scenes, scene_stages=((0, 2), (10, 6)), **kw)
  first_two = pipeline.BatchSampler(scenes[:2], **kw)
  every = pipeline.BatchSampler(scenes, **kw)
  drawn = set()
  for step in range(20):
    batch = staged.batch(step)
    _assert_same_batch(batch, (first_two if step < 10 else every).batch(step))
    if step < 10:
      assert set(batch["scene_index"].tolist()) <= {0, 1}
    else:
      drawn |= set(batch["scene_index"].tolist())
  assert drawn - {0, 1}  # the later scenes are drawn once their stage starts


def test_ray_stages_change_the_rays_per_scene_from_their_step():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  staged = pipeline.BatchSampler(scenes, batch_scenes=2, rays_per_scene=13, num_source_views=1,
                                 novel_ray_prob=0.75, seed=3, ray_stages=((5, 20),))
  for step in (0, 4, 5, 9):
    expected = sampler_for(scenes, r=13 if step < 5 else 20).batch(step)
    _assert_same_batch(staged.batch(step), expected)
    assert staged.batch(step)["target_rgb"].shape == (2, 13 if step < 5 else 20, 3)


def test_bad_stages_are_named():
  scenes = [make_scene(f"s{i}", seed=i) for i in range(3)]
  kw = dict(batch_scenes=2, rays_per_scene=13, num_source_views=1, novel_ray_prob=0.75, seed=3)
  with pytest.raises(ValueError, match=r"data.scene_stages: 4 \(stage from step 10\) must lie in "
                                       r"\[1, 3\]"):
    pipeline.BatchSampler(scenes, scene_stages=((0, 2), (10, 4)), **kw)
  with pytest.raises(ValueError, match="data.scene_stages: start steps .10, 0. must be ≥ 0 and "
                                       "strictly increasing"):
    pipeline.BatchSampler(scenes, scene_stages=((10, 2), (0, 3)), **kw)
  with pytest.raises(ValueError, match="train.ray_stages: stage .* is not"):
    pipeline.BatchSampler(scenes, ray_stages=((5,),), **kw)
  with pytest.raises(DataError, match=f"fewer than {4 * H * W} pixels"):
    pipeline.BatchSampler(scenes, ray_stages=((5, 4 * H * W),), **kw)
  with pytest.raises(ValueError, match=r"train.ray_stages: 30 \(stage from step 2\) is not a "
                                       r"multiple of 4"):
    config_checks.check_stages(((2, 30),), field="train.ray_stages", upper=100, multiple_of=4)


def test_floor_reprojection_error_is_exact_for_one_camera_twice():
  # Two views from the same pose: every ray that meets the floor reprojects onto its own pixel,
  # so the error is the colour difference of the two images there, whatever the texture.
  rng = np.random.default_rng(0)
  h = w = 12
  pose = cameras.look_at_cam_to_world(np.array([1.2, -0.9, 1.1]))
  k = np.array([[14.0, 0, (w - 1) / 2], [0, 14.0, (h - 1) / 2], [0, 0, 1]])
  first = rng.uniform(size=(h, w, 3)).astype(np.float32)
  second = first.copy()
  second[3:5, 6:9] += 0.25  # "an object" in the second view only
  scene = Scene(name="twice", images=np.stack([first, second]),
                cam_to_world=np.stack([pose, pose]).astype(np.float32),
                intrinsics=np.stack([k, k]).astype(np.float32), source_indices=(0,))
  error = pipeline.floor_reprojection_error(scene).reshape(2, h, w)
  expected = np.linalg.norm(second.astype(np.float64) - first, axis=-1)
  # Rays above the horizon never meet the floor: 0 there.
  v, u = np.mgrid[0:h, 0:w]
  dirs = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones((h, w))], -1)
  meets_floor = (dirs @ pose[:3, :3].T)[..., 2] < -1e-6
  assert meets_floor.mean() > 0.5
  np.testing.assert_allclose(error[0], np.where(meets_floor, expected, 0.0), atol=1e-6)
  np.testing.assert_allclose(error[1], np.where(meets_floor, expected, 0.0), atol=1e-6)


def test_floor_parallax_weights_favour_chairs_on_a_textured_floor():
  from slotlifter_jax.data import generator
  from slotlifter_jax.data import layout
  g = generator.generate_scene(generator.scene_rng(seed=1, family="room", split="val", index=2),
                               family="room", views=4, image_size=48)
  poses = g.cam_to_world.copy()
  poses[:, :3, 3] *= layout.SCENE_SCALE  # the readers' normalised frame
  scene = Scene(name="room", images=g.rgb.astype(np.float32) / 255.0,
                cam_to_world=poses.astype(np.float32), intrinsics=np.stack([g.intrinsics] * 4),
                source_indices=(0,), masks=g.label)
  assert scene.images.std() > 0.05
  error = pipeline.floor_reprojection_error(scene).reshape(g.label.shape)
  # Ground truth from the ray caster: floor pixels are background at depth on the plane z = 0.
  k = g.intrinsics
  v, u = np.mgrid[0:48, 0:48]
  z_world = []
  for a in range(4):
    cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones((48, 48))], -1)
    z_world.append((cam * g.depth[a][..., None]) @ g.cam_to_world[a, :3, :3].T[:, 2]
                   + g.cam_to_world[a, 2, 3])
  floor = (g.label == 0) & (np.abs(np.stack(z_world)) < 1e-3)
  on_chairs = g.label > 0
  assert floor.sum() > 1000 and on_chairs.sum() > 100
  # A floor point shows the same texture from every view (up to the nearest-pixel lookup), a
  # chair pixel's floor point shows floor: several times the error.
  assert np.median(error[on_chairs]) > 4 * np.median(error[floor])
  weights = pipeline.parallax_weights(scene).reshape(g.label.shape)
  np.testing.assert_allclose(weights.reshape(4, -1).sum(axis=1), 1.0, rtol=1e-5)
  assert weights[on_chairs].sum() / 4 > 2 * on_chairs.mean()
