"""Is what one view lifts placed right in depth? Novel views against the truth, pixel by pixel.

  python experiments/depth_placement.py --workdir=DIR [--split=val --scenes=100
      --checkpoint=best --params=average --out=experiments/results/NAME.json]

With one source view, a novel view's pixel shows either a surface the source view sees or one it
does not. The evaluation reports the two kinds' PSNR apart (`psnr_novel_seen`,
slotlifter_jax/regions.py); this script asks whether the model puts what the source sees at the
right depth, with ground-truth depth (the embedded sets store it), on the pixels the source sees,
split into background and objects:

  PSNR             the rendering's PSNR, pooled over the region's pixels of a scene's novel views
  displacement     median distance in source pixels between where the model's surface point (its
                   expected depth along the novel ray) and the true one project into the source
                   view: 0 when placed right; a point behind the source camera counts as infinite
  relative depth   median |z_model − z_true| / z_true, z the camera depth
  depth bias       median (z_model − z_true) / z_true: > 0 when the model puts the surface too
                   deep; also on the source view itself, where every pixel is seen
  opacity          mean Σ_i w_i along the novel rays and the source view's rays (docs/method.md
                   §1.5): below 1 the ray's remainder goes to the far plane, in the expected
                   depth as in the colour, which has no background added

The colour does not come from the source image: a point's colour is decoded from its slot
feature F_s = Linear(W·S') and its position (docs/method.md §1.4), so the lifted features reach it
only through the mapping W. What one view shows therefore constrains the geometry (the density
and W) more directly than the colour.

For the split, NV-ARI (all pixels, background included, docs/method.md §4) of the novel views
on the pixels the source sees and on those it does not, against the source view's own rendered
split carried to the novel view by the true geometry (each seen pixel takes the rendered label of
the source pixel nearest its true point's projection): the NV-ARI the seen pixels would read if
the model placed the source view's split at the right depth. Where that transported split reads
far above the model's own, the placement loses the split; where they read alike, the source
view's split itself is the limit.

Nothing here reads the test split unless --split says so.
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

from experiments import diagnose_slots  # noqa: E402

REGIONS = ("seen", "seen_bg", "seen_fg")


def project(points: np.ndarray, *, cam_to_world: np.ndarray,
            intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Homogeneous world points [..., 4] → pixel coordinates [..., 2] (centres at integers) and
  whether each lies in front of the camera (`regions.project_points`)."""
  from slotlifter_jax import geometry
  from slotlifter_jax import regions
  u, v, z = regions.project_points(points, cam_to_world=cam_to_world, intrinsics=intrinsics)
  return np.stack([u, v], -1), z > geometry.MIN_DEPTH


def nearest(labels: np.ndarray, uv: np.ndarray) -> np.ndarray:
  """labels [H, W] at the pixel nearest each coordinate of uv [..., 2], clamped to the image."""
  h, w = labels.shape
  col = np.clip(np.rint(uv[..., 0]), 0, w - 1).astype(np.int64)
  row = np.clip(np.rint(uv[..., 1]), 0, h - 1).astype(np.int64)
  return labels[row, col]


def camera_z(distance: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
  """Distance along each pixel's unit ray [H, W] → camera z [H, W] (the stored depth's kind)."""
  from slotlifter_jax import geometry
  h, w = distance.shape
  pix = np.asarray(geometry.image_pixels(h, w), np.float64)
  ray = geometry.pix_to_cam(pix=pix, intrinsics=np.asarray(intrinsics, np.float64), xp=np)
  return distance / np.linalg.norm(ray, axis=-1)


def region_ari(true: np.ndarray, pred: np.ndarray, region: np.ndarray) -> float:
  """ARI (background included) of one view's labels [H, W] over the pixels of `region`; NaN when
  fewer than two pixels lie in it."""
  from slotlifter_jax import metrics
  t, p = true[region], pred[region]
  if t.size < 2:
    return float("nan")
  return float(metrics.ari(true_labels=t[None], pred_labels=p[None])[0])


def scene_placement(*, images, masks, depth, cam_to_world, intrinsics, source: int,
                    novel: list[int], colour, rendered_distance, labels, opacity=None) -> dict:
  """One scene's figures (module docstring). Arrays are the scene's views; colour [n, H, W, 3],
  rendered_distance, labels and opacity [n, H, W] are the model's, for views [source] + novel
  (opacity None: its figures are left out)."""
  from slotlifter_jax import regions
  src = dict(cam_to_world=cam_to_world[source], intrinsics=intrinsics[source])
  sq = []
  disp = {r: [] for r in REGIONS}
  rel = {r: [] for r in REGIONS}
  bias = {r: [] for r in REGIONS}
  region_masks = {r: [] for r in REGIONS}
  ari = {"nv_ari_seen": [], "nv_ari_unseen": [], "nv_ari_seen_transported": []}
  for i, view in enumerate(novel, start=1):
    true_pts = regions.surface_points(depth=depth[view], cam_to_world=cam_to_world[view],
                                      intrinsics=intrinsics[view])
    seen = regions.seen_by_source(points=true_pts, source_depth=depth[source],
                                  source_cam_to_world=cam_to_world[source],
                                  source_intrinsics=intrinsics[source])
    z_model = camera_z(rendered_distance[i], intrinsics[view])
    model_pts = regions.surface_points(depth=z_model, cam_to_world=cam_to_world[view],
                                       intrinsics=intrinsics[view])
    uv_true, _ = project(true_pts, **src)
    uv_model, ahead = project(model_pts, **src)
    sq.append(np.mean((colour[i] - images[view]) ** 2, -1))
    fg = masks[view] > 0
    # A model's point behind the source camera lands nowhere near the true one.
    d = np.where(ahead, np.linalg.norm(uv_model - uv_true, axis=-1), np.inf)
    for name, where in (("seen", seen), ("seen_bg", seen & ~fg), ("seen_fg", seen & fg)):
      region_masks[name].append(where)
      disp[name].append(d[where])
      zt = depth[view][where]
      bias[name].append((z_model[where] - zt) / zt)
      rel[name].append(np.abs(bias[name][-1]))
    ari["nv_ari_seen"].append(region_ari(masks[view], labels[i], seen))
    ari["nv_ari_unseen"].append(region_ari(masks[view], labels[i], ~seen))
    transported = nearest(labels[0], uv_true)
    ari["nv_ari_seen_transported"].append(region_ari(masks[view], transported, seen))
  out = {}
  if opacity is not None:
    mean_in = lambda x, where: float(x[where].mean()) if where.any() else float("nan")
    seen_all = np.stack(region_masks["seen"])  # [n − 1, H, W]
    fg_all = np.stack([masks[v] > 0 for v in novel])
    out["opacity_seen_bg"] = mean_in(opacity[1:], seen_all & ~fg_all)
    out["opacity_seen_fg"] = mean_in(opacity[1:], seen_all & fg_all)
    out["opacity_source_bg"] = mean_in(opacity[0], masks[source] == 0)
    out["opacity_source_fg"] = mean_in(opacity[0], masks[source] > 0)
  z_source = camera_z(rendered_distance[0], intrinsics[source])
  source_bias = (z_source - depth[source]) / depth[source]
  fg_source, finite = masks[source] > 0, np.isfinite(depth[source])
  for name, where in (("bg", ~fg_source & finite), ("fg", fg_source & finite)):
    out[f"depth_bias_source_{name}"] = (float(np.median(source_bias[where])) if where.any()
                                        else float("nan"))
  for r in REGIONS:
    where = np.stack(region_masks[r])
    out[f"psnr_{r}"] = regions.pooled_psnr(np.stack(sq), where)
    d, e = np.concatenate(disp[r]), np.concatenate(rel[r])
    out[f"displacement_px_{r}"] = float(np.median(d)) if d.size else float("nan")
    out[f"relative_depth_error_{r}"] = float(np.median(e)) if e.size else float("nan")
    b = np.concatenate(bias[r])
    out[f"depth_bias_{r}"] = float(np.median(b)) if b.size else float("nan")
    out[f"pixel_share_{r}"] = float(where.mean())
  with np.errstate(invalid="ignore"):
    out.update({k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
                for k, v in ((k, np.asarray(v)) for k, v in ari.items())})
  return out


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  diagnose_slots.add_run_arguments(p)
  p.add_argument("--params", default="average", help="average | trained")
  p.add_argument("--out", default="", help="write the means and the per-scene figures here")
  args = p.parse_args(argv)

  from slotlifter_jax import metrics
  from slotlifter_jax import provenance
  from slotlifter_jax.rendering import views as views_lib

  run = diagnose_slots.load_run(args, params=args.params)
  renderer = views_lib.SceneRenderer(run.model, run.config)
  per_scene = []
  t0 = time.perf_counter()
  for n, scene in enumerate(run.scenes):
    if scene.masks is None or scene.depth is None:
      raise SystemExit(f"{args.workdir}: split {args.split!r} has no ground-truth masks or depth; "
                       f"only the embedded sets store both")
    source = int(np.asarray(scene.source_indices)[0])
    novel = [v for v in range(scene.num_views) if v not in set(np.asarray(scene.source_indices))]
    out = renderer.render(run.params, scene, [source] + novel)
    row = scene_placement(images=scene.images, masks=scene.masks, depth=scene.depth,
                          cam_to_world=scene.cam_to_world, intrinsics=scene.intrinsics,
                          source=source, novel=novel, colour=np.asarray(out.colour),
                          rendered_distance=np.asarray(out.depth),
                          labels=metrics.segmentation_from_render(out.segmentation),
                          opacity=None if out.opacity is None else np.asarray(out.opacity))
    per_scene.append(dict(scene=n, **row))
    if n == 0 or (n + 1) % 10 == 0:
      print(f"  scene {n + 1}/{len(run.scenes)} ({time.perf_counter() - t0:.0f} s)", flush=True)
  keys = [k for k in per_scene[0] if k != "scene"]
  means = {k: float(np.nanmean([r[k] for r in per_scene])) for k in keys}
  print(f"{args.workdir}: step {run.step} ({run.parameters} parameters), {len(run.scenes)} "
        f"{args.split} scenes; the novel views' pixels the source sees:")
  for r in REGIONS:
    print(f"  {r:8s} share {means[f'pixel_share_{r}']:.3f}  PSNR {means[f'psnr_{r}']:.2f}  "
          f"displacement "
          f"{means[f'displacement_px_{r}']:.2f} px  relative depth error "
          f"{means[f'relative_depth_error_{r}']:.3f}  depth bias {means[f'depth_bias_{r}']:+.3f}")
  print(f"  source view's depth bias: background {means['depth_bias_source_bg']:+.3f}, objects "
        f"{means['depth_bias_source_fg']:+.3f}")
  if "opacity_seen_bg" in means:
    print(f"  opacity, background / objects: novel views' seen pixels "
          f"{means['opacity_seen_bg']:.3f} / {means['opacity_seen_fg']:.3f}, source view "
          f"{means['opacity_source_bg']:.3f} / {means['opacity_source_fg']:.3f}")
  print(f"  NV-ARI seen {means['nv_ari_seen']:.3f}, unseen {means['nv_ari_unseen']:.3f}; the "
        f"source view's rendered split carried to the seen pixels by the true geometry "
        f"{means['nv_ari_seen_transported']:.3f}")
  # s_σ, the learned log scale of the density (docs/method.md §1.4), which the opacity follows.
  log_density_scale = float(np.asarray(run.params["allocation"]["log_density_scale"]))
  print(f"  learned log density scale s_σ {log_density_scale:.3f}")
  if args.out:
    record = dict(means=means, per_scene=per_scene, log_density_scale=log_density_scale,
                  workdir=args.workdir, split=args.split,
                  scenes=len(run.scenes), step=int(run.step), parameters=run.parameters,
                  checkpoint=args.checkpoint, seconds=round(time.perf_counter() - t0, 1),
                  provenance=provenance.collect(run.config))
    tmp = args.out + ".tmp"
    with open(tmp, "w") as f:
      json.dump(record, f, indent=1, default=lambda x: x.item() if hasattr(x, "item") else str(x))
    os.replace(tmp, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
