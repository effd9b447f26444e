"""Train-step and rendering benchmark: step time, rays/s, FLOPs, model FLOP utilisation, memory.

  python experiments/bench.py                         # every configuration below, ~15 min on 2 cores
  python experiments/bench.py --configs=B,paper_cpu --steps=10
  python experiments/bench.py --configs=B,A --allocators=system,mimalloc,tcmalloc
  python experiments/bench.py --configs=A,B --dtypes=float32,bfloat16

For each configuration, in a fresh process (so its peak memory is its own) that runs exactly what
`python -m slotlifter_jax.main` runs (same allocator preload, XLA flags, mesh and jitted step):
  - train-step time: median (and spread) of --steps steps after two warm-up steps, rays per second;
  - compile time of the step, XLA's temp buffer size, and the process's peak resident memory (on a
    GPU also the device's peak memory, `device_peak_gb`; the paper's batch is `paper_batch`);
  - matmul + convolution FLOPs of one step (forward and backward, counted on the jaxpr by
    slotlifter_jax.flops), the achieved GFLOP/s, this machine's fp32 matmul peak (a 2048² matmul in
    the same process) and their ratio, the model FLOP utilisation (MFU);
  - the time to render one full 128×128 view (after its compilation), with the plain renderer.
Results go to experiments/results/bench_<platform>.json (merged with what is there, so
configurations can be measured in separate calls) and a table on stdout. Each configuration's entry
and the file carry a provenance record (config, git commit, CPU or GPU, jax version, wall time;
slotlifter_jax/provenance.py).

With --allocators every configuration is measured once per allocator (SLOTLIFTER_ALLOCATOR,
slotlifter_jax/runtime.py: system = glibc malloc, mimalloc from the cmeel-mimalloc wheel, tcmalloc
or jemalloc where installed), one after the other in the same call, and stored as
"<config>@<allocator>"; an allocator that is not installed is reported and skipped.

With --dtypes every configuration (and allocator) is measured once per `model.dtype` (float32;
bfloat16 = bf16 matmuls and convolutions with float32 parameters, slotlifter_jax/model.py
"Numerics"), stored as "<config>@<dtype>" (or "<config>@<allocator>@<dtype>"). FLOPs, the matmul
peak and MFU stay float32-based so that rows compare; a bfloat16 row also records the peak of a
bf16 2048² matmul (`matmul_peak_dtype_gflops`), the yardstick of its own compute dtype.

Configurations (issue #7; every other setting is the paper's, configs/clevr.py):
  A           128×128, V = 1, K = 8, 96 samples, 2 scenes × 1024 rays
  A_lowmem    A in memory mode: decoder blocks under nn.scan + nn.remat, gradients accumulated over
              2 scene chunks × 2 ray chunks
  paper_batch the paper's 4 scenes × 1024 rays (A's settings), 2 accumulation chunks
  B           64×64, 32 samples, 2 scenes × 256 rays
  paper_cpu   configs/clevr.py:paper_cpu, the paper's model shrunk to a CPU
  scene       configs/clevr.py:scene, the scene-sized model (host batches, one step per dispatch)
  scene_device scene with its batches drawn inside the jitted step (data.sampler=device)
  scene_scan10 scene_device with 10 steps per dispatch (lax.scan over steps; a call is a block,
              s/step = block time / 10)
  scene_stride2 scene with the encoder's half-size feature map (model.encoder_output_stride = 2)
  scene_samples8 scene with 8 samples per ray (16 in scene; the pareto grid's samples8)
The batches come from scenes of the embedded generator (two per batch, made in memory), so rays
and source views look like training data; speed does not depend on the pixel values.
"""

from __future__ import annotations

import gc
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from slotlifter_jax import runtime  # noqa: E402  (no JAX import)
from slotlifter_jax import provenance  # noqa: E402  (no JAX import)
from experiments import bench_common  # noqa: E402
from experiments.bench_common import CONFIGS  # noqa: E402

RENDER_SIZE = 128

flags.DEFINE_list("configs", ["B", "paper_cpu", "A", "A_lowmem", "paper_batch"],
                  f"Which of {sorted(CONFIGS)} to measure.")
flags.DEFINE_integer("steps", 10, "Timed train steps per configuration (after 2 warm-up steps).")
flags.DEFINE_integer("render_repeats", 3, "Timed full-view renders per configuration.")
flags.DEFINE_string("out", os.path.join(REPO, "experiments", "results"), "Results folder.")
flags.DEFINE_list("allocators", [],
                  "Measure each configuration under each of these SLOTLIFTER_ALLOCATOR values "
                  "(e.g. system,mimalloc,tcmalloc); empty: this process's allocator only.")
flags.DEFINE_list("dtypes", [],
                  "Measure each configuration with each of these model.dtype values "
                  "(float32,bfloat16); empty: the configuration's own (float32).")
flags.DEFINE_string("worker", None, "Internal: measure this one configuration in this process.")
flags.DEFINE_string("worker_dtype", None, "Internal: the worker's model.dtype (None: as configured).")
flags.DEFINE_string("worker_json", None, "Internal: where the worker writes its result.")
FLAGS = flags.FLAGS


def _matmul_peak_gflops(n: int = 2048, repeats: int = 10, dtype: str = "float32") -> float:
  import jax
  import jax.numpy as jnp
  a = jax.random.normal(jax.random.key(0), (n, n), dtype)
  b = jax.random.normal(jax.random.key(1), (n, n), dtype)
  f = jax.jit(jnp.matmul)
  f(a, b).block_until_ready()
  times = []
  for _ in range(repeats):
    t = time.perf_counter()
    f(a, b).block_until_ready()
    times.append(time.perf_counter() - t)
  return 2 * n**3 / min(times) / 1e9


def _reset_peak_rss() -> bool:
  """Resets the kernel's high-water mark of this process's RSS (Linux ≥ 4.0), so the peak we read
  belongs to training and not to the scene generator that ran before it."""
  try:
    with open("/proc/self/clear_refs", "w") as f:
      f.write("5")
    return True
  except OSError:
    return False


def _status_bytes(field: str) -> int | None:
  try:
    with open("/proc/self/status") as f:
      for line in f:
        if line.startswith(field + ":"):
          return int(line.split()[1]) * 1024
  except OSError:
    pass
  return None


def _peak_rss_bytes() -> int:
  peak = _status_bytes("VmHWM")
  return peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure(name: str, steps: int, render_repeats: int, dtype: str | None = None) -> dict:
  import jax
  import numpy as np
  from slotlifter_jax import flops as flops_lib
  from slotlifter_jax.rendering import views as views_lib

  wanted = bench_common.config(name, dtype)
  train_scenes = bench_common.scenes(wanted.train.batch_scenes, wanted.data.image_size, seed=0)
  render_scene = bench_common.scenes(1, RENDER_SIZE, seed=1)[0]
  gc.collect()
  peak_reset = _reset_peak_rss()  # what follows is what training holds, not the generator
  rss_before = _status_bytes("VmRSS") or 0
  config, model, state, batches, train_step = bench_common.setup_step(name, steps + 2, train_scenes,
                                                                      dtype)
  c = config.train
  # A device-sampled configuration's call is a block of steps_per_dispatch steps.
  per_call = int(c.steps_per_dispatch) if config.data.sampler == "device" else 1

  step_flops = flops_lib.count_flops(train_step, state, batches[0]) / per_call
  t = time.perf_counter()
  compiled = train_step.lower(state, batches[0]).compile()
  compile_s = time.perf_counter() - t
  rss_after_compile = _status_bytes("VmRSS") or 0
  mem = compiled.memory_analysis()
  temp_bytes = int(getattr(mem, "temp_size_in_bytes", 0) or 0) if mem is not None else None

  times = []
  for i, batch in enumerate(batches):
    t = time.perf_counter()
    state, metrics = compiled(state, batch)
    jax.block_until_ready(state)
    if i >= 2:
      times.append((time.perf_counter() - t) / per_call)
  loss = float(np.asarray(metrics["loss"]).reshape(-1)[-1])
  host_batch_s = None
  if per_call == 1:
    # What the host sampler adds per step (NumPy gather + transfer); the training loop overlaps
    # it with the step on a thread, which on 2 cores competes with the step for a core.
    from slotlifter_jax import train_step as step_lib
    from slotlifter_jax.data import pipeline
    sampler = pipeline.BatchSampler(train_scenes, batch_scenes=c.batch_scenes,
                                    rays_per_scene=c.rays_per_scene, num_source_views=1,
                                    novel_ray_prob=config.data.novel_ray_prob, seed=0,
                                    ray_sampling=config.data.ray_sampling,
                                    contrast_mix=config.data.contrast_mix)
    mesh = step_lib.make_mesh()
    host = []
    for i in range(steps):
      t = time.perf_counter()
      jax.block_until_ready(step_lib.shard_batch(sampler.batch(i), mesh))
      host.append(time.perf_counter() - t)
    host_batch_s = statistics.median(host)
  train_peak_rss = _peak_rss_bytes()
  device_peak = bench_common.device_peak_bytes(jax.local_devices()[0])  # None on XLA:CPU
  del batches

  # One full view at 128×128 through the evaluation renderer (its own compile excluded).
  renderer = views_lib.SceneRenderer(model, config)
  t = time.perf_counter()
  renderer.render(state.params, render_scene, [1]).colour.sum()
  render_first_s = time.perf_counter() - t
  render_times = []
  for _ in range(render_repeats):
    t = time.perf_counter()
    renderer.render(state.params, render_scene, [1]).colour.sum()
    render_times.append(time.perf_counter() - t)

  peak = _matmul_peak_gflops()
  compute_dtype = str(config.model.get("dtype", "float32"))
  dtype_peak = peak if compute_dtype == "float32" else _matmul_peak_gflops(dtype=compute_dtype)
  step_s = statistics.median(times)
  achieved = step_flops / step_s / 1e9
  return dict(
      allocator=runtime.describe(),
      config=name, image_size=config.data.image_size, num_samples=config.render.num_samples,
      batch_scenes=c.batch_scenes, rays_per_scene=c.rays_per_scene,
      remat_scan=bool(config.model.remat_scan), grad_accum_chunks=int(c.grad_accum_chunks),
      ray_chunks=int(c.ray_chunks),
      dtype=compute_dtype, matmul_peak_dtype_gflops=dtype_peak,
      prng_impl=c.prng_impl, num_params=int(sum(x.size for x in jax.tree.leaves(state.params))),
      step_s_median=step_s, step_s_min=min(times), step_s_max=max(times), steps_timed=len(times),
      steps_per_dispatch=per_call, host_batch_s=host_batch_s,
      rays_per_s=c.batch_scenes * c.rays_per_scene / step_s,
      step_gflop=step_flops / 1e9, achieved_gflops=achieved, matmul_peak_gflops=peak,
      mfu=achieved / peak, compile_s=compile_s, xla_temp_gb=None if temp_bytes is None else temp_bytes / 1e9,
      train_peak_rss_gb=train_peak_rss / 1e9, peak_rss_excludes_data_generation=peak_reset,
      device_peak_gb=None if device_peak is None else device_peak / 1e9,
      rss_before_model_gb=rss_before / 1e9, rss_after_compile_gb=rss_after_compile / 1e9, render_view_s=statistics.median(render_times),
      render_first_call_s=render_first_s, render_size=RENDER_SIZE, render_chunk=config.render.chunk,
      final_loss=loss, finite=bool(np.isfinite(loss)),
  )


def _platform_info() -> dict:
  import jax
  dev = jax.devices()[0]
  return dict(platform=dev.platform, device_kind=getattr(dev, "device_kind", ""),
              num_devices=jax.device_count(), cpu_count=os.cpu_count(), jax=jax.__version__,
              host=platform.node(), allocator=runtime.describe(),
              xla_flags=os.environ.get("XLA_FLAGS", ""), **bench_common.cpu_info(),
              date=time.strftime("%Y-%m-%d %H:%M:%S"))


def _table(rows: list[dict]) -> str:
  head = ("config", "s/step", "host batch s", "rays/s", "GFLOP", "GFLOP/s", "peak", "MFU", "compile s",
          "temp GB", "peak RSS GB", "render 128² s")
  lines = [" | ".join(head), " | ".join("---" for _ in head)]
  for r in rows:
    lines.append(" | ".join([
        r["config"], f"{r['step_s_median']:.4f}",
        "on device" if r.get("host_batch_s") is None else f"{r['host_batch_s']:.4f}",
        f"{r['rays_per_s']:.0f}", f"{r['step_gflop']:.1f}",
        f"{r['achieved_gflops']:.1f}", f"{r['matmul_peak_gflops']:.0f}", f"{100 * r['mfu']:.1f} %",
        f"{r['compile_s']:.1f}", f"{r['xla_temp_gb']:.2f}" if r["xla_temp_gb"] is not None else "–",
        f"{r['train_peak_rss_gb']:.2f}", f"{r['render_view_s']:.2f}"]))
  return "\n".join("| " + l + " |" for l in lines)


def main(argv):
  del argv
  if FLAGS.worker:
    t0 = time.perf_counter()
    result = measure(FLAGS.worker, FLAGS.steps, FLAGS.render_repeats, FLAGS.worker_dtype)
    # The configuration as measured, the commit, the machine and this worker's wall time.
    result[provenance.KEY] = provenance.collect(
        bench_common.config(FLAGS.worker, FLAGS.worker_dtype), wall_s=time.perf_counter() - t0)
    with open(FLAGS.worker_json, "w") as f:
      json.dump(result, f)
    return
  unknown = [n for n in FLAGS.configs if n not in CONFIGS]
  if unknown:
    raise app.UsageError(f"unknown configs {unknown}; choose from {sorted(CONFIGS)}")
  runtime.set_xla_flags()
  t_start = time.perf_counter()
  info = _platform_info()
  os.makedirs(FLAGS.out, exist_ok=True)
  out_path = os.path.join(FLAGS.out, f"bench_{info['platform']}.json")
  previous = {}
  if os.path.exists(out_path):
    with open(out_path) as f:
      previous = json.load(f).get("configs", {})
  for choice in FLAGS.allocators:
    if choice not in runtime.ALLOCATORS:
      raise app.UsageError(f"--allocators: unknown {choice!r}; choose from {runtime.ALLOCATORS}")
  from slotlifter_jax import emergence  # its atomic JSON writer (numpy only, no JAX)
  from slotlifter_jax import model as model_lib  # the valid model.dtype names
  for dtype in FLAGS.dtypes:
    if dtype not in model_lib.COMPUTE_DTYPES:
      raise app.UsageError(f"--dtypes: unknown {dtype!r}; choose from "
                           f"{sorted(model_lib.COMPUTE_DTYPES)}")
  rows = []
  runs = [(name, choice, dtype) for name in FLAGS.configs for choice in FLAGS.allocators or [None]
          for dtype in FLAGS.dtypes or [None]]
  for name, choice, dtype in runs:
    key = "@".join(x for x in (name, choice, dtype) if x is not None)
    env = dict(os.environ)
    if choice is not None:
      try:
        runtime.allocator_env(choice)
      except RuntimeError as e:
        print(f"[bench] {key}: skipped ({e})", flush=True)
        continue
      # A fresh worker picks its own allocator: drop what this process was preloaded with.
      for var in ("LD_PRELOAD", "MALLOC_CONF", runtime.MARK, *runtime.MIMALLOC_ENV):
        env.pop(var, None)
      env[runtime.ENV] = choice
    print(f"[bench] {key} …", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
      result_path = os.path.join(tmp, "result.json")
      cmd = [sys.executable, os.path.abspath(__file__), f"--worker={name}",
             f"--worker_json={result_path}", f"--steps={FLAGS.steps}",
             f"--render_repeats={FLAGS.render_repeats}"]
      if dtype is not None:
        cmd.append(f"--worker_dtype={dtype}")
      proc = subprocess.run(cmd, env=env)
      if proc.returncode != 0:
        print(f"[bench] {key} failed with exit code {proc.returncode}", flush=True)
        continue
      with open(result_path) as f:
        result = json.load(f)
    result["config"] = key
    result["measured"] = dict(info, allocator=result.get("allocator", info["allocator"]))
    previous[key] = result
    rows.append(result)
    print(_table([result]).splitlines()[-1], flush=True)
    # After every configuration, so a call cut short (a lease's time limit) keeps what it measured.
    # The file's own record: this call's commit, machine and wall time so far (each
    # configuration carries its config in its own record).
    emergence.write_json_atomically(out_path, dict(
        info, configs=previous,
        **{provenance.KEY: provenance.collect(wall_s=time.perf_counter() - t_start)}))
  print(_table(rows))
  print(f"[bench] wrote {out_path}" if rows else "[bench] nothing measured, nothing written")


if __name__ == "__main__":
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  app.run(main)
