"""slotlifter_jax/tools/metrics_table.py: evaluation metrics of several runs side by side, from
metrics.json."""

import json
import os
import subprocess
import sys

import pytest

from slotlifter_jax.tools import metrics_table

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _write(path, *, step, **means):
  data = {"split": "test", "num_scenes": 100, "parameters": "average",
          "checkpoint": {"step": step, "path": "x"},
          "metrics": {k: {"mean": v, "stderr": 0.0, "count": 100, "skipped": 0}
                      for k, v in means.items()}}
  path.write_text(json.dumps(data))
  return str(path)


def test_the_command_prints_mean_and_sample_std_per_group(tmp_path):
  a = _write(tmp_path / "a.json", step=50000, fg_ari=0.8, psnr_novel=26.0)
  b = _write(tmp_path / "b.json", step=48000, fg_ari=0.9, psnr_novel=25.0)
  c = _write(tmp_path / "c.json", step=50000, fg_ari=0.25, psnr_novel=27.5)
  out = subprocess.run(
      [sys.executable, "-m", "slotlifter_jax.tools.metrics_table", f"--group=full={a},{b}",
       f"--group=ablated={c}", "--metrics=fg_ari,psnr_novel"],
      cwd=REPO, capture_output=True, text=True, check=True).stdout
  lines = out.splitlines()
  assert lines[0] == "| name | runs | fg_ari | psnr_novel |"
  # By hand: mean 0.85, sample std |0.9 − 0.8|/√2 = 0.0707; PSNR 25.5 ± 0.7071.
  assert lines[2] == "| full | 2 | 0.850 ± 0.071 | 25.50 ± 0.71 |"
  assert lines[3] == "| ablated | 1 | 0.250 | 27.50 |"
  assert "- full: split test, 100 scenes, checkpoint steps 50000, 48000, parameters average" in out


def test_bad_input_is_one_line_naming_the_file_or_flag(tmp_path):
  good = _write(tmp_path / "good.json", step=1, fg_ari=0.5)
  (tmp_path / "bad.json").write_text("{not json")
  cases = [
      ([f"--group=x={good}", "--metrics=nv_ari"], f"{good}: no metric 'nv_ari' (it has fg_ari)"),
      ([f"--group=x={tmp_path / 'none.json'}"], f"{tmp_path / 'none.json'}: cannot read"),
      ([f"--group=x={tmp_path / 'bad.json'}"], f"{tmp_path / 'bad.json'}: not JSON"),
      (["--group=noequals"], "--group='noequals': expected NAME=FILE[,FILE...]"),
      ([], "give at least one --group"),
  ]
  for argv, message in cases:
    with pytest.raises(SystemExit) as e:
      metrics_table.main(argv)
    assert str(e.value).startswith("metrics_table: " + message), (argv, str(e.value))
    assert "\n" not in str(e.value)
