"""slotlifter_jax/tools/by_object_count.py: an evaluation's per-scene metrics by object count."""

import math
import os
import subprocess
import sys

import pytest

import data_fixtures as fx
from slotlifter_jax.tools import by_object_count

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOOL = [sys.executable, "-m", "slotlifter_jax.tools.by_object_count"]


def test_groups_by_hand(tmp_path):
  # One-object scenes: fg_ari 1 (kept whole) and 0 (split): mean 0.5, sample std √0.5, s.e. 0.5.
  # Two-object scenes: fg_ari 0.6, 0.8, 0.7: mean 0.7, std 0.1, s.e. 0.1/√3; fg_ari_multi NaN on
  # the one-object scenes is left out of their group.
  folder = fx.write_eval(tmp_path / "e", {
      "a": {"num_objects": 1, "fg_ari": 1.0, "fg_ari_multi": math.nan},
      "b": {"num_objects": 2, "fg_ari": 0.6, "fg_ari_multi": 0.6},
      "c": {"num_objects": 1, "fg_ari": 0.0, "fg_ari_multi": math.nan},
      "d": {"num_objects": 2, "fg_ari": 0.8, "fg_ari_multi": 0.8},
      "e": {"num_objects": 2, "fg_ari": 0.7, "fg_ari_multi": 0.7}})
  _, rows = by_object_count.paired_eval.read_eval(folder)
  groups = by_object_count.group_by_count(rows, ["fg_ari", "fg_ari_multi"], source=folder)
  assert list(groups) == [1, 2]
  assert groups[1]["scenes"] == 2 and groups[2]["scenes"] == 3
  assert groups[1]["fg_ari"].mean == pytest.approx(0.5)
  assert groups[1]["fg_ari"].std == pytest.approx(math.sqrt(0.5))
  assert groups[1]["fg_ari_multi"].n == 0
  assert groups[2]["fg_ari"].mean == pytest.approx(0.7)
  table = by_object_count.format_table(groups, ["fg_ari", "fg_ari_multi"])
  assert "| 1 | 2 | 0.500 ± 0.500 | – |" in table
  assert f"| 2 | 3 | 0.700 ± {0.1 / math.sqrt(3):.3f} | 0.700 ± {0.1 / math.sqrt(3):.3f} |" in table


def test_command_line_and_errors(tmp_path):
  good = fx.write_eval(tmp_path / "good", {"a": {"num_objects": 3, "nv_ari": 0.9},
                                         "b": {"num_objects": 3, "nv_ari": 0.7}})
  out = subprocess.run(TOOL + [good, "--metrics=nv_ari"], cwd=REPO, capture_output=True,
                       text=True, check=True).stdout
  assert "| 3 | 2 | 0.800 ± 0.100 |" in out
  no_counts = fx.write_eval(tmp_path / "masks", {"a": {"nv_ari": 0.9}})
  r = subprocess.run(TOOL + [no_counts], cwd=REPO, capture_output=True, text=True)
  assert r.returncode == 2 and "no num_objects column" in r.stderr and "masks" in r.stderr
  r = subprocess.run(TOOL + [good, "--metrics=mbo"], cwd=REPO, capture_output=True, text=True)
  assert r.returncode == 2 and "no mbo column" in r.stderr
  r = subprocess.run(TOOL + [str(tmp_path / "missing")], cwd=REPO, capture_output=True, text=True)
  assert r.returncode == 2 and "not found" in r.stderr and r.stderr.count("\n") == 1
