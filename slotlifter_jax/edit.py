"""`--mode=edit`: a trained run's scenes edited by their slots (docs/editing.md).

Two uses, both with the checkpoint `--mode=eval` takes (best if the run has one, else latest;
`--checkpoint`, `--params`); neither trains nor writes anything but DIR/edit/<split>/:

- Scores, on a split of the embedded set: every object of the first `--max_scenes` scenes
  removed and moved, against the generator's ground truth of the same edit, into
  DIR/edit/<split>/edit_metrics.json and a few pictures (slotlifter_jax/edit_eval.py, which
  also holds the command, `edit_eval.run`).
- One edit of chosen scenes of any set, with or without ground truth (`render_edit`):
  `--scenes=0,3 --remove_slot=k`, or `--move_slot=k --by=dx,dy,dz` (world units and axes of the
  stored cameras, turned into the model's frame by rendering.edits.frame_map). Writes
  DIR/edit/<split>/scene_XXXX_<remove|move>_sK.png (per view: source | render before | render
  after | change | segmentation after) and scene_XXXX_<…>_orbit.gif of the edited scene, as
  `--mode=render`'s orbit; no metrics.

Here: the flags of the mode and their checks, the renderer of edited views (`EditRenderer`,
rendering.edits in fixed-size ray chunks) and the pictures' layout. A change picture shows
min(1, 4·mean |after − before|) over the channels, in grey. Bad requests raise `EditFlagError`,
whose message starts with the flag, before any file is written.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Optional, Sequence

import jax
import ml_collections
import numpy as np
from tqdm import tqdm

from slotlifter_jax import config_checks
from slotlifter_jax import edit_scores
from slotlifter_jax import evaluate
from slotlifter_jax import multihost
from slotlifter_jax import vis
from slotlifter_jax.checkpoints import EvalSetupError
from slotlifter_jax.data import registry
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import edits
from slotlifter_jax.rendering import pictures
from slotlifter_jax.rendering import views as views_lib

CHANGE_GAIN = 4.0  # a change picture shows min(1, 4·mean |Δ|): small changes stay visible


class EditFlagError(EvalSetupError):
  """A bad edit request; str() is "<flag>: <what is wrong>", one line."""

  def __init__(self, flag: str, message: str):
    super().__init__(f"{flag}: {message}")
    self.flag = flag


@dataclasses.dataclass(frozen=True)
class Request:
  """One edit asked for on the command line: remove or move slot `slot` (by `by`, world units)."""
  kind: str  # "remove" | "move"
  slot: int
  by: Optional[tuple[float, float, float]] = None

  @property
  def name(self) -> str:
    return f"{self.kind}_s{self.slot}"


def parse_vector(text: str) -> tuple[float, float, float]:
  """'dx,dy,dz' → three finite floats; EditFlagError naming --by otherwise."""
  parts = [p.strip() for p in str(text).split(",")]
  try:
    values = tuple(float(p) for p in parts)
  except ValueError:
    values = ()
  if len(values) != 3 or not all(math.isfinite(v) for v in values):
    raise EditFlagError("--by", f"{text!r} is not a vector dx,dy,dz of three finite numbers "
                                f"(world units), e.g. --by=1.5,0,0")
  return values


def parse_request(*, num_slots: int, remove_slot: Optional[int], move_slot: Optional[int],
                  by: str) -> Optional[Request]:
  """The edit the flags ask for, or None (score the split); EditFlagError for a bad one."""
  if remove_slot is not None and move_slot is not None:
    raise EditFlagError("--remove_slot", "give --remove_slot or --move_slot, not both")
  if by and move_slot is None:
    raise EditFlagError("--by", "moves the slot of --move_slot; give --move_slot too")
  for flag, slot in (("--remove_slot", remove_slot), ("--move_slot", move_slot)):
    if slot is not None and not 0 <= slot < num_slots:
      raise EditFlagError(flag, f"slot {slot} out of range: the model has slots 0 … "
                                f"{num_slots - 1} (model.num_slots = {num_slots})")
  if remove_slot is not None:
    return Request("remove", int(remove_slot))
  if move_slot is not None:
    if not by:
      raise EditFlagError("--move_slot", "needs --by=dx,dy,dz, the translation in world units")
    return Request("move", int(move_slot), parse_vector(by))
  return None


def parse_scenes(text: str) -> list[int]:
  try:
    return pictures.parse_scene_indices(text)
  except EvalSetupError as e:
    raise EditFlagError("--scenes", str(e).split(": ", 1)[-1]) from e


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------


class EditRenderer:
  """Edited renderings of whole views (`rendering.edits.render_edit` in fixed-size ray chunks);
  one compiled function for every edit without a move, one for every move."""

  def __init__(self, model, config: ml_collections.ConfigDict):
    self.model = model
    self.signed = config.model.colour_range == "signed"
    self.chunk = int(config.render.chunk)
    self.supersample = config_checks.check_supersample(config.render)
    unit = (lambda c: (c + 1.0) * 0.5) if self.signed else (lambda c: c)

    @jax.jit
    def render_chunk(params, encoded, sources, origins, directions, edit):
      r = edits.render_edit(model, params, encoded, sources, edit, origins=origins,
                            directions=directions)
      return unit(r.colour), r.depth, r.segmentation

    self._render_chunk = render_chunk
    self._encode = views_lib.make_encode(model)

  def encode(self, params, scene: Scene):
    sources = views_lib.scene_sources(scene, signed=self.signed)
    return self._encode(params, sources), sources

  def render(self, params, encoded, sources, edit: edits.Edit, *, cam_to_world: np.ndarray,
             intrinsics: np.ndarray, image_size: tuple[int, int]):
    """(colour [n, H, W, 3] in [0, 1], depth [n, H, W], segmentation [n, H, W, K])."""
    height, width = image_size
    colour, depth, seg = views_lib.render_cameras(
        lambda o, d: self._render_chunk(params, encoded, sources, o, d, edit),
        cam_to_world=cam_to_world, intrinsics=intrinsics, height=height, width=width,
        chunk=self.chunk, supersample=self.supersample)
    return (colour.reshape(-1, height, width, 3), depth.reshape(-1, height, width),
            seg.reshape(-1, height, width, seg.shape[-1]))


def change_picture(after: np.ndarray, before: np.ndarray) -> np.ndarray:
  grey = np.minimum(1.0, CHANGE_GAIN * np.mean(np.abs(np.asarray(after, np.float32)
                                                      - np.asarray(before, np.float32)), -1))
  return np.repeat(grey[..., None], 3, axis=-1)


def panel(rows: Sequence[Sequence[np.ndarray]], titles: Sequence[str], footer: str) -> np.ndarray:
  """Tiles [H, W, 3] under a strip of column titles, above a one-line footer."""
  body = vis.grid([list(r) for r in rows], pad=pictures.PAD)
  width = body.shape[1]
  tile = rows[0][0].shape[1]
  chars = max(1, tile // 6)  # PIL's default font: about 6 px a character
  head = pictures._text(width, pictures.HEADER, [(j * (tile + pictures.PAD) + 1, 0, t[:chars])
                                                 for j, t in enumerate(titles)])
  foot = pictures._text(width, pictures.FOOTER, [(1, 1, footer)])
  return np.concatenate([head, body, foot], axis=0)


# ---------------------------------------------------------------------------------------------
# One edit of chosen scenes, with or without ground truth
# ---------------------------------------------------------------------------------------------


def _world_rotation(config, split: str, index: int, scene: Scene) -> np.ndarray:
  """The turn A of rendering.edits.frame_map for `scene` (identity in the world frame)."""
  if config.data.get("frame", "world") == "world":
    return np.eye(3)
  world_data = config.data.copy_and_resolve_references()
  with world_data.unlocked():
    world_data.frame = "world"
  world = registry.load_split(world_data, split, max_scenes=index + 1)[index]
  # Both loads are already scaled by data.scene_scale: the map between them is the turn alone.
  rot, _ = edits.frame_map(world_cam_to_world=world.cam_to_world,
                           model_cam_to_world=scene.cam_to_world, scene_scale=1.0)
  return rot


def render_edit(config: ml_collections.ConfigDict, workdir: str, request: Request, *,
                split: str = "test", scene_indices: Sequence[int] = (0,), checkpoint: str = "",
                params: str = "average", num_orbit_frames: int = 24,
                progress: bool = True,
                removal: str = edit_scores.REMOVAL,
                move_background: str = edit_scores.MOVE_BACKGROUND,
                uncovered: str = edit_scores.UNCOVERED) -> list[tuple[str, str]]:
  """Pictures and an orbit GIF of `request` on each chosen scene (module docstring);
  returns [(panel path, orbit path)]."""
  if not 1 <= num_orbit_frames <= pictures.MAX_ORBIT_FRAMES:
    raise EditFlagError("--orbit_frames", f"{num_orbit_frames} must be in "
                                          f"[1, {pictures.MAX_ORBIT_FRAMES}]")
  indices = list(scene_indices)
  run = evaluate.load_run(config, workdir, split=split, checkpoint=checkpoint,
                          max_scenes=max(indices) + 1, params=params)
  if max(indices) >= len(run.scenes):
    raise EditFlagError("--scenes", f"index {max(indices)} is past the split: {split!r} has "
                                    f"{len(run.scenes)} scenes")
  if request.kind == "move" and run.model.num_fine_samples > 0:
    raise EditFlagError("--move_slot", "the model has a fine pass (DTU/ScanNet); a move needs "
                                       "one set of sample depths for both passes, remove slots "
                                       "instead")
  renderer = EditRenderer(run.model, run.config)
  k = run.model.num_slots
  carry, fill = edit_scores.background_roles(run.config, move_background, uncovered)
  out_dir = os.path.join(workdir, "edit", split)
  written = []
  for i in tqdm(indices, desc=f"edit {split}", unit="scene", disable=not progress):
    scene = run.scenes[i]
    if request.kind == "remove":
      edit = edits.removal_edit(request.slot, k, removal).filling(fill)
    else:
      rot = _world_rotation(run.config, split, i, scene)
      t_model = edits.world_translation(request.by, rotation=rot,
                                        scene_scale=float(run.config.data.scene_scale))
      edit = edits.move_edit(request.slot, k, edits.RigidMove.make(t_model), removal,
                             carry).filling(fill)
    encoded, sources = renderer.encode(run.params, scene)
    cams = dict(cam_to_world=scene.cam_to_world, intrinsics=scene.intrinsics,
                image_size=scene.image_size)
    before = renderer.render(run.params, encoded, sources, edits.Edit.identity(k), **cams)
    after = renderer.render(run.params, encoded, sources, edit, **cams)
    src = scene.images[scene.source_indices[0]]
    rows = [[src, before[0][v], after[0][v], change_picture(after[0][v], before[0][v]),
             pictures.overlay(rendering=after[0][v], segmentation=after[2][v])]
            for v in range(scene.num_views)]
    what = (f"remove slot {request.slot}" if request.kind == "remove" else
            f"move slot {request.slot} by {','.join(f'{x:g}' for x in request.by)}")
    stem = os.path.join(out_dir, f"scene_{i:04d}_{request.name}")
    source = scene.source_indices[0]
    poses = pictures.orbit_cam_to_world(source_cam_to_world=scene.cam_to_world[source],
                                        num_frames=num_orbit_frames)
    orbit = renderer.render(run.params, encoded, sources, edit, cam_to_world=poses,
                            intrinsics=np.broadcast_to(scene.intrinsics[source],
                                                       (len(poses), 3, 3)),
                            image_size=scene.image_size)
    frames = pictures.orbit_frames(pictures.CameraRenders(
        colour=orbit[0], depth=orbit[1], segmentation=orbit[2],
        slot_colour=np.zeros(orbit[0].shape[:3] + (0, 3), np.float32)))
    if multihost.is_primary():
      vis.save_png(stem + ".png", panel(rows, ["source", "render", "edited", "change", "seg"],
                                        f"scene {i} {what} · step {run.step}"))
      pictures.save_gif(stem + "_orbit.gif", frames)
    written.append((stem + ".png", stem + "_orbit.gif"))
  return written

