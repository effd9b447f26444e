"""`--mode=edit`: a trained run's scenes edited by their slots (docs/editing.md).

Two uses, both with the checkpoint `--mode=eval` takes (best if the run has one, else latest;
`--checkpoint`, `--params`); neither trains nor writes anything but DIR/edit/<split>/:

- Scores, on a split of the embedded set (`score_split`): for each of the first `--max_scenes`
  scenes, every object removed and every object moved (edit_scores.MOVE_DISTANCE, seeded), the
  slot chosen as the one whose source-view mask best matches the object (edit_scores.match_slot),
  rendered with `rendering.edits` and compared on the novel views with the generator's ground
  truth of the same edit (data/scene_edits.py). Writes DIR/edit/<split>/edit_metrics.json:

    remove, move: num_edits, num_skipped (no slot), improved_fraction, improved_count,
                  for every figure of edit_scores.FIGURES (iou for moves only) and its
                  `_baseline` (the unedited rendering against the edited truth): the mean (the
                  IoU's as `iou_mean`), `_stderr` and `_count` over edits; changed_share;
                  move also num_no_translation
    edits:        one record per object and kind (scene, label, slot, match IoU, translation,
                  figures, or why it was skipped)
    settings:     match_iou, move_distance, move_tries, move_seed
    checkpoint, parameters, split, data_root, definitions, provenance (resolved config, git
    commit, CPU model, …: slotlifter_jax/provenance.py)

  and DIR/edit/<split>/pictures/scene_XXXX_<kind>_oL.png for the first edits of each kind: per
  novel view, source | truth before | truth after | render before | render after | render change |
  truth change (titled source, GT, GT edit, render, edited, change, GT chg), a change being
  4·mean |after − before| over the channels, in grey.
- Renders one edit of chosen scenes of any set, with or without ground truth (`render_edit`):
  `--scenes=0,3 --remove_slot=k`, or `--move_slot=k --by=dx,dy,dz` (world units and axes of the
  stored cameras, turned into the model's frame by rendering.edits.frame_map). Writes
  DIR/edit/<split>/scene_XXXX_<remove|move>_sK.png (per view: source | render before | render
  after | change | segmentation after) and scene_XXXX_<…>_orbit.gif of the edited scene, as
  `--mode=render`'s orbit; no metrics.

Bad requests raise `EditFlagError`, whose message starts with the flag, before any file is
written; an existing edit_metrics.json is kept unless `overwrite`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from tqdm import tqdm

from slotlifter_jax import config_checks
from slotlifter_jax import edit_scores
from slotlifter_jax import evaluate
from slotlifter_jax import multihost
from slotlifter_jax import provenance
from slotlifter_jax import regions
from slotlifter_jax import vis
from slotlifter_jax.checkpoints import EvalSetupError
from slotlifter_jax.data import registry
from slotlifter_jax.data import scene_edits
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import edits
from slotlifter_jax.rendering import pictures
from slotlifter_jax.rendering import views as views_lib

NUM_PICTURES = 2  # edits of each kind drawn as pictures
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


def _change(after: np.ndarray, before: np.ndarray) -> np.ndarray:
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
# Scores against the generator's ground truth
# ---------------------------------------------------------------------------------------------


def _manifest(config, split: str) -> dict:
  """The split's dataset.json, from which its scenes are re-drawn (data/scene_edits.py)."""
  d = config.data
  folder = registry.split_folder(d.root, d.subset, split) if d.format in ("uorf", "uocf") else None
  if folder is None or not os.path.exists(os.path.join(folder, "dataset.json")):
    raise EditFlagError("--mode=edit", f"split {split!r} of {d.root} has no generator ground "
                                       f"truth (dataset.json of the embedded set); give "
                                       f"--remove_slot=k or --move_slot=k --by=dx,dy,dz to "
                                       f"render an edit without scores")
  try:
    return scene_edits.read_manifest(folder)
  except scene_edits.SceneEditError as e:
    raise EditFlagError("--mode=edit", str(e)) from e


def _report_head(run, split: str, t_start: float) -> dict:
  return {
      "split": split,
      "num_scenes": len(run.scenes),
      "image_size": list(run.scenes[0].image_size),
      "data_root": run.config.data.root,
      "checkpoint": {"name": pictures.checkpoint_name(run.checkpoint_dir), "step": run.step,
                     "path": run.checkpoint_dir},
      "parameters": run.parameters,
      "renderer": "plain",  # edits render every sample (no adaptive windows)
      "differs_from_training": run.differs_from_training,
      "settings": {"match_iou": edit_scores.MATCH_IOU,
                   "move_distance": list(edit_scores.MOVE_DISTANCE),
                   "move_tries": edit_scores.MOVE_TRIES, "move_seed": edit_scores.MOVE_SEED},
      "definitions": edit_scores.DEFINITIONS,
      provenance.KEY: provenance.collect(run.config, wall_s=time.perf_counter() - t_start),
      "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
  }


def score_split(config: ml_collections.ConfigDict, workdir: str, *, split: str = "test",
                checkpoint: str = "", params: str = "average", max_scenes: Optional[int] = None,
                overwrite: bool = False, progress: bool = True,
                match_iou: float = edit_scores.MATCH_IOU) -> dict:
  """Scores removal and translation of every object of the first scenes (module docstring);
  returns the report it writes. `match_iou` other than MATCH_IOU is for tests of the scoring path
  on untrained runs; the report records the value used."""
  t_start = time.perf_counter()
  out_dir = os.path.join(workdir, "edit", split)
  metrics_path = os.path.join(out_dir, "edit_metrics.json")
  if os.path.exists(metrics_path) and not overwrite:
    raise FileExistsError(f"{metrics_path} exists; pass --overwrite to replace it")
  run = evaluate.load_run(config, workdir, split=split, checkpoint=checkpoint,
                          max_scenes=max_scenes, params=params)
  manifest = _manifest(run.config, split)
  if not run.config.data.has_masks or run.scenes[0].depth is None:
    raise EditFlagError("--mode=edit", "scores need the ground-truth masks and depth of the "
                                       "embedded set (data.has_masks)")
  scale = float(run.config.data.scene_scale)
  renderer = EditRenderer(run.model, run.config)
  k = run.model.num_slots
  records = {kind: [] for kind in edit_scores.EDIT_KINDS}
  skipped = {kind: 0 for kind in edit_scores.EDIT_KINDS}
  no_translation, drawn_pictures = 0, {kind: 0 for kind in edit_scores.EDIT_KINDS}
  log = []
  for index, scene in enumerate(tqdm(run.scenes, desc=f"edit {split}", unit="scene",
                                     disable=not progress)):
    drawn = scene_edits.redraw(manifest, scene.name)
    before_truth = scene_edits.render(drawn)
    scene_edits.check_redraw(before_truth, images=scene.images, masks=scene.masks,
                             name=scene.name)
    rot, _ = edits.frame_map(world_cam_to_world=drawn.cam_to_world,
                             model_cam_to_world=scene.cam_to_world, scene_scale=scale)
    src, novel = list(scene.source_indices), list(scene.novel_indices)
    encoded, sources = renderer.encode(run.params, scene)
    cams = dict(intrinsics=scene.intrinsics, image_size=scene.image_size)
    plain = renderer.render(run.params, encoded, sources, edits.Edit.identity(k),
                            cam_to_world=scene.cam_to_world, **cams)
    unedited = (plain[0][novel], plain[2][novel])
    entry = next(e for e in manifest["scenes"] if e["name"] == scene.name)
    for obj in drawn.spec.objects:
      slot, iou = edit_scores.match_slot(segmentation=plain[2][src[0]],
                                         labels=scene.masks[src[0]], label=obj.label,
                                         threshold=match_iou)
      rng = edit_scores.translation_rng(data_seed=manifest["seed"], split=split,
                                        index=entry["index"], label=obj.label)
      t = edit_scores.draw_translation(drawn.spec, obj.label, rng)
      base = {"scene": index, "scene_name": scene.name, "label": obj.label,
              "slot": slot, "match_iou": iou}
      for kind in edit_scores.EDIT_KINDS:
        if slot is None:
          skipped[kind] += 1
          log.append(dict(base, kind=kind, skipped="no slot"))
          continue
        if kind == "move" and t is None:
          no_translation += 1
          log.append(dict(base, kind=kind, skipped="no translation fits"))
          continue
        if kind == "remove":
          spec, edit = scene_edits.remove_object(drawn.spec, obj.label), edits.Edit.remove([slot], k)
        else:
          t_model = edits.world_translation((t[0], t[1], 0.0), rotation=rot, scene_scale=scale)
          spec = scene_edits.translate_object(drawn.spec, obj.label, t)
          edit = edits.Edit.moving(slot, k, edits.RigidMove.make(t_model))
        after_truth = scene_edits.render(drawn, spec)
        edited = renderer.render(run.params, encoded, sources, edit,
                                 cam_to_world=scene.cam_to_world[novel],
                                 intrinsics=scene.intrinsics[novel],
                                 image_size=scene.image_size)
        seen = regions.seen_by_sources(
            depth=after_truth.depth[novel] * np.float32(scale),
            cam_to_world=scene.cam_to_world[novel], intrinsics=scene.intrinsics[novel],
            source_depth=scene.depth[src], source_cam_to_world=scene.cam_to_world[src],
            source_intrinsics=scene.intrinsics[src])
        figures = edit_scores.score_edit(
            edited=(edited[0], edited[2]), unedited=unedited, truth_before=before_truth,
            truth_after=after_truth, seen=seen, novel=novel, slot=slot,
            moved_label=obj.label if kind == "move" else None)
        records[kind].append(figures)
        log.append(dict(base, kind=kind, figures=figures,
                        **({"translation": [float(t[0]), float(t[1]), 0.0]}
                           if kind == "move" else {})))
        if drawn_pictures[kind] < NUM_PICTURES and multihost.is_primary():
          drawn_pictures[kind] += 1
          rows = [[scene.images[src[0]], before_truth.images[v], after_truth.images[v],
                   plain[0][v], edited[0][i], _change(edited[0][i], plain[0][v]),
                   _change(after_truth.images[v], before_truth.images[v])]
                  for i, v in enumerate(novel)]
          what = f"move by {t[0]:.2f},{t[1]:.2f}" if kind == "move" else "remove"
          vis.save_png(os.path.join(out_dir, "pictures",
                                    f"scene_{index:04d}_{kind}_o{obj.label}.png"),
                       panel(rows, ["source", "GT", "GT edit", "render", "edited", "change",
                                    "GT chg"],
                             f"scene {index} {what} object {obj.label}: slot {slot} "
                             f"(IoU {iou:.2f}) · step {run.step}"))
  report = _report_head(run, split, t_start)
  report["settings"]["match_iou"] = float(match_iou)
  for kind in edit_scores.EDIT_KINDS:
    report[kind] = edit_scores.summarize_kind(records[kind], skipped=skipped[kind],
                                              no_translation=no_translation,
                                              move=kind == "move")
  report["edits"] = log
  report = _json_safe(report)
  if multihost.is_primary():
    evaluate._atomic_write(metrics_path, json.dumps(report, indent=2, allow_nan=False) + "\n")
  report["metrics_path"] = metrics_path
  return report


def _json_safe(x):
  """NaN and ±inf as null, so the file stays strict JSON (as metrics.json)."""
  if isinstance(x, float):
    return x if math.isfinite(x) else None
  if isinstance(x, dict):
    return {k: _json_safe(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_json_safe(v) for v in x]
  if isinstance(x, (np.floating, np.integer)):
    return _json_safe(x.item())
  return x


def format_summary(report: dict) -> str:
  lines = [f"split {report['split']}: {report['num_scenes']} scenes, checkpoint "
           f"{report['checkpoint']['name']} step {report['checkpoint']['step']} "
           f"({report['parameters']} parameters)"]
  fmt = lambda v: "   n/a" if v is None else f"{v:6.2f}"
  for kind in edit_scores.EDIT_KINDS:
    s = report[kind]
    line = (f"{kind:<6} {s['num_edits']} edits ({s['num_skipped']} without a slot): PSNR changed "
            f"{fmt(s['psnr_changed'])} dB (unedited {fmt(s['psnr_changed_baseline'])}), "
            f"improved {fmt(s['improved_fraction'])}")
    if kind == "move":
      line += f", IoU {fmt(s['iou_mean'])} (unmoved {fmt(s['iou_baseline_mean'])})"
    lines.append(line)
  lines.append(f"wrote {report['metrics_path']}")
  return "\n".join(lines)


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
                progress: bool = True) -> list[tuple[str, str]]:
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
  out_dir = os.path.join(workdir, "edit", split)
  written = []
  for i in tqdm(indices, desc=f"edit {split}", unit="scene", disable=not progress):
    scene = run.scenes[i]
    if request.kind == "remove":
      edit = edits.Edit.remove([request.slot], k)
    else:
      rot = _world_rotation(run.config, split, i, scene)
      t_model = edits.world_translation(request.by, rotation=rot,
                                        scene_scale=float(run.config.data.scene_scale))
      edit = edits.Edit.moving(request.slot, k, edits.RigidMove.make(t_model))
    encoded, sources = renderer.encode(run.params, scene)
    cams = dict(cam_to_world=scene.cam_to_world, intrinsics=scene.intrinsics,
                image_size=scene.image_size)
    before = renderer.render(run.params, encoded, sources, edits.Edit.identity(k), **cams)
    after = renderer.render(run.params, encoded, sources, edit, **cams)
    src = scene.images[scene.source_indices[0]]
    rows = [[src, before[0][v], after[0][v], _change(after[0][v], before[0][v]),
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


def run(config: ml_collections.ConfigDict, workdir: str, *, split: str, scenes: str,
        remove_slot: Optional[int], move_slot: Optional[int], by: str, checkpoint: str,
        params: str, max_scenes: Optional[int], overwrite: bool, orbit_frames: int) -> str:
  """The `--mode=edit` command (module docstring): what it prints."""
  request = parse_request(num_slots=int(config.model.num_slots), remove_slot=remove_slot,
                          move_slot=move_slot, by=by)
  if request is None:
    return format_summary(score_split(config, workdir, split=split, checkpoint=checkpoint,
                                      params=params, max_scenes=max_scenes, overwrite=overwrite))
  written = render_edit(config, workdir, request, split=split, scene_indices=parse_scenes(scenes),
                        checkpoint=checkpoint, params=params, num_orbit_frames=orbit_frames)
  return "\n".join(f"{p}\n  {g}" for p, g in written)
