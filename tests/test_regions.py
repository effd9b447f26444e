"""Novel-view error by region (slotlifter_jax/regions.py): source visibility from depth against
ray casting in a scene of closed-form surfaces, and the pooled PSNRs against hand-computed cases."""

import math

import numpy as np
import pytest

import data_fixtures as fx
from slotlifter_jax import evaluate
from slotlifter_jax import regions
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering.views import RenderedViews

SIZE = 40
FLOOR, SKY, BALL = 1, 0, 2


def _intrinsics(fov_deg=70.0):
  f = 0.5 * SIZE / math.tan(math.radians(fov_deg) / 2)
  return np.array([[f, 0.0, (SIZE - 1) / 2], [0.0, f, (SIZE - 1) / 2], [0.0, 0.0, 1.0]])


def _pixel_rays(pose, k):
  """Unnormalised world directions with camera z = 1, so a hit's ray parameter is its depth."""
  v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
  cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1)
  return cam @ pose[:3, :3].T


def _ball_hits(origin, d, ball):
  """Ray parameters [..., 2] of entry and exit of the ball (NaN: missed, or no ball)."""
  if ball is None:
    return np.full(d.shape[:-1] + (2,), np.nan)
  centre, radius = ball
  oc = np.asarray(origin, np.float64) - centre
  a, b, c = (d * d).sum(-1), 2 * (d * oc).sum(-1), oc @ oc - radius**2
  disc = b * b - 4 * a * c
  root = np.sqrt(np.where(disc > 0, disc, np.nan))
  return np.stack([(-b - root) / (2 * a), (-b + root) / (2 * a)], -1)


def _trace(pose, k, ball):
  """Closed-form camera depth and surface label of a floor z = 0 and a ball (inf, SKY: none)."""
  d = _pixel_rays(pose, k)
  o = pose[:3, 3]
  floor = np.where(d[..., 2] < 0, -o[2] / np.minimum(d[..., 2], -1e-12), np.inf)
  entry = _ball_hits(o, d, ball)[..., 0] if ball else np.full(floor.shape, np.nan)
  on_ball = entry > 0  # NaN compares False
  depth = np.where(on_ball & (entry < floor), entry, floor)
  label = np.where(on_ball & (entry < floor), BALL, np.where(np.isinf(floor), SKY, FLOOR))
  return depth, label


def _project(points, pose, k):
  """(u, v, z) of world points [..., 3] in a camera, by the pinhole model."""
  cam = (points - pose[:3, 3]) @ pose[:3, :3]
  return k[0, 0] * cam[..., 0] / cam[..., 2] + k[0, 2], k[1, 1] * cam[..., 1] / cam[..., 2] \
      + k[1, 2], cam[..., 2]


def _cast_visibility(novel_pose, source_pose, k, ball):
  """Whether the source sees each novel pixel's surface, by casting the segment from the surface
  point to the source camera against the ball; also whether the source pixels around the
  projection show more than one surface (an occluding edge, where depth maps must guess)."""
  depth, label = _trace(novel_pose, k, ball)
  d = _pixel_rays(novel_pose, k)
  finite = np.isfinite(depth)
  point = novel_pose[:3, 3] + np.where(finite, depth, 1.0)[..., None] * d
  # A point at infinity projects by its direction: use a point far along it.
  far = source_pose[:3, 3] + 1e6 * d / np.linalg.norm(d, axis=-1, keepdims=True)
  target = np.where(finite[..., None], point, far)
  u, v, z = _project(target, source_pose, k)
  inside = (z > 0) & (u >= 0) & (u <= SIZE - 1) & (v >= 0) & (v <= SIZE - 1)
  hits = _ball_hits(source_pose[:3, 3], target - source_pose[:3, 3], ball)  # segment: t in (0, 1)
  # The point's own surface is at t = 1; anything entered before it occludes it.
  blocked = np.any((hits > 1e-9) & (hits < 1 - 1e-7), axis=-1)
  if ball:
    blocked |= (~finite) & np.any(hits > 0, axis=-1)  # a sky direction through the ball
  _, source_label = _trace(source_pose, k, ball)
  u0 = np.floor(np.where(inside, u, 0)).astype(int)
  v0 = np.floor(np.where(inside, v, 0)).astype(int)
  u1, v1 = np.minimum(u0 + 1, SIZE - 1), np.minimum(v0 + 1, SIZE - 1)
  taps = np.stack([source_label[v0, u0], source_label[v0, u1], source_label[v1, u0],
                   source_label[v1, u1]])
  edge = inside & np.any(taps != taps[0], axis=0)
  return inside & ~blocked, edge, label


def _seen(novel_pose, source_pose, k, ball):
  depth, _ = _trace(novel_pose, k, ball)
  source_depth, _ = _trace(source_pose, k, ball)
  return regions.seen_by_sources(
      depth=depth[None], cam_to_world=novel_pose[None], intrinsics=k[None],
      source_depth=source_depth[None], source_cam_to_world=source_pose[None],
      source_intrinsics=k[None])[0]


BALL_AT = (np.array([0.6, -0.4, 1.6]), 1.6)


@pytest.mark.parametrize("azimuth", [35.0, 70.0, 180.0])
def test_seen_by_source_agrees_with_ray_casting_away_from_occluding_edges(azimuth):
  k = _intrinsics()
  source, novel = fx.orbit_pose(0.0, radius=9.0, elevation_deg=18.0), \
      fx.orbit_pose(azimuth, radius=9.0, elevation_deg=18.0)
  seen = _seen(novel, source, k, BALL_AT)
  cast, edge, label = _cast_visibility(novel, source, k, BALL_AT)
  # The fixture shows every case: sky, floor and ball, seen and hidden.
  for surface in (SKY, FLOOR, BALL):
    assert (label == surface).mean() > 0.05
  assert cast.mean() > 0.05 and (~cast).mean() > 0.05
  assert edge.mean() < 0.1
  # Where the source pixels around a projection straddle an occluding edge, depth maps cannot
  # tell; everywhere else the answer is the ray caster's, pixel for pixel.
  np.testing.assert_array_equal(seen[~edge], cast[~edge])


def test_floor_alone_is_seen_exactly_where_it_projects_into_the_source():
  """No occluder: visibility is the source frustum, to the pixel."""
  k = _intrinsics(50.0)
  source, novel = fx.orbit_pose(0.0, radius=9.0, elevation_deg=35.0), \
      fx.orbit_pose(50.0, radius=9.0, elevation_deg=35.0)
  seen = _seen(novel, source, k, None)
  cast, edge, label = _cast_visibility(novel, source, k, None)
  assert np.all(label == FLOOR) and not edge.any()
  assert 0.2 < cast.mean() < 0.8
  np.testing.assert_array_equal(seen, cast)


def test_source_view_sees_all_of_itself():
  k = _intrinsics()
  pose = fx.orbit_pose(20.0, radius=9.0, elevation_deg=18.0)
  assert _seen(pose, pose, k, BALL_AT).all()


def test_split_metrics_hand_computed():
  # Two 2×2 views: squared errors 0.01 inside the region (3 pixels), 0.0001 outside (5 pixels).
  region = np.array([[[True, False], [False, True]], [[False, False], [True, False]]])
  se = np.where(region, 0.01, 0.0001)
  out = regions.split_metrics(squared_error=se, region=region, inside="unseen", outside="seen")
  assert out["psnr_novel_unseen"] == pytest.approx(20.0)
  assert out["psnr_novel_seen"] == pytest.approx(40.0)
  assert out["unseen_pixel_share"] == pytest.approx(3 / 8)
  assert out["unseen_error_share"] == pytest.approx(0.03 / (0.03 + 0.0005))
  # An empty side is NaN; no error at all gives +inf and an undefined share.
  empty = regions.split_metrics(squared_error=np.zeros((1, 2, 2)), region=np.zeros((1, 2, 2),
                                bool), inside="fg", outside="bg")
  assert math.isnan(empty["psnr_novel_fg"]) and empty["psnr_novel_bg"] == math.inf
  assert empty["fg_pixel_share"] == 0.0 and math.isnan(empty["fg_error_share"])


def test_scene_metrics_split_novel_psnr_by_visibility_and_objects():
  """A two-view scene of the floor: the rendering errs by 0.1 where the source cannot see and
  by 0.01 where it can, so the split PSNRs are 20 and 40 dB whatever the pixel counts."""
  k = _intrinsics(50.0)
  source, novel = fx.orbit_pose(0.0, radius=9.0, elevation_deg=35.0), \
      fx.orbit_pose(50.0, radius=9.0, elevation_deg=35.0)
  cast, _, _ = _cast_visibility(novel, source, k, None)
  depth = np.stack([_trace(p, k, None)[0] for p in (source, novel)]).astype(np.float32)
  rng = np.random.default_rng(0)
  images = rng.uniform(0.2, 0.8, size=(2, SIZE, SIZE, 3)).astype(np.float32)
  masks = np.zeros((2, SIZE, SIZE), np.int32)
  masks[:, 10:20, 5:30] = 1  # an "object" straddling both regions
  error = np.where(cast, 0.01, 0.1)[..., None]
  colour = images.copy()
  colour[1] += error
  scene = Scene(name="floor", images=images, cam_to_world=np.stack([source, novel]),
                intrinsics=np.stack([k, k]), source_indices=(0,), masks=masks, depth=depth)
  segmentation = np.zeros((2, SIZE, SIZE, 2), np.float32)
  segmentation[..., 0] = 1.0
  rendered = RenderedViews(colour=colour, depth=depth, segmentation=segmentation,
                           slots=np.zeros((2, 4)), slot_attn=np.zeros((2, 4)),
                           source_labels=np.zeros((1, SIZE, SIZE), np.int64))
  out = evaluate.scene_metrics(rendered, scene, [0, 1], image_metrics=True)
  assert out["psnr_novel_seen"] == pytest.approx(40.0, abs=1e-4)
  assert out["psnr_novel_unseen"] == pytest.approx(20.0, abs=1e-4)
  unseen = ~cast
  assert out["unseen_pixel_share"] == pytest.approx(unseen.mean())
  assert out["unseen_error_share"] == pytest.approx(
      0.01 * unseen.sum() / (0.01 * unseen.sum() + 1e-4 * cast.sum()), rel=1e-4)
  fg = masks[1] > 0
  se = error[..., 0] ** 2
  assert out["psnr_novel_fg"] == pytest.approx(-10 * np.log10(se[fg].mean()), abs=1e-4)
  assert out["psnr_novel_bg"] == pytest.approx(-10 * np.log10(se[~fg].mean()), abs=1e-4)
  assert out["fg_error_share"] == pytest.approx(se[fg].sum() / se.sum(), rel=1e-4)
  # The object's border at 40 px is 1 px (round(40 / 32)): the 8-neighbourhood ring of the
  # 10×25 rectangle, a 12×27 box less the rectangle.
  ring = np.zeros((SIZE, SIZE), bool)
  ring[9:21, 4:31] = True
  ring &= ~fg
  assert ring.sum() == 12 * 27 - 10 * 25
  assert out["psnr_novel_border"] == pytest.approx(-10 * np.log10(se[ring].mean()), abs=1e-4)
  assert out["border_pixel_share"] == pytest.approx(ring.mean())
  assert out["border_error_share"] == pytest.approx(se[ring].sum() / se.sum(), rel=1e-4)
  far = ~fg & ~ring
  assert out["psnr_novel_bg_far"] == pytest.approx(-10 * np.log10(se[far].mean()), abs=1e-4)
  # Validation (no image metrics) leaves the split out.
  assert "psnr_novel_seen" not in evaluate.scene_metrics(rendered, scene, [0, 1])


def test_object_border_is_the_chessboard_ring_brute_force():
  rng = np.random.default_rng(3)
  masks = np.zeros((3, 13, 17), np.int32)
  for view in range(3):  # a few labelled pixels and blobs, some on the image edge
    masks[view][rng.uniform(size=(13, 17)) < 0.04] = view + 1
  masks[0, 0, 0] = 2
  masks[2, 5:8, 14:17] = 3
  vv, uu = np.mgrid[0:13, 0:17]
  for radius in (1, 2, 3):
    border = regions.object_border(masks, radius)
    for view in range(3):
      ov, ou = np.nonzero(masks[view])
      # Chessboard distance from every pixel to its nearest object pixel.
      dist = np.max(np.abs(np.stack([vv[..., None] - ov, uu[..., None] - ou])), axis=0).min(-1)
      expected = (dist >= 1) & (dist <= radius)
      np.testing.assert_array_equal(border[view], expected, err_msg=f"radius {radius}")
  assert not regions.object_border(np.zeros((1, 4, 4), np.int32), 2).any()
  with pytest.raises(ValueError, match="radius"):
    regions.object_border(masks, 0)


def test_border_radius_scales_with_the_image():
  assert [regions.border_radius(w) for w in (16, 40, 64, 128, 256)] == [1, 1, 2, 4, 8]
