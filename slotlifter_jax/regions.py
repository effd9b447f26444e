"""Where the novel views' error lies: pixels the source views see or not, objects or background
(docs/method.md §4, beyond the paper).

With one source view, every novel view shows parts of the scene the source never saw: the far
sides of objects, the floor they hide, floor outside the source's frustum. Lifting (§1.3) gives
such a point nothing (outside the frustum) or the colour of the surface in front of it (behind
an occluder), so it is rendered from the slots and from what the model learnt across scenes,
while a point the source sees can draw on its own lifted colour. Novel-view PSNR pools both
kinds of pixel; evaluation (slotlifter_jax/evaluate.py) also reports them apart:

- `seen_by_sources`: which pixels of a view show a surface point that a source view also sees,
  from ground-truth depth (the embedded sets store it, docs/method.md §3.5);
- `split_metrics`: PSNR of the squared error pooled inside and outside a region of a scene's
  views, the region's share of the pixels and its share of the squared error;
- `object_border`: the background pixels next to an object. A novel view's silhouettes and the
  contact shadows around them sit there, so it tells an object's misplaced or blurred outline
  from a floor rendered wrong far from any object, which the plain object / background split
  pools.

Vocabulary (docs/method.md §0): n views, V source views, H×W image size. Pure NumPy, float64.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from slotlifter_jax import geometry

# Slack of the occlusion test, relative to depth: the stored depth maps are float32.
DEPTH_SLACK = 1e-4
# Slack of the image bounds in pixels: a border pixel's own centre must project inside.
PIXEL_SLACK = 1e-6
# Width of `object_border` as a fraction of the image width: 2 px at 64 px, 4 px at 128 px, so
# the band covers the same part of a scene at either resolution.
BORDER_FRACTION = 1 / 32


def surface_points(*, depth: np.ndarray, cam_to_world: np.ndarray,
                   intrinsics: np.ndarray) -> np.ndarray:
  """Each pixel's surface point, homogeneous world coordinates: depth [H, W] → [H, W, 4].

  `depth` is camera z (not the distance along the ray), pixel centres at integers. A pixel with
  infinite depth (its ray hits nothing, e.g. sky) gives the point at infinity in its direction,
  w = 0, which projects by direction alone.
  """
  height, width = depth.shape
  pix = np.asarray(geometry.image_pixels(height, width), np.float64)  # [H, W, 2]
  ray_cam = geometry.pix_to_cam(pix=pix, intrinsics=np.asarray(intrinsics, np.float64),
                                xp=np)  # [H, W, 3], z = 1
  finite = np.isfinite(depth)
  scaled = ray_cam * np.where(finite, depth, 1.0)[..., None]
  pose = np.asarray(cam_to_world, np.float64)
  world = scaled @ pose[:3, :3].T + finite[..., None] * pose[:3, 3]
  return np.concatenate([world, finite[..., None].astype(np.float64)], axis=-1)


def project_points(points: np.ndarray, *, cam_to_world: np.ndarray,
                   intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Homogeneous world points [..., 4] into a camera: pixel coordinates u, v (centres at
  integers) and camera depth z, each [...]. A point at or behind the camera
  (z ≤ geometry.MIN_DEPTH) gets finite but meaningless u, v; a point at infinity (w = 0) projects
  by its direction."""
  pose = np.asarray(cam_to_world, np.float64)
  k = np.asarray(intrinsics, np.float64)
  # Camera coordinates R^T (p - w t), as row vectors.
  cam = (points[..., :3] - points[..., 3:] * pose[:3, 3]) @ pose[:3, :3]
  z = cam[..., 2]
  safe_z = np.where(z > geometry.MIN_DEPTH, z, 1.0)
  u = (k[0, 0] * cam[..., 0] + k[0, 1] * cam[..., 1]) / safe_z + k[0, 2]
  v = k[1, 1] * cam[..., 1] / safe_z + k[1, 2]
  return u, v, z


def seen_by_source(*, points: np.ndarray, source_depth: np.ndarray,
                   source_cam_to_world: np.ndarray, source_intrinsics: np.ndarray) -> np.ndarray:
  """Whether one source view sees each point: points [..., 4] homogeneous → [...] bool.

  A point is seen when it projects in front of the source camera into the image (between the
  outermost pixel centres, [0, W − 1] × [0, H − 1], where four pixels surround every projection)
  and is no deeper than the farthest of the four source pixels around its projection. The
  farthest, not an interpolation: camera depth over a plane or the front of a convex object is a
  convex function of the pixel, so its value inside a pixel square never exceeds the corners'
  largest, and where the four pixels show one surface the answer is exact. Where they straddle
  an occluding edge it can go either way, in a band at most one source pixel wide. A point at
  infinity is seen when one of those pixels shows nothing either.
  """
  height, width = source_depth.shape
  u, v, z = project_points(points, cam_to_world=source_cam_to_world,
                           intrinsics=source_intrinsics)
  ahead = z > geometry.MIN_DEPTH
  inside = (ahead & (u >= -PIXEL_SLACK) & (u <= width - 1 + PIXEL_SLACK) & (v >= -PIXEL_SLACK)
            & (v <= height - 1 + PIXEL_SLACK))
  u0 = np.floor(np.clip(np.where(inside, u, 0.0), 0, width - 1)).astype(np.int64)
  v0 = np.floor(np.clip(np.where(inside, v, 0.0), 0, height - 1)).astype(np.int64)
  u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
  sd = np.asarray(source_depth, np.float64)
  farthest = np.maximum(np.maximum(sd[v0, u0], sd[v0, u1]), np.maximum(sd[v1, u0], sd[v1, u1]))
  finite = points[..., 3] > 0
  seen = np.where(finite, z <= farthest * (1.0 + DEPTH_SLACK), np.isinf(farthest))
  return inside & seen


def seen_by_sources(*, depth: np.ndarray, cam_to_world: np.ndarray, intrinsics: np.ndarray,
                    source_depth: np.ndarray, source_cam_to_world: np.ndarray,
                    source_intrinsics: np.ndarray) -> np.ndarray:
  """Pixels of n views whose surface point some source view sees: → [n, H, W] bool.

  Args:
    depth, cam_to_world, intrinsics: the views, [n, H, W], [n, 4, 4], [n, 3, 3].
    source_depth, source_cam_to_world, source_intrinsics: the V source views, same layout.
  """
  out = []
  for d, pose, k in zip(depth, cam_to_world, intrinsics):
    points = surface_points(depth=d, cam_to_world=pose, intrinsics=k)
    seen = np.zeros(d.shape, bool)
    for sd, spose, sk in zip(source_depth, source_cam_to_world, source_intrinsics):
      seen |= seen_by_source(points=points, source_depth=sd, source_cam_to_world=spose,
                             source_intrinsics=sk)
    out.append(seen)
  return np.stack(out)


def pooled_psnr(squared_error: np.ndarray, region: np.ndarray) -> float:
  """PSNR (dB, data range 1) of the squared error pooled over `region`; NaN for an empty one."""
  count = int(region.sum())
  if count == 0:
    return math.nan
  mse = float(squared_error[region].sum()) / count
  return math.inf if mse == 0 else -10.0 * math.log10(mse)


def region_metrics(*, squared_error: np.ndarray, region: np.ndarray,
                   name: str) -> dict[str, float]:
  """PSNR inside a region of a scene's views, the region's pixel and error shares.

  squared_error: [n, H, W] per pixel, averaged over colour channels; region: [n, H, W] bool.
  Returns {psnr_novel_<name>, <name>_pixel_share, <name>_error_share}; the error share is NaN
  when there is no error at all.
  """
  region = np.asarray(region, bool)
  total = float(squared_error.sum())
  return {
      f"psnr_novel_{name}": pooled_psnr(squared_error, region),
      f"{name}_pixel_share": float(region.mean()),
      f"{name}_error_share": float(squared_error[region].sum()) / total if total > 0
                             else math.nan,
  }


def split_metrics(*, squared_error: np.ndarray, region: np.ndarray, inside: str,
                  outside: str) -> dict[str, float]:
  """`region_metrics` of a region and the PSNR of the pixels outside it,
  psnr_novel_<outside>."""
  region = np.asarray(region, bool)
  return {**region_metrics(squared_error=squared_error, region=region, name=inside),
          f"psnr_novel_{outside}": pooled_psnr(squared_error, ~region)}


def border_radius(width: int) -> int:
  """`object_border`'s width in pixels for images `width` pixels wide (at least 1)."""
  return max(1, round(width * BORDER_FRACTION))


def object_border(masks: np.ndarray, radius: int) -> np.ndarray:
  """Background pixels within `radius` pixels of an object pixel: masks [n, H, W] → [n, H, W] bool.

  Distance is the chessboard distance (a (2·radius + 1)² square around each object pixel), so one
  pixel of radius is the 8-neighbourhood. Label 0 is background, any other label an object.
  """
  if radius < 1:
    raise ValueError(f"object_border: radius must be at least 1, got {radius}")
  objects = np.asarray(masks) > 0
  size = 2 * radius + 1
  near = ndimage.maximum_filter(objects, size=(1, size, size), mode="constant", cval=False)
  return near & ~objects
