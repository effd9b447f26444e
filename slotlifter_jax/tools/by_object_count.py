"""An evaluation's per-scene metrics grouped by the scenes' object count.

  python -m slotlifter_jax.tools.by_object_count EVAL [EVAL ...] [--metrics=fg_ari,nv_ari,...]

Each EVAL is an evaluation folder, DIR/eval/<split>, as `python -m slotlifter_jax.main
--mode=eval` writes it (metrics.json and per_scene.csv). For sets whose scenes hold different
numbers of objects (the embedded room family: 1–4 for K = 5 slots) a mean over all scenes mixes
two different failures: on a one-object view FG-ARI is 1 when the object lies in one slot and 0
as soon as any of its pixels falls in another (the adjusted index of a single true cluster,
docs/method.md §4), so a lone object split over two slots costs a whole scene, while on views of
several objects FG-ARI measures how they are told apart. Prints, per folder, one markdown row per
object count: scenes, then each metric's mean ± standard error over those scenes (NaN values,
e.g. `fg_ari_multi` on one-object scenes, left out). Nothing is written.
"""

from __future__ import annotations

import argparse
import math
import sys

from slotlifter_jax.tools import group_stats
from slotlifter_jax.tools import metrics_table
from slotlifter_jax.tools import paired_eval

DEFAULT_METRICS = ("fg_ari", "nv_ari", "active_slots", "psnr_novel")


class ByCountError(ValueError):
  """A folder without object counts or a metric it lacks; the message names it."""


def group_by_count(rows: dict[str, dict[str, float]], metrics, *, source: str) -> dict:
  """{object count: {"scenes": n, metric: group_stats.Stat}} over the per-scene rows."""
  groups: dict[int, list[dict[str, float]]] = {}
  for scene, values in rows.items():
    if "num_objects" not in values:
      raise ByCountError(f"{source}: no num_objects column; evaluate with a set that has masks")
    count = values["num_objects"]
    if math.isnan(count) or count != int(count):
      raise ByCountError(f"{source}: scene {scene} has num_objects = {count}, not a count")
    groups.setdefault(int(count), []).append(values)
  out = {}
  for count in sorted(groups):
    scenes = groups[count]
    out[count] = {"scenes": len(scenes)}
    for m in metrics:
      if m not in scenes[0]:
        raise ByCountError(f"{source}: no {m} column (it has {', '.join(sorted(scenes[0]))})")
      out[count][m] = group_stats.stat(s[m] for s in scenes)
  return out


def format_table(groups: dict, metrics) -> str:
  lines = ["| objects | scenes | " + " | ".join(metrics) + " |",
           "|---" * (2 + len(metrics)) + "|"]
  for count, g in groups.items():
    cells = []
    for m in metrics:
      s = g[m]
      digits = metrics_table.DIGITS.get(m, 3)
      if s.n == 0:
        cells.append("–")
      elif s.n == 1:
        cells.append(f"{s.mean:.{digits}f}")
      else:
        cells.append(f"{s.mean:.{digits}f} ± {s.std / math.sqrt(s.n):.{digits}f}")
    lines.append(f"| {count} | {g['scenes']} | " + " | ".join(cells) + " |")
  return "\n".join(lines)


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("evals", nargs="+", metavar="EVAL", help="evaluation folders DIR/eval/<split>")
  p.add_argument("--metrics", default=",".join(DEFAULT_METRICS),
                 help="comma-separated per_scene.csv columns")
  args = p.parse_args(argv)
  metrics = [m for m in args.metrics.split(",") if m]
  try:
    for folder in args.evals:
      meta, rows = paired_eval.read_eval(folder)
      groups = group_by_count(rows, metrics, source=f"{folder}/per_scene.csv")
      step = meta.get("checkpoint", {}).get("step", "?")
      print(f"{folder}: split {meta.get('split', '?')}, {len(rows)} scenes, checkpoint step "
            f"{step}, {meta.get('parameters', '?')} parameters")
      print(format_table(groups, metrics))
  except (paired_eval.PairedEvalError, ByCountError) as e:
    print(f"by_object_count: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
