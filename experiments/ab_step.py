"""Paired train-step timing of two checkouts: which of two versions of the code steps faster.

  python experiments/ab_step.py --base=HEAD~1 --configs=scene,paper_cpu --out=DIR/ab.json
  python experiments/ab_step.py --base=/path/to/other/checkout --head=. --rounds=12 --steps=10 …
  python experiments/ab_step.py --base=. --configs=scene:scene_fold,paper_cpu:paper_cpu_fold --out=…

On a shared or throttled host one step's time drifts by ±10 % between calls of
`experiments/bench.py` minutes apart (experiments/journal/2026-12.md, "Folded products"), more
than most code changes are worth. Here both versions are compiled once, each in its own process with the
project's allocator and XLA flags, and then take turns on the same cores: in every round each
worker times --steps steps of its configuration (experiments/bench_common.py's configurations and
batches) while the other waits on a pipe, and the order alternates from round to round. A drift
of the host then moves both sides of a round alike, and the per-round ratio head/base cancels it.

A configuration NAME runs on both sides; BASE:HEAD runs configuration BASE on the base side and
HEAD on the head side (two settings of one checkout, e.g. a switch's effect).
--base and --head are checkout directories or git revisions of this repository (a revision is
checked out into a temporary worktree, removed at the end). Each worker imports `slotlifter_jax`
and `experiments.bench_common` from its own checkout, so both must have `bench_common.setup_step`.
Prints, per configuration, the median step time of each side over all timed steps and the median,
min and max over rounds of the paired ratio head/base; writes them as JSON to --out, which must
not exist yet, with the provenance record of the call (slotlifter_jax/provenance.py).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

flags.DEFINE_string("base", "HEAD", "Checkout directory or git revision of the reference side.")
flags.DEFINE_string("head", REPO, "Checkout directory or git revision of the side measured against it.")
flags.DEFINE_list("configs", ["scene"], "Configurations of experiments/bench_common.py to time: "
                  "NAME on both sides, or BASE:HEAD.")
flags.DEFINE_integer("rounds", 8, "Turns per side; the order of the two sides alternates.")
flags.DEFINE_integer("steps", 10, "Timed steps per turn (after two warm-up steps per worker).")
flags.DEFINE_string("out", None, "JSON file for the results (refused if it exists).")
flags.DEFINE_string("worker", None, "Internal: run configuration NAME's step on command.")
flags.DEFINE_string("worker_repo", None, "Internal: the checkout whose code the worker runs.")
FLAGS = flags.FLAGS


def paired_summary(base_times: list[list[float]], head_times: list[list[float]]) -> dict:
  """Per-step times of each round, [round][step] per side → medians and the paired ratio.

  A round's time is the median of its steps; its ratio is head's over base's in that round."""
  if not base_times or len(base_times) != len(head_times):
    raise ValueError("both sides need the same number (≥ 1) of rounds")
  base_rounds = [statistics.median(r) for r in base_times]
  head_rounds = [statistics.median(r) for r in head_times]
  ratios = [h / b for b, h in zip(base_rounds, head_rounds)]
  return dict(
      base_step_s=statistics.median([t for r in base_times for t in r]),
      head_step_s=statistics.median([t for r in head_times for t in r]),
      ratio_median=statistics.median(ratios), ratio_min=min(ratios), ratio_max=max(ratios),
      rounds=len(ratios), base_round_s=base_rounds, head_round_s=head_rounds)


def _worker(name: str, steps: int) -> None:
  """Set up and compile NAME's step, then on each 'go' line time `steps` steps and print them."""
  import jax
  from experiments import bench_common
  _, _, state, batches, train_step = bench_common.setup_step(name, steps)
  for i in range(2):  # compile and warm up
    state, _ = train_step(state, batches[i % len(batches)])
  jax.block_until_ready(state)
  print("ready", flush=True)
  for line in sys.stdin:
    if line.strip() != "go":
      break
    times = []
    for batch in batches:
      t = time.perf_counter()
      state, _ = train_step(state, batch)
      jax.block_until_ready(state)
      times.append(time.perf_counter() - t)
    print(json.dumps(times), flush=True)


class _Checkout:
  """A directory as given, or a revision checked out into a temporary worktree."""

  def __init__(self, spec: str):
    self.spec, self.tmp = spec, None
    if os.path.isdir(spec):
      self.path = os.path.abspath(spec)
      return
    rev = subprocess.run(["git", "-C", REPO, "rev-parse", "--verify", "--quiet", spec + "^{commit}"],
                         capture_output=True, text=True)
    if rev.returncode != 0:
      raise app.UsageError(f"{spec!r} is neither a directory nor a git revision of {REPO}")
    self.tmp = tempfile.mkdtemp(prefix="ab_step_")
    self.path = os.path.join(self.tmp, "checkout")
    subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", "--quiet", self.path,
                    rev.stdout.strip()], check=True)

  def close(self):
    if self.tmp is not None:
      subprocess.run(["git", "-C", REPO, "worktree", "remove", "--force", self.path], check=False)
      os.rmdir(self.tmp)


def _start(checkout: _Checkout, name: str, steps: int) -> subprocess.Popen:
  env = dict(os.environ, PYTHONPATH=checkout.path)
  cmd = [sys.executable, os.path.abspath(__file__), f"--worker={name}", f"--steps={steps}",
         f"--worker_repo={checkout.path}"]
  proc = subprocess.Popen(cmd, cwd=checkout.path, env=env, stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True)
  return proc


def _expect(proc: subprocess.Popen, label: str) -> str:
  line = proc.stdout.readline()
  if not line:
    raise RuntimeError(f"the {label} worker exited with code {proc.wait()} before answering")
  return line


def config_pair(spec: str) -> tuple[str, str]:
  """'NAME' → (NAME, NAME); 'BASE:HEAD' → (BASE, HEAD)."""
  parts = spec.split(":")
  if len(parts) == 1:
    return spec, spec
  if len(parts) == 2 and all(parts):
    return parts[0], parts[1]
  raise ValueError(f"--configs: {spec!r} is neither NAME nor BASE:HEAD")


def compare(base: _Checkout, head: _Checkout, spec: str, rounds: int, steps: int) -> dict:
  names = dict(zip(("base", "head"), config_pair(spec)))
  procs = {}
  try:
    for label, checkout in (("base", base), ("head", head)):
      procs[label] = _start(checkout, names[label], steps)
      if _expect(procs[label], label).strip() != "ready":
        raise RuntimeError(f"the {label} worker did not get ready")
    times = {"base": [], "head": []}
    for i in range(rounds):
      for label in (("base", "head") if i % 2 == 0 else ("head", "base")):
        procs[label].stdin.write("go\n")
        procs[label].stdin.flush()
        times[label].append(json.loads(_expect(procs[label], label)))
      print(f"[ab_step] {spec} round {i + 1}/{rounds}: base {statistics.median(times['base'][-1]):.4f} s, "
            f"head {statistics.median(times['head'][-1]):.4f} s", flush=True)
  finally:
    for proc in procs.values():
      if proc.poll() is None:
        proc.stdin.close()
        proc.wait()
  return dict(config=spec, base_config=names["base"], head_config=names["head"],
              steps_per_round=steps, **paired_summary(times["base"], times["head"]))


def result_record(results: list[dict], *, base: str, head: str, wall_s: float) -> dict:
  """What --out receives: the two sides as given, the date, the CPU, the results and the
  provenance record of this process (commit, machine, jax version, wall time). Its config is
  None: each side builds its configurations from its own checkout's bench_common, and the
  results name them (base_config, head_config)."""
  from experiments.bench_common import cpu_info
  from slotlifter_jax import provenance
  return dict(base=base, head=head, date=time.strftime("%Y-%m-%d %H:%M:%S"), **cpu_info(),
              results=results, **{provenance.KEY: provenance.collect(None, wall_s=wall_s)})


def main(argv):
  del argv
  t_start = time.perf_counter()
  if FLAGS.worker:
    import slotlifter_jax
    here = os.path.dirname(os.path.dirname(os.path.abspath(slotlifter_jax.__file__)))
    if here != os.path.abspath(FLAGS.worker_repo):
      raise RuntimeError(f"the worker for {FLAGS.worker_repo} imported the package from {here}")
    _worker(FLAGS.worker, FLAGS.steps)
    return
  if not FLAGS.out:
    raise app.UsageError("--out: give the JSON file for the results")
  if os.path.exists(FLAGS.out):
    raise app.UsageError(f"--out: {FLAGS.out} exists; not overwritten")
  from experiments.bench_common import CONFIGS
  try:
    pairs = [config_pair(spec) for spec in FLAGS.configs]
  except ValueError as e:
    raise app.UsageError(str(e))
  unknown = sorted({n for pair in pairs for n in pair if n not in CONFIGS})
  if unknown:
    raise app.UsageError(f"--configs: unknown {unknown}; choose from {sorted(CONFIGS)}")
  if FLAGS.rounds < 1 or FLAGS.steps < 1:
    raise app.UsageError("--rounds and --steps must be ≥ 1")
  base = _Checkout(FLAGS.base)
  try:
    head = _Checkout(FLAGS.head)
  except Exception:
    base.close()
    raise
  try:
    results = [compare(base, head, name, FLAGS.rounds, FLAGS.steps) for name in FLAGS.configs]
  finally:
    base.close()
    head.close()
  print("| config | base s/step | head s/step | head/base (median of rounds) | min–max |")
  print("| --- | --- | --- | --- | --- |")
  for r in results:
    print(f"| {r['config']} | {r['base_step_s']:.4f} | {r['head_step_s']:.4f} | "
          f"{r['ratio_median']:.3f} | {r['ratio_min']:.3f}–{r['ratio_max']:.3f} |")
  os.makedirs(os.path.dirname(os.path.abspath(FLAGS.out)), exist_ok=True)
  record = result_record(results, base=FLAGS.base, head=FLAGS.head,
                         wall_s=time.perf_counter() - t_start)
  with open(FLAGS.out, "x") as f:
    json.dump(record, f, indent=1)
  print(f"[ab_step] wrote {FLAGS.out}")


def _root_from_argv(argv: list[str]) -> str:
  """The checkout a process runs: a worker's --worker_repo, else this file's. Read before any
  import of the package, which would otherwise come from this checkout."""
  for arg in argv:
    if arg.startswith("--worker_repo="):
      return arg.split("=", 1)[1]
  return REPO


if __name__ == "__main__":
  sys.path.insert(0, _root_from_argv(sys.argv))
  from slotlifter_jax import runtime  # noqa: E402  (no JAX import)
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  app.run(main)
