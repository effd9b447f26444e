"""Study rows for runs trained outside the study runner, with `python -m slotlifter_jax.main`.

A user who trained seeds of one config with the entry point (one `--workdir` per seed) should not
have to train them again to get the seed-stability table; `stability.py --workdirs=A,B,...` reads
them through `workdir_row`. What the runner guarantees by construction (one config, one budget,
one evaluation protocol) is checked here instead, and a run that fails a check stops the study
with one line naming its directory and the problem:
  - its DIR/config.json equals the named config (`configs/<file>.py[:variant]`) except for the
    seed and the fields that cannot change the trained parameters (NOT_TRAINING: how often it
    validated, logged or checkpointed, and how it picked its best checkpoint); a field the saved
    config lacks was added to the code later and reads as its default, as on resume; the
    moving average of the parameters (AVERAGE, `train.ema_decay`) never changes what trains, so
    a run is evaluated with the parameters it kept, whatever the named config says, and its row
    records which (`parameters`: "average" or "trained"); the
    embedded data set may lie under another cache root ($SLOTLIFTER_DATA_CACHE) when its folder
    name, which holds every generator argument, is the same;
  - a run that restarted (`train.restarts`, slotlifter_jax/restarts.py) saved its last attempt's
    seed and the restarts it had left: each attempt archived under DIR/restarted/ spent one, so
    the named config's count less the archived attempts must equal the saved one. Its row keeps
    the command's seed (`command_seed`, the first attempt's), the seed whose parameters it
    evaluates (`seed`) and the number of attempts, so a restarted seed is counted once and seen;
  - its last checkpoint is the config's full budget (`train.num_steps`);
  - its evaluation is of the requested checkpoint (the last one, or with checkpoint="best" the
    best by validation, which `python -m slotlifter_jax.main --mode=eval` evaluates by default)
    on the requested number of scenes: an existing DIR/eval/<split>/metrics.json is reused when
    it is, refused (never overwritten) when it is not, and written by `evaluate_split` when
    there is none. Best and last rows of one run have distinct run ids (`workdir_id`).
The row has the runner's columns (study_common.CSV_COLUMNS). `train_s` is the run's own clock
(`wall_s` of its last log record: seconds of training summed over resumed invocations, with its
validations); `train_segments` is unknown and left empty.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from typing import Optional

from experiments import study_common as sc

# Fields that decide when the loop looks at the model, never what it trains.
NOT_TRAINING = ("seed", "train.eval_every", "train.eval_scenes", "train.log_every",
                "train.checkpoint_every", "train.select_by")
# Fields that decide which parameters are evaluated (slotlifter_jax/averaging.py), never what
# trains; a run is read with its own values of them.
AVERAGE = ("train.ema_decay", "train.ema_start_step")


def training_differences(saved: dict, config) -> dict:
  """{field: [saved, named]} for the fields, other than NOT_TRAINING, in which the run's saved
  config differs from `config`; a field the saved config lacks reads as base_config's value."""
  from slotlifter_jax import checkpoints
  return {field: values for field, values in checkpoints.config_changes(saved, config).items()
          if field not in NOT_TRAINING}


def workdir_id(run_dir: str, checkpoint: str = "latest") -> str:
  """The row's key: the directory's name and a hash of its absolute path (two runs named
  `seed0` in different folders stay two rows), marked when the row evaluates the best
  checkpoint (so one CSV keeps a run's best and last rows)."""
  path = os.path.abspath(run_dir)
  mark = "" if checkpoint == "latest" else f"-{checkpoint}"
  return f"{os.path.basename(path)}-{hashlib.sha1(path.encode()).hexdigest()[:6]}{mark}"


def check_workdir(run_dir: str, config_spec: str):
  """The run's config (the named one with its seed and resolved data), after the checks of the
  module docstring that need no evaluation; raises StudyError naming the problem."""
  from slotlifter_jax import checkpoints
  if not os.path.isdir(run_dir):
    raise sc.StudyError(f"--workdirs: {run_dir} is not a directory")
  saved = checkpoints.load_saved_config(run_dir)
  if saved is None:
    raise sc.StudyError(f"{run_dir}: no config.json; not a training run directory")
  config = sc.load_config(config_spec)
  config.seed = int(saved.get("seed", 0))
  attempts, _ = attempts_and_command_seed(run_dir, config.seed)
  config.train.restarts = int(config.train.restarts) - (attempts - 1)  # one spent per restart
  config = _embedded_root_as_saved(config, saved)
  config = _average_as_saved(config, saved)
  diffs = training_differences(saved, config)
  if diffs:
    field, (a, b) = next(iter(diffs.items()))
    more = f" (and {len(diffs) - 1} more)" if len(diffs) > 1 else ""
    raise sc.StudyError(f"{run_dir}: trained with {field}={a!r}, but {config_spec} has {b!r}"
                        f"{more}; only {', '.join(NOT_TRAINING)} may differ")
  step = sc.checkpoint_step(run_dir)
  if step != int(config.train.num_steps):
    raise sc.StudyError(f"{run_dir}: last checkpoint is step {step}, not the budget "
                        f"{config.train.num_steps}; finish training with the same command first")
  return config


def _embedded_root_as_saved(config, saved: dict):
  """`config` with the embedded set's root filled in, as the run saved it when the run trained
  on the same set. The set's folder name holds every generator argument (data/embedded.py), so a
  run that generated it under another cache root ($SLOTLIFTER_DATA_CACHE) trained on the same
  data; a run on another set keeps this cache's path, and the check names the difference. Nothing
  is generated here."""
  from slotlifter_jax.data import embedded
  if config.data.root:
    return config
  mine = embedded.dataset_dir(config.data, seed=config.data.get("seed", 0))
  theirs = str(saved.get("data", {}).get("root") or "")
  with config.unlocked():
    config.data.root = theirs if os.path.basename(theirs) == os.path.basename(mine) else mine
  return config


def _average_as_saved(config, saved: dict):
  """`config` with the run's own moving-average settings (AVERAGE): a checkpoint holds the
  average only when its run kept one, so it restores only with the run's setting."""
  from slotlifter_jax import checkpoints
  saved = checkpoints.with_base_defaults(saved)
  with config.unlocked():
    for field in AVERAGE:
      section, key = field.split(".")
      config[section][key] = saved[section][key]
  return config


def _evaluation(config, run_dir: str, *, split: str, eval_scenes: Optional[int],
                progress: bool, checkpoint: str = "latest") -> dict:
  from slotlifter_jax import evaluate
  path = os.path.join(run_dir, "eval", split, "metrics.json")
  # The best and the last checkpoint at one step hold one state (both managers save the step's
  # train state), so the step alone tells which checkpoint an evaluation read.
  step = sc.checkpoint_step(run_dir, checkpoint)
  if not step:
    raise sc.StudyError(f"{run_dir}: no {checkpoint} checkpoint")
  if not os.path.exists(path):
    evaluate.evaluate_split(config, run_dir, split=split, checkpoint=checkpoint,
                            max_scenes=eval_scenes, progress=progress)
  with open(path) as f:
    result = json.load(f)
  want = eval_scenes or result["num_scenes"]
  got = (int(result["checkpoint"]["step"]), int(result["num_scenes"]))
  if got != (step, want):
    which = "last" if checkpoint == "latest" else checkpoint
    raise sc.StudyError(f"{path}: evaluates step {got[0]} on {got[1]} scenes, not the {which} "
                        f"checkpoint {step} on {want}; move it aside to evaluate again")
  return result


def attempts_and_command_seed(run_dir: str, seed: int) -> tuple[int, int]:
  """(attempts, the seed the command named) of a run whose last attempt trained `seed`."""
  from slotlifter_jax import restarts
  archived = restarts.archived_attempts(run_dir)
  return 1 + len(archived), (restarts.attempt_seed(archived[0]) if archived else seed)


def workdir_row(run_dir: str, config, *, config_spec: str, study: str, name: str,
                eval_split: str, eval_scenes: Optional[int], progress: bool = True,
                checkpoint: str = "latest") -> dict:
  """One study row (study_common.CSV_COLUMNS, and `attempts`, `command_seed`) for a finished run
  trained by the entry point; `config` is what `check_workdir(run_dir, config_spec)` returned."""
  from slotlifter_jax import collapse
  if checkpoint not in ("latest", "best"):
    raise sc.StudyError(f"checkpoint={checkpoint!r}: use latest or best")
  result = _evaluation(config, run_dir, split=eval_split, eval_scenes=eval_scenes,
                       progress=progress, checkpoint=checkpoint)
  train_records, val_records = sc.read_log(run_dir)
  clock = [float(r["wall_s"]) for r in train_records + val_records if "wall_s" in r]
  row = dict(
      study=study, name=name, config=config_spec, overrides={}, seed=int(config.seed),
      num_steps=int(config.train.num_steps), run_id=workdir_id(run_dir, checkpoint),
      run_dir=os.path.abspath(run_dir), train_s=max(clock, default=math.nan),
      train_segments=math.nan, step_s=sc.median_step_seconds(train_records),
      eval_split=eval_split, eval_scenes=int(result["num_scenes"]),
      checkpoint_step=int(result["checkpoint"]["step"]),
      render_per_view_s=float(result["timing"]["render_per_view_s"]),
      eval_s=float(result["timing"]["total_s"]))
  # An evaluation written before the field existed used the trained parameters.
  row["parameters"] = result.get("parameters", "trained")
  row["attempts"], row["command_seed"] = attempts_and_command_seed(run_dir, int(config.seed))
  for k in sc.METRIC_KEYS:
    value = result["metrics"].get(k, {}).get("mean")
    row[k] = math.nan if value is None else float(value)
  # The collapse flag of the validation that chose (best) or followed (latest) the checkpoint.
  upto = [r for r in val_records if int(r["step"]) <= row["checkpoint_step"]]
  row.update(sc.collapse_record(upto, collapse.settled_step(config.train)))
  return row


def workdir_rows(run_dirs, **kwargs) -> list[dict]:
  """`workdir_row` for each directory; every directory is checked before any is evaluated, and
  two runs of one command seed are refused (they would count one seed twice)."""
  configs, seen = [], {}
  for d in run_dirs:
    config = check_workdir(d, kwargs["config_spec"])
    _, seed = attempts_and_command_seed(d, int(config.seed))
    if seed in seen:
      raise sc.StudyError(f"--workdirs: {seen[seed]} and {d} are both seed {seed}")
    seen[seed] = d
    configs.append(config)
  return [workdir_row(d, config, **kwargs) for d, config in zip(run_dirs, configs)]
