"""Do the slots of a run hold objects before any 3D rendering? Slot attention on the source view.

  python experiments/diagnose_slots.py --workdir=runs/clevr_quick [--split=val --scenes=20
      --checkpoint=best]

The rendered segmentation (evaluate.py's FG-ARI) mixes two stages: slot attention grouping the
source view's features into K slots, and the allocation transformer mapping 3D points to those
slots. This script looks at the first stage alone, with the run's own config (DIR/config.json),
for the first --scenes scenes of --split:
  2D FG-ARI / ARI   the argmax over slots of the last slot-attention iteration's attention
                    (softmax over slots, [K, h·w]), upsampled to the image (nearest), against the
                    source view's ground-truth mask
  slots used        slots that own at least 1 % of the source view's pixels as that argmax
  slot cosine       mean pairwise cosine similarity of the K slots (1: identical slots, which no
                    point-slot mapping can tell apart)
  key cosine        the same for the mapping keys k(S') of the real slots (what the points'
                    queries are compared with, decoder.SlotDecoder)
A run whose 2D FG-ARI is low has not learnt to group objects in the image at all, so the rendered
segmentation cannot split them either; a high 2D FG-ARI with a low rendered FG-ARI points at the
point-slot mapping instead.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def attention_segmentation(attn: np.ndarray, *, feature_hw: tuple[int, int],
                           image_hw: tuple[int, int]) -> np.ndarray:
  """[K, h·w] attention (softmax over K) → [H, W] slot labels, each feature cell's argmax slot
  spread over the image pixels it covers (H, W multiples of h, w: the encoder's stride)."""
  h, w = feature_hw
  height, width = image_hw
  if height % h or width % w:
    raise ValueError(f"image {height}×{width} is not a multiple of the feature map {h}×{w}")
  labels = np.asarray(attn).argmax(0).reshape(h, w)
  return np.repeat(np.repeat(labels, height // h, axis=0), width // w, axis=1)


def mean_pairwise_cosine(x: np.ndarray) -> float:
  """Mean cosine similarity over the distinct pairs of rows of x [K, D]."""
  x = np.asarray(x, np.float64)
  unit = x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
  sim = unit @ unit.T
  k = x.shape[0]
  return float((sim.sum() - np.trace(sim)) / (k * (k - 1)))


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--workdir", required=True, help="a training run directory")
  p.add_argument("--split", default="val")
  p.add_argument("--scenes", type=int, default=20)
  p.add_argument("--checkpoint", default="best", help="best | latest | a step")
  args = p.parse_args(argv)

  import ml_collections
  from slotlifter_jax import checkpoints as ckpt_lib
  from slotlifter_jax import evaluate
  from slotlifter_jax import metrics
  from slotlifter_jax import render_views

  saved = ckpt_lib.load_saved_config(args.workdir)
  if saved is None:
    raise SystemExit(f"{ckpt_lib.config_path(args.workdir)}: not found; --workdir must be a "
                     f"training run directory")
  run = evaluate.load_run(ml_collections.ConfigDict(saved), args.workdir, split=args.split,
                          checkpoint=args.checkpoint, max_scenes=args.scenes)
  encode = render_views.make_encode(run.model)
  signed = run.config.model.colour_range == "signed"
  fg_ari, ari, used, slot_cos, key_cos = [], [], [], [], []
  for scene in run.scenes:
    idx = np.asarray(scene.source_indices)
    encoded = encode(run.params, render_views.scene_sources(scene, signed=signed))
    _, v, h, w, _ = encoded.features.shape
    attn = np.asarray(encoded.slot_attn[0]).reshape(-1, v, h * w)[:, 0]  # first source view
    labels = attention_segmentation(attn, feature_hw=(h, w), image_hw=scene.image_size)
    share = np.bincount(labels.ravel(), minlength=attn.shape[0]) / labels.size
    used.append(float((share >= 0.01).sum()))
    if scene.masks is not None:
      true = scene.masks[idx[0]].reshape(1, -1)
      fg_ari.append(float(metrics.fg_ari(true_labels=true, pred_labels=labels.reshape(1, -1))[0]))
      ari.append(float(metrics.ari(true_labels=true, pred_labels=labels.reshape(1, -1))[0]))
    slots = np.asarray(encoded.slots[0])
    slot_cos.append(mean_pairwise_cosine(slots))
    mapping = run.params["allocation"]["map_key"]
    key_cos.append(mean_pairwise_cosine(slots @ np.asarray(mapping["kernel"])
                                        + np.asarray(mapping["bias"])))
  mean = lambda xs: float(np.nanmean(xs)) if xs else float("nan")
  print(f"{args.workdir}: step {run.step}, {len(run.scenes)} {args.split} scenes, "
        f"K = {run.config.model.num_slots}")
  print(f"  slot attention on the source view: 2D FG-ARI {mean(fg_ari):.3f}, "
        f"2D ARI {mean(ari):.3f}, slots used {mean(used):.2f}")
  print(f"  slot cosine {mean(slot_cos):.3f}, key cosine {mean(key_cos):.3f}")


if __name__ == "__main__":
  main()
