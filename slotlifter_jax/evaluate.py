"""Evaluation (docs/method.md §4): per-scene metrics of rendered views and the `--mode=eval` entry
point. Validation during training (slotlifter_jax/validation.py) scores with `scene_metrics` too.

Vocabulary (docs/method.md §0): K slots, V source views, H×W image size, n rendered views of a
scene.

Every view of every scene is rendered at full resolution (`rendering.views.SceneRenderer`,
chunked), source views included. Per scene:
  source views  PSNR, ARI, FG-ARI, FG-ARI on views with ≥ 2 objects, mBO, matched mIoU
  novel views   PSNR, SSIM, LPIPS, NV-ARI, NV-FG-ARI (also on views with ≥ 2 objects), NV-mBO,
                NV-mIoU; in the full evaluation also PSNR split by region (`regions`): pixels a
                source view sees or not (sets with depth), objects or background (sets with masks)
  all views     slots owning ≥ 1 % of the foreground vs the ground-truth object count
A per-view value is averaged over the scene's views of its kind (views where it is NaN — no
ground-truth mask, or no foreground for the FG metrics — are skipped), then `metrics.summarize`
gives the mean ± standard error over scenes. Prediction = argmax over the K real slots of the
rendered segmentation (`metrics.segmentation_from_render`). Segmentation metrics exist only for
sets with masks (config.data.has_masks and scene.masks); they are never computed on made-up masks.

`evaluate_split` writes DIR/eval/<split>/metrics.json and per_scene.csv (temp file + rename). The
official-code quirks of docs/method.md §8 that move these numbers are off by default and recorded in
the JSON when on: `lpips_quirk` (LPIPS fed [0, 1] images) and `nv_ari_last_view` (uORF's NV-ARI and
NV-FG-ARI from the last novel view only).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import time
from typing import Optional, Sequence

import ml_collections
import numpy as np
from absl import logging
from tqdm import tqdm

from slotlifter_jax import config_checks
from slotlifter_jax import averaging
from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import metrics
from slotlifter_jax import model as model_lib
from slotlifter_jax import multihost
from slotlifter_jax import provenance
from slotlifter_jax import regions
from slotlifter_jax.checkpoints import EvalSetupError
from slotlifter_jax.data import embedded
from slotlifter_jax.data import pipeline
from slotlifter_jax.data import registry
from slotlifter_jax.data.types import DataError
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import adaptive
from slotlifter_jax.rendering import views as views_lib

# Metric names in the order of the printed table, with the definition written into metrics.json.
METRIC_DEFINITIONS = {
    "psnr_source": "PSNR (dB, data range 1) of the rendered source view(s), mean of per-image "
                   "PSNRs",
    "ari": "ARI (= sklearn adjusted_rand_score) over all pixels of the source view(s)",
    "fg_ari": "ARI over the pixels whose ground-truth label is not background, source view(s); "
              "views without foreground skipped",
    "fg_ari_multi": "FG-ARI of the source view(s) that show at least two ground-truth objects "
                    "(with one object FG-ARI is 0 for any split and 1 for none: it does not "
                    "measure grouping); other views skipped",
    "mbo": "mean best overlap, source view(s): each ground-truth object's best IoU over the "
           "predicted slot masks, averaged over objects",
    "miou": "Hungarian-matched mean IoU, source view(s): one-to-one object-slot matching "
            "maximising total IoU, unmatched objects count 0, divided by the object count",
    "attn_fg_ari": "FG-ARI of the slot attention alone on the source view(s): each pixel takes "
                   "the argmax slot of its nearest encoder feature cell (align-corners), the "
                   "grouping before any 3D point-slot mapping",
    "attn_ari": "ARI of the slot attention alone on the source view(s) over all pixels, so the "
                "background counts: low when slot attention shares the floor out among slots",
    "psnr_novel": "PSNR (dB, data range 1) of the novel views, mean of per-image PSNRs",
    "ssim": "SSIM of the novel views: Gaussian window 11, sigma 1.5, K1 0.01, K2 0.03, valid "
            "region only, after piq's average pooling by round(min(H, W)/256)",
    "lpips": "LPIPS of the novel views ({net}); images mapped to [-1, 1] ({quirk})",
    "psnr_novel_unseen": "PSNR (dB) of the novel views' pixels whose surface point no source view "
                         "sees (ground-truth depth: outside the source frustum or occluded), "
                         "squared error pooled over the scene's novel views",
    "psnr_novel_seen": "PSNR (dB) of the novel views' pixels whose surface point a source view "
                       "sees, squared error pooled over the scene's novel views",
    "unseen_pixel_share": "share of the novel views' pixels that no source view sees",
    "unseen_error_share": "share of the novel views' squared error on those pixels",
    "psnr_novel_fg": "PSNR (dB) of the novel views' ground-truth object pixels, squared error "
                     "pooled over the scene's novel views with masks",
    "psnr_novel_bg": "PSNR (dB) of the novel views' background pixels, pooled likewise",
    "fg_pixel_share": "share of the novel views' pixels (views with masks) on objects",
    "fg_error_share": "share of the novel views' squared error (views with masks) on objects",
    "psnr_novel_border": "PSNR (dB) of the novel views' background pixels within W/32 pixels "
                         "(chessboard distance; 2 at 64 px) of an object: silhouettes and contact "
                         "shadows, pooled like psnr_novel_fg",
    "psnr_novel_bg_far": "PSNR (dB) of the novel views' other background pixels, pooled likewise",
    "border_pixel_share": "share of the novel views' pixels (views with masks) in that border",
    "border_error_share": "share of the novel views' squared error (views with masks) in it",
    "nv_ari": "ARI over all pixels of the novel views ({nv_rule})",
    "nv_fg_ari": "FG-ARI of the novel views ({nv_rule}); views without foreground skipped",
    "nv_fg_ari_multi": "FG-ARI of the novel views that show at least two ground-truth objects, "
                       "averaged over a scene's such views",
    "nv_mbo": "mean best overlap of the novel views, averaged over a scene's novel views",
    "nv_miou": "Hungarian-matched mean IoU of the novel views, averaged over a scene's novel views",
    "active_slots": "slots owning (as argmax) at least 1 % of the scene's foreground pixels, all "
                    "rendered views with masks pooled",
    "num_objects": "ground-truth foreground objects visible in those views",
    "slot_excess": "active_slots - num_objects (0: one slot per visible object)",
}
AGGREGATION = ("a per-view value is averaged over the scene's views of its kind (NaN views "
               "skipped), then mean, standard error (sample std / sqrt(count)) and count over "
               "scenes; a scene without a usable view is skipped. Prediction = argmax over the K "
               "real slots of the rendered segmentation. Non-finite numbers are written as null.")


# ---------------------------------------------------------------------------------------------
# Per-scene metrics
# ---------------------------------------------------------------------------------------------


def lpips_net_for(config: ml_collections.ConfigDict) -> str:
  """docs/method.md §4: AlexNet LPIPS for the synthetic sets, VGG for DTU and ScanNet."""
  real = config.model.colour_range == "signed" or config.data.format in ("dtu", "scannet")
  return "vgg" if real else "alex"


def _nan_mean(values: np.ndarray) -> float:
  """Mean of the non-NaN entries; NaN (silently) when there are none."""
  return metrics.summarize(values).mean


def _views_with_mask(scene: Scene, views: np.ndarray) -> np.ndarray:
  """[n] bool: which of `views` have a ground-truth mask (all when the scene has no mask_views)."""
  if scene.mask_views is None:
    return np.ones(views.size, bool)
  return np.asarray(scene.mask_views, bool)[views]


def scene_metrics(rendered: views_lib.RenderedViews, scene: Scene, view_indices: Sequence[int],
                  *, image_metrics: bool = False, lpips_net: str = "alex",
                  lpips_quirk: bool = False, nv_ari_last_view: bool = False) -> dict[str, float]:
  """The metrics of one scene from its rendered views (module docstring), as {name: float}.

  Args:
    rendered: the views `view_indices` of `scene`, in that order (colour in [0, 1]).
    scene: ground truth; views in `scene.source_indices` count as source, all others as novel.
    view_indices: which views of the scene `rendered` holds.
    image_metrics: also SSIM and LPIPS of the novel views (the full evaluation; validation during
      training skips them for speed).
    lpips_net: "alex" or "vgg" (`lpips_net_for`).
    lpips_quirk: feed [0, 1] images to LPIPS as the official evaluation does (docs/method.md §8).
    nv_ari_last_view: NV-ARI and NV-FG-ARI from the scene's last novel view only (uORF,
      docs/method.md §8).

  Keys are present only when the scene has views of their kind (and masks for the segmentation
  metrics); values may be NaN (e.g. FG-ARI when no view shows foreground).
  """
  views = np.asarray(list(view_indices), np.int64)  # [n]
  is_source = np.isin(views, np.asarray(scene.source_indices, np.int64))
  source, novel = np.flatnonzero(is_source), np.flatnonzero(~is_source)
  target = scene.images[views]  # [n, H, W, 3]
  colour = np.asarray(rendered.colour)
  out = {}
  psnr = metrics.psnr(pred=colour, target=target)  # [n]
  if source.size:
    out["psnr_source"] = _nan_mean(psnr[source])
  if novel.size:
    out["psnr_novel"] = _nan_mean(psnr[novel])
    if image_metrics:
      out["ssim"] = _nan_mean(metrics.ssim(pred=colour[novel], target=target[novel]))
      out["lpips"] = _nan_mean(metrics.lpips(pred=colour[novel], target=target[novel],
                                             net=lpips_net, official_quirk=lpips_quirk))
      out.update(_region_metrics(colour[novel], scene, views[novel]))
  if scene.masks is None:
    return out

  n = views.size
  has_mask = _views_with_mask(scene, views)  # [n]
  true = scene.masks[views].reshape(n, -1)  # [n, H·W]
  pred = metrics.segmentation_from_render(rendered.segmentation).reshape(n, -1)  # [n, H·W]
  overlap = metrics.object_overlap(true_labels=true, pred_labels=pred)
  fg_ari = metrics.fg_ari(true_labels=true, pred_labels=pred)
  per_view = {  # [n] each; NaN where a view has no ground-truth mask
      "ari": metrics.ari(true_labels=true, pred_labels=pred),
      "fg_ari": fg_ari,
      # FG-ARI of a view with one visible object is 0 for any split of it and 1 only for none
      # (one true cluster), so it says nothing about grouping objects; sets with few objects (the
      # easy rung) are read on views showing at least two.
      "fg_ari_multi": np.where(overlap.num_objects >= 2, fg_ari, np.nan),
      "mbo": overlap.mbo,
      "miou": overlap.miou,
  }
  per_view = {k: np.where(has_mask, v, np.nan) for k, v in per_view.items()}
  if source.size and has_mask[source].any():
    out.update({k: _nan_mean(v[source]) for k, v in per_view.items()})
  if novel.size and has_mask[novel].any():
    for k, v in per_view.items():
      last = nv_ari_last_view and k in ("ari", "fg_ari")
      out[f"nv_{k}"] = float(metrics.per_scene_novel_mean(values=[v[novel]],
                                                          last_novel_only=last)[0])
  src = np.asarray(scene.source_indices, np.int64)
  src_has_mask = _views_with_mask(scene, src)
  if np.shape(rendered.source_labels)[0] != src.size:
    raise ValueError(f"scene {scene.name}: {np.shape(rendered.source_labels)[0]} source views "
                     f"rendered, but the scene names {src.size} (source_indices {tuple(src)})")
  if src_has_mask.any():
    attn = dict(true_labels=scene.masks[src].reshape(src.size, -1),
                pred_labels=np.asarray(rendered.source_labels).reshape(src.size, -1))
    out["attn_fg_ari"] = _nan_mean(np.where(src_has_mask, metrics.fg_ari(**attn), np.nan))
    out["attn_ari"] = _nan_mean(np.where(src_has_mask, metrics.ari(**attn), np.nan))
  masked = np.flatnonzero(has_mask)
  if masked.size:
    # The whole scene as one long view, so the 1 % threshold is of the scene's foreground.
    count = metrics.active_slots(true_labels=true[masked].reshape(1, -1),
                                 pred_labels=pred[masked].reshape(1, -1))
    out["active_slots"] = float(count.num_active[0])
    out["num_objects"] = float(count.num_objects[0])
    out["slot_excess"] = out["active_slots"] - out["num_objects"]
  return out


def _region_metrics(colour: np.ndarray, scene: Scene, novel_views: np.ndarray) -> dict:
  """Novel-view PSNR split by source visibility, by object / background, and the background by
  distance to an object (`regions`)."""
  squared_error = np.mean((colour - scene.images[novel_views]) ** 2, axis=-1)  # [n, H, W]
  out = {}
  if scene.depth is not None:
    src = np.asarray(scene.source_indices, np.int64)
    seen = regions.seen_by_sources(
        depth=scene.depth[novel_views], cam_to_world=scene.cam_to_world[novel_views],
        intrinsics=scene.intrinsics[novel_views], source_depth=scene.depth[src],
        source_cam_to_world=scene.cam_to_world[src], source_intrinsics=scene.intrinsics[src])
    out.update(regions.split_metrics(squared_error=squared_error, region=~seen, inside="unseen",
                                     outside="seen"))
  if scene.masks is not None:
    masked = _views_with_mask(scene, novel_views)  # [n]
    if masked.any():
      masks, error = scene.masks[novel_views[masked]], squared_error[masked]
      out.update(regions.split_metrics(squared_error=error, region=masks > 0, inside="fg",
                                       outside="bg"))
      border = regions.object_border(masks, regions.border_radius(masks.shape[-1]))
      out.update(regions.region_metrics(squared_error=error, region=border, name="border"))
      out["psnr_novel_bg_far"] = regions.pooled_psnr(error, (masks == 0) & ~border)
  return out


def mean_over_scenes(per_scene: list[dict]) -> dict[str, float]:
  """{name: mean over the scenes that have a non-NaN value} (NaN when none has)."""
  keys = sorted({k for d in per_scene for k in d})
  return {k: metrics.summarize([d.get(k, math.nan) for d in per_scene]).mean for k in keys}


# ---------------------------------------------------------------------------------------------
# Loading a run: config check, data, checkpoint
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LoadedRun:
  """A trained run ready to render: the (data-resolved) config, model, parameters and scenes."""
  config: ml_collections.ConfigDict
  model: model_lib.SlotLifter
  params: dict
  step: int  # the checkpoint's training step
  checkpoint_dir: str  # DIR/checkpoints/{best,latest}/<step>
  scenes: list[Scene]
  split: str
  differs_from_training: dict  # `differences_from_training`
  parameters: str = "trained"  # "average" when the run's average of the parameters was restored


def differences_from_training(config, saved: dict) -> dict:
  """{'section.field': [saved, now]} for the settings that differ from training.

  The data and render settings, and the model fields that shape no parameter
  (`checkpoints.NOT_ARCHITECTURE`: the compute dtype, the slot attention iterations), may
  legitimately differ (another data root, more samples per ray, more iterations): they are
  warned about and recorded in metrics.json, not refused. The rest of the model section must
  match (check_compatible). The data root and how the same samples are computed (chunk size,
  adaptive rendering, recorded as "renderer") are left out.
  """
  changes = {field: values for field, values in ckpt_lib.config_changes(saved, config).items()
             if (field.split(".")[0] in ("data", "render") or field in ckpt_lib.NOT_ARCHITECTURE)
             and field not in ("data.root", "render.chunk")
             and not field.startswith("render.adaptive")}
  for field, (a, b) in changes.items():
    logging.warning("%s differs from the training run: saved %r, now %r", field, a, b)
  return changes


def load_run(config: ml_collections.ConfigDict, workdir: str, *, split: str,
             checkpoint: str = "", max_scenes: Optional[int] = None,
             params: str = "average") -> LoadedRun:
  """Checks `config` against DIR/config.json, resolves and loads the split, restores parameters:
  the run's average of them, when it keeps one (`train.ema_decay`), unless params="trained".

  Raises:
    EvalSetupError: unknown split or checkpoint name.
    FileNotFoundError: DIR is not a training run (no config.json or no checkpoint).
    checkpoints.CheckpointMismatchError: the model config or the parameter shapes differ, naming
      the fields / parameters.
    DataError: the split is missing or empty on disk.
  """
  if split not in registry.SPLITS:
    raise EvalSetupError(f"--split={split!r}: must be one of {', '.join(registry.SPLITS)}")
  if params not in averaging.PARAMS:
    raise EvalSetupError(f"--params={params!r}: must be one of {', '.join(averaging.PARAMS)}")
  saved = ckpt_lib.load_saved_config(workdir)
  if saved is None:
    raise FileNotFoundError(f"{ckpt_lib.config_path(workdir)}: not found; {workdir} is not a "
                            f"training run directory (train it first with --mode=train)")
  ckpt_lib.check_compatible(config, saved, workdir)
  try:  # render settings are read when the first scene renders: fail before any work instead
    config_checks.check_supersample(config.render)
    if config.render.get("adaptive", False):
      adaptive.AdaptiveSettings.from_config(config)
  except ValueError as e:
    raise EvalSetupError(str(e)) from e
  differs = differences_from_training(config, saved)
  config = multihost.primary_first(lambda: embedded.resolve_data(config), "data")  # generated once
  scenes = registry.load_split(config.data, split, max_scenes=max_scenes)
  # DTU/ScanNet training scenes pool their sources; evaluate them one target at a time, as the
  # readers already deliver the val and test splits.
  num_sources = int(config.data.num_source_views)
  scenes = [t for s in scenes for t in pipeline.per_target_scenes(s, num_source_views=num_sources)]
  if not scenes:
    raise DataError(f"{config.data.root}: split {split!r} has no scenes")
  model = model_lib.build_model(config)
  restored, used, step, step_dir = ckpt_lib.restore_params(
      model, config, workdir, scene=scenes[0], checkpoint=checkpoint, params=params)
  return LoadedRun(config=config, model=model, params=restored, step=step,
                   checkpoint_dir=step_dir, scenes=scenes, split=split,
                   differs_from_training=differs, parameters=used)


# ---------------------------------------------------------------------------------------------
# The evaluation of a split
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class EvalResult:
  split: str
  summary: dict[str, metrics.Summary]  # metric name → mean ± s.e. over scenes
  per_scene: list[dict[str, float]]
  scene_names: list[str]
  checkpoint_step: int
  checkpoint_dir: str
  timing: dict[str, float]
  metrics_path: str
  per_scene_path: str
  parameters: str = "trained"  # LoadedRun.parameters


def _finite_or_none(x: float) -> Optional[float]:
  return float(x) if x is not None and math.isfinite(x) else None


def _atomic_write(path: str, text: str) -> None:
  os.makedirs(os.path.dirname(path), exist_ok=True)
  tmp = path + ".tmp"
  with open(tmp, "w", newline="") as f:
    f.write(text)
  os.replace(tmp, path)


def _definitions(keys, *, lpips_net: str, lpips_quirk: bool, nv_ari_last_view: bool) -> dict:
  fill = dict(
      net={"alex": "AlexNet", "vgg": "VGG"}[lpips_net],
      quirk="quirk on: fed [0, 1] unchanged, as the official code" if lpips_quirk
      else "the official code feeds [0, 1]; --lpips_quirk reproduces that",
      nv_rule="uORF quirk on: the scene's last novel view only" if nv_ari_last_view
      else "averaged over all novel views of a scene")
  return {k: METRIC_DEFINITIONS[k].format(**fill) for k in keys}


def _ordered(keys) -> list[str]:
  known = [k for k in METRIC_DEFINITIONS if k in keys]
  return known + sorted(set(keys) - set(known))


def evaluate_split(config: ml_collections.ConfigDict, workdir: str, *, split: str = "test",
                   checkpoint: str = "", overwrite: bool = False,
                   max_scenes: Optional[int] = None, lpips_quirk: bool = False,
                   nv_ari_last_view: bool = False, progress: bool = True,
                   params: str = "average") -> EvalResult:
  """`--mode=eval`: renders every view of every scene of `split` and writes the metrics.

  Writes DIR/eval/<split>/metrics.json (summary, definitions, checkpoint, quirks, timing,
  provenance) and
  per_scene.csv. Refuses (FileExistsError, before any work) to replace an existing metrics.json
  unless `overwrite`. See `load_run` for the other errors.
  """
  t_start = time.perf_counter()
  out_dir = os.path.join(workdir, "eval", split)
  metrics_path = os.path.join(out_dir, "metrics.json")
  per_scene_path = os.path.join(out_dir, "per_scene.csv")
  if os.path.exists(metrics_path) and not overwrite:
    raise FileExistsError(f"{metrics_path} exists; pass --overwrite to replace it")
  multihost.barrier("eval_start")  # every process has checked before process 0 writes the file
  run = load_run(config, workdir, split=split, checkpoint=checkpoint, max_scenes=max_scenes,
                 params=params)
  net = lpips_net_for(run.config)
  renderer = adaptive.make_scene_renderer(run.model, run.config)  # render.adaptive switches
  t_setup = time.perf_counter() - t_start

  per_scene, render_s, metric_s, num_views = [], [], [], []
  for scene in tqdm(run.scenes, desc=f"eval {split}", unit="scene", dynamic_ncols=True,
                    disable=not progress):
    t0 = time.perf_counter()
    views = list(range(scene.num_views))
    rendered = renderer.render(run.params, scene, views)
    t1 = time.perf_counter()
    if not run.config.data.has_masks:
      scene = dataclasses.replace(scene, masks=None, mask_views=None)
    per_scene.append(scene_metrics(rendered, scene, views, image_metrics=True, lpips_net=net,
                                   lpips_quirk=lpips_quirk, nv_ari_last_view=nv_ari_last_view))
    render_s.append(t1 - t0)
    metric_s.append(time.perf_counter() - t1)
    num_views.append(len(views))

  keys = _ordered({k for d in per_scene for k in d})
  summary = {k: metrics.summarize([d.get(k, math.nan) for d in per_scene]) for k in keys}
  scene_s = np.add(render_s, metric_s)
  view_s = np.divide(render_s, num_views)  # [scenes] seconds to render one view
  timing = {
      "total_s": time.perf_counter() - t_start,
      "setup_s": t_setup,  # config check, data loading, checkpoint restore
      "scenes_s": float(scene_s.sum()),
      "per_scene_mean_s": float(scene_s.mean()),
      # The first scene also compiles the renderer (and LPIPS); the median is the steady rate.
      "per_scene_median_s": float(np.median(scene_s)),
      "first_scene_s": float(scene_s[0]),
      "render_s": float(np.sum(render_s)),
      "metrics_s": float(np.sum(metric_s)),
      # Seconds to render one full view: the median over the scenes after the first (which also
      # compiles the renderer), or the first when it is the only one.
      "render_per_view_s": float(np.median(view_s[1:] if view_s.size > 1 else view_s)),
  }
  names = [s.name for s in run.scenes]
  result = EvalResult(split=split, summary=summary, per_scene=per_scene, scene_names=names,
                      checkpoint_step=run.step, checkpoint_dir=run.checkpoint_dir, timing=timing,
                      metrics_path=metrics_path, per_scene_path=per_scene_path,
                      parameters=run.parameters)
  if not multihost.is_primary():  # every host evaluates the same scenes; one writes
    return result

  buf = io.StringIO()
  writer = csv.writer(buf)
  writer.writerow(["index", "scene", "num_views"] + keys)
  for i, (scene, row) in enumerate(zip(run.scenes, per_scene)):
    writer.writerow([i, scene.name, scene.num_views] +
                    [repr(float(row.get(k, math.nan))) for k in keys])
  _atomic_write(per_scene_path, buf.getvalue())

  report = {
      "split": split,
      "num_scenes": len(run.scenes),
      "image_size": list(run.scenes[0].image_size),
      "data_root": run.config.data.root,
      "checkpoint": {"step": run.step, "path": run.checkpoint_dir},
      # Which of a checkpoint's parameters: "average" (train.ema_decay > 0) or "trained".
      "parameters": run.parameters,
      "quirks": {"lpips_quirk": bool(lpips_quirk), "nv_ari_last_view": bool(nv_ari_last_view)},
      "lpips_net": net,
      # Adaptive rendering approximates the plain path; record that it was used.
      "renderer": ({k: run.config.render[k] for k in run.config.render if k.startswith("adaptive")}
                   if run.config.render.get("adaptive", False) else "plain"),
      # A metric of a run rendered otherwise than it was trained (e.g. more samples per ray)
      # must say so: {field: [trained with, evaluated with]}.
      "differs_from_training": run.differs_from_training,
      "metrics": {k: {"mean": _finite_or_none(s.mean), "stderr": _finite_or_none(s.stderr),
                      "count": s.count, "skipped": s.skipped} for k, s in summary.items()},
      "definitions": _definitions(keys, lpips_net=net, lpips_quirk=lpips_quirk,
                                  nv_ari_last_view=nv_ari_last_view),
      "aggregation": AGGREGATION,
      "timing": timing,
      "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
      # Config, commit, machine, jax version and wall time (slotlifter_jax/provenance.py).
      provenance.KEY: provenance.collect(run.config, wall_s=time.perf_counter() - t_start),
  }
  _atomic_write(metrics_path, json.dumps(report, indent=2, allow_nan=False) + "\n")
  return result


def format_table(result: EvalResult) -> str:
  """The means, standard errors and counts as a text table, with the evaluation time."""
  width = max([len("metric")] + [len(k) for k in result.summary]) + 2
  average = ", average of the parameters" if result.parameters == "average" else ""
  lines = [f"split {result.split}: {len(result.per_scene)} scenes, checkpoint step "
           f"{result.checkpoint_step} ({result.checkpoint_dir}){average}",
           f"{'metric':<{width}}{'mean':>10}{'s.e.':>10}{'n':>6}"]
  for k, s in result.summary.items():
    lines.append(f"{k:<{width}}{s.mean:>10.4f}{s.stderr:>10.4f}{s.count:>6d}")
  t = result.timing
  lines.append(f"time: {t['total_s']:.1f} s in all (setup {t['setup_s']:.1f} s); per scene "
               f"{t['per_scene_mean_s']:.2f} s mean, {t['per_scene_median_s']:.2f} s median "
               f"(first {t['first_scene_s']:.1f} s, with compilation)")
  lines.append(f"wrote {result.metrics_path}\n      {result.per_scene_path}")
  return "\n".join(lines)
