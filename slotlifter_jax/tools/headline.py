"""A data set's headline result from its seeds' run folders: one JSON file the README's tables are
written from (experiments/tables.py).

    python -m slotlifter_jax.tools.headline --name=room --split=test \
        --out=experiments/results/headline_room.json runs/room_seed0 runs/room_seed1 ...

Each RUN is a run folder of the training command, evaluated with `--mode=eval --split=SPLIT`.
Per seed it records FG-ARI, NV-ARI and novel-view PSNR (means and standard errors over the
split's scenes), the checkpoint evaluated, the attempts (1 + the restarts the run made), the
training wall time in minutes (restarts included: `wall_s` of the run's last training record),
the hosts and commits it trained on (DIR/machines.jsonl) and the commit of the evaluation; then
the mean ± sample standard deviation over the seeds (null for one seed), and the split's name. A run without that evaluation is
an error naming the file: a headline never mixes splits or leaves a seed out silently.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

from slotlifter_jax import emergence  # no JAX
from slotlifter_jax import restarts

KEYS = ("fg_ari", "nv_ari", "psnr_novel")


def _load_json(path: str) -> dict:
  try:
    with open(path) as f:
      return json.load(f)
  except FileNotFoundError:
    raise ValueError(f"{path}: no such file") from None
  except json.JSONDecodeError as e:
    raise ValueError(f"{path}: not valid JSON ({e})") from None


def seed_row(run: str, split: str) -> dict:
  """One seed's entry from its run folder (module doc)."""
  evaluation = _load_json(os.path.join(run, "eval", split, "metrics.json"))
  metrics = evaluation.get("metrics", {})
  missing = [k for k in KEYS if k not in metrics]
  if missing:
    raise ValueError(f"{os.path.join(run, 'eval', split, 'metrics.json')}: no {missing}")
  config = _load_json(os.path.join(run, "config.json"))
  attempts = restarts.archived_attempts(run)
  first_seed = restarts.attempt_seed(attempts[0]) if attempts else int(config["seed"])
  log = os.path.join(run, "metrics.jsonl")
  train = emergence.latest_records(emergence.load_records(log), "train") if os.path.exists(
      log) else []
  wall_s = max((float(r["wall_s"]) for r in train if "wall_s" in r), default=math.nan)
  hosts, train_commits = [], []
  machines = os.path.join(run, "machines.jsonl")
  if os.path.exists(machines):
    with open(machines) as f:
      for line in f:
        host = json.loads(line)
        name = host.get("cpu_model", "") if host.get("platform") == "cpu" else host.get(
            "device_kind", "")
        if name and name not in hosts:
          hosts.append(name)
        if host.get("git_commit") and host["git_commit"] not in train_commits:
          train_commits.append(host["git_commit"])
  checkpoint = evaluation.get("checkpoint", {})
  row = dict(run=run, seed=first_seed, final_seed=int(config["seed"]),
             attempts=len(attempts) + 1,
             wall_minutes=None if math.isnan(wall_s) else round(wall_s / 60.0, 1),
             hosts=hosts, train_commits=train_commits, checkpoint=checkpoint,
             eval_commit=evaluation.get("provenance", {}).get("git_commit"))
  for k in KEYS:
    row[k] = float(metrics[k]["mean"])
    row[f"{k}_stderr"] = float(metrics[k].get("stderr", math.nan))
  return row


def headline(runs: list[str], *, name: str, split: str) -> dict:
  rows = sorted((seed_row(r, split) for r in runs), key=lambda r: r["seed"])
  summary = {}
  for k in KEYS:
    values = [r[k] for r in rows]
    mean = sum(values) / len(values)
    # One seed has no spread: null in the file (JSON has no NaN), "n/a" where printed.
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1)) if len(
        values) > 1 else None
    summary[k] = dict(mean=mean, std=std)
  return dict(name=name, split=split, num_seeds=len(rows), seeds=rows, summary=summary,
              collapsed_seeds=sum(r["fg_ari"] < 0.5 for r in rows))


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("runs", nargs="+")
  parser.add_argument("--name", required=True, help="data set, e.g. clevr or room")
  parser.add_argument("--split", default="test")
  parser.add_argument("--out", required=True)
  args = parser.parse_args(argv)
  try:
    result = headline(args.runs, name=args.name, split=args.split)
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 1
  tmp = args.out + ".partial"
  with open(tmp, "w") as f:
    json.dump(result, f, indent=1, sort_keys=True)
    f.write("\n")
  os.replace(tmp, args.out)
  s = result["summary"]
  show = lambda k, fmt: (f"{fmt.format(s[k]['mean'])} ± "
                         f"{'n/a' if s[k]['std'] is None else fmt.format(s[k]['std'])}")
  print(f"{args.name} on {args.split}, {result['num_seeds']} seeds: FG-ARI "
        f"{show('fg_ari', '{:.3f}')}, NV-ARI {show('nv_ari', '{:.3f}')}, novel PSNR "
        f"{show('psnr_novel', '{:.2f}')} dB → {args.out}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
