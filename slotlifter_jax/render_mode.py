"""`--mode=render`: pictures of chosen scenes of a trained run — a panel per scene and an orbit GIF.

Vocabulary (docs/method.md §0): B scenes, R rays, S samples per ray, K slots (K+1 with the empty
slot at index 0), H×W image size, F orbit frames.

DIR/render/<split>/scene_XXXX_panel.png (XXXX = the scene's index in the split) has one row per
view, columns
  source | truth | [ground-truth mask] | rendering | depth | segmentation overlay | s0 … s(K−1)
(the K real slots, the empty slot excluded; s0 is the background slot when the locality constraint
was on). The overlay blends the slot colours (vis.PALETTE mixed by the soft weights) over the
rendering; "sk" is what slot k renders alone: the volume rendering with only slot k's share σ_k
of the density (the model's `RenderOutput.slot_density`: exp(s_σ)·W_k·ReLU(A_k), docs/method.md
§1.4, or with `model.density_mode = "mlp"` the head's σ split by the weights W_k; Σ_k σ_k = σ)
and each sample's colour unchanged. No background colour is added
(docs/method.md §1.5), so what a slot does not hold is black.

DIR/render/<split>/scene_XXXX_orbit.gif shows rendering | segmentation side by side from F cameras
circling the world z axis at the source camera's height and horizontal radius, looking at the
origin (OpenCV cam2world, z up), starting at the source camera. A thin bar under the frames grows
with the azimuth.

With `render.adaptive` on, panels and orbits are rendered adaptively (slotlifter_jax.adaptive,
issue #7); the per-slot renderings of a windowed pixel then composite that pixel's window.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from PIL import Image, ImageDraw
from tqdm import tqdm

from slotlifter_jax import adaptive
from slotlifter_jax import evaluate
from slotlifter_jax import model as model_lib
from slotlifter_jax import render
from slotlifter_jax import render_views
from slotlifter_jax import vis
from slotlifter_jax.data import cameras
from slotlifter_jax.data.types import Scene

MAX_ORBIT_FRAMES = 64  # keeps a GIF at 128×128 well under a few MB
ORBIT_FRAME_MS = 80
OVERLAY_ALPHA = 0.5  # weight of the segmentation colours over the rendering
MIN_ORBIT_RADIUS = 1e-6  # a camera on the z axis has no azimuth to orbit
PAD = 2  # pixels between panel tiles
HEADER = 12  # pixels of the column-title strip (PIL's default bitmap font is 11 px high)
BAR = 3  # pixels of the orbit progress bar


# ---------------------------------------------------------------------------------------------
# Per-slot rendering
# ---------------------------------------------------------------------------------------------


def render_rays(model: model_lib.SlotLifter, params, encoded: model_lib.Encoded, *,
                sources: dict, ray_origins: jax.Array, ray_directions: jax.Array,
                z: Optional[jax.Array] = None,
                last_delta: Optional[jax.Array] = None) -> model_lib.RenderOutput:
  """`model.render_rays` at evaluation; with z [B, R, S'] (and last_delta [B, R]) the coarse pass
  at those depths instead (`model.render_at_depths`, adaptive rendering).

  sources: source_images [B, V, H, W, 3] (in the model's colour range), source_cam_to_world,
  source_intrinsics; rays [B, R, 3]. The output carries each slot's share of the density and each
  sample's colour (`RenderOutput.slot_density`, `.sample_colour`) for `render_each_slot`.
  """
  if z is None:
    method, extra = model.render_rays, dict(train=False)
  else:
    method, extra = model.render_at_depths, dict(z=z, last_delta=last_delta)
  return model.apply({"params": params}, encoded, **sources, ray_origins=ray_origins,
                     ray_directions=ray_directions, method=method, **extra)


def render_each_slot(out: model_lib.RenderOutput, *, far: float, density_scale: float,
                     last_delta: Optional[jax.Array] = None) -> render.RenderResult:
  """Volume rendering of every slot alone (module docstring): colour [B, R, K, 3], depth [B, R, K].

  out: the model's rendering of the rays (its last pass's per-slot densities and sample colours).
  last_delta: None, or [B, R] the grid δ of the last sample of a window (adaptive rendering).
  """
  sigma = jnp.moveaxis(out.slot_density, -1, -2)  # [B, R, K, S]
  z = jnp.broadcast_to(out.z[..., None, :], sigma.shape)  # [B, R, K, S]
  colour = jnp.broadcast_to(out.sample_colour[..., None, :, :],
                            sigma.shape + out.sample_colour.shape[-1:])  # [B, R, K, S, 3]
  if last_delta is not None:
    last_delta = jnp.broadcast_to(last_delta[..., None], sigma.shape[:-1])  # [B, R, K]
  return render.volume_render(density=sigma, z=z, colour=colour, slot_weights=None, far=far,
                              density_scale=density_scale, last_delta=last_delta)


@dataclasses.dataclass(frozen=True)
class CameraRenders:
  """Full-resolution renderings of n cameras (NumPy, colours in [0, 1])."""
  colour: np.ndarray  # [n, H, W, 3]
  depth: np.ndarray  # [n, H, W]
  segmentation: np.ndarray  # [n, H, W, K]
  slot_colour: np.ndarray  # [n, H, W, K, 3] each slot rendered alone


def slot_render_fn(model: model_lib.SlotLifter, params, encoded, sources: dict, *, signed: bool):
  """adaptive.RenderFn of the panel's outputs: colour, depth, segmentation, per-slot colours."""
  unit = (lambda c: (c + 1.0) * 0.5) if signed else (lambda c: c)
  def fn(origins, directions, z, last_delta):
    out = render_rays(model, params, encoded, sources=sources, ray_origins=origins,
                      ray_directions=directions, z=z, last_delta=last_delta)
    final = out.coarse
    slots = render_each_slot(out, far=model.far, density_scale=model.density_scale,
                             last_delta=last_delta)
    return (unit(final.colour), final.depth, final.segmentation, unit(slots.colour)), final.weights
  return fn


class SlotRenderer:
  """Renders arbitrary cameras of a scene in fixed-size ray chunks, with per-slot renderings;
  adaptively (slotlifter_jax.adaptive) when `render.adaptive` is on."""

  def __init__(self, model: model_lib.SlotLifter, config: ml_collections.ConfigDict):
    self.signed = config.model.colour_range == "signed"
    self.chunk = int(config.render.chunk)
    self.adaptive = None
    if config.render.get("adaptive", False):
      if int(config.render.num_fine_samples) > 0:
        raise ValueError("render.adaptive: the model has a fine pass (DTU/ScanNet); adaptive "
                         "rendering covers coarse-only models only, set render.adaptive=False")
      self.adaptive = adaptive.AdaptiveSettings.from_config(config)
      grid = adaptive.SampleGrid(near=model.near, far=model.far, num_samples=model.num_samples)
      st = self.adaptive

      @jax.jit
      def proposal_chunk(params, encoded, sources, origins, directions):
        fn = slot_render_fn(model, params, encoded, sources, signed=self.signed)
        return adaptive.proposal_pass(fn, origins=origins, directions=directions, grid=grid,
                                      mass_eps=st.mass_eps)

      @jax.jit
      def window_chunk(params, encoded, sources, origins, directions, start):
        fn = slot_render_fn(model, params, encoded, sources, signed=self.signed)
        return adaptive.window_pass(fn, origins=origins, directions=directions, start=start,
                                    grid=grid, window=st.window)

      self._proposal_chunk, self._window_chunk = proposal_chunk, window_chunk

    @jax.jit
    def render_chunk(params, encoded, sources, origins, directions):
      out = render_rays(model, params, encoded, sources=sources, ray_origins=origins,
                        ray_directions=directions)
      final = out.fine if out.fine is not None else out.coarse
      slots = render_each_slot(out, far=model.far, density_scale=model.density_scale)
      unit = (lambda c: (c + 1.0) * 0.5) if self.signed else (lambda c: c)
      return unit(final.colour), final.depth, final.segmentation, unit(slots.colour)

    self._encode, self._render_chunk = render_views.make_encode(model), render_chunk

  def sources(self, scene: Scene) -> dict:
    return render_views.scene_sources(scene, signed=self.signed)

  def render(self, params, scene: Scene, *, cam_to_world: np.ndarray,
             intrinsics: np.ndarray) -> CameraRenders:
    """cam_to_world [n, 4, 4], intrinsics [n, 3, 3] at the scene's image size."""
    sources = self.sources(scene)
    encoded = self._encode(params, sources)
    height, width = scene.image_size
    if self.adaptive is not None:
      return self._render_adaptive(params, encoded, sources, cam_to_world=cam_to_world,
                                   intrinsics=intrinsics, height=height, width=width)
    colour, depth, seg, slots = render_views.render_cameras(
        lambda o, d: self._render_chunk(params, encoded, sources, o, d),
        cam_to_world=cam_to_world, intrinsics=intrinsics, height=height, width=width,
        chunk=self.chunk)
    k = seg.shape[-1]
    return CameraRenders(colour=colour.reshape(-1, height, width, 3),
                         depth=depth.reshape(-1, height, width),
                         segmentation=seg.reshape(-1, height, width, k),
                         slot_colour=slots.reshape(-1, height, width, k, 3))

  def _render_adaptive(self, params, encoded, sources, *, cam_to_world, intrinsics, height,
                       width) -> CameraRenders:
    proposal_fn = lambda o, d: self._proposal_chunk(params, encoded, sources, o, d)
    window_fn = lambda o, d, i0: self._window_chunk(params, encoded, sources, o, d, i0)
    views = []
    for c2w, k in zip(cam_to_world, intrinsics):
      origins, directions = adaptive.camera_rays(cam_to_world=c2w, intrinsics=k, height=height,
                                                 width=width)
      outputs, _ = adaptive.render_view(proposal_fn=proposal_fn, window_fn=window_fn,
                                        origins=origins, directions=directions, height=height,
                                        width=width, settings=self.adaptive)
      views.append(outputs)
    colour, depth, seg, slots = (np.stack([v[i] for v in views]) for i in range(4))
    k = seg.shape[-1]
    return CameraRenders(colour=colour.reshape(-1, height, width, 3),
                         depth=depth.reshape(-1, height, width),
                         segmentation=seg.reshape(-1, height, width, k),
                         slot_colour=slots.reshape(-1, height, width, k, 3))


# ---------------------------------------------------------------------------------------------
# Cameras and pictures
# ---------------------------------------------------------------------------------------------


def orbit_cam_to_world(*, source_cam_to_world: np.ndarray, num_frames: int) -> np.ndarray:
  """[F, 4, 4] OpenCV cam2world poses circling the world z axis, looking at the origin.

  Every camera has the source camera's height and horizontal distance from the z axis; frame i
  sits at the source azimuth + 2π·i/F, so frame 0 is at the source camera's position.
  """
  eye = np.asarray(source_cam_to_world, np.float64)[:3, 3]
  radius = math.hypot(eye[0], eye[1])
  if radius < MIN_ORBIT_RADIUS:
    raise ValueError(f"source camera at {eye.tolist()} lies on the z axis: no orbit around it")
  azimuth = math.atan2(eye[1], eye[0]) + 2.0 * np.pi * np.arange(num_frames) / num_frames  # [F]
  eyes = np.stack([radius * np.cos(azimuth), radius * np.sin(azimuth),
                   np.full(num_frames, eye[2])], axis=-1)  # [F, 3]
  return np.stack([cameras.look_at_cam_to_world(e) for e in eyes])  # [F, 4, 4]


def overlay(*, rendering: np.ndarray, segmentation: np.ndarray) -> np.ndarray:
  """Slot colours (mixed by the soft weights) blended over the rendering: [..., 3]."""
  return ((1.0 - OVERLAY_ALPHA) * rendering
          + OVERLAY_ALPHA * vis.colour_segmentation(segmentation))


def _titled(panel: np.ndarray, titles: list[str], tile_width: int) -> np.ndarray:
  """Adds a white strip with a short title above each column (truncated to the tile width)."""
  strip = Image.new("RGB", (panel.shape[1], HEADER), (255, 255, 255))
  draw = ImageDraw.Draw(strip)
  chars = max(1, tile_width // 6)  # the default bitmap font is about 6 px per character
  for j, title in enumerate(titles):
    draw.text((j * (tile_width + PAD) + 1, 0), title[:chars], fill=(0, 0, 0))
  return np.concatenate([np.asarray(strip, np.float32) / 255.0, panel], axis=0)


def scene_panel(scene: Scene, renders: CameraRenders, *, near: float, far: float) -> np.ndarray:
  """The panel picture (module docstring) of all views of `scene`: [rows·H, cols·W, 3] + titles."""
  has_masks = scene.masks is not None
  k = renders.segmentation.shape[-1]
  rows = []
  for v in range(scene.num_views):
    row = [scene.images[scene.source_indices[0]], scene.images[v]]
    if has_masks:
      row.append(vis.colour_labels(scene.masks[v]))
    row += [renders.colour[v], vis.colour_depth(renders.depth[v], near=near, far=far),
            overlay(rendering=renders.colour[v], segmentation=renders.segmentation[v])]
    row += [renders.slot_colour[v, :, :, i] for i in range(k)]
    rows.append(row)
  titles = ["source", "truth"] + (["mask"] if has_masks else []) + ["render", "depth", "seg"]
  titles += [f"s{i}" for i in range(k)]
  return _titled(vis.grid(rows, pad=PAD), titles, scene.image_size[1])


def orbit_frames(renders: CameraRenders) -> list[np.ndarray]:
  """[rendering | segmentation colours] per frame, a progress bar below: [H + BAR, 2W + PAD, 3]."""
  n, height, width = renders.colour.shape[:3]
  frames = []
  for i in range(n):
    frame = np.ones((height + BAR, 2 * width + PAD, 3), np.float32)
    frame[:height, :width] = renders.colour[i]
    frame[:height, width + PAD:] = vis.colour_segmentation(renders.segmentation[i])
    # Distinct bar lengths also keep PIL from merging two identical consecutive frames.
    frame[height + 1:, :max(1, (i + 1) * frame.shape[1] // n)] = 0.0
    frames.append(frame)
  return frames


def save_gif(path: str, frames: Sequence[np.ndarray], *, frame_ms: int = ORBIT_FRAME_MS) -> None:
  """Writes float [H, W, 3] frames in [0, 1] as a looping GIF (temp file + rename)."""
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  images = [Image.fromarray((np.clip(f, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
            for f in frames]
  tmp = path + ".tmp.gif"
  images[0].save(tmp, save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
  os.replace(tmp, path)


# ---------------------------------------------------------------------------------------------
# The mode
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RenderedFiles:
  scene_index: int
  scene_name: str
  panel: str
  orbit: str


def parse_scene_indices(text: str) -> list[int]:
  """'0,3,5' → [0, 3, 5]."""
  try:
    indices = [int(t) for t in text.split(",") if t.strip()]
  except ValueError as e:
    raise evaluate.EvalSetupError(f"--scenes={text!r}: expected comma-separated scene indices, "
                                  f"e.g. 0,3,5") from e
  if not indices or min(indices) < 0:
    raise evaluate.EvalSetupError(f"--scenes={text!r}: give one or more indices ≥ 0")
  return indices


def render_scenes(config: ml_collections.ConfigDict, workdir: str, *, split: str = "test",
                  scene_indices: Sequence[int] = (0,), checkpoint: str = "",
                  num_orbit_frames: int = 24, progress: bool = True) -> list[RenderedFiles]:
  """`--mode=render`: writes the panel and orbit GIF of each chosen scene (module docstring)."""
  if not 1 <= num_orbit_frames <= MAX_ORBIT_FRAMES:
    raise evaluate.EvalSetupError(f"--orbit_frames={num_orbit_frames}: must be in "
                                  f"[1, {MAX_ORBIT_FRAMES}]")
  indices = list(scene_indices)
  run = evaluate.load_run(config, workdir, split=split, checkpoint=checkpoint,
                          max_scenes=max(indices) + 1)
  if max(indices) >= len(run.scenes):
    raise evaluate.EvalSetupError(f"--scenes: index {max(indices)} out of range; split {split!r} "
                                  f"has {len(run.scenes)} scenes")
  renderer = SlotRenderer(run.model, run.config)
  near, far = float(run.config.render.near), float(run.config.render.far)
  out_dir = os.path.join(workdir, "render", split)
  write = jax.process_index() == 0  # several processes render the same scenes; process 0 writes
  written = []
  for i in tqdm(indices, desc=f"render {split}", unit="scene", disable=not progress):
    scene = run.scenes[i]
    if not run.config.data.has_masks:
      scene = dataclasses.replace(scene, masks=None, mask_views=None)
    views = renderer.render(run.params, scene, cam_to_world=scene.cam_to_world,
                            intrinsics=scene.intrinsics)
    panel = os.path.join(out_dir, f"scene_{i:04d}_panel.png")
    if write:
      vis.save_png(panel, scene_panel(scene, views, near=near, far=far))
    source = scene.source_indices[0]
    poses = orbit_cam_to_world(source_cam_to_world=scene.cam_to_world[source],
                               num_frames=num_orbit_frames)
    intrinsics = np.broadcast_to(scene.intrinsics[source], (len(poses), 3, 3))
    orbit = renderer.render(run.params, scene, cam_to_world=poses, intrinsics=intrinsics)
    gif = os.path.join(out_dir, f"scene_{i:04d}_orbit.gif")
    if write:
      save_gif(gif, orbit_frames(orbit))
    written.append(RenderedFiles(scene_index=i, scene_name=scene.name, panel=panel, orbit=gif))
  return written
