"""Where the time of one compiled train step goes, by model part, forward and backward.

  python experiments/profile_step.py --config=A --steps=3
  python experiments/profile_step.py --config=paper_cpu --top=25

Captures a JAX profiler trace of a few steps of the same jitted step as experiments/bench.py
(configurations A, B, paper_cpu, … defined there), sums the duration of every executed XLA
instruction, and attributes each to the model scope its HLO metadata names (e.g.
`allocation/transformer/block_2/self_attn`), split into forward, backward (`transpose(…)`) and
optimiser. Prints a table (share of the step per scope) and the most expensive instructions, and
writes experiments/results/profile_<config>_<platform>.json, with its provenance record
(slotlifter_jax/provenance.py).
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


from slotlifter_jax import provenance  # noqa: E402  (no JAX import)
from slotlifter_jax import runtime  # noqa: E402

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined when run, not at import: a test that imports this module for result_record must not
  # clash with the absl flags of the same names that other scripts define in its process.
  flags.DEFINE_string("config", "A", "A configuration name of experiments/bench.py.")
  flags.DEFINE_integer("steps", 3, "Profiled steps (after 2 warm-up steps).")
  flags.DEFINE_integer("depth", 4, "Scope components kept when grouping (after the model root); "
                       "the blocks of the allocation transformer are summed as block_*.")
  flags.DEFINE_integer("top", 20, "Rows of each table.")
  flags.DEFINE_string("out", os.path.join(REPO, "experiments", "results"), "Results folder.")

_INSTR = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=.*?metadata=\{([^}]*)\}")
_OP_NAME = re.compile(r'op_name="([^"]*)"')


def hlo_op_names(hlo_text: str) -> dict[str, str]:
  """HLO instruction name → the op_name of its metadata (the JAX scope that produced it)."""
  names = {}
  for line in hlo_text.splitlines():
    m = _INSTR.match(line)
    if m:
      op = _OP_NAME.search(m.group(2))
      if op:
        names[m.group(1)] = op.group(1)
  return names


def scope_of(op_name: str, depth: int) -> tuple[str, str]:
  """(phase, scope): phase forward / backward / optimiser / other, scope the model path."""
  phase = "backward" if "transpose(" in op_name else "forward"
  parts = [p for p in op_name.split("/") if p and not p.startswith(("jit(", "pjit("))]
  clean = []
  for p in parts:
    p = re.sub(r"^(?:transpose\(|jvp\(|remat\(|checkpoint\(|vmap\()+", "", p).rstrip(")")
    clean.append(p)
  if "SlotLifter" not in " ".join(clean) and not any(
      c.startswith(("encoder", "slot_attention", "allocation", "colour_mlp", "lift"))
      for c in clean):
    return "optimiser/other", "/".join(clean[:2]) or "?"
  clean = [c for c in clean if not c.startswith("SlotLifter") and c not in ("while", "body", "scan")]
  clean = [re.sub(r"^block_\d+$", "block_*", c) for c in clean]  # the 4 blocks together
  model_parts = [c for c in clean if not re.fullmatch(r"[a-z_]+(?:_p)?", c) or c in (
      "encoder", "slot_attention", "transformer", "self_attn", "cross_attn", "conv", "ffn_in",
      "ffn_out", "final_norm", "map_query", "map_key", "map_out", "lift", "positional")
      or c.startswith(("block", "allocation", "colour", "layer", "norm", "ln"))]
  return phase, "/".join(model_parts[:depth]) or "/".join(clean[:depth])


def _trace_durations(trace_dir: str) -> collections.Counter:
  paths = glob.glob(os.path.join(trace_dir, "**", "*.trace.json.gz"), recursive=True)
  if not paths:
    raise FileNotFoundError(f"no *.trace.json.gz under {trace_dir}")
  with gzip.open(paths[0]) as f:
    events = json.load(f)["traceEvents"]
  dur = collections.Counter()
  for e in events:
    if e.get("ph") == "X":
      dur[e["name"]] += float(e.get("dur", 0.0)) * 1e-6
  return dur


def result_record(name: str, config, *, wall: float, attributed: float,
                  by_phase: collections.Counter, by_scope: collections.Counter,
                  wall_s: float) -> dict:
  """The JSON this writes: configuration `name`'s step time, profiled and attributed, by phase
  and by scope, with the provenance record of `config` (the step as measured) and `wall_s`."""
  return dict(config=name, wall_s_per_step=wall, attributed_s_per_step=attributed,
              allocator=runtime.describe(), by_phase=dict(by_phase),
              by_scope=[dict(phase=p, scope=s, seconds=v) for (p, s), v in by_scope.most_common()],
              **{provenance.KEY: provenance.collect(config, wall_s=wall_s)})


def main(argv):
  del argv
  t_start = time.perf_counter()
  runtime.set_xla_flags()
  import jax
  from experiments import bench_common as bench

  config, _, state, batches, train_step = bench.setup_step(FLAGS.config, FLAGS.steps + 2)
  compiled = train_step.lower(state, batches[0]).compile()
  op_names = hlo_op_names(compiled.as_text())
  for b in batches[:2]:
    state, _ = compiled(state, b)
  jax.block_until_ready(state)

  with tempfile.TemporaryDirectory() as tmp:
    t = time.perf_counter()
    jax.profiler.start_trace(tmp, create_perfetto_trace=True)
    for b in batches[2:]:
      state, _ = compiled(state, b)
      jax.block_until_ready(state)
    jax.profiler.stop_trace()
    wall = (time.perf_counter() - t) / FLAGS.steps
    durations = _trace_durations(tmp)

  by_scope = collections.Counter()
  by_instr = collections.Counter()
  for name, seconds in durations.items():
    base = name.split(":")[-1].strip()
    if base not in op_names:
      continue
    phase, scope = scope_of(op_names[base], FLAGS.depth)
    by_scope[(phase, scope)] += seconds / FLAGS.steps
    by_instr[(base, op_names[base][-90:])] += seconds / FLAGS.steps
  attributed = sum(by_scope.values())
  print(f"config {FLAGS.config}: {wall:.3f} s/step wall (profiled), {attributed:.3f} s/step in "
        f"attributed XLA instructions ({runtime.describe()})")
  print("\n| phase | scope | s/step | share |\n|---|---|---|---|")
  for (phase, scope), s in by_scope.most_common(FLAGS.top):
    print(f"| {phase} | {scope} | {s:.3f} | {100 * s / attributed:.1f} % |")
  by_phase = collections.Counter()
  for (phase, _), s in by_scope.items():
    by_phase[phase] += s
  print("\nby phase: " + ", ".join(f"{p} {100 * s / attributed:.1f} %" for p, s in by_phase.most_common()))
  print("\n| instruction | op_name (tail) | s/step |\n|---|---|---|")
  for (instr, op), s in by_instr.most_common(FLAGS.top):
    print(f"| {instr} | {op} | {s:.3f} |")

  os.makedirs(FLAGS.out, exist_ok=True)
  path = os.path.join(FLAGS.out, f"profile_{FLAGS.config}_{jax.devices()[0].platform}.json")
  with open(path + ".tmp", "w") as f:
    json.dump(result_record(FLAGS.config, config, wall=wall, attributed=attributed,
                            by_phase=by_phase, by_scope=by_scope,
                            wall_s=time.perf_counter() - t_start), f, indent=1)
  os.replace(path + ".tmp", path)
  print(f"\nwrote {path}")


if __name__ == "__main__":
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  _define_flags()
  app.run(main)
