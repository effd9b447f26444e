"""Evaluation (SPEC §4): per-scene metrics of rendered views, and validation during training.

Source views: PSNR, ARI, FG-ARI. Novel views: PSNR (and SSIM/LPIPS in the full evaluation),
NV-ARI and NV-FG-ARI averaged over the novel views of a scene, then over scenes. Prediction =
argmax over the K real slots of the rendered segmentation.
"""

from __future__ import annotations

import os

import numpy as np

from slotlifter_jax import metrics
from slotlifter_jax import render_views
from slotlifter_jax import vis
from slotlifter_jax.data.types import Scene


def scene_metrics(rendered: render_views.RenderedViews, scene: Scene, view_indices) -> dict:
  """PSNR and segmentation metrics of one scene's rendered views, split into source and novel."""
  view_indices = list(view_indices)
  out = {}
  groups = {"source": [i for i, v in enumerate(view_indices) if v in scene.source_indices],
            "novel": [i for i, v in enumerate(view_indices) if v not in scene.source_indices]}
  for group, rows in groups.items():
    if not rows:
      continue
    views = [view_indices[i] for i in rows]
    psnrs = [metrics.psnr(pred=rendered.colour[i], target=scene.images[v]) for i, v in zip(rows, views)]
    out[f"psnr_{group}"] = float(np.mean(psnrs))
    if scene.masks is None:
      continue
    has = [scene.mask_views is None or bool(scene.mask_views[v]) for v in views]
    rows_m = [i for i, h in zip(rows, has) if h]
    views_m = [v for v, h in zip(views, has) if h]
    if not rows_m:
      continue
    pred = np.argmax(rendered.segmentation[rows_m], axis=-1).reshape(len(rows_m), -1)
    true = scene.masks[views_m].reshape(len(rows_m), -1)
    ari = metrics.ari(true_labels=true, pred_labels=pred)
    fg = metrics.ari(true_labels=true, pred_labels=pred, ignore_background=True)
    prefix = "" if group == "source" else "nv_"
    out[f"{prefix}ari"] = float(np.nanmean(ari))
    if np.any(np.isfinite(fg)):
      out[f"{prefix}fg_ari"] = float(np.nanmean(fg))
  return out


def mean_over_scenes(per_scene: list[dict]) -> dict:
  keys = sorted({k for d in per_scene for k in d})
  return {k: float(np.nanmean([d.get(k, np.nan) for d in per_scene])) for k in keys}


class Validator:
  """Renders a few validation scenes during training, scores them and writes a PNG panel."""

  def __init__(self, model, config, scenes: list[Scene], workdir: str, *, num_pictures: int = 3):
    self.renderer = render_views.SceneRenderer(model, config)
    self.scenes = scenes
    self.workdir = workdir
    self.num_pictures = num_pictures
    self.has_masks = bool(config.data.has_masks) and all(s.masks is not None for s in scenes)
    self.near, self.far = config.render.near, config.render.far

  def run(self, params, step: int) -> dict:
    per_scene, rows = [], []
    for n, scene in enumerate(self.scenes):
      views = list(range(scene.num_views))
      rendered = self.renderer.render(params, scene, views)
      per_scene.append(scene_metrics(rendered, scene, views))
      if n < self.num_pictures:
        v = scene.novel_indices[0] if scene.novel_indices else 0
        row = [scene.images[v], rendered.colour[v], vis.colour_segmentation(rendered.segmentation[v]),
               vis.colour_depth(rendered.depth[v], near=self.near, far=self.far)]
        if scene.masks is not None:
          row.insert(1, vis.colour_labels(scene.masks[v]))
        rows.append(row)
    result = mean_over_scenes(per_scene)
    result["score"] = result.get("nv_ari", np.nan) if self.has_masks else result.get("psnr_novel", np.nan)
    if not np.isfinite(result["score"]):
      result["score"] = -1.0
    if rows:
      vis.save_png(os.path.join(self.workdir, "val", f"step_{step:07d}.png"), vis.grid(rows))
    return result
