"""A new run folder that starts where another run was at one of its checkpoints, so that a probe
can change one setting from that step on and be compared with the run it forked from.

  python -m slotlifter_jax.tools.fork_run SRC DST --checkpoint=30000
  python -m slotlifter_jax.main --config=configs/clevr.py:scene --workdir=DST --config.train.base_lr=5e-5

SRC is a training run's --workdir, DST a folder that does not exist yet. --checkpoint picks the
checkpoint to start from: latest (the default), best, or a step number (among the latest
checkpoints, then the best), as in `--mode=eval`. Then the run's own command, pointed at DST,
resumes it there; any --config override it adds is a change from that step on, which the run
records in DST/config_history.jsonl.

DST gets what SRC had at that step and nothing after it:
- the checkpoint, as DST's only latest checkpoint, and SRC's best checkpoint if it is not later;
- metrics.jsonl, config_history.jsonl and the validation pictures (val/) up to that step;
- config.json as it was at that step: changes SRC recorded at later resumes are undone;
- the abandoned attempts (restarted/) whole: they precede the attempt in the folder.
TensorBoard events (tb/), emergence.json and eval/ are not copied: they describe later steps or
later checkpoints. DST/fork.json records where the fork came from.

Why: a run's batches and keys are functions of (seed, step), so the fork's unchanged command
retraces SRC exactly (tests/test_fork_run.py), and a change made at the fork is the only
difference between the two from there on: a late-phase probe costs the steps after the fork
only, and the two curves are paired.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time


class ForkError(ValueError):
  """A fork that cannot be made; nothing has been written."""


def _jsonl_upto(path: str, step: int) -> list[str]:
  """The lines of a JSON-lines log whose record's step is at most `step` (records without a step
  are kept; a line cut by a kill is dropped)."""
  if not os.path.exists(path):
    return []
  kept = []
  with open(path) as f:
    for line in f:
      try:
        record = json.loads(line)
      except json.JSONDecodeError:
        continue
      if int(record.get("step", 0)) <= step:
        kept.append(line if line.endswith("\n") else line + "\n")
  return kept


def config_at(config: dict, history: list[dict], step: int) -> dict:
  """`config` (a run's config.json) with the changes recorded after `step` undone, latest first.
  Each history record is {"step": s, "changes": {"a.b": [old, new], ...}} (checkpoints.save_config)."""
  config = json.loads(json.dumps(config))
  for record in sorted((r for r in history if int(r["step"]) > step),
                       key=lambda r: -int(r["step"])):
    for field, (old, _) in record["changes"].items():
      *parents, leaf = field.split(".")
      node = config
      for name in parents:
        node = node.setdefault(name, {})
      node[leaf] = old
  return config


def fork(src: str, dst: str, checkpoint: str = "latest") -> dict:
  """Makes the run folder `dst` from `src` at its checkpoint `checkpoint`; returns fork.json's
  record. Raises ForkError (or FileNotFoundError / ValueError from the checkpoint lookup) before
  writing anything."""
  from slotlifter_jax import checkpoints as ckpt_lib
  if os.path.lexists(dst):
    raise ForkError(f"{dst}: exists; a fork is made into a new folder only")
  config_file = ckpt_lib.config_path(src)
  if not os.path.exists(config_file):
    raise ForkError(f"{config_file}: missing; {src} is not a training run's folder")
  step_dir, step, best = ckpt_lib.locate_checkpoint(src, checkpoint)
  with open(config_file) as f:
    config = json.load(f)
  history_all = _jsonl_upto(ckpt_lib.config_history_path(src), sys.maxsize)
  history = [json.loads(line) for line in history_all]
  history_lines = [line for line, r in zip(history_all, history) if int(r.get("step", 0)) <= step]

  # Build the fork beside its destination and move it into place at the end, so an interrupted
  # fork leaves no folder that looks like a run.
  staging = f"{dst.rstrip(os.sep)}.forking-{os.getpid()}"
  os.makedirs(staging)
  try:
    root = os.path.join(staging, "checkpoints")
    shutil.copytree(step_dir, os.path.join(root, "latest", str(step)))
    if best is not None and best <= step:
      shutil.copytree(os.path.join(os.path.dirname(os.path.dirname(step_dir)), "best", str(best)),
                      os.path.join(root, "best", str(best)))
    with open(os.path.join(staging, "config.json"), "w") as f:
      json.dump(config_at(config, history, step), f, indent=2, sort_keys=True)
    if history_lines:
      with open(os.path.join(staging, "config_history.jsonl"), "w") as f:
        f.writelines(history_lines)
    with open(os.path.join(staging, "metrics.jsonl"), "w") as f:
      f.writelines(_jsonl_upto(os.path.join(src, "metrics.jsonl"), step))
    val = os.path.join(src, "val")
    for name in sorted(os.listdir(val)) if os.path.isdir(val) else []:
      digits = name.removeprefix("step_").split(".")[0]
      if digits.isdigit() and int(digits) <= step:
        os.makedirs(os.path.join(staging, "val"), exist_ok=True)
        shutil.copy2(os.path.join(val, name), os.path.join(staging, "val", name))
    restarted = os.path.join(src, "restarted")
    if os.path.isdir(restarted):
      shutil.copytree(restarted, os.path.join(staging, "restarted"))
    record = dict(source=os.path.abspath(src), checkpoint=os.path.relpath(step_dir, src),
                  step=step, best_copied=best if best is not None and best <= step else None,
                  created=time.strftime("%Y-%m-%dT%H:%M:%S%z"))
    with open(os.path.join(staging, "fork.json"), "w") as f:
      json.dump(record, f, indent=1)
    os.rename(staging, dst)
  except BaseException:
    shutil.rmtree(staging, ignore_errors=True)
    raise
  return record


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("src", help="the run folder to fork")
  parser.add_argument("dst", help="the new run folder (must not exist)")
  parser.add_argument("--checkpoint", default="latest",
                      help="latest (default), best, or a step number")
  args = parser.parse_args(argv)
  try:
    record = fork(args.src, args.dst, args.checkpoint)
  except (OSError, ValueError) as e:  # ForkError and checkpoints.EvalSetupError are ValueErrors
    print(f"error: {e}", file=sys.stderr)
    return 2
  best = (f"; best checkpoint {record['best_copied']}" if record["best_copied"] is not None
          else "; no best checkpoint at or before it")
  print(f"forked {args.src} at step {record['step']} ({record['checkpoint']}) into {args.dst}"
        f"{best}. Resume it with the run's command and --workdir={args.dst}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
