"""Feature lifting: project sample points into the source views, gather RGB + features
(docs/method.md §1.3).

Vocabulary (docs/method.md §0): B scenes, V source views, R rays per scene, S samples per ray, D
feature width, H×W source-image size, h×w feature-map size, C channels. Pure functions, keyword-only
arguments.

Sampling convention: bilinear with align_corners=True semantics (pixel centres at integer
coordinates, the corner pixels' centres map onto each other between resolutions) and zero padding
per tap, i.e. torch's `grid_sample(..., align_corners=True, padding_mode='zeros')`. A full-resolution
pixel coordinate u therefore sits at u·(w−1)/(W−1) on the h×w feature map.

Lifted values put RGB first, then the D features ([..., 3 + D]), as the official projector does
(`torch.cat([rgbs_sampled, feat_sampled], -1)`).
"""

from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

from slotlifter_jax import geometry

# Projected coordinates up to this far outside the image (in pixels) snap onto the border pixel
# (docs/method.md §1.3, the official projector's "avoid numerical precision errors" clamp).
BORDER_SNAP = 0.5
# Guard of the visibility weights valid / (Σ valid + ε) (docs/method.md §1.3; official 1e-6).
VISIBILITY_EPS = 1e-6


@flax.struct.dataclass
class Lifted:
  values: jax.Array  # [B, R, S, V, 3 + D]: RGB then features; exactly zero where invalid
  valid: jax.Array  # [B, R, S, V] float 0/1: in front of the camera and inside the (snapped) image


def bilinear_sample(*, image: jax.Array, pix: jax.Array) -> jax.Array:
  """Bilinear lookup with zero padding per tap: image [h, w, C], pix [..., 2] (u, v) -> [..., C].

  `pix` is in this image's own pixel coordinates, centres at integers. Each of the four taps that
  falls outside the image contributes zero, so the result equals scipy's
  `map_coordinates(order=1, mode='grid-constant', cval=0)` everywhere and
  `map_coordinates(order=1, mode='constant', cval=0)` inside [0, w−1]×[0, h−1] including the border.
  In the band less than one pixel outside the border the two scipy modes differ: 'constant' returns
  0 outright, while this function (like torch's grid_sample) fades linearly to 0, e.g. u = −0.5 gives
  half of column 0. `project_and_gather` only ever samples inside, so the difference never reaches the
  model.
  """
  height, width = image.shape[0], image.shape[1]
  # Clipping to one pixel beyond the image changes nothing (all taps there are zero) and keeps the
  # int cast well defined for huge coordinates.
  u = jnp.clip(pix[..., 0], -2.0, width + 1.0)
  v = jnp.clip(pix[..., 1], -2.0, height + 1.0)
  u0, v0 = jnp.floor(u), jnp.floor(v)
  fu, fv = u - u0, v - v0
  u0, v0 = u0.astype(jnp.int32), v0.astype(jnp.int32)
  flat = image.reshape(height * width, image.shape[-1])  # [h·w, C]

  def tap(du, dv, weight):
    ui, vi = u0 + du, v0 + dv
    inside = (ui >= 0) & (ui <= width - 1) & (vi >= 0) & (vi <= height - 1)
    index = jnp.clip(vi, 0, height - 1) * width + jnp.clip(ui, 0, width - 1)  # [...]
    # Indices are clipped above, so the gather may skip its bounds handling.
    rows = flat.at[index].get(mode="promise_in_bounds")  # [..., C]
    return jnp.where(inside, weight, 0.0)[..., None] * rows

  # Four static taps (not a loop over data): top-left, top-right, bottom-left, bottom-right.
  return (tap(0, 0, (1 - fu) * (1 - fv)) + tap(1, 0, fu * (1 - fv))
          + tap(0, 1, (1 - fu) * fv) + tap(1, 1, fu * fv))


def _project_one_view(points, cam_to_world, intrinsics, image, features):
  """One scene, one view: points [R, S, 3] -> values [R, S, 3 + D], valid [R, S]."""
  height, width = image.shape[0], image.shape[1]
  feat_h, feat_w = features.shape[0], features.shape[1]
  pix, depth = geometry.world_to_pix(points=points, cam_to_world=cam_to_world,
                                     intrinsics=intrinsics)  # [R, S, 2], [R, S]
  size = jnp.array([width, height], jnp.float32)
  inside = jnp.all((pix >= -BORDER_SNAP) & (pix <= size - 1 + BORDER_SNAP), axis=-1)  # [R, S]
  valid = inside & (depth > 0)
  pix = jnp.clip(pix, 0.0, size - 1)  # the half-pixel snap (a no-op for points strictly inside)
  # Same normalised coordinate on the feature map (align_corners=True); clip guards float round-off.
  feat_size = jnp.array([feat_w, feat_h], jnp.float32)
  pix_feat = jnp.clip(pix * (feat_size - 1) / jnp.maximum(size - 1, 1), 0.0, feat_size - 1)
  rgb = bilinear_sample(image=image, pix=pix)  # [R, S, 3]
  feat = bilinear_sample(image=features, pix=pix_feat)  # [R, S, D]
  values = jnp.concatenate([rgb, feat], axis=-1)  # [R, S, 3 + D]
  values = jnp.where(valid[..., None], values, 0.0)  # invalid points give exactly zero
  return values, valid.astype(values.dtype)


def project_and_gather(*, points: jax.Array, cam_to_world: jax.Array, intrinsics: jax.Array,
                       images: jax.Array, features: jax.Array) -> Lifted:
  """Lifts source-view RGB and features onto 3D sample points (docs/method.md §1.3).

  A point is valid in a view iff it is in front of the camera (z > 0) and its projection lies in
  [−0.5, W−0.5]×[−0.5, H−0.5]; coordinates in the half-pixel band outside [0, W−1]×[0, H−1] snap to
  the border before sampling.

  Args:
    points: [B, R, S, 3] world-frame sample points.
    cam_to_world: [B, V, 4, 4] source poses.
    intrinsics: [B, V, 3, 3] source K in pixels of `images`.
    images: [B, V, H, W, 3] source images.
    features: [B, V, h, w, D] encoder feature maps.

  Returns:
    Lifted with values [B, R, S, V, 3 + D] (RGB first) and valid [B, R, S, V].
  """
  # vmap over V (points shared, result's V axis placed after S), then over B.
  per_scene = jax.vmap(_project_one_view, in_axes=(None, 0, 0, 0, 0), out_axes=(2, 2))
  values, valid = jax.vmap(per_scene)(points, cam_to_world, intrinsics, images, features)
  return Lifted(values=values, valid=valid)  # [B, R, S, V, 3+D], [B, R, S, V]


def fuse_views(*, values: jax.Array, valid: jax.Array) -> jax.Array:
  """Combines the V views of each point (docs/method.md §1.3).

  V = 1: valid·values, [..., C]. Note the official code multiplies *after* its Linear layer
  (valid·Linear(x)), so a module reproducing it must mask the Linear output, not rely on this
  product alone (Linear(0) = bias).
  V > 1: visibility-weighted mean and variance, weights = valid / (Σ valid + 1e-6), concatenated as
  [mean, var], [..., 2C].

  Args:
    values: [..., V, C].
    valid: [..., V] float 0/1.
  """
  if values.shape[-2] == 1:
    return values[..., 0, :] * valid[..., 0, None]  # [..., C]
  weight = valid / (jnp.sum(valid, axis=-1, keepdims=True) + VISIBILITY_EPS)  # [..., V]
  mean = jnp.einsum("...v,...vc->...c", weight, values)  # [..., C]
  var = jnp.einsum("...v,...vc->...c", weight, (values - mean[..., None, :]) ** 2)  # [..., C]
  return jnp.concatenate([mean, var], axis=-1)  # [..., 2C]


def sample_ray_keep(*, key: jax.Array, keep_ratio, shape, shared_across_batch: bool = True
                    ) -> jax.Array:
  """Per-ray keep mask for random masking of lifted features (docs/method.md §1.3): 0/1 [B, R].

  A ray keeps its lifted features with probability keep_ratio. With shared_across_batch=True (the
  default, as in the official code, which draws one [1, R] mask) ray r is masked in every scene of the
  batch alike; False draws independently per scene.
  """
  batch, rays = shape
  draw_shape = (1, rays) if shared_across_batch else (batch, rays)
  keep = jax.random.uniform(key, draw_shape) < keep_ratio  # u ∈ [0, 1): ratio 1 keeps all, 0 none
  return jnp.broadcast_to(keep, (batch, rays)).astype(jnp.float32)


def apply_ray_mask(*, lifted: jax.Array, keep: jax.Array) -> jax.Array:
  """Zeroes the lifted features of masked rays: lifted [B, R, S, F], keep [B, R] -> [B, R, S, F]."""
  return lifted * keep[..., None, None].astype(lifted.dtype)
