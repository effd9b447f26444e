"""Adaptive full-view rendering (issue #7, slotlifter_jax/rendering/adaptive.py): speed against
the plain path, and quality at that speed on a trained model.

  python experiments/bench_render.py --workdir=runs/clevr_paper_cpu   # ~15 min on 2 cores
  python experiments/bench_render.py --scenes=5 --skip_timing --skip_context

Three parts, each renderer pair in one process so the ratio is trustworthy on a noisy machine
(tcmalloc and XLA flags as slotlifter_jax.main, via slotlifter_jax.runtime):

1. Timing, random-init weights (shapes are fixed, so the plain path's time does not depend on
   them): one full view of config A (experiments/bench_common.py: 128×128, 96 samples) and of
   `configs/clevr.py:paper_cpu` (32 samples) at 64×64 and 128×128, plain vs adaptive, median of
   --repeats renders after one compiling render, alternating the two. The adaptive renderer runs
   with the fallback off here: its fixed-shape passes are what is timed, because a random-init
   model's density is spread along every ray and would send nearly every pixel to the fallback.
   The trained model's fallback share and its cost are measured in part 2.
2. Quality, the trained paper_cpu model (--workdir, default runs/clevr_paper_cpu) on --scenes test
   scenes, every view: novel-view PSNR, ARI / FG-ARI (source view) and NV-ARI / NV-FG-ARI of the
   plain path and of each --settings entry (stride:window:eps:fallback), their differences, the
   share of pixels whose argmax slot differs, the overflow and fallback shares, the decoder work
   relative to the plain path (rays × samples, padding included), and the time per view (median
   over the scenes after the first, which compiles). The fastest setting within --max_psnr_drop
   dB and --max_argmax_diff argmax disagreement is picked.
3. Context, the same model: what windowing alone costs. Every pixel of the novel views of
   --context_scenes scenes is rendered on the whole grid and on a window of W samples centred on
   its own significant range (ε = 0.01, no neighbours involved); reported per W: the share of
   rays whose range fits, and on those the mean / max colour error and argmax-slot disagreement.
   A ray's result depends on all its samples through the per-ray self-attention, so this is the
   floor of the adaptive path's error at that W.

Writes experiments/results/render_adaptive_<platform>.json and prints the tables.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import time

from absl import app, flags

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from slotlifter_jax import runtime  # noqa: E402  (no JAX import)
from slotlifter_jax import provenance  # noqa: E402  (no JAX import)
from experiments import bench_common  # noqa: E402

flags.DEFINE_string("workdir", "runs/clevr_paper_cpu", "A trained configs/clevr.py:paper_cpu run.")
flags.DEFINE_string("checkpoint", "", "Checkpoint of --workdir: '' (best, else latest), best, "
                    "latest or a step.")
flags.DEFINE_integer("scenes", 20, "Test scenes for the quality part.")
flags.DEFINE_integer("repeats", 3, "Timed renders per renderer in the timing part.")
flags.DEFINE_list("settings", ["3:24:0.01:1", "4:24:0.01:1", "3:16:0.01:1", "4:16:0.01:1",
                               "3:12:0.01:1", "3:12:0.03:1", "3:12:0.01:0"],
                  "Adaptive settings of the quality part, stride:window:eps:fallback(0/1).")
flags.DEFINE_list("timing_A", ["3:24:0.01", "4:24:0.01", "4:16:0.01"],
                  "stride:window:eps settings timed on config A.")
flags.DEFINE_string("timing_paper_cpu", "", "stride:window:eps timed on the paper_cpu config; empty: "
                    "the setting picked in the quality part (3:12:0.01 with --skip_quality).")
flags.DEFINE_float("max_psnr_drop", 0.1, "Quality bound: |novel-view PSNR difference| in dB.")
flags.DEFINE_float("max_argmax_diff", 0.01, "Quality bound: share of pixels whose argmax slot "
                   "differs from the plain path's.")
flags.DEFINE_list("plain_chunks", ["4096", "1024"], "Rays per chunk of the plain renderer in "
                  "the timing part; speed-ups are against the fastest (the adaptive passes size "
                  "their own chunks).")
flags.DEFINE_bool("skip_timing", False, "Skip the timing part.")
flags.DEFINE_bool("skip_quality", False, "Skip the quality part.")
flags.DEFINE_bool("skip_context", False, "Skip the context part.")
flags.DEFINE_list("context_windows", ["12", "16", "24"], "Windows of the context part.")
flags.DEFINE_integer("context_scenes", 3, "Test scenes (novel views) of the context part.")
flags.DEFINE_string("out", os.path.join(REPO, "experiments", "results"), "Results folder.")
FLAGS = flags.FLAGS


def _setting(*, stride: int, window: int, eps: float, fallback: bool) -> dict:
  name = f"s{stride}/W{window}/eps{eps:g}/" + ("fb" if fallback else "nofb")
  return dict(stride=stride, window=window, eps=eps, fallback=fallback, name=name)


def _parse(text: str) -> dict:
  """'stride:window:eps[:fallback 0/1]' → a setting (fallback on when not given)."""
  parts = text.split(":")
  return _setting(stride=int(parts[0]), window=int(parts[1]), eps=float(parts[2]),
                  fallback=bool(int(parts[3])) if len(parts) > 3 else True)


def _with_adaptive(config, setting: dict):
  config = config.copy_and_resolve_references()
  r = config.render
  r.adaptive, r.adaptive_stride, r.adaptive_window = True, setting["stride"], setting["window"]
  r.adaptive_mass_eps, r.adaptive_fallback = setting["eps"], setting["fallback"]
  return config


def _random_params(model, scene):
  import jax
  from slotlifter_jax import train_step
  inputs = train_step.init_batch(scene)
  inputs.pop("target_rgb")
  return jax.jit(lambda: model.init(jax.random.key(0), **inputs, train=False))()["params"]


# ---------------------------------------------------------------------------------------------
# 1. Timing
# ---------------------------------------------------------------------------------------------


def time_group(name: str, size: int, settings: list[dict], repeats: int) -> list[dict]:
  """Plain (at each of --plain_chunks) vs adaptive (fallback off) on one view of a generated
  scene, random-init weights; each repeat renders every renderer once, so drift in the machine's
  load hits all alike. Speed-ups are against the fastest plain chunk size."""
  from slotlifter_jax import model as model_lib
  from slotlifter_jax.rendering import adaptive, views as views_lib
  config = bench_common.config(name)
  config.data.image_size = size
  scene = bench_common.scenes(1, size, seed=1)[0]
  model = model_lib.build_model(config)
  params = _random_params(model, scene)
  plains = {}
  for chunk in FLAGS.plain_chunks:
    c = config.copy_and_resolve_references()
    c.render.chunk = int(chunk)
    plains[f"plain/chunk{chunk}"] = views_lib.SceneRenderer(model, c)
  fixed = [_setting(**dict((k, s[k]) for k in ("stride", "window", "eps")), fallback=False)
           for s in settings]
  renderers = dict(plains, **{f["name"]: adaptive.AdaptiveSceneRenderer(
      model, _with_adaptive(config, f)) for f in fixed})
  first, works, times = {}, {}, {k: [] for k in renderers}
  for key, r in renderers.items():  # compiles
    t = time.perf_counter()
    if key in plains:
      r.render(params, scene, [1])
    else:
      works[key] = r.render_with_diagnostics(params, scene, [1])[1][0].work_fraction
    first[key] = time.perf_counter() - t
  for _ in range(repeats):
    for key, r in renderers.items():
      t = time.perf_counter()
      r.render(params, scene, [1])
      times[key].append(time.perf_counter() - t)
  med = {k: statistics.median(v) for k, v in times.items()}
  best_plain = min(plains, key=lambda k: med[k])
  for k in plains:
    print(f"[timing] {name} {size}² {k}: {med[k]:.2f} s {times[k]}", flush=True)
  rows = []
  for f in fixed:
    key = f["name"]
    rows.append(dict(config=name, size=size, num_samples=int(config.render.num_samples),
                     setting=key, plain=best_plain, plain_s=med[best_plain],
                     adaptive_s=med[key], speedup=med[best_plain] / med[key],
                     plain_times={k: times[k] for k in plains}, adaptive_times=times[key],
                     first_call_s={k: first[k] for k in (*plains, key)},
                     work_fraction=works[key]))
    print(f"[timing] {name} {size}² {key}: {med[key]:.2f} s, ×{rows[-1]['speedup']:.2f} against "
          f"{best_plain} (decoder work {works[key]:.3f})", flush=True)
  return rows


# ---------------------------------------------------------------------------------------------
# 2. Quality on a trained run
# ---------------------------------------------------------------------------------------------


def quality(settings: list[dict]) -> dict:
  import numpy as np
  from slotlifter_jax import evaluate, metrics
  from slotlifter_jax.rendering import adaptive, views as views_lib
  sys.path.insert(0, os.path.join(REPO, "configs"))
  import clevr  # configs/clevr.py
  config = clevr.get_config("paper_cpu")
  run = evaluate.load_run(config, FLAGS.workdir, split="test", checkpoint=FLAGS.checkpoint,
                          max_scenes=FLAGS.scenes)
  plain = views_lib.SceneRenderer(run.model, run.config)
  renderers = [adaptive.AdaptiveSceneRenderer(run.model, _with_adaptive(run.config, s))
               for s in settings]
  names = ["plain"] + [s["name"] for s in settings]
  per_scene = {n: [] for n in names}
  view_s = {n: [] for n in names}
  disagree = {n: [] for n in names[1:]}
  diag_rows = {n: [] for n in names[1:]}
  for i, scene in enumerate(run.scenes):
    views = list(range(scene.num_views))
    t = time.perf_counter()
    ref = plain.render(run.params, scene, views)
    view_s["plain"].append((time.perf_counter() - t) / len(views))
    per_scene["plain"].append(evaluate.scene_metrics(ref, scene, views))
    ref_label = metrics.segmentation_from_render(ref.segmentation)
    for name, renderer in zip(names[1:], renderers):
      t = time.perf_counter()
      got, diags = renderer.render_with_diagnostics(run.params, scene, views)
      view_s[name].append((time.perf_counter() - t) / len(views))
      per_scene[name].append(evaluate.scene_metrics(got, scene, views))
      disagree[name].append(float(np.mean(metrics.segmentation_from_render(got.segmentation)
                                          != ref_label)))
      diag_rows[name] += [(d.overflow_fraction, float(d.fallback.mean()), d.work_fraction,
                           float(np.mean(d.proposal))) for d in diags]
    print(f"[quality] scene {i + 1}/{len(run.scenes)}: plain {view_s['plain'][-1]:.2f} s/view",
          flush=True)

  keys = ("psnr_novel", "psnr_source", "ari", "fg_ari", "nv_ari", "nv_fg_ari")
  steady = lambda xs: statistics.median(xs[1:] if len(xs) > 1 else xs)  # the first compiles
  plain_mean = evaluate.mean_over_scenes(per_scene["plain"])
  plain_view_s = steady(view_s["plain"])
  rows = [dict(setting="plain", **{k: plain_mean.get(k) for k in keys},
               view_s=plain_view_s, speedup=1.0)]
  for name, s in zip(names[1:], settings):
    mean = evaluate.mean_over_scenes(per_scene[name])
    d = np.asarray(diag_rows[name])  # [views, 4]
    dpsnr = [a["psnr_novel"] - b["psnr_novel"] for a, b in zip(per_scene[name],
                                                               per_scene["plain"])]
    row = dict(setting=name, **s, **{k: mean.get(k) for k in keys},
               d_psnr_novel=mean["psnr_novel"] - plain_mean["psnr_novel"],
               max_scene_abs_d_psnr_novel=float(np.max(np.abs(dpsnr))),
               d_fg_ari=mean["fg_ari"] - plain_mean["fg_ari"],
               d_ari=mean["ari"] - plain_mean["ari"],
               argmax_diff=float(np.mean(disagree[name])),
               overflow=float(d[:, 0].mean()), fallback_share=float(d[:, 1].mean()),
               work_fraction=float(d[:, 2].mean()), proposal_share=float(d[:, 3].mean()),
               view_s=steady(view_s[name]))
    row["speedup"] = plain_view_s / row["view_s"]
    row["within_bounds"] = bool(abs(row["d_psnr_novel"]) <= FLAGS.max_psnr_drop
                                and row["argmax_diff"] <= FLAGS.max_argmax_diff)
    rows.append(row)
  ok = [r for r in rows[1:] if r["within_bounds"]]
  best = max(ok, key=lambda r: r["speedup"]) if ok else None
  return dict(workdir=FLAGS.workdir, checkpoint_step=run.step, num_scenes=len(run.scenes),
              image_size=list(run.scenes[0].image_size),
              num_samples=int(run.config.render.num_samples), rows=rows,
              picked=None if best is None else best["setting"],
              picked_spec=None if best is None else
              f"{best['stride']}:{best['window']}:{best['eps']:g}",
              bounds=dict(max_psnr_drop=FLAGS.max_psnr_drop,
                          max_argmax_diff=FLAGS.max_argmax_diff))


def context(windows: list[int]) -> dict:
  """Part 3 of the module docstring."""
  import jax
  import numpy as np
  from slotlifter_jax import evaluate
  from slotlifter_jax.rendering import adaptive, views as views_lib
  sys.path.insert(0, os.path.join(REPO, "configs"))
  import clevr  # configs/clevr.py
  run = evaluate.load_run(clevr.get_config("paper_cpu"), FLAGS.workdir, split="test",
                          checkpoint=FLAGS.checkpoint, max_scenes=FLAGS.context_scenes)
  model, params, eps = run.model, run.params, 0.01
  grid = adaptive.SampleGrid(near=model.near, far=model.far, num_samples=model.num_samples)

  @jax.jit
  def full(encoded, sources, origins, directions):
    fn = adaptive.model_render_fn(model, params, encoded, sources, False)
    return adaptive.proposal_pass(fn, origins=origins, directions=directions, grid=grid,
                                  mass_eps=eps)

  def windowed(window):
    @jax.jit
    def f(encoded, sources, origins, directions, start):
      fn = adaptive.model_render_fn(model, params, encoded, sources, False)
      return adaptive.window_pass(fn, origins=origins, directions=directions, start=start,
                                  grid=grid, window=window)
    return f

  encode = views_lib.make_encode(model)
  stats = {w: dict(fits=[], err=[], argmax=[]) for w in windows}
  for scene in run.scenes:
    sources = views_lib.scene_sources(scene, signed=False)
    encoded = encode(params, sources)
    height, width = scene.image_size
    for v in scene.novel_indices:
      o, d = adaptive.camera_rays(cam_to_world=scene.cam_to_world[v],
                                  intrinsics=scene.intrinsics[v], height=height, width=width)
      colour, _, seg, lo, hi = (np.asarray(x)[0] for x in full(encoded, sources, o[None],
                                                               d[None]))
      for w in windows:
        win = adaptive.choose_windows(lo=lo[:, None], hi=hi[:, None], window=w,
                                      num_samples=model.num_samples)
        fits = np.asarray(win.overflow) == 0
        c2, _, s2 = (np.asarray(x)[0] for x in windowed(w)(
            encoded, sources, o[None], d[None], np.asarray(win.start)[None]))
        stats[w]["fits"].append(fits)
        stats[w]["err"].append(np.abs(c2 - colour).max(-1)[fits])
        stats[w]["argmax"].append((s2.argmax(-1) != seg.argmax(-1))[fits])
  rows = []
  for w in windows:
    err = np.concatenate(stats[w]["err"])
    rows.append(dict(window=w, fits=float(np.mean(np.concatenate(stats[w]["fits"]))),
                     colour_err_mean=float(err.mean()), colour_err_max=float(err.max()),
                     argmax_diff=float(np.mean(np.concatenate(stats[w]["argmax"])))))
    print(f"[context] W {w}: {100 * rows[-1]['fits']:.1f} % of rays fit; colour error mean "
          f"{rows[-1]['colour_err_mean']:.4f} max {rows[-1]['colour_err_max']:.3f}; argmax "
          f"differs {100 * rows[-1]['argmax_diff']:.2f} %", flush=True)
  return dict(num_scenes=len(run.scenes), num_samples=int(model.num_samples), mass_eps=eps,
              rows=rows)


# ---------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------


def _fmt(x, spec):
  return "–" if x is None else format(x, spec)


def timing_table(rows: list[dict]) -> str:
  head = ("config", "view", "S", "adaptive setting", "plain (fastest chunk)", "plain s",
          "adaptive s", "speed-up", "decoder work")
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for r in rows:
    lines.append(f"| {r['config']} | {r['size']}² | {r['num_samples']} | {r['setting']} | "
                 f"{r['plain']} | {r['plain_s']:.2f} | {r['adaptive_s']:.2f} | "
                 f"×{r['speedup']:.2f} | {r['work_fraction']:.3f} |")
  return "\n".join(lines)


def quality_table(q: dict) -> str:
  head = ("setting", "PSNR nv", "ΔPSNR", "max |ΔPSNR| scene", "ARI", "FG-ARI", "NV-ARI",
          "NV-FG-ARI", "argmax diff", "overflow", "fallback", "work", "s/view", "speed-up")
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for r in q["rows"]:
    mark = " ✓" if r.get("within_bounds") else ""
    lines.append(" | ".join([
        f"| {r['setting']}{' ← picked' if r['setting'] == q['picked'] else ''}",
        _fmt(r["psnr_novel"], ".3f"), _fmt(r.get("d_psnr_novel"), "+.3f") + mark,
        _fmt(r.get("max_scene_abs_d_psnr_novel"), ".3f"), _fmt(r["ari"], ".4f"),
        _fmt(r["fg_ari"], ".4f"), _fmt(r["nv_ari"], ".4f"), _fmt(r["nv_fg_ari"], ".4f"),
        _fmt(None if r.get("argmax_diff") is None else 100 * r["argmax_diff"], ".2f") + (
            " %" if r.get("argmax_diff") is not None else ""),
        _fmt(None if r.get("overflow") is None else 100 * r["overflow"], ".1f") + (
            " %" if r.get("overflow") is not None else ""),
        _fmt(None if r.get("fallback_share") is None else 100 * r["fallback_share"], ".1f") + (
            " %" if r.get("fallback_share") is not None else ""),
        _fmt(r.get("work_fraction", 1.0), ".3f"), f"{r['view_s']:.3f}",
        f"×{r['speedup']:.2f} |"]))
  return "\n".join(lines)


def main(argv):
  del argv
  t_start = time.perf_counter()
  import jax
  os.makedirs(FLAGS.out, exist_ok=True)
  platform = jax.devices()[0].platform
  out_path = os.path.join(FLAGS.out, f"render_adaptive_{platform}.json")
  previous = {}
  if os.path.exists(out_path):  # the part not measured this time is kept
    with open(out_path) as f:
      previous = json.load(f)
  result = dict(platform=platform, cpu_count=os.cpu_count(), jax=jax.__version__,
                allocator=runtime.describe(), xla_flags=os.environ.get("XLA_FLAGS", ""),
                note="timings on a shared 2-core CPU are noisy; the ratios are measured in one "
                     "process, renders alternating")
  stamp = lambda: time.strftime("%Y-%m-%d %H:%M:%S")
  if FLAGS.skip_quality:
    if "quality" in previous:
      result["quality"] = previous["quality"]
  else:
    result["quality"] = dict(quality([_parse(s) for s in FLAGS.settings]), date=stamp())
    print(quality_table(result["quality"]), flush=True)
  if FLAGS.skip_context:
    if "context" in previous:
      result["context"] = previous["context"]
  else:
    result["context"] = dict(context([int(w) for w in FLAGS.context_windows]), date=stamp())
  if FLAGS.skip_timing:
    if "timing" in previous:
      result["timing"] = previous["timing"]
  else:
    picked = result.get("quality", {}).get("picked_spec")
    paper_cpu_setting = FLAGS.timing_paper_cpu or picked or "3:16:0.01"
    rows = time_group("A", 128, [_parse(s) for s in FLAGS.timing_A], FLAGS.repeats)
    for size in (64, 128):
      rows += time_group("paper_cpu", size, [_parse(paper_cpu_setting)], FLAGS.repeats)
    result["timing"] = dict(rows=rows, date=stamp(), plain_chunks=FLAGS.plain_chunks)
    print(timing_table(rows), flush=True)
  # Commit, machine, jax version and wall time; the configs are the benchmark's "A" and "paper_cpu".
  result[provenance.KEY] = provenance.collect(
      {name: provenance.config_dict(bench_common.config(name)) for name in ("A", "paper_cpu")},
      wall_s=time.perf_counter() - t_start)
  tmp = out_path + ".tmp"
  with open(tmp, "w") as f:
    json.dump(result, f, indent=1)
  os.replace(tmp, out_path)
  print(f"[bench_render] wrote {out_path}")


if __name__ == "__main__":
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  app.run(main)
