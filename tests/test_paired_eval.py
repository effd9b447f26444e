"""slotlifter_jax/tools/paired_eval.py: paired per-scene differences between evaluations of one
split."""

import json
import math
import os
import subprocess
import sys

import pytest

import data_fixtures as fx
from slotlifter_jax.tools import paired_eval

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL = [sys.executable, "-m", "slotlifter_jax.tools.paired_eval"]


def test_paired_difference_by_hand(tmp_path):
  # fg_ari: differences +0.1, +0.3, −0.1 and a NaN scene (no foreground) left out:
  # mean 0.1, sample std 0.2, s.e. 0.2/√3.
  base = fx.write_eval(tmp_path / "a", {"s0": {"fg_ari": 0.5, "psnr_novel": 20.0},
                                         "s1": {"fg_ari": 0.4, "psnr_novel": 22.0},
                                         "s2": {"fg_ari": 0.9, "psnr_novel": 24.0},
                                         "s3": {"fg_ari": math.nan, "psnr_novel": 26.0}})
  other = fx.write_eval(tmp_path / "b", {"s3": {"fg_ari": 0.7, "psnr_novel": 26.0},  # other order
                                          "s0": {"fg_ari": 0.6, "psnr_novel": 20.0},
                                          "s1": {"fg_ari": 0.7, "psnr_novel": 21.0},
                                          "s2": {"fg_ari": 0.8, "psnr_novel": 25.0}},
                         differs={"model.slot_iters": [3, 5]})
  result = paired_eval.compare([base, other], ["fg_ari", "psnr_novel"])
  rows = result["others"][0]["rows"]
  fg = rows["fg_ari"]
  assert fg["scenes"] == 3 and fg["higher"] == 2 and fg["lower"] == 1
  assert fg["difference"] == pytest.approx(0.1)
  assert fg["stderr"] == pytest.approx(0.2 / math.sqrt(3))
  assert fg["base"] == pytest.approx(0.6) and fg["other"] == pytest.approx(0.7)
  psnr = rows["psnr_novel"]  # −1, +1, 0, 0 over four scenes
  assert psnr["scenes"] == 4 and psnr["higher"] == 1 and psnr["lower"] == 1
  assert psnr["difference"] == pytest.approx(0.0, abs=1e-12)
  assert psnr["stderr"] == pytest.approx(math.sqrt(2 / 3) / 2)
  assert "model.slot_iters=5" in result["others"][0]["label"]
  assert "as trained" in result["baseline"]["label"]


def test_refuses_different_scenes_missing_files_and_metrics(tmp_path):
  a = fx.write_eval(tmp_path / "a", {"s0": {"fg_ari": 0.5}, "s1": {"fg_ari": 0.4}})
  b = fx.write_eval(tmp_path / "b", {"s0": {"fg_ari": 0.5}, "s2": {"fg_ari": 0.4}})
  with pytest.raises(paired_eval.PairedEvalError, match="different scenes"):
    paired_eval.compare([a, b], ["fg_ari"])
  with pytest.raises(paired_eval.PairedEvalError, match="nv_ari"):
    paired_eval.compare([a, a], ["nv_ari"])
  missing = str(tmp_path / "none")
  with pytest.raises(paired_eval.PairedEvalError, match="none.*metrics.json: not found"):
    paired_eval.compare([a, missing], ["fg_ari"])
  with pytest.raises(paired_eval.PairedEvalError, match="at least two"):
    paired_eval.compare([a], ["fg_ari"])


def test_command_line_prints_writes_and_keeps_an_existing_file(tmp_path):
  a = fx.write_eval(tmp_path / "a", {"s0": {"fg_ari": 0.2}, "s1": {"fg_ari": 0.4}})
  b = fx.write_eval(tmp_path / "b", {"s0": {"fg_ari": 0.5}, "s1": {"fg_ari": 0.5}},
                  parameters="average")
  out = tmp_path / "cmp.json"
  cmd = [*TOOL, a, b, "--metrics=fg_ari", f"--out={out}"]
  done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
  assert done.returncode == 0, done.stderr
  assert "+0.2000" in done.stdout  # (0.3 + 0.1) / 2
  written = json.loads(out.read_text())
  assert written["others"][0]["rows"]["fg_ari"]["difference"] == pytest.approx(0.2)
  # Which parameters each side evaluated: a moving average's against the trained ones.
  assert (written["baseline"]["parameters"], written["others"][0]["parameters"]) == (
      "trained", "average")
  assert "average of the parameters" in done.stdout
  before = out.read_bytes()
  again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
  assert again.returncode == 1 and "--overwrite" in again.stderr
  assert len(again.stderr.strip().splitlines()) == 1
  assert out.read_bytes() == before
  bad = subprocess.run([*TOOL, a, str(tmp_path / "x")],
                       cwd=REPO, capture_output=True, text=True)
  assert bad.returncode == 1 and "x/metrics.json: not found" in bad.stderr
