"""Do the slots of a run hold objects before any 3D rendering? Slot attention on the source view.

  python experiments/diagnose_slots.py --workdir=runs/clevr_scene [--split=val --scenes=20
      --checkpoint=best]

The rendered segmentation (evaluate.py's FG-ARI) mixes two stages: slot attention grouping the
source view's features into K slots, and the allocation transformer mapping 3D points to those
slots. This script looks at the first stage alone, with the run's own config (DIR/config.json),
for the first --scenes scenes of --split:
  2D FG-ARI / ARI   the argmax over slots of the last slot-attention iteration's attention
                    (softmax over slots, [K, h·w]), each pixel taking its nearest feature
                    cell's (align-corners, metrics.feature_cells), against the source view's
                    ground-truth mask (the 2D FG-ARI is what evaluation and
                    validation report as attn_fg_ari)
  slots used        slots that own at least 1 % of the source view's pixels as that argmax
  slot cosine       mean pairwise cosine similarity of the K slots (1: identical slots, which no
                    point-slot mapping can tell apart)
  key cosine        the same for the mapping keys k(S') of the real slots (what the points'
                    queries are compared with, decoder.SlotDecoder)
A run whose 2D FG-ARI is low has not learnt to group objects in the image at all, so the rendered
segmentation cannot split them either; a high 2D FG-ARI with a low rendered FG-ARI points at the
point-slot mapping instead.

Two references on the same views put the 2D FG-ARI on a scale:
  cell ceiling      the best any grouping of whole feature cells can score: each cell takes the
                    ground-truth label most of its pixels carry (small objects at a coarse feature
                    map lose most of their pixels to the floor)
  colour k-means    K-means of the source view's pixel colours into K clusters (no learning,
                    no position): what grouping by colour alone gives
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


def cell_ceiling_labels(mask: np.ndarray, *, feature_hw: tuple[int, int]) -> np.ndarray:
  """[H, W] ground-truth labels → [H, W]: every pixel gets its feature cell's majority label
  (cells as `metrics.feature_cells`; ties to the lowest label)."""
  from slotlifter_jax import metrics
  mask = np.asarray(mask)
  cells = metrics.feature_cells(feature_hw=feature_hw, image_hw=mask.shape).ravel()
  values, labels = np.unique(mask.ravel(), return_inverse=True)
  counts = np.zeros((feature_hw[0] * feature_hw[1], values.size), np.int64)
  np.add.at(counts, (cells, labels), 1)
  return values[counts.argmax(1)][cells].reshape(mask.shape)


def colour_kmeans_labels(image: np.ndarray, *, num_clusters: int, seed: int = 0,
                         restarts: int = 3) -> np.ndarray:
  """[H, W, 3] colours → [H, W] cluster labels: k-means++ (scipy), the best of `restarts` runs by
  within-cluster sum of squares."""
  from scipy.cluster.vq import kmeans2
  pixels = np.asarray(image, np.float64).reshape(-1, 3)
  rng = np.random.default_rng(seed)
  best, best_cost = None, np.inf
  for _ in range(restarts):
    centres, labels = kmeans2(pixels, num_clusters, minit="++", seed=rng)
    cost = float(((pixels - centres[labels]) ** 2).sum())
    if cost < best_cost:
      best, best_cost = labels, cost
  return best.reshape(image.shape[:2])


def mean_pairwise_cosine(x: np.ndarray) -> float:
  """Mean cosine similarity over the distinct pairs of rows of x [K, D]."""
  x = np.asarray(x, np.float64)
  unit = x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
  sim = unit @ unit.T
  k = x.shape[0]
  return float((sim.sum() - np.trace(sim)) / (k * (k - 1)))


def add_run_arguments(p: argparse.ArgumentParser) -> None:
  """The arguments that pick a trained run's checkpoint and scenes (shared with slot_routing.py)."""
  p.add_argument("--workdir", required=True, help="a training run directory")
  p.add_argument("--split", default="val")
  p.add_argument("--scenes", type=int, default=20)
  p.add_argument("--checkpoint", default="best", help="best | latest | a step")


def load_run(args, *, params: str = "average"):
  """evaluate.load_run with the run's own config (DIR/config.json); a one-line exit without it."""
  import ml_collections
  from slotlifter_jax import checkpoints as ckpt_lib
  from slotlifter_jax import evaluate
  saved = ckpt_lib.load_saved_config(args.workdir)
  if saved is None:
    raise SystemExit(f"{ckpt_lib.config_path(args.workdir)}: not found; --workdir must be a "
                     f"training run directory")
  return evaluate.load_run(ml_collections.ConfigDict(saved), args.workdir, split=args.split,
                           checkpoint=args.checkpoint, max_scenes=args.scenes, params=params)


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  add_run_arguments(p)
  args = p.parse_args(argv)

  from slotlifter_jax import metrics
  from slotlifter_jax.rendering import views as views_lib

  run = load_run(args)
  encode = views_lib.make_encode(run.model)
  signed = run.config.model.colour_range == "signed"
  fg_ari, ari, used, slot_cos, key_cos, ceiling, kmeans = [], [], [], [], [], [], []
  for scene in run.scenes:
    idx = np.asarray(scene.source_indices)
    encoded = encode(run.params, views_lib.scene_sources(scene, signed=signed))
    labels = views_lib.source_attention_labels(encoded, scene.image_size)[0]  # first source
    share = np.bincount(labels.ravel(), minlength=encoded.slots.shape[1]) / labels.size
    used.append(float((share >= 0.01).sum()))
    if scene.masks is not None:
      true = scene.masks[idx[0]].reshape(1, -1)
      fg_ari.append(float(metrics.fg_ari(true_labels=true, pred_labels=labels.reshape(1, -1))[0]))
      ari.append(float(metrics.ari(true_labels=true, pred_labels=labels.reshape(1, -1))[0]))
      best = cell_ceiling_labels(scene.masks[idx[0]], feature_hw=encoded.features.shape[2:4])
      ceiling.append(float(metrics.fg_ari(true_labels=true, pred_labels=best.reshape(1, -1))[0]))
      colour = colour_kmeans_labels(scene.images[idx[0]],
                                    num_clusters=run.config.model.num_slots)
      kmeans.append(float(metrics.fg_ari(true_labels=true, pred_labels=colour.reshape(1, -1))[0]))
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
  if ceiling:
    h, w = encoded.features.shape[2:4]
    print(f"  references: cell ceiling ({h}×{w} cells) 2D FG-ARI {mean(ceiling):.3f}, colour "
          f"k-means ({run.config.model.num_slots} clusters) 2D FG-ARI {mean(kmeans):.3f}")


if __name__ == "__main__":
  main()
