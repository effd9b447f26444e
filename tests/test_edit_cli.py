"""`--mode=edit` end to end on a trained smoke run (slotlifter_jax/edit.py, docs/editing.md): the
command line writes edit_metrics.json with its keys, refuses to overwrite it, names the flag of
a bad request in one line without touching the run, and renders one edit's pictures and orbit."""

import hashlib
import json
import os
import subprocess
import sys

import pytest

from slotlifter_jax import edit
from slotlifter_jax import edit_eval
from slotlifter_jax import edit_scores
from slotlifter_jax import train
from slotlifter_jax.data import registry
from slotlifter_jax.data import scene_edits
from train_helpers import REPO, load_config


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
  workdir = str(tmp_path_factory.mktemp("edit_run"))
  train.train_and_evaluate(load_config(), workdir)
  return workdir


def _main(*args):
  proc = subprocess.run([sys.executable, "-m", "slotlifter_jax.main",
                         "--config=configs/clevr.py:smoke", *args], cwd=REPO,
                        capture_output=True, text=True, timeout=600)
  return proc.returncode, proc.stdout + proc.stderr


def _tree_digest(folder):
  """Every file under `folder` with its bytes' digest: what must not change."""
  out = {}
  for root, _, files in os.walk(folder):
    for name in files:
      with open(os.path.join(root, name), "rb") as f:
        out[os.path.relpath(os.path.join(root, name), folder)] = hashlib.sha256(
            f.read()).hexdigest()
  return out


def _objects_in_first_scene(config):
  from slotlifter_jax.data import embedded
  config = embedded.resolve_data(config.copy_and_resolve_references())
  d = config.data
  folder = registry.split_folder(d.root, d.subset, "test")
  return len(scene_edits.read_manifest(folder)["scenes"][0]["objects"])


@pytest.mark.slow
def test_edit_scores_a_split_from_the_command_line(run_dir):
  checkpoints = _tree_digest(os.path.join(run_dir, "checkpoints"))
  code, out = _main(f"--workdir={run_dir}", "--mode=edit", "--max_scenes=1")
  assert code == 0, out[-3000:]
  path = os.path.join(run_dir, "edit", "test", "edit_metrics.json")
  with open(path) as f:
    report = json.load(f)
  num_objects = _objects_in_first_scene(load_config())
  for kind in ("remove", "move"):
    s = report[kind]
    for key in ("improved_fraction", "psnr_changed", "psnr_changed_baseline", "num_edits",
                "num_skipped", "psnr_changed_stderr", "ssim", "ssim_baseline",
                "psnr_changed_seen", "psnr_changed_unseen"):
      assert key in s, (kind, key)
    # Every object is tried once per kind: scored, or skipped for no slot (or, when moved, for
    # no translation that fits).
    assert s["num_edits"] + s["num_skipped"] + s.get("num_no_translation", 0) == num_objects
  assert "iou_mean" in report["move"] and "iou_baseline_mean" in report["move"]
  best = max(int(s) for s in os.listdir(os.path.join(run_dir, "checkpoints", "best")))
  assert report["checkpoint"]["step"] == best and report["checkpoint"]["name"] == "best"
  assert report["parameters"] in ("average", "trained")
  prov = report["provenance"]
  assert prov["config"]["model"]["num_slots"] == 4 and "cpu_model" in prov
  assert "git_commit" in prov
  assert report["settings"]["match_iou"] == edit_scores.MATCH_IOU
  assert report["settings"]["removal"] == edit_scores.REMOVAL
  assert report["settings"]["move_background"] == edit_scores.MOVE_BACKGROUND
  assert report["settings"]["uncovered"] == edit_scores.UNCOVERED
  # Again without --overwrite: refused, the file kept.
  with open(path, "rb") as f:
    kept = f.read()
  code, out = _main(f"--workdir={run_dir}", "--mode=edit", "--max_scenes=1")
  assert code != 0 and "exists" in out and "--overwrite" in out
  with open(path, "rb") as f:
    assert f.read() == kept
  # Bad requests: one line naming the flag, before anything is written.
  for args, flag in ((["--move_slot=9", "--by=1,0,0"], "--move_slot"),
                     (["--move_slot=1", "--by=1,0"], "--by"),
                     (["--remove_slot=0", "--scenes=7"], "--scenes")):
    code, out = _main(f"--workdir={run_dir}", "--mode=edit", *args)
    assert code != 0
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"error: {flag}: "), out[-2000:]
  code, out = _main(f"--workdir={run_dir}", "--mode=eval", "--remove_slot=0")
  assert code != 0 and out.strip().splitlines()[-1] == "error: --remove_slot: only with --mode=edit"
  code, out = _main(f"--workdir={run_dir}", "--mode=eval", "--removal=delete")
  assert code != 0 and out.strip().splitlines()[-1] == "error: --removal: only with --mode=edit"
  for flag, value in (("move_background", "stay"), ("uncovered", "black")):
    code, out = _main(f"--workdir={run_dir}", "--mode=eval", f"--{flag}={value}")
    assert code != 0 and out.strip().splitlines()[-1] == f"error: --{flag}: only with --mode=edit"
  assert _tree_digest(os.path.join(run_dir, "checkpoints")) == checkpoints
  with open(path, "rb") as f:
    assert f.read() == kept


@pytest.mark.slow
def test_scoring_path_and_one_edit_pictures(run_dir, tmp_path):
  config = load_config()
  checkpoints = _tree_digest(os.path.join(run_dir, "checkpoints"))
  # An untrained smoke model matches no object at IoU 0.5; at 0 every object has a slot, so
  # every edit of the first scene is rendered and scored.
  report = edit_eval.score_split(config, run_dir, max_scenes=1, overwrite=True, progress=False,
                            match_iou=0.0)
  num_objects = _objects_in_first_scene(config)
  assert report["remove"]["num_edits"] == num_objects and report["remove"]["num_skipped"] == 0
  assert report["settings"]["match_iou"] == 0.0
  for record in report["edits"]:
    if "figures" in record:
      f = record["figures"]
      assert 0 < f["changed_share"] < 1  # every edit changes part of the novel views
      assert all(f[k] is None or f[k] == f[k] for k in f)  # no NaN: null or a number
  pictures = os.listdir(os.path.join(run_dir, "edit", "test", "pictures"))
  assert {p.split("_")[2] for p in pictures} == {"remove", "move"}
  # The other removal scores the same edits, and says so.
  deleted = edit_eval.score_split(config, run_dir, max_scenes=1, overwrite=True, progress=False,
                                  match_iou=0.0, removal="delete")
  assert deleted["settings"]["removal"] == "delete"
  assert [r.get("slot") for r in deleted["edits"]] == [r.get("slot") for r in report["edits"]]
  # A move that leaves the background where it is scores the same edits, and says so; the
  # smoke model is trained with the locality constraint, so carrying names slot 0.
  stay = edit_eval.score_split(config, run_dir, max_scenes=1, overwrite=True, progress=False,
                               match_iou=0.0, move_background="stay", uncovered="black")
  assert stay["settings"]["move_background"] == "stay" and stay["settings"]["uncovered"] == "black"
  assert report["settings"]["background_slot"] == (0 if config.train.locality_steps > 0 else None)
  assert [r.get("slot") for r in stay["edits"]] == [r.get("slot") for r in report["edits"]]
  # One edit of chosen scenes: pictures and an orbit, no metrics file touched.
  metrics_path = os.path.join(run_dir, "edit", "test", "edit_metrics.json")
  with open(metrics_path, "rb") as f:
    kept = f.read()
  lines = edit_eval.run(config, run_dir, split="test", scenes="1", remove_slot=None,
                        move_slot=2, by="1.5,0,0", checkpoint="", params="average",
                        max_scenes=None, overwrite=False, orbit_frames=3)
  png = os.path.join(run_dir, "edit", "test", "scene_0001_move_s2.png")
  assert png in lines and os.path.getsize(png) > 0
  assert os.path.getsize(png.replace(".png", "_orbit.gif")) > 0
  with open(metrics_path, "rb") as f:
    assert f.read() == kept
  assert _tree_digest(os.path.join(run_dir, "checkpoints")) == checkpoints
