"""Shading and the full render of the embedded generator's ray caster (docs/method.md §3.5):
procedural textures, lights with shadows, one mirror bounce, camera rays and the staged render of
all views of a scene.

Vocabulary (docs/method.md §0, plus the generator's own letters): N views per scene, H×W image
size, A anti-aliasing samples per pixel (a √A×√A grid), R rays (N·H·W·A for a colour pass, N·H·W
for the centre pass), P primitives, G = P + 5 surfaces, L = 3 lights.

The ray caster is written in jax.numpy and compiled once per (N, H, W, P): it traces all rays of
all views of a scene at once, with shadow rays to each light, one mirror bounce for metal and
procedural textures for the room family. Colour comes from A supersamples per pixel; the instance
mask and the depth come from one extra ray through each pixel centre, so they are exact (not
derived from colour).

It sits above `raycaster.py` (intersection, which it calls for primary, shadow and bounce rays) and
below `writer.py`, so the look of the images can change without touching the geometry or the files.
"""

from __future__ import annotations

import functools
import math
from typing import Optional

import flax
import jax
import jax.numpy as jnp

from slotlifter_jax import geometry
from slotlifter_jax.data.layout import BACKGROUND_LABEL
from slotlifter_jax.data.raycaster import (GAMMA, TEX_CHECKER, TEX_NOISE, TEX_STRIPES, TEX_TILES,
                                           TEX_WOOD, Hit, RenderOptions, SceneArrays, Vec, _blocked,
                                           _dot, _gather_columns, _surface_normals_xyz, _trace_xyz,
                                           _unit, _unstack, trace)

# ---- shading numerics ----
SURFACE_OFFSET = 1e-3  # shadow / reflection rays start this far off the surface, along the normal
SKY_LINEAR = (0.55, 0.57, 0.62)  # seen only in metal reflections pointing up


# =============================================================================================
# Procedural textures
# =============================================================================================


def _hash01(ix: jax.Array, iy: jax.Array, iz: jax.Array) -> jax.Array:
  """Integer lattice → [0, 1): a murmur-style mix, deterministic on every platform."""
  u = lambda v: v.astype(jnp.int32).astype(jnp.uint32)
  h = (u(ix) * jnp.uint32(0x8DA6B343)) ^ (u(iy) * jnp.uint32(0xD8163841)) ^ (
      u(iz) * jnp.uint32(0xCB1AB31F))
  h = (h ^ (h >> 16)) * jnp.uint32(0x7FEB352D)
  h = (h ^ (h >> 15)) * jnp.uint32(0x846CA68B)
  h = h ^ (h >> 16)
  return (h >> 8).astype(jnp.float32) / float(1 << 24)


def value_noise(x: jax.Array, y: jax.Array, z: jax.Array) -> jax.Array:
  """Smooth 3-D value noise in [0, 1] at [...] coordinates."""
  bx, by, bz = jnp.floor(x), jnp.floor(y), jnp.floor(z)
  smooth = lambda f: f * f * (3.0 - 2.0 * f)
  fx, fy, fz = smooth(x - bx), smooth(y - by), smooth(z - bz)
  out = 0.0
  for cx in (0, 1):
    for cy in (0, 1):
      for cz in (0, 1):
        w = (fx if cx else 1 - fx) * (fy if cy else 1 - fy) * (fz if cz else 1 - fz)
        out = out + w * _hash01(bx + cx, by + cy, bz + cz)
  return out


def _texture_mix(q: Vec, kind, scale, direction: Vec):
  """Blend weight towards the second colour and a brightness tint, both [R]."""
  sq = (q[0] * scale, q[1] * scale, q[2] * scale)
  stripes = 0.5 + 0.5 * jnp.tanh(4.0 * jnp.sin(2 * math.pi * _dot(sq, direction)))
  checker = jnp.mod(jnp.floor(sq[0]) + jnp.floor(sq[1]) + jnp.floor(sq[2]), 2.0)
  noise = value_noise(*sq)
  # Wood planks along `direction` (in xy), plank width 1/scale, with seams and per-plank tint.
  along = q[0] * direction[0] + q[1] * direction[1]
  across = (q[1] * direction[0] - q[0] * direction[1]) * scale
  plank = jnp.floor(across)
  plank_offset = 7.0 * _hash01(plank, plank * 0 + 3, plank * 0 + 5)
  board_pos = (along + plank_offset) / 3.0
  board = jnp.floor(board_pos)
  grain = 0.5 + 0.5 * jnp.sin(9.0 * along + 5.0 * value_noise(along * 0.7, across * 3.0, board))
  seam = ((across - plank) < 0.05) | ((board_pos - board) < 0.01)
  wood_tint = (0.8 + 0.35 * _hash01(plank, board, plank * 0 + 11)) * jnp.where(seam, 0.35, 1.0)
  # Tiles: a checker of the two colours with darker grout lines.
  tu, tv = q[0] * scale, q[1] * scale
  fu, fv = tu - jnp.floor(tu), tv - jnp.floor(tv)
  tiles = jnp.mod(jnp.floor(tu) + jnp.floor(tv), 2.0)
  grout = (fu < 0.04) | (fu > 0.96) | (fv < 0.04) | (fv > 0.96)
  mix = jnp.select([kind == TEX_STRIPES, kind == TEX_CHECKER, kind == TEX_NOISE,
                    kind == TEX_WOOD, kind == TEX_TILES],
                   [stripes, checker, noise, 0.6 * grain, tiles], 0.0)
  tint = jnp.select([kind == TEX_WOOD, kind == TEX_TILES],
                    [wood_tint, jnp.where(grout, 0.45, 1.0)], 1.0)
  return mix, tint


def _material_table(scene: SceneArrays) -> jax.Array:
  """[G, 25] packed per-surface parameters, one gather per shading pass (see _material_columns)."""
  return jnp.concatenate([
      scene.albedo, scene.albedo2, scene.specular, scene.reflect, scene.frame_centre,
      jnp.cos(scene.frame_yaw)[:, None], jnp.sin(scene.frame_yaw)[:, None], scene.texture_dir,
      scene.texture_scale[:, None], scene.texture.astype(jnp.float32)[:, None],
      scene.shininess[:, None], scene.label.astype(jnp.float32)[:, None]], axis=1)


def _albedo_xyz(points: Vec, cols: list, textures: bool = True) -> Vec:
  a1, a2 = cols[0:3], cols[3:6]
  if not textures:
    return tuple(a1)
  fcx, fcy, fcz, cos, sin = cols[12:17]
  tdir = tuple(cols[17:20])
  scale, kind = cols[20], cols[21]
  px, py = points[0] - fcx, points[1] - fcy
  q = (cos * px + sin * py, -sin * px + cos * py, points[2] - fcz)
  mix, tint = _texture_mix(q, jnp.round(kind).astype(jnp.int32), scale, tdir)
  return tuple((a + (b - a) * mix) * tint for a, b in zip(a1, a2))


# =============================================================================================
# Shading and the full render
# =============================================================================================


@flax.struct.dataclass
class _Surface:
  """What the lighting needs at each ray's first hit (a "G-buffer"); vectors are xyz tuples."""
  hit: jax.Array  # [R] bool
  points: tuple
  normals: tuple
  view: tuple  # unit ray direction
  albedo: tuple
  specular: tuple
  reflect: tuple
  shininess: jax.Array  # [R]


def _surface_xyz(origins: Vec, directions: Vec, hit: Hit, scene: SceneArrays,
                 options: RenderOptions) -> _Surface:
  g = jnp.where(hit.hit, hit.surface, 0)
  t = jnp.where(hit.hit, hit.t, 0.0)
  points = tuple(o + t * d for o, d in zip(origins, directions))
  cols = _gather_columns(_material_table(scene), g)
  return _Surface(hit=hit.hit, points=points,
                  normals=_surface_normals_xyz(origins, directions, hit, scene, options),
                  view=_unit(directions), albedo=_albedo_xyz(points, cols, options.textures),
                  specular=tuple(cols[6:9]), reflect=tuple(cols[9:12]), shininess=cols[22])


def _offset_points(surface: _Surface) -> Vec:
  """Start points of secondary rays, just off the surface so they do not hit it again."""
  return tuple(p + SURFACE_OFFSET * n for p, n in zip(surface.points, surface.normals))


def _light_visibility(surface: _Surface, scene: SceneArrays, options: RenderOptions) -> list:
  """L arrays [R]: 1 where the directional light is unoccluded (a shadow ray per light)."""
  lights = [(scene.light_dir[l, 0], scene.light_dir[l, 1], scene.light_dir[l, 2])
            for l in range(scene.light_dir.shape[0])]
  blocked = _blocked(_offset_points(surface), lights, scene, options.quadrics)
  return [jnp.where(b, 0.0, 1.0) for b in blocked]


def _direct_light(surface: _Surface, visibility: Optional[list], scene: SceneArrays) -> Vec:
  """Ambient + Lambert + Blinn–Phong per light, linear RGB; the sky colour where nothing is hit."""
  diffuse_light = [scene.ambient[c] for c in range(3)]
  highlight_light = [0.0, 0.0, 0.0]
  for l in range(scene.light_dir.shape[0]):  # L = 3 lights, unrolled
    light = (scene.light_dir[l, 0], scene.light_dir[l, 1], scene.light_dir[l, 2])
    visible = 1.0 if visibility is None else visibility[l]
    n_dot_l = jnp.maximum(_dot(surface.normals, light), 0.0)
    half = _unit(tuple(li - v for li, v in zip(light, surface.view)))
    n_dot_h = jnp.maximum(_dot(surface.normals, half), 0.0)
    highlight = jnp.where(n_dot_l > 0, n_dot_h ** surface.shininess, 0.0) * visible
    for c in range(3):
      diffuse_light[c] = diffuse_light[c] + scene.light_rgb[l, c] * n_dot_l * visible
      highlight_light[c] = highlight_light[c] + scene.light_rgb[l, c] * highlight
  return tuple(jnp.where(surface.hit, a * dl + k * hl, sky) for a, dl, k, hl, sky in zip(
      surface.albedo, diffuse_light, surface.specular, highlight_light, SKY_LINEAR))


def _mirror_rays(surface: _Surface) -> tuple[Vec, Vec]:
  dn = 2.0 * _dot(surface.view, surface.normals)
  mirror = _unit(tuple(v - dn * n for v, n in zip(surface.view, surface.normals)))
  return _offset_points(surface), mirror


def _add_reflection(radiance: Vec, surface: _Surface, bounced: Vec) -> Vec:
  return tuple(jnp.where(surface.hit, r + k * b, r)
               for r, k, b in zip(radiance, surface.reflect, bounced))


def _shade_xyz(origins: Vec, directions: Vec, hit: Hit, scene: SceneArrays,
               options: RenderOptions, *, shadows: bool, bounce: bool) -> Vec:
  surface = _surface_xyz(origins, directions, hit, scene, options)
  visibility = _light_visibility(surface, scene, options) if shadows else None
  radiance = _direct_light(surface, visibility, scene)
  if bounce:
    # One mirror bounce (metal), its hit shaded without shadows or further bounces.
    start, mirror = _mirror_rays(surface)
    hit2 = _trace_xyz(start, mirror, scene, options)
    bounced = _direct_light(_surface_xyz(start, mirror, hit2, scene, options), None, scene)
    radiance = _add_reflection(radiance, surface, bounced)
  return radiance


def shade(*, origins: jax.Array, directions: jax.Array, hit: Hit, scene: SceneArrays,
          options: RenderOptions, shadows: bool, bounce: bool) -> jax.Array:
  """Linear radiance [R, 3] of the first hit: ambient + Lambert + Blinn–Phong per light.

  Shadow rays go to each directional light (only primitives occlude); metal adds one mirror bounce
  whose hit is shaded without shadows or further bounces. (`render_views` runs the same steps as
  separately compiled stages.)
  """
  return jnp.stack(_shade_xyz(_unstack(origins), _unstack(directions), hit, scene, options,
                              shadows=shadows, bounce=bounce), axis=-1)


def camera_rays(*, cam_to_world: jax.Array, intrinsics: jax.Array, image_size: int,
                offsets: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Rays through pixel (u, v) + offset: [N,4,4], [3,3], offsets [A,2] → origins, dirs [N,H,W,A,3].

  Directions are not normalised: their camera-z component is 1, so the ray parameter of a hit is
  its camera-z depth.
  """
  pix = geometry.image_pixels(image_size, image_size)[:, :, None, :] + offsets  # [H, W, A, 2]
  # The model's back-projection K⁻¹[u, v, 1] (camera z = 1), not geometry.pixel_rays: that one
  # normalises the directions, which would make the hit parameter a distance instead of the depth.
  d_cam = geometry.pix_to_cam(pix=pix, intrinsics=intrinsics)  # [H, W, A, 3]
  dirs = jnp.einsum("nij,hwaj->nhwai", cam_to_world[:, :3, :3], d_cam)  # [N, H, W, A, 3]
  origins = jnp.broadcast_to(cam_to_world[:, None, None, None, :3, 3], dirs.shape)
  return origins, dirs


@flax.struct.dataclass
class Render:
  rgb: jax.Array  # [N, H, W, 3] gamma-encoded in [0, 1]
  label: jax.Array  # [N, H, W] int32 mask label of the pixel-centre ray, 0 = background
  depth: jax.Array  # [N, H, W] float32 camera-z depth of the pixel-centre ray (0 where no hit)


@functools.partial(jax.jit, static_argnames=("image_size", "options"))
def render_centre(scene: SceneArrays, *, cam_to_world: jax.Array, intrinsics: jax.Array,
                  image_size: int, options: RenderOptions) -> tuple[jax.Array, jax.Array]:
  """Label and depth [N, H, W] of the ray through every pixel centre (no shading)."""
  origins, dirs = camera_rays(cam_to_world=cam_to_world, intrinsics=intrinsics,
                              image_size=image_size, offsets=jnp.zeros((1, 2), jnp.float32))
  shape = origins.shape[:3]
  hit = trace(origins=origins.reshape(-1, 3), directions=dirs.reshape(-1, 3), scene=scene,
              options=options)  # [N·H·W]
  label = jnp.where(hit.hit, scene.label[jnp.where(hit.hit, hit.surface, 0)], BACKGROUND_LABEL)
  depth = jnp.where(hit.hit, hit.t, 0.0)
  return label.reshape(shape), depth.reshape(shape)


# render_views runs as separately compiled stages. Each stage's inputs are materialised arrays,
# which keeps XLA from fusing (and so recomputing) shading inputs into every ray×primitive loop of
# the shadow and bounce traces; one jit over everything was 2–3× slower on CPU.
_options_jit = functools.partial(jax.jit, static_argnames=("options",))
_stage_trace = _options_jit(_trace_xyz)
_stage_surface = _options_jit(_surface_xyz)
_stage_visibility = _options_jit(_light_visibility)
_stage_direct_light = jax.jit(_direct_light)
_stage_mirror_rays = jax.jit(_mirror_rays)
_stage_add_reflection = jax.jit(_add_reflection)


@functools.partial(jax.jit, static_argnames=("image_size", "supersample"))
def _stage_rays(cam_to_world, intrinsics, *, image_size: int, supersample: int):
  origins, dirs = camera_rays(cam_to_world=cam_to_world, intrinsics=intrinsics,
                              image_size=image_size,
                              offsets=jnp.asarray(geometry.subpixel_offsets(supersample)))
  return _unstack(origins.reshape(-1, 3)), _unstack(dirs.reshape(-1, 3))  # 3 × [R]


@functools.partial(jax.jit, static_argnames=("shape",))
def _stage_resolve(radiance: Vec, *, shape: tuple) -> jax.Array:
  # Anti-aliasing (docs/method.md §3.5): average the A supersamples in linear light, gamma-encode.
  rgb = [jnp.mean(jnp.clip(r, 0.0, 1.0).reshape(shape), axis=3) ** (1.0 / GAMMA)
         for r in radiance]  # 3 × [N, H, W]
  return jnp.stack(rgb, axis=-1)


def render_views(scene: SceneArrays, *, cam_to_world: jax.Array, intrinsics: jax.Array,
                 image_size: int, options: RenderOptions) -> Render:
  """All N views of a scene: cam_to_world [N, 4, 4] (world units), pixel intrinsics [3, 3]."""
  o, d = _stage_rays(cam_to_world, intrinsics, image_size=image_size,
                     supersample=options.supersample)  # 3 × [R], R = N·H·W·A
  hit = _stage_trace(o, d, scene, options)
  surface = _stage_surface(o, d, hit, scene, options)
  radiance = _stage_direct_light(surface, _stage_visibility(surface, scene, options), scene)
  if options.reflections:
    start, mirror = _stage_mirror_rays(surface)
    hit2 = _stage_trace(start, mirror, scene, options)
    bounced = _stage_direct_light(_stage_surface(start, mirror, hit2, scene, options), None, scene)
    radiance = _stage_add_reflection(radiance, surface, bounced)
  shape = (cam_to_world.shape[0], image_size, image_size, options.supersample ** 2)
  label, depth = render_centre(scene, cam_to_world=cam_to_world, intrinsics=intrinsics,
                               image_size=image_size, options=options)
  return Render(rgb=_stage_resolve(radiance, shape=shape), label=label, depth=depth)
