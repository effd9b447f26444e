"""slotlifter_jax/tools/headline.py on hand-built run folders."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

TOOL = [sys.executable, "-m", "slotlifter_jax.tools.headline"]


def _run_folder(root, name, *, seed, fg, nv, psnr, restarted=(), wall_s=600.0, split="test"):
  run = root / name
  (run / "eval" / split).mkdir(parents=True)
  metrics = {k: dict(mean=v, stderr=0.01, count=100) for k, v in
             (("fg_ari", fg), ("nv_ari", nv), ("psnr_novel", psnr))}
  (run / "eval" / split / "metrics.json").write_text(json.dumps(dict(
      metrics=metrics, checkpoint=dict(step=48000), provenance=dict(git_commit="abc"))))
  (run / "config.json").write_text(json.dumps(dict(seed=seed + 1000 * len(restarted))))
  for s in restarted:
    (run / "restarted" / f"seed_{s}").mkdir(parents=True)
  with open(run / "metrics.jsonl", "w") as f:
    for step, wall in ((50, wall_s / 2), (100, wall_s)):
      f.write(json.dumps(dict(step=step, kind="train", wall_s=wall)) + "\n")
  (run / "machines.jsonl").write_text(
      json.dumps(dict(step=0, platform="cpu", cpu_model="CPU A", git_commit="c1")) + "\n"
      + json.dumps(dict(step=60, platform="cpu", cpu_model="CPU B", git_commit="c2")) + "\n")
  return str(run)


def test_headline_of_three_seeds_against_numpy(tmp_path):
  runs = [_run_folder(tmp_path, "s1", seed=1, fg=0.80, nv=0.85, psnr=25.0),
          _run_folder(tmp_path, "s0", seed=0, fg=0.86, nv=0.83, psnr=26.0, restarted=(0,),
                      wall_s=3000.0),
          _run_folder(tmp_path, "s2", seed=2, fg=0.40, nv=0.60, psnr=24.0)]
  out = tmp_path / "headline.json"
  result = subprocess.run([*TOOL, "--name=room", "--split=test", f"--out={out}",
                           *runs], capture_output=True, text=True, timeout=120)
  assert result.returncode == 0, result.stderr
  h = json.loads(out.read_text())
  assert h["split"] == "test" and h["num_seeds"] == 3 and h["collapsed_seeds"] == 1
  assert [r["seed"] for r in h["seeds"]] == [0, 1, 2]  # seed 0 restarted once, as 1000
  first = h["seeds"][0]
  assert (first["attempts"], first["final_seed"], first["wall_minutes"]) == (2, 1000, 50.0)
  assert first["hosts"] == ["CPU A", "CPU B"] and first["checkpoint"]["step"] == 48000
  assert first["train_commits"] == ["c1", "c2"]
  fg = np.array([0.86, 0.80, 0.40])
  assert h["summary"]["fg_ari"]["mean"] == pytest.approx(fg.mean())
  assert h["summary"]["fg_ari"]["std"] == pytest.approx(fg.std(ddof=1))
  assert h["summary"]["psnr_novel"]["mean"] == pytest.approx(25.0)


def test_a_seed_without_that_evaluation_is_one_line_naming_the_file(tmp_path):
  runs = [_run_folder(tmp_path, "s0", seed=0, fg=0.8, nv=0.8, psnr=25.0, split="dev")]
  out = tmp_path / "h.json"
  result = subprocess.run([*TOOL, "--name=clevr", f"--out={out}", *runs],
                          capture_output=True, text=True, timeout=120)
  assert result.returncode == 1 and not out.exists()
  assert result.stderr.strip() == (
      f"error: {os.path.join(runs[0], 'eval', 'test', 'metrics.json')}: no such file")


def test_one_seed_has_no_spread_and_the_file_stays_strict_json(tmp_path):
  runs = [_run_folder(tmp_path, "s0", seed=0, fg=0.84, nv=0.86, psnr=26.2)]
  out = tmp_path / "h.json"
  result = subprocess.run([*TOOL, "--name=clevr", f"--out={out}", *runs],
                          capture_output=True, text=True, timeout=120)
  assert result.returncode == 0, result.stderr
  # NaN is not JSON: a strict parser must read the file, and one seed's std is null.
  h = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the file"))
  assert h["summary"]["fg_ari"] == {"mean": pytest.approx(0.84), "std": None}
  assert "FG-ARI 0.840 ± n/a" in result.stdout
