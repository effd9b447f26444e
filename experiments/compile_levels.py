"""What LLVM's optimisation level costs and changes: the init program and the train step.

  python experiments/compile_levels.py
  python experiments/compile_levels.py --configs=clevr:smoke,clevr:scene --levels=3,1

For each configuration of --configs (`<config file>:<variant>`), compiles the init program of
`train_step.init_state` (the weights of the model; its forward is dead code, what is left is one
threefry draw per weight), and for those of --step_configs also the train step (forward, backward,
Lion), each at every XLA CPU `xla_backend_optimization_level` of --levels (3 is XLA's default),
with the persistent compilation cache off. It prints and records the compile times, whether the
weights and the parameters after --steps steps are bit-identical to those of level 3, and the
step's run time. Writes experiments/results/compile_levels_<platform>.json, with its
provenance record (slotlifter_jax/provenance.py).

Why: `init_state` compiles its program at level 1 (same weights, 0.47–0.73× the time), and the test
suite compiles everything at level 0 (tests/conftest.py).
"""

from __future__ import annotations

import json
import os
import sys
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, "tests"))

FLAGS = flags.FLAGS


def _define_flags() -> None:
  # Defined when run, not at import: a test that imports this module for result_record must not
  # clash with the absl flags of the same names that other scripts define in its process.
  flags.DEFINE_list("configs", ["clevr:smoke", "clevr:scene", "clevr:paper_cpu", "clevr:",
                                "room_chair:"],
                    "Configurations, <file in configs/>:<variant> (empty variant: the paper's).")
  flags.DEFINE_list("step_configs", ["clevr:smoke", "clevr:scene"],
                    "The configurations whose train step is also compiled and run (the paper's "
                    "takes minutes per level on a CPU).")
  flags.DEFINE_list("levels", ["3", "1", "0"], "xla_backend_optimization_level values; 3 first.")
  flags.DEFINE_integer("steps", 3, "Train steps run from the init with each compiled step.")
  flags.DEFINE_string("out", os.path.join(REPO, "experiments", "results"), "Results folder.")


def _config(spec: str):
  """The config of `<file in configs/>:<variant>`."""
  from train_helpers import load_config
  name, _, variant = spec.partition(":")
  return load_config(name, variant)


def _timed_compile(lowered, level: int):
  start = time.perf_counter()
  compiled = lowered.compile(compiler_options={"xla_backend_optimization_level": level})
  return compiled, time.perf_counter() - start


def measure(spec: str, levels: list[int], steps: int, with_step: bool) -> dict:
  import jax
  import numpy as np
  from slotlifter_jax import model as model_lib
  from slotlifter_jax import train_step as step_lib
  from train_helpers import fake_batch

  config = _config(spec)
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  key = jax.random.key(0)
  init, init_args = step_lib.init_program(model, config, batch, key)
  init_lowered = init.lower(*init_args)
  if with_step:
    step = step_lib.make_train_step(model, config, key=jax.random.key(1))
    state0 = step_lib.init_state(model, config, batch, key)
    host = jax.tree.map(np.asarray, state0)
    step_lowered = step.lower(state0, batch)
  same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(a, b))

  rows, reference = [], {}
  for level in levels:
    compiled_init, init_s = _timed_compile(init_lowered, level)
    weights = [np.asarray(x) for x in jax.tree.leaves(compiled_init(*init_args))]
    reference.setdefault("weights", weights)
    row = dict(level=level, init_compile_s=round(init_s, 2),
               init_bit_identical_to_level_3=same(weights, reference["weights"]))
    line = (f"{spec} level {level}: init {init_s:5.1f} s to compile "
            f"(same weights as level 3: {row['init_bit_identical_to_level_3']})")
    if with_step:
      compiled_step, step_s = _timed_compile(step_lowered, level)
      state = jax.tree.map(jax.numpy.asarray, host)  # the step donates its state
      state, _ = compiled_step(state, batch)
      jax.block_until_ready(state)
      start = time.perf_counter()
      for _ in range(steps - 1):
        state, _ = compiled_step(state, batch)
      jax.block_until_ready(state)
      run_s = (time.perf_counter() - start) / max(steps - 1, 1)
      trained = [np.asarray(x) for x in jax.tree.leaves(state.params)]
      reference.setdefault("trained", trained)
      row.update(step_compile_s=round(step_s, 2), step_run_s=round(run_s, 4),
                 params_after_steps_bit_identical_to_level_3=same(trained, reference["trained"]),
                 max_param_difference_after_steps=float(max(
                     np.abs(a - b).max() for a, b in zip(trained, reference["trained"]))))
      line += (f"; step {step_s:5.1f} s to compile, {run_s * 1e3:7.1f} ms to run (same after "
               f"{steps} steps: {row['params_after_steps_bit_identical_to_level_3']})")
    rows.append(row)
    print(line, flush=True)
  return dict(config=spec, num_params=sum(w.size for w in reference["weights"]),
              levels=rows)


def result_record(platform: str, steps: int, results: list[dict], configs: dict,
                  *, wall_s: float) -> dict:
  """The JSON this writes: the measurements of each configuration, with the provenance record of
  the configs measured ({spec: config}) and the call's wall time."""
  from slotlifter_jax import provenance
  return dict(platform=platform, steps=steps, results=results,
              **{provenance.KEY: provenance.collect(
                  {spec: provenance.config_dict(c) for spec, c in configs.items()},
                  wall_s=wall_s)})


def main(argv):
  del argv
  t_start = time.perf_counter()
  from slotlifter_jax import runtime
  runtime.set_xla_flags()
  import jax
  jax.config.update("jax_enable_compilation_cache", False)  # every compile is measured
  levels = [int(x) for x in FLAGS.levels]
  if levels[0] != 3:
    raise app.UsageError(f"--levels={','.join(FLAGS.levels)}: the first must be 3 (the reference)")
  results = [measure(spec, levels, FLAGS.steps, spec in FLAGS.step_configs)
             for spec in FLAGS.configs]
  os.makedirs(FLAGS.out, exist_ok=True)
  path = os.path.join(FLAGS.out, f"compile_levels_{jax.default_backend()}.json")
  with open(path, "w") as f:
    json.dump(result_record(jax.default_backend(), FLAGS.steps, results,
                            {spec: _config(spec) for spec in FLAGS.configs},
                            wall_s=time.perf_counter() - t_start), f, indent=1)
  print("wrote", path)


if __name__ == "__main__":
  _define_flags()
  app.run(main)
