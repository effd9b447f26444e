"""Does an early validation score foretell how a run ends? The evidence behind a restart rule
(`train.restarts` with `train.restart_check_step` and `train.restart_min_score`).

    python experiments/early_check.py --step=14000 --min_score=0.55 RUN ...

RUN is a run folder (its metrics.jsonl, and eval/test/metrics.json once evaluated) or a copied
`NAME_val_metrics.jsonl` (with `NAME_test_metrics.json` beside it, if there is one), as in
experiments/results/. For each run it prints the worse of validation FG-ARI and NV-ARI (the
`min_fg_nv` selection score) at `--step`, what the rule would do (keep the attempt, or restart it
from a new seed), the same score at the run's last validation, and, where a test evaluation
exists, its FG-ARI and NV-ARI and whether both reach `--target`. The last line counts how often
the rule keeps a run that ends below the target and restarts one that would have reached it.
"""

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from slotlifter_jax import emergence  # noqa: E402  (numpy and absl only, no JAX)


def _val_records(path: str) -> dict[int, dict]:
  """Validation rows with both ARIs, by step, as they survive resumes (emergence.latest_records)."""
  records = emergence.latest_records(emergence.load_records(path), "val")
  return {int(r["step"]): r for r in records if "fg_ari" in r and "nv_ari" in r}


def _paths(run: str) -> tuple[str, str]:
  if os.path.isdir(run):
    return (os.path.join(run, "metrics.jsonl"),
            os.path.join(run, "eval", "test", "metrics.json"))
  if not run.endswith("_val_metrics.jsonl"):
    raise ValueError(f"{run}: neither a run folder nor a NAME_val_metrics.jsonl file")
  return run, run[:-len("_val_metrics.jsonl")] + "_test_metrics.json"


def _score(row: dict) -> float:
  return min(float(row["fg_ari"]), float(row["nv_ari"]))


def check(run: str, *, step: int, min_score: float, target: float) -> dict:
  val_path, test_path = _paths(run)
  if not os.path.exists(val_path):
    raise ValueError(f"{val_path}: no such file")
  rows = _val_records(val_path)
  if step not in rows:
    raise ValueError(f"{val_path}: no validation at step {step} (steps {min(rows, default=None)}"
                     f"–{max(rows, default=None)})")
  last = max(rows)
  out = dict(run=run, early=_score(rows[step]), keep=_score(rows[step]) >= min_score,
             last_step=last, last=_score(rows[last]), test_fg=None, test_nv=None, passes=None)
  if os.path.exists(test_path):
    with open(test_path) as f:
      m = json.load(f)["metrics"]
    out.update(test_fg=m["fg_ari"]["mean"], test_nv=m["nv_ari"]["mean"])
    out["passes"] = min(out["test_fg"], out["test_nv"]) >= target
  return out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("runs", nargs="+")
  parser.add_argument("--step", type=int, required=True)
  parser.add_argument("--min_score", type=float, required=True)
  parser.add_argument("--target", type=float, default=0.8)
  args = parser.parse_args(argv)
  try:
    results = [check(r, step=args.step, min_score=args.min_score, target=args.target)
               for r in args.runs]
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 1
  print(f"| run | min(FG, NV) at {args.step} | rule | last validation | test FG-ARI | "
        f"test NV-ARI | both ≥ {args.target} |")
  print("|---|---|---|---|---|---|---|")
  for r in results:
    test = ("–", "–", "–") if r["passes"] is None else (
        f"{r['test_fg']:.3f}", f"{r['test_nv']:.3f}", "yes" if r["passes"] else "no")
    name = os.path.basename(r["run"].rstrip("/")).removesuffix("_val_metrics.jsonl")
    print(f"| {name} | {r['early']:.3f} | "
          f"{'keep' if r['keep'] else 'restart'} | {r['last']:.3f} (step {r['last_step']}) | "
          + " | ".join(test) + " |")
  judged = [r for r in results if r["passes"] is not None]
  kept_failing = sum(r["keep"] and not r["passes"] for r in judged)
  lost_passing = sum(not r["keep"] and r["passes"] for r in judged)
  print(f"{len(judged)} runs with a test evaluation: the rule keeps {kept_failing} that end below "
        f"the target and restarts {lost_passing} that reach it")
  return 0


if __name__ == "__main__":
  sys.exit(main())
