"""Scores of slot edits against the generator's edited ground truth (docs/editing.md): which slot
an object is, the fixed translations, the figures of one edit and their summary over edits.

Vocabulary (docs/method.md §0): K slots, n novel views, H×W image size. Pure NumPy on renderings
and ground truth; `slotlifter_jax/edit.py` renders both and writes the results.

The two settings below are fixed before any result was seen, for the reasons written beside them
(docs/editing.md, "Settings"); nothing here is tuned on a split.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from slotlifter_jax import metrics
from slotlifter_jax import regions
from slotlifter_jax.data import scene_edits
from slotlifter_jax.data.layout import SceneSpec

# An object's slot is the slot whose rendered source-view mask has the largest IoU with the
# object's true mask; below this IoU the object has no slot and its edits are skipped. 0.5 is the
# usual criterion for "this mask is that object" (PASCAL VOC's detection rule). An object at or
# above it covers at least half of the slot's mask, so two objects merged into one slot cannot
# both pass (but in the tie where each is exactly half): a merge shows as a skipped object, or as
# a removal that takes a second object with it.
MATCH_IOU = 0.5
# Translations (world units; CLEVR's objects have half-sizes 0.35 and 0.7): at least 1.0, more
# than a small object's bounding diameter (0.99), so a small object always leaves its old place
# entirely; at most 2.0, about a large cube's bounding diameter (1.98), a third of the 6-unit
# placement range, so the object stays in the part of the floor the cameras frame. The direction
# is uniform; a draw that collides or leaves the footprint (scene_edits) is drawn again.
MOVE_DISTANCE = (1.0, 2.0)
MOVE_TRIES = 64
# First entry of every translation's seed (the rest: the set's seed, the split, the scene's index
# in it, the object's label), so the translations are one fixed list per data set.
MOVE_SEED = 8_062_024

# How removals and moves take the slot away from where the object stood (rendering/edits.py,
# REMOVALS). Chosen on the validation split (docs/editing.md §4): on its first 20 scenes
# deleting the slot beats the unedited render in 83 % of removals and 93 % of moves, zeroing its
# density in 0 % and 3 % (experiments/results/edit_clevr_val_removal_*.json).
REMOVAL = "delete"

# What a move does with the background slot (rendering/edits.py, carried_shares): "carry" it
# along the rays the moved slot covers (by edits.CARRY_RULE), or let it "stay" where it is; and what an edit shows
# where it uncovers space the scene held opaque (rendering/edits.py, fill_uncovered): the
# "background" slot's colour, or "black", the renderer's empty ray. Chosen on the validation
# split (docs/editing.md §4).
MOVE_BACKGROUNDS = ("stay", "carry")
MOVE_BACKGROUND = "carry"
UNCOVERED_MODES = ("black", "background")
UNCOVERED = "background"


def check_choice(name: str, value: str, choices: Sequence[str]) -> str:
  if value not in choices:
    raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
  return value


def background_slot(config) -> Optional[int]:
  """The background slot of a trained model: real slot 0, the one the locality constraint
  reserves for the background (docs/method.md §1.4), or None for a model trained without it."""
  return 0 if int(config.train.locality_steps) > 0 else None


def background_roles(config, move_background: str, uncovered: str) -> tuple[Optional[int],
                                                                            Optional[int]]:
  """(the slot a move carries, the slot that fills what an edit uncovers), each None when off."""
  check_choice("move_background", move_background, MOVE_BACKGROUNDS)
  check_choice("uncovered", uncovered, UNCOVERED_MODES)
  background = background_slot(config)
  return (background if move_background == "carry" else None,
          background if uncovered == "background" else None)

EDIT_KINDS = ("remove", "move")
# Per-edit figures, each also computed for the unedited rendering as `<name>_baseline`.
FIGURES = ("psnr", "ssim", "psnr_changed", "psnr_changed_seen", "psnr_changed_unseen", "iou")
DEFINITIONS = {
    "psnr": "PSNR (dB, data range 1) of the edited rendering against the edited ground truth, "
            "mean of the per-image PSNRs of the scene's novel views",
    "ssim": "SSIM (metrics.ssim, docs/method.md §4) of the same, mean over the novel views",
    "psnr_changed": "PSNR (dB) over the novel views' pixels whose ground truth the edit changed "
                    "(any 8-bit channel differs), squared error pooled over those pixels",
    "psnr_changed_seen": "psnr_changed over the changed pixels whose surface point, in the "
                         "edited scene, the source view saw before the edit (regions.py, from "
                         "ground-truth depth)",
    "psnr_changed_unseen": "psnr_changed over the changed pixels whose surface point the source "
                           "view did not see: disoccluded floor, the far side of a moved object",
    "iou": "moves: IoU of the moved slot's rendered mask (argmax of the segmentation) and the "
           "moved object's true mask, pixels pooled over the novel views",
    "changed_share": "share of the novel views' pixels the edit changed",
    "improved_fraction": "share of the edits (with changed pixels) whose psnr_changed beats "
                         "psnr_changed_baseline",
    "baseline": "<figure>_baseline: the same figure for the unedited rendering against the "
                "edited ground truth, what an edit must beat",
    "num_edits": "edits scored", "num_skipped": "edits skipped: no slot matches the object",
    "num_no_translation": "moves skipped: no translation within MOVE_TRIES draws fits the scene",
}


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
  """|a ∧ b| / |a ∨ b| of two boolean masks of any shape (pooled); NaN when both are empty."""
  union = int(np.logical_or(a, b).sum())
  return float(np.logical_and(a, b).sum()) / union if union else math.nan


def match_slot(*, segmentation: np.ndarray, labels: np.ndarray, label: int,
               threshold: float = MATCH_IOU) -> tuple[Optional[int], float]:
  """The slot of object `label` on the source view: (slot or None below `threshold`, its IoU).

  segmentation: [H, W, K] the rendered source view's soft segmentation; labels: [H, W] its true
  mask. A slot's mask is where it is the argmax (metrics.segmentation_from_render).
  """
  pred = metrics.segmentation_from_render(segmentation)  # [H, W]
  truth = labels == label
  ious = [mask_iou(pred == k, truth) for k in range(segmentation.shape[-1])]
  ious = [0.0 if math.isnan(v) else v for v in ious]
  best = int(np.argmax(ious))
  return (best if ious[best] >= threshold else None), float(ious[best])


def translation_rng(*, data_seed: int, split: str, index: int, label: int) -> np.random.Generator:
  return np.random.default_rng(np.random.SeedSequence(
      [MOVE_SEED, int(data_seed), int(index), int(label)] + list(split.encode())))


def draw_translation(spec: SceneSpec, label: int,
                     rng: np.random.Generator) -> Optional[np.ndarray]:
  """A horizontal translation [2] (world units) of object `label` by MOVE_DISTANCE in a uniform
  direction that the ground truth accepts (scene_edits.check_placement), or None after
  MOVE_TRIES draws."""
  obj = next(o for o in spec.objects if o.label == label)
  for _ in range(MOVE_TRIES):
    distance = rng.uniform(*MOVE_DISTANCE)
    angle = rng.uniform(0.0, 2.0 * math.pi)
    t = distance * np.array([math.cos(angle), math.sin(angle)])
    try:
      scene_edits.check_placement(spec, label, (obj.position[0] + t[0], obj.position[1] + t[1]))
    except scene_edits.SceneEditError:
      continue
    return t
  return None


def _figures(colour: np.ndarray, segmentation: np.ndarray, *, truth: np.ndarray,
             changed: np.ndarray, seen: np.ndarray, slot: Optional[int],
             object_mask: Optional[np.ndarray]) -> dict:
  """The figures of one rendering [n, H, W, 3] of the novel views against the edited truth."""
  error = np.mean((np.asarray(colour, np.float64) - truth) ** 2, axis=-1)  # [n, H, W]
  out = {
      "psnr": float(np.mean(metrics.psnr(pred=colour, target=truth))),
      "ssim": float(np.mean(metrics.ssim(pred=colour, target=truth))),
      "psnr_changed": regions.pooled_psnr(error, changed),
      "psnr_changed_seen": regions.pooled_psnr(error, changed & seen),
      "psnr_changed_unseen": regions.pooled_psnr(error, changed & ~seen),
  }
  if object_mask is not None:
    out["iou"] = mask_iou(metrics.segmentation_from_render(segmentation) == slot, object_mask)
  return out


def score_edit(*, edited: tuple, unedited: tuple, truth_before: scene_edits.GroundTruth,
               truth_after: scene_edits.GroundTruth, seen: np.ndarray, novel: Sequence[int],
               slot: int, moved_label: Optional[int] = None) -> dict:
  """The figures (FIGURES, their `_baseline`s, changed_share) of one edit on the novel views.

  edited, unedited: (colour [n, H, W, 3], segmentation [n, H, W, K]) of the novel views `novel`,
  rendered with and without the edit; truth_before, truth_after: all views of the scene before and
  after the edit; seen: [n, H, W] the novel pixels whose edited surface point the source view saw;
  moved_label: the moved object's label (moves only: the IoU figures).
  """
  novel = np.asarray(novel, np.int64)
  truth = truth_after.images[novel].astype(np.float64)
  changed = np.any(truth_before.rgb[novel] != truth_after.rgb[novel], axis=-1)  # [n, H, W]
  mask = None if moved_label is None else truth_after.label[novel] == moved_label
  kw = dict(truth=truth, changed=changed, seen=seen, slot=slot, object_mask=mask)
  after = _figures(*edited, **kw)
  before = _figures(*unedited, **kw)
  out = dict(after)
  out.update({f"{k}_baseline": v for k, v in before.items()})
  out["changed_share"] = float(changed.mean())
  return out


def _finite(x) -> Optional[float]:
  return float(x) if x is not None and math.isfinite(x) else None


def summarize_kind(records: Sequence[dict], *, skipped: int, no_translation: int = 0,
                   move: bool = False) -> dict:
  """One edit kind's summary over its scored edits (module docstring of edit.py lists the keys):
  every figure and its baseline as mean, `_stderr` and `_count` (the IoU's means as `iou_mean`
  and `iou_baseline_mean`: a mean of per-edit IoUs, not the IoU of pooled masks),
  improved_fraction, num_edits, num_skipped (and num_no_translation for moves)."""
  out = {"num_edits": len(records), "num_skipped": int(skipped)}
  if move:
    out["num_no_translation"] = int(no_translation)
  names = [f for f in FIGURES if move or f != "iou"] + ["changed_share"]
  for name in names:
    for key in ([name, f"{name}_baseline"] if name != "changed_share" else [name]):
      s = metrics.summarize([r.get(key, math.nan) for r in records])
      mean_key = f"{key}_mean" if key.startswith("iou") else key
      out[mean_key] = _finite(s.mean)
      out[f"{key}_stderr"] = _finite(s.stderr)
      out[f"{key}_count"] = s.count
  pairs = [(r["psnr_changed"], r["psnr_changed_baseline"]) for r in records
           if not (math.isnan(r["psnr_changed"]) or math.isnan(r["psnr_changed_baseline"]))]
  out["improved_fraction"] = (sum(a > b for a, b in pairs) / len(pairs)) if pairs else None
  out["improved_count"] = len(pairs)
  return out
