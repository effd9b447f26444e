"""slotlifter_jax/tools/early_check.py on hand-written validation logs: it reads validation only."""

import json
import subprocess
import sys

TOOL = [sys.executable, "-m", "slotlifter_jax.tools.early_check"]


def _write_run(folder, name, val_rows, slots=None, entropy=None, agreement=None):
  """val_rows: (step, fg_ari, nv_ari); slots, entropy, agreement: {step: mf_active_slots},
  {step: mf_pixel_entropy} and {step: mf_attn_agreement}, or None."""
  path = folder / f"{name}_val_metrics.jsonl"
  with open(path, "w") as f:
    for step, fg, nv in val_rows:
      row = dict(step=step, kind="val", fg_ari=fg, nv_ari=nv)
      if slots and step in slots:
        row["mf_active_slots"] = slots[step]
      if entropy and step in entropy:
        row["mf_pixel_entropy"] = entropy[step]
      if agreement and step in agreement:
        row["mf_attn_agreement"] = agreement[step]
      f.write(json.dumps(row) + "\n")
  # A test evaluation beside it must change nothing: the tool never reads it.
  (folder / f"{name}_test_metrics.json").write_text("not json: opening this is a failure")
  return str(path)


def _run(*args):
  return subprocess.run([*TOOL, *args], capture_output=True, text=True,
                        timeout=60)


def _rows(stdout):
  return {line.split(" | ")[0].lstrip("| "): line for line in stdout.splitlines()
          if line.startswith("| ") and not line.startswith("| run")}


def test_rule_outcomes_and_counts_by_hand(tmp_path):
  runs = [
      # kept (0.60 ≥ 0.55) and ends split: the worse of FG 0.70 and NV 0.60 is what counts
      _write_run(tmp_path, "a", [(2, 0.1, 0.1), (4, 0.70, 0.60), (6, 0.9, 0.85)], {4: 4.0},
                 {4: 0.20}),
      # restarted (NV 0.50) and never split: the rule was right; its four slots in use share
      # the pixels (entropy 0.50), as a floor spread over slots does
      _write_run(tmp_path, "b", [(4, 0.80, 0.50), (6, 0.9, 0.5)], {4: 4.0}, {4: 0.50}),
      # kept and ends below on FG (0.79 < 0.8): a miss of the rule
      _write_run(tmp_path, "c", [(4, 0.56, 0.70), (6, 0.79, 0.9)], {4: 2.0}),
      # restarted although it ends split; resumed, step 4 logged twice (the later row counts)
      _write_run(tmp_path, "d", [(4, 0.10, 0.10), (4, 0.54, 0.90), (6, 0.8, 0.8)]),
  ]
  result = _run("--step=4", "--min_score=0.55", "--min_active_slots=3", *runs)
  assert result.returncode == 0, result.stderr
  rows = _rows(result.stdout)
  assert "| 0.600 | keep | 0.850 (6) | yes | 4.00 | 0.20 | – | keep |" in rows["a"]
  assert "| 0.500 | restart | 0.500 (4) | no | 4.00 | 0.50 | – | keep |" in rows["b"]
  assert "| 0.560 | keep | 0.790 (6) | no | 2.00 | – | – | restart |" in rows["c"]
  assert "| 0.540 | restart | 0.800 (6) | yes | – | – | – | – |" in rows["d"]
  lines = result.stdout.splitlines()
  assert lines[-2] == "4 runs: the rule keeps 1 that end below the target and restarts 1 that reach it"
  # a keeps with both, b and c are decided differently, d has no mask-free statistics
  assert lines[-1] == "3 runs log the mask-free statistics: the two rules decide alike on 1"
  # The entropy cap restarts b (0.50 > 0.33) and keeps a (0.20); c, without the statistic, was
  # restarted by its slots already.
  result = _run("--step=4", "--min_score=0.55", "--min_active_slots=3",
                "--max_pixel_entropy=0.33", *runs)
  assert result.returncode == 0, result.stderr
  rows = _rows(result.stdout)
  assert rows["a"].endswith("| 4.00 | 0.20 | – | keep |")
  assert rows["b"].endswith("| 4.00 | 0.50 | – | restart |")
  assert result.stdout.splitlines()[-1] == (
      "3 runs log the mask-free statistics: the two rules decide alike on 2")


def test_the_agreement_floor_restarts_runs_whose_slot_attention_does_not_group(tmp_path):
  runs = [
      # slot attention agrees with the rendering (0.30) and the run ends split
      _write_run(tmp_path, "grouping", [(4, 0.60, 0.60), (6, 0.85, 0.82)], {4: 3.0}, {4: 0.2},
                 {4: 0.30}),
      # as many slots in use and as low an entropy, but slot attention groups nothing the
      # decoder renders (0.01): the slots and entropy keep it, the agreement floor does not
      _write_run(tmp_path, "parting", [(4, 0.30, 0.40), (6, 0.5, 0.6)], {4: 3.0}, {4: 0.2},
                 {4: 0.01}),
      # no agreement logged (an older log): restarted, since nothing says it groups
      _write_run(tmp_path, "older", [(4, 0.60, 0.60), (6, 0.9, 0.9)], {4: 3.0}, {4: 0.2}),
  ]
  common = ("--step=4", "--min_score=0.55", "--min_active_slots=3", "--max_pixel_entropy=0.33")
  rows = _rows(_run(*common, *runs).stdout)
  assert [rows[n].endswith("| keep |") for n in ("grouping", "parting", "older")] == [True] * 3
  result = _run(*common, "--min_attn_agreement=0.15", *runs)
  assert result.returncode == 0, result.stderr
  rows = _rows(result.stdout)
  assert rows["grouping"].endswith("| 3.00 | 0.20 | 0.30 | keep |")
  assert rows["parting"].endswith("| 3.00 | 0.20 | 0.01 | restart |")
  assert rows["older"].endswith("| 3.00 | 0.20 | – | restart |")
  assert result.stdout.splitlines()[-1] == (
      "3 runs log the mask-free statistics: the two rules decide alike on 2")


def test_sweep_ranks_rules_by_misjudged_runs(tmp_path):
  runs = [_write_run(tmp_path, "a", [(2, 0.30, 0.30), (4, 0.62, 0.7), (6, 0.9, 0.9)]),
          _write_run(tmp_path, "b", [(2, 0.50, 0.50), (4, 0.40, 0.7), (6, 0.5, 0.5)]),
          _write_run(tmp_path, "c", [(2, 0.35, 0.40), (4, 0.58, 0.6), (6, 0.85, 0.81)])]
  result = _run("--sweep", "--top=3", *runs)
  assert result.returncode == 0, result.stderr
  lines = result.stdout.splitlines()
  assert lines[0] == "3 runs, 2 of which end split (best validation min(FG, NV) ≥ 0.8)"
  # Step 4 separates them from 0.45 to 0.55 (a, c ≥ 0.58 end split, b at 0.40 does not); step 2
  # cannot at any threshold of the grid (b, which never splits, is highest there).
  assert lines[3:6] == ["| 4 | 0.45 | 0 | 0 |", "| 4 | 0.50 | 0 | 0 |", "| 4 | 0.55 | 0 | 0 |"]


def test_a_missing_step_or_file_is_one_line(tmp_path):
  run = _write_run(tmp_path, "a", [(2, 0.1, 0.1), (4, 0.2, 0.2)])
  result = _run("--step=3", "--min_score=0.5", run)
  assert result.returncode == 1
  assert result.stderr.strip() == f"error: {run}: no validation at step 3 (steps 2–4)"
  result = _run("--step=3", "--min_score=0.5", str(tmp_path / "nothing_here"))
  assert result.returncode == 1 and len(result.stderr.strip().splitlines()) == 1
  assert "neither a run folder nor a NAME_val_metrics.jsonl file" in result.stderr
