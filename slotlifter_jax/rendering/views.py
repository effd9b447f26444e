"""Rendering whole views of a scene with a trained model, chunk by chunk.

The slots are computed once per scene (`SlotLifter.encode`) and the rays of a view are decoded in
chunks of fixed size (the last chunk padded), so one compiled function serves every view of a
size; a view with fewer rays than a chunk is one chunk of exactly its rays.
"""

from __future__ import annotations

from typing import Optional

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax import config_checks
from slotlifter_jax import geometry
from slotlifter_jax import metrics
from slotlifter_jax import programs
from slotlifter_jax.data.types import Scene


@flax.struct.dataclass
class RenderedViews:
  colour: np.ndarray  # [n, H, W, 3] in [0, 1]
  depth: np.ndarray  # [n, H, W] normalised scene frame
  segmentation: np.ndarray  # [n, H, W, K] soft, sums to 1 over K
  slots: np.ndarray  # [K, slot_dim]
  slot_attn: np.ndarray  # [K, V·h·w]
  # [V, H, W] each source pixel's slot under the slot attention alone (metrics.attention_labels)
  source_labels: np.ndarray
  # [n, H, W] Σ_i w_i along each ray (docs/method.md §1.5); None where a renderer does not keep it
  opacity: Optional[np.ndarray] = None


def source_attention_labels(encoded, image_hw: tuple[int, int]) -> np.ndarray:
  """The first scene of `encoded` (model.Encoded): its slot attention's argmax slot per source
  pixel [V, H, W], from the last iteration's attention over the V·h·w feature cells."""
  _, v, h, w, _ = encoded.features.shape
  attn = np.asarray(encoded.slot_attn[0]).reshape(-1, v, h * w)  # [K, V, h·w]
  return np.stack([metrics.attention_labels(attn[:, i], feature_hw=(h, w), image_hw=image_hw)
                   for i in range(v)])


def scene_sources(scene: Scene, *, signed: bool, source_indices=None) -> dict:
  """The model's source inputs for one scene (batch of 1); DTU/ScanNet models see [−1, 1] images."""
  idx = np.asarray(scene.source_indices if source_indices is None else source_indices)
  images = scene.images[idx][None]  # [1, V, H, W, 3]
  if signed:
    images = images * 2.0 - 1.0
  return dict(source_images=jnp.asarray(images),
              source_cam_to_world=jnp.asarray(scene.cam_to_world[idx][None]),
              source_intrinsics=jnp.asarray(scene.intrinsics[idx][None]))


def make_encode(model):
  """encode(params, sources) -> Encoded, jitted, evaluation mode (no slot noise)."""
  return programs.shared(("encode", model), lambda: jax.jit(lambda params, sources: model.apply(
      {"params": params}, **sources, slot_noise_sigma=0.0, train=False, method=model.encode)))


def render_cameras(render_chunk, *, cam_to_world, intrinsics, height: int, width: int,
                   chunk: int, supersample: int = 1) -> list[np.ndarray]:
  """Every pixel of each camera through `render_chunk(origins [1, chunk, 3], directions)`.

  `render_chunk` returns a tuple of [1, chunk, ...] arrays; the result holds, per tuple entry, an
  array [n, H·W, ...]. The last chunk repeats its last ray, so one compiled shape serves any size,
  and cameras go one at a time to bound memory. The chunk shrinks to H·W for a smaller view: a
  32² view padded to a 4096-ray chunk cost as much as a 64² one (experiments/journal/2026-11.md,
  "Speed against accuracy").

  supersample S > 1: each entry is the mean of S×S rays per pixel (`geometry.subpixel_offsets`),
  the footprint average that the embedded generator records as a pixel's colour; S² times the
  work. A model trained on centre rays gains little from it (experiments/journal/2026-11.md,
  "what one ray per pixel can reach").
  """
  centres = geometry.image_pixels(height, width).reshape(-1, 2)  # [H·W, 2]
  offsets = geometry.subpixel_offsets(supersample)
  n = height * width
  chunk = min(int(chunk), n)
  pad = (-n) % chunk
  per_camera = []
  for c2w, k in zip(cam_to_world, intrinsics):
    total = None
    for offset in offsets:
      rays = geometry.pixel_rays(cam_to_world=jnp.asarray(c2w, jnp.float32),
                                 intrinsics=jnp.asarray(k, jnp.float32), pix=centres + offset)
      origins = jnp.concatenate([rays.origins, jnp.repeat(rays.origins[-1:], pad, 0)])
      directions = jnp.concatenate([rays.directions, jnp.repeat(rays.directions[-1:], pad, 0)])
      parts = [render_chunk(origins[None, s:s + chunk], directions[None, s:s + chunk])
               for s in range(0, n + pad, chunk)]
      out = [np.concatenate([np.asarray(p[i][0]) for p in parts])[:n]
             for i in range(len(parts[0]))]
      total = out if total is None else [t + o for t, o in zip(total, out)]
    per_camera.append([t / len(offsets) for t in total])  # exact for S = 1
  return [np.stack([c[i] for c in per_camera]) for i in range(len(per_camera[0]))]


class SceneRenderer:
  """Renders chosen views of a Scene at full resolution with fixed-size ray chunks."""

  def __init__(self, model, config, *, drop_lifted: bool = False):
    """drop_lifted: render every ray without its lifted features (`SlotLifter.render_rays`)."""
    self.model = model
    self.signed = config.model.colour_range == "signed"
    self.chunk = int(config.render.chunk)
    self.supersample = config_checks.check_supersample(config.render)
    self.num_source_views = int(config.data.num_source_views)

    signed = self.signed

    def render_chunk(params, encoded, sources, origins, directions, locality):
      out = model.apply({"params": params}, encoded, **sources, ray_origins=origins,
                        ray_directions=directions, keep_ratio=1.0, locality=locality, train=False,
                        drop_lifted=drop_lifted, method=model.render_rays)
      final = out.fine if out.fine is not None else out.coarse
      colour = (final.colour + 1.0) * 0.5 if signed else final.colour
      return colour, final.depth, final.segmentation, final.opacity

    # Every validation of a run (and every Validator of one model in a process) renders with the
    # same jitted function, traced once (slotlifter_jax/programs.py).
    self._encode = make_encode(model)
    self._render_chunk = programs.shared(("render_chunk", model, signed, drop_lifted),
                                         lambda: jax.jit(render_chunk))

  def sources(self, scene: Scene, source_indices=None) -> dict:
    return scene_sources(scene, signed=self.signed, source_indices=source_indices)

  def render(self, params, scene: Scene, view_indices, *, source_indices=None,
             locality: bool = False) -> RenderedViews:
    """`locality`: apply the locality constraint (docs/method.md §1.4), as training does before its
    switch-off step, so a validation picture shows the function that is being trained."""
    sources = self.sources(scene, source_indices)
    encoded = self._encode(params, sources)
    height, width = scene.image_size
    views = list(view_indices)
    colour, depth, seg, opacity = render_cameras(
        lambda o, d: self._render_chunk(params, encoded, sources, o, d, jnp.asarray(locality)),
        cam_to_world=scene.cam_to_world[views], intrinsics=scene.intrinsics[views],
        height=height, width=width, chunk=self.chunk, supersample=self.supersample)
    n = len(views)
    colours, depths = colour.reshape(n, height, width, -1), depth.reshape(n, height, width)
    segs = seg.reshape(n, height, width, -1)
    return RenderedViews(colour=colours, depth=depths, segmentation=segs,
                         slots=np.asarray(encoded.slots[0]),
                         slot_attn=np.asarray(encoded.slot_attn[0]),
                         source_labels=source_attention_labels(encoded, (height, width)),
                         opacity=opacity.reshape(n, height, width))
