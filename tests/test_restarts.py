"""Restarts: an attempt that collapses or fails the check is archived and the run goes on from a
new seed; the selection score; the bookkeeping of seeds and restarts left across resumes."""

import json
import os

import pytest

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import collapse
from slotlifter_jax import config_checks
from slotlifter_jax import restarts
from slotlifter_jax import train
from slotlifter_jax import validation
from train_helpers import final_params, load_config


@pytest.mark.slow
@pytest.mark.parametrize("trigger", ["collapsed", "score"])
def test_abandoned_attempt_is_kept_and_the_run_restarts_from_a_new_seed(trigger, tmp_path,
                                                                        monkeypatch):
  config = load_config()
  config.train.restarts = 2
  if trigger == "score":
    config.train.restart_check_step = config.train.eval_every
    config.train.restart_min_score = 0.5
  real_run = validation.Validator.run
  calls = {"n": 0}
  def run_failing_the_first_validation(self, params, step):
    result = real_run(self, params, step)
    calls["n"] += 1
    first = calls["n"] == 1  # the first validation of seed 0
    result["collapsed"] = 1.0 if first and trigger == "collapsed" else 0.0
    result["score"] = 0.4 if first else 0.9  # below, then above, restart_min_score
    return result
  monkeypatch.setattr(validation.Validator, "run", run_failing_the_first_validation)
  workdir = str(tmp_path / "run")
  assert collapse.settled_step(config.train) <= config.train.eval_every  # the first flag counts
  train.train_and_evaluate(config, workdir)

  archive = os.path.join(workdir, restarts.RESTARTED_DIR, "seed_0")
  with open(os.path.join(archive, "metrics.jsonl")) as f:
    first = [json.loads(line) for line in f]
  assert max(r["step"] for r in first) == config.train.eval_every  # stopped at that validation
  assert os.path.isdir(os.path.join(archive, "checkpoints"))  # nothing was deleted
  with open(os.path.join(archive, "restart.json")) as f:
    why = json.load(f)
  assert why["seed"] == 0 and why["step"] == config.train.eval_every
  assert why["reason"].startswith("collapsed" if trigger == "collapsed" else "selection score")
  with open(os.path.join(workdir, "config.json")) as f:
    saved = json.load(f)
  # Not seed 1: a seed's second attempt must not be another seed's first. One restart of two
  # is spent, so one is left.
  assert saved["seed"] == restarts.SEED_STRIDE and saved["train"]["restarts"] == 1
  assert final_params(workdir, config)[0] == config.train.num_steps
  # The clock goes on across the restart: the run's wall time includes the abandoned attempt.
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    second = [json.loads(line) for line in f]
  assert min(r["wall_s"] for r in second) > max(r["wall_s"] for r in first)
  # The same command again resumes the new attempt (already finished) instead of starting over.
  train.train_and_evaluate(config, workdir)
  assert sorted(os.listdir(os.path.join(workdir, restarts.RESTARTED_DIR))) == ["seed_0"]


def test_restart_reasons_and_config_checks():
  config = load_config()
  t = config.train
  t.restart_check_step, t.restart_min_score = 2 * t.eval_every, 0.55
  settled = collapse.settled_step(t)
  ok = dict(collapsed=0.0, score=0.60)
  assert restarts.reason(t, t.restart_check_step, ok) is None
  assert restarts.reason(t, t.restart_check_step, dict(ok, score=0.55)) is None  # not below
  assert "0.540" in restarts.reason(t, t.restart_check_step, dict(ok, score=0.54))
  assert restarts.reason(t, t.eval_every, dict(ok, score=0.0)) is None  # only at the check step
  assert restarts.reason(t, settled, dict(ok, collapsed=1.0)) == "collapsed"
  if settled > 0:
    assert restarts.reason(t, settled - 1, dict(ok, collapsed=1.0)) is None
  assert config_checks.restarts_problem(t) is None
  t.restart_check_step = t.eval_every + 1
  assert "train.restart_check_step" in config_checks.restarts_problem(t)
  t.restart_check_step, t.restarts = 0, -1
  assert "train.restarts=-1 must be ≥ 0" in config_checks.restarts_problem(t)


@pytest.mark.parametrize("select_by, has_masks, expected", [
    ("nv_ari", True, 0.84),
    ("min_fg_nv", True, 0.61),  # the objects merged while the scene split improved: FG-ARI rules
    ("psnr_novel", True, 26.0),
    ("min_fg_nv", False, 26.0),  # no masks, no ARI: novel-view PSNR whatever was asked
])
def test_selection_score(select_by, has_masks, expected):
  result = {"fg_ari": 0.61, "nv_ari": 0.84, "psnr_novel": 26.0}
  assert validation.selection_score(result, select_by, has_masks=has_masks) == pytest.approx(
      expected)


def test_selection_score_without_a_foreground_ranks_last():
  # FG-ARI is NaN when no validation view shows an object; min() must not drop it silently.
  result = {"fg_ari": float("nan"), "nv_ari": 0.9, "psnr_novel": 30.0}
  assert validation.selection_score(result, "min_fg_nv", has_masks=True) == -1.0
  assert validation.selection_score(result, "nv_ari", has_masks=True) == pytest.approx(0.9)


def test_each_restart_spends_one_of_the_restarts(tmp_path):
  # The loop hands the next attempt the config archive_and_reseed returns; train_and_evaluate
  # then passes it through resumed_seed with whatever config.json the folder holds.
  config = load_config()
  config.train.restarts = 2
  workdir = str(tmp_path / "run")
  ckpt_lib.save_config(config, workdir)
  attempt = config
  for seed, left in ((restarts.SEED_STRIDE, 1), (2 * restarts.SEED_STRIDE, 0)):
    nxt = restarts.archive_and_reseed(attempt, workdir, 14_000, "test")
    assert (nxt.seed, nxt.train.restarts) == (seed, left)
    attempt = restarts.resumed_seed(nxt, ckpt_lib.load_saved_config(workdir), workdir)
    assert (attempt.seed, attempt.train.restarts) == (seed, left)
    # The command line's config, run again in that folder, goes on with the same attempt.
    again = restarts.resumed_seed(config, ckpt_lib.load_saved_config(workdir), workdir)
    assert (again.seed, again.train.restarts) == (seed, left)
  archived = restarts.archived_attempts(workdir)
  assert [os.path.basename(a) for a in archived] == ["seed_0", f"seed_{restarts.SEED_STRIDE}"]
  with open(os.path.join(archived[1], "config.json")) as f:
    assert json.load(f)["train"]["restarts"] == 1  # each attempt keeps the config it ran with


def test_a_run_stopped_between_two_attempts_goes_on_with_the_next_seed(tmp_path):
  config = load_config()
  config.train.restarts = 2
  workdir = tmp_path / "run"
  os.makedirs(workdir / restarts.RESTARTED_DIR / "seed_0")
  # Nothing saved yet for the next attempt: seed 0 was abandoned, so the run is seed 1000's.
  resumed = restarts.resumed_seed(config, None, str(workdir))
  assert (resumed.seed, resumed.train.restarts) == (restarts.SEED_STRIDE, 1)
  # Saved by that attempt: its own seed and restarts left, whatever the command line says.
  saved = dict(seed=restarts.SEED_STRIDE, train=dict(restarts=1))
  resumed = restarts.resumed_seed(config, saved, str(workdir))
  assert (resumed.seed, resumed.train.restarts) == (restarts.SEED_STRIDE, 1)
  # No attempt archived: the command line's config as it is.
  assert restarts.resumed_seed(config, None, str(tmp_path / "fresh")) is config


def test_mask_free_statistics_on_a_hand_built_split():
  import numpy as np
  from sklearn.metrics import adjusted_rand_score
  k, n = 4, 200
  one_hot = lambda labels: np.eye(k, dtype=np.float32)[labels]
  # Novel view 0: slot 0 holds 180 pixels, slot 1 holds 18, slot 2 holds 2 (1 %, active), slot 3
  # none; view 1: slot 2 holds everything.
  view0 = np.array([0] * 180 + [1] * 18 + [2] * 2)
  view1 = np.full(n, 2)
  source = np.array([0] * 100 + [1] * 60 + [3] * 40)
  attention = np.array([2] * 100 + [0] * 60 + [0] * 40)  # merges slots 1 and 3 of the render
  stats = validation.mask_free_statistics(
      novel_segmentation=one_hot(np.stack([view0, view1])),
      source_segmentation=one_hot(source[None]), source_attention=attention[None])
  assert stats["mf_active_slots"] == pytest.approx((3 + 1) / 2)
  assert stats["mf_largest_share"] == pytest.approx((0.9 + 1.0) / 2)
  assert stats["mf_pixel_entropy"] == pytest.approx(0.0, abs=1e-6)  # one-hot pixels
  assert stats["mf_attn_agreement"] == pytest.approx(adjusted_rand_score(attention, source))
  # A relabelled copy of the same grouping agrees exactly.
  same = validation.mask_free_statistics(
      novel_segmentation=one_hot(view0[None]), source_segmentation=one_hot(source[None]),
      source_attention=((source + 1) % k)[None])
  assert same["mf_attn_agreement"] == pytest.approx(1.0)


def test_mask_free_check_on_a_constructed_metrics_log():
  config = load_config()
  t = config.train
  t.restarts, t.restart_check_step, t.restart_min_score = 2, 6, 0.55
  t.restart_min_active_slots = 3.0
  t.noise_anneal_steps = t.mask_anneal_steps = 100  # the collapse flag does not count yet
  # A log as a mask-free set's validation writes it: no ARI, PSNR as the score.
  log = [{"step": 3, "score": 18.0, "mf_active_slots": 1.5, "collapsed": 1.0},
         {"step": 6, "score": 19.0, "mf_active_slots": 2.4, "collapsed": 1.0},
         {"step": 9, "score": 19.5, "mf_active_slots": 1.0, "collapsed": 1.0}]
  decide = lambda val, **kw: restarts.reason(t, val["step"], val, **kw)
  # Only the check step decides, and without masks "auto" reads the slots in use.
  assert [decide(v, has_masks=False) is not None for v in log] == [False, True, False]
  assert "mask-free" in decide(log[1], has_masks=False)
  assert decide(dict(log[1], mf_active_slots=3.4), has_masks=False) is None
  assert decide(dict(log[1], mf_active_slots=float("nan")), has_masks=False) is not None
  # The entropy cap: enough slots in use whose pixels are shared (a floor spread over them)
  # restart; a missing entropy restarts too; no cap (1.0) reads the slots alone.
  t.restart_max_pixel_entropy = 0.33
  spread = dict(log[1], mf_active_slots=4.4, mf_pixel_entropy=0.68)
  assert "entropy 0.68" in decide(spread, has_masks=False)
  assert decide(dict(spread, mf_pixel_entropy=0.13), has_masks=False) is None
  assert decide(dict(log[1], mf_active_slots=4.4), has_masks=False) is not None
  t.restart_max_pixel_entropy = 1.0
  assert decide(spread, has_masks=False) is None
  # The agreement floor: slots in use whose split slot attention does not share (ARI 0.02)
  # restart; one that agrees (0.30) is kept; a log without the statistic restarts; −1 is off.
  t.restart_min_attn_agreement = 0.15
  assert "agrees with the rendered split at 0.02" in decide(
      dict(spread, mf_attn_agreement=0.02), has_masks=False)
  assert decide(dict(spread, mf_attn_agreement=0.30), has_masks=False) is None
  assert decide(spread, has_masks=False) is not None
  t.restart_min_attn_agreement = -1.0
  assert decide(dict(spread, mf_attn_agreement=-0.2), has_masks=False) is None
  # With masks, "auto" is the labelled check: a score of 19 passes 0.55 whatever the slots.
  assert decide(log[1], has_masks=True) is None
  t.restart_signal = "mask_free"
  assert decide(log[1], has_masks=True) is not None
  t.restart_signal = "labelled"
  assert decide(dict(log[1], score=0.5), has_masks=True) is not None


def test_labelled_check_is_refused_on_a_set_without_masks():
  config = load_config()
  config.data.has_masks = False
  config.train.restart_check_step = config.train.eval_every
  config.train.restart_signal = "labelled"
  with pytest.raises(config_checks.ConfigError, match="has_masks"):
    config_checks.check_config(config)
  config.train.restart_signal = "auto"
  config_checks.check_config(config)
  config.train.restart_signal = "labels"
  with pytest.raises(config_checks.ConfigError, match="restart_signal"):
    config_checks.check_config(config)
