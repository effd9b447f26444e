"""Scenes and cameras of the embedded data set (docs/method.md §3.5): what a scene holds and where
it is seen from, as NumPy and frozen dataclasses.

This is the generator's description layer, kept free of JAX so that code needing only the set's
conventions (folder names, object options and their checks, the camera rig, the version that keys
the data cache) can import it without loading the renderer: `embedded.py` reads SUBSETS from it at
import time. The ray caster (`raycaster.py`, `shading.py`) turns a SceneSpec into pixels and the
writer (`writer.py`) draws scenes and stores them; both build on this module, never the reverse.
Camera math shared with the data readers (uORF intrinsics, look-at poses) lives in `cameras.py`.

A scene is a list of objects; every object is made of convex primitives (CLEVR: one cube, sphere or
cylinder; room: a chair of six boxes), each yawed about world z. World units are the uORF ones
(camera radius ≈ 12.4); readers apply the 1/7 scene scale (docs/method.md §3.1).
"""

from __future__ import annotations

import colorsys
import dataclasses
import math
from typing import Optional, Sequence

import numpy as np

from slotlifter_jax.data import cameras
from slotlifter_jax.data.cameras import look_at_cam_to_world

GENERATOR_VERSION = 1
FAMILIES = ("clevr", "room")
SUBSETS = {"clevr": "clevr_567", "room": "room_chair"}  # uORF folder prefixes (docs/method.md §3.2)
# "dev" holds the scenes that were the set's test split before a held-out one existed, from the
# same seed stream, so its files are byte for byte the former test split's. Recipe choices were
# made by reading those scenes, so they only serve development. "test" is held out: drawn from a
# seed stream that no run, probe or choice has used, and opened only by evaluation.
SPLITS = ("train", "val", "dev", "test")
SPLIT_STREAMS = {"train": 0, "val": 1, "dev": 2, "test": 3}  # the SeedSequence entry of a split
SCENE_SCALE = 1.0 / 7.0  # uORF "nss_scale": readers scale world units by it (docs/method.md §3.1)

# ---- cameras (docs/method.md §3.1, §3.5) ----
CAMERA_RADIUS = 12.4
CAMERA_RADIUS_JITTER = 0.2
CAMERA_ELEVATION_DEG = 40.0
CAMERA_ELEVATION_JITTER_DEG = 2.0
# uORF intrinsics: a 4:3 camera squeezed to a square, fx = 1.09375·W and fy = fx·4/3 = 1.458333·H
# (one definition, cameras.UORF_FOCAL_RATIO, shared with the readers).
FOCAL_X_PER_WIDTH, FOCAL_Y_PER_HEIGHT = cameras.UORF_FOCAL_RATIO

# ---- masks ----
BACKGROUND_LABEL = 0
# Label l is drawn as grey (17·l, 17·l, 17·l); PIL's RGB→L conversion maps it back to 17·l exactly.
LABEL_GREY_STEP = 17
MAX_OBJECTS = {"clevr": 7, "room": 4}
# The room family's object shapes, a rung of the room ladder each (docs/method.md §3.5): "chairs"
# (seat, back and four legs), "solid" (the legs and the space between them one block under the
# seat: no thin parts but the back), "boxes" (one box of the chair's footprint and full height).
# Every form makes the same random draws, so a scene differs between forms only in its shapes.
# "clevr" keeps the room (floor, walls, lights, cameras) and stands CLEVR's objects in it, drawn
# as the clevr family draws them (5–7 by default) from a stream jumped off the room's: the rung
# that tells the room's background from its objects, starting from objects that split on a plain
# floor.
ROOM_OBJECTS = ("chairs", "solid", "boxes", "clevr")
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


def uorf_intrinsics(image_size: int) -> np.ndarray:
  """[3, 3] pixel-unit K with pixel centres at integer coordinates (cx = (W − 1)/2): the square
  uORF camera of `cameras.uorf_intrinsics`."""
  return cameras.uorf_intrinsics(height=image_size, width=image_size)


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


def object_family(family: str, room_objects: str = "chairs") -> str:
  """The family whose objects a scene draws: "clevr" for rooms holding CLEVR's objects."""
  return "clevr" if family == "room" and room_objects == "clevr" else family


def object_count_range(family: str, min_objects: int = 0, max_objects: int = 0,
                       room_objects: str = "chairs") -> tuple[int, int]:
  """(lo, hi) objects per scene; 0 stands for the family's default bound (CLEVR 5–7, room 1–4)."""
  default = CLEVR_NUM_OBJECTS if object_family(family, room_objects) == "clevr" else ROOM_NUM_CHAIRS
  lo, hi = min_objects or default[0], max_objects or default[1]
  return lo, hi


class ObjectOptionError(ValueError):
  """A bad min_objects / max_objects / object_scale; `field` names it (the CLI prints its flag)."""

  def __init__(self, field: str, message: str):
    super().__init__(message)
    self.field = field


def check_object_options(family: str, min_objects: int = 0, max_objects: int = 0,
                         object_scale: float = 1.0, plain_background: bool = False,
                         plain_objects: bool = False, no_walls: bool = False,
                         room_objects: str = "chairs", grey_floor: bool = False) -> None:
  """ObjectOptionError (a ValueError) naming the offending field unless the options describe a
  set this generator can draw."""
  if family not in FAMILIES:
    raise ValueError(f"unknown family {family!r}; choose one of {FAMILIES}")
  if room_objects not in ROOM_OBJECTS:
    raise ObjectOptionError("room_objects", f"room_objects must be one of {ROOM_OBJECTS}, got "
                                            f"{room_objects!r}")
  objects = object_family(family, room_objects)
  for name, v in (("min_objects", min_objects), ("max_objects", max_objects)):
    if v < 0 or v > MAX_OBJECTS[objects]:
      raise ObjectOptionError(name, f"{name} must lie in 0..{MAX_OBJECTS[objects]} for the "
                                    f"{objects} family's objects (0: the family's default), got {v}")
  lo, hi = object_count_range(family, min_objects, max_objects, room_objects)
  if lo > hi:
    raise ObjectOptionError("min_objects", f"min_objects ({lo}) must not exceed max_objects ({hi}) "
                                           f"(0 stands for the {objects} default "
                                           f"{object_count_range(objects)})")
  if objects == "room" and object_scale > 1.0:
    raise ObjectOptionError("object_scale", f"object_scale must lie in (0, 1] for the room family "
                                            f"(its tallest chair already reaches the top of the "
                                            f"room's scene slab), got {object_scale}")
  for name, on in (("plain_background", plain_background), ("plain_objects", plain_objects),
                   ("no_walls", no_walls), ("grey_floor", grey_floor)):
    if on and family != "room":
      raise ObjectOptionError(name, f"{name} applies to the room family only (the {family} "
                                    f"set is plain already)")
  if room_objects == "clevr" and plain_objects:
    raise ObjectOptionError("plain_objects", "plain_objects has nothing to flatten in CLEVR's "
                                             "one-colour objects (room_objects=clevr)")
  if room_objects != "chairs" and family != "room":
    raise ObjectOptionError("room_objects", f"room_objects applies to the room family only, got "
                                            f"{room_objects!r} for {family}")
  if not 0.0 < object_scale <= MAX_OBJECT_SCALE:
    raise ObjectOptionError("object_scale", f"object_scale must lie in (0, {MAX_OBJECT_SCALE}] "
                                            f"(larger objects no longer fit the default scene "
                                            f"footprint), got {object_scale}")


def is_default_objects(family: str, min_objects: int = 0, max_objects: int = 0,
                       object_scale: float = 1.0, plain_background: bool = False,
                       plain_objects: bool = False, no_walls: bool = False,
                       room_objects: str = "chairs", grey_floor: bool = False) -> bool:
  """True when the options draw the family's default set (explicit 5 and 7 count as default)."""
  untouched = not (plain_background or plain_objects or no_walls or grey_floor)
  return untouched and room_objects == "chairs" and object_scale == 1.0 and (
      object_count_range(family, min_objects, max_objects) == object_count_range(family))



# The clevr family's floor, which every clevr scene shares; room scenes may borrow it (grey_floor).
CLEVR_GROUND = Material(rgb=(160, 160, 158), rgb2=(160, 160, 158), specular=0.03, shininess=6.0)


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
  return SceneSpec(family="clevr", objects=tuple(objects), lights=_default_lights(rng),
                   ambient=(0.16, 0.16, 0.17), floor=CLEVR_GROUND, walls=None)


def _random_rgb(rng: np.random.Generator, value_range=(0.3, 0.9),
                saturation_range=(0.25, 0.9)) -> tuple[int, int, int]:
  h, s, v = rng.uniform(0, 1), rng.uniform(*saturation_range), rng.uniform(*value_range)
  return tuple(int(round(255 * c)) for c in colorsys.hsv_to_rgb(h, s, v))


def _chair(rng: np.random.Generator, label: int, xy: np.ndarray, yaw: float,
           dims: dict, form: str = "chairs") -> SceneObject:
  """A chair of six boxes in its own frame (x width, y depth with the back at −y, z up), or of
  the `form` (ROOM_OBJECTS) with the same footprint and height."""
  w, d, seat_top = dims["seat_width"], dims["seat_depth"], dims["seat_height"]
  seat_t, leg_t, back_t, back_h = (dims["seat_thickness"], dims["leg_thickness"],
                                   dims["back_thickness"], dims["back_height"])
  inset = dims["leg_inset"]
  c, s = math.cos(yaw), math.sin(yaw)

  def world(local):  # chair-local → world
    return (float(xy[0] + c * local[0] - s * local[1]), float(xy[1] + s * local[0] + c * local[1]),
            float(local[2]))

  seat_z = seat_top - seat_t / 2
  back = Primitive("box", world((0.0, -d / 2 + back_t / 2, seat_top + back_h / 2)),
                   (w / 2, back_t / 2, back_h / 2), yaw)
  if form == "boxes":
    height = seat_top + back_h
    parts = [Primitive("box", world((0.0, 0.0, height / 2)), (w / 2, d / 2, height / 2), yaw)]
  elif form == "solid":
    parts = [Primitive("box", world((0.0, 0.0, seat_top / 2)), (w / 2, d / 2, seat_top / 2), yaw),
             back]
  else:
    parts = [Primitive("box", world((0.0, 0.0, seat_z)), (w / 2, d / 2, seat_t / 2), yaw), back]
    leg_h = seat_top - seat_t
    for sx in (-1, 1):
      for sy in (-1, 1):
        lx = sx * (w / 2 - inset - leg_t / 2)
        ly = sy * (d / 2 - inset - leg_t / 2)
        parts.append(Primitive("box", world((lx, ly, leg_h / 2)),
                               (leg_t / 2, leg_t / 2, leg_h / 2), yaw))
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
      size=[w, d, seat_top + back_h], position=world((0.0, 0.0, seat_z)), yaw=yaw,
      bounding_radius=radius,
      parts=tuple(parts), material=material, leg_material=leg_material)


def sample_room_layout(rng: np.random.Generator, *, min_objects: int = 0,
                       max_objects: int = 0, plain_background: bool = False,
                       plain_objects: bool = False, no_walls: bool = False,
                       room_objects: str = "chairs", object_scale: float = 1.0,
                       grey_floor: bool = False) -> SceneSpec:
  """1–4 primitive chairs on a textured floor inside four walls (docs/method.md §3.5).

  `min_objects`, `max_objects` (0: 1 and 4) narrow the chair count; the defaults draw as before.
  `plain_background`: the same scenes (every random draw is made as before) with the floor and the
  walls in their base colour, untextured: the rung that tells a texture problem from a chair one.
  `plain_objects`: likewise each chair in its one base colour, legs included. `no_walls`: the
  same scenes without walls, the floor running to the horizon as in the clevr family.
  `room_objects` (ROOM_OBJECTS): the same scenes with each chair's legs filled in ("solid") or
  each chair one box of its footprint and height ("boxes"). `object_scale` (≤ 1) multiplies every
  size the chairs are drawn with, so their heights, and with them the floor they hide from a view
  and the length of their shadows, come near CLEVR's (0.6: 0.8–1.2 wide, 1.3–2.1 tall); the
  positions keep the default range. `grey_floor`: the same scenes on the clevr family's plain grey
  floor (CLEVR_GROUND) instead of the scene's own wood or tiles, the one floor every scene shares.
  `room_objects="clevr"`: the room drawn as with chairs (its default count; every draw as before),
  holding instead CLEVR's objects as `sample_clevr_layout` draws them with `min_objects`,
  `max_objects` and `object_scale`, from a generator jumped off this one (so the room's own draws
  do not move); the CLEVR layout's lights are not used, the room's are.
  """
  check_object_options("room", min_objects, max_objects, object_scale,
                       room_objects=room_objects, grey_floor=grey_floor)
  if room_objects == "clevr":
    clevr = sample_clevr_layout(np.random.Generator(rng.bit_generator.jumped()),
                                min_objects=min_objects, max_objects=max_objects,
                                object_scale=object_scale)
    room = sample_room_layout(rng, plain_background=plain_background, no_walls=no_walls,
                              grey_floor=grey_floor)
    return dataclasses.replace(room, objects=clevr.objects)
  lo, hi = object_count_range("room", min_objects, max_objects)
  while True:
    n = int(rng.integers(lo, hi + 1))
    dims = [{"seat_width": rng.uniform(1.3, 2.0), "seat_depth": rng.uniform(1.3, 2.0),
             "seat_height": rng.uniform(1.1, 1.7), "seat_thickness": rng.uniform(0.12, 0.25),
             "leg_thickness": rng.uniform(0.1, 0.2), "back_thickness": rng.uniform(0.1, 0.2),
             "back_height": rng.uniform(1.0, 1.8), "leg_inset": rng.uniform(0.0, 0.12)}
            for _ in range(n)]
    dims = [{k: float(v) * object_scale for k, v in dd.items()} for dd in dims]
    radii = [math.hypot(dd["seat_width"] / 2, dd["seat_depth"] / 2) for dd in dims]
    xy = _place(rng, radii, ROOM_XY_RANGE)
    if xy is not None:
      break
  yaws = rng.uniform(0.0, 2 * math.pi, size=n)
  objects = tuple(_chair(rng, i + 1, xy[i], float(yaws[i]), dims[i], room_objects)
                  for i in range(n))
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
  lights = _default_lights(rng)
  if plain_background:
    floor = dataclasses.replace(floor, texture="plain", rgb2=floor.rgb)
    walls = tuple(dataclasses.replace(w, texture="plain", rgb2=w.rgb) for w in walls)
  if grey_floor:
    floor = CLEVR_GROUND
  if plain_objects:
    objects = tuple(dataclasses.replace(
        o, material=dataclasses.replace(o.material, texture="plain", rgb2=o.material.rgb),
        leg_material=dataclasses.replace(o.material, texture="plain", rgb2=o.material.rgb))
        for o in objects)
  return SceneSpec(family="room", objects=objects, lights=lights, ambient=(0.2, 0.2, 0.21),
                   floor=floor, walls=None if no_walls else walls)
