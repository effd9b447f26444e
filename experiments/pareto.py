"""Speed/accuracy chart (issue #6): what rays, samples, resolution and encoder width buy.

  python experiments/pareto.py --dry_run        # the plan and its estimated time, nothing run
  python experiments/pareto.py                  # train + evaluate every point, then plot
  python experiments/pareto.py --plot_only      # redraw from experiments/results/pareto.csv
  python experiments/pareto.py --grid=scene --eval_scenes=100   # around `scene`, 50 000 steps

Base: configs/clevr.py:paper_cpu on the embedded clevr set (64², 32 samples, 2 scenes × 256 rays, the
narrow ResNet-18-style encoder). Each point changes one axis of the base, plus one cheap corner,
rather than the full product (POINTS below, 7 runs, one seed):
  base          the paper_cpu config
  rays512/1024  train.rays_per_scene 512 / 1024 (cost per step ∝ rays)
  samples16     render.num_samples 16 (training and rendering ∝ samples)
  res32         data.image_size 32 (its own 32² set; rendering ∝ pixels; metrics at 32²)
  wide_encoder  encoder stem 64, widths (64, 128, 256), D = 64 (blocks stay (2, 2, 2))
  cheap         32² and 16 samples together
Every run trains --num_steps steps with the schedules scaled to the budget (study_common.py) and is
evaluated on the first --eval_scenes test scenes. Per point the CSV holds training wall-clock
seconds, render seconds per view, PSNR, ARI, FG-ARI, NV-ARI, NV-FG-ARI, active slots and the
collapse flag; the figure plots novel-view PSNR and FG-ARI against training time and against render
time per view, with the Pareto front (lower time, higher metric) as a step line and larger markers.
Note that PSNR and ARI at 32² are measured at 32², so they are not the same task as at 64².

`--grid=scene` draws the same chart around configs/clevr.py:scene at its own budget (50 000 steps,
the schedules unscaled), where the model decomposes, so the FG-ARI axis measures decomposition
rather than noise (SCENE_POINTS: samples per ray 8 / 32 against 16, rays per scene 64 / 256
against 128, slot width 64, 4 allocation blocks, colour MLP width 64). Its files keep the
variant's former name, pareto_fast.csv/.md/.png. Its `base` run is the same run directory as
`ablations.py --config=configs/clevr.py:scene`'s `full` (study_common.run_id), so the two studies
share it. About 80 min per point alone on the 2026-11-27 host (seed 3 of `scene`: 79.5 min).

Time: 45 min measured on the 2-core CPU for the defaults (600 steps, 20 scenes; 19:17–20:11 on
2026-11-22, experiments/journal/2026-11.md); --dry_run prints an estimate from the cost model in
study_common.py (0.3 s per paper_cpu step, 2.6 s per 64² scene). The
32² set is generated once (about a minute) before its first run. Runs live in --root (default
runs/study/, shared with ablations.py and stability.py); a finished run is skipped, so running the
script again resumes where it stopped.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common as sc  # noqa: E402  (no JAX import)
from experiments import study_tables as st  # noqa: E402

BASE = "configs/clevr.py:paper_cpu"
NUM_STEPS = 600  # per run: the seven points in about 45 min (experiments/journal/2026-11.md)
WIDE_ENCODER = {"model.encoder_stem_width": 64, "model.encoder_widths": (64, 128, 256),
                "model.feature_dim": 64}
POINTS = {
    "base": {},
    "rays512": {"train.rays_per_scene": 512},
    "rays1024": {"train.rays_per_scene": 1024},
    "samples16": {"render.num_samples": 16},
    "res32": {"data.image_size": 32},
    "wide_encoder": WIDE_ENCODER,
    "cheap": {"data.image_size": 32, "render.num_samples": 16},
}
# One axis of `scene` at a time, each side of its value: what the scene-sized model's cuts cost.
SCENE_POINTS = {
    "base": {},
    "samples8": {"render.num_samples": 8},
    "samples32": {"render.num_samples": 32},
    "rays64": {"train.rays_per_scene": 64},
    "rays256": {"train.rays_per_scene": 256},
    "slots64": {"model.slot_dim": 64, "model.slot_mlp_dim": 128},
    "blocks4": {"model.num_blocks": 4},
    # Colour per point, not the allocation to slots: PSNR that need not cost the split?
    "colour64": {"model.colour_hidden": 64},
}
# --grid: (base config, points, budget, file stem); budget None: the config's own train.num_steps.
GRIDS = {"paper_cpu": (BASE, POINTS, NUM_STEPS, "pareto"),
         "scene": ("configs/clevr.py:scene", SCENE_POINTS, None, "pareto_fast")}
# (CSV column, axis label) of the figure's rows and columns.
METRICS = (("psnr_novel", "novel-view PSNR (dB)"), ("fg_ari", "FG-ARI"))
COSTS = (("train_s", "training wall-clock (s)"), ("render_per_view_s", "render time per view (s)"))


def plan(*, config: str = BASE, num_steps: int = NUM_STEPS, seed: int = 0,
         points: dict = POINTS) -> list[sc.Run]:
  return [sc.Run(name=name, config=config, overrides=overrides, seed=seed, num_steps=num_steps)
          for name, overrides in points.items()]


def plot(rows: list[dict], out: str, *, base: str = BASE) -> None:
  """2×2: METRICS (rows) against COSTS (columns); the Pareto front as a step line."""
  import matplotlib
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt
  fig, axes = plt.subplots(len(METRICS), len(COSTS), figsize=(10, 7.5), squeeze=False)
  for i, (metric, metric_label) in enumerate(METRICS):
    for j, (cost, cost_label) in enumerate(COSTS):
      ax = axes[i][j]
      xs = [float(r.get(cost, math.nan)) for r in rows]
      ys = [float(r.get(metric, math.nan)) for r in rows]
      front = st.pareto_front(xs, ys)
      ax.scatter(xs, ys, s=25, c="tab:gray", label="run")
      if front:
        fx, fy = [xs[k] for k in front], [ys[k] for k in front]
        # Best value reachable at a given cost: flat until the next front point ("post").
        ax.step(fx, fy, where="post", c="tab:red", lw=1.2, label="Pareto front")
        ax.scatter(fx, fy, s=70, c="tab:red", zorder=3)
      for x, y, r in zip(xs, ys, rows):
        if not (math.isnan(x) or math.isnan(y)):
          ax.annotate(str(r["name"]), (x, y), fontsize=7, xytext=(3, 3),
                      textcoords="offset points")
      ax.set_xscale("log")
      ax.set_xlabel(cost_label)
      ax.set_ylabel(metric_label)
      ax.grid(alpha=0.3)
      if i == 0 and j == 0:
        ax.legend(fontsize=8)
  steps = sorted({int(r["num_steps"]) for r in rows})
  fig.suptitle(f"speed vs accuracy, {base} variations, {'/'.join(map(str, steps))} steps, "
               f"{rows[0]['eval_scenes'] if rows else '?'} {rows[0]['eval_split'] if rows else ''} "
               f"scenes", fontsize=10)
  fig.tight_layout()
  os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
  fig.savefig(out, dpi=90)
  plt.close(fig)


def table(rows: list[dict], *, base: str = BASE) -> str:
  """pareto.md: one row per point; '*' marks the points on the PSNR / FG-ARI fronts over
  training time (the figure's left column), `R` those over render time (its right column)."""
  marks = {}
  for metric, _ in METRICS:
    for cost, tag in (("train_s", "*"), ("render_per_view_s", "R")):
      front = st.pareto_front([float(r.get(cost, math.nan)) for r in rows],
                              [float(r.get(metric, math.nan)) for r in rows])
      for k in front:
        marks.setdefault((k, metric), set()).add(tag)
  steps = sorted({int(r["num_steps"]) for r in rows})
  head = (f"# Speed vs accuracy ({base} variations, {'/'.join(map(str, steps))} steps, "
          f"{rows[0]['eval_scenes'] if rows else '?'} {rows[0]['eval_split'] if rows else ''} "
          f"scenes per run)\n\n"
          f"Training time includes compilation and in-training validation; render time is one full "
          f"view at evaluation. * on the front over training time, R over render time. Written by "
          f"experiments/pareto.py on {time.strftime('%Y-%m-%d %H:%M')}.\n\n")
  cols = ["point", "overrides", "train s", "s/step", "render s/view", "PSNR (dB)", "SSIM",
          "FG-ARI", "NV-ARI", "active slots", "collapsed"]
  lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
  for k, r in enumerate(rows):
    cell = lambda key, digits: st.format_value(r.get(key, math.nan), digits=digits)
    mark = lambda m: "".join(sorted(marks.get((k, m), ())))
    overrides = r.get("overrides", {})
    if isinstance(overrides, str):  # as the CSV holds it
      overrides = json.loads(overrides or "{}")
    lines.append("| " + " | ".join([
        str(r["name"]), ", ".join(f"{a}={b}" for a, b in overrides.items()) or "–",
        cell("train_s", 0), cell("step_s", 3), cell("render_per_view_s", 2),
        cell("psnr_novel", 2) + mark("psnr_novel"), cell("ssim", 3),
        cell("fg_ari", 3) + mark("fg_ari"), cell("nv_ari", 3), cell("active_slots", 2),
        cell("collapsed", 0)]) + " |")
  return head + "\n".join(lines) + "\n"


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--root", default=sc.DEFAULT_ROOT, help="where the run directories go")
  p.add_argument("--results_dir", default=sc.RESULTS_DIR, help="where pareto.csv/.md/.png go")
  p.add_argument("--grid", default="paper_cpu", choices=sorted(GRIDS),
                 help="paper_cpu: variations of configs/clevr.py:paper_cpu; scene: of configs/clevr.py:scene")
  p.add_argument("--num_steps", type=int, default=None,
                 help=f"training budget per run (default: the grid's, {NUM_STEPS} for paper_cpu)")
  p.add_argument("--eval_scenes", type=int, default=20, help="test scenes evaluated per run")
  p.add_argument("--eval_split", default="test")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--points", default="", help="a subset of the grid's points (default: all)")
  p.add_argument("--dry_run", action="store_true", help="print the plan and estimate; run nothing")
  p.add_argument("--plot_only", action="store_true", help="redraw from the CSV; run nothing")
  return p.parse_args(argv)


def main(argv=None) -> None:
  args = parse_args(argv)
  base, grid_points, budget, stem = GRIDS[args.grid]
  names = args.points.split(",") if args.points else list(grid_points)
  unknown = [n for n in names if n not in grid_points]
  if unknown:
    raise SystemExit(f"--points: unknown points {unknown} for --grid={args.grid}; choose from "
                     f"{list(grid_points)}")
  points = {n: grid_points[n] for n in names}
  if budget is None:
    budget = int(sc.load_config(base).train.num_steps)
  runs = plan(config=base, num_steps=args.num_steps or budget, seed=args.seed, points=points)
  csv_path = os.path.join(args.results_dir, f"{stem}.csv")
  png_path = os.path.join(args.results_dir, f"{stem}.png")
  md_path = os.path.join(args.results_dir, f"{stem}.md")
  rows = sc.run_study(runs, study="pareto", root=args.root, eval_split=args.eval_split,
                      eval_scenes=args.eval_scenes, csv_path=csv_path, dry_run=args.dry_run,
                      from_csv_only=args.plot_only)
  if rows is None:
    return
  plot(rows, png_path, base=base)
  text = table(rows, base=base)
  st.write_text(md_path, text)
  print(text)
  print(f"[pareto] wrote {csv_path}, {md_path} and {png_path}")


if __name__ == "__main__":
  from slotlifter_jax import runtime  # no JAX import
  if "--dry_run" not in sys.argv:
    runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  main()
