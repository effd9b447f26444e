"""FG-ARI and ARI of segmentations that are the ground truth but for a few pixels, by object count.

  python experiments/fg_ari_ceiling.py [--config=configs/room_chair.py:scene] [--scenes=100] \
      [--set=data.room_objects=boxes ...] [--out=experiments/results/NAME.json]

FG-ARI (docs/method.md §4) scores how a view's foreground pixels are grouped, up to relabelling.
When the view holds one object, the foreground is one true cluster, and sklearn's ARI is then 1 if
every one of its pixels carries the same predicted label and exactly 0 otherwise (the pair counts
leave no chance agreement to adjust for). One pixel of a lone object that the argmax gives to a
second slot therefore costs that view all of its FG-ARI, where in a view of four objects it costs
almost nothing. The embedded room family draws 1–4 objects per scene, so about a quarter of its
scenes score in this all-or-nothing way; the paper's room sets hold four chairs (Room-Chair,
Room-Diverse) or 2–4 (Room-Texture).

This script measures what that does to a set's FG-ARI. On the validation split's ground-truth
masks it builds, from the truth alone, the segmentations

- `truth`: the masks themselves (FG-ARI and ARI 1 by construction; a check of the scorer);
- `one_pixel`: one foreground pixel per view (the first, in raster order, of the first object's
  edge) given to the background's label;
- `edge`: every object pixel with a 4-neighbour of another label given to the background's label:
  objects rendered one pixel too small, the error a soft density edge makes;

and scores them with the evaluation's own `metrics.fg_ari` on the source view (as FG-ARI is
reported) and `metrics.ari` with background on the novel views (as NV-ARI). Rows group scenes by
the number of objects in the source view. Only the validation split is read.
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
from slotlifter_jax import metrics  # noqa: E402
from slotlifter_jax import provenance  # noqa: E402
from slotlifter_jax.data import embedded  # noqa: E402
from slotlifter_jax.data import registry  # noqa: E402

BACKGROUND = metrics.BACKGROUND_LABEL
VARIANTS = ("truth", "one_pixel", "edge")


def edge_pixels(labels: np.ndarray) -> np.ndarray:
  """[H, W] bool: foreground pixels with a 4-neighbour (inside the image) of another label."""
  edge = np.zeros(labels.shape, bool)
  differs_down = labels[1:, :] != labels[:-1, :]
  differs_right = labels[:, 1:] != labels[:, :-1]
  edge[1:, :] |= differs_down
  edge[:-1, :] |= differs_down
  edge[:, 1:] |= differs_right
  edge[:, :-1] |= differs_right
  return edge & (labels != BACKGROUND)


def perturbed(labels: np.ndarray, variant: str) -> np.ndarray:
  """The ground truth [H, W] with `variant`'s pixels given to the background's label."""
  out = labels.copy()
  if variant == "truth":
    return out
  edge = edge_pixels(labels)
  if variant == "edge":
    out[edge] = BACKGROUND
    return out
  if variant == "one_pixel":
    objects = np.unique(labels[labels != BACKGROUND])
    if objects.size:
      first = np.flatnonzero(edge & (labels == objects[0]))
      if first.size:
        out.flat[first[0]] = BACKGROUND
    return out
  raise ValueError(f"unknown variant {variant!r}; use one of {VARIANTS}")


def scene_scores(scene) -> dict:
  """{variant: (FG-ARI of the source view, mean ARI of the novel views)} and the object count."""
  source = scene.source_indices[0]
  novel = list(scene.novel_indices)
  truth = scene.masks
  count = int(np.unique(truth[source][truth[source] != BACKGROUND]).size)
  row = {"num_objects": count}
  for variant in VARIANTS:
    pred = np.stack([perturbed(view, variant) for view in truth])
    fg = metrics.fg_ari(true_labels=truth[source].reshape(1, -1),
                        pred_labels=pred[source].reshape(1, -1))[0]
    nv = metrics.ari(true_labels=truth[novel].reshape(len(novel), -1),
                     pred_labels=pred[novel].reshape(len(novel), -1))
    row[variant] = {"fg_ari": float(fg), "nv_ari": float(np.mean(nv))}
  return row


def summarise(rows: list[dict]) -> dict:
  """Means per object count ("1", "2", …) and over all scenes ("all"), per variant and metric."""
  groups = {str(n): [r for r in rows if r["num_objects"] == n]
            for n in sorted({r["num_objects"] for r in rows})}
  groups["all"] = rows
  return {name: {"scenes": len(group),
                 **{variant: {key: float(np.nanmean([r[variant][key] for r in group]))
                              for key in ("fg_ari", "nv_ari")} for variant in VARIANTS}}
          for name, group in groups.items() if group}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--config", default="configs/room_chair.py:scene")
  parser.add_argument("--scenes", type=int, default=100)
  parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                      help="a dotted config override, e.g. data.object_scale=0.6 (repeatable)")
  parser.add_argument("--out", default="")
  args = parser.parse_args()
  try:
    overrides = study_common.parse_set_overrides(args.set)
    config = study_common.apply_overrides(study_common.load_config(args.config), overrides)
  except study_common.StudyError as e:
    parser.error(str(e))
  t0 = time.perf_counter()
  config = embedded.resolve_data(config)
  scenes = registry.load_split(config.data, "val", max_scenes=args.scenes)
  if not scenes or scenes[0].masks is None:
    raise SystemExit(f"error: {config.data.root}: the validation split has no ground-truth masks")
  summary = summarise([scene_scores(scene) for scene in scenes])
  print(f"{len(scenes)} validation scenes of {config.data.root}")
  print("| objects | scenes | " + " | ".join(f"{v} FG-ARI | {v} NV-ARI" for v in VARIANTS) + " |")
  print("|---|---|" + "---|---|" * len(VARIANTS))
  for name, group in summary.items():
    print(f"| {name} | {group['scenes']} | " + " | ".join(
        f"{group[v]['fg_ari']:.3f} | {group[v]['nv_ari']:.3f}" for v in VARIANTS) + " |")
  if args.out:
    result = {"config": args.config, "overrides": overrides, "split": "val",
              "data_root": config.data.root, "by_object_count": summary,
              provenance.KEY: provenance.collect(config, wall_s=time.perf_counter() - t0)}
    with open(args.out, "w") as f:
      json.dump(result, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
