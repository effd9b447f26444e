"""experiments/early_check.py on hand-written validation logs and test metrics."""

import json
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(REPO, "experiments", "early_check.py")


def _write_run(folder, name, val_rows, test=None):
  """val_rows: (step, fg_ari, nv_ari); test: (fg_ari, nv_ari) or None."""
  path = folder / f"{name}_val_metrics.jsonl"
  with open(path, "w") as f:
    for step, fg, nv in val_rows:
      f.write(json.dumps(dict(step=step, kind="val", fg_ari=fg, nv_ari=nv)) + "\n")
  if test is not None:
    metrics = dict(fg_ari=dict(mean=test[0]), nv_ari=dict(mean=test[1]))
    (folder / f"{name}_test_metrics.json").write_text(json.dumps(dict(metrics=metrics)))
  return str(path)


def _run(*args):
  return subprocess.run([sys.executable, SCRIPT, *args], capture_output=True, text=True,
                        timeout=60)


def test_rule_outcomes_and_counts_by_hand(tmp_path):
  runs = [
      # kept (0.60 ≥ 0.55) and passes: the worse of FG 0.70 and NV 0.60 is what counts
      _write_run(tmp_path, "a", [(2, 0.1, 0.1), (4, 0.70, 0.60), (6, 0.9, 0.9)], (0.85, 0.82)),
      # restarted (NV 0.50) and fails: the rule was right
      _write_run(tmp_path, "b", [(4, 0.80, 0.50), (6, 0.9, 0.5)], (0.86, 0.52)),
      # kept and fails on FG (0.79 < 0.8): a miss of the rule
      _write_run(tmp_path, "c", [(4, 0.56, 0.70)], (0.79, 0.90)),
      # restarted although it passes: the other kind of miss; resumed, step 4 logged twice
      _write_run(tmp_path, "d", [(4, 0.10, 0.10), (4, 0.54, 0.90), (6, 0.8, 0.8)], (0.81, 0.80)),
      # no test evaluation: judged by nothing
      _write_run(tmp_path, "e", [(4, 0.3, 0.3)]),
  ]
  result = _run("--step=4", "--min_score=0.55", *runs)
  assert result.returncode == 0, result.stderr
  rows = {line.split(" | ")[0].lstrip("| "): line for line in result.stdout.splitlines()
          if line.startswith("| ") and not line.startswith("| run")}
  assert "| 0.600 | keep | 0.900 (step 6) | 0.850 | 0.820 | yes |" in rows["a"]
  assert "| 0.500 | restart | 0.500 (step 6) | 0.860 | 0.520 | no |" in rows["b"]
  assert "| 0.560 | keep |" in rows["c"] and rows["c"].endswith("| no |")
  assert "| 0.540 | restart |" in rows["d"] and rows["d"].endswith("| yes |")
  assert rows["e"].endswith("| – | – | – |")
  assert result.stdout.splitlines()[-1] == (
      "4 runs with a test evaluation: the rule keeps 1 that end below the target and restarts 1 "
      "that reach it")


def test_a_missing_step_or_file_is_one_line(tmp_path):
  run = _write_run(tmp_path, "a", [(2, 0.1, 0.1), (4, 0.2, 0.2)])
  result = _run("--step=3", "--min_score=0.5", run)
  assert result.returncode == 1
  assert result.stderr.strip() == f"error: {run}: no validation at step 3 (steps 2–4)"
  result = _run("--step=3", "--min_score=0.5", str(tmp_path / "nothing_here"))
  assert result.returncode == 1 and len(result.stderr.strip().splitlines()) == 1
  assert "neither a run folder nor a NAME_val_metrics.jsonl file" in result.stderr
