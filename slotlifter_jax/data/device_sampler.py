"""Training batches drawn on the device, inside the jitted step (`data.sampler = "device"`).

The host sampler (`pipeline.BatchSampler`) gathers every batch in NumPy on a thread and copies it
in. Once the decoder is small, that host work, the copy and the per-step dispatch cost as much as
the step itself, so a fast run keeps the whole training split on the device (64 px clevr, 1000
scenes × 4 views: 49 MB as uint8) and draws each step's batch with `jax.random` inside the step,
which then runs `train.steps_per_dispatch` steps per call under `lax.scan`
(`train_step.make_train_block`).

It draws from the same distribution as the host sampler for fixed-source scenes (the uORF-style
sets; the pooled-source DTU/ScanNet scenes and contrast sampling stay host-only):
- B distinct scenes per batch (with repetition only when there are fewer than B);
- per scene, with probability `novel_ray_prob` its R rays come from the novel views only, else from
  all its views, sources included;
- R distinct pixels per scene, uniformly among the candidates (Gumbel top-R over every
  (view, pixel) of the scene, non-candidates excluded);
- rays through pixel centres, as `geometry.pixel_rays`.
The random stream is `jax.random`, not NumPy's, so the batches differ from the host sampler's, but
batch t is still a pure function of (seed, t): resumes stay exact.

An object-count curriculum (`data.curriculum`, uOCF's "one object first, then more") restricts the
scenes a step may draw to those with at most n objects, n a step function of the training step.
"""

from __future__ import annotations

from typing import Sequence

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax import config_checks
from slotlifter_jax import geometry
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene


@flax.struct.dataclass
class DeviceScenes:
  """A fixed-source training split as device arrays. N scenes, M views each, V sources."""
  # [N, M, H, W, 3]: uint8 (0..255, a quarter of float32's memory) when that is lossless (PNG
  # data at its own size), else float32 in [0, 1] (resized reads).
  images: jax.Array
  cam_to_world: jax.Array  # [N, M, 4, 4] float32
  intrinsics: jax.Array  # [N, M, 3, 3] float32
  source_views: jax.Array  # [N, V] int32
  novel_views: jax.Array  # [N, M] bool, views that are not sources
  num_objects: jax.Array  # [N] int32 (−1 when the data set does not say)


def scene_object_count(scene: Scene) -> int:
  """Objects in a scene: its dataset.json metadata, else the distinct labels of its masks, else −1."""
  if scene.objects is not None:
    return len(scene.objects)
  if scene.masks is not None:
    labels = np.unique(scene.masks)
    return int(np.sum(labels > 0))
  return -1


def to_device_scenes(scenes: Sequence[Scene], *, num_source_views: int) -> DeviceScenes:
  """Stacks a list of fixed-source scenes; a scene that does not fit gets a DataError naming it."""
  if not scenes:
    raise DataError("data.sampler=device: no training scenes")
  first = scenes[0]
  for s in scenes:
    if s.source_pool is not None:
      raise DataError(f"scene {s.name}: pooled sources (DTU/ScanNet) need data.sampler=host")
    if s.num_views != first.num_views or s.image_size != first.image_size:
      raise DataError(f"scene {s.name}: {s.num_views} views of {s.image_size}, scene "
                      f"{first.name} has {first.num_views} of {first.image_size}; "
                      f"data.sampler=device needs one shape")
    if len(s.source_indices) != num_source_views:
      raise DataError(f"scene {s.name}: {len(s.source_indices)} source views, "
                      f"data.num_source_views is {num_source_views}")
    if s.target_indices is not None:
      raise DataError(f"scene {s.name}: restricted target views need data.sampler=host")
  m = first.num_views
  novel = np.ones((len(scenes), m), bool)
  for i, s in enumerate(scenes):
    novel[i, list(s.source_indices)] = False
  if images_are_exact_uint8(scenes):
    images = np.stack([np.round(s.images * 255.0).astype(np.uint8) for s in scenes])
  else:
    images = np.stack([s.images for s in scenes]).astype(np.float32)
  return DeviceScenes(
      images=jnp.asarray(images),
      cam_to_world=jnp.asarray(np.stack([s.cam_to_world for s in scenes]), jnp.float32),
      intrinsics=jnp.asarray(np.stack([s.intrinsics for s in scenes]), jnp.float32),
      source_views=jnp.asarray(np.array([s.source_indices for s in scenes], np.int32)),
      novel_views=jnp.asarray(novel),
      num_objects=jnp.asarray(np.array([scene_object_count(s) for s in scenes], np.int32)))


def images_are_exact_uint8(scenes: Sequence[Scene]) -> bool:
  """True when every image is a multiple of 1/255 (PNG data): the uint8 store is then lossless
  (float32 holds k/255 to 1e-7, far inside the tolerance)."""
  return all(np.allclose(np.round(s.images * 255.0), s.images * 255.0, rtol=0.0, atol=1e-3)
             for s in scenes)


def _unit_colour(x: jax.Array) -> jax.Array:
  return x.astype(jnp.float32) / 255.0 if x.dtype == jnp.uint8 else x


def curriculum_limit(step, stages: Sequence[Sequence[int]]):
  """The largest object count step `step` may draw: stages ((start_step, max_objects), …) sorted by
  start step; before the first stage and with no stages, no limit (a large number)."""
  limit = jnp.asarray(np.iinfo(np.int32).max, jnp.int32)
  for start, max_objects in stages:
    limit = jnp.where(step >= start, jnp.asarray(max_objects, jnp.int32), limit)
  return limit


def check_curriculum(stages, scenes: Sequence[Scene]) -> tuple[tuple[int, int], ...]:
  """Validates data.curriculum against the training scenes; returns it as int pairs."""
  out = config_checks.curriculum_stages(stages)
  counts = [scene_object_count(s) for s in scenes]
  if out and min(counts) < 0:
    raise DataError("data.curriculum needs object counts, but the training scenes have neither "
                    "object metadata nor masks")
  for start, max_objects in out:
    if not any(0 <= c <= max_objects for c in counts):
      raise DataError(f"data.curriculum: no training scene has at most {max_objects} objects "
                      f"(stage from step {start}); counts range {min(counts)}–{max(counts)}")
  return tuple(out)


def sample_batch(scenes: DeviceScenes, key: jax.Array, *, batch_scenes: int, rays_per_scene: int,
                 novel_ray_prob: float, max_objects=None, with_draw: bool = False) -> dict:
  """The pipeline's batch dict (data/pipeline.py's docstring), drawn with jax.random.

  max_objects: None, or a (traced) int: only scenes with at most that many objects are drawn.
  with_draw: also return the draw (ray_views, ray_rows, ray_cols [B, R], novel_only [B]).
  """
  n, m, height, width, _ = scenes.images.shape
  b, r = batch_scenes, rays_per_scene
  k_scene, k_novel, k_pix = jax.random.split(key, 3)
  # Distinct scenes (Gumbel top-B); ineligible scenes get −inf keys and are drawn only when fewer
  # than B scenes are eligible, which check_curriculum and the caller's sizes rule out for B ≤ N.
  keys = jax.random.gumbel(k_scene, (n,))
  if max_objects is not None:
    keys = jnp.where(scenes.num_objects <= max_objects, keys, -jnp.inf)
  if b <= n:
    scene_index = jax.lax.top_k(keys, b)[1]  # [B]
  else:  # fewer scenes than a batch: with repetition, as the host sampler
    scene_index = jax.random.categorical(k_scene, keys, shape=(b,))
  novel = scenes.novel_views[scene_index]  # [B, M]
  has_novel = jnp.any(novel, axis=-1)  # [B]
  novel_only = jax.random.bernoulli(k_novel, novel_ray_prob, (b,)) & has_novel
  candidate = jnp.where(novel_only[:, None], novel, True)  # [B, M]
  pixels = height * width
  gumbel = jax.random.gumbel(k_pix, (b, m, pixels))
  gumbel = jnp.where(candidate[..., None], gumbel, -jnp.inf).reshape(b, m * pixels)
  flat = jax.lax.top_k(gumbel, r)[1]  # [B, R] distinct (view, pixel)
  view = flat // pixels
  pix = flat % pixels
  row, col = pix // width, pix % width
  c2w = scenes.cam_to_world[scene_index[:, None], view]  # [B, R, 4, 4]
  k = scenes.intrinsics[scene_index[:, None], view]  # [B, R, 3, 3]
  rays = geometry.pixel_rays(cam_to_world=c2w, intrinsics=k,
                             pix=jnp.stack([col, row], axis=-1).astype(jnp.float32))
  target = scenes.images[scene_index[:, None], view, row, col]  # [B, R, 3]
  src = scenes.source_views[scene_index]  # [B, V]
  source_images = scenes.images[scene_index[:, None], src]  # [B, V, H, W, 3]
  batch = dict(
      source_images=_unit_colour(source_images),
      source_cam_to_world=scenes.cam_to_world[scene_index[:, None], src],
      source_intrinsics=scenes.intrinsics[scene_index[:, None], src],
      ray_origins=rays.origins,
      ray_directions=rays.directions,
      target_rgb=_unit_colour(target),
      scene_index=scene_index.astype(jnp.int32))
  if with_draw:
    batch.update(ray_views=view.astype(jnp.int32), ray_rows=row.astype(jnp.int32),
                 ray_cols=col.astype(jnp.int32), novel_only=novel_only)
  return batch



def debug_draw(scenes: DeviceScenes, key: jax.Array, **kwargs) -> dict:
  """`sample_batch` as NumPy arrays (for tests and inspection)."""
  draw = jax.jit(lambda s, k: sample_batch(s, k, **kwargs))
  return jax.tree.map(np.asarray, draw(scenes, key))
