"""slotlifter_jax/provenance.py: the record of where a result came from (config, commit, machine,
jax version, wall time), and that result files written before it existed still load."""

import glob
import json
import os
import shutil
import subprocess

import jax
import pytest

from slotlifter_jax import provenance
from slotlifter_jax.tools import metrics_table
from train_helpers import load_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")

_CPUINFO = ("processor\t: 0\nmodel name\t: Some CPU @ 2.0GHz\nflags\t\t: sse2 fma avx2 avx512f\n\n"
            "processor\t: 1\nmodel name\t: Another CPU\nflags\t\t: sse2\n")


def _git(cwd, *args):
  subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=cwd,
                 check=True, capture_output=True)


def test_cpu_model_flags_and_extensions_come_from_the_first_processor():
  assert provenance.cpu_info(_CPUINFO) == {"cpu_model": "Some CPU @ 2.0GHz",
                                           "cpu_extensions": ["avx2", "fma", "avx512f"]}
  assert provenance.cpu_flags(_CPUINFO) == ["avx2", "avx512f", "fma", "sse2"]
  assert provenance.cpu_flags("") == [] and provenance.cpu_info("")["cpu_model"] == ""


@needs_git
def test_git_commit_is_head_marked_dirty_by_tracked_changes_only(tmp_path):
  repo = tmp_path / "repo"
  repo.mkdir()
  _git(repo, "init", "-q")
  (repo / "a.txt").write_text("one\n")
  _git(repo, "add", "a.txt")
  _git(repo, "commit", "-q", "-m", "first")
  head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True,
                        text=True, check=True).stdout.strip()
  assert provenance.git_commit(str(repo)) == head
  (repo / "runs").mkdir()
  (repo / "runs" / "untracked.txt").write_text("a run folder\n")
  assert provenance.git_commit(str(repo)) == head  # untracked files do not count
  (repo / "a.txt").write_text("two\n")
  assert provenance.git_commit(str(repo)) == head + "-dirty"
  # A folder inside a checkout is not the checkout (a wheel installed into another repository).
  assert provenance.git_commit(str(repo / "runs")) is None
  assert provenance.git_commit(str(tmp_path)) is None  # no checkout at all


def test_collect_records_config_commit_machine_jax_and_wall_time():
  config = load_config()
  record = provenance.collect(config, wall_s=12.5)
  assert record["config"] == json.loads(config.to_json_best_effort())
  assert record["jax"] == jax.__version__
  assert record["platform"] == jax.devices()[0].platform and record["device_kind"]
  assert record["num_devices"] == jax.device_count()
  assert record["wall_s"] == 12.5
  assert record["cpu_extensions"] == [e for e in provenance.CPU_EXTENSIONS
                                      if e in record["cpu_flags"]]
  if shutil.which("git") and os.path.isdir(os.path.join(REPO, ".git")):
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()
    assert record["git_commit"] in (head, head + "-dirty")
  json.dumps(record, allow_nan=False)  # as metrics.json writes it
  assert provenance.collect()["config"] is None and provenance.collect()["wall_s"] is None


def test_non_finite_config_values_stay_writable():
  config = load_config()
  config.train.base_lr = float("inf")
  json.dumps(provenance.config_dict(config), allow_nan=False)


def test_result_files_load_with_and_without_a_record(tmp_path):
  old = sorted(glob.glob(os.path.join(REPO, "experiments", "results", "*_test_metrics.json")))
  assert old, "no metrics.json files under experiments/results"
  with open(old[0]) as f:
    data = json.load(f)
  assert provenance.of(data) == {}  # written before records existed
  metrics_table.read_metrics(old[0], ["fg_ari"])
  data[provenance.KEY] = provenance.collect(load_config(), wall_s=1.0)
  new = tmp_path / "metrics.json"
  new.write_text(json.dumps(data, allow_nan=False))
  assert metrics_table.read_metrics(str(new), ["fg_ari"])["fg_ari"] == pytest.approx(
      data["metrics"]["fg_ari"]["mean"])
  with open(new) as f:
    assert provenance.of(json.load(f))["wall_s"] == 1.0
