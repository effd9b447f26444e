"""Restarting a run from a new seed when validation says the attempt will not decompose.

Two triggers, both read from the validation that just ran:
- collapse (`slotlifter_jax/collapse.py`), once the masking and slot-noise schedules have settled;
- the early check at the validation of step `train.restart_check_step`, by `train.restart_signal`:
  - "labelled": the selection score (`train.select_by`) below `train.restart_min_score`. On the
    embedded clevr set the worse of validation FG-ARI and NV-ARI at step 14 000 already separates
    the seeds that end split from those that do not (slotlifter_jax/tools/early_check.py);
  - "mask_free": fewer than `train.restart_min_active_slots` slots in use on the validation views,
    a mean per-pixel slot entropy above `train.restart_max_pixel_entropy`, or slot attention's
    grouping of the source view agreeing with the rendered split less than
    `train.restart_min_attn_agreement` (`validation.mask_free_statistics`), read from the model's
    outputs alone, for sets without masks (a capture, the kitchens), which have no ARI to read.
    Slots in use alone cannot tell objects from a floor spread over several slots; the spread
    floor shares its pixels among them, which the entropy reads; a run whose slot attention has
    not begun to group what the decoder renders reads near 0 agreement
    (slotlifter_jax/mask_free.py);
  - "auto" (default): "labelled" when the validation scenes have masks, else "mask_free".
Like `select_by`, this is model selection on the validation split, never the test split, and
training still sees only the photometric loss.

An abandoned attempt is moved, never deleted, to DIR/restarted/seed_<s>/, and the next attempt
trains from seed s + SEED_STRIDE in the emptied run folder, so that the attempts of one seed
never repeat the first attempt of another (seed 1's second attempt is not seed 2's run). The run's
wall clock (`wall_s`) goes on across attempts: the time to decomposition includes the restarts.
"""

import glob
import json
import os
from typing import Optional

import ml_collections
import numpy as np
from absl import logging

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import collapse
from slotlifter_jax import mask_free
from slotlifter_jax import multihost

RESTARTED_DIR = "restarted"
_LEGACY_DIRS = ("collapsed",)  # run folders written before the score trigger existed
ATTEMPT_FILES = ("checkpoints", "metrics.jsonl", "tb", "val", "config.json", "emergence.json")
SEED_STRIDE = 1000


RESTART_SIGNALS = ("auto", "labelled", "mask_free")


def check_signal(train_config, *, has_masks: bool) -> str:
  """The early check `train.restart_signal` resolves to: "labelled" or "mask_free"."""
  signal = train_config.get("restart_signal", "auto")
  if signal == "auto":
    return "labelled" if has_masks else "mask_free"
  return signal


def reason(train_config, step: int, val: dict, *, has_masks: bool = True) -> Optional[str]:
  """Why the validation `val` of step `step` calls for a new seed, or None. `has_masks`: whether
  the validation scenes have ground-truth masks (the labelled check needs them)."""
  if val.get("collapsed") == 1.0 and step >= collapse.settled_step(train_config):
    return "collapsed"
  check = int(train_config.get("restart_check_step", 0))
  if not check or step != check:
    return None
  if check_signal(train_config, has_masks=has_masks) == "mask_free":
    why = mask_free.shortfall(
        val, min_active_slots=float(train_config.get("restart_min_active_slots", 0.0)),
        max_pixel_entropy=float(train_config.get("restart_max_pixel_entropy", 1.0)),
        min_attn_agreement=float(train_config.get("restart_min_attn_agreement", -1.0)))
    return None if why is None else f"{why} at step {check} (mask-free check)"
  floor = float(train_config.get("restart_min_score", 0.0))
  if val["score"] < floor:
    return (f"selection score ({train_config.get('select_by', 'nv_ari')}) {val['score']:.3f} "
            f"< train.restart_min_score={floor} at step {check}")
  return None


def archived_attempts(workdir: str) -> list[str]:
  """The folders of this run's abandoned attempts, oldest first."""
  found = []
  for name in (RESTARTED_DIR,) + _LEGACY_DIRS:
    found += glob.glob(os.path.join(workdir, name, "seed_*"))
  # Each attempt's seed is larger than the one before it.
  return sorted(found, key=attempt_seed)


def attempt_seed(folder: str) -> int:
  """The seed an archived attempt (DIR/restarted/seed_<seed>) trained with."""
  return int(os.path.basename(folder).removeprefix("seed_"))


def latest_archived_log(workdir: str) -> Optional[str]:
  """The metrics.jsonl of the latest abandoned attempt, or None: its last `wall_s` already counts
  the attempts before it, so the next attempt's clock goes on from there."""
  attempts = archived_attempts(workdir)
  return os.path.join(attempts[-1], "metrics.jsonl") if attempts else None


def resumed_seed(config: ml_collections.ConfigDict, saved: Optional[dict],
                 workdir: str) -> ml_collections.ConfigDict:
  """The config of the attempt to resume: after a restart the saved seed (and restarts left)
  differ from the command line's, and the run goes on with the attempt in the folder. A run
  stopped between moving an attempt away and saving the next one's config goes on with the
  next seed."""
  attempts = archived_attempts(workdir)
  if not attempts or (saved is not None and saved.get("seed") == config.seed):
    return config
  new = ml_collections.ConfigDict(config.to_dict())
  if saved is None:
    new.seed = attempt_seed(attempts[-1]) + SEED_STRIDE
    new.train.restarts = max(int(config.train.restarts) - len(attempts), 0)
  else:
    new.seed = int(saved["seed"])
    new.train.restarts = int(saved["train"].get("restarts",
                                              saved["train"].get("collapse_restarts", 0)))
  logging.info("resuming the restarted attempt with seed %d", new.seed)
  return new


def archive_and_reseed(config: ml_collections.ConfigDict, workdir: str, step: int,
                       why: str) -> ml_collections.ConfigDict:
  """Moves this attempt's files to workdir/restarted/seed_<seed>/ and saves the next attempt's
  config.json (its seed and the restarts it has left) in the emptied folder; returns that config.

  The next attempt must find its config saved: with none, `resumed_seed` rebuilds it from the
  command line's count of restarts less the archived attempts, and the config passed on here
  already counts this restart, so the run would lose one.
  """
  archive = os.path.join(workdir, RESTARTED_DIR, f"seed_{config.seed}")
  new = ml_collections.ConfigDict(config.to_dict())
  new.seed = int(config.seed) + SEED_STRIDE
  new.train.restarts = int(config.train.restarts) - 1
  if multihost.is_primary():
    os.makedirs(archive, exist_ok=False)
    for name in ATTEMPT_FILES:
      if os.path.exists(os.path.join(workdir, name)):
        os.replace(os.path.join(workdir, name), os.path.join(archive, name))
    with open(os.path.join(archive, "restart.json"), "w") as f:
      json.dump(dict(seed=int(config.seed), step=int(step), reason=why), f)
    ckpt_lib.save_config(new, workdir)
  multihost.barrier("restart")  # the next attempt starts from a folder holding only its config
  logging.warning("step %d: %s; moved the attempt to %s and restarting from seed %d (%d restarts "
                  "left)", step, why, archive, new.seed, new.train.restarts)
  return new
