"""Does an early validation foretell how a run ends? The evidence behind the restart rules
(`train.restarts`, `train.restart_check_step`, `train.restart_signal`; slotlifter_jax/restarts.py).

    python -m slotlifter_jax.tools.early_check --step=14000 --min_score=0.55 RUN ...
    python -m slotlifter_jax.tools.early_check --sweep RUN ...
    python -m slotlifter_jax.tools.early_check --sweep @experiments/early_check_runs.txt
    python -m slotlifter_jax.tools.early_check --step=14000 --min_score=0.55 \
        --min_active_slots=3 [--max_pixel_entropy=0.33] [--min_attn_agreement=0.15] RUN ...

RUN is a run folder (its metrics.jsonl) or a copied `NAME_val_metrics.jsonl`, as in
experiments/results/. Everything here reads the validation split only, so that a rule fitted
with it never looked at the scenes it is reported on: a run's outcome is its best validation
score of `min_fg_nv` (the worse of FG-ARI and NV-ARI, what the best checkpoint is chosen by), and
it "ends split" when that reaches `--target`.

For each run it prints the score at `--step`, what the labelled rule would do (keep the attempt or
restart it from a new seed) and the outcome; the last line counts how often the rule keeps a run
that ends below the target and restarts one that reaches it. With `--min_active_slots` it also
applies the mask-free rule (slots in use on the validation views at `--step`, with
`--max_pixel_entropy` their mean per-pixel slot entropy, with `--min_attn_agreement` the agreement
of slot attention's grouping with the rendered split; `validation.mask_free_statistics`,
`mask_free.shortfall`) to the runs whose logs have it, and counts how often the two
rules decide alike. `--sweep` fits the labelled rule instead: every validated step and a grid of
thresholds, ranked by the number of misjudged runs.
"""

import argparse
import os
import sys

import numpy as np

from slotlifter_jax import emergence  # numpy and absl only, no JAX
from slotlifter_jax import mask_free

SWEEP_THRESHOLDS = np.round(np.arange(0.30, 0.801, 0.05), 2)


def _val_records(path: str) -> dict[int, dict]:
  """Validation rows with both ARIs, by step, as they survive resumes (emergence.latest_records)."""
  records = emergence.latest_records(emergence.load_records(path), "val")
  return {int(r["step"]): r for r in records if "fg_ari" in r and "nv_ari" in r}


def _path(run: str) -> str:
  if os.path.isdir(run):
    return os.path.join(run, "metrics.jsonl")
  if not run.endswith("_val_metrics.jsonl"):
    raise ValueError(f"{run}: neither a run folder nor a NAME_val_metrics.jsonl file")
  return run


def _maybe(value) -> str:
  return "–" if value is None else f"{float(value):.2f}"


def _score(row: dict) -> float:
  return min(float(row["fg_ari"]), float(row["nv_ari"]))


def load(run: str) -> dict[int, dict]:
  path = _path(run)
  if not os.path.exists(path):
    raise ValueError(f"{path}: no such file")
  rows = _val_records(path)
  if not rows:
    raise ValueError(f"{path}: no validation with FG-ARI and NV-ARI")
  return rows


def check(run: str, rows: dict[int, dict], *, step: int, min_score: float, target: float,
          min_active_slots=None, max_pixel_entropy: float = 1.0,
          min_attn_agreement: float = -1.0) -> dict:
  if step not in rows:
    raise ValueError(f"{_path(run)}: no validation at step {step} (steps {min(rows)}–{max(rows)})")
  best_step = max(rows, key=lambda s: (_score(rows[s]), -s))
  out = dict(run=run, early=_score(rows[step]), keep=_score(rows[step]) >= min_score,
             best=_score(rows[best_step]), best_step=best_step,
             ends_split=_score(rows[best_step]) >= target, slots=None, keep_mask_free=None)
  if min_active_slots is not None and "mf_active_slots" in rows[step]:
    out["slots"] = float(rows[step]["mf_active_slots"])
    out["entropy"] = rows[step].get("mf_pixel_entropy")
    out["agreement"] = rows[step].get("mf_attn_agreement")
    out["keep_mask_free"] = mask_free.shortfall(
        rows[step], min_active_slots=min_active_slots, max_pixel_entropy=max_pixel_entropy,
        min_attn_agreement=min_attn_agreement) is None
  return out


def sweep(all_rows: list[dict[int, dict]], *, target: float) -> list[tuple[int, float, int, int]]:
  """(step, threshold, kept that end below, restarted that end split) for every step that all
  runs validated and every threshold of SWEEP_THRESHOLDS, fewest misjudged runs first, then the
  earliest step."""
  steps = sorted(set.intersection(*(set(rows) for rows in all_rows)))
  ends = [max(_score(r) for r in rows.values()) >= target for rows in all_rows]
  table = []
  for step in steps:
    early = np.array([_score(rows[step]) for rows in all_rows])
    for threshold in SWEEP_THRESHOLDS:
      keep = early >= threshold
      table.append((step, float(threshold), int(np.sum(keep & ~np.array(ends))),
                    int(np.sum(~keep & np.array(ends)))))
  return sorted(table, key=lambda r: (r[2] + r[3], r[0], r[1]))


def main(argv=None) -> int:
  # @FILE reads arguments from FILE, one per line (experiments/early_check_runs.txt lists the runs
  # of the clevr fit).
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                   fromfile_prefix_chars="@")
  parser.add_argument("runs", nargs="+")
  parser.add_argument("--step", type=int)
  parser.add_argument("--min_score", type=float)
  parser.add_argument("--target", type=float, default=0.8)
  parser.add_argument("--min_active_slots", type=float)
  parser.add_argument("--max_pixel_entropy", type=float, default=1.0,
                      help="with --min_active_slots: the mask-free rule's entropy cap (1: none)")
  parser.add_argument("--min_attn_agreement", type=float, default=-1.0,
                      help="with --min_active_slots: the mask-free rule's least agreement of slot "
                           "attention with the rendered split (-1: none)")
  parser.add_argument("--sweep", action="store_true")
  parser.add_argument("--top", type=int, default=10, help="--sweep: rules to print")
  args = parser.parse_args(argv)
  if not args.sweep and (args.step is None or args.min_score is None):
    print("error: --step and --min_score are required (or --sweep)", file=sys.stderr)
    return 2
  try:
    all_rows = [load(r) for r in args.runs]
    if args.sweep:
      table = sweep(all_rows, target=args.target)
    else:
      results = [check(r, rows, step=args.step, min_score=args.min_score, target=args.target,
                       min_active_slots=args.min_active_slots,
                       max_pixel_entropy=args.max_pixel_entropy,
                       min_attn_agreement=args.min_attn_agreement)
                 for r, rows in zip(args.runs, all_rows)]
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 1
  ends = sum(max(_score(r) for r in rows.values()) >= args.target for rows in all_rows)
  if args.sweep:
    print(f"{len(all_rows)} runs, {ends} of which end split (best validation min(FG, NV) ≥ "
          f"{args.target})")
    print("| step | min(FG, NV) ≥ | kept, end below | restarted, end split |")
    print("|---|---|---|---|")
    for step, threshold, kept_failing, lost_passing in table[:args.top]:
      print(f"| {step} | {threshold:.2f} | {kept_failing} | {lost_passing} |")
    return 0
  with_mask_free = args.min_active_slots is not None
  print(f"| run | min(FG, NV) at {args.step} | rule | best validation (step) | ends split |"
        + (" slots in use | pixel entropy | agreement | mask-free rule |" if with_mask_free
           else ""))
  print("|---|---|---|---|---|" + ("---|---|---|---|" if with_mask_free else ""))
  for r in results:
    name = os.path.basename(r["run"].rstrip("/")).removesuffix("_val_metrics.jsonl")
    line = (f"| {name} | {r['early']:.3f} | {'keep' if r['keep'] else 'restart'} | "
            f"{r['best']:.3f} ({r['best_step']}) | {'yes' if r['ends_split'] else 'no'} |")
    if with_mask_free:
      line += (" – | – | – | – |" if r["slots"] is None else
               f" {r['slots']:.2f} | {_maybe(r['entropy'])} | {_maybe(r['agreement'])} |"
               f" {'keep' if r['keep_mask_free'] else 'restart'} |")
    print(line)
  kept_failing = sum(r["keep"] and not r["ends_split"] for r in results)
  lost_passing = sum(not r["keep"] and r["ends_split"] for r in results)
  print(f"{len(results)} runs: the rule keeps {kept_failing} that end below the target and "
        f"restarts {lost_passing} that reach it")
  if with_mask_free:
    both = [r for r in results if r["keep_mask_free"] is not None]
    agree = sum(r["keep"] == r["keep_mask_free"] for r in both)
    print(f"{len(both)} runs log the mask-free statistics: the two rules decide alike on {agree}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
