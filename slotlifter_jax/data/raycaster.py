"""Ray–scene intersection of the embedded generator's ray caster (docs/method.md §3.5): a scene
packed into padded arrays, and the closest surface and its normal along every ray.

Vocabulary (docs/method.md §0, plus the generator's own letters): R rays, P primitives of a scene
(padded to the family's maximum), G = P + 5 surfaces (the primitives, then the floor and the four
room walls), L = 3 lights.

Every primitive is the intersection of three slabs and one quadric in its local frame (yawed about
world z), so one branch-free formula intersects them all: a box uses the slabs only, a sphere the
quadric only, a capped cylinder the z slab and an xy quadric.

The geometry is its own module because it is the part whose correctness is checked against
independent NumPy code (tests/test_generator.py) and whose loop structure decides the generator's
speed; `shading.py` builds the lighting and the staged render of views on top of it, and the scene
description it packs comes from `layout.py` (which never imports JAX).
"""

from __future__ import annotations

import dataclasses

import flax
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax.data.layout import CHAIR_PARTS, MAX_OBJECTS, ROOM_HALF_SIZE, Material, SceneSpec

# ---- renderer numerics ----
UNBOUNDED = 1e6  # slab half-size of an axis a primitive does not bound; far beyond the scene
T_MIN = 1e-4  # smallest accepted ray parameter: rejects self-hits of rays leaving a surface
DIR_EPS = 1e-12  # |direction component| below this is treated as ±DIR_EPS in slab divisions
QUAD_EPS = 1e-12  # quadric leading coefficient below this: the ray is parallel to its axis
GAMMA = 2.2  # shading is in linear light; images are stored gamma-encoded

# Surface slots after the P primitives.
FLOOR = 0
WALLS = 4  # +x, −x, +y, −y
NUM_BACKGROUND_SURFACES = 1 + WALLS

# Texture kinds (per surface).
TEX_PLAIN, TEX_STRIPES, TEX_CHECKER, TEX_NOISE, TEX_WOOD, TEX_TILES = range(6)
TEXTURE_IDS = {"plain": TEX_PLAIN, "stripes": TEX_STRIPES, "checker": TEX_CHECKER,
               "noise": TEX_NOISE, "wood": TEX_WOOD, "tiles": TEX_TILES}


# =============================================================================================
# Renderer input (JAX side)
# =============================================================================================


@flax.struct.dataclass
class SceneArrays:
  """A scene as padded arrays; surfaces g < P are primitives, then floor and walls."""
  centre: jax.Array  # [P, 3]
  yaw: jax.Array  # [P]
  slab: jax.Array  # [P, 3] slab half-sizes (UNBOUNDED where an axis is not bounded)
  quad: jax.Array  # [P, 3] quadric weights: sphere (1,1,1), cylinder (1,1,0), box (0,0,0)
  radius: jax.Array  # [P] quadric radius (1 for boxes, whose quadric is then everywhere ≤ 0)
  active: jax.Array  # [P] bool
  frame_centre: jax.Array  # [G, 3] origin of the texture frame
  frame_yaw: jax.Array  # [G]
  albedo: jax.Array  # [G, 3] linear
  albedo2: jax.Array  # [G, 3] linear
  texture: jax.Array  # [G] int32 texture kind
  texture_scale: jax.Array  # [G]
  texture_dir: jax.Array  # [G, 3]
  specular: jax.Array  # [G, 3] linear highlight colour
  shininess: jax.Array  # [G]
  reflect: jax.Array  # [G, 3] mirror bounce colour
  label: jax.Array  # [G] int32
  light_dir: jax.Array  # [L, 3]
  light_rgb: jax.Array  # [L, 3]
  ambient: jax.Array  # [3]
  room_half: jax.Array  # [] wall position (walls exist only when RenderOptions.walls)


@dataclasses.dataclass(frozen=True)
class RenderOptions:
  """Static (compile-time) renderer switches."""
  supersample: int = 2  # √A: colour uses a supersample×supersample grid per pixel
  reflections: bool = True
  textures: bool = False
  walls: bool = False
  quadrics: bool = True  # False: every primitive is a box, skip the quadric term


def render_options(family: str, supersample: int = 2, walls: bool = True,
                   clevr_objects: bool = False) -> RenderOptions:
  """`walls`: False renders a room family scene without walls (its floor to the horizon);
  `clevr_objects`: a room holding CLEVR's objects, whose spheres and cylinders need the quadric
  and whose metal the mirror bounce."""
  if family == "clevr":
    return RenderOptions(supersample=supersample, reflections=True, textures=False, walls=False,
                         quadrics=True)
  return RenderOptions(supersample=supersample, reflections=clevr_objects, textures=True,
                       walls=walls, quadrics=clevr_objects)


def _linear(rgb) -> np.ndarray:
  return (np.asarray(rgb, np.float64) / 255.0) ** GAMMA


def scene_arrays(spec: SceneSpec) -> SceneArrays:
  """Packs a SceneSpec into padded float32 arrays (P = the family's maximum primitive count)."""
  max_prims = MAX_OBJECTS[spec.family] * (CHAIR_PARTS if spec.family == "room" else 1)
  p = max_prims
  g = p + NUM_BACKGROUND_SURFACES
  centre = np.zeros((p, 3)); centre[:, 2] = -100.0
  yaw = np.zeros(p); slab = np.ones((p, 3)); quad = np.zeros((p, 3)); radius = np.ones(p)
  active = np.zeros(p, bool)
  frame_centre = np.zeros((g, 3)); frame_yaw = np.zeros(g)
  albedo = np.zeros((g, 3)); albedo2 = np.zeros((g, 3)); texture = np.zeros(g, np.int32)
  texture_scale = np.ones(g); texture_dir = np.tile([1.0, 0.0, 0.0], (g, 1))
  specular = np.zeros((g, 3)); shininess = np.ones(g); reflect = np.zeros((g, 3))
  label = np.zeros(g, np.int32)

  def set_material(i, m: Material):
    a = _linear(m.rgb)
    albedo[i] = m.diffuse * a
    albedo2[i] = m.diffuse * _linear(m.rgb2)
    texture[i] = TEXTURE_IDS[m.texture]
    texture_scale[i] = m.texture_scale
    texture_dir[i] = m.texture_dir
    specular[i] = m.specular * ((1 - m.specular_tint) + m.specular_tint * a)
    shininess[i] = m.shininess
    reflect[i] = m.reflect * (0.1 + 0.9 * a)  # metal reflects in its own colour

  i = 0
  for obj in spec.objects:
    for j, part in enumerate(obj.parts):
      centre[i] = part.centre
      yaw[i] = part.yaw
      h = np.asarray(part.half_size)
      if part.kind == "box":
        slab[i] = h
      elif part.kind == "sphere":
        slab[i] = UNBOUNDED; quad[i] = (1, 1, 1); radius[i] = h[0]
      elif part.kind == "cylinder":
        slab[i] = (UNBOUNDED, UNBOUNDED, h[2]); quad[i] = (1, 1, 0); radius[i] = h[0]
      else:
        raise ValueError(f"unknown primitive kind {part.kind!r}")
      active[i] = True
      # Textures live in the object's frame (a chair's seat, back and legs share it).
      frame_centre[i] = obj.parts[0].centre
      frame_yaw[i] = obj.yaw
      is_leg = obj.shape == "chair" and j >= 2
      set_material(i, obj.leg_material if is_leg else obj.material)
      label[i] = obj.label
      i += 1
  set_material(p + FLOOR, spec.floor)
  if spec.walls is not None:
    for w, m in enumerate(spec.walls):
      set_material(p + 1 + w, m)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return SceneArrays(
      centre=f32(centre), yaw=f32(yaw), slab=f32(slab), quad=f32(quad), radius=f32(radius),
      active=jnp.asarray(active), frame_centre=f32(frame_centre), frame_yaw=f32(frame_yaw),
      albedo=f32(albedo), albedo2=f32(albedo2), texture=jnp.asarray(texture),
      texture_scale=f32(texture_scale), texture_dir=f32(texture_dir), specular=f32(specular),
      shininess=f32(shininess), reflect=f32(reflect), label=jnp.asarray(label),
      light_dir=f32([l.direction for l in spec.lights]),
      light_rgb=f32([l.intensity for l in spec.lights]), ambient=f32(spec.ambient),
      room_half=f32(ROOM_HALF_SIZE))


# =============================================================================================
# Ray–primitive intersection (pure jnp, any leading shape)
# =============================================================================================


# Vectors are tuples of [R] component arrays, not [R, 3] stacks, in the intersection and shading
# code: XLA then fuses each step into a few loops over the rays instead of materialising (and, at
# every stack, recomputing per channel) [R, 3] intermediates; stacked code was 3–5× slower on CPU.
Vec = tuple  # (x, y, z), each [...]


def _dot(a: Vec, b: Vec) -> jax.Array:
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _unit(a: Vec) -> Vec:
  inv = 1.0 / jnp.maximum(jnp.sqrt(_dot(a, a)), 1e-12)
  return a[0] * inv, a[1] * inv, a[2] * inv


def _unstack(v: jax.Array) -> Vec:
  return v[..., 0], v[..., 1], v[..., 2]


def _slab(o, d, half):
  """Entry and exit parameter of the slab |x| ≤ half along one axis."""
  inv = 1.0 / jnp.where(d >= 0, jnp.maximum(d, DIR_EPS), jnp.minimum(d, -DIR_EPS))
  ta = (-half - o) * inv
  tb = (half - o) * inv
  return jnp.minimum(ta, tb), jnp.maximum(ta, tb)


def _quadric(o, d, quad, radius):
  """Entry, exit and crossing flag of Σ quad_i x_i² ≤ radius² (xyz component tuples)."""
  a = quad[0] * d[0] * d[0] + quad[1] * d[1] * d[1] + quad[2] * d[2] * d[2]
  b = quad[0] * o[0] * d[0] + quad[1] * o[1] * d[1] + quad[2] * o[2] * d[2]
  c = quad[0] * o[0] * o[0] + quad[1] * o[1] * o[1] + quad[2] * o[2] * o[2] - radius * radius
  disc = b * b - a * c
  has_a = a > QUAD_EPS
  # Numerically stable roots: q = −(b + sign(b)·√disc), roots q/a and c/q.
  q = -(b + jnp.where(b >= 0, 1.0, -1.0) * jnp.sqrt(jnp.maximum(disc, 0.0)))
  r1 = q / jnp.where(has_a, a, 1.0)
  r2 = c / jnp.where(jnp.abs(q) > QUAD_EPS, q, QUAD_EPS)
  near = jnp.where(has_a, jnp.minimum(r1, r2), -UNBOUNDED)
  far = jnp.where(has_a, jnp.maximum(r1, r2), UNBOUNDED)
  ok = jnp.where(has_a, disc >= 0, c <= 0)
  return near, far, ok


def _span_terms(o, d, slab, quad, radius, quadrics: bool):
  """(near_x, near_y, near_z, near_quadric, exit, ok); o, d, slab, quad: xyz component tuples."""
  nx, fx = _slab(o[0], d[0], slab[0])
  ny, fy = _slab(o[1], d[1], slab[1])
  nz, fz = _slab(o[2], d[2], slab[2])
  exit_ = jnp.minimum(jnp.minimum(fx, fy), fz)
  if not quadrics:  # boxes only (room family): the quadric term is everywhere satisfied
    return nx, ny, nz, jnp.full_like(nx, -UNBOUNDED), exit_, jnp.ones(nx.shape, bool)
  nq, fq, ok = _quadric(o, d, quad, radius)
  return nx, ny, nz, nq, jnp.minimum(exit_, fq), ok


def _primitive_entry(o: tuple, d: tuple, scene: SceneArrays, p, quadrics: bool) -> jax.Array:
  """Entry parameter [...] of rays (xyz component tuples) into primitive p (inf: missed)."""
  cos, sin = jnp.cos(scene.yaw[p]), jnp.sin(scene.yaw[p])
  ox, oy, oz = (c - scene.centre[p, i] for i, c in enumerate(o))
  o_l = (cos * ox + sin * oy, -sin * ox + cos * oy, oz)
  d_l = (cos * d[0] + sin * d[1], -sin * d[0] + cos * d[1], d[2])
  slab = (scene.slab[p, 0], scene.slab[p, 1], scene.slab[p, 2])
  quad = (scene.quad[p, 0], scene.quad[p, 1], scene.quad[p, 2])
  nx, ny, nz, nq, exit_, ok = _span_terms(o_l, d_l, slab, quad, scene.radius[p], quadrics)
  entry = jnp.maximum(jnp.maximum(nx, ny), jnp.maximum(nz, nq))
  hit = ok & (entry <= exit_) & (entry > T_MIN) & scene.active[p]
  return jnp.where(hit, entry, jnp.inf)


# Loops over primitives are lax.fori_loops whose body handles one primitive with its parameters as
# scalars: XLA:CPU compiles the body into one vectorised pass over contiguous rays (≈ 1 ns per
# ray·primitive). Both alternatives were slower: a [P, R] array reduced over P ran ≈ 7× slower
# (scalar reduction code), and unrolling P made compilation take 3× longer.


def _nearest_primitive(o: tuple, d: tuple, scene: SceneArrays,
                       quadrics: bool) -> tuple[jax.Array, jax.Array]:
  """Nearest entry parameter [R] over the primitives and its index (ties keep the lower)."""
  shape = jnp.broadcast_shapes(*(jnp.shape(c) for c in o + d))

  def body(p, carry):
    best, index = carry
    t = _primitive_entry(o, d, scene, p, quadrics)
    closer = t < best
    return jnp.where(closer, t, best), jnp.where(closer, p, index)

  init = (jnp.full(shape, jnp.inf, jnp.float32), jnp.zeros(shape, jnp.int32))
  return jax.lax.fori_loop(0, scene.centre.shape[0], body, init)


def _blocked(o: tuple, directions: list, scene: SceneArrays, quadrics: bool) -> list:
  """For each of the given directions, whether any primitive blocks the rays from o: [R] bools."""
  shape = jnp.broadcast_shapes(*(jnp.shape(c) for c in o))

  def body(p, carry):
    return tuple(c | (_primitive_entry(o, d, scene, p, quadrics) < jnp.inf)
                 for c, d in zip(carry, directions))

  init = tuple(jnp.zeros(shape, bool) for _ in directions)
  return list(jax.lax.fori_loop(0, scene.centre.shape[0], body, init))


def intersect_primitives(*, origins: jax.Array, directions: jax.Array, scene: SceneArrays,
                         quadrics: bool = True) -> jax.Array:
  """Ray parameter of the first entry into each primitive, inf where missed: [..., 3] → [..., P].

  `quadrics=False` skips the quadric term (valid when every primitive is a box).
  """
  o, d = _unstack(origins), _unstack(directions)
  t = [_primitive_entry(o, d, scene, p, quadrics) for p in range(scene.centre.shape[0])]
  return jnp.stack(jnp.broadcast_arrays(*t), axis=-1)


def _intersect_background_xyz(o: tuple, d: tuple, scene: SceneArrays, walls: bool) -> list:
  ox, oy, oz = o
  dx, dy, dz = d
  t_floor = jnp.where(dz < -DIR_EPS, -oz / jnp.minimum(dz, -DIR_EPS), jnp.inf)
  t_floor = jnp.where(t_floor > T_MIN, t_floor, jnp.inf)
  if not walls:
    return [t_floor]
  half = scene.room_half
  fx, fy = ox + t_floor * dx, oy + t_floor * dy
  inside = (jnp.abs(fx) <= half) & (jnp.abs(fy) <= half)
  ts = [jnp.where(inside, t_floor, jnp.inf)]
  safe = lambda v: jnp.where(v >= 0, jnp.maximum(v, DIR_EPS), jnp.minimum(v, -DIR_EPS))
  # Wall at axis = sign·half, inner face hit when the ray moves towards it (sign·d_axis > 0).
  for axis_o, axis_d, other_o, other_d, sign in ((ox, dx, oy, dy, 1.0), (ox, dx, oy, dy, -1.0),
                                                 (oy, dy, ox, dx, 1.0), (oy, dy, ox, dx, -1.0)):
    t = (sign * half - axis_o) / safe(axis_d)
    other = other_o + t * other_d
    z = oz + t * dz
    ok = (sign * axis_d > DIR_EPS) & (t > T_MIN) & (jnp.abs(other) <= half) & (z >= 0.0)
    ts.append(jnp.where(ok, t, jnp.inf))
  return ts


@flax.struct.dataclass
class Hit:
  t: jax.Array  # [R] ray parameter (inf: no hit)
  surface: jax.Array  # [R] int32 surface index g (meaningless where not hit)
  hit: jax.Array  # [R] bool


def _trace_xyz(o: tuple, d: tuple, scene: SceneArrays, options: RenderOptions) -> Hit:
  t, surface = _nearest_primitive(o, d, scene, options.quadrics)  # [R]
  p = scene.centre.shape[0]
  for b, t_b in enumerate(_intersect_background_xyz(o, d, scene, options.walls)):
    closer = t_b < t
    t = jnp.where(closer, t_b, t)
    surface = jnp.where(closer, p + b, surface)
  return Hit(t=t, surface=surface, hit=jnp.isfinite(t))


def trace(*, origins: jax.Array, directions: jax.Array, scene: SceneArrays,
          options: RenderOptions) -> Hit:
  """Closest surface along each ray: [R, 3] rays → Hit of [R] (surfaces g ∈ [0, P + 5))."""
  return _trace_xyz(_unstack(origins), _unstack(directions), scene, options)


def _gather_columns(table: jax.Array, index: jax.Array) -> list[jax.Array]:
  """One gather of a packed [G, F] table at [R] indices → F arrays of [R]."""
  rows = table[index]  # [R, F]
  return [rows[:, f] for f in range(table.shape[1])]


def _surface_normals_xyz(origins: Vec, directions: Vec, hit: Hit, scene: SceneArrays,
                         options: RenderOptions) -> Vec:
  p = scene.centre.shape[0]
  k = jnp.minimum(hit.surface, p - 1)
  prim_table = jnp.concatenate([scene.centre, jnp.cos(scene.yaw)[:, None],
                                jnp.sin(scene.yaw)[:, None], scene.slab, scene.quad,
                                scene.radius[:, None]], axis=1)  # [P, 12]
  cx, cy, cz, cos, sin, sx, sy, sz, qx, qy, qz, radius = _gather_columns(prim_table, k)
  ox, oy, oz = origins[0] - cx, origins[1] - cy, origins[2] - cz
  o = (cos * ox + sin * oy, -sin * ox + cos * oy, oz)
  d = (cos * directions[0] + sin * directions[1], -sin * directions[0] + cos * directions[1],
       directions[2])
  nx, ny, nz, nq, _, _ = _span_terms(o, d, (sx, sy, sz), (qx, qy, qz), radius, options.quadrics)
  # The entry point lies on the constraint that set the entry: a slab face or the quadric.
  m = jnp.maximum(jnp.maximum(nx, ny), jnp.maximum(nz, nq))
  is_q = nq >= m
  is_x = ~is_q & (nx >= m)
  is_y = ~is_q & ~is_x & (ny >= m)
  is_z = ~is_q & ~is_x & ~is_y
  t = jnp.where(hit.hit, hit.t, 0.0)
  g = _unit((qx * (o[0] + t * d[0]), qy * (o[1] + t * d[1]), qz * (o[2] + t * d[2])))
  lx = jnp.where(is_q, g[0], jnp.where(is_x, -jnp.sign(d[0]), 0.0))
  ly = jnp.where(is_q, g[1], jnp.where(is_y, -jnp.sign(d[1]), 0.0))
  lz = jnp.where(is_q, g[2], jnp.where(is_z, -jnp.sign(d[2]), 0.0))
  wx, wy = cos * lx - sin * ly, sin * lx + cos * ly
  # Background surfaces: floor (0, 0, 1), walls +x, −x, +y, −y face inwards.
  b = hit.surface - p
  is_prim = hit.surface < p
  bx = jnp.where(b == 1, -1.0, jnp.where(b == 2, 1.0, 0.0))
  by = jnp.where(b == 3, -1.0, jnp.where(b == 4, 1.0, 0.0))
  bz = jnp.where(b == FLOOR, 1.0, 0.0)
  return (jnp.where(is_prim, wx, bx), jnp.where(is_prim, wy, by), jnp.where(is_prim, lz, bz))


def surface_normals(*, origins: jax.Array, directions: jax.Array, hit: Hit,
                    scene: SceneArrays, options: RenderOptions) -> jax.Array:
  """World unit normals [R, 3] at the hit points, from the constraint that set the entry."""
  return jnp.stack(_surface_normals_xyz(_unstack(origins), _unstack(directions), hit, scene,
                                        options), axis=-1)
