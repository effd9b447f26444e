"""The runner shared by the studies of issue #6 (pareto.py, ablations.py, stability.py).

One *run* = a base config (`configs/<file>.py:<variant>`), a dict of dotted overrides, a seed and a
training budget (steps). `execute(run, root=...)`:
  1. builds the config: the variant, then the budget (`budget_config`: train.num_steps, which
     the variant's schedules follow, a fixed number of validations), then the overrides, then the
     seed; unknown override keys, a missing config file or an unknown variant fail here, naming
     the problem, before any work;
  2. names the run directory after a hash of the config spec, the overrides that change it, the
     seed and the budget (`run_id`), so two studies that ask for the same training share one run
     (stability.py reuses ablations.py's `full`);
  3. trains with `slotlifter_jax.train.train_and_evaluate`, which resumes from the last checkpoint
     in the directory; the wall-clock seconds of each training call are added to
     DIR/study_timing.json (a segment killed so hard that Python cannot record it is lost);
  4. evaluates the last checkpoint with `slotlifter_jax.evaluate.evaluate_split` on a capped number
     of scenes of one split;
  5. writes the result to DIR/study_result_<split>_<scenes>.json and upserts its row into a CSV
     (temp file + os.replace, keyed by run id, so running a script again adds no duplicates).
A run whose result JSON exists is skipped; a run with a finished training but no result is only
evaluated. So re-running a study script resumes where it stopped.

Why the schedules follow the budget: configs/*.py:paper_cpu anneal masking and slot noise over 3000 of
6500 steps. Cut to 1000 steps with fixed schedules, a run would stop with most of its rays still
masked and the locality constraint on, and the "without random masking" ablation would compare a
finished method against an unfinished one. The variants state each schedule as a share of
train.num_steps (slotlifter_jax/defaults.py), so a run of any budget is a complete, compressed
version of its method (pass scale_schedules=False to hold them at the variant's own budget).
A config without such shares (the paper's, `smoke`) keeps its schedules as written.

Recorded per run (the CSV's columns, METRIC_KEYS and below):
  train_s            wall-clock seconds of training, summed over resumed segments; includes the
                     step compilation and the in-training validations (their cost is part of
                     training), excludes data generation (done before the clock starts)
  step_s             median seconds per step from the training log (steps_per_sec)
  render_per_view_s  seconds to render one full view at evaluation (median, compilation excluded)
  psnr_novel, ari, fg_ari, nv_ari, nv_fg_ari, active_slots, …  evaluate_split's means over scenes
  collapsed          1/0: the last validation of the run flags collapse (train.py writes
                     `collapsed` into DIR/metrics.jsonl), counted only once the masking and noise
                     schedules have settled (collapse.settled_step); NaN without validation

Nothing here imports JAX at module level, so a script can re-execute itself with the allocator of
`slotlifter_jax.runtime` first (as experiments/bench.py does).
"""

from __future__ import annotations

import ast
import copy
import csv
import dataclasses
import functools
import hashlib
import importlib.util
import io
import json
import math
import os
import statistics
import sys
import time
from typing import Any, Iterable, Mapping, Optional, Sequence

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_ROOT = os.path.join(REPO, "runs", "study")  # runs/ is git-ignored
RESULTS_DIR = os.path.join(REPO, "experiments", "results")

TIMING_FILE = "study_timing.json"
# Metrics copied from evaluate_split's summary (the mean over scenes) into a run's row.
METRIC_KEYS = ("psnr_novel", "psnr_source", "ssim", "lpips", "ari", "fg_ari", "nv_ari",
               "nv_fg_ari", "active_slots", "num_objects")
CSV_COLUMNS = (("study", "name", "config", "overrides", "seed", "num_steps", "run_id", "run_dir",
                "train_s", "train_segments", "step_s", "eval_split", "eval_scenes",
                "checkpoint_step", "render_per_view_s", "eval_s") + METRIC_KEYS +
               ("collapsed", "collapse_step", "probe_active_slots", "probe_largest_share"))

# Rough cost model for --dry_run (estimates, not measurements): experiments/journal/2026-11.md
# measured configs/clevr.py:paper_cpu at about 0.3 s per step (64², 32 samples, 2 × 256 rays) on the 2-core CPU,
# and evaluation at about 2.6 s per 4-view scene at 64²; the allocation transformer is most of a
# step, so its part scales with rays × samples × its blocks × widths, and a view's render with
# pixels × samples. What does not shrink with the decoder (encoder, optimiser, host work) is a
# fixed part per step, fitted so that clevr.py:scene comes out near its measured ~0.045 s per
# step with validations (docs/fast_model.md).
_REF_STEP_S, _REF_RAYS, _REF_SAMPLES = 0.3, 2 * 256, 32
_REF_DECODER = 4 * (64 + 256)  # paper_cpu: num_blocks × (point_dim + ffn_dim)
_FIXED_STEP_S = 0.025
_REF_SCENE_S, _REF_PIXELS = 2.6, 64 * 64
_COMPILE_S = 60.0  # step + renderer compilation and set-up per run, a guess


class StudyError(ValueError):
  """A bad study request: unknown config, variant or override key."""


class TrainingStopped(RuntimeError):
  """Training left before the budget (a signal): the checkpoint is kept, run again to resume."""


@dataclasses.dataclass(frozen=True)
class Run:
  """One training run of a study. `overrides` maps dotted config keys to values."""
  name: str  # the point / variant this run belongs to (a CSV column, not part of the identity)
  config: str  # "configs/clevr.py:paper_cpu" (relative to the repository, or absolute)
  overrides: Mapping[str, Any]
  seed: int
  num_steps: int


# ---------------------------------------------------------------------------------------------
# Configs


def load_config(spec: str):
  """The config of `path.py[:variant]` (path relative to the repository, or absolute)."""
  path, _, variant = spec.partition(":")
  full = path if os.path.isabs(path) else os.path.join(REPO, path)
  if not os.path.isfile(full):
    raise StudyError(f"config file {path!r} not found (looked for {full}); use e.g. "
                     f"configs/clevr.py:paper_cpu")
  module_spec = importlib.util.spec_from_file_location(
      "study_config_" + hashlib.sha1(full.encode()).hexdigest()[:8], full)
  module = importlib.util.module_from_spec(module_spec)
  module_spec.loader.exec_module(module)
  if not hasattr(module, "get_config"):
    raise StudyError(f"{path}: has no get_config(variant)")
  try:
    return module.get_config(variant)
  except ValueError as e:
    raise StudyError(f"{spec}: {e}") from e


def parse_set_overrides(items) -> dict:
  """{dotted key: value} from `--set=KEY=VALUE` strings: a Python literal where the value parses
  as one, else the bare word (a string such as boxes). StudyError names an item without '='."""
  overrides = {}
  for item in items:
    key, sep, value = item.partition("=")
    if not sep:
      raise StudyError(f"--set={item!r}: expected KEY=VALUE")
    try:
      overrides[key] = ast.literal_eval(value)
    except (ValueError, SyntaxError):
      overrides[key] = value
  return overrides


def apply_overrides(config, overrides: Mapping[str, Any]):
  """A copy of `config` with the dotted `overrides` set; every key must exist already."""
  config = config.copy_and_resolve_references()
  for key, value in overrides.items():
    *parents, field = key.split(".")
    node = config
    for i, part in enumerate(parents):
      if part not in node or not hasattr(node[part], "keys"):
        raise StudyError(f"unknown override key {key!r}: no section "
                         f"{'.'.join(parents[:i + 1])!r} in the config")
      node = node[part]
    if not parents or field not in node:
      where = ".".join(parents) or "the config"
      known = ", ".join(sorted(node.keys())) if parents else ""
      raise StudyError(f"unknown override key {key!r}: {where} has no field {field!r}"
                       + (f" (it has: {known})" if known else ""))
    if hasattr(node[field], "keys"):
      raise StudyError(f"override key {key!r} names a section, not a field")
    try:
      node[field] = tuple(value) if isinstance(value, list) else value
    except TypeError as e:
      raise StudyError(f"override {key}={value!r}: {e}") from e
  return config


def budget_config(config, num_steps: int, *, scale_schedules: bool = True,
                  num_validations: int = 2):
  """A resolved copy of `config` that trains `num_steps` steps (module docstring: why schedules
  follow the budget).

  The variants state their schedules as shares of train.num_steps (slotlifter_jax/defaults.py,
  `_share`), so setting the budget moves them; scale_schedules=False resolves them at the
  config's own budget first. Validates `num_validations` times (the last at the final step, which
  gives the collapse flag), and checkpoints at least as often.
  """
  if num_steps < 1:
    raise StudyError(f"the budget must be at least one step, got {num_steps}")
  config = copy.deepcopy(config) if scale_schedules else config.copy_and_resolve_references()
  config.train.num_steps = int(num_steps)
  config = config.copy_and_resolve_references()
  t = config.train
  t.eval_every = max(1, num_steps // max(1, num_validations))
  t.checkpoint_every = max(1, min(int(t.checkpoint_every), t.eval_every))
  # One run is one attempt of one seed: a study measures how often a recipe fails (stability.py's
  # collapse rate, an ablation's loss), which restarts would hide, and its two validations fall on
  # no restart check step anyway.
  t.restarts = 0
  t.restart_check_step = 0
  return config


def _base_config(run: Run, *, scale_schedules: bool, num_validations: int):
  if "train.num_steps" in run.overrides:
    raise StudyError("override 'train.num_steps' is the budget: set it with num_steps instead")
  return budget_config(load_config(run.config), run.num_steps, scale_schedules=scale_schedules,
                       num_validations=num_validations)


def run_config(run: Run, *, scale_schedules: bool = True, num_validations: int = 2):
  """The full config of `run`: variant → budget → overrides → seed."""
  config = apply_overrides(_base_config(run, scale_schedules=scale_schedules,
                                        num_validations=num_validations), run.overrides)
  config.seed = int(run.seed)
  return config


def _canonical(value):
  return list(value) if isinstance(value, tuple) else value


def run_id(run: Run, *, scale_schedules: bool = True, num_validations: int = 2) -> str:
  """`<config>-<variant>-s<seed>-n<steps>-<hash>`, the hash of (config spec, the overrides that
  change the budgeted config, seed, budget, schedule scaling, validations).

  An override equal to the config's own value is dropped, so two studies asking for the same
  training share the directory however they spell it (stability.py reuses ablations.py's `full`).
  The resolved config is not hashed: a field added to the code later would rename every run and
  throw away finished work. The price: after editing a config file's variant, use another --root
  (train.py still refuses to resume a run whose model section changed).
  """
  base = _base_config(run, scale_schedules=scale_schedules, num_validations=num_validations)
  apply_overrides(base, run.overrides)  # unknown keys fail here, by name
  flat = lambda key: functools.reduce(lambda node, part: node[part], key.split("."), base)
  effective = {k: _canonical(v) for k, v in sorted(run.overrides.items())
               if json.dumps(_canonical(v)) != json.dumps(_canonical(flat(k)))}
  identity = dict(config=run.config, overrides=effective, seed=int(run.seed),
                  num_steps=int(run.num_steps), scale_schedules=bool(scale_schedules),
                  num_validations=int(num_validations))
  digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:10]
  path, _, variant = run.config.partition(":")
  stem = os.path.splitext(os.path.basename(path))[0]
  return f"{stem}-{variant or 'paper'}-s{run.seed}-n{run.num_steps}-{digest}"


# ---------------------------------------------------------------------------------------------
# Files of a run


def result_path(run_dir: str, split: str, eval_scenes: Optional[int]) -> str:
  return os.path.join(run_dir, f"study_result_{split}_{eval_scenes or 'all'}.json")


def _write_json(path: str, data) -> None:
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    json.dump(data, f, indent=1, sort_keys=True, allow_nan=True)
  os.replace(tmp, path)


def read_timing(run_dir: str) -> dict:
  path = os.path.join(run_dir, TIMING_FILE)
  if not os.path.exists(path):
    return {"segments": [], "train_s": 0.0}
  with open(path) as f:
    return json.load(f)


def add_training_segment(run_dir: str, *, seconds: float, from_step: int, to_step: int) -> dict:
  """Adds one training call's wall-clock seconds to DIR/study_timing.json; returns the record."""
  timing = read_timing(run_dir)
  timing["segments"].append({"seconds": float(seconds), "from_step": int(from_step),
                             "to_step": int(to_step),
                             "ended": time.strftime("%Y-%m-%dT%H:%M:%S")})
  timing["train_s"] = float(sum(s["seconds"] for s in timing["segments"]))
  _write_json(os.path.join(run_dir, TIMING_FILE), timing)
  return timing


def checkpoint_step(run_dir: str, which: str = "latest") -> int:
  """The step of DIR/checkpoints/<which> ("latest" or "best"), the newest when it keeps several
  (orbax names step folders by number; 0 when none)."""
  folder = os.path.join(run_dir, "checkpoints", which)
  steps = [int(n) for n in os.listdir(folder) if n.isdigit()] if os.path.isdir(folder) else []
  return max(steps, default=0)


def read_log(run_dir: str) -> tuple[list[dict], list[dict]]:
  """(train records, validation records) of DIR/metrics.jsonl (empty when absent)."""
  train, val = [], []
  path = os.path.join(run_dir, "metrics.jsonl")
  if os.path.exists(path):
    with open(path) as f:
      for line in f:
        if line.strip():
          row = json.loads(line)
          (val if row.get("kind") == "val" else train).append(row)
  return train, val


def collapse_record(val_records: Sequence[dict], settled_step: int) -> dict:
  """The collapse fields of a row from the last validation record (module docstring)."""
  if not val_records:
    return dict(collapsed=math.nan, collapse_step=math.nan, probe_active_slots=math.nan,
                probe_largest_share=math.nan)
  last = max(val_records, key=lambda r: r["step"])
  flag = float(last.get("collapsed", math.nan))
  if last["step"] < settled_step and flag == 1.0:
    flag = 0.0  # diffuse segmentations are expected while masking and slot noise anneal
  return dict(collapsed=flag, collapse_step=int(last["step"]),
              probe_active_slots=float(last.get("probe_active_slots", math.nan)),
              probe_largest_share=float(last.get("probe_largest_share", math.nan)))


def median_step_seconds(train_records: Sequence[dict]) -> float:
  rates = [r["steps_per_sec"] for r in train_records if r.get("steps_per_sec", 0) > 0]
  return 1.0 / statistics.median(rates) if rates else math.nan


# ---------------------------------------------------------------------------------------------
# CSV


def upsert_csv(path: str, rows: Iterable[dict], *, key: str = "run_id") -> None:
  """Writes `rows` into the CSV at `path`, replacing rows with the same `key` and keeping the
  others; temp file + os.replace, so the CSV on disk is always whole."""
  existing = read_csv(path) if os.path.exists(path) else []
  new = list(rows)
  replaced = {r[key] for r in new}
  merged = [r for r in existing if r.get(key) not in replaced] + new
  columns = list(CSV_COLUMNS) + sorted({k for r in merged for k in r} - set(CSV_COLUMNS))
  buf = io.StringIO()
  writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
  writer.writeheader()
  for r in merged:
    writer.writerow({k: _csv_value(r.get(k, "")) for k in columns})
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  tmp = path + ".tmp"
  with open(tmp, "w", newline="") as f:
    f.write(buf.getvalue())
  os.replace(tmp, path)


def _csv_value(v):
  if isinstance(v, float):
    return repr(v)
  if isinstance(v, (dict, list, tuple)):
    return json.dumps(v, sort_keys=True)
  return v


def read_csv(path: str) -> list[dict]:
  """Rows of a study CSV with numbers parsed back (empty cells stay '')."""
  def parse(v: str):
    try:
      return int(v)
    except ValueError:
      pass
    try:
      return float(v)
    except ValueError:
      return v
  with open(path, newline="") as f:
    return [{k: parse(v) for k, v in row.items()} for row in csv.DictReader(f)]


# ---------------------------------------------------------------------------------------------
# Running


def execute(run: Run, *, root: str = DEFAULT_ROOT, study: str = "", eval_split: str = "test",
            eval_scenes: Optional[int] = 20, csv_path: Optional[str] = None,
            scale_schedules: bool = True, num_validations: int = 2,
            checkpoint: str = "latest", progress: bool = True) -> dict:
  """Trains (or resumes) and evaluates `run` unless its result exists; returns its row.

  The row is also written to DIR/study_result_<split>_<scenes>.json and, with `csv_path`, upserted
  into that CSV. `checkpoint` is evaluated ("latest": what the budget bought; "best": the best
  validation score). Raises StudyError on a bad config or override, TrainingStopped when training
  was stopped by a signal before the budget (the checkpoint is kept; run again to resume).
  """
  config = run_config(run, scale_schedules=scale_schedules, num_validations=num_validations)
  rid = run_id(run, scale_schedules=scale_schedules, num_validations=num_validations)
  run_dir = os.path.join(root, rid)
  done_path = result_path(run_dir, eval_split, eval_scenes)
  if os.path.exists(done_path):
    with open(done_path) as f:
      row = json.load(f)
    row.update(study=study or row.get("study", ""), name=run.name)
    if csv_path:
      upsert_csv(csv_path, [row])
    return row

  from slotlifter_jax import collapse  # JAX only from here on
  from slotlifter_jax import evaluate
  from slotlifter_jax import train
  from slotlifter_jax.data import embedded
  os.makedirs(run_dir, exist_ok=True)
  # Data generation is shared by every run of a data set and happens once: keep it off the clock.
  config = embedded.resolve_data(config)
  start = checkpoint_step(run_dir)
  if start < run.num_steps:
    t0 = time.perf_counter()
    try:
      train.train_and_evaluate(config, run_dir)
    except train.Interrupted as e:  # a signal: checkpointed, the study resumes from here
      raise TrainingStopped(f"{run_dir}: {e}") from e
    finally:
      add_training_segment(run_dir, seconds=time.perf_counter() - t0, from_step=start,
                           to_step=checkpoint_step(run_dir))
    if checkpoint_step(run_dir) < run.num_steps:
      raise TrainingStopped(f"{run_dir}: training stopped at step {checkpoint_step(run_dir)} of "
                            f"{run.num_steps}; run the study again to resume")

  result = evaluate.evaluate_split(config, run_dir, split=eval_split, checkpoint=checkpoint,
                                   max_scenes=eval_scenes, overwrite=True, progress=progress)
  timing = read_timing(run_dir)
  train_records, val_records = read_log(run_dir)
  row = dict(
      study=study, name=run.name, config=run.config, overrides=dict(run.overrides),
      seed=int(run.seed), num_steps=int(run.num_steps), run_id=rid, run_dir=run_dir,
      train_s=timing["train_s"], train_segments=len(timing["segments"]),
      step_s=median_step_seconds(train_records), eval_split=eval_split,
      eval_scenes=len(result.per_scene), checkpoint_step=int(result.checkpoint_step),
      render_per_view_s=result.timing["render_per_view_s"], eval_s=result.timing["total_s"])
  for k in METRIC_KEYS:
    row[k] = float(result.summary[k].mean) if k in result.summary else math.nan
  row.update(collapse_record(val_records, collapse.settled_step(config.train)))
  _write_json(done_path, row)
  if csv_path:
    upsert_csv(csv_path, [row])
  return row


def run_status(run: Run, *, root: str = DEFAULT_ROOT, eval_split: str = "test",
               eval_scenes: Optional[int] = 20, scale_schedules: bool = True,
               num_validations: int = 2) -> tuple[str, str, int]:
  """(run id, "done" | "trained" | "partial" | "new", steps already trained) without running."""
  rid = run_id(run, scale_schedules=scale_schedules, num_validations=num_validations)
  run_dir = os.path.join(root, rid)
  if os.path.exists(result_path(run_dir, eval_split, eval_scenes)):
    return rid, "done", run.num_steps
  step = checkpoint_step(run_dir)
  return rid, ("trained" if step >= run.num_steps else "partial" if step else "new"), step


def estimate_seconds(run: Run, *, steps_done: int = 0, eval_scenes: Optional[int] = 20,
                     val_scenes: Optional[int] = None, num_validations: int = 2,
                     scale_schedules: bool = True) -> float:
  """A rough wall-clock estimate for the rest of `run` on the 2-core CPU (the cost model above);
  an estimate, not a measurement."""
  config = run_config(run, scale_schedules=scale_schedules, num_validations=num_validations)
  t, r, d = config.train, config.render, config.data
  m = config.model
  decoder = m.num_blocks * (m.point_dim + m.ffn_dim) / _REF_DECODER
  step_s = _FIXED_STEP_S + (_REF_STEP_S - _FIXED_STEP_S) * decoder * (
      t.batch_scenes * t.rays_per_scene * r.num_samples) / (_REF_RAYS * _REF_SAMPLES)
  scene_s = _REF_SCENE_S * (d.image_size ** 2 * r.num_samples) / (_REF_PIXELS * _REF_SAMPLES)
  val_scenes = t.eval_scenes if val_scenes is None else val_scenes
  validations = num_validations * val_scenes * scene_s
  evaluation = (eval_scenes or d.num_test_scenes) * scene_s
  remaining = max(0, run.num_steps - steps_done)
  return remaining * step_s + (validations + _COMPILE_S if remaining else 0) + evaluation


def print_plan(runs: Sequence[Run], *, root: str, eval_split: str, eval_scenes: Optional[int],
               out=None) -> float:
  """Prints one line per run (status, run directory, estimate) and the total; returns seconds."""
  out = out or sys.stdout  # looked up per call, so a redirected stdout receives the plan
  total = 0.0
  for run in runs:
    rid, status, step = run_status(run, root=root, eval_split=eval_split, eval_scenes=eval_scenes)
    est = 0.0 if status == "done" else estimate_seconds(run, steps_done=step,
                                                        eval_scenes=eval_scenes)
    total += est
    print(f"  {run.name:<18} seed {run.seed}  {status:<8} ~{est / 60:5.1f} min  "
          f"{json.dumps(dict(run.overrides), sort_keys=True)}  {os.path.join(root, rid)}", file=out)
  print(f"{len(runs)} runs; estimated remaining time ≈ {total / 60:.0f} min on the 2-core CPU "
        f"(a rough cost model, not a measurement; data generation not included)", file=out)
  return total


def select_rows(rows: Sequence[dict], runs: Sequence[Run], **kwargs) -> list[dict]:
  """The rows of a study CSV that belong to `runs` (a CSV keeps rows of earlier settings, e.g.
  another budget, so that they are not lost; a table or figure must not mix them in)."""
  ids = {run_id(r, **kwargs) for r in runs}
  return [row for row in rows if row.get("run_id") in ids]


def execute_all(runs: Sequence[Run], **kwargs) -> list[dict]:
  """`execute` each run in order; returns their rows."""
  rows = []
  for i, run in enumerate(runs):
    print(f"[study] run {i + 1}/{len(runs)}: {run.name} seed {run.seed}", flush=True)
    rows.append(execute(run, **kwargs))
  return rows


def run_study(runs: Sequence[Run], *, study: str, root: str, eval_split: str,
              eval_scenes: Optional[int], csv_path: str, dry_run: bool,
              from_csv_only: bool) -> Optional[list[dict]]:
  """What every study script's main does with its plan: print it (`dry_run`, returns None), or
  train and evaluate what is not finished yet (unless `from_csv_only`), then return the CSV rows
  that belong to `runs`. A training run that stops (non-finite loss, signal) ends the script with
  its message; finished runs stay recorded for the next call."""
  if dry_run:
    print_plan(runs, root=root, eval_split=eval_split, eval_scenes=eval_scenes)
    return None
  if not from_csv_only:
    try:
      execute_all(runs, root=root, study=study, eval_split=eval_split, eval_scenes=eval_scenes,
                  csv_path=csv_path)
    except TrainingStopped as e:
      raise SystemExit(f"[{study}] {e}")
  return select_rows(read_csv(csv_path), runs)
