"""slotlifter_jax/tools/fork_run.py: a run folder forked at a checkpoint resumes into the run it
came from."""

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from slotlifter_jax import train
from slotlifter_jax.tools import fork_run
from train_helpers import REPO, final_params, load_config, load_config_with


def test_config_at_undoes_later_changes_latest_first():
  config = {"seed": 0, "train": {"base_lr": 3.0, "mask_min": 0.5}}
  history = [
      {"step": 10, "changes": {"train.base_lr": [1.0, 2.0]}},
      {"step": 20, "changes": {"train.base_lr": [2.0, 3.0], "train.mask_min": [0.0, 0.5]}},
  ]
  assert fork_run.config_at(config, history, 20) == config
  assert fork_run.config_at(config, history, 15) == {"seed": 0,
                                                     "train": {"base_lr": 2.0, "mask_min": 0.0}}
  assert fork_run.config_at(config, history, 5)["train"]["base_lr"] == 1.0
  assert config["train"]["base_lr"] == 3.0  # the source's record is not modified


def test_jsonl_upto_keeps_records_to_the_step_and_drops_a_cut_line(tmp_path):
  path = tmp_path / "metrics.jsonl"
  path.write_text('{"step": 2, "loss": 1}\n{"note": "no step"}\n{"step": 3}\n{"step": 4}\n'
                  '{"step": 5, "lo')
  kept = [json.loads(line) for line in fork_run._jsonl_upto(str(path), 3)]
  assert kept == [{"step": 2, "loss": 1}, {"note": "no step"}, {"step": 3}]
  assert fork_run._jsonl_upto(str(tmp_path / "absent.jsonl"), 3) == []


def _run(*args):
  return subprocess.run([sys.executable, "-m", "slotlifter_jax.tools.fork_run", *map(str, args)],
                        capture_output=True, text=True, cwd=REPO)


@pytest.mark.slow
def test_fork_retraces_its_source_and_keeps_only_the_past(tmp_path):
  config = load_config()  # smoke: 6 steps, checkpoints and validations at steps 3 and 6
  src, dst = tmp_path / "src", tmp_path / "dst"
  train.train_and_evaluate(config, str(src))
  # A later resume with another rate: the source's config.json and history now say 2× from step 6.
  changed = load_config_with(config)
  changed.train.base_lr = config.train.base_lr * 2
  train.train_and_evaluate(changed, str(src))

  done = _run(src, dst, "--checkpoint=3")
  assert done.returncode == 0, done.stderr
  assert f"forked {src} at step 3 (checkpoints/latest/3) into {dst}" in done.stdout
  assert sorted(os.listdir(dst / "checkpoints" / "latest")) == ["3"]
  with open(dst / "metrics.jsonl") as f:
    steps = [json.loads(line)["step"] for line in f]
  assert steps and max(steps) == 3
  with open(src / "metrics.jsonl") as f:
    assert max(json.loads(line)["step"] for line in f) == 6  # the source is untouched
  with open(dst / "config.json") as f:
    assert json.load(f)["train"]["base_lr"] == config.train.base_lr  # the change at 6 undone
  assert not os.path.exists(dst / "config_history.jsonl")  # its only record is after step 3
  assert sorted(os.listdir(dst / "val")) == sorted(
      n for n in os.listdir(src / "val") if int(n.split("_")[1].split(".")[0]) <= 3)
  with open(dst / "fork.json") as f:
    assert json.load(f)["source"] == str(src)

  # Resumed with the source's command, the fork ends where the source's straight run ended.
  train.train_and_evaluate(load_config_with(config), str(dst))
  step_a, params_a = final_params(str(src), config)
  step_b, params_b = final_params(str(dst), config)
  assert step_a == step_b == 6
  jax.tree.map(np.testing.assert_array_equal, params_a, params_b)

  # Refusals: one line each, and nothing written or changed.
  before = sorted(os.listdir(dst))
  for args, message in [
      ((src, dst), f"{dst}: exists; a fork is made into a new folder only"),
      ((src, tmp_path / "new", "--checkpoint=4"), "--checkpoint=4: no such step; saved steps"),
      ((tmp_path / "absent", tmp_path / "new"), "config.json: missing"),
  ]:
    failed = _run(*args)
    err = failed.stderr.strip()
    assert failed.returncode == 2 and message in err and "\n" not in err, err
  assert sorted(os.listdir(dst)) == before
  assert not os.path.exists(tmp_path / "new") and not os.path.exists(tmp_path / "absent")
  assert not [n for n in os.listdir(tmp_path) if ".forking-" in n]
