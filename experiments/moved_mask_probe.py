"""Where a moved object's pixels go: the moved slot's mask in edited renders, on validation scenes.

  python experiments/moved_mask_probe.py --config=configs/clevr.py:scene --workdir=runs/clevr_scene \
      [--scenes=20] [--out=experiments/results/moved_mask_probe_clevr.json]

For every object of the first validation scenes that `--mode=edit` would move (the same matched
slot and the same seeded translation t, slotlifter_jax/edit_scores.py), the IoU of the moved
slot's rendered mask (argmax of the segmentation) with the moved object's true mask on the novel
views, for
  - `stay`: the edit with the background slot left where it is (what the edit uncovers filled as
    edit_scores.UNCOVERED says, as in both edits),
  - `carry_<rule>`: the edit with the background slot carried along the rays the moved slot
    covers, in the fraction each of rendering/edits.py's CARRY_RULES gives (carry_fraction;
    docs/editing.md §1),
  - `moved_camera`: no edit, the unedited scene seen from the novel cameras moved by −t: the model's
    own rendering of the object and the floor around it from the relative pose the edit asks for,
    what compositing two passes can at best give the moved slot,
  - `unmoved`: no edit, the slot against the same object's mask where it stood (the slot's own
    quality in novel views),
and the background slot's share of the segmentation on the moved object's true pixels in each
edit. Reads the validation split only. Prints the means and writes every record with the
run's provenance.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common  # noqa: E402
from slotlifter_jax import edit_eval  # noqa: E402
from slotlifter_jax import edit_scores  # noqa: E402
from slotlifter_jax import evaluate  # noqa: E402
from slotlifter_jax import metrics  # noqa: E402
from slotlifter_jax import provenance  # noqa: E402
from slotlifter_jax.data import scene_edits  # noqa: E402
from slotlifter_jax.edit import EditRenderer  # noqa: E402
from slotlifter_jax.rendering import edits  # noqa: E402

SPLIT = "val"  # choices read validation only
EDITS = ("stay",) + tuple(f"carry_{rule}" for rule in edits.CARRY_RULES)
KINDS = EDITS + ("moved_camera", "unmoved")


def _iou(segmentation: np.ndarray, slot: int, truth: np.ndarray) -> float:
  return edit_scores.mask_iou(metrics.segmentation_from_render(segmentation) == slot, truth)


def probe(config, workdir: str, num_scenes: int) -> dict:
  t_start = time.perf_counter()
  run = evaluate.load_run(config, workdir, split=SPLIT, max_scenes=num_scenes)
  manifest = edit_eval._manifest(run.config, SPLIT)
  scale, k = float(run.config.data.scene_scale), run.model.num_slots
  background = edit_scores.background_slot(run.config)
  fill = background if edit_scores.UNCOVERED == "background" else None
  if background is None:
    raise SystemExit(f"error: --config: {workdir} was trained without the locality constraint, "
                     f"so no slot is the background and carrying is the same as staying")
  renderer = EditRenderer(run.model, run.config)
  records = []
  for index, scene in enumerate(run.scenes):
    u = edit_eval._unedited(renderer, run.params, manifest, index, scene, scale, k)
    novel, src = u.novel, scene.source_indices[0]
    entry = next(e for e in manifest["scenes"] if e["name"] == scene.name)
    cams = dict(intrinsics=scene.intrinsics[novel], image_size=scene.image_size)
    for obj in u.drawn.spec.objects:
      slot, match = edit_scores.match_slot(segmentation=u.render[2][src], labels=scene.masks[src],
                                           label=obj.label)
      t = edit_scores.draw_translation(u.drawn.spec, obj.label, edit_scores.translation_rng(
          data_seed=manifest["seed"], split=SPLIT, index=entry["index"], label=obj.label))
      if slot is None or t is None or slot == background:
        continue
      truth = scene_edits.render(u.drawn, scene_edits.translate_object(u.drawn.spec, obj.label, t))
      moved_mask = truth.label[novel] == obj.label
      t_model = edits.world_translation((t[0], t[1], 0.0), rotation=u.rotation,
                                        scene_scale=scale).astype(np.float32)
      record = {"scene": index, "label": obj.label, "slot": slot, "match_iou": match,
                "translation": [float(t[0]), float(t[1]), 0.0]}
      for kind in EDITS:
        rule = kind.removeprefix("carry_")
        edit = edits.move_edit(slot, k, edits.RigidMove.make(t_model), edit_scores.REMOVAL,
                               None if kind == "stay" else background,
                               **({} if kind == "stay" else {"carry_rule": rule})).filling(fill)
        _, _, seg = renderer.render(run.params, u.encoded, u.sources, edit,
                                    cam_to_world=scene.cam_to_world[novel], **cams)
        record[kind] = _iou(seg, slot, moved_mask)
        record[f"background_share_{kind}"] = float(seg[..., background][moved_mask].mean())
      shifted = scene.cam_to_world[novel].copy()
      shifted[:, :3, 3] -= t_model
      _, _, seg = renderer.render(run.params, u.encoded, u.sources, edits.Edit.identity(k),
                                  cam_to_world=shifted, **cams)
      record["moved_camera"] = _iou(seg, slot, moved_mask)
      record["unmoved"] = _iou(u.render[2][novel], slot, scene.masks[novel] == obj.label)
      records.append(record)
      print(json.dumps({key: (round(v, 3) if isinstance(v, float) else v)
                        for key, v in record.items() if key != "translation"}), flush=True)
  means = {kind: float(np.mean([r[kind] for r in records])) for kind in KINDS}
  for kind in EDITS:
    key = f"background_share_{kind}"
    means[key] = float(np.mean([r[key] for r in records]))
  return {"split": SPLIT, "num_scenes": len(run.scenes), "num_moves": len(records),
          "checkpoint": {"step": run.step, "path": run.checkpoint_dir},
          "parameters": run.parameters, "background_slot": background,
          "uncovered": edit_scores.UNCOVERED, "means": means,
          "moves": records,
          provenance.KEY: provenance.collect(run.config, wall_s=time.perf_counter() - t_start)}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", required=True)
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--scenes", type=int, default=20)
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  report = probe(study_common.load_config(args.config), args.workdir, args.scenes)
  print(f"{report['num_moves']} moves on {report['num_scenes']} validation scenes, step "
        f"{report['checkpoint']['step']}: mean IoU " + ", ".join(
            f"{kind} {report['means'][kind]:.3f}" for kind in KINDS)
        + "; background share on the moved object's pixels: " + ", ".join(
            f"{kind} {report['means'][f'background_share_{kind}']:.3f}" for kind in EDITS))
  if args.out:
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
      json.dump(report, f, indent=1)
      f.write("\n")
    os.replace(tmp, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
