"""`--mode=render`: pictures of chosen scenes of a trained run — a panel per scene and an orbit GIF.

Vocabulary (docs/method.md §0): B scenes, R rays, S samples per ray, K slots (K+1 with the empty
slot at index 0), V source views, H×W image size, F orbit frames.

DIR/render/<split>/scene_XXXX_panel.png (XXXX = the scene's index in the split) has one row per
view, columns
  label | source | truth | [ground-truth mask] | rendering | depth | depth scale |
  segmentation overlay | s0 … s(K−1)
under a strip of column titles and above a footer "checkpoint <best|latest> · step <N>" naming
the restored checkpoint. The label column names each row's view: "source" for the source view
(with V > 1 source views "source 1" … "source V", in the order of `Scene.source_indices`) and
"novel 1", "novel 2", … for the other views in view order. The depth tiles map `render.near`
(white) to `render.far` (black) with `vis.colour_depth`; the depth-scale column beside them is a
vertical bar of the same colouring over all rows, with the near value at its top and the far value
at its bottom. "s0" … "s(K−1)" are the K real slots, the empty slot excluded; s0 is the background
slot when the locality constraint was on. The overlay blends the slot colours (vis.PALETTE mixed by
the soft weights) over the rendering; "sk" is what slot k renders alone: the volume rendering with
only slot k's share σ_k of the density (the model's `RenderOutput.slot_density`:
exp(s_σ)·W_k·ReLU(A_k), docs/method.md §1.4, or with `model.density_mode = "mlp"` the head's σ
split by the weights W_k; Σ_k σ_k = σ) and each sample's colour unchanged. No background colour
is added (docs/method.md §1.5), so what a slot does not hold is black.

DIR/render/<split>/scene_XXXX_orbit.gif shows rendering | segmentation side by side, titled
"rendering" and "segmentation" above the tiles, from F cameras circling the world z axis at the
source camera's height and horizontal radius, looking at the origin (OpenCV cam2world, z up),
starting at the source camera. Each tile is enlarged by a whole factor to at least ORBIT_TILE
pixels on its shorter side by nearest-neighbour repetition: every rendered pixel becomes a square
block of one colour, nothing is interpolated, so the GIF shows the rendering's real resolution. A
thin bar under the frames grows with the azimuth.

Text is drawn with PIL's default font (what `ImageDraw.text` uses without a font).

With `render.adaptive` on, panels and orbits are rendered adaptively
(slotlifter_jax.rendering.adaptive); the per-slot renderings of a windowed pixel then
composite that pixel's window.
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

from slotlifter_jax import config_checks
from slotlifter_jax import evaluate
from slotlifter_jax import model as model_lib
from slotlifter_jax import multihost
from slotlifter_jax import vis
from slotlifter_jax.data import cameras
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import adaptive
from slotlifter_jax.rendering import views as views_lib
from slotlifter_jax.rendering import volume

MAX_ORBIT_FRAMES = 64  # 64 frames of 256-px tiles: about 2 MB measured on a noisy smoke render
ORBIT_FRAME_MS = 80
OVERLAY_ALPHA = 0.5  # weight of the segmentation colours over the rendering
MIN_ORBIT_RADIUS = 1e-6  # a camera on the z axis has no azimuth to orbit
PAD = 2  # pixels between panel tiles
HEADER = 12  # pixels of the column-title strip (PIL's default font draws 10-11 px high)
LABEL_WIDTH = 48  # pixels of the panel's row-label column ("source", "novel 1", …)
FOOTER = 14  # pixels of the strip under the panel with the checkpoint and step
DEPTH_BAR = 6  # pixels wide: the depth colour bar, framed in grey
SCALE_WIDTH = 40  # pixels of the depth-scale column: the bar, a gap, the near and far values
BAR = 3  # pixels of the orbit progress bar
ORBIT_TILE = 256  # an orbit tile's shorter side is enlarged (nearest neighbour) to at least this
ORBIT_HEADER = 14  # pixels of the orbit's title strip
ORBIT_PAD = 4  # pixels between the orbit's two tiles
TEXT_HEIGHT = 12  # pixels a line of the default font needs (its ink lies in rows 2 to 11)
FRAME_GREY = 0.5  # the depth bar's frame, so its white (near) end stands out from the background


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
                     last_delta: Optional[jax.Array] = None) -> volume.RenderResult:
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
  return volume.volume_render(density=sigma, z=z, colour=colour, slot_weights=None, far=far,
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
  adaptively (slotlifter_jax.rendering.adaptive) when `render.adaptive` is on."""

  def __init__(self, model: model_lib.SlotLifter, config: ml_collections.ConfigDict):
    self.signed = config.model.colour_range == "signed"
    self.chunk = int(config.render.chunk)
    self.supersample = config_checks.check_supersample(config.render)
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

    self._encode, self._render_chunk = views_lib.make_encode(model), render_chunk

  def sources(self, scene: Scene) -> dict:
    return views_lib.scene_sources(scene, signed=self.signed)

  def render(self, params, scene: Scene, *, cam_to_world: np.ndarray,
             intrinsics: np.ndarray) -> CameraRenders:
    """cam_to_world [n, 4, 4], intrinsics [n, 3, 3] at the scene's image size."""
    sources = self.sources(scene)
    encoded = self._encode(params, sources)
    height, width = scene.image_size
    if self.adaptive is not None:
      return self._render_adaptive(params, encoded, sources, cam_to_world=cam_to_world,
                                   intrinsics=intrinsics, height=height, width=width)
    colour, depth, seg, slots = views_lib.render_cameras(
        lambda o, d: self._render_chunk(params, encoded, sources, o, d),
        cam_to_world=cam_to_world, intrinsics=intrinsics, height=height, width=width,
        chunk=self.chunk, supersample=self.supersample)
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


def _text(width: int, height: int, items: Sequence[tuple[int, int, str]]) -> np.ndarray:
  """A white [height, width, 3] float picture with black text: each item (x, y, text) drawn with
  its top-left corner at (x, y); what runs past the edges is cut off."""
  image = Image.new("RGB", (width, height), (255, 255, 255))
  draw = ImageDraw.Draw(image)
  for x, y, text in items:
    draw.text((x, y), text, fill=(0, 0, 0))
  return np.asarray(image, np.float32) / 255.0


def view_labels(scene: Scene) -> list[str]:
  """The panel's row labels (module docstring): 'source' (or 'source 1' … 'source V' with V > 1
  source views) for the source views, 'novel 1', 'novel 2', … for the others, in view order."""
  sources = list(scene.source_indices)
  labels, novel = [], 0
  for v in range(scene.num_views):
    if v in sources:
      labels.append("source" if len(sources) == 1 else f"source {sources.index(v) + 1}")
    else:
      novel += 1
      labels.append(f"novel {novel}")
  return labels


def depth_scale(height: int, *, near: float, far: float) -> np.ndarray:
  """The depth-scale column [height, SCALE_WIDTH, 3]: a vertical bar coloured by
  `vis.colour_depth` from near (top row inside the frame) to far (bottom row), in a one-pixel grey
  frame, with the near value beside its top and the far value beside its bottom."""
  values = [(DEPTH_BAR + 2, 0, f"{near:.3g}"),
            (DEPTH_BAR + 2, max(0, height - TEXT_HEIGHT), f"{far:.3g}")]
  column = _text(SCALE_WIDTH, height, values)
  column[:, :DEPTH_BAR] = FRAME_GREY
  inside = max(height - 2, 1)
  depth = np.linspace(near, far, inside, dtype=np.float64)  # [inside], top to bottom
  column[1:1 + inside, 1:DEPTH_BAR - 1] = vis.colour_depth(depth, near=near, far=far)[:, None]
  return column


def checkpoint_name(checkpoint_dir: str) -> str:
  """'best' or 'latest' of a DIR/checkpoints/{best,latest}/<step> folder."""
  return os.path.basename(os.path.dirname(os.path.normpath(checkpoint_dir)))


def scene_panel(scene: Scene, renders: CameraRenders, *, near: float, far: float,
                checkpoint: str, step: int, parameters: str = "trained") -> np.ndarray:
  """The panel picture (module docstring) of all views of `scene`:
  [HEADER + n·(H + PAD) − PAD + FOOTER, LABEL_WIDTH + PAD + cols·(W + PAD) + SCALE_WIDTH, 3].

  checkpoint, step: the restored checkpoint ('best' | 'latest') and its training step, for the
  footer, which also says when the parameters are the run's average (`parameters="average"`).
  """
  has_masks = scene.masks is not None
  k = renders.segmentation.shape[-1]
  height, width = scene.image_size
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
  depth_column = titles.index("depth")
  # Left edge of each tile column; the depth-scale column sits right of the depth tiles.
  xs = [LABEL_WIDTH + PAD + j * (width + PAD) + (SCALE_WIDTH + PAD if j > depth_column else 0)
        for j in range(len(titles))]
  body = len(rows) * (height + PAD) - PAD
  panel = np.ones((HEADER + body + FOOTER, xs[-1] + width, 3), np.float32)

  chars = max(1, width // 6)  # the default font is about 6 px per character
  panel[:HEADER] = _text(panel.shape[1], HEADER,
                         [(x + 1, 0, title[:chars]) for x, title in zip(xs, titles)])
  label_y = max(0, (height - TEXT_HEIGHT) // 2)
  panel[HEADER:HEADER + body, :LABEL_WIDTH] = _text(
      LABEL_WIDTH, body, [(1, i * (height + PAD) + label_y, label)
                          for i, label in enumerate(view_labels(scene))])
  for i, row in enumerate(rows):
    top = HEADER + i * (height + PAD)
    for x, tile in zip(xs, row):
      panel[top:top + height, x:x + width] = tile[..., :3]
  scale_x = xs[depth_column] + width + PAD
  panel[HEADER:HEADER + body, scale_x:scale_x + SCALE_WIDTH] = depth_scale(body, near=near,
                                                                           far=far)
  panel[HEADER + body:] = _text(panel.shape[1], FOOTER,
                                [(1, 1, f"checkpoint {checkpoint} · step {int(step)}"
                                         + (" · average" if parameters == "average" else ""))])
  return panel


def orbit_scale(height: int, width: int) -> int:
  """The whole factor an orbit tile is enlarged by: its shorter side reaches ORBIT_TILE."""
  return max(1, math.ceil(ORBIT_TILE / min(height, width)))


def _enlarge(image: np.ndarray, factor: int) -> np.ndarray:
  """Nearest-neighbour enlargement [H, W, C] → [f·H, f·W, C]: each pixel a block of one colour."""
  return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)


def orbit_frames(renders: CameraRenders) -> list[np.ndarray]:
  """[rendering | segmentation colours] per frame, enlarged by f = orbit_scale(H, W), titles above
  and a progress bar below: [ORBIT_HEADER + f·H + BAR, 2·f·W + ORBIT_PAD, 3]."""
  n, height, width = renders.colour.shape[:3]
  f = orbit_scale(height, width)
  tile_h, tile_w = f * height, f * width
  frame_w = 2 * tile_w + ORBIT_PAD
  titles = _text(frame_w, ORBIT_HEADER, [(1, 1, "rendering"),
                                         (tile_w + ORBIT_PAD + 1, 1, "segmentation")])
  frames = []
  for i in range(n):
    frame = np.ones((ORBIT_HEADER + tile_h + BAR, frame_w, 3), np.float32)
    frame[:ORBIT_HEADER] = titles
    tiles = frame[ORBIT_HEADER:ORBIT_HEADER + tile_h]
    tiles[:, :tile_w] = _enlarge(renders.colour[i], f)
    tiles[:, tile_w + ORBIT_PAD:] = _enlarge(vis.colour_segmentation(renders.segmentation[i]), f)
    # Distinct bar lengths also keep PIL from merging two identical consecutive frames.
    frame[ORBIT_HEADER + tile_h + 1:, :max(1, (i + 1) * frame_w // n)] = 0.0
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
                  num_orbit_frames: int = 24, progress: bool = True,
                  params: str = "average") -> list[RenderedFiles]:
  """`--mode=render`: writes the panel and orbit GIF of each chosen scene (module docstring)."""
  if not 1 <= num_orbit_frames <= MAX_ORBIT_FRAMES:
    raise evaluate.EvalSetupError(f"--orbit_frames={num_orbit_frames}: must be in "
                                  f"[1, {MAX_ORBIT_FRAMES}]")
  indices = list(scene_indices)
  run = evaluate.load_run(config, workdir, split=split, checkpoint=checkpoint,
                          max_scenes=max(indices) + 1, params=params)
  if max(indices) >= len(run.scenes):
    raise evaluate.EvalSetupError(f"--scenes: index {max(indices)} out of range; split {split!r} "
                                  f"has {len(run.scenes)} scenes")
  renderer = SlotRenderer(run.model, run.config)
  near, far = float(run.config.render.near), float(run.config.render.far)
  out_dir = os.path.join(workdir, "render", split)
  write = multihost.is_primary()  # several processes render the same scenes; process 0 writes
  written = []
  for i in tqdm(indices, desc=f"render {split}", unit="scene", disable=not progress):
    scene = run.scenes[i]
    if not run.config.data.has_masks:
      scene = dataclasses.replace(scene, masks=None, mask_views=None)
    views = renderer.render(run.params, scene, cam_to_world=scene.cam_to_world,
                            intrinsics=scene.intrinsics)
    panel = os.path.join(out_dir, f"scene_{i:04d}_panel.png")
    if write:
      vis.save_png(panel, scene_panel(scene, views, near=near, far=far,
                                      checkpoint=checkpoint_name(run.checkpoint_dir),
                                      step=run.step, parameters=run.parameters))
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
