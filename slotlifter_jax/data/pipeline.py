"""The training batch pipeline (docs/method.md §2): fixed-shape NumPy batches, reproducible from
(seed, step).

Vocabulary: B scenes (or target views) per batch, V source views, R rays per scene, H×W image size.

A batch is a dict of NumPy arrays:
  source_images        [B, V, H, W, 3] float32 in [0, 1]
  source_cam_to_world  [B, V, 4, 4]    float32, OpenCV, normalised scene frame
  source_intrinsics    [B, V, 3, 3]    float32, pixels
  ray_origins          [B, R, 3]       float32
  ray_directions       [B, R, 3]       float32, unit length
  target_rgb           [B, R, 3]       float32 in [0, 1]
  scene_index          [B]             int32, index into the sampler's scene list

Fixed-source scenes (uORF-style sets): scenes are drawn at random (without repetition within a batch
when there are enough); per scene, with probability `novel_ray_prob` the R rays are random pixels of
the novel views only, otherwise of all views (sources included); pixels never repeat within a scene.
Pooled-source scenes (DTU, ScanNet): per batch element a scene and one of its target views are
drawn, the sources are the V views of its pool nearest to the target (`cameras.nearest_sources`), and the
R rays are distinct random pixels of that target view.

Ray sampling (`ray_sampling`): "uniform" is the paper's (every candidate pixel equally likely).
"contrast" draws a fraction `contrast_mix` of the probability mass in proportion to how far a pixel's
colour lies from its view's median colour (`pixel_contrast`), the rest uniformly; pixels still never
repeat. It uses the images only (no masks). It exists for CPU-sized runs, where small objects on a
plain floor get few rays: on embedded clevr at 64×64 objects cover 11 % of the pixels, so about five
of a scene's 256 uniform rays per step fall on each object; contrast sampling at mix 0.5 raises the
objects' share of the rays to 41 % (experiments/ray_foreground_share.py). It reweights the
photometric loss towards contrasted pixels, a departure from the paper. `clevr.py:scene` uses it
(docs/fast_model.md §3; experiments/journal/2026-11.md, "the scene frame, ray sampling, a longer
masked phase, more scenes"); it did not help the `paper_cpu` run (docs/quick_model.md). Grey objects on the grey floor are not left out: on the 100 validation scenes the
pixels of a grey object are drawn 3.88× as often as under uniform sampling, those of a coloured
one 3.92× (medians over object views; `python experiments/ray_foreground_share.py
--config=configs/clevr.py:scene --scenes=100`).

"floor_parallax" draws the same share `contrast_mix` by `parallax_weights`: the contrast above
times how far a pixel's colour is from what the other views of its scene show where its ray meets
the floor plane z = 0. On a textured floor the median colour no longer marks the background (floor
texture and walls are as far from it as the objects), and contrast sampling puts 17 % of the rays
on the embedded room set's chairs, which cover 11 % of the pixels; a floor point keeps its colour
from view to view whatever its texture, so the product puts 36 % there (mix 0.5, 60 validation
scenes; `python experiments/ray_foreground_share.py --config=configs/room_chair.py:scene`). It
needs a floor at z = 0 (the uORF-style and embedded sets) and two or more views per scene.

Stages (`scene_stages`, `ray_stages`: ((start_step, value), …), sorted by start step): from each
start step on, batches are drawn from the first `value` scenes of the list, or carry `value` rays
per scene; before the first stage, from all scenes and with `rays_per_scene` rays. A step's draw
depends on the stage it falls in only, so until a stage starts every batch equals that of a sampler
without it, and a run may be resumed with a stage added after its last step. They exist to grow the
training set and the ray batch once slot attention's grouping has settled: from step 0, more
scenes or rays delay the grouping the embedded runs rely on (docs/fast_model.md §2;
experiments/journal/2026-11.md, "more training scenes against the PSNR gap" and "more scenes and
rays only after the grouping has settled").

Every random choice of step t comes from `np.random.default_rng([seed, t])`, so batch t is the same
in a resumed run, whatever came before. `prefetch` builds batches on a background thread.
"""

from __future__ import annotations

import dataclasses
import queue
import threading
from typing import Iterable, Iterator, Optional, Sequence

import numpy as np

from slotlifter_jax import config_checks
from slotlifter_jax import geometry
from slotlifter_jax.data import cameras
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene

RAY_SAMPLING = ("uniform", "contrast", "floor_parallax")
# The plane the floor_parallax sampler reprojects through: the ground plane of the uORF-style sets
# and the embedded ones, in their normalised frame (docs/method.md §3.1, §3.5).
FLOOR_Z = 0.0


def pixel_contrast(images: np.ndarray) -> np.ndarray:
  """Distance of every pixel's colour from its view's per-channel median: [N, H, W, 3] → [N, H·W].

  The median is the background colour of a view that is mostly floor or wall, so the distance is
  large on objects, their shadows and highlights, and near zero on plain background.
  """
  flat = images.reshape(images.shape[0], -1, images.shape[-1]).astype(np.float64)  # [N, H·W, 3]
  median = np.median(flat, axis=1, keepdims=True)  # [N, 1, 3]
  return np.linalg.norm(flat - median, axis=-1)  # [N, H·W]


def contrast_weights(images: np.ndarray) -> np.ndarray:
  """`pixel_contrast` normalised per view: [N, H, W, 3] → [N, H·W] float32, rows sum to 1. Each
  view gets the same total mass, so a busy view does not crowd out the others; a view without
  contrast is uniform."""
  contrast = pixel_contrast(images)
  total = contrast.sum(axis=1, keepdims=True)
  return np.where(total > 0, contrast / np.maximum(total, 1e-12),
                  1.0 / contrast.shape[1]).astype(np.float32)


def floor_reprojection_error(scene: Scene, *, floor_z: float = FLOOR_Z) -> np.ndarray:
  """How far each pixel's colour lies from what the scene's other views show where its ray meets
  the floor plane z = floor_z: [N, H·W], the smallest colour distance over the views that see
  that point (nearest pixel), 0 where no other view does or the ray never meets the floor.

  A floor pixel, textured or not, finds its own colour again in another view, and so does a
  shadow on the floor; a pixel on an object does not, because the other views see the floor behind
  it from another side. Walls and highlights are off the floor plane too. Uses the images and the
  poses only (no masks, no depth).
  """
  n, height, width, _ = scene.images.shape
  v, u = np.mgrid[0:height, 0:width].astype(np.float64)
  pix = np.stack([u, v], axis=-1)  # [H, W, 2]
  images = scene.images.astype(np.float64)
  error = np.zeros((n, height, width))
  for a in range(n):
    rays = geometry.pixel_rays(cam_to_world=scene.cam_to_world[a].astype(np.float64),
                               intrinsics=scene.intrinsics[a].astype(np.float64), pix=pix, xp=np)
    down = rays.directions[..., 2] < -1e-6
    t = np.where(down, (floor_z - rays.origins[..., 2]) / np.where(down, rays.directions[..., 2],
                                                                     -1.0), 0.0)
    points = rays.origins + t[..., None] * rays.directions  # [H, W, 3]
    best = np.full((height, width), np.inf)
    for b in range(n):
      if b == a:
        continue
      # NumPy on the sampler's thread, as the rays are: the rigid inverse Rᵀ(p − t), then K.
      pose = scene.cam_to_world[b].astype(np.float64)
      points_cam = (points - pose[:3, 3]) @ pose[:3, :3]
      z = points_cam[..., 2]
      uvw = points_cam @ scene.intrinsics[b].astype(np.float64).T
      with np.errstate(divide="ignore", invalid="ignore"):
        col = np.round(np.where(z > 0, uvw[..., 0] / z, -1.0))
        row = np.round(np.where(z > 0, uvw[..., 1] / z, -1.0))
      seen = down & (z > 0) & (col >= 0) & (col < width) & (row >= 0) & (row < height)
      col = np.where(seen, col, 0).astype(np.int64)
      row = np.where(seen, row, 0).astype(np.int64)
      other = images[b][row, col]
      distance = np.linalg.norm(other - images[a], axis=-1)
      best = np.where(seen, np.minimum(best, distance), best)
    error[a] = np.where(np.isfinite(best), best, 0.0)
  return error.reshape(n, -1)


def parallax_weights(scene: Scene) -> np.ndarray:
  """The floor_parallax sampler's weights [N, H·W], rows summing to 1: `pixel_contrast` times
  `floor_reprojection_error`. The first is large on objects and on a textured floor's texture, the
  second on objects and walls, so their product is large where both are: on the objects."""
  weight = pixel_contrast(scene.images) * floor_reprojection_error(scene)
  total = weight.sum(axis=1, keepdims=True)
  return np.where(total > 0, weight / np.maximum(total, 1e-12),
                  1.0 / weight.shape[1]).astype(np.float32)


def mix_with_uniform(weights: np.ndarray, mix: float) -> np.ndarray:
  """Contrast sampling's per-pixel probability: `mix` of the mass by `weights` [..., H·W] (rows
  summing to 1), the rest uniform."""
  return (1.0 - mix) / weights.shape[-1] + mix * weights


def weighted_choice_without_replacement(rng: np.random.Generator, *, probs: np.ndarray,
                                        size: int) -> np.ndarray:
  """`size` distinct indices drawn one after another with probability ∝ probs among those left
  (Gumbel top-k: the `size` largest log p + Gumbel noise). Zero-probability entries come last."""
  keys = np.log(np.maximum(probs, 1e-300)) + rng.gumbel(size=probs.shape)
  return np.argpartition(-keys, size - 1)[:size]


def stage_value(step: int, stages, default: int) -> int:
  """The value of the last stage ((start_step, value), …, sorted) started by `step`; before the
  first stage and with no stages, `default`."""
  value = default
  for start, v in stages:
    if step >= start:
      value = v
  return int(value)


BATCH_KEYS = ("source_images", "source_cam_to_world", "source_intrinsics", "ray_origins",
              "ray_directions", "target_rgb", "scene_index")


def sources_for_target(scene: Scene, *, target_idx: int, num_source_views: int) -> tuple[int, ...]:
  """The source views used to render `target_idx`: fixed sources, or the pool's nearest views."""
  if scene.source_pool is None:
    return tuple(scene.source_indices)
  return cameras.nearest_sources(cam_to_world=scene.cam_to_world, target_idx=target_idx,
                                 pool=scene.source_pool, n=num_source_views)


def per_target_scenes(scene: Scene, *, num_source_views: int) -> list[Scene]:
  """Evaluation form of a pooled-source scene: one fixed-source Scene per target.

  Each holds its V nearest sources followed by the target (views [sources…, target]), so code that
  renders "every view of a scene with its source_indices" evaluates one target with its own sources.
  A fixed-source scene is returned unchanged (as a one-element list).
  """
  if scene.source_pool is None:
    return [scene]
  out = []
  for target in scene.target_indices:
    views = list(sources_for_target(scene, target_idx=target, num_source_views=num_source_views))
    views.append(target)
    idx = np.array(views)
    names = scene.view_names
    out.append(dataclasses.replace(
        scene,
        name=f"{scene.name}/{names[target] if names else target}",
        images=scene.images[idx],
        cam_to_world=scene.cam_to_world[idx],
        intrinsics=scene.intrinsics[idx],
        source_indices=tuple(range(num_source_views)),
        masks=None if scene.masks is None else scene.masks[idx],
        mask_views=None if scene.mask_views is None else scene.mask_views[idx],
        depth=None if scene.depth is None else scene.depth[idx],
        target_indices=None,
        source_pool=None,
        view_names=None if names is None else tuple(names[i] for i in views),
    ))
  return out


@dataclasses.dataclass(frozen=True)
class BatchDraw:
  """The random choices of one step, before any pixel is gathered."""
  scene_index: np.ndarray  # [B] int32
  source_views: np.ndarray  # [B, V] int32, view indices within each scene
  ray_views: np.ndarray  # [B, R] int32
  ray_rows: np.ndarray  # [B, R] int32
  ray_cols: np.ndarray  # [B, R] int32
  novel_only: np.ndarray  # [B] bool: the rays were restricted to non-source views

  def take(self, rows) -> "BatchDraw":
    """The draw of batch elements `rows` only (a process's share of a global batch)."""
    return BatchDraw(**{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)})


class BatchSampler:
  """Draws the step-t batch of a scene list; a pure function of (scenes, settings, seed, t)."""

  def __init__(self, scenes: Sequence[Scene], *, batch_scenes: int, rays_per_scene: int,
               num_source_views: int, novel_ray_prob: float, seed: int,
               ray_sampling: str = "uniform", contrast_mix: float = 0.5,
               scene_stages=(), ray_stages=()):
    if not scenes:
      raise DataError("BatchSampler: no scenes to draw from")
    if ray_sampling not in RAY_SAMPLING:
      raise ValueError(f"data.ray_sampling is {ray_sampling!r}; use one of {RAY_SAMPLING}")
    if not 0.0 <= contrast_mix <= 1.0:
      raise ValueError(f"data.contrast_mix is {contrast_mix}; it must lie in [0, 1]")
    self.ray_sampling = ray_sampling
    self.contrast_mix = float(contrast_mix)
    self._contrast: dict[int, np.ndarray] = {}  # scene → [views, H·W] normalised per view
    self.scenes = list(scenes)
    self.batch_scenes = int(batch_scenes)
    self.rays_per_scene = int(rays_per_scene)
    self.num_source_views = int(num_source_views)
    self.novel_ray_prob = float(novel_ray_prob)
    self.seed = int(seed)
    self._sources: dict[tuple[int, int], tuple[int, ...]] = {}  # (scene, target) → sources
    self.scene_stages = config_checks.check_stages(scene_stages, field="data.scene_stages",
                                                   upper=len(self.scenes))
    self.ray_stages = config_checks.check_stages(ray_stages, field="train.ray_stages",
                                                 upper=2**31 - 1)
    self._check()

  def num_scenes_at(self, step: int) -> int:
    """How many scenes (the first ones of the list) step `step` draws from."""
    return stage_value(step, self.scene_stages, len(self.scenes))

  def rays_at(self, step: int) -> int:
    """Rays per scene of step `step`'s batch."""
    return stage_value(step, self.ray_stages, self.rays_per_scene)

  def _check(self) -> None:
    size = self.scenes[0].image_size
    pixels = size[0] * size[1]
    rays = max([self.rays_per_scene] + [r for _, r in self.ray_stages])
    for scene in self.scenes:
      if scene.image_size != size:
        raise DataError(f"scene {scene.name}: images are {scene.image_size} but scene "
                        f"{self.scenes[0].name}'s are {size}; a batch needs one size")
      if scene.source_pool is None:
        if len(scene.source_indices) != self.num_source_views:
          raise DataError(f"scene {scene.name}: {len(scene.source_indices)} source views, "
                          f"data.num_source_views is {self.num_source_views}")
        novel = len(scene.novel_indices) or scene.num_views
        if novel * pixels < rays:
          raise DataError(f"scene {scene.name}: {novel} novel views of {size} hold fewer than "
                          f"{rays} pixels")
      elif pixels < rays:
        raise DataError(f"scene {scene.name}: a {size} target view holds fewer than "
                        f"{rays} pixels")

  def _scene_sources(self, scene_idx: int, target: int) -> tuple[int, ...]:
    key = (scene_idx, target)
    if key not in self._sources:
      self._sources[key] = sources_for_target(self.scenes[scene_idx], target_idx=target,
                                              num_source_views=self.num_source_views)
    return self._sources[key]

  def _pick(self, rng: np.random.Generator, scene_idx: int, views: np.ndarray,
            pixels: int, r: int) -> np.ndarray:
    """r distinct flat (view-in-pool, pixel) indices into len(views)·pixels candidates."""
    if self.ray_sampling == "uniform":
      return rng.choice(len(views) * pixels, size=r, replace=False)
    if scene_idx not in self._contrast:
      scene = self.scenes[scene_idx]
      self._contrast[scene_idx] = (parallax_weights(scene)
                                   if self.ray_sampling == "floor_parallax"
                                   else contrast_weights(scene.images))
    probs = mix_with_uniform(self._contrast[scene_idx][views], self.contrast_mix)
    return weighted_choice_without_replacement(rng, probs=probs.reshape(-1), size=r)

  def draw(self, step: int) -> BatchDraw:
    """The random choices of step `step` (scenes, targets, sources, pixels)."""
    rng = np.random.default_rng([self.seed, int(step)])
    n, b, r = self.num_scenes_at(step), self.batch_scenes, self.rays_at(step)
    scene_index = rng.choice(n, size=b, replace=n < b)
    height, width = self.scenes[0].image_size
    pixels = height * width
    sources, views, flat, novel_only = [], [], [], []
    for s in scene_index:
      scene = self.scenes[s]
      if scene.source_pool is None:
        novel = scene.novel_indices
        only_novel = bool(novel) and rng.random() < self.novel_ray_prob
        pool = np.array(novel if only_novel else range(scene.num_views))  # candidate views
        pick = self._pick(rng, int(s), pool, pixels, r)  # distinct (view, pixel)
        views.append(pool[pick // pixels])
        sources.append(scene.source_indices)
        novel_only.append(only_novel)
      else:
        target = int(scene.target_indices[rng.integers(len(scene.target_indices))])
        pick = self._pick(rng, int(s), np.array([target]), pixels, r)
        views.append(np.full(r, target))
        sources.append(self._scene_sources(int(s), target))
        novel_only.append(True)
      flat.append(pick % pixels)
    flat = np.stack(flat)  # [B, R]
    return BatchDraw(
        scene_index=scene_index.astype(np.int32),
        source_views=np.array(sources, dtype=np.int32).reshape(b, self.num_source_views),
        ray_views=np.stack(views).astype(np.int32),
        ray_rows=(flat // width).astype(np.int32),
        ray_cols=(flat % width).astype(np.int32),
        novel_only=np.array(novel_only, dtype=bool))

  def gather(self, draw: BatchDraw) -> dict[str, np.ndarray]:
    """The batch arrays (module docstring) for a draw."""
    out = {k: [] for k in BATCH_KEYS[:-1]}
    for b, s in enumerate(draw.scene_index):
      scene = self.scenes[s]
      src = draw.source_views[b]  # [V]
      out["source_images"].append(scene.images[src])
      out["source_cam_to_world"].append(scene.cam_to_world[src])
      out["source_intrinsics"].append(scene.intrinsics[src])
      view = draw.ray_views[b]  # [R]
      pix = np.stack([draw.ray_cols[b], draw.ray_rows[b]], axis=-1).astype(np.float64)  # [R, 2]
      rays = geometry.pixel_rays(cam_to_world=scene.cam_to_world[view].astype(np.float64),
                                 intrinsics=scene.intrinsics[view].astype(np.float64), pix=pix,
                                 xp=np)
      out["ray_origins"].append(rays.origins)
      out["ray_directions"].append(rays.directions)
      out["target_rgb"].append(scene.images[view, draw.ray_rows[b], draw.ray_cols[b]])  # [R, 3]
    batch = {k: np.stack(v).astype(np.float32) for k, v in out.items()}
    batch["scene_index"] = draw.scene_index.astype(np.int32)
    return batch

  def batch(self, step: int, rows=None) -> dict[str, np.ndarray]:
    """The batch of step `step`; with `rows` (indices into the batch), only those elements.

    The draw is always that of the whole batch (its random choices come one after another from
    one generator), so `batch(t, rows)` is `batch(t)` restricted to `rows`, and processes that
    each gather their own rows together hold exactly the single-process batch."""
    draw = self.draw(step)
    return self.gather(draw if rows is None else draw.take(rows))


class _End:
  pass


@dataclasses.dataclass(frozen=True)
class _Failure:
  error: BaseException


class Prefetcher:
  """Iterates `iterator` on a daemon thread, `size` items ahead; `close()` stops it cleanly.

  An exception raised by the iterator is re-raised by `next()` in the consumer.
  """

  _POLL_SECONDS = 0.05  # how often a blocked producer checks whether it should stop

  def __init__(self, iterator: Iterable, size: int = 2):
    if size < 1:
      raise ValueError(f"prefetch size must be ≥ 1, got {size}")
    self._queue: queue.Queue = queue.Queue(maxsize=size)
    self._stop = threading.Event()
    self._done = False
    self._thread = threading.Thread(target=self._produce, args=(iter(iterator),), daemon=True,
                                    name="batch-prefetch")
    self._thread.start()

  def _put(self, item) -> bool:
    while not self._stop.is_set():
      try:
        self._queue.put(item, timeout=self._POLL_SECONDS)
        return True
      except queue.Full:
        continue
    return False

  def _produce(self, iterator: Iterator) -> None:
    try:
      for item in iterator:
        if not self._put(item):
          return
    except BaseException as e:  # handed to the consumer, which re-raises it
      self._put(_Failure(e))
      return
    self._put(_End())

  def __iter__(self) -> "Prefetcher":
    return self

  def __next__(self):
    if self._done:
      raise StopIteration
    item = self._queue.get()
    if isinstance(item, _End):
      self._done = True
      raise StopIteration
    if isinstance(item, _Failure):
      self._done = True
      raise item.error
    return item

  def close(self, timeout: Optional[float] = 5.0) -> None:
    """Stops the producer (it finishes at most the item it is building) and joins it."""
    self._stop.set()
    self._done = True
    while True:  # unblock a producer waiting on a full queue
      try:
        self._queue.get_nowait()
      except queue.Empty:
        break
    self._thread.join(timeout)

  @property
  def alive(self) -> bool:
    return self._thread.is_alive()

  def __enter__(self) -> "Prefetcher":
    return self

  def __exit__(self, *exc) -> None:
    self.close()

  def __del__(self):
    self._stop.set()


def prefetch(iterator: Iterable, size: int = 2) -> Prefetcher:
  """Runs `iterator` `size` items ahead on a background thread (so the jitted step never waits)."""
  return Prefetcher(iterator, size=size)
