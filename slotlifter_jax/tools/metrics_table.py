"""Mean ± sample std of evaluation metrics over groups of runs, read from their metrics.json files.

  python -m slotlifter_jax.tools.metrics_table \
      --group=full=A/eval/test/metrics.json,B/eval/test/metrics.json \
      --group=no_masking=C/eval/test/metrics.json \
      --metrics=psnr_novel,ssim,fg_ari,nv_ari,mbo,attn_fg_ari,active_slots

`--mode=eval` writes one metrics.json per run (DIR/eval/<split>/metrics.json, each metric the mean
over the split's scenes). The study scripts tabulate only the columns of their own CSVs; this
puts any of a run's metrics side by side, e.g. runs a study trained next to runs of the README's
command. One markdown row per group (in the order given), then one line per group naming the
split, scene count, checkpoint steps and parameters its files were evaluated with, so rows that
were evaluated differently are seen to be. Values are printed as stored (ARIs in [−1, 1]);
a group of one run shows its value alone. Nothing is written; the table goes to stdout.
"""

from __future__ import annotations

import argparse
import json

from slotlifter_jax.tools import group_stats as st  # no JAX import

DEFAULT_METRICS = "psnr_novel,ssim,fg_ari,nv_ari,ari,mbo,attn_fg_ari,active_slots"
# Decimal places per metric; others get 3.
DIGITS = {"psnr_novel": 2, "psnr_source": 2, "attn_fg_ari": 2, "active_slots": 2,
          "num_objects": 2}


class TableError(ValueError):
  """A bad --group or --metrics value, or a metrics file that cannot be read."""


def parse_group(text: str) -> tuple[str, list[str]]:
  """'name=path1,path2' → (name, [path1, path2])."""
  name, sep, paths = text.partition("=")
  files = [p for p in paths.split(",") if p]
  if not sep or not name or not files:
    raise TableError(f"--group={text!r}: expected NAME=FILE[,FILE...]")
  return name, files


def read_metrics(path: str, metrics: list[str]) -> dict:
  """{metric: mean} of one metrics.json, plus '_about' (split, scenes, step, parameters)."""
  try:
    with open(path) as f:
      data = json.load(f)
  except OSError as e:
    raise TableError(f"{path}: cannot read ({e.strerror})") from None
  except json.JSONDecodeError as e:
    raise TableError(f"{path}: not JSON ({e.msg} at line {e.lineno})") from None
  stored = data.get("metrics") if isinstance(data, dict) else None
  if not isinstance(stored, dict):
    raise TableError(f"{path}: no 'metrics' object (not a metrics.json of --mode=eval)")
  row = {}
  for m in metrics:
    if m not in stored:
      raise TableError(f"{path}: no metric {m!r} (it has {', '.join(sorted(stored))})")
    row[m] = float(stored[m]["mean"])
  checkpoint = data.get("checkpoint") or {}
  row["_about"] = (data.get("split"), data.get("num_scenes"), checkpoint.get("step"),
                   data.get("parameters"))
  return row


def table(groups: list[tuple[str, list[str]]], metrics: list[str]) -> str:
  rows, notes = [], []
  for name, files in groups:
    about = []
    for path in files:
      row = read_metrics(path, metrics)
      about.append(row.pop("_about"))
      rows.append(dict(row, name=name))
    split = sorted({str(a[0]) for a in about})
    scenes = sorted({str(a[1]) for a in about})
    steps = [str(a[2]) for a in about]
    params = sorted({str(a[3]) for a in about})
    notes.append(f"- {name}: split {'/'.join(split)}, {'/'.join(scenes)} scenes, checkpoint steps "
                 f"{', '.join(steps)}, parameters {'/'.join(params)}")
  stats = st.aggregate(rows, metrics=metrics, order=[n for n, _ in groups])
  columns = [(m, m, 1.0, DIGITS.get(m, 3)) for m in metrics]
  # No collapse column: it needs each run's validation flag, which metrics.json does not hold.
  text = st.markdown_table(stats, columns=columns, collapse=False)
  return text + "\n\n" + "\n".join(notes) + "\n"


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--group", action="append", default=[], help="NAME=FILE[,FILE...] (repeat)")
  p.add_argument("--metrics", default=DEFAULT_METRICS, help="comma-separated metric names")
  args = p.parse_args(argv)
  try:
    if not args.group:
      raise TableError("give at least one --group=NAME=FILE[,FILE...]")
    metrics = [m for m in args.metrics.split(",") if m]
    if not metrics:
      raise TableError("--metrics is empty")
    print(table([parse_group(g) for g in args.group], metrics), end="")
  except TableError as e:
    raise SystemExit(f"metrics_table: {e}") from None


if __name__ == "__main__":
  main()
