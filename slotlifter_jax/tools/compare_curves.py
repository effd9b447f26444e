"""Validation curves of several runs on one chart, e.g. an ablation against the full model.

  python -m slotlifter_jax.tools.compare_curves --run=full=RUN_DIR --run=no_masking=METRICS.jsonl \
      --keys=attn_fg_ari,fg_ari,nv_ari,psnr_novel --out=curves.png

Each --run is LABEL=PATH, PATH a run folder (its metrics.jsonl) or a metrics .jsonl file such as
the `*_val_metrics.jsonl` copies in experiments/results/. One panel per key against the step, one
line per run; a run that logged no value of a key is left out of that panel. Prints, per key, a
markdown table of the validations (a step per row, a run per column; – where a run has no
validation at that step). plot_curves.py draws one run with its schedules and wall time.

  --loss_windows=N --from_step=S also prints the mean training loss over the windows (w, w + N]
  from step S on, a run per column, for the runs whose file holds training records (a run
  folder's metrics.jsonl; the committed `*_val_metrics.jsonl` copies hold validations only).
  Validation on 20 scenes is noisy; the training loss shows when a run's fit changed.
"""

from __future__ import annotations

import argparse
import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from slotlifter_jax import emergence  # noqa: E402  (numpy and absl only, no JAX)

FORMATS = {"psnr_novel": "{:.2f}", "psnr_source": "{:.2f}", "active_slots": "{:.2f}"}


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--run", action="append", default=[], metavar="LABEL=PATH", required=True,
                 help="a run folder or metrics .jsonl, with its label (repeat per run)")
  p.add_argument("--keys", default=",".join(emergence.CURVE_KEYS),
                 help="validation metrics to draw, comma-separated")
  p.add_argument("--out", required=True, help="the PNG to write")
  p.add_argument("--loss_windows", type=int, default=0, metavar="N",
                 help="also print the mean training loss per window of N steps (0: no)")
  p.add_argument("--from_step", type=int, default=0, metavar="S",
                 help="--loss_windows: the first window starts after step S")
  return p.parse_args(argv)


def _runs(specs: list[str]) -> list[tuple[str, str]]:
  runs = []
  for spec in specs:
    label, sep, path = spec.partition("=")
    if not sep or not label or not path:
      raise SystemExit(f"error: --run={spec}: expected LABEL=PATH")
    if label in dict(runs):
      raise SystemExit(f"error: --run={spec}: the label {label!r} is given twice")
    if os.path.isdir(path):
      path = os.path.join(path, emergence.METRICS_FILE)
    if not os.path.isfile(path):
      raise SystemExit(f"error: --run={spec}: {path} does not exist")
    runs.append((label, path))
  return runs


def _logged(curve: dict, key: str) -> bool:
  return not all(math.isnan(v) for v in curve[key])


def read(runs: list[tuple[str, str]]) -> dict[str, list[dict]]:
  """{label: the records of its file}; a one-line error for an unreadable file."""
  out = {}
  for label, path in runs:
    try:
      out[label] = emergence.load_records(path)
    except (ValueError, OSError) as e:
      raise SystemExit(f"error: {e}") from None
  return out


def load(runs: list[tuple[str, str]], records: dict[str, list[dict]],
         keys: list[str]) -> dict[str, dict]:
  """{label: emergence.curves(...)} with the given keys; a one-line error for a run without
  validations or a key that no run logged."""
  out = {}
  for label, path in runs:
    out[label] = emergence.curves(records[label], keys)
    if not out[label]["step"].size:
      raise SystemExit(f"error: {path}: no validation records")
  for key in keys:
    if not any(_logged(c, key) for c in out.values()):
      raise SystemExit(f"error: --keys: no run logged {key!r}")
  return out


def table(curves: dict[str, dict], key: str) -> list[str]:
  labels = list(curves)
  steps = sorted({int(s) for c in curves.values() for s in c["step"]})
  fmt = FORMATS.get(key, "{:.3f}")
  by_step = {label: dict(zip(c["step"].tolist(), c[key].tolist())) for label, c in curves.items()}
  lines = [f"{emergence.label(key)}", "", "| step | " + " | ".join(labels) + " |",
           "|---" * (len(labels) + 1) + "|"]
  for step in steps:
    values = [by_step[label].get(step, math.nan) for label in labels]
    cells = ["–" if math.isnan(v) else fmt.format(v) for v in values]
    lines.append(f"| {step} | " + " | ".join(cells) + " |")
  return lines


def loss_windows(records: dict[str, list[dict]], size: int, from_step: int) -> list[str]:
  """A markdown table of each run's mean training `loss` over the windows (w, w + size], w =
  from_step, from_step + size, …; a step logged twice (a resumed run) counts once, as its later
  record. Runs without training records are left out; none at all is an error."""
  means = {}
  for label, rows in records.items():
    by_step = {r["step"]: r["loss"] for r in rows
               if r["kind"] == "train" and "loss" in r and r["step"] > from_step}
    if not by_step:
      continue
    sums: dict[int, list[float]] = {}
    for step, loss in by_step.items():
      sums.setdefault(from_step + (step - from_step - 1) // size * size, []).append(loss)
    means[label] = {w: sum(v) / len(v) for w, v in sums.items()}
  if not means:
    raise SystemExit(f"error: --loss_windows: no run has training records after step {from_step}")
  windows = sorted({w for m in means.values() for w in m})
  lines = [f"mean training loss per {size} steps", "",
           "| steps | " + " | ".join(means) + " |", "|---" * (len(means) + 1) + "|"]
  for w in windows:
    cells = [f"{m[w]:.4f}" if w in m else "–" for m in means.values()]
    lines.append(f"| {w + 1}–{w + size} | " + " | ".join(cells) + " |")
  return lines


def plot(curves: dict[str, dict], keys: list[str], out: str) -> None:
  fig, axes = plt.subplots(1, len(keys), figsize=(3.6 * len(keys), 3.2), squeeze=False)
  for ax, key in zip(axes[0], keys):
    for label, c in curves.items():
      if _logged(c, key):
        ax.plot(c["step"], c[key], "o-", ms=2.5, lw=1, label=label)
    ax.set_title(emergence.label(key), fontsize=9)
    ax.set_xlabel("step")
  # One legend beside the panels: inside them it hides the curves' ends.
  handles = {h.get_label(): h for ax in axes[0] for h in ax.get_legend_handles_labels()[0]}
  fig.legend(handles.values(), handles.keys(), loc="center left", bbox_to_anchor=(1.0, 0.5),
             fontsize=7, frameon=False)
  fig.tight_layout()
  fig.savefig(out, dpi=80, bbox_inches="tight")
  plt.close(fig)


def main(argv=None) -> None:
  args = parse_args(argv)
  keys = [k for k in args.keys.split(",") if k]
  if not keys:
    raise SystemExit("error: --keys: no metric named")
  if args.loss_windows < 0 or args.from_step < 0:
    raise SystemExit("error: --loss_windows and --from_step must be ≥ 0")
  runs = _runs(args.run)
  records = read(runs)
  curves = load(runs, records, keys)
  for key in keys:
    print("\n".join(table(curves, key)), end="\n\n")
  if args.loss_windows:
    print("\n".join(loss_windows(records, args.loss_windows, args.from_step)), end="\n\n")
  plot(curves, keys, args.out)
  print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
