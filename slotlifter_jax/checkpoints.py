"""Checkpoints of a run's work directory, the config saved beside them, and the choice and restore
of a trained run's parameters for --mode=eval and --mode=render (`restore_params`).

Layout of a work directory:
  DIR/config.json            the config the run was started with (compared on resume and eval)
  DIR/checkpoints/latest/N   the last few train states (orbax, written atomically)
  DIR/checkpoints/best/N     the best state by validation score (train.select_by; PSNR without masks)
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

import jax
import ml_collections
from absl import logging
import orbax.checkpoint as ocp
from etils import epath

from slotlifter_jax import averaging
from slotlifter_jax import schedules
from slotlifter_jax import train_step as step_lib
from slotlifter_jax.data.types import Scene

# Fields whose change makes a checkpoint unusable: the parameter shapes depend on them.
ARCHITECTURE_FIELDS = ("model",)
# ...except these. The computation precision leaves parameters, gradients and optimiser state
# float32 with the same shapes (model.py, "Numerics"), so a run trained in float32 can be evaluated,
# resumed or rendered in bfloat16 and back. Every slot attention iteration applies the same
# parameters, so a run can be evaluated with more iterations than it was trained with (Locatello
# et al. 2020 test with more); the folded products compute the same function from the same
# parameters. Evaluation records any of these changes (evaluate.differences_from_training).
NOT_ARCHITECTURE = ("model.dtype", "model.slot_iters", "model.fold_products")
# ...and these fields of other sections, because the weights are tied to them: a model trained with
# positions in the source view's azimuth frame renders another frame's positions wrongly.
ALSO_ARCHITECTURE = ("data.frame",)
# Probe switches retired from the code, with the value that meant "off" (None: the field only
# qualified a switch of this table, so any value is off). A saved run with every one of them off
# trained what today's code trains and is read without them; a run that had one on is refused.
# What they showed: experiments/journal/2026-12.md, "Retired switches".
RETIRED = {"model.slot_position_embedding": False, "model.locality_floor": False,
           "model.locality_floor_z": None, "model.locality_attention": False,
           "train.locality_attention_start": None, "train.slot_attention_lr_scale_steps": 0}


class CheckpointMismatchError(ValueError):
  """A checkpoint or saved config does not fit the requested config."""


class EvalSetupError(ValueError):
  """A bad request to the evaluation (unknown split, checkpoint or scene index).

  Defined here, beside the checkpoint choice that raises it, so that this module need not import
  evaluate; evaluate imports it, and the command line catches it as evaluate.EvalSetupError.
  """


def _processes(name: str) -> ocp.options.MultiprocessingOptions:
  """Each manager's own barrier names: with several processes, orbax synchronises a save through
  barriers named after the step alone, so the latest and best managers saving the same step at
  once collide ("Barrier _async_write_complete.3 is already ongoing") and the save never ends."""
  return ocp.options.MultiprocessingOptions(barrier_sync_key_prefix=name)


class Checkpoints:
  """The latest and best managers. Every process of a multi-process run makes the same calls (orbax
  synchronises them, creates the folders and writes each file once, from process 0 or from the
  process that holds a shard)."""

  def __init__(self, workdir: str, *, keep: int = 3):
    root = os.path.abspath(os.path.join(workdir, "checkpoints"))
    self.latest = ocp.CheckpointManager(
        os.path.join(root, "latest"),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True,
                                             multiprocessing_options=_processes("latest")))
    self.best = ocp.CheckpointManager(
        os.path.join(root, "best"),
        options=ocp.CheckpointManagerOptions(
            max_to_keep=1, best_fn=lambda m: m["score"], best_mode="max", create=True,
            multiprocessing_options=_processes("best")))

  def latest_step(self) -> int | None:
    return self.latest.latest_step()

  def save(self, state, *, force: bool = False) -> None:
    step = int(jax.device_get(state.step))
    if step in self.latest.all_steps():
      return
    self.latest.save(step, args=ocp.args.StandardSave(state), force=force)

  def save_best(self, state, score: float) -> None:
    step = int(jax.device_get(state.step))
    if step in self.best.all_steps():
      return
    self.best.save(step, args=ocp.args.StandardSave(state), metrics={"score": float(score)},
                   force=True)

  def restore(self, abstract_state, *, step: int | None = None, which: str = "latest"):
    manager = self.latest if which == "latest" else self.best
    step = manager.latest_step() if step is None and which == "latest" else step
    if step is None and which == "best":
      step = manager.best_step()
    if step is None:
      raise FileNotFoundError(f"no {which} checkpoint under {manager.directory}")
    try:
      return manager.restore(step, args=ocp.args.StandardRestore(abstract_state))
    except (ValueError, KeyError, TypeError) as e:
      raise CheckpointMismatchError(
          f"checkpoint {manager.directory}/{step} does not match the model built from the config "
          f"(different K, feature width or layout?): {e}") from e

  def wait(self) -> None:
    self.latest.wait_until_finished()
    self.best.wait_until_finished()

  def close(self) -> None:
    self.latest.close()
    self.best.close()


def latest_step_on_disk(workdir: str) -> int:
  """The step a resume starts from (0 for a new run), read from the `Checkpoints` layout without
  opening a manager, which would create the folders."""
  latest = os.path.join(workdir, "checkpoints", "latest")
  steps = [int(s) for s in os.listdir(latest) if s.isdigit()] if os.path.isdir(latest) else []
  return max(steps, default=0)


def config_path(workdir: str) -> str:
  return os.path.join(workdir, "config.json")


def config_history_path(workdir: str) -> str:
  return os.path.join(workdir, "config_history.jsonl")


def config_changes(saved: dict, config: ml_collections.ConfigDict) -> dict:
  """{'section.field': [saved, requested]} for every field whose value differs.

  A field the saved config lacks reads as its default (`with_base_defaults`), so it is no change
  (a `[None, default]` entry would claim one).
  """
  saved = with_base_defaults(saved)
  current = json.loads(config.to_json_best_effort())
  changes = {}
  def walk(a: dict, b: dict, prefix: str):
    for k in sorted(set(a) | set(b)):
      x, y = a.get(k), b.get(k)
      if isinstance(x, dict) and isinstance(y, dict):
        walk(x, y, f"{prefix}{k}.")
      elif _normalise(x) != _normalise(y):
        changes[prefix + k] = [x, y]
  walk(saved, current, "")
  return changes


def save_config(config: ml_collections.ConfigDict, workdir: str, *, step: int = 0) -> None:
  """Writes DIR/config.json atomically (temp file + rename).

  A resume with other (non-architecture) values first appends them to DIR/config_history.jsonl,
  `{"step", "time", "changes": {field: [before, after]}}`, so the record of how the run was
  trained up to `step` is never lost by overwriting config.json.
  """
  saved = load_saved_config(workdir)
  changes = config_changes(saved, config) if saved is not None else {}
  if changes:
    with open(config_history_path(workdir), "a") as f:
      f.write(json.dumps({"step": int(step), "time": time.time(), "changes": changes}) + "\n")
    logging.warning("%s: resuming at step %d with changed fields (kept in %s): %s", workdir,
                    step, os.path.basename(config_history_path(workdir)),
                    "; ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in changes.items()))
  os.makedirs(workdir, exist_ok=True)
  path = config_path(workdir)
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    f.write(config.to_json_best_effort(indent=2, sort_keys=True))
  os.replace(tmp, path)


def load_saved_config(workdir: str) -> dict | None:
  path = config_path(workdir)
  if not os.path.exists(path):
    return None
  try:
    with open(path) as f:
      return json.load(f)
  except json.JSONDecodeError as e:
    raise CheckpointMismatchError(f"{path}: not valid JSON ({e})") from e


def check_compatible(config: ml_collections.ConfigDict, saved: dict | None, where: str) -> None:
  """Raises when the architecture fields of `config` differ from the saved ones, naming them.

  A field the saved config lacks was added to the code after that run was made; new fields
  default to the behaviour from before they existed (e.g. model.feature_lifting), so the saved run
  is read as having `defaults.base_config()`'s value for it.
  """
  if saved is None:
    return
  try:
    saved = with_base_defaults(saved)
  except CheckpointMismatchError as e:
    raise CheckpointMismatchError(f"{where}: {e}") from None
  current = with_base_defaults(json.loads(config.to_json_best_effort()))
  fields = sorted({f"{section}.{k}" for section in ARCHITECTURE_FIELDS
                   for cfg in (saved, current) for k in cfg.get(section, {})}
                  - set(NOT_ARCHITECTURE))
  fields += [f for f in ALSO_ARCHITECTURE if f not in fields]
  diffs = []
  for field in fields:
    section, key = field.split(".")
    a, b = saved.get(section, {}).get(key), current.get(section, {}).get(key)
    if _normalise(a) != _normalise(b):
      diffs.append(f"{field}: saved {a!r}, requested {b!r}")
  # The optimiser state holds the parameters' average only when it is on (averaging.py).
  a, b = saved.get("train", {}), current.get("train", {})
  if averaging.enabled(a) != averaging.enabled(b):
    diffs.append(f"train.ema_decay: saved {a.get('ema_decay')!r}, requested "
                 f"{b.get('ema_decay')!r} (the average is on in one and off in the other)")
  # Slot attention has an optimiser group of its own only at a scale other than 1 (train_step.py).
  saved_group = schedules.has_slot_attention_group(a)
  if saved_group != schedules.has_slot_attention_group(b):
    why = ("the checkpoint holds slot attention's own optimiser group, which a scale of 1 drops; "
           "a scale near 1 such as 1.0001 keeps it" if saved_group else
           "the checkpoint has no optimiser group of slot attention's own, which a scale other "
           "than 1 needs")
    diffs.append(f"train.slot_attention_lr_scale: saved {a.get('slot_attention_lr_scale')!r}, "
                 f"requested {b.get('slot_attention_lr_scale')!r} ({why})")
  if diffs:
    raise CheckpointMismatchError(
        f"{where}: the run in this directory was made with another model config:\n  "
        + "\n  ".join(diffs))


def without_retired(cfg: dict) -> dict:
  """`cfg` (a config as JSON) without the `RETIRED` fields; raises CheckpointMismatchError, naming
  the field, when one of them was on."""
  out = {}
  for section, values in cfg.items():
    if not isinstance(values, dict):
      out[section] = values
      continue
    kept = {}
    for key, value in values.items():
      field = f"{section}.{key}"
      if field not in RETIRED:
        kept[key] = value
      elif RETIRED[field] is not None and _normalise(value) != RETIRED[field]:
        raise CheckpointMismatchError(
            f"the run was made with {field}={value!r}, a switch retired from the code "
            f"(experiments/journal/2026-12.md, \"Retired switches\"); evaluate or resume it with "
            f"a commit from before its retirement")
    out[section] = kept
  return out


def with_base_defaults(cfg: dict) -> dict:
  """`cfg` (a config as JSON) with every field it lacks set to `defaults.base_config()`'s value:
  a run saved before a field was added trained with the behaviour the field defaults to. Retired
  switches are dropped (`without_retired`), or refused when they were on."""
  from slotlifter_jax import defaults
  cfg = without_retired(cfg)
  base = json.loads(defaults.base_config().to_json_best_effort())
  return {k: dict(base[k], **v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
          for k, v in dict(base, **cfg).items()}


def _normalise(v: Any):
  return list(v) if isinstance(v, tuple) else v


# ---------------------------------------------------------------------------------------------
# Restoring a trained run's parameters (evaluation and render modes)
# ---------------------------------------------------------------------------------------------


def abstract_state(model, config, scene: Scene) -> step_lib.TrainState:
  """The train state's shapes and dtypes (nothing computed), placed on the first device."""
  device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  return step_lib.state_shapes(model, config, step_lib.init_batch(scene), sharding=device)


def _choose_checkpoint(manager: Checkpoints, checkpoint: str) -> tuple[str, int]:
  """('best' | 'latest', step) for --checkpoint = '' (best if any, else latest) | best | latest |
  <step>."""
  latest, best = manager.latest.all_steps(), manager.best.all_steps()
  if not latest and not best:
    raise FileNotFoundError(f"{manager.latest.directory}: no checkpoint; train this run first")
  if checkpoint in ("", "best") and best:
    return "best", int(manager.best.best_step())
  if checkpoint == "best":
    raise EvalSetupError(f"{manager.best.directory}: no best checkpoint (the run never "
                         f"validated); use --checkpoint=latest")
  if checkpoint in ("", "latest"):
    if not latest:
      raise EvalSetupError(f"{manager.latest.directory}: no latest checkpoint; use "
                           f"--checkpoint=best")
    return "latest", int(manager.latest.latest_step())
  if not checkpoint.isdigit():
    raise EvalSetupError(f"--checkpoint={checkpoint!r}: use best, latest or a step number")
  step = int(checkpoint)
  if step in latest:
    return "latest", step
  if step in best:
    return "best", step
  raise EvalSetupError(f"--checkpoint={step}: no such step; saved steps: latest "
                       f"{sorted(latest)}, best {sorted(best)}")


def _open_trained(workdir: str) -> tuple[str, Checkpoints]:
  """(the checkpoints folder, its managers) of a trained run; FileNotFoundError, and nothing
  created, when the run has no checkpoints folder."""
  root = os.path.join(os.path.abspath(workdir), "checkpoints")  # orbax refuses relative paths
  if not os.path.isdir(root):
    raise FileNotFoundError(f"{root}: no checkpoints; train this run first (--mode=train)")
  return root, Checkpoints(workdir)


def locate_checkpoint(workdir: str, checkpoint: str = "latest") -> tuple[str, int, int | None]:
  """(the step folder of the run's checkpoint `checkpoint`, its step, the step of the run's best
  checkpoint or None), `checkpoint` as in `_choose_checkpoint`. Reads only the folder names and
  the best checkpoints' recorded scores; creates nothing."""
  root, manager = _open_trained(workdir)
  try:
    which, step = _choose_checkpoint(manager, checkpoint)
    best = manager.best.best_step() if manager.best.all_steps() else None
  finally:
    manager.close()
  return os.path.join(root, which, str(step)), step, (None if best is None else int(best))


def read_saved_state(workdir: str, checkpoint: str = "latest") -> tuple[dict, str]:
  """(the train state of the run's checkpoint `checkpoint` as saved: a nested dict of arrays on
  the first device; its step directory), `checkpoint` as in `_choose_checkpoint`.

  Shapes and dtypes come from the checkpoint's own metadata, so no config, model or data is
  needed: experiments/compare_checkpoints.py compares two runs' states with it."""
  step_dir, _, _ = locate_checkpoint(workdir, checkpoint)
  item = epath.Path(step_dir) / "default"
  device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  handler = ocp.StandardCheckpointHandler()
  try:
    abstract = jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device),
                            handler.metadata(item), is_leaf=lambda x: hasattr(x, "shape"))
    state = handler.restore(item, args=ocp.args.StandardRestore(abstract))
  finally:
    handler.close()
  return state, step_dir


def _parameter_differences(abstract_params, step_dir: str, *, limit: int = 8) -> list[str]:
  """'path: checkpoint shape, model shape' for every parameter whose shape differs, read from the
  checkpoint's metadata (nothing is restored)."""
  handler = ocp.StandardCheckpointHandler()
  try:
    saved = handler.metadata(epath.Path(step_dir) / "default")["params"]
  finally:
    handler.close()
  def shapes(tree):
    return {jax.tree_util.keystr(p): tuple(x.shape) for p, x in
            jax.tree_util.tree_flatten_with_path(tree, is_leaf=lambda x: hasattr(x, "shape"))[0]}
  a, b = shapes(saved), shapes(abstract_params)
  out = [f"params{k}: checkpoint {a.get(k, 'absent')}, model {b.get(k, 'absent')}"
         for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
  return out[:limit] + ([f"... and {len(out) - limit} more"] if len(out) > limit else [])


def restore_params(model, config, workdir: str, *, scene: Scene, checkpoint: str = "",
                   params: str = "average") -> tuple[dict, str, int, str]:
  """(params, which params, step, step directory) of the run's checkpoint `checkpoint` (see
  `_choose_checkpoint`); `params` chooses between a run's average of the parameters and its
  trained ones, and "which params" says which they are (`averaging.chosen_params`).

  Raises CheckpointMismatchError naming the parameters whose shapes differ when the checkpoint
  does not fit the model built from `config`. The shapes are compared on the checkpoint's
  metadata first, so a mismatch never starts (and abandons) orbax's array reads.
  """
  root, manager = _open_trained(workdir)
  try:
    which, step = _choose_checkpoint(manager, checkpoint)
    step_dir = os.path.join(root, which, str(step))
    abstract = abstract_state(model, config, scene)
    diffs = _parameter_differences(abstract.params, step_dir)
    if diffs:
      raise CheckpointMismatchError(
          f"{step_dir}: the checkpoint does not fit the model built from the config (other K, "
          f"feature width or layout?)" + "".join(f"\n  {d}" for d in diffs))
    state = manager.restore(abstract, step=step, which=which)
  finally:
    manager.close()
  restored, used = averaging.chosen_params(state, config.train, params)
  return restored, used, step, step_dir
