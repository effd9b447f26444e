"""slotlifter_jax/tools/compare_curves.py through its command line: the tables it prints and its
errors."""

import json
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL = [sys.executable, "-m", "slotlifter_jax.tools.compare_curves"]


def _write(path, records):
  with open(path, "w") as f:
    for r in records:
      f.write(json.dumps(r) + "\n")


def _run(*args):
  return subprocess.run([*TOOL, *args], capture_output=True, text=True, cwd=REPO)


def test_tables_list_each_runs_validations_by_step(tmp_path):
  full = tmp_path / "full.jsonl"
  _write(full, [
      {"step": 50, "kind": "train", "time": 0.0, "loss": 0.1},
      {"step": 2000, "kind": "val", "time": 60.0, "fg_ari": 0.25, "psnr_novel": 19.5},
      {"step": 4000, "kind": "val", "time": 120.0, "fg_ari": 0.5, "psnr_novel": 20.25},
  ])
  run_dir = tmp_path / "ablation"
  run_dir.mkdir()
  _write(run_dir / "metrics.jsonl", [
      {"step": 2000, "kind": "val", "time": 10.0, "fg_ari": 0.125, "psnr_novel": 18.0},
      # a resumed run validated step 2000 again: the later record is the one kept
      {"step": 2000, "kind": "val", "time": 20.0, "fg_ari": 0.0625, "psnr_novel": 18.5},
      {"step": 6000, "kind": "val", "time": 30.0, "fg_ari": 0.75},
  ])
  out = tmp_path / "c.png"
  r = _run(f"--run=full={full}", f"--run=no_masking={run_dir}", "--keys=fg_ari,psnr_novel",
           f"--out={out}")
  assert r.returncode == 0, r.stderr
  assert out.stat().st_size > 0
  text = r.stdout
  assert "| step | full | no_masking |" in text
  fg = text.split("FG-ARI")[1].split("novel-view PSNR")[0]
  assert "| 2000 | 0.250 | 0.062 |" in fg  # 0.0625 to three decimals
  assert "| 4000 | 0.500 | – |" in fg
  assert "| 6000 | – | 0.750 |" in fg
  psnr = text.split("novel-view PSNR")[1]
  assert "| 2000 | 19.50 | 18.50 |" in psnr
  assert "| 6000 | – | – |" in psnr  # no PSNR at step 6000 in either run


def test_bad_input_is_a_one_line_error_naming_what_is_wrong(tmp_path):
  good = tmp_path / "g.jsonl"
  _write(good, [{"step": 2000, "kind": "val", "time": 1.0, "fg_ari": 0.5}])
  out = tmp_path / "c.png"
  cases = [
      ([f"--run={good}", f"--out={out}"], "expected LABEL=PATH"),
      ([f"--run=a={tmp_path / 'missing.jsonl'}", f"--out={out}"], "missing.jsonl does not exist"),
      ([f"--run=a={good}", f"--run=a={good}", f"--out={out}"], "'a' is given twice"),
      ([f"--run=a={good}", "--keys=nv_ari", f"--out={out}"], "no run logged 'nv_ari'"),
  ]
  for args, message in cases:
    r = _run(*args)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], r.stderr
  assert not out.exists()
  bad = tmp_path / "bad.jsonl"
  bad.write_text('{"step": 1, "kind": "val"}\nnot json\n{"step": 2, "kind": "val"}\n')
  r = _run(f"--run=a={bad}", f"--out={out}")
  assert r.returncode != 0 and "bad.jsonl line 2" in r.stderr.strip().splitlines()[-1]


def test_loss_windows_average_each_runs_training_loss_per_window(tmp_path):
  """Windows (w, w + N] from --from_step on, means by hand; a step logged twice (a resumed run)
  counts once, as its later record; a file of validations only is left out of the table."""
  run_dir = tmp_path / "fork"
  run_dir.mkdir()
  _write(run_dir / "metrics.jsonl", [
      {"step": 100, "kind": "train", "time": 0.0, "loss": 9.0},  # at --from_step: not counted
      {"step": 150, "kind": "train", "time": 1.0, "loss": 0.5},
      {"step": 200, "kind": "train", "time": 2.0, "loss": 0.25},
      {"step": 200, "kind": "val", "time": 3.0, "fg_ari": 0.5},
      {"step": 250, "kind": "train", "time": 4.0, "loss": 4.0},
      {"step": 250, "kind": "train", "time": 5.0, "loss": 1.0},  # resumed: this one counts
      {"step": 300, "kind": "train", "time": 6.0, "loss": 2.0},
      {"step": 400, "kind": "train", "time": 7.0, "loss": 0.125},
      {"step": 400, "kind": "val", "time": 8.0, "fg_ari": 0.25},
  ])
  vals = tmp_path / "v.jsonl"
  _write(vals, [{"step": 200, "kind": "val", "time": 1.0, "fg_ari": 0.75}])
  r = _run(f"--run=fork={run_dir}", f"--run=copy={vals}", "--keys=fg_ari",
           f"--out={tmp_path / 'c.png'}", "--loss_windows=100", "--from_step=100")
  assert r.returncode == 0, r.stderr
  text = r.stdout.split("mean training loss per 100 steps")[1]
  assert "| steps | fork |" in text and "copy" not in text
  assert "| 101–200 | 0.3750 |" in text  # (0.5 + 0.25) / 2
  assert "| 201–300 | 1.5000 |" in text  # (1.0 + 2.0) / 2, the resumed record at 250
  assert "| 301–400 | 0.1250 |" in text
  r = _run(f"--run=copy={vals}", "--keys=fg_ari", f"--out={tmp_path / 'c.png'}",
           "--loss_windows=100")
  assert r.returncode != 0
  assert r.stderr.strip() == "error: --loss_windows: no run has training records after step 0"
