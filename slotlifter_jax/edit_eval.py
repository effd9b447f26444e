"""Scores of slot edits against the generator's edited ground truth: `--mode=edit` on a split of
the embedded set (docs/editing.md §3).

For each of the first `--max_scenes` scenes: every object removed and every object moved
(edit_scores.MOVE_DISTANCE, seeded), the slot chosen as the one whose source-view mask best
matches the object (edit_scores.match_slot), rendered with rendering.edits (edit.EditRenderer)
and compared on the novel views with the generator's ground truth of the same edit
(data/scene_edits.py). Writes DIR/edit/<split>/edit_metrics.json:

  remove, move: num_edits, num_skipped (no slot), improved_fraction, improved_count,
                for every figure of edit_scores.FIGURES (iou for moves only) and its
                `_baseline` (the unedited rendering against the edited truth): the mean (the
                IoU's as `iou_mean`, `iou_baseline_mean`), `_stderr` and `_count` over edits;
                changed_share; move also num_no_translation
  edits:        one record per object and kind (scene, label, slot, match IoU, translation,
                figures, or why it was skipped)
  settings:     match_iou, move_distance, move_tries, move_seed
  checkpoint, parameters, split, data_root, definitions, provenance (resolved config, git
  commit, CPU model, …: slotlifter_jax/provenance.py)

and DIR/edit/<split>/pictures/scene_XXXX_<kind>_oL.png for the first edits of each kind: per
novel view, source | truth before | truth after | render before | render after | render change |
truth change (titled source, GT, GT edit, render, edited, change, GT chg). An existing
edit_metrics.json is kept unless `overwrite`. `run` is the whole `--mode=edit` command: these
scores, or one asked-for edit of chosen scenes (edit.render_edit).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from typing import Optional

import ml_collections
import numpy as np
from tqdm import tqdm

from slotlifter_jax import edit_scores
from slotlifter_jax import evaluate
from slotlifter_jax import multihost
from slotlifter_jax import provenance
from slotlifter_jax import regions
from slotlifter_jax import vis
from slotlifter_jax.data import registry
from slotlifter_jax.data import scene_edits
from slotlifter_jax.data.types import Scene
from slotlifter_jax import edit
from slotlifter_jax.edit import EditFlagError, EditRenderer, change_picture, panel
from slotlifter_jax.rendering import edits
from slotlifter_jax.rendering import pictures

NUM_PICTURES = 2  # edits of each kind drawn as pictures


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


@dataclasses.dataclass(frozen=True)
class _Unedited:
  """One scene ready for its edits: re-drawn, checked, rendered without an edit."""
  index: int
  scene: Scene
  drawn: scene_edits.DrawnScene
  truth: scene_edits.GroundTruth
  rotation: np.ndarray  # rendering.edits.frame_map's turn, world → model frame
  encoded: object
  sources: dict
  render: tuple  # (colour, depth, segmentation) of every view

  @property
  def novel(self) -> list[int]:
    return list(self.scene.novel_indices)


def _unedited(renderer: EditRenderer, params, manifest: dict, index: int, scene: Scene,
              scale: float, num_slots: int) -> _Unedited:
  drawn = scene_edits.redraw(manifest, scene.name)
  truth = scene_edits.render(drawn)
  scene_edits.check_redraw(truth, images=scene.images, masks=scene.masks, name=scene.name)
  rot, _ = edits.frame_map(world_cam_to_world=drawn.cam_to_world,
                           model_cam_to_world=scene.cam_to_world, scene_scale=scale)
  encoded, sources = renderer.encode(params, scene)
  plain = renderer.render(params, encoded, sources, edits.Edit.identity(num_slots),
                          cam_to_world=scene.cam_to_world, intrinsics=scene.intrinsics,
                          image_size=scene.image_size)
  return _Unedited(index=index, scene=scene, drawn=drawn, truth=truth, rotation=rot,
                   encoded=encoded, sources=sources, render=plain)


def _score_one(renderer: EditRenderer, params, u: _Unedited, *, kind: str, label: int, slot: int,
               translation: Optional[np.ndarray], scale: float, num_slots: int,
               removal: str = edit_scores.REMOVAL, carry: Optional[int] = None,
               fill: Optional[int] = None):
  """(figures, edited novel views (colour, depth, segmentation), edited ground truth)."""
  scene, novel, src = u.scene, u.novel, list(u.scene.source_indices)
  if kind == "remove":
    spec = scene_edits.remove_object(u.drawn.spec, label)
    edit = edits.removal_edit(slot, num_slots, removal).filling(fill)
  else:
    spec = scene_edits.translate_object(u.drawn.spec, label, translation)
    t_model = edits.world_translation((translation[0], translation[1], 0.0),
                                      rotation=u.rotation, scene_scale=scale)
    edit = edits.move_edit(slot, num_slots, edits.RigidMove.make(t_model), removal,
                           carry).filling(fill)
  truth = scene_edits.render(u.drawn, spec)
  edited = renderer.render(params, u.encoded, u.sources, edit,
                           cam_to_world=scene.cam_to_world[novel],
                           intrinsics=scene.intrinsics[novel], image_size=scene.image_size)
  # The stored depth is in world units; the readers scale it as they do the cameras.
  seen = regions.seen_by_sources(
      depth=truth.depth[novel] * np.float32(scale), cam_to_world=scene.cam_to_world[novel],
      intrinsics=scene.intrinsics[novel], source_depth=scene.depth[src],
      source_cam_to_world=scene.cam_to_world[src], source_intrinsics=scene.intrinsics[src])
  figures = edit_scores.score_edit(
      edited=(edited[0], edited[2]), unedited=(u.render[0][novel], u.render[2][novel]),
      truth_before=u.truth, truth_after=truth, seen=seen, novel=novel, slot=slot,
      moved_label=label if kind == "move" else None)
  return figures, edited, truth


def _edit_picture(path: str, u: _Unedited, edited: tuple, truth: scene_edits.GroundTruth,
                  footer: str) -> None:
  """The scores' picture of one edit (module docstring)."""
  source = u.scene.images[u.scene.source_indices[0]]
  rows = [[source, u.truth.images[v], truth.images[v], u.render[0][v], edited[0][i],
           change_picture(edited[0][i], u.render[0][v]), change_picture(truth.images[v], u.truth.images[v])]
          for i, v in enumerate(u.novel)]
  vis.save_png(path, panel(rows, ["source", "GT", "GT edit", "render", "edited", "change",
                                  "GT chg"], footer))


def score_split(config: ml_collections.ConfigDict, workdir: str, *, split: str = "test",
                checkpoint: str = "", params: str = "average", max_scenes: Optional[int] = None,
                overwrite: bool = False, progress: bool = True,
                match_iou: float = edit_scores.MATCH_IOU,
                removal: str = edit_scores.REMOVAL,
                move_background: str = edit_scores.MOVE_BACKGROUND,
                uncovered: str = edit_scores.UNCOVERED) -> dict:
  """Scores removal and translation of every object of the first scenes (module docstring);
  returns the report it writes. `match_iou` other than MATCH_IOU is for tests of the scoring path
  on untrained runs; `removal` (rendering.edits.REMOVALS) how a slot leaves its place;
  `move_background` (edit_scores.MOVE_BACKGROUNDS) whether a move carries the background slot;
  `uncovered` (edit_scores.UNCOVERED_MODES) what fills the space an edit uncovers. The report
  records the values used."""
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
  carry, fill = edit_scores.background_roles(run.config, move_background, uncovered)
  renderer = EditRenderer(run.model, run.config)
  k = run.model.num_slots
  records = {kind: [] for kind in edit_scores.EDIT_KINDS}
  skipped = {kind: 0 for kind in edit_scores.EDIT_KINDS}
  pictures_left = {kind: NUM_PICTURES for kind in edit_scores.EDIT_KINDS}
  no_translation, log = 0, []
  for index, scene in enumerate(tqdm(run.scenes, desc=f"edit {split}", unit="scene",
                                     disable=not progress)):
    u = _unedited(renderer, run.params, manifest, index, scene, scale, k)
    src = scene.source_indices[0]
    entry = next(e for e in manifest["scenes"] if e["name"] == scene.name)
    for obj in u.drawn.spec.objects:
      slot, iou = edit_scores.match_slot(segmentation=u.render[2][src], labels=scene.masks[src],
                                         label=obj.label, threshold=match_iou)
      # Drawn for every object, matched or not, so the translations do not depend on the model.
      t = edit_scores.draw_translation(
          u.drawn.spec, obj.label, edit_scores.translation_rng(
              data_seed=manifest["seed"], split=split, index=entry["index"], label=obj.label))
      base = {"scene": index, "scene_name": scene.name, "label": obj.label, "slot": slot,
              "match_iou": iou}
      for kind in edit_scores.EDIT_KINDS:
        if slot is None:
          skipped[kind] += 1
          log.append(dict(base, kind=kind, skipped="no slot"))
          continue
        if kind == "move" and t is None:
          no_translation += 1
          log.append(dict(base, kind=kind, skipped="no translation fits"))
          continue
        figures, edited, truth = _score_one(renderer, run.params, u, kind=kind, label=obj.label,
                                            slot=slot, translation=t, scale=scale, num_slots=k,
                                            removal=removal, carry=carry, fill=fill)
        records[kind].append(figures)
        moved = {"translation": [float(t[0]), float(t[1]), 0.0]} if kind == "move" else {}
        log.append(dict(base, kind=kind, figures=figures, **moved))
        if pictures_left[kind] and multihost.is_primary():
          pictures_left[kind] -= 1
          what = f"move by {t[0]:.2f},{t[1]:.2f}" if kind == "move" else "remove"
          _edit_picture(os.path.join(out_dir, "pictures",
                                     f"scene_{index:04d}_{kind}_o{obj.label}.png"),
                        u, edited, truth, f"scene {index} {what} object {obj.label}: slot "
                                          f"{slot} (IoU {iou:.2f}) · step {run.step}")
  report = _report_head(run, split, t_start)
  report["settings"]["match_iou"] = float(match_iou)
  report["settings"]["removal"] = removal
  report["settings"]["move_background"] = move_background
  if carry is not None:
    report["settings"]["carry_rule"] = edits.CARRY_RULE
  report["settings"]["uncovered"] = uncovered
  report["settings"]["background_slot"] = edit_scores.background_slot(run.config)
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


def run(config: ml_collections.ConfigDict, workdir: str, *, split: str, scenes: str,
        remove_slot: Optional[int], move_slot: Optional[int], by: str, checkpoint: str,
        params: str, max_scenes: Optional[int], overwrite: bool, orbit_frames: int,
        removal: str = edit_scores.REMOVAL,
        move_background: str = edit_scores.MOVE_BACKGROUND,
        uncovered: str = edit_scores.UNCOVERED) -> str:
  """The `--mode=edit` command: the scores of the split (this module), or with --remove_slot or
  --move_slot one edit of the --scenes (edit.render_edit); returns what it prints."""
  request = edit.parse_request(num_slots=int(config.model.num_slots), remove_slot=remove_slot,
                               move_slot=move_slot, by=by)
  if request is None:
    return format_summary(score_split(config, workdir, split=split, checkpoint=checkpoint,
                                      params=params, max_scenes=max_scenes, overwrite=overwrite,
                                      removal=removal, move_background=move_background,
                                      uncovered=uncovered))
  written = edit.render_edit(config, workdir, request, split=split,
                             scene_indices=edit.parse_scenes(scenes), checkpoint=checkpoint,
                             params=params, num_orbit_frames=orbit_frames, removal=removal,
                             move_background=move_background, uncovered=uncovered)
  return "\n".join(f"{p}\n  {g}" for p, g in written)
