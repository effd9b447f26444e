"""Exact resume: a run interrupted by SIGINT and resumed ends bit-identical to a straight run,
with host batches, with staged batches, and with batches drawn on the device."""

import json
import os
import signal

import jax
import numpy as np
import pytest

from slotlifter_jax import train
from slotlifter_jax import train_step as step_lib
from train_helpers import final_params, load_config, load_config_with


def _straight_and_interrupted_runs(config, tmp_path, monkeypatch, factory: str):
  """Trains `config` straight, then again with SIGINT during the 3rd call of the compiled step
  that step_lib.<factory> makes (the loop checkpoints and leaves) and a resume; checks that both
  end at step 6 with identical parameters."""
  train.train_and_evaluate(config, str(tmp_path / "straight"))
  real_make = getattr(step_lib, factory)
  def make_interrupting(*args, **kwargs):
    inner = real_make(*args, **kwargs)
    calls = {"n": 0}
    def step(state, data):
      calls["n"] += 1
      if calls["n"] == 3:
        os.kill(os.getpid(), signal.SIGINT)
      return inner(state, data)
    return step
  monkeypatch.setattr(step_lib, factory, make_interrupting)
  with pytest.raises(train.Interrupted) as interrupted:
    train.train_and_evaluate(load_config_with(config), str(tmp_path / "resumed"))
  assert (interrupted.value.signum, interrupted.value.step) == (signal.SIGINT, 3)
  assert final_params(str(tmp_path / "resumed"), config)[0] == 3
  monkeypatch.setattr(step_lib, factory, real_make)
  train.train_and_evaluate(load_config_with(config), str(tmp_path / "resumed"))

  step_a, params_a = final_params(str(tmp_path / "straight"), config)
  step_b, params_b = final_params(str(tmp_path / "resumed"), config)
  assert step_a == step_b == 6
  jax.tree.map(np.testing.assert_array_equal, params_a, params_b)


@pytest.mark.slow
def test_resume_after_interrupt_is_exact(tmp_path, monkeypatch):
  config = load_config()
  config.train.num_steps = 6
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_step")

  # Resuming with another learning rate keeps the record of the first one.
  changed = load_config_with(config)
  changed.train.base_lr = config.train.base_lr * 0.5
  train.train_and_evaluate(changed, str(tmp_path / "straight"))
  with open(tmp_path / "straight" / "config_history.jsonl") as f:
    history = [json.loads(line) for line in f]
  assert [(h["step"], h["changes"]) for h in history] == [
      (6, {"train.base_lr": [config.train.base_lr, changed.train.base_lr]})]
  with open(tmp_path / "straight" / "config.json") as f:
    assert json.load(f)["train"]["base_lr"] == changed.train.base_lr


@pytest.mark.slow
def test_staged_run_changes_its_batch_and_resumes_exactly(tmp_path, monkeypatch):
  """Stages of scenes and rays that start at the interrupted step: the step compiles for the new
  ray count, and the resumed run still ends bit-identical to the straight one."""
  config = load_config()
  config.train.num_steps = 6
  config.data.scene_stages = ((0, 2), (3, config.data.num_train_scenes))
  config.train.ray_stages = ((3, 2 * config.train.rays_per_scene),)
  seen = []
  real_assemble = step_lib.assemble_batch
  def recording(batch, *args, **kwargs):
    seen.append((batch["target_rgb"].shape[1], set(batch["scene_index"].tolist())))
    return real_assemble(batch, *args, **kwargs)
  monkeypatch.setattr(step_lib, "assemble_batch", recording)
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_step")
  r = config.train.rays_per_scene
  straight = seen[:6]  # the straight run's batches come first
  assert [rays for rays, _ in straight] == [r] * 3 + [2 * r] * 3
  assert set().union(*(scenes for _, scenes in straight[:3])) <= {0, 1}


@pytest.mark.slow
def test_device_sampled_run_resumes_exactly_and_records_its_clock(tmp_path, monkeypatch):
  """data.sampler=device: batches drawn inside the step are a function of (seed, step), so an
  interrupted and resumed run ends bit-identical; every record carries the run's wall clock,
  which a resume continues, and the run writes emergence.json."""
  config = load_config()
  config.data.sampler = "device"
  config.train.num_steps = 6
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_block")
  with open(tmp_path / "resumed" / "metrics.jsonl") as f:
    records = [json.loads(line) for line in f]
  clock = [r["wall_s"] for r in records]
  assert all(b >= a for a, b in zip(clock, clock[1:])), clock  # continues across the resume
  assert [r["step"] for r in records if r["kind"] == "val"] == [3, 6]
  with open(tmp_path / "resumed" / "emergence.json") as f:
    assert json.load(f)["num_validations"] == 2
