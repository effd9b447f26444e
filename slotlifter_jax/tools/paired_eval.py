"""Paired comparison of evaluations of the same scenes.

  python -m slotlifter_jax.tools.paired_eval BASE_EVAL OTHER_EVAL [OTHER_EVAL ...] \
      [--out=FILE.json]

Each argument is an evaluation folder, DIR/eval/<split>, as `python -m slotlifter_jax.main
--mode=eval` writes it (metrics.json and per_scene.csv): one checkpoint evaluated with other
settings (more slot attention iterations, more samples per ray; metrics.json records them under
`differs_from_training`), or two runs on one split. The first is the baseline. For every other
evaluation and metric it prints the mean of the per-scene differences (other − baseline) with
its standard error over the scenes where both values are finite, and on how many scenes the
metric rose and fell. Scenes differ more from each other than two settings do on one scene, so
the standard error of a paired difference is smaller than that of either mean: 1.4–2.4× for
FG-ARI and 3.5–12× for novel PSNR on the comparisons of experiments/journal/2026-11.md, "more slot
attention iterations".

`--out` also writes the comparison as JSON (evaluation folders, their checkpoints,
`differs_from_training` and `parameters`, and the rows printed); an existing file is replaced only with
`--overwrite`.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

import numpy as np

from slotlifter_jax import emergence
from slotlifter_jax import metrics

DEFAULT_METRICS = ("fg_ari", "nv_ari", "attn_fg_ari", "mbo", "psnr_novel", "psnr_source")


class PairedEvalError(ValueError):
  """An evaluation folder that cannot be read or compared; the message names it."""


def read_eval(folder: str) -> tuple[dict, dict[str, dict[str, float]]]:
  """(metrics.json as a dict, {scene name: {metric: value}}) of one evaluation folder."""
  meta_path = os.path.join(folder, "metrics.json")
  rows_path = os.path.join(folder, "per_scene.csv")
  for path in (meta_path, rows_path):
    if not os.path.isfile(path):
      raise PairedEvalError(f"{path}: not found; pass an evaluation folder DIR/eval/<split> "
                            f"written by --mode=eval")
  try:
    with open(meta_path) as f:
      meta = json.load(f)
  except json.JSONDecodeError as e:
    raise PairedEvalError(f"{meta_path}: not valid JSON ({e.msg}, line {e.lineno})") from None
  rows = {}
  with open(rows_path, newline="") as f:
    reader = csv.DictReader(f)
    if reader.fieldnames is None or "scene" not in reader.fieldnames:
      raise PairedEvalError(f"{rows_path}: no 'scene' column; not a per_scene.csv of --mode=eval")
    for line, row in enumerate(reader, start=2):
      values = {}
      for k, v in row.items():
        if k in ("index", "scene", "num_views"):
          continue
        try:
          values[k] = float(v)
        except (TypeError, ValueError):
          raise PairedEvalError(f"{rows_path}, line {line}: {k} = {v!r} is not a number") from None
      rows[row["scene"]] = values
  if not rows:
    raise PairedEvalError(f"{rows_path}: no scenes")
  return meta, rows


def paired_difference(base: dict[str, dict[str, float]], other: dict[str, dict[str, float]],
                      metric: str) -> dict:
  """Per-scene other − base of one metric, summarised over the scenes where both are finite.

  Returns {"base", "other"} (the means over those scenes), "difference" (mean difference),
  "stderr" (its standard error; nan with fewer than two scenes), "scenes", "higher", "lower".
  Both must hold the same scenes (a paired comparison of different scenes means nothing).
  """
  if set(base) != set(other):
    only = sorted(set(base) ^ set(other))
    raise PairedEvalError(f"the evaluations hold different scenes ({len(base)} and {len(other)}; "
                          f"e.g. {only[0]!r} is in one only): evaluate the same split and "
                          f"--max_scenes")
  for scene in base:
    if metric not in base[scene] or metric not in other[scene]:
      raise PairedEvalError(f"metric {metric!r} is not in both evaluations")
  scenes = sorted(base)
  a = np.array([base[s][metric] for s in scenes], np.float64)
  b = np.array([other[s][metric] for s in scenes], np.float64)
  both = np.isfinite(a) & np.isfinite(b)
  d = (b - a)[both]
  diff = metrics.summarize(d)  # the evaluation's own mean ± s.e.
  return {"base": metrics.summarize(a[both]).mean, "other": metrics.summarize(b[both]).mean,
          "difference": diff.mean, "stderr": diff.stderr, "scenes": diff.count,
          "higher": int(np.sum(d > 0)), "lower": int(np.sum(d < 0))}


def _label(meta: dict, folder: str) -> str:
  differs = meta.get("differs_from_training") or {}
  setting = ", ".join(f"{k}={v[1]}" for k, v in differs.items()) or "as trained"
  step = (meta.get("checkpoint") or {}).get("step")
  # A run that keeps a moving average has two sets of parameters per checkpoint (--params).
  params = ", average of the parameters" if meta.get("parameters") == "average" else ""
  return f"{folder} (step {step}, {setting}{params})"


def compare(folders: list[str], metrics: list[str]) -> dict:
  """The baseline's and every other evaluation's paired differences, as `--out` writes them."""
  if len(folders) < 2:
    raise PairedEvalError("give at least two evaluation folders: the baseline, then the others")
  evals = [(folder, *read_eval(folder)) for folder in folders]
  base_folder, base_meta, base_rows = evals[0]
  result = {"baseline": {"folder": base_folder, "label": _label(base_meta, base_folder),
                         "checkpoint": base_meta.get("checkpoint"),
                         "differs_from_training": base_meta.get("differs_from_training"),
                         "parameters": base_meta.get("parameters", "trained")},
            "metrics": list(metrics), "others": []}
  for folder, meta, rows in evals[1:]:
    result["others"].append({
        "folder": folder, "label": _label(meta, folder), "checkpoint": meta.get("checkpoint"),
        "differs_from_training": meta.get("differs_from_training"),
        "parameters": meta.get("parameters", "trained"),
        "rows": {m: paired_difference(base_rows, rows, m) for m in metrics}})
  return result


def format_rows(result: dict) -> list[str]:
  width = max(len("metric"), *(len(m) for m in result["metrics"])) + 2
  lines = [f"baseline: {result['baseline']['label']}"]
  for other in result["others"]:
    lines += ["", f"against: {other['label']}",
              f"{'metric':<{width}}{'baseline':>10}{'other':>10}{'difference':>12}{'s.e.':>9}"
              f"{'scenes':>8}{'up':>5}{'down':>6}"]
    for m in result["metrics"]:
      r = other["rows"][m]
      lines.append(f"{m:<{width}}{r['base']:>10.4f}{r['other']:>10.4f}{r['difference']:>+12.4f}"
                   f"{r['stderr']:>9.4f}{r['scenes']:>8d}{r['higher']:>5d}{r['lower']:>6d}")
  return lines


def main(argv=None) -> int:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("evals", nargs="+", help="evaluation folders DIR/eval/<split>; the first is the "
                 "baseline")
  p.add_argument("--metrics", default=",".join(DEFAULT_METRICS),
                 help="comma-separated per_scene.csv columns")
  p.add_argument("--out", default="", help="also write the comparison to this JSON file")
  p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
  args = p.parse_args(argv)
  metrics = [m for m in args.metrics.split(",") if m]
  try:
    if args.out and os.path.exists(args.out) and not args.overwrite:
      raise PairedEvalError(f"{args.out} exists; pass --overwrite to replace it")
    result = compare(args.evals, metrics)
  except PairedEvalError as e:
    print(f"error: {e}", file=sys.stderr)
    return 1
  print("\n".join(format_rows(result)))
  if args.out:
    emergence.write_json_atomically(args.out, result)  # NaN (no scenes to average) as null
    print(f"wrote {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
