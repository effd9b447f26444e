"""Step time and resident memory after every step, under a chosen allocator.

  SLOTLIFTER_ALLOCATOR=tcmalloc python experiments/rss_per_step.py --config=A --steps=6
  SLOTLIFTER_ALLOCATOR=jemalloc python experiments/rss_per_step.py --config=A --steps=4

Shows whether the allocator reuses XLA's per-step temp buffer (RSS flat, steps fast) or maps a
fresh one (RSS jumps by the temp size, that step slow). This is how tcmalloc was chosen over
jemalloc in slotlifter_jax/runtime.py. Configurations are those of experiments/bench.py.
"""

from __future__ import annotations

import os
import sys
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from slotlifter_jax import runtime  # noqa: E402

flags.DEFINE_string("config", "A", "A configuration name of experiments/bench.py.")
flags.DEFINE_integer("steps", 6, "Steps to run (the first includes the first allocation).")
FLAGS = flags.FLAGS


def _rss_gb() -> tuple[float, float]:
  values = {}
  with open("/proc/self/status") as f:
    for line in f:
      if line.startswith(("VmRSS:", "VmHWM:")):
        values[line.split(":")[0]] = int(line.split()[1]) / 1e6  # kB → GB
  return values.get("VmRSS", float("nan")), values.get("VmHWM", float("nan"))


def main(argv):
  del argv
  import jax
  from experiments import bench_common
  _, _, state, batches, train_step = bench_common.setup_step(FLAGS.config, 1)
  t = time.perf_counter()
  compiled = train_step.lower(state, batches[0]).compile()
  temp = compiled.memory_analysis().temp_size_in_bytes / 1e9
  rss, _ = _rss_gb()
  print(f"config {FLAGS.config} ({runtime.describe()}): compile {time.perf_counter() - t:.1f} s, "
        f"XLA temp {temp:.2f} GB, RSS after compile {rss:.2f} GB", flush=True)
  for i in range(FLAGS.steps):
    t = time.perf_counter()
    state, _ = compiled(state, batches[0])
    jax.block_until_ready(state)
    rss, peak = _rss_gb()
    print(f"step {i}: {time.perf_counter() - t:6.2f} s   RSS {rss:6.2f} GB   peak {peak:6.2f} GB",
          flush=True)


if __name__ == "__main__":
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  app.run(main)
