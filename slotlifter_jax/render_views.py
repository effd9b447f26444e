"""Rendering whole views of a scene with a trained model, chunk by chunk.

The slots are computed once per scene (`SlotLifter.encode`) and the rays of a view are decoded in
chunks of fixed size (the last chunk padded), so one compiled function serves every view size.
"""

from __future__ import annotations

import functools

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax import geometry
from slotlifter_jax.data.types import Scene


@flax.struct.dataclass
class RenderedViews:
  colour: np.ndarray  # [n, H, W, 3] in [0, 1]
  depth: np.ndarray  # [n, H, W] normalised scene frame
  segmentation: np.ndarray  # [n, H, W, K] soft, sums to 1 over K
  slots: np.ndarray  # [K, slot_dim]
  slot_attn: np.ndarray  # [K, V·h·w]


class SceneRenderer:
  """Renders chosen views of a Scene at full resolution with fixed-size ray chunks."""

  def __init__(self, model, config):
    self.model = model
    self.signed = config.model.colour_range == "signed"
    self.chunk = int(config.render.chunk)
    self.num_source_views = int(config.data.num_source_views)

    @jax.jit
    def encode(params, sources):
      return model.apply({"params": params}, **sources, slot_noise_sigma=0.0, train=False,
                         method=model.encode)

    @jax.jit
    def render_chunk(params, encoded, sources, origins, directions, locality):
      out = model.apply({"params": params}, encoded, **sources, ray_origins=origins,
                        ray_directions=directions, keep_ratio=1.0, locality=locality, train=False,
                        method=model.render_rays)
      final = out.fine if out.fine is not None else out.coarse
      colour = (final.colour + 1.0) * 0.5 if self.signed else final.colour
      return colour, final.depth, final.segmentation

    self._encode, self._render_chunk = encode, render_chunk

  def sources(self, scene: Scene, source_indices=None) -> dict:
    idx = np.asarray(scene.source_indices if source_indices is None else source_indices)
    images = scene.images[idx][None]  # [1, V, H, W, 3]
    if self.signed:
      images = images * 2.0 - 1.0
    return dict(source_images=jnp.asarray(images),
                source_cam_to_world=jnp.asarray(scene.cam_to_world[idx][None]),
                source_intrinsics=jnp.asarray(scene.intrinsics[idx][None]))

  def render(self, params, scene: Scene, view_indices, *, source_indices=None,
             locality: bool = False) -> RenderedViews:
    """`locality`: apply the locality constraint (SPEC §1.4), as training does before its switch-off
    step, so a validation picture shows the function that is being trained."""
    sources = self.sources(scene, source_indices)
    encoded = self._encode(params, sources)
    height, width = scene.image_size
    pix = np.asarray(geometry.image_pixels(height, width)).reshape(-1, 2)  # [H·W, 2]
    colours, depths, segs = [], [], []
    for v in view_indices:
      rays = geometry.pixel_rays(cam_to_world=jnp.asarray(scene.cam_to_world[v]),
                                 intrinsics=jnp.asarray(scene.intrinsics[v]), pix=jnp.asarray(pix))
      origins, directions = np.asarray(rays.origins), np.asarray(rays.directions)
      n = origins.shape[0]
      pad = (-n) % self.chunk
      origins = np.concatenate([origins, np.repeat(origins[-1:], pad, 0)])
      directions = np.concatenate([directions, np.repeat(directions[-1:], pad, 0)])
      parts = []
      for start in range(0, n + pad, self.chunk):
        sl = slice(start, start + self.chunk)
        parts.append(self._render_chunk(params, encoded, sources, origins[None, sl],
                                        directions[None, sl], jnp.asarray(locality)))
      c, d, s = (np.concatenate([np.asarray(p[i][0]) for p in parts])[:n] for i in range(3))
      colours.append(c.reshape(height, width, -1))
      depths.append(d.reshape(height, width))
      segs.append(s.reshape(height, width, -1))
    return RenderedViews(colour=np.stack(colours), depth=np.stack(depths),
                         segmentation=np.stack(segs), slots=np.asarray(encoded.slots[0]),
                         slot_attn=np.asarray(encoded.slot_attn[0]))
