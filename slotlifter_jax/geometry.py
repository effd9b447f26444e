"""Cameras, rays, depth sampling and positional encoding (docs/method.md §1.3, §1.5, §3.1).

Vocabulary (docs/method.md §0): B scenes, V source views, R rays per scene, S samples per ray, H×W
image size, C channels. Every function here is pure, takes keyword-only arguments and works on any
leading batch shape `...`.

Camera convention (stated once, see `slotlifter_jax/__init__.py`): `cam_to_world` is a 4×4 OpenCV
camera-to-world pose (camera x right, y down, z forward); `intrinsics` is a 3×3 pixel-unit matrix K.
A pixel coordinate `pix = (u, v) = (x, y)` has pixel centres at integers, so pixel (0, 0) is the centre
of the top-left pixel and an uORF camera's principal point is ((W−1)/2, (H−1)/2).

Broadcasting: camera arrays `[..., 4, 4]` / `[..., 3, 3]` broadcast against the leading dims of the
point or pixel arrays by NumPy rules on the leading dims only, e.g. `cam_to_world [B, 1, 4, 4]` with
`pix [B, R, 2]` gives rays `[B, R, 3]`; a single camera `[4, 4]` works with any `pix [..., 2]`.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

# Depth below which a camera-space point counts as "at or behind the camera" when dividing by z; the
# official projector clamps z to the same value. Such points are always marked invalid by callers.
MIN_DEPTH = 1e-8
# Projected pixel coordinates are clipped to ±PIX_LIMIT so that points near the camera plane (or
# behind it) give finite, int-castable coordinates (the official projector clips to the same bound).
PIX_LIMIT = 1e5
# Added to every coarse weight before building the pdf, so an all-zero weight vector gives a uniform
# pdf instead of 0/0 (the official `sample_pdf` adds the same 1e-5).
PDF_EPS = 1e-5
# A cdf step below this is treated as an empty bin when inverting the cdf (official value).
PDF_DENOM_EPS = 1e-5


@flax.struct.dataclass
class Rays:
  origins: jax.Array  # [..., 3] camera centre in the world frame
  directions: jax.Array  # [..., 3] unit length, world frame


class Projection(NamedTuple):
  """A NamedTuple (not a struct dataclass) so that `pix, depth = cam_to_pix(...)` also works."""
  pix: jax.Array  # [..., 2] (u, v) pixel coordinates, clipped to ±PIX_LIMIT
  depth: jax.Array  # [...] camera-space z; the point is in front of the camera iff depth > 0


def _matvec(matrix: jax.Array, vector: jax.Array, xp=jnp) -> jax.Array:
  """[..., 3, 3] @ [..., 3] -> [...] with NumPy broadcasting of the leading dims."""
  return xp.matmul(matrix, vector[..., None])[..., 0]


def image_pixels(height: int, width: int) -> jax.Array:
  """All pixel centres of an H×W image as (u, v) = (x, y): returns [H, W, 2], float32."""
  v, u = jnp.meshgrid(
      jnp.arange(height, dtype=jnp.float32), jnp.arange(width, dtype=jnp.float32), indexing="ij")
  return jnp.stack([u, v], axis=-1)  # [H, W, 2]


def subpixel_offsets(per_side: int) -> np.ndarray:
  """[S·S, 2] (du, dv) from a pixel's centre: the centres of an S×S grid of equal cells inside it.

  The embedded generator averages these rays per pixel (anti-aliasing) and full-view rendering
  can do the same (`render.supersample`); S = 1 gives the centre alone.
  """
  if int(per_side) < 1:
    raise ValueError(f"sub-pixel grid of {per_side} per side; it must be ≥ 1")
  g = (np.arange(per_side) + 0.5) / per_side - 0.5
  du, dv = np.meshgrid(g, g, indexing="xy")
  return np.stack([du.ravel(), dv.ravel()], axis=-1).astype(np.float32)


def pix_to_cam(*, pix: jax.Array, intrinsics: jax.Array, xp=jnp) -> jax.Array:
  """Back-projects pixels to camera-space points on the plane z = 1: [..., 2] -> [..., 3].

  Uses the exact inverse of the upper-triangular K, skew included, so that `cam_to_pix` undoes it
  (the official code ignores skew here but not in the projection; DTU's decomposed K has a tiny one).
  xp: the array namespace, `jax.numpy` or `numpy` (see `pixel_rays`).
  """
  fx, fy = intrinsics[..., 0, 0], intrinsics[..., 1, 1]
  skew, cx, cy = intrinsics[..., 0, 1], intrinsics[..., 0, 2], intrinsics[..., 1, 2]
  y = (pix[..., 1] - cy) / fy
  x = (pix[..., 0] - cx - skew * y) / fx
  return xp.stack([x, y, xp.ones_like(x)], axis=-1)


def pixel_rays(*, cam_to_world: jax.Array, intrinsics: jax.Array, pix: jax.Array,
               xp=jnp) -> Rays:
  """Rays through pixel centres.

  Args:
    cam_to_world: [..., 4, 4] OpenCV pose; leading dims broadcast against pix's (e.g. [B, 1, 4, 4]).
    intrinsics: [..., 3, 3] pixel-unit K, same broadcasting.
    pix: [..., 2] (u, v) pixel coordinates, centres at integers.
    xp: the array namespace. `numpy` computes on the host in the inputs' precision (the batch
      pipeline draws rays per step in float64 on a thread, with no device dispatch); `jax.numpy`
      (default) traces into the model and the renderers.

  Returns:
    Rays with origins and unit directions, both [..., 3] (the broadcast leading shape).
  """
  dirs_cam = pix_to_cam(pix=pix, intrinsics=intrinsics, xp=xp)  # [..., 3], z = 1
  dirs = _matvec(cam_to_world[..., :3, :3], dirs_cam, xp)  # [..., 3]
  dirs = dirs / xp.linalg.norm(dirs, axis=-1, keepdims=True)  # never zero: z component is 1
  origins = xp.broadcast_to(cam_to_world[..., :3, 3], dirs.shape)
  return Rays(origins=origins, directions=dirs)


def cam_to_world_points(*, points_cam: jax.Array, cam_to_world: jax.Array) -> jax.Array:
  """Camera-space points to the world frame: R·p + t. [..., 3] -> [..., 3]."""
  return _matvec(cam_to_world[..., :3, :3], points_cam) + cam_to_world[..., :3, 3]


def world_to_cam(*, points: jax.Array, cam_to_world: jax.Array) -> jax.Array:
  """World points to camera space with the closed-form rigid inverse Rᵀ(p − t): [..., 3] -> [..., 3].

  A general 4×4 inverse (as in the official projector) is slower and less accurate in float32; the
  pose is rigid so the transpose is exact.
  """
  rot_t = jnp.swapaxes(cam_to_world[..., :3, :3], -1, -2)
  return _matvec(rot_t, points - cam_to_world[..., :3, 3])


def cam_to_pix(*, points_cam: jax.Array, intrinsics: jax.Array) -> Projection:
  """Perspective projection (docs/method.md §1.3): (u, v) = (K·p)[:2] / z.

  [..., 3] -> pix [..., 2], depth [...].

  Points at or behind the camera (z ≤ MIN_DEPTH) get finite but meaningless pixels; callers must use
  `depth > 0` as part of the validity test.
  """
  depth = points_cam[..., 2]
  safe_depth = jnp.maximum(depth, MIN_DEPTH)
  proj = _matvec(intrinsics, points_cam)  # [..., 3]
  pix = jnp.clip(proj[..., :2] / safe_depth[..., None], -PIX_LIMIT, PIX_LIMIT)
  return Projection(pix=pix, depth=depth)


def world_to_pix(*, points: jax.Array, cam_to_world: jax.Array,
                 intrinsics: jax.Array) -> Projection:
  """`cam_to_pix(world_to_cam(points))`: [..., 3] -> pix [..., 2], depth [...]."""
  return cam_to_pix(points_cam=world_to_cam(points=points, cam_to_world=cam_to_world),
                    intrinsics=intrinsics)


def stratified_depths(*, near, far, num_samples: int, batch_shape: Sequence[int],
                      key: Optional[jax.Array] = None, endpoint: bool = False) -> jax.Array:
  """Depths linear in z, with one uniform jitter per ray when a key is given (docs/method.md §1.5).

  With `endpoint=False` (default) [near, far] is cut into S equal bins of width Δ = (far − near)/S and
  z_i = near + (i + u)·Δ: u ~ U[0, 1) shared by all samples of a ray in training, u = 0 without a key
  (lower bin edges, i.e. linspace over [near, far)). All samples lie in [near, far] and evaluation is
  training with zero jitter, the same relation as in the official code.

  With `endpoint=True` this is exactly the official `sample_points_in_box`: Δ = (far − near)/(S − 1),
  evaluation is linspace(near, far, S) including far, and jittered training samples reach up to
  far + Δ (past the far plane).

  Args:
    near, far: scalars or arrays broadcastable to batch_shape.
    num_samples: S.
    batch_shape: leading shape of the result, e.g. (B, R).
    key: a PRNG key for training; None for the deterministic evaluation grid.
    endpoint: see above.

  Returns:
    z: [*batch_shape, S], sorted along the last axis.
  """
  batch_shape = tuple(batch_shape)
  near = jnp.broadcast_to(jnp.asarray(near, jnp.float32), batch_shape)[..., None]
  far = jnp.broadcast_to(jnp.asarray(far, jnp.float32), batch_shape)[..., None]
  num_bins = num_samples - 1 if endpoint else num_samples
  step = (far - near) / max(num_bins, 1)  # [..., 1]
  index = jnp.arange(num_samples, dtype=jnp.float32)  # [S]
  if key is not None:
    index = index + jax.random.uniform(key, batch_shape + (1,))  # one jitter per ray: [..., S]
  return near + step * index  # [..., S]


def _slab_crossing(o: jax.Array, d: jax.Array, *, lower, upper) -> tuple[jax.Array, jax.Array]:
  """The t interval [t_lo, t_hi] in which o + t·d lies in [lower, upper], per coordinate
  (elementwise; empty when t_lo > t_hi). A ray parallel to the slab is in it for all t or none."""
  flat = jnp.abs(d) < 1e-9
  safe = jnp.where(flat, 1.0, d)
  t1, t2 = (lower - o) / safe, (upper - o) / safe
  inside = (o >= lower) & (o <= upper)
  t_lo = jnp.where(flat, jnp.where(inside, -jnp.inf, jnp.inf), jnp.minimum(t1, t2))
  t_hi = jnp.where(flat, jnp.where(inside, jnp.inf, -jnp.inf), jnp.maximum(t1, t2))
  return t_lo, t_hi


def slab_interval(*, origins: jax.Array, directions: jax.Array, near, far, z_min: float,
                  z_max: float) -> tuple[jax.Array, jax.Array]:
  """Each ray's part of [near, far] inside the horizontal slab z_min ≤ z ≤ z_max (world frame).

  A scene on a floor has nothing to render below the floor or above its tallest object, and most
  of [near, far] lies there (embedded clevr: about half of it below the floor). Sampling only the
  slab puts every sample where the scene is. A ray that misses the slab within [near, far] keeps
  the whole interval, so it is rendered exactly as without bounds.

  Args:
    origins, directions: [..., 3] rays (directions need not be unit; t is in their units).
    near, far: scalars.
    z_min, z_max: the slab, z_min < z_max.

  Returns:
    (near, far), each [...]: near ≤ far, both inside the scalar [near, far].
  """
  oz = origins[..., 2]
  t_lo, t_hi = _slab_crossing(oz, directions[..., 2], lower=z_min, upper=z_max)
  lo = jnp.maximum(t_lo, near)
  hi = jnp.minimum(t_hi, far)
  miss = hi <= lo
  near = jnp.broadcast_to(jnp.asarray(near, jnp.float32), oz.shape)
  far = jnp.broadcast_to(jnp.asarray(far, jnp.float32), oz.shape)
  return jnp.where(miss, near, lo), jnp.where(miss, far, hi)


def sample_pdf(*, bins: jax.Array, weights: jax.Array, num_samples: int,
               key: Optional[jax.Array] = None) -> jax.Array:
  """Inverse-cdf sampling of a piecewise-constant pdf (NeRF hierarchical, docs/method.md §1.5).

  Args:
    bins: [..., M + 1] bin edges, sorted (the official fine pass passes the S − 1 midpoints of the
      coarse depths as edges and the S − 2 inner coarse weights, see `fine_depths`).
    weights: [..., M] non-negative; gradients are stopped (the fine pass samples on detached weights).
    num_samples: N.
    key: PRNG key for u ~ U[0, 1) (sorted); None for the deterministic u = linspace(0, 1, N).

  Returns:
    z: [..., N] sorted samples inside [bins[0], bins[M]], with stopped gradients.
  """
  bins = jax.lax.stop_gradient(bins)
  weights = jax.lax.stop_gradient(weights) + PDF_EPS
  num_bins = weights.shape[-1]
  batch_shape = jnp.broadcast_shapes(bins.shape[:-1], weights.shape[:-1])
  pdf = weights / jnp.sum(weights, axis=-1, keepdims=True)  # [..., M]
  cdf = jnp.minimum(1.0, jnp.cumsum(pdf[..., :-1], axis=-1))  # [..., M-1]
  zeros = jnp.zeros(cdf.shape[:-1] + (1,), cdf.dtype)
  cdf = jnp.concatenate([zeros, cdf, jnp.ones_like(zeros)], axis=-1)  # [..., M+1], exact 0 and 1 ends
  cdf = jnp.broadcast_to(cdf, batch_shape + (num_bins + 1,))
  bins = jnp.broadcast_to(bins, batch_shape + (num_bins + 1,))

  if key is None:
    u = jnp.broadcast_to(jnp.linspace(0.0, 1.0, num_samples), batch_shape + (num_samples,))
  else:
    u = jnp.sort(jax.random.uniform(key, batch_shape + (num_samples,)), axis=-1)

  # Index of the bin holding u: the number of left edges cdf[0..M-1] at or below u, minus one.
  # A [..., N, M] comparison instead of searchsorted keeps it batch-shape agnostic; M is small.
  above = jnp.sum(u[..., :, None] >= cdf[..., None, :num_bins], axis=-1)  # [..., N] in [1, M]
  below = above - 1
  cdf_lo = jnp.take_along_axis(cdf, below, axis=-1)  # [..., N]
  cdf_hi = jnp.take_along_axis(cdf, above, axis=-1)
  bin_lo = jnp.take_along_axis(bins, below, axis=-1)
  bin_hi = jnp.take_along_axis(bins, above, axis=-1)
  denom = cdf_hi - cdf_lo
  denom = jnp.where(denom < PDF_DENOM_EPS, 1.0, denom)
  t = jnp.clip((u - cdf_lo) / denom, 0.0, 1.0)
  return jax.lax.stop_gradient(bin_lo + t * (bin_hi - bin_lo))  # [..., N]


def fine_depths(*, z: jax.Array, weights: jax.Array, num_samples: int,
                key: Optional[jax.Array] = None) -> jax.Array:
  """Coarse + importance samples for the fine pass, sorted (official `sample_fine_pts`).

  The pdf lives on the S − 1 midpoints of the coarse depths with the S − 2 inner coarse weights (the
  first and last weights are dropped, as in NeRF). Note docs/method.md §8: the official code passes
  `det=is_train`, i.e. it samples deterministically in training and randomly at evaluation; the
  caller chooses by giving a key or not.

  Args:
    z: [..., S] coarse depths, sorted.
    weights: [..., S] coarse render weights (gradients are stopped).
    num_samples: N fine samples.
    key: PRNG key or None (deterministic).

  Returns:
    [..., S + N] sorted depths.
  """
  mids = 0.5 * (z[..., 1:] + z[..., :-1])  # [..., S-1]
  z_fine = sample_pdf(bins=mids, weights=weights[..., 1:-1], num_samples=num_samples, key=key)
  return jnp.sort(jnp.concatenate([jax.lax.stop_gradient(z), z_fine], axis=-1), axis=-1)


def points_along_rays(*, origins: jax.Array, directions: jax.Array, z: jax.Array) -> jax.Array:
  """o + z·d for every depth: origins, directions [..., 3], z [..., S] -> [..., S, 3]."""
  return origins[..., None, :] + directions[..., None, :] * z[..., :, None]


def positional_encoding(x: jax.Array, num_freqs: int = 10) -> jax.Array:
  """sin and cos of 2^k·x, k = 0..F−1, no π factor, raw input not included (docs/method.md §1.3).

  Feature order follows the official `positional_encoding`: first all sines, then all cosines; within
  each half channel-major, i.e. index c·F + k holds frequency 2^k of channel c:
  [sin(2^0 x_0) … sin(2^{F−1} x_0), sin(2^0 x_1) …, …, cos(2^0 x_0) …].

  Args:
    x: [..., C].
    num_freqs: F.

  Returns:
    [..., 2·C·F].
  """
  freqs = 2.0 ** jnp.arange(num_freqs, dtype=jnp.float32)  # [F], exact powers of two
  scaled = x[..., :, None] * freqs  # [..., C, F]
  scaled = scaled.reshape(x.shape[:-1] + (x.shape[-1] * num_freqs,))  # [..., C·F]
  return jnp.concatenate([jnp.sin(scaled), jnp.cos(scaled)], axis=-1)  # [..., 2·C·F]
