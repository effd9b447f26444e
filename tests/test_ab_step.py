"""The paired step timing of two checkouts (experiments/ab_step.py): its summary and its refusals."""

import json
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import ab_step  # noqa: E402
from slotlifter_jax import provenance  # noqa: E402

SCRIPT = os.path.join(REPO, "experiments", "ab_step.py")


def test_paired_summary_takes_each_rounds_median_and_the_ratio_within_rounds():
  # The host slows down by 2× in the second round; within each round head is 0.8× base.
  base = [[1.0, 1.2, 0.9], [2.0, 2.2, 1.8]]
  head = [[0.8, 0.7, 0.9], [1.6, 1.5, 1.7]]
  s = ab_step.paired_summary(base, head)
  assert s["base_round_s"] == [1.0, 2.0]
  assert s["head_round_s"] == [0.8, 1.6]
  assert s["ratio_median"] == pytest.approx(0.8)
  assert s["ratio_min"] == pytest.approx(0.8) and s["ratio_max"] == pytest.approx(0.8)
  # Pooled medians over all six steps of a side: base 1.5 (between 1.2 and 1.8), head 1.2 (between 0.9 and 1.5).
  assert s["base_step_s"] == pytest.approx(1.5)
  assert s["head_step_s"] == pytest.approx(1.2)
  assert s["rounds"] == 2


def test_paired_summary_refuses_unequal_rounds():
  with pytest.raises(ValueError, match="same number"):
    ab_step.paired_summary([[1.0]], [[1.0], [1.0]])
  with pytest.raises(ValueError, match="same number"):
    ab_step.paired_summary([], [])


def test_a_config_pair_names_each_sides_configuration():
  assert ab_step.config_pair("scene") == ("scene", "scene")
  assert ab_step.config_pair("scene:scene_fold") == ("scene", "scene_fold")
  for bad in ("scene:", ":scene", "a:b:c"):
    with pytest.raises(ValueError, match="neither NAME nor BASE:HEAD"):
      ab_step.config_pair(bad)


def test_the_written_record_carries_provenance():
  # What --out receives, without compiling a step: the results and where they came from.
  results = [dict(config="scene", base_step_s=1.0, head_step_s=0.9)]
  record = ab_step.result_record(results, base="HEAD~1", head=".", wall_s=12.5)
  assert record["results"] == results and (record["base"], record["head"]) == ("HEAD~1", ".")
  assert "cpu_model" in record and "date" in record
  prov = provenance.of(record)
  assert prov["wall_s"] == 12.5 and prov["config"] is None  # each side's configs are its own
  assert {"git_commit", "cpu_model", "platform", "jax"} <= set(prov)
  json.dumps(record, allow_nan=False)


def _run(*args):
  return subprocess.run([sys.executable, SCRIPT, *args], capture_output=True, text=True,
                        cwd=REPO, timeout=120)


def test_the_command_refuses_an_existing_out_file_and_leaves_it(tmp_path):
  out = tmp_path / "ab.json"
  out.write_text("earlier results")
  proc = _run("--configs=scene", f"--out={out}")
  assert proc.returncode != 0
  assert "exists; not overwritten" in proc.stderr
  assert out.read_text() == "earlier results"


@pytest.mark.parametrize("args, message", [
    (["--configs=nope"], "unknown ['nope']"),
    (["--configs=scene:nope"], "unknown ['nope']"),
    (["--base=no-such-revision-or-folder"], "neither a directory nor a git revision"),
])
def test_the_command_names_a_bad_flag(tmp_path, args, message):
  out = tmp_path / "ab.json"
  proc = _run(*args, f"--out={out}")
  assert proc.returncode != 0
  assert message in proc.stderr
  assert not out.exists()
