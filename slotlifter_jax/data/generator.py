"""The embedded default data set: procedural scenes, analytic ray caster (docs/method.md §3.5).

Vocabulary (docs/method.md §0, plus the generator's own letters): N views per scene, H×W image size,
A anti-aliasing samples per pixel (a √A×√A grid), R rays (N·H·W·A for a colour pass, N·H·W for the
centre pass), P primitives of a scene (padded to the family's maximum), G = P + 5 surfaces (the
primitives, then the floor and the four room walls), L = 3 lights.

A scene is a list of objects; every object is made of convex primitives (CLEVR: one cube, sphere or
cylinder; room: a chair of six boxes). Every primitive is the intersection of three slabs and one
quadric in its local frame (yawed about world z), so one branch-free formula intersects them all:
a box uses the slabs only, a sphere the quadric only, a capped cylinder the z slab and an xy
quadric.

The ray caster is written in jax.numpy and compiled once per (N, H, W, P): it traces all rays of all
views of a scene at once, with shadow rays to each light, one mirror bounce for metal and
procedural textures for the room family. Colour comes from A supersamples per pixel; the instance
mask and the depth come from one extra ray through each pixel centre, so they are exact (not derived
from colour). World units are the uORF ones (camera radius ≈ 12.4); readers apply the 1/7 scene
scale (docs/method.md §3.1).

This module also writes a data set in the uORF folder format (docs/method.md §3.2/§3.3, see
`generate_dataset`): per view `NNNNN_scSSSS_azAA.png`, `_RT.txt` (OpenCV cam2world, world units),
`_intrinsics.txt` (normalised K), `_depth.npy` (camera-z depth, world units), `_mask.png` (label l
drawn in grey `LABEL_GREY_STEP·l`), and per split a `dataset.json`.
"""

from __future__ import annotations

import colorsys
import dataclasses
import functools
import json
import math
import multiprocessing
import os
import shutil
import time
from typing import Optional, Sequence

import flax
import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

GENERATOR_VERSION = 1
FAMILIES = ("clevr", "room")
SUBSETS = {"clevr": "clevr_567", "room": "room_chair"}  # uORF folder prefixes (docs/method.md §3.2)
SPLITS = ("train", "val", "test")
SCENE_SCALE = 1.0 / 7.0  # uORF "nss_scale": readers scale world units by it (docs/method.md §3.1)

# ---- cameras (docs/method.md §3.1, §3.5) ----
CAMERA_RADIUS = 12.4
CAMERA_RADIUS_JITTER = 0.2
CAMERA_ELEVATION_DEG = 40.0
CAMERA_ELEVATION_JITTER_DEG = 2.0
# uORF intrinsics: a 4:3 camera squeezed to a square, fx = 1.09375·W and fy = fx·4/3 = 1.458333·H.
FOCAL_X_PER_WIDTH = 35.0 / 32.0
FOCAL_Y_PER_HEIGHT = 35.0 / 24.0

# ---- masks ----
BACKGROUND_LABEL = 0
# Label l is drawn as grey (17·l, 17·l, 17·l); PIL's RGB→L conversion maps it back to 17·l exactly.
LABEL_GREY_STEP = 17
MAX_OBJECTS = {"clevr": 7, "room": 4}
# An object must cover at least this many pixels of the source view at 128×128 (scaled by area).
MIN_VISIBLE_PIXELS_128 = 20

# ---- CLEVR statistics (docs/method.md §3.5) ----
CLEVR_COLOURS = {
    "gray": (87, 87, 87), "red": (173, 35, 35), "blue": (42, 75, 215), "green": (29, 105, 20),
    "brown": (129, 74, 25), "purple": (129, 38, 192), "cyan": (41, 208, 208),
    "yellow": (255, 238, 51),
}
CLEVR_SIZES = {"large": 0.7, "small": 0.35}  # CLEVR half-sizes r
CLEVR_SHAPES = ("cube", "sphere", "cylinder")
CLEVR_MATERIALS = ("rubber", "metal")
CLEVR_NUM_OBJECTS = (5, 7)
CLEVR_XY_RANGE = 3.0
MIN_GAP = 0.25  # between bounding circles
# Optional easier sets (`object_scale` > 1, e.g. 1–3 objects at 1.6×) keep every object's bounding
# circle inside the footprint of the default scenes, |x|, |y| ≤ CLEVR_FOOTPRINT = 3.99: the range of
# the largest default object (a large cube, bounding radius 0.7·√2) placed at CLEVR_XY_RANGE. An
# object larger than that is placed within CLEVR_FOOTPRINT − its bounding radius, so the framing
# stays the default one and the scene stays inside the model's locality box (0.64 / scene scale
# = 4.48 world units; the tallest object's top, 2·0.7·scale, is then at most 2.8).
CLEVR_MAX_BOUNDING_RADIUS = CLEVR_SIZES["large"] * math.sqrt(2.0)
CLEVR_FOOTPRINT = CLEVR_XY_RANGE + CLEVR_MAX_BOUNDING_RADIUS
# At 2× a large cube's bounding radius is 1.98, which leaves it a placement range of 2.01: three
# large cubes (pairwise ≥ 4.21 apart) no longer fit together (such a draw is redrawn, ~5% of
# 1–3-object layouts), and beyond 2.31× not even two do. Hence the cap.
MAX_OBJECT_SCALE = 2.0
# Layout draws (each up to 200 tries per object) before sample_clevr_layout gives up: only an
# option set whose objects cannot fit (many objects at a large scale) gets near it.
MAX_LAYOUT_DRAWS = 2000

# ---- room family ----
ROOM_NUM_CHAIRS = (1, 4)
ROOM_XY_RANGE = 3.0
ROOM_HALF_SIZE = 7.0  # walls at x, y = ±7: inside the camera circle, so the near walls are culled
CHAIR_PARTS = 6  # seat, back, four legs
ROOM_TEXTURES = ("plain", "stripes", "checker", "noise")
WOOD_COLOURS = ((164, 116, 73), (193, 154, 107), (133, 94, 66), (110, 75, 50), (205, 170, 125))

# ---- renderer numerics ----
UNBOUNDED = 1e6  # slab half-size of an axis a primitive does not bound; far beyond the scene
T_MIN = 1e-4  # smallest accepted ray parameter: rejects self-hits of rays leaving a surface
SURFACE_OFFSET = 1e-3  # shadow / reflection rays start this far off the surface, along the normal
DIR_EPS = 1e-12  # |direction component| below this is treated as ±DIR_EPS in slab divisions
QUAD_EPS = 1e-12  # quadric leading coefficient below this: the ray is parallel to its axis
GAMMA = 2.2  # shading is in linear light; images are stored gamma-encoded
SKY_LINEAR = (0.55, 0.57, 0.62)  # seen only in metal reflections pointing up

# Surface slots after the P primitives.
FLOOR = 0
WALLS = 4  # +x, −x, +y, −y
NUM_BACKGROUND_SURFACES = 1 + WALLS

# Texture kinds (per surface).
TEX_PLAIN, TEX_STRIPES, TEX_CHECKER, TEX_NOISE, TEX_WOOD, TEX_TILES = range(6)
TEXTURE_IDS = {"plain": TEX_PLAIN, "stripes": TEX_STRIPES, "checker": TEX_CHECKER,
               "noise": TEX_NOISE, "wood": TEX_WOOD, "tiles": TEX_TILES}

PRIMITIVE_KINDS = ("box", "sphere", "cylinder")


def min_visible_pixels(image_size: int) -> int:
  return max(1, math.ceil(MIN_VISIBLE_PIXELS_128 * image_size * image_size / 128 ** 2))


def num_source_views_for(views: int) -> int:
  """1 source view for the uORF-style sets; with 8 or more views the first 4 are sources."""
  return 4 if views >= 8 else 1


def label_grey_levels(max_objects: int) -> list[int]:
  return [LABEL_GREY_STEP * l for l in range(max_objects + 1)]


# =============================================================================================
# Scene description (numpy side)
# =============================================================================================


@dataclasses.dataclass(frozen=True)
class Primitive:
  """One convex primitive in world units; it is yawed by `yaw` (radians) about world z."""
  kind: str  # box | sphere | cylinder
  centre: tuple[float, float, float]
  # box: half extents; sphere: (r, r, r); cylinder: (radius, radius, half height)
  half_size: tuple[float, float, float]
  yaw: float

  def to_json(self) -> dict:
    return {"kind": self.kind, "centre": list(self.centre), "half_size": list(self.half_size),
            "yaw": self.yaw}


@dataclasses.dataclass(frozen=True)
class Material:
  """Linear-light surface parameters; colours are sRGB 0..255 tuples converted when rendering."""
  rgb: tuple[int, int, int]
  rgb2: tuple[int, int, int]  # second texture colour
  texture: str = "plain"
  texture_scale: float = 1.0  # texture frequency (1 / world units)
  texture_dir: tuple[float, float, float] = (1.0, 0.0, 0.0)
  diffuse: float = 1.0  # multiplies the albedo
  specular: float = 0.04  # highlight strength
  specular_tint: float = 0.0  # 0: white highlight; 1: tinted by the colour (metal)
  shininess: float = 10.0
  reflect: float = 0.0  # mirror bounce strength, tinted by the colour


@dataclasses.dataclass(frozen=True)
class SceneObject:
  label: int  # mask label, 1..num_objects
  shape: str  # cube | sphere | cylinder | chair
  colour: str  # CLEVR colour name, or "#rrggbb"
  material_name: str  # rubber | metal | matte
  size: object  # CLEVR: "large" / "small"; chair: [width, depth, height]
  position: tuple[float, float, float]  # centre; for a chair the centre of its seat box
  yaw: float
  bounding_radius: float  # radius of the bounding circle on the ground
  parts: tuple[Primitive, ...]
  material: Material
  leg_material: Optional[Material] = None  # chairs: legs are plain

  def to_json(self) -> dict:
    d = {"label": self.label, "shape": self.shape, "colour": self.colour,
         "rgb": list(self.material.rgb), "material": self.material_name, "size": self.size,
         "position": list(self.position), "yaw": self.yaw,
         "bounding_radius": self.bounding_radius, "texture": self.material.texture,
         "parts": [p.to_json() for p in self.parts]}
    if self.shape in CLEVR_SHAPES:
      # The primitive's own half-size: CLEVR_SIZES[size] times the set's object_scale.
      d["radius"] = self.parts[0].half_size[0]
    return d


@dataclasses.dataclass(frozen=True)
class Light:
  direction: tuple[float, float, float]  # unit vector towards the light (directional light)
  intensity: tuple[float, float, float]  # linear RGB


@dataclasses.dataclass(frozen=True)
class SceneSpec:
  family: str
  objects: tuple[SceneObject, ...]
  lights: tuple[Light, ...]
  ambient: tuple[float, float, float]
  floor: Material
  walls: Optional[tuple[Material, ...]]  # 4 walls (+x, −x, +y, −y) for the room family, else None


@dataclasses.dataclass(frozen=True)
class CameraSpec:
  azimuth_deg: float
  elevation_deg: float
  radius: float

  def to_json(self) -> dict:
    return dataclasses.asdict(self)


# =============================================================================================
# Cameras
# =============================================================================================


def look_at_cam_to_world(eye: np.ndarray, target: np.ndarray = np.zeros(3)) -> np.ndarray:
  """OpenCV cam2world [4, 4] (x right, y down, z forward) looking from `eye` at `target`, z up."""
  forward = target - eye
  forward = forward / np.linalg.norm(forward)
  right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
  right = right / np.linalg.norm(right)
  down = np.cross(forward, right)
  m = np.eye(4)
  m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, forward, eye
  return m


def uorf_intrinsics(image_size: int) -> np.ndarray:
  """[3, 3] pixel-unit K with pixel centres at integer coordinates (cx = (W − 1)/2)."""
  h = w = image_size
  return np.array([[FOCAL_X_PER_WIDTH * w, 0.0, (w - 1) / 2.0],
                   [0.0, FOCAL_Y_PER_HEIGHT * h, (h - 1) / 2.0],
                   [0.0, 0.0, 1.0]])


def normalised_intrinsics(k: np.ndarray, image_size: int) -> np.ndarray:
  """uOCF `_intrinsics.txt` convention (docs/method.md §3.3): f' = f/W, c' = 2c/W − 1."""
  h = w = image_size
  return np.array([[k[0, 0] / w, 0.0, 2.0 * k[0, 2] / w - 1.0],
                   [0.0, k[1, 1] / h, 2.0 * k[1, 2] / h - 1.0],
                   [0.0, 0.0, 1.0]])


def sample_cameras(rng: np.random.Generator, num_views: int) -> list[CameraSpec]:
  """Random azimuths around the origin at radius ≈ 12.4 and elevation ≈ 40° (view 0 = source)."""
  cams = []
  for _ in range(num_views):
    cams.append(CameraSpec(
        azimuth_deg=float(rng.uniform(0.0, 360.0)),
        elevation_deg=float(CAMERA_ELEVATION_DEG +
                            rng.uniform(-1, 1) * CAMERA_ELEVATION_JITTER_DEG),
        radius=float(CAMERA_RADIUS + rng.uniform(-1, 1) * CAMERA_RADIUS_JITTER)))
  return cams


def camera_to_world(cam: CameraSpec) -> np.ndarray:
  az, el = math.radians(cam.azimuth_deg), math.radians(cam.elevation_deg)
  eye = cam.radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                               math.sin(el)])
  return look_at_cam_to_world(eye)


# =============================================================================================
# Scene sampling
# =============================================================================================


def _place(rng: np.random.Generator, radii: Sequence[float], xy_range,
           max_tries: int = 200) -> Optional[np.ndarray]:
  """Rejection-samples ground positions [n, 2] whose bounding circles keep MIN_GAP apart.

  `xy_range`: one half-width for all objects, or one per object (scaled CLEVR objects).
  """
  ranges = [xy_range] * len(radii) if np.isscalar(xy_range) else list(xy_range)
  placed: list[np.ndarray] = []
  for i, r in enumerate(radii):
    for _ in range(max_tries):
      xy = rng.uniform(-ranges[i], ranges[i], size=2)
      if all(np.linalg.norm(xy - placed[j]) >= r + radii[j] + MIN_GAP for j in range(i)):
        placed.append(xy)
        break
    else:
      return None
  return np.stack(placed)


def _default_lights(rng: np.random.Generator) -> tuple[Light, ...]:
  """Key, fill and back light (directional, all casting shadows), fixed in the world per scene."""

  def direction(azimuth_deg, elevation_deg):
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))

  key_az = float(rng.uniform(0.0, 360.0))
  key = Light(direction(key_az, rng.uniform(45.0, 65.0)), (1.05, 1.0, 0.95))
  fill = Light(direction(key_az + 180.0 + rng.uniform(-30.0, 30.0), rng.uniform(25.0, 40.0)),
               (0.28, 0.29, 0.32))
  back = Light(direction(key_az + 90.0 + rng.uniform(-30.0, 30.0), rng.uniform(50.0, 70.0)),
               (0.3, 0.3, 0.3))
  return key, fill, back


def object_count_range(family: str, min_objects: int = 0, max_objects: int = 0) -> tuple[int, int]:
  """(lo, hi) objects per scene; 0 stands for the family's default bound (CLEVR 5–7, room 1–4)."""
  default = CLEVR_NUM_OBJECTS if family == "clevr" else ROOM_NUM_CHAIRS
  lo, hi = min_objects or default[0], max_objects or default[1]
  return lo, hi


class ObjectOptionError(ValueError):
  """A bad min_objects / max_objects / object_scale; `field` names it (the CLI prints its flag)."""

  def __init__(self, field: str, message: str):
    super().__init__(message)
    self.field = field


def check_object_options(family: str, min_objects: int = 0, max_objects: int = 0,
                         object_scale: float = 1.0) -> None:
  """ObjectOptionError (a ValueError) naming the offending field unless the options describe a
  set this generator can draw."""
  if family not in FAMILIES:
    raise ValueError(f"unknown family {family!r}; choose one of {FAMILIES}")
  for name, v in (("min_objects", min_objects), ("max_objects", max_objects)):
    if v < 0 or v > MAX_OBJECTS[family]:
      raise ObjectOptionError(name, f"{name} must lie in 0..{MAX_OBJECTS[family]} for the {family} "
                                    f"family (0: the family's default), got {v}")
  lo, hi = object_count_range(family, min_objects, max_objects)
  if lo > hi:
    raise ObjectOptionError("min_objects", f"min_objects ({lo}) must not exceed max_objects ({hi}) "
                                           f"(0 stands for the {family} default "
                                           f"{object_count_range(family)})")
  if family != "clevr" and object_scale != 1.0:
    raise ObjectOptionError("object_scale", f"object_scale applies to the clevr family only (the "
                                            f"{family} family's objects have their own size "
                                            f"ranges), got {object_scale}")
  if not 0.0 < object_scale <= MAX_OBJECT_SCALE:
    raise ObjectOptionError("object_scale", f"object_scale must lie in (0, {MAX_OBJECT_SCALE}] "
                                            f"(larger objects no longer fit the default scene "
                                            f"footprint), got {object_scale}")


def sample_clevr_layout(rng: np.random.Generator, *, min_objects: int = 0, max_objects: int = 0,
                        object_scale: float = 1.0) -> SceneSpec:
  """5–7 CLEVR objects on the ground plane, no interpenetration (docs/method.md §3.5).

  `min_objects`, `max_objects` (0: 5 and 7) and `object_scale` (multiplies every size) give easier
  sets; with the defaults the random draws are exactly those of the default set.
  """
  check_object_options("clevr", min_objects, max_objects, object_scale)
  lo, hi = object_count_range("clevr", min_objects, max_objects)
  for _ in range(MAX_LAYOUT_DRAWS):
    n = int(rng.integers(lo, hi + 1))
    shapes = [CLEVR_SHAPES[i] for i in rng.integers(0, len(CLEVR_SHAPES), size=n)]
    sizes = [list(CLEVR_SIZES)[i] for i in rng.integers(0, len(CLEVR_SIZES), size=n)]
    colours = [list(CLEVR_COLOURS)[i] for i in rng.integers(0, len(CLEVR_COLOURS), size=n)]
    materials = [CLEVR_MATERIALS[i] for i in rng.integers(0, len(CLEVR_MATERIALS), size=n)]
    yaws = rng.uniform(0.0, 2 * math.pi, size=n)
    # A cube's bounding circle is its diagonal half-length; spheres and cylinders have radius r.
    radii = [CLEVR_SIZES[s] * object_scale * (math.sqrt(2.0) if sh == "cube" else 1.0)
             for sh, s in zip(shapes, sizes)]
    # Objects no larger than the default ones use the default range (so the default draws are
    # unchanged); larger ones are pulled in to keep their circle inside CLEVR_FOOTPRINT.
    ranges = [CLEVR_XY_RANGE if r <= CLEVR_MAX_BOUNDING_RADIUS else CLEVR_FOOTPRINT - r
              for r in radii]
    xy = _place(rng, radii, ranges)
    if xy is not None:
      break
  else:
    raise RuntimeError(f"no layout of {lo}–{hi} CLEVR objects at object_scale {object_scale} "
                       f"fits after {MAX_LAYOUT_DRAWS} draws; use fewer or smaller objects")
  objects = []
  for i in range(n):
    r = CLEVR_SIZES[sizes[i]] * object_scale
    yaw = float(yaws[i]) if shapes[i] != "sphere" else 0.0
    centre = (float(xy[i, 0]), float(xy[i, 1]), r)  # resting on z = 0
    kind = {"cube": "box", "sphere": "sphere", "cylinder": "cylinder"}[shapes[i]]
    rgb = CLEVR_COLOURS[colours[i]]
    if materials[i] == "metal":
      material = Material(rgb=rgb, rgb2=rgb, diffuse=0.3, specular=1.0, specular_tint=0.8,
                          shininess=90.0, reflect=0.55)
    else:
      material = Material(rgb=rgb, rgb2=rgb, diffuse=1.0, specular=0.05, shininess=8.0)
    objects.append(SceneObject(
        label=i + 1, shape=shapes[i], colour=colours[i], material_name=materials[i],
        size=sizes[i], position=centre, yaw=yaw, bounding_radius=radii[i],
        parts=(Primitive(kind, centre, (r, r, r), yaw),), material=material))
  ground = Material(rgb=(160, 160, 158), rgb2=(160, 160, 158), specular=0.03, shininess=6.0)
  return SceneSpec(family="clevr", objects=tuple(objects), lights=_default_lights(rng),
                   ambient=(0.16, 0.16, 0.17), floor=ground, walls=None)


def _random_rgb(rng: np.random.Generator, value_range=(0.3, 0.9),
                saturation_range=(0.25, 0.9)) -> tuple[int, int, int]:
  h, s, v = rng.uniform(0, 1), rng.uniform(*saturation_range), rng.uniform(*value_range)
  return tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(h, s, v))


def _chair(rng: np.random.Generator, label: int, xy: np.ndarray, yaw: float,
           dims: dict) -> SceneObject:
  """A chair of six boxes in its own frame (x width, y depth with the back at −y, z up)."""
  w, d, seat_top = dims["seat_width"], dims["seat_depth"], dims["seat_height"]
  seat_t, leg_t, back_t, back_h = (dims["seat_thickness"], dims["leg_thickness"],
                                   dims["back_thickness"], dims["back_height"])
  inset = dims["leg_inset"]
  c, s = math.cos(yaw), math.sin(yaw)

  def world(local):  # chair-local → world
    return (float(xy[0] + c * local[0] - s * local[1]), float(xy[1] + s * local[0] + c * local[1]),
            float(local[2]))

  seat_z = seat_top - seat_t / 2
  parts = [Primitive("box", world((0.0, 0.0, seat_z)), (w / 2, d / 2, seat_t / 2), yaw),
           Primitive("box", world((0.0, -d / 2 + back_t / 2, seat_top + back_h / 2)),
                     (w / 2, back_t / 2, back_h / 2), yaw)]
  leg_h = seat_top - seat_t
  for sx in (-1, 1):
    for sy in (-1, 1):
      lx = sx * (w / 2 - inset - leg_t / 2)
      ly = sy * (d / 2 - inset - leg_t / 2)
      parts.append(Primitive("box", world((lx, ly, leg_h / 2)), (leg_t / 2, leg_t / 2, leg_h / 2),
                             yaw))
  rgb = _random_rgb(rng)
  texture = ROOM_TEXTURES[int(rng.integers(0, len(ROOM_TEXTURES)))]
  rgb2 = _random_rgb(rng) if rng.uniform() < 0.5 else tuple(int(v * 0.45) for v in rgb)
  theta = rng.uniform(0, math.pi)
  tex_dir = (math.cos(theta), math.sin(theta), float(rng.uniform(-0.5, 0.5)))
  norm = math.sqrt(sum(v * v for v in tex_dir))
  material = Material(rgb=rgb, rgb2=rgb2, texture=texture,
                      texture_scale=float(rng.uniform(2.0, 5.0)),
                      texture_dir=tuple(v / norm for v in tex_dir), specular=0.12, shininess=24.0)
  leg_rgb = _random_rgb(rng, (0.15, 0.55)) if rng.uniform() < 0.5 else tuple(
      int(v * 0.6) for v in rgb)
  leg_material = Material(rgb=leg_rgb, rgb2=leg_rgb, specular=0.2, shininess=30.0)
  radius = math.hypot(w / 2, d / 2)
  return SceneObject(
      label=label, shape="chair", colour="#%02x%02x%02x" % rgb, material_name="matte",
      size=[w, d, seat_top + back_h], position=parts[0].centre, yaw=yaw, bounding_radius=radius,
      parts=tuple(parts), material=material, leg_material=leg_material)


def sample_room_layout(rng: np.random.Generator, *, min_objects: int = 0,
                       max_objects: int = 0) -> SceneSpec:
  """1–4 primitive chairs on a textured floor inside four walls (docs/method.md §3.5).

  `min_objects`, `max_objects` (0: 1 and 4) narrow the chair count; the defaults draw as before.
  """
  check_object_options("room", min_objects, max_objects)
  lo, hi = object_count_range("room", min_objects, max_objects)
  while True:
    n = int(rng.integers(lo, hi + 1))
    dims = [{"seat_width": rng.uniform(1.3, 2.0), "seat_depth": rng.uniform(1.3, 2.0),
             "seat_height": rng.uniform(1.1, 1.7), "seat_thickness": rng.uniform(0.12, 0.25),
             "leg_thickness": rng.uniform(0.1, 0.2), "back_thickness": rng.uniform(0.1, 0.2),
             "back_height": rng.uniform(1.0, 1.8), "leg_inset": rng.uniform(0.0, 0.12)}
            for _ in range(n)]
    dims = [{k: float(v) for k, v in dd.items()} for dd in dims]
    radii = [math.hypot(dd["seat_width"] / 2, dd["seat_depth"] / 2) for dd in dims]
    xy = _place(rng, radii, ROOM_XY_RANGE)
    if xy is not None:
      break
  yaws = rng.uniform(0.0, 2 * math.pi, size=n)
  objects = tuple(_chair(rng, i + 1, xy[i], float(yaws[i]), dims[i]) for i in range(n))
  if rng.uniform() < 0.5:
    base = WOOD_COLOURS[int(rng.integers(0, len(WOOD_COLOURS)))]
    base = tuple(int(np.clip(v + rng.integers(-12, 13), 0, 255)) for v in base)
    floor = Material(rgb=base, rgb2=tuple(int(v * 0.6) for v in base), texture="wood",
                     texture_scale=float(rng.uniform(1.2, 2.2)),
                     texture_dir=(1.0, 0.0, 0.0) if rng.uniform() < 0.5 else (0.0, 1.0, 0.0),
                     specular=0.08, shininess=20.0)
  else:
    a = _random_rgb(rng, (0.6, 0.9), (0.0, 0.35))
    b = _random_rgb(rng, (0.3, 0.6), (0.0, 0.45))
    floor = Material(rgb=a, rgb2=b, texture="tiles", texture_scale=float(rng.uniform(0.5, 1.0)),
                     specular=0.1, shininess=30.0)
  wall_rgb = _random_rgb(rng, (0.6, 0.9), (0.05, 0.4))
  wall_rgb2 = tuple(int(v * 0.85) for v in wall_rgb)
  wall_texture = "stripes" if rng.uniform() < 0.5 else "plain"
  walls = tuple(Material(rgb=wall_rgb, rgb2=wall_rgb2, texture=wall_texture, texture_scale=1.5,
                         texture_dir=dir_, specular=0.0)
                for dir_ in ((0.0, 1.0, 0.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0), (1.0, 0.0, 0.0)))
  return SceneSpec(family="room", objects=objects, lights=_default_lights(rng),
                   ambient=(0.2, 0.2, 0.21), floor=floor, walls=walls)


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


def render_options(family: str, supersample: int = 2) -> RenderOptions:
  if family == "clevr":
    return RenderOptions(supersample=supersample, reflections=True, textures=False, walls=False,
                         quadrics=True)
  return RenderOptions(supersample=supersample, reflections=False, textures=True, walls=True,
                       quadrics=False)


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
  h = w = image_size
  v, u = jnp.meshgrid(jnp.arange(h, dtype=jnp.float32), jnp.arange(w, dtype=jnp.float32),
                      indexing="ij")
  pu = u[:, :, None] + offsets[:, 0]  # [H, W, A]
  pv = v[:, :, None] + offsets[:, 1]
  d_cam = jnp.stack([(pu - intrinsics[0, 2]) / intrinsics[0, 0],
                     (pv - intrinsics[1, 2]) / intrinsics[1, 1], jnp.ones_like(pu)], axis=-1)
  dirs = jnp.einsum("nij,hwaj->nhwai", cam_to_world[:, :3, :3], d_cam)  # [N, H, W, A, 3]
  origins = jnp.broadcast_to(cam_to_world[:, None, None, None, :3, 3], dirs.shape)
  return origins, dirs


def supersample_offsets(supersample: int) -> np.ndarray:
  """[A, 2] sub-pixel offsets of a regular supersample×supersample grid inside the pixel."""
  g = (np.arange(supersample) + 0.5) / supersample - 0.5
  du, dv = np.meshgrid(g, g, indexing="xy")
  return np.stack([du.ravel(), dv.ravel()], axis=-1).astype(np.float32)


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
                              offsets=jnp.asarray(supersample_offsets(supersample)))
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


# =============================================================================================
# One scene: sample, check visibility in the source view, render
# =============================================================================================


@dataclasses.dataclass(frozen=True)
class GeneratedScene:
  spec: SceneSpec
  cameras: tuple[CameraSpec, ...]
  cam_to_world: np.ndarray  # [N, 4, 4] float64, world units
  intrinsics: np.ndarray  # [3, 3] float64, pixels
  rgb: np.ndarray  # [N, H, W, 3] uint8
  label: np.ndarray  # [N, H, W] int32
  depth: np.ndarray  # [N, H, W] float32
  attempts: int  # layouts drawn before every object was visible in the source view


def scene_rng(*, seed: int, family: str, split: str, index: int) -> np.random.Generator:
  """Independent stream per (seed, family, split, scene index): order of workers cannot matter."""
  return np.random.default_rng(
      np.random.SeedSequence([seed, FAMILIES.index(family), SPLITS.index(split), index]))


def generate_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
                   supersample: int = 2, max_attempts: int = 100, min_objects: int = 0,
                   max_objects: int = 0, object_scale: float = 1.0) -> GeneratedScene:
  """Samples layouts and cameras until every object covers enough pixels of view 0, then renders.

  `min_objects`, `max_objects` (0: the family's default count) and `object_scale` (CLEVR only)
  select an easier set; see `sample_clevr_layout`.

  Always renders on the CPU backend, so the files do not depend on the accelerator (if any) of the
  calling process, and a training process never shares its accelerator memory with the generator.
  """
  with jax.default_device(jax.local_devices(backend="cpu")[0]):
    return _generate_scene(rng, family=family, views=views, image_size=image_size,
                           supersample=supersample, max_attempts=max_attempts,
                           min_objects=min_objects, max_objects=max_objects,
                           object_scale=object_scale)


def _generate_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
                    supersample: int, max_attempts: int, min_objects: int, max_objects: int,
                    object_scale: float) -> GeneratedScene:
  check_object_options(family, min_objects, max_objects, object_scale)
  options = render_options(family, supersample)
  k = uorf_intrinsics(image_size)
  k32 = jnp.asarray(k, jnp.float32)
  threshold = min_visible_pixels(image_size)
  for attempt in range(1, max_attempts + 1):
    if family == "clevr":
      spec = sample_clevr_layout(rng, min_objects=min_objects, max_objects=max_objects,
                                 object_scale=object_scale)
    else:
      spec = sample_room_layout(rng, min_objects=min_objects, max_objects=max_objects)
    cameras = tuple(sample_cameras(rng, views))
    c2w = np.stack([camera_to_world(c) for c in cameras])
    arrays = scene_arrays(spec)
    # All N views, although only view 0 is checked: the same shape as render_views' centre pass,
    # so nothing extra is compiled.
    labels, _ = render_centre(arrays, cam_to_world=jnp.asarray(c2w, jnp.float32),
                              intrinsics=k32, image_size=image_size, options=options)
    counts = np.bincount(np.asarray(labels[0]).ravel(), minlength=len(spec.objects) + 1)
    if np.all(counts[1:len(spec.objects) + 1] >= threshold):
      break
  else:
    raise RuntimeError(f"no {family} layout with every object visible after {max_attempts} tries")
  out = render_views(arrays, cam_to_world=jnp.asarray(c2w, jnp.float32), intrinsics=k32,
                     image_size=image_size, options=options)
  rgb = np.asarray(out.rgb, np.float32)
  return GeneratedScene(
      spec=spec, cameras=cameras, cam_to_world=c2w, intrinsics=k,
      rgb=np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8),
      label=np.asarray(out.label, np.int32), depth=np.asarray(out.depth, np.float32),
      attempts=attempt)


# =============================================================================================
# Writing a data set (uORF folder format, docs/method.md §3.2 / §3.3)
# =============================================================================================

PNG_COMPRESS_LEVEL = 6  # fixed so files are byte-identical between runs


def _save_png(path: str, array: np.ndarray) -> None:
  Image.fromarray(array, "RGB").save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def mask_to_grey_rgb(label: np.ndarray) -> np.ndarray:
  """[H, W] labels → [H, W, 3] uint8 grey (17·l, 17·l, 17·l)."""
  grey = (label.astype(np.int32) * LABEL_GREY_STEP).astype(np.uint8)
  return np.repeat(grey[..., None], 3, axis=-1)


def view_stem(*, image_index: int, scene_index: int, view: int) -> str:
  return f"{image_index:05d}_sc{scene_index:04d}_az{view:02d}"


@dataclasses.dataclass(frozen=True)
class _SceneTask:
  family: str
  split: str
  index: int  # within the split (seeds the scene)
  global_index: int  # SSSS in the file names
  views: int
  image_size: int
  seed: int
  supersample: int
  folder: str
  min_objects: int = 0
  max_objects: int = 0
  object_scale: float = 1.0


def _write_scene(task: _SceneTask) -> dict:
  """Renders one scene and writes its files; returns its dataset.json entry."""
  rng = scene_rng(seed=task.seed, family=task.family, split=task.split, index=task.index)
  scene = generate_scene(rng, family=task.family, views=task.views, image_size=task.image_size,
                         supersample=task.supersample, min_objects=task.min_objects,
                         max_objects=task.max_objects, object_scale=task.object_scale)
  k_norm = normalised_intrinsics(scene.intrinsics, task.image_size)
  stems = []
  for a in range(task.views):
    stem = view_stem(image_index=task.index * task.views + a, scene_index=task.global_index,
                     view=a)
    base = os.path.join(task.folder, stem)
    _save_png(base + ".png", scene.rgb[a])
    _save_png(base + "_mask.png", mask_to_grey_rgb(scene.label[a]))
    # "+ 0.0" turns −0.0 into 0.0 so the text never shows "-0.0000000000".
    np.savetxt(base + "_RT.txt", scene.cam_to_world[a] + 0.0, fmt="%.10f")
    np.savetxt(base + "_intrinsics.txt", k_norm + 0.0, fmt="%.10f")
    np.save(base + "_depth.npy", scene.depth[a])
    stems.append(stem)
  return {"name": f"sc{task.global_index:04d}", "index": task.index, "views": stems,
          "objects": [o.to_json() for o in scene.spec.objects],
          "cameras": [c.to_json() for c in scene.cameras],
          "lights": [dataclasses.asdict(l) for l in scene.spec.lights],
          "layout_attempts": scene.attempts}


def _worker_init() -> None:
  # Workers render on the CPU only (no accelerator start-up or memory reservation per worker), with
  # one XLA thread each: the pool already uses every core.
  os.environ["JAX_PLATFORMS"] = "cpu"
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                             " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")


def is_default_objects(family: str, min_objects: int = 0, max_objects: int = 0,
                       object_scale: float = 1.0) -> bool:
  """True when the options draw the family's default set (explicit 5 and 7 count as default)."""
  return (object_count_range(family, min_objects, max_objects) == object_count_range(family)
          and object_scale == 1.0)


def _split_header(*, family: str, split: str, seed: int, views: int, image_size: int,
                  num_scenes: int, supersample: int, min_objects: int = 0, max_objects: int = 0,
                  object_scale: float = 1.0) -> dict:
  k = uorf_intrinsics(image_size)
  header = {
      "format": "slotlifter_jax.generated", "generator_version": GENERATOR_VERSION,
      "family": family, "subset": SUBSETS[family], "split": split, "seed": seed,
      "num_scenes": num_scenes, "image_size": [image_size, image_size], "views_per_scene": views,
      "num_source_views": num_source_views_for(views), "scene_scale": SCENE_SCALE,
      "supersample": supersample,
      "camera": {"convention": "opencv_cam2world", "world_up": "z", "units": "world",
                 "look_at": [0.0, 0.0, 0.0], "radius": CAMERA_RADIUS,
                 "radius_jitter": CAMERA_RADIUS_JITTER, "elevation_deg": CAMERA_ELEVATION_DEG,
                 "elevation_jitter_deg": CAMERA_ELEVATION_JITTER_DEG, "azimuth": "uniform",
                 "intrinsics_pixels": {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2],
                                       "cy": k[1, 2], "width": image_size,
                                       "height": image_size}},
      "background": {"floor_z": 0.0,
                     "wall_half_size": ROOM_HALF_SIZE if family == "room" else None},
      "depth": {"kind": "camera_z", "units": "world", "dtype": "float32",
                "sample": "pixel centre", "no_hit": 0.0},
      "mask": {"background_label": BACKGROUND_LABEL, "max_objects": MAX_OBJECTS[family],
               "label_grey_levels": label_grey_levels(MAX_OBJECTS[family]),
               "encoding": "RGB PNG, label l drawn as (g, g, g) with g = label_grey_levels[l]",
               "sample": "pixel centre", "views": "all"},
  }
  # Only non-default sets record their object options, so default dataset.json files are unchanged
  # (and _existing_split_matches tells the two apart by the key's presence).
  if not is_default_objects(family, min_objects, max_objects, object_scale):
    lo, hi = object_count_range(family, min_objects, max_objects)
    header["objects"] = {"min_objects": lo, "max_objects": hi,
                         "object_scale": float(object_scale)}
  return header


def _existing_split_matches(path: str, header: dict) -> bool:
  try:
    with open(os.path.join(path, "dataset.json")) as f:
      old = json.load(f)
  except (OSError, ValueError):
    return False
  # The same keys too: a set with object options must not pass for a default one, or vice versa.
  header = json.loads(json.dumps(header))
  return set(old) - {"scenes"} == set(header) and all(old.get(k) == v for k, v in header.items())


def generate_dataset(out_dir: str, *, family: str, num_train: int, num_val: int, num_test: int,
                     views: int = 4, image_size: int = 128, seed: int = 0,
                     num_workers: Optional[int] = None, progress: bool = True,
                     overwrite: bool = False, supersample: int = 2, min_objects: int = 0,
                     max_objects: int = 0, object_scale: float = 1.0) -> dict:
  """Writes <out_dir>/<subset>_{train,val,test} and returns a summary (seconds per split).

  `min_objects`, `max_objects` (0: the family's default count) and `object_scale` (CLEVR only)
  select an easier set (`sample_clevr_layout`); its dataset.json headers record them under
  "objects", and each scene's entry lists its objects. The folder names stay the family's.

  A split whose folder already holds a dataset.json with the same generation parameters is kept
  as it is (this resumes an interrupted run); any other non-empty split folder is an error unless
  `overwrite`. Each split is written to a temporary sibling folder and renamed into place only
  when complete. Scene s of a split is seeded by (seed, family, split, s), so the files do not
  depend on `num_workers`; SSSS in the file names counts scenes over train, val, test in turn.
  """
  from tqdm import tqdm

  if family not in FAMILIES:
    raise ValueError(f"unknown family {family!r}; choose one of {FAMILIES}")
  if views < 1 or image_size < 8:
    raise ValueError(f"need views ≥ 1 and image_size ≥ 8, got {views}, {image_size}")
  check_object_options(family, min_objects, max_objects, object_scale)
  objects = dict(min_objects=min_objects, max_objects=max_objects, object_scale=object_scale)
  subset = SUBSETS[family]
  counts = {"train": num_train, "val": num_val, "test": num_test}
  headers = {s: _split_header(family=family, split=s, seed=seed, views=views,
                              image_size=image_size, num_scenes=n, supersample=supersample,
                              **objects)
             for s, n in counts.items()}
  paths = {s: os.path.join(out_dir, f"{subset}_{s}") for s in SPLITS}
  todo = []
  for s in SPLITS:
    p = paths[s]
    if os.path.isdir(p) and os.listdir(p) and not overwrite:
      if _existing_split_matches(p, headers[s]):
        continue
      raise FileExistsError(f"{p} exists and is not empty (and was generated with other "
                            f"parameters); pass overwrite=True / --overwrite to replace it")
    todo.append(s)
  os.makedirs(out_dir, exist_ok=True)
  if num_workers is None:
    num_workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
  total = sum(counts[s] for s in todo)
  num_workers = max(1, min(num_workers, total))
  pool = None
  if num_workers > 1:
    # spawn, not fork: the parent may already hold an initialised XLA runtime.
    pool = multiprocessing.get_context("spawn").Pool(num_workers, initializer=_worker_init)
  summary = {"out_dir": out_dir, "family": family, "subset": subset, "num_workers": num_workers,
             "splits": {}}
  start_all = time.perf_counter()
  try:
    offsets = {"train": 0, "val": num_train, "test": num_train + num_val}
    for s in SPLITS:
      if s not in todo:
        summary["splits"][s] = {"path": paths[s], "num_scenes": counts[s], "seconds": 0.0,
                                "kept_existing": True}
        continue
      start = time.perf_counter()
      tmp = paths[s] + ".partial"
      if os.path.exists(tmp):
        shutil.rmtree(tmp)  # left by an interrupted run
      os.makedirs(tmp)
      tasks = [_SceneTask(family=family, split=s, index=i, global_index=offsets[s] + i,
                          views=views, image_size=image_size, seed=seed,
                          supersample=supersample, folder=tmp, **objects)
               for i in range(counts[s])]
      results = pool.imap(_write_scene, tasks, chunksize=2) if pool else map(_write_scene, tasks)
      scenes = list(tqdm(results, total=len(tasks), desc=f"{subset}_{s}", unit="scene",
                         disable=not progress, dynamic_ncols=True))
      dataset = dict(headers[s], scenes=scenes)
      with open(os.path.join(tmp, "dataset.json"), "w") as f:
        json.dump(dataset, f, sort_keys=True, indent=1)
        f.write("\n")
      if os.path.exists(paths[s]):
        shutil.rmtree(paths[s])  # empty, or overwrite was asked for
      os.rename(tmp, paths[s])
      seconds = time.perf_counter() - start
      summary["splits"][s] = {"path": paths[s], "num_scenes": counts[s],
                              "num_images": counts[s] * views, "seconds": seconds,
                              "scenes_per_second": counts[s] / seconds if seconds > 0 else 0.0}
  except BaseException:
    if pool is not None:
      pool.terminate()  # an interrupted run stops its workers; the .partial folder is not renamed
    raise
  finally:
    if pool is not None:
      pool.close()
      pool.join()
  summary["seconds"] = time.perf_counter() - start_all
  return summary
