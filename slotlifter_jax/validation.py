"""Validation during training (docs/method.md §4, §6): a few fixed validation scenes rendered,
scored with evaluate.scene_metrics, checked for collapse and drawn into a PNG panel.

The training loop imports this module; evaluation does not. Keeping the Validator out of
evaluate.py lets the dependency run one way (train → validation → evaluate) instead of in a cycle.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from slotlifter_jax import collapse
from slotlifter_jax import config_checks
from slotlifter_jax import evaluate
from slotlifter_jax import metrics
from slotlifter_jax import schedules
from slotlifter_jax import vis
from slotlifter_jax.data.types import Scene
from slotlifter_jax.rendering import views as views_lib


def collapse_statistics(*, segmentation, rendered, target, foreground=None) -> dict[str, float]:
  """Run-level collapse flag and its statistics for probe views (slotlifter_jax.collapse).

  segmentation [n, N, K], rendered / target colours [n, N, 3], foreground [n, N] bool or None
  (sets without masks: every pixel counts). Returns floats for the metric log: `collapsed` (1/0),
  one flag per reason, and the probe's largest slot share, active slots and pixel entropy.
  """
  usage = collapse.slot_usage(segmentation=segmentation, foreground_mask=foreground)
  brightness = collapse.black_render(rendered=rendered, target=target)
  verdict = collapse.is_collapsed(usage, brightness=brightness)
  has_fg = np.asarray(usage.foreground_pixels) > 0
  mean = lambda x: float(np.mean(np.asarray(x, np.float64)[has_fg])) if has_fg.any() else math.nan
  return dict(
      collapsed=float(verdict.collapsed), collapse_dominant_slot=float(verdict.dominant_slot),
      collapse_too_few_active=float(verdict.too_few_active),
      collapse_near_uniform=float(verdict.near_uniform), collapse_black=float(verdict.black),
      probe_largest_share=mean(usage.largest_share), probe_active_slots=mean(usage.active_slots),
      probe_pixel_entropy=mean(usage.pixel_entropy))


def mask_free_statistics(*, novel_segmentation, source_segmentation,
                         source_attention) -> dict[str, float]:
  """How the model splits its validation scenes, from its own outputs only: no mask is read, so
  a set without ground truth (a capture, the kitchens) gets the same numbers as one with it.

  novel_segmentation [n, N, K] rendered on the novel views, source_segmentation [m, N, K] rendered
  on the source views, source_attention [m, N] int: slot attention's slot per source pixel.
  Returns, over every pixel (the background slot counts as one slot):
  - mf_active_slots: slots owning ≥ 1 % of a novel view's pixels, mean over views; a run that puts
    the scene in one or two slots has not split it, whatever its colours;
  - mf_largest_share: the largest slot's share of a novel view's pixels, mean over views;
  - mf_pixel_entropy: the mean per-pixel slot entropy / log K (1: every pixel shared evenly);
  - mf_attn_agreement: ARI between the decoder's split of the source view and slot attention's
    grouping of it, mean over source views: the two agree once the rendered slots are the groups
    slot attention found.
  """
  usage = collapse.slot_usage(segmentation=novel_segmentation, foreground_mask=None)
  rendered_labels = np.argmax(np.asarray(source_segmentation), axis=-1)
  agreement = metrics.ari(true_labels=np.asarray(source_attention), pred_labels=rendered_labels)
  mean = lambda x: float(np.mean(np.asarray(x, np.float64)))
  return dict(mf_active_slots=mean(usage.active_slots), mf_largest_share=mean(usage.largest_share),
              mf_pixel_entropy=mean(usage.pixel_entropy), mf_attn_agreement=mean(agreement))


def selection_score(result: dict, select_by: str, *, has_masks: bool) -> float:
  """The number the best checkpoint maximises (docs/method.md §4; `train.select_by`).

  "nv_ari"; "min_fg_nv", the worse of FG-ARI and NV-ARI, so that a checkpoint whose scene
  segmentation improved while its objects merged does not win; "psnr_novel". A set without masks
  has no ARI, so it is always scored by novel-view PSNR. Not finite (no foreground in any view):
  −1, below any real score.
  """
  problem = config_checks.selection_problem({"select_by": select_by})
  if problem:
    raise ValueError(problem)
  if not has_masks or select_by == "psnr_novel":
    score = result.get("psnr_novel", np.nan)
  elif select_by == "min_fg_nv":
    score = np.minimum(result.get("fg_ari", np.nan), result.get("nv_ari", np.nan))
  else:
    score = result.get("nv_ari", np.nan)
  return float(score) if np.isfinite(score) else -1.0


class Validator:
  """Renders a few validation scenes during training, scores them and writes a PNG panel."""

  def __init__(self, model, config, scenes: list[Scene], workdir: str, *, num_pictures: int = 3,
               write_pictures: bool = True):
    self.renderer = views_lib.SceneRenderer(model, config)
    self.scenes = scenes
    self.workdir = workdir
    self.num_pictures = num_pictures
    # False on the processes other than process 0 of a multi-process run: they score, never write.
    self.write_pictures = write_pictures
    self.use_masks = bool(config.data.has_masks)  # never score made-up masks (docs/method.md §3.3)
    self.has_masks = self.use_masks and all(s.masks is not None for s in scenes)
    self.near, self.far = config.render.near, config.render.far
    self.locality_steps = int(config.train.locality_steps)
    self.select_by = config.train.get("select_by", "nv_ari")

  def run(self, params, step: int) -> dict:
    # `step` updates have been applied, so the next training step is `step`.
    locality = bool(schedules.locality_on(step, steps=self.locality_steps))
    per_scene, rows = [], []
    probe_seg, probe_fg, probe_rgb, probe_target = [], [], [], []
    source_seg, source_attn = [], []
    for n, scene in enumerate(self.scenes):
      views = list(range(scene.num_views))
      rendered = self.renderer.render(params, scene, views, locality=locality)
      if not self.use_masks:
        scene = dataclasses.replace(scene, masks=None, mask_views=None)
      per_scene.append(evaluate.scene_metrics(rendered, scene, views))
      # The fixed validation scenes are the collapse probe (docs/method.md §6): their novel views.
      novel = list(scene.novel_indices)
      probe_seg.append(rendered.segmentation[novel].reshape(len(novel), -1,
                                                             rendered.segmentation.shape[-1]))
      probe_rgb.append(rendered.colour[novel].reshape(len(novel), -1, 3))
      probe_target.append(scene.images[novel].reshape(len(novel), -1, 3))
      src = list(scene.source_indices)
      source_seg.append(rendered.segmentation[src].reshape(len(src), -1,
                                                           rendered.segmentation.shape[-1]))
      source_attn.append(np.asarray(rendered.source_labels).reshape(len(src), -1))
      if self.has_masks:
        probe_fg.append((scene.masks[novel] > 0).reshape(len(novel), -1))
      if n < self.num_pictures:
        v = scene.novel_indices[0] if scene.novel_indices else 0
        row = [scene.images[v], rendered.colour[v],
               vis.colour_segmentation(rendered.segmentation[v]),
               vis.colour_depth(rendered.depth[v], near=self.near, far=self.far)]
        if scene.masks is not None:
          row.insert(1, vis.colour_labels(scene.masks[v]))
        rows.append(row)
    result = evaluate.mean_over_scenes(per_scene)
    if probe_seg:
      result.update(collapse_statistics(
          segmentation=np.concatenate(probe_seg), rendered=np.concatenate(probe_rgb),
          target=np.concatenate(probe_target),
          foreground=np.concatenate(probe_fg) if self.has_masks else None))
    if source_seg:
      result.update(mask_free_statistics(
          novel_segmentation=np.concatenate(probe_seg),
          source_segmentation=np.concatenate(source_seg),
          source_attention=np.concatenate(source_attn)))
    result["score"] = selection_score(result, self.select_by, has_masks=self.has_masks)
    if rows and self.write_pictures:
      vis.save_png(os.path.join(self.workdir, "val", f"step_{step:07d}.png"), vis.grid(rows))
    return result
