"""Adaptive full-view rendering: the allocation decoder only where a scene needs it
(experiments/journal/2026-11.md, "Adaptive full-view rendering").

Vocabulary (docs/method.md §0): H×W image, S samples of the evaluation grid
(`geometry.stratified_depths` without jitter, the plain path's z), Wn window samples
(`render.adaptive_window`), s the proposal stride (`render.adaptive_stride`), ε the mass left out of
a significant range (`render.adaptive_mass_eps`), R rays of a chunk, K slots.

Why a window of the grid, not fewer or other samples: the allocation transformer's per-ray
self-attention and its Conv1d act along the samples of a ray, so a ray's result depends on its whole
sample set. The adaptive path keeps the plain path's z values and evaluates a contiguous window of
them, which is what the plain path would composite when the density outside the window is zero.

  pass 1  proposals: every s-th pixel in both image axes, and the last row and column (so every
          pixel lies inside a cell of proposals), rendered exactly as the plain path on the whole
          grid. Their outputs are used as they are, and per ray the smallest contiguous range of
          sample indices [lo, hi) that leaves out at most ε of its render weight
          (`significant_range`; weights are fractions of the pixel, so ε bounds the colour left
          out; a ray with Σw ≤ ε gets an empty range).
  window  every other pixel takes the union (hull) of the ranges of its cell's four corners and a
          window start i0 ∈ [0, S − Wn] covering it, centred when shorter (`choose_windows`).
          Empty hulls (all four corners transparent) take i0 = 0: the pixel is transparent anyway.
  pass 2  those pixels on the Wn samples z[i0 : i0+Wn] of the grid (`SlotLifter.render_at_depths`);
          the last sample keeps its grid δ (`volume.volume_render(last_delta=…)`), the
          transmittance in front of the window is 1 (the window starts where the neighbours found
          ≤ ε of weight).
  pass 3  fallback (`render.adaptive_fallback`, default on): a pixel whose hull is longer than Wn
          (an occlusion edge between two depths, a silhouette against empty space, or a soft
          ray) is rendered on the whole grid like a proposal, so it is exact. With the fallback
          off it is rendered on the window holding the front of its hull (what its nearest
          surface needs) and counted as overflow.

Every pass runs fixed-size chunks of rays through one compiled function: pass 1 and 2 chunks are
sized from the image size (fixed for a data set) so they carry almost no padding, pass 3 uses
chunks of H·W/FALLBACK_CHUNK_DIVISOR rays (its pixel count varies per view). Pass 2 chunks hold
up to chunk·S/Wn rays, the memory of a plain chunk.

The passes take the renderer as a function `render_fn(origins [B, R, 3], directions, z [B, R, S'],
last_delta [B, R] or None) -> (outputs tuple, weights [B, R, S'])`, so a test can composite an
analytic field through the same code. Only coarse-only models (the synthetic sets) are supported:
the fine pass of DTU/ScanNet places its samples from the whole ray's coarse weights.

Measured speed and quality: experiments/journal/2026-11.md ("Adaptive full-view rendering"),
experiments/bench_render.py.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional, Sequence

import flax.struct
import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from slotlifter_jax import config_checks
from slotlifter_jax import geometry
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import views as views_lib

# The fallback pass's pixel count changes from view to view, so its chunk is fixed per image size
# and small: 1/FALLBACK_CHUNK_DIVISOR of the pixels, so its padding wastes at most that share of
# a plain view's work.
FALLBACK_CHUNK_DIVISOR = 64
# Chunk sizes are rounded up to a multiple of this (vector-friendly shapes).
CHUNK_MULTIPLE = 8


# ---------------------------------------------------------------------------------------------
# Pure functions
# ---------------------------------------------------------------------------------------------


@flax.struct.dataclass
class SampleRange:
  lo: jax.Array  # [...] int32, first sample index
  hi: jax.Array  # [...] int32, one past the last; lo == hi: empty (Σw ≤ ε)


def significant_range(*, weights: jax.Array, eps) -> SampleRange:
  """The smallest contiguous [lo, hi) with Σ_{i ∉ [lo, hi)} w_i ≤ ε, the first one on ties.

  weights [..., S] ≥ 0 (render weights, Σ ≤ 1); eps ≥ 0 an absolute weight. With prefix sums P
  (P_0 = 0, P_j = Σ_{i<j} w_i) the range from i must reach the first j with P_j ≥ P_i + (P_S − ε);
  every start is tried at once ([..., S+1, S+1] comparisons; S ≤ 128 here).
  """
  s = weights.shape[-1]
  prefix = jnp.concatenate([jnp.zeros_like(weights[..., :1]), jnp.cumsum(weights, axis=-1)],
                           axis=-1)  # [..., S+1]
  need = prefix[..., -1:] - eps  # [..., 1] mass the range must hold
  target = prefix + need  # [..., S+1] per start i
  # end_i = #{j : P_j < P_i + need}: the first j reaching the target (P is non-decreasing);
  # end_i = S + 1 when even the whole rest of the ray falls short.
  end = jnp.sum(prefix[..., None, :] < target[..., :, None], axis=-1)  # [..., S+1]
  start = jnp.arange(s + 1)
  length = jnp.where(end <= s, end - start, s + 1)  # [..., S+1]
  lo = jnp.argmin(length, axis=-1)  # [...]
  best = jnp.take_along_axis(length, lo[..., None], axis=-1)[..., 0]
  empty = need[..., 0] <= 0.0  # the whole ray holds ≤ ε
  lo = jnp.where(empty, 0, lo).astype(jnp.int32)
  hi = jnp.where(empty, 0, lo + best).astype(jnp.int32)
  return SampleRange(lo=lo, hi=hi)


@flax.struct.dataclass
class Windows:
  start: jax.Array  # [...] int32, i0 ∈ [0, S − Wn]
  overflow: jax.Array  # [...] int32, samples of the hull beyond the window (0 when it fits)


def choose_windows(*, lo: jax.Array, hi: jax.Array, window: int, num_samples: int) -> Windows:
  """A window of `window` samples per pixel from the ranges of its n proposal rays.

  lo, hi [..., n] → Windows [...]. The window covers the hull [min lo, max hi) of the non-empty
  ranges, centred on it when the hull is shorter (any extra sample goes behind), starting at the
  hull when longer (the front surface first); clipped to the grid. A pixel whose ranges are all
  empty (lo == hi: transparent neighbours) gets start 0. When only some are empty the pixel sits
  on a silhouette against empty space, where the surface it sees may lie anywhere behind the
  non-empty ranges (a sphere's rim is deeper than its face), so the hull reaches the grid's end.
  """
  if not 1 <= window <= num_samples:
    raise ValueError(f"window={window}: must be in [1, num_samples={num_samples}]")
  nonempty = hi > lo  # [..., n]
  any_mass = jnp.any(nonempty, axis=-1)  # [...]
  hull_lo = jnp.min(jnp.where(nonempty, lo, num_samples), axis=-1)  # [...]
  hull_hi = jnp.max(jnp.where(nonempty, hi, 0), axis=-1)
  hull_hi = jnp.where(jnp.all(nonempty, axis=-1), hull_hi, num_samples)  # mixed: to the end
  length = hull_hi - hull_lo
  start = jnp.where(length <= window, hull_lo - (window - length) // 2, hull_lo)
  start = jnp.clip(start, 0, num_samples - window)
  start = jnp.where(any_mass, start, 0).astype(jnp.int32)
  overflow = jnp.where(any_mass, jnp.maximum(length - window, 0), 0).astype(jnp.int32)
  return Windows(start=start, overflow=overflow)


@flax.struct.dataclass
class WindowDepths:
  z: jax.Array  # [..., Wn] the grid's z[i0 : i0+Wn]
  last_delta: jax.Array  # [...] z[i0+Wn] − z[i0+Wn−1], or 0 when the window ends the grid


def window_depths(*, z_grid: jax.Array, start: jax.Array, window: int) -> WindowDepths:
  """z_grid [..., S] sorted, start [...] int → the window's depths and its last sample's δ."""
  s = z_grid.shape[-1]
  index = start[..., None] + jnp.arange(window)  # [..., Wn]
  z = jnp.take_along_axis(z_grid, index, axis=-1)  # [..., Wn]
  end = start + window  # [...] grid index after the window
  after = jnp.take_along_axis(z_grid, jnp.minimum(end, s - 1)[..., None], axis=-1)[..., 0]
  last_delta = jnp.where(end < s, after - z[..., -1], jnp.zeros_like(after))
  return WindowDepths(z=z, last_delta=last_delta)


@dataclasses.dataclass(frozen=True)
class SampleGrid:
  """The plain path's evaluation grid: S depths linear in [near, far), the same for every ray."""
  near: float
  far: float
  num_samples: int

  def depths(self, batch_shape: Sequence[int]) -> jax.Array:  # → [*batch_shape, S]
    return geometry.stratified_depths(near=self.near, far=self.far,
                                      num_samples=self.num_samples, batch_shape=batch_shape)


# render_fn(origins [B, R, 3], directions [B, R, 3], z [B, R, S'], last_delta [B, R] | None)
#   -> (outputs: tuple of [B, R, ...] arrays, weights [B, R, S'])
RenderFn = Callable[..., tuple]


def proposal_pass(render_fn: RenderFn, *, origins: jax.Array, directions: jax.Array,
                  grid: SampleGrid, mass_eps) -> tuple:
  """Rays [B, R, 3] on the whole grid (exactly the plain path) → outputs + (lo [B, R], hi)."""
  outputs, weights = render_fn(origins, directions, grid.depths(origins.shape[:-1]), None)
  sig = significant_range(weights=weights, eps=mass_eps)
  return tuple(outputs) + (sig.lo, sig.hi)


def window_pass(render_fn: RenderFn, *, origins: jax.Array, directions: jax.Array,
                start: jax.Array, grid: SampleGrid, window: int) -> tuple:
  """Rays [B, R, 3] on the window of `window` grid samples from start [B, R] → outputs."""
  win = window_depths(z_grid=grid.depths(origins.shape[:-1]), start=start, window=window)
  outputs, _ = render_fn(origins, directions, win.z, win.last_delta)
  return tuple(outputs)


# ---------------------------------------------------------------------------------------------
# The proposal raster and fixed-size chunks (NumPy, host side)
# ---------------------------------------------------------------------------------------------


def proposal_lines(size: int, stride: int) -> np.ndarray:
  """Proposal rows (or columns) of an image axis: every stride-th index and the last one."""
  if stride < 1:
    raise ValueError(f"stride={stride}: must be ≥ 1")
  return np.unique(np.append(np.arange(0, size, stride), size - 1))


@dataclasses.dataclass(frozen=True)
class ProposalRaster:
  """Which pixels are proposals and which proposals enclose each pixel (row-major, flat)."""
  proposals: np.ndarray  # [n1] flat pixel indices of the proposals, row-major over (rows, cols)
  others: np.ndarray  # [n2] flat pixel indices of the other pixels
  corners: np.ndarray  # [n2, 4] indices into `proposals` of each other pixel's enclosing cell


def proposal_raster(*, height: int, width: int, stride: int) -> ProposalRaster:
  rows, cols = proposal_lines(height, stride), proposal_lines(width, stride)
  is_proposal = np.zeros((height, width), bool)
  is_proposal[np.ix_(rows, cols)] = True
  others = np.flatnonzero(~is_proposal)
  y, x = np.divmod(others, width)
  # The proposal lines at or before and at or after each pixel (the same line when it is one).
  r0, r1 = np.searchsorted(rows, y, side="right") - 1, np.searchsorted(rows, y, side="left")
  c0, c1 = np.searchsorted(cols, x, side="right") - 1, np.searchsorted(cols, x, side="left")
  n = len(cols)
  corners = np.stack([r0 * n + c0, r0 * n + c1, r1 * n + c0, r1 * n + c1], axis=-1)  # [n2, 4]
  proposals = (rows[:, None] * width + cols[None, :]).reshape(-1)
  return ProposalRaster(proposals=proposals, others=others, corners=corners)


def balanced_chunk(n: int, max_chunk: int) -> int:
  """Rays per chunk so that ceil(n / max_chunk) chunks hold n rays with < CHUNK_MULTIPLE·chunks
  padding (a plain fixed chunk would pad the last one by up to max_chunk − 1)."""
  num = max(1, -(-n // max_chunk))
  per = -(-n // num)
  return max(CHUNK_MULTIPLE, -(-per // CHUNK_MULTIPLE) * CHUNK_MULTIPLE)


def run_chunks(fn, inputs: Sequence[np.ndarray], chunk: int) -> list[np.ndarray]:
  """fn(*[x[None, chunk rows] for x in inputs]) -> tuple of [1, chunk, ...], over all n rows.

  The last chunk repeats its last row, so one compiled shape serves any n; returns [n, ...] each.
  """
  n = inputs[0].shape[0]
  pad = (-n) % chunk
  padded = [np.concatenate([x, np.repeat(x[-1:], pad, axis=0)]) if pad else x for x in inputs]
  parts = [fn(*[x[None, s:s + chunk] for x in padded]) for s in range(0, n + pad, chunk)]
  return [np.concatenate([np.asarray(p[i][0]) for p in parts])[:n] for i in range(len(parts[0]))]


# ---------------------------------------------------------------------------------------------
# One view
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class AdaptiveSettings:
  stride: int  # s: proposals every s-th pixel in both axes
  window: int  # Wn samples of the grid per non-proposal pixel
  mass_eps: float  # ε weight a significant range may leave out
  fallback: bool  # overflowing pixels on the whole grid (exact) instead of the front window
  num_samples: int  # S of the grid
  chunk: int  # rays per plain chunk (pass 2 chunks hold up to chunk·S/Wn rays)

  @classmethod
  def from_config(cls, config: ml_collections.ConfigDict) -> "AdaptiveSettings":
    r = config.render
    if tuple(r.get("z_bounds", ())):
      raise ValueError("render.adaptive: render.z_bounds gives every ray its own sample interval, "
                       "the adaptive renderer shares one grid; set render.adaptive=False")
    if config_checks.check_supersample(r) > 1:
      raise ValueError(f"render.adaptive: render.supersample={r.supersample} is not supported by "
                       "the adaptive renderer (one ray per pixel); set one of them back")
    settings = cls(stride=int(r.adaptive_stride), window=int(r.adaptive_window),
                   mass_eps=float(r.adaptive_mass_eps), fallback=bool(r.adaptive_fallback),
                   num_samples=int(r.num_samples), chunk=int(r.chunk))
    settings.check()
    return settings

  def check(self) -> None:
    if self.stride < 1:
      raise ValueError(f"render.adaptive_stride={self.stride}: must be ≥ 1")
    if not 1 <= self.window <= self.num_samples:
      raise ValueError(f"render.adaptive_window={self.window}: must be in [1, "
                       f"render.num_samples={self.num_samples}]")
    if not self.mass_eps >= 0.0:
      raise ValueError(f"render.adaptive_mass_eps={self.mass_eps}: must be ≥ 0")


@dataclasses.dataclass(frozen=True)
class ViewDiagnostics:
  """What the adaptive path did on one view."""
  proposal: np.ndarray  # [H, W] bool, pass 1 (exact)
  fallback: np.ndarray  # [H, W] bool, pass 3 (exact)
  overflow: np.ndarray  # [H, W] int, hull samples beyond the window (0 on proposals)
  window_start: np.ndarray  # [H, W] int, i0 of the pass 2 pixels, −1 elsewhere
  work_fraction: float  # Σ rays·samples decoded / (H·W·S), padding included

  @property
  def overflow_fraction(self) -> float:  # pixels whose hull did not fit the window
    return float(np.mean(self.overflow > 0))


def render_view(*, proposal_fn, window_fn, origins: np.ndarray, directions: np.ndarray,
                height: int, width: int,
                settings: AdaptiveSettings) -> tuple[list[np.ndarray], ViewDiagnostics]:
  """One view through the passes of the module docstring.

  proposal_fn(origins [1, R, 3], directions) -> outputs + (lo, hi), all [1, R, ...];
  window_fn(origins, directions, start [1, R]) -> outputs; origins, directions [H·W, 3].
  Returns the outputs as [H·W, ...] arrays and the view's diagnostics.
  """
  st, s, wn = settings, settings.num_samples, settings.window
  raster = proposal_raster(height=height, width=width, stride=st.stride)
  n_pix = height * width
  chunk1 = balanced_chunk(len(raster.proposals), st.chunk)
  *first, lo, hi = run_chunks(proposal_fn, [origins[raster.proposals],
                                            directions[raster.proposals]], chunk1)
  outputs = [np.zeros((n_pix,) + x.shape[1:], x.dtype) for x in first]
  for out, x in zip(outputs, first):
    out[raster.proposals] = x
  work = chunk1 * -(-len(raster.proposals) // chunk1) * s
  overflow = np.zeros(n_pix, np.int32)
  start = np.full(n_pix, -1, np.int32)
  fallback = np.zeros(n_pix, bool)
  if raster.others.size:
    win = _choose_windows_jit(lo=lo[raster.corners], hi=hi[raster.corners], window=wn,
                              num_samples=s)
    win_start, win_over = np.asarray(win.start), np.asarray(win.overflow)
    overflow[raster.others] = win_over
    redo = st.fallback & (win_over > 0)
    second, third = raster.others[~redo], raster.others[redo]
    if second.size:
      chunk2 = balanced_chunk(raster.others.size, max(1, st.chunk * s // wn))
      results = run_chunks(window_fn, [origins[second], directions[second],
                                       win_start[~redo]], chunk2)
      for out, x in zip(outputs, results):
        out[second] = x
      start[second] = win_start[~redo]
      work += chunk2 * -(-second.size // chunk2) * wn
    if third.size:
      chunk3 = balanced_chunk(-(-n_pix // FALLBACK_CHUNK_DIVISOR), st.chunk)
      *results, _, _ = run_chunks(proposal_fn, [origins[third], directions[third]], chunk3)
      for out, x in zip(outputs, results):
        out[third] = x
      fallback[third] = True
      work += chunk3 * -(-third.size // chunk3) * s
  proposal = np.zeros(n_pix, bool)
  proposal[raster.proposals] = True
  shape = (height, width)
  diag = ViewDiagnostics(proposal=proposal.reshape(shape), fallback=fallback.reshape(shape),
                         overflow=overflow.reshape(shape), window_start=start.reshape(shape),
                         work_fraction=work / (n_pix * s))
  return outputs, diag


_choose_windows_jit = jax.jit(choose_windows, static_argnames=("window", "num_samples"))


def camera_rays(*, cam_to_world: np.ndarray, intrinsics: np.ndarray, height: int,
                width: int) -> tuple[np.ndarray, np.ndarray]:
  """Origins and unit directions [H·W, 3] of every pixel, row-major (as render_cameras)."""
  pix = geometry.image_pixels(height, width).reshape(-1, 2)  # [H·W, 2]
  rays = geometry.pixel_rays(cam_to_world=jnp.asarray(cam_to_world, jnp.float32),
                             intrinsics=jnp.asarray(intrinsics, jnp.float32), pix=pix)
  return np.asarray(rays.origins), np.asarray(rays.directions)


# ---------------------------------------------------------------------------------------------
# The renderer beside views.SceneRenderer
# ---------------------------------------------------------------------------------------------


def model_render_fn(model, params, encoded, sources: dict, locality) -> RenderFn:
  """`render_fn` of a SlotLifter at evaluation: outputs (colour in [0, 1], depth, segmentation)."""
  signed = model.colour_range == "signed"
  def fn(origins, directions, z, last_delta):
    out = model.apply({"params": params}, encoded, **sources, ray_origins=origins,
                      ray_directions=directions, z=z, last_delta=last_delta, locality=locality,
                      method=model.render_at_depths).coarse
    colour = (out.colour + 1.0) * 0.5 if signed else out.colour
    return (colour, out.depth, out.segmentation), out.weights
  return fn


class AdaptiveSceneRenderer:
  """`views.SceneRenderer` with adaptive rendering (module docstring): the same `render`
  signature and RenderedViews; `render_with_diagnostics` also returns what each view cost."""

  def __init__(self, model, config: ml_collections.ConfigDict):
    if int(config.render.num_fine_samples) > 0:
      raise ValueError("render.adaptive: the model has a fine pass (DTU/ScanNet); adaptive "
                       "rendering covers coarse-only models only, set render.adaptive=False")
    self.model = model
    self.settings = AdaptiveSettings.from_config(config)
    self.signed = config.model.colour_range == "signed"
    grid = SampleGrid(near=float(config.render.near), far=float(config.render.far),
                      num_samples=int(config.render.num_samples))
    st = self.settings

    @jax.jit
    def proposal_chunk(params, encoded, sources, origins, directions, locality):
      fn = model_render_fn(model, params, encoded, sources, locality)
      return proposal_pass(fn, origins=origins, directions=directions, grid=grid,
                           mass_eps=st.mass_eps)

    @jax.jit
    def window_chunk(params, encoded, sources, origins, directions, start, locality):
      fn = model_render_fn(model, params, encoded, sources, locality)
      return window_pass(fn, origins=origins, directions=directions, start=start, grid=grid,
                         window=st.window)

    self._encode = views_lib.make_encode(model)
    self._proposal_chunk, self._window_chunk = proposal_chunk, window_chunk

  def sources(self, scene: Scene, source_indices=None) -> dict:
    return views_lib.scene_sources(scene, signed=self.signed, source_indices=source_indices)

  def render_with_diagnostics(self, params, scene: Scene, view_indices, *, source_indices=None,
                              locality: bool = False,
                              cam_to_world: Optional[np.ndarray] = None,
                              intrinsics: Optional[np.ndarray] = None
                              ) -> tuple[views_lib.RenderedViews, list[ViewDiagnostics]]:
    """Views `view_indices` of `scene` (or the cameras cam_to_world [n, 4, 4], intrinsics
    [n, 3, 3] when given) → RenderedViews and one ViewDiagnostics per view."""
    sources = self.sources(scene, source_indices)
    encoded = self._encode(params, sources)
    loc = jnp.asarray(locality)
    height, width = scene.image_size
    views = list(view_indices)
    cams = scene.cam_to_world[views] if cam_to_world is None else cam_to_world
    intr = scene.intrinsics[views] if intrinsics is None else intrinsics
    proposal_fn = lambda o, d: self._proposal_chunk(params, encoded, sources, o, d, loc)
    window_fn = lambda o, d, i0: self._window_chunk(params, encoded, sources, o, d, i0, loc)
    colours, depths, segs, diags = [], [], [], []
    for c2w, k in zip(cams, intr):
      origins, directions = camera_rays(cam_to_world=c2w, intrinsics=k, height=height,
                                        width=width)
      (colour, depth, seg), diag = render_view(
          proposal_fn=proposal_fn, window_fn=window_fn, origins=origins, directions=directions,
          height=height, width=width, settings=self.settings)
      colours.append(colour.reshape(height, width, -1))
      depths.append(depth.reshape(height, width))
      segs.append(seg.reshape(height, width, -1))
      diags.append(diag)
    rendered = views_lib.RenderedViews(
        colour=np.stack(colours), depth=np.stack(depths), segmentation=np.stack(segs),
        slots=np.asarray(encoded.slots[0]), slot_attn=np.asarray(encoded.slot_attn[0]),
        source_labels=views_lib.source_attention_labels(encoded, (height, width)))
    return rendered, diags

  def render(self, params, scene: Scene, view_indices, *, source_indices=None,
             locality: bool = False) -> views_lib.RenderedViews:
    """As `views.SceneRenderer.render`."""
    return self.render_with_diagnostics(params, scene, view_indices,
                                        source_indices=source_indices, locality=locality)[0]


def make_scene_renderer(model, config):
  """The renderer the eval mode uses: `AdaptiveSceneRenderer` when `render.adaptive` is on
  (same `render` signature and result), else `views.SceneRenderer` (every pixel on
  the whole sample grid). Validation during training keeps SceneRenderer, so model selection is
  exact. The switch lives here, not in views.py, because this module builds on views.py:
  the import then runs one way."""
  if config.render.get("adaptive", False):
    return AdaptiveSceneRenderer(model, config)
  return views_lib.SceneRenderer(model, config)
