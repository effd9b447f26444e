"""Ground truth for scene edits (docs/editing.md): an embedded scene's SceneSpec re-drawn from its
seed, with one object removed or translated, rendered from the scene's own cameras.

The files of a generated split hold the images, masks, depth and cameras of every view, and in
dataset.json each scene's objects, cameras and lights, but not the SceneSpec itself (materials,
floor, ambient light). Every scene is drawn from its own random stream,
`writer.scene_rng(seed, family, split, index)`, and dataset.json records all the arguments of the
draw (seed, family, split, views, image size, supersampling, object options), so `redraw` draws
the same SceneSpec and cameras again. `render` renders a SceneSpec exactly as the writer did, so
the unedited spec gives the stored images, masks and depth byte for byte; `check_redraw` verifies
that against a loaded scene before any edit is scored.

Edits keep the layout rules the generator draws with (layout.py): a translated object's bounding
circle must stay `layout.MIN_GAP` clear of every other object's and inside the scene footprint
(`footprint_half_size`); otherwise the edit is refused with a `SceneEditError` (a ValueError)
whose one-line message names the problem. Translations are horizontal: objects rest on the floor,
and the collision rule is one of circles on the ground. Mask labels are kept: object l keeps
label l after another object is removed.

World units throughout (camera radius ≈ 12.4); the model's frame is these times data.scene_scale,
turned by data.frame (rendering/edits.py converts).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from typing import Optional, Sequence

import numpy as np

from slotlifter_jax.data import layout
from slotlifter_jax.data.layout import SceneObject, SceneSpec


class SceneEditError(ValueError):
  """An edit the ground truth cannot render; the message names the problem in one line."""


class UnknownObjectError(SceneEditError):
  """No object of the scene has the label."""


class CollisionError(SceneEditError):
  """The translated object's bounding circle would come within MIN_GAP of another's."""


class FootprintError(SceneEditError):
  """The translated object's bounding circle would leave the scene footprint."""


class RedrawError(SceneEditError):
  """A stored scene cannot be re-drawn from its dataset.json, or re-drawing does not give it."""


def footprint_half_size(family: str) -> float:
  """Half-side of the square on the ground, centred at the origin, that holds every object's
  bounding circle in the generator's layouts (world units).

  clevr: layout.CLEVR_FOOTPRINT (the largest default object placed at the edge of the placement
  range). room: the chair placement range plus the largest chair's bounding radius (seat half
  sizes up to 1.0 each, layout.sample_room_layout), well inside the walls at ±7.
  """
  if family == "clevr":
    return layout.CLEVR_FOOTPRINT
  if family == "room":
    return layout.ROOM_XY_RANGE + math.hypot(1.0, 1.0)
  raise ValueError(f"unknown family {family!r}; choose one of {layout.FAMILIES}")


def _find(spec: SceneSpec, label: int) -> int:
  for i, obj in enumerate(spec.objects):
    if obj.label == label:
      return i
  raise UnknownObjectError(f"object {label}: the scene has objects "
                           f"{[o.label for o in spec.objects]}")


def remove_object(spec: SceneSpec, label: int) -> SceneSpec:
  """The scene without object `label`; the others keep their labels, lights and floor stay."""
  i = _find(spec, label)
  return dataclasses.replace(spec, objects=spec.objects[:i] + spec.objects[i + 1:])


def horizontal(translation: Sequence[float]) -> tuple[float, float]:
  """(dx, dy) of a translation given as (dx, dy) or (dx, dy, 0); SceneEditError otherwise."""
  t = [float(x) for x in translation]
  if len(t) not in (2, 3) or not all(math.isfinite(x) for x in t):
    raise SceneEditError(f"translation {t}: give (dx, dy) or (dx, dy, dz), finite")
  if len(t) == 3 and t[2] != 0.0:
    raise SceneEditError(f"translation {t}: dz must be 0, objects rest on the floor")
  return t[0], t[1]


def check_placement(spec: SceneSpec, label: int, xy: Sequence[float],
                    radius: Optional[float] = None) -> None:
  """Refuses (CollisionError, FootprintError) object `label` with its bounding circle centred at
  `xy` (radius: the object's own unless given) among the other objects of `spec`."""
  i = _find(spec, label)
  obj = spec.objects[i]
  r = obj.bounding_radius if radius is None else radius
  x, y = float(xy[0]), float(xy[1])
  half = footprint_half_size(spec.family)
  if max(abs(x), abs(y)) + r > half:
    raise FootprintError(f"object {label} at ({x:.3f}, {y:.3f}) with bounding radius {r:.3f} "
                         f"leaves the scene footprint |x|, |y| <= {half:.3f}")
  for other in spec.objects:
    if other.label == label:
      continue
    gap = math.hypot(x - other.position[0], y - other.position[1])
    need = r + other.bounding_radius + layout.MIN_GAP
    if gap < need:
      raise CollisionError(f"object {label} at ({x:.3f}, {y:.3f}) collides with object "
                           f"{other.label}: centres {gap:.3f} apart, need {need:.3f} "
                           f"(bounding circles + MIN_GAP {layout.MIN_GAP})")


def _moved(obj: SceneObject, dx: float, dy: float) -> SceneObject:
  shift = lambda p: (p[0] + dx, p[1] + dy, p[2])
  parts = tuple(dataclasses.replace(p, centre=shift(p.centre)) for p in obj.parts)
  return dataclasses.replace(obj, position=shift(obj.position), parts=parts)


def translate_object(spec: SceneSpec, label: int, translation: Sequence[float]) -> SceneSpec:
  """The scene with object `label` (all its parts) shifted by `translation` (world units,
  horizontal); refused when the shifted object would collide or leave the footprint. Textures
  live in the object's frame (raycaster.scene_arrays), so they move with it."""
  dx, dy = horizontal(translation)
  i = _find(spec, label)
  obj = spec.objects[i]
  check_placement(spec, label, (obj.position[0] + dx, obj.position[1] + dy))
  objects = list(spec.objects)
  objects[i] = _moved(obj, dx, dy)
  return dataclasses.replace(spec, objects=tuple(objects))


@dataclasses.dataclass(frozen=True)
class GroundTruth:
  """What the writer stores of a scene's views (world units)."""
  rgb: np.ndarray  # [N, H, W, 3] uint8
  label: np.ndarray  # [N, H, W] int32, 0 = background
  depth: np.ndarray  # [N, H, W] float32 camera-z depth, 0 where no hit

  @property
  def images(self) -> np.ndarray:
    """[N, H, W, 3] float32 in [0, 1], as the readers load the PNGs."""
    return self.rgb.astype(np.float32) / 255.0


@dataclasses.dataclass(frozen=True)
class DrawnScene:
  """A stored scene re-drawn: its SceneSpec and cameras, and how it was rendered."""
  spec: SceneSpec
  cam_to_world: np.ndarray  # [N, 4, 4] float64, world units
  image_size: int
  supersample: int


def render(drawn: DrawnScene, spec: Optional[SceneSpec] = None) -> GroundTruth:
  """`spec` (default: the drawn scene's own) rendered from the drawn scene's cameras, as the
  writer renders it (writer.render_scene)."""
  from slotlifter_jax.data import writer  # the ray caster: JAX, compiled on first use
  rgb, label, depth = writer.render_scene(drawn.spec if spec is None else spec,
                                          drawn.cam_to_world, image_size=drawn.image_size,
                                          supersample=drawn.supersample)
  return GroundTruth(rgb=rgb, label=label, depth=depth)


def read_manifest(folder: str) -> dict:
  """A generated split folder's dataset.json as stored; RedrawError when there is none."""
  path = os.path.join(folder, "dataset.json")
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (OSError, ValueError) as e:
    raise RedrawError(f"{path}: no readable dataset.json, so the split's scenes cannot be "
                      f"re-drawn ({e})") from e


def redraw(manifest: dict, name: str) -> DrawnScene:
  """Scene `name` of a split re-drawn from its dataset.json (`manifest`): the same random stream,
  the same arguments, so the same SceneSpec and cameras (module docstring)."""
  from slotlifter_jax.data import writer
  entry = next((s for s in manifest.get("scenes", []) if s.get("name") == name), None)
  if entry is None:
    raise RedrawError(f"scene {name!r} is not listed in the split's dataset.json")
  try:
    size = manifest["image_size"]
    if size[0] != size[1]:
      raise RedrawError(f"scene {name}: image_size {size} is not square; the generator writes "
                        f"square views")
    objects = manifest.get("objects", {})
    rng = writer.scene_rng(seed=int(manifest["seed"]), family=manifest["family"],
                           split=manifest["split"], index=int(entry["index"]))
    spec, cameras, c2w, _ = writer.draw_scene(
        rng, family=manifest["family"], views=int(manifest["views_per_scene"]),
        image_size=int(size[0]), supersample=int(manifest.get("supersample", 2)),
        min_objects=int(objects.get("min_objects", 0)),
        max_objects=int(objects.get("max_objects", 0)),
        object_scale=float(objects.get("object_scale", 1.0)),
        # Recorded only by sets drawn with it, as the writer's header does.
        room_objects=str(objects.get("room_objects", "chairs")),
        **{k: True for k in ("plain_background", "plain_objects", "no_walls", "grey_floor")
           if objects.get(k)})
  except (KeyError, TypeError, ValueError) as e:
    if isinstance(e, RedrawError):
      raise
    raise RedrawError(f"scene {name}: dataset.json lacks what re-drawing needs ({e!r})") from e
  stored = [o["label"] for o in entry.get("objects", [])]
  drawn_positions = np.array([o.position for o in spec.objects])
  stored_positions = np.array([o["position"] for o in entry.get("objects", [])])
  if (stored != [o.label for o in spec.objects]
      or not np.allclose(drawn_positions, stored_positions, rtol=0, atol=1e-9)):
    raise RedrawError(f"scene {name}: re-drawn objects differ from dataset.json's (written by "
                      f"another generator version or seed stream)")
  return DrawnScene(spec=spec, cam_to_world=c2w, image_size=int(size[0]),
                    supersample=int(manifest.get("supersample", 2)))


def check_redraw(truth: GroundTruth, *, images: np.ndarray, masks: Optional[np.ndarray],
                 name: str) -> None:
  """RedrawError unless the re-drawn render equals a loaded scene's images (and masks) exactly.

  images: [N, H, W, 3] float32 as the readers load them (uint8 / 255); masks [N, H, W] or None.
  """
  if truth.rgb.shape != images.shape or not np.array_equal(truth.images, images):
    raise RedrawError(f"scene {name}: re-drawn images differ from the stored ones "
                      f"(data.image_size other than the stored size, or files from another "
                      f"generator)")
  if masks is not None and not np.array_equal(truth.label, masks):
    raise RedrawError(f"scene {name}: re-drawn masks differ from the stored ones")
