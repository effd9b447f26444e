"""Tests of slotlifter_jax.emergence and slotlifter_jax/tools/plot_curves.py on hand-written metrics
logs.

Every expected value below is read off the constructed log (steps, wall_s, time), not computed by
the code under test.
"""

import json
import logging
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from slotlifter_jax import emergence

PLOT_CURVES = [sys.executable, "-m", "slotlifter_jax.tools.plot_curves"]


def _train(step, time, wall_s=None):
  row = {"step": step, "kind": "train", "time": time, "loss": 0.1, "psnr": 15.0 + step / 1000,
         "keep_ratio": 0.5, "slot_noise_sigma": 0.2, "locality": 1.0, "lr_backbone": 1e-5}
  return row if wall_s is None else {**row, "wall_s": wall_s}


def _val(step, time, fg_ari, wall_s=None, **extra):
  row = {"step": step, "kind": "val", "time": time, "fg_ari": fg_ari, "nv_ari": fg_ari + 0.1,
         "attn_fg_ari": fg_ari / 2, "psnr_novel": 20.0, **extra}
  return row if wall_s is None else {**row, "wall_s": wall_s}


def _write(path, rows, tail=""):
  """rows as JSON lines (json.dumps writes NaN as the training writer does), then `tail` raw."""
  with open(path, "w") as f:
    f.writelines(json.dumps(r) + "\n" for r in rows)
    f.write(tail)
  return str(path)


# FG-ARI crosses 0.5 at step 3000 (1800 s; previous 2000 at 1200 s), dips to 0.48 at 4000, crosses
# 0.8 at step 5000 (3000 s; previous 4000 at 2400 s) and ends at 0.79; the best is 0.81 at 5000.
# The time stamps are 1000 s ahead of wall_s and jittered, so using them instead would show.
LOG = [
    _train(100, 1000.0, wall_s=60.0),
    _val(1000, 1700.0, 0.20, wall_s=600.0),
    _train(1100, 1710.0, wall_s=660.0),
    _val(2000, 2201.0, 0.45, wall_s=1200.0),
    _val(3000, 2799.0, 0.55, wall_s=1800.0),
    _val(4000, 3450.0, 0.48, wall_s=2400.0),
    _val(5000, 4010.0, 0.81, wall_s=3000.0),
    _val(6000, 4620.0, 0.79, wall_s=3600.0),
]


def test_curves_are_the_validation_records_in_step_order():
  c = emergence.curves(LOG)
  np.testing.assert_array_equal(c["step"], [1000, 2000, 3000, 4000, 5000, 6000])
  np.testing.assert_allclose(c["wall_s"], [600, 1200, 1800, 2400, 3000, 3600])
  np.testing.assert_allclose(c["minutes"], [10, 20, 30, 40, 50, 60])
  np.testing.assert_allclose(c["fg_ari"], [0.20, 0.45, 0.55, 0.48, 0.81, 0.79])
  np.testing.assert_allclose(c["attn_fg_ari"], [0.10, 0.225, 0.275, 0.24, 0.405, 0.395])
  np.testing.assert_allclose(c["psnr_novel"], [20.0] * 6)
  assert np.isnan(emergence.curves(LOG, keys=("mbo",))["mbo"]).all()  # absent key → NaN


def test_both_thresholds_first_crossing_counts():
  r = emergence.time_to_decomposition(LOG)
  assert r["key"] == "fg_ari" and r["wall_clock"] == "wall_s"
  assert r["num_validations"] == 6 and r["last_step"] == 6000
  half, high = r["crossings"]["0.5"], r["crossings"]["0.8"]
  # 0.55 at step 3000 counts although 4000 dips to 0.48 (a later re-crossing would not)
  assert (half["step"], half["wall_s"], half["minutes"], half["value"]) == (3000, 1800.0, 30.0, 0.55)
  assert half["previous"] == {"step": 2000, "wall_s": 1200.0, "minutes": 20.0}
  assert (high["step"], high["wall_s"], high["minutes"], high["value"]) == (5000, 3000.0, 50.0, 0.81)
  assert high["previous"] == {"step": 4000, "wall_s": 2400.0, "minutes": 40.0}
  assert r["best"] == {"step": 5000, "wall_s": 3000.0, "minutes": 50.0, "value": 0.81}
  lines = emergence.summary_lines(r)
  assert lines[0] == ("time to decomposition (FG-ARI ≥ 0.5): 30.0 min (step 3000, FG-ARI 0.55; "
                      "previous validation 2000 at 20.0 min)")
  assert lines[1].startswith("time to decomposition (FG-ARI ≥ 0.8): 50.0 min (step 5000")
  assert "best FG-ARI 0.81 at step 5000" in lines[2]
  assert not any("wall clock" in line for line in lines)  # every record has wall_s


def test_threshold_equal_to_value_counts_and_first_validation_has_no_previous():
  rows = [_val(1000, 5.0, 0.5, wall_s=90.0), _val(2000, 9.0, 0.8, wall_s=150.0)]
  r = emergence.time_to_decomposition(rows)
  assert r["crossings"]["0.5"]["step"] == 1000 and r["crossings"]["0.5"]["previous"] is None
  assert r["crossings"]["0.8"]["step"] == 2000
  assert r["crossings"]["0.8"]["previous"] == {"step": 1000, "wall_s": 90.0, "minutes": 1.5}
  assert "the first validation" in emergence.summary_lines(r)[0]


def test_threshold_never_reached_reports_the_best():
  r = emergence.time_to_decomposition(LOG, thresholds=(0.5, 0.9))
  assert r["crossings"]["0.5"]["step"] == 3000
  assert r["crossings"]["0.9"] is None
  assert r["best"]["step"] == 5000 and r["best"]["value"] == 0.81
  assert emergence.summary_lines(r)[1] == ("time to decomposition (FG-ARI ≥ 0.9): not reached by "
                                           "step 6000 (best FG-ARI 0.81 at step 5000)")
  # another key: NV-ARI is FG-ARI + 0.1 here, so it reaches 0.9 at step 5000 (0.91)
  nv = emergence.time_to_decomposition(LOG, key="nv_ari", thresholds=(0.9,))
  assert nv["crossings"]["0.9"]["step"] == 5000


def test_no_value_of_the_key_and_nan_values():
  rows = [_val(1000, 5.0, math.nan, wall_s=10.0), _val(2000, 9.0, 0.3, wall_s=20.0)]
  r = emergence.time_to_decomposition(rows)
  assert r["crossings"] == {"0.5": None, "0.8": None}
  assert r["best"]["step"] == 2000  # the NaN validation neither crosses nor is best
  r = emergence.time_to_decomposition(rows, key="mbo")
  assert r["best"] is None and "no validation record has a value of mbo" in \
      emergence.summary_lines(r)[0]
  empty = emergence.time_to_decomposition([_train(100, 1.0)])
  assert empty["num_validations"] == 0 and empty["crossings"]["0.5"] is None


def test_resume_last_record_of_a_repeated_step_wins():
  # killed after step 2000's validation; resumed from the step-1000 checkpoint, which logs 1100..
  # and step 2000 again with a lower FG-ARI, then 3000
  rows = [
      _train(100, 100.0, wall_s=50.0),
      _val(1000, 600.0, 0.20, wall_s=600.0),
      _train(1100, 700.0, wall_s=660.0),
      _val(2000, 1300.0, 0.60, wall_s=1200.0),
      _train(1100, 9000.0, wall_s=650.0),
      _val(2000, 9600.0, 0.40, wall_s=1250.0),
      _val(3000, 10200.0, 0.70, wall_s=1850.0),
  ]
  c = emergence.curves(rows)
  np.testing.assert_array_equal(c["step"], [1000, 2000, 3000])
  np.testing.assert_allclose(c["fg_ari"], [0.20, 0.40, 0.70])
  np.testing.assert_allclose(c["wall_s"], [600.0, 1250.0, 1850.0])
  half = emergence.time_to_decomposition(rows)["crossings"]["0.5"]
  assert (half["step"], half["wall_s"]) == (3000, 1850.0)  # not the abandoned 0.60 at 2000
  assert half["previous"]["wall_s"] == 1250.0
  train = emergence.latest_records(rows, "train")
  assert [(r["step"], r["wall_s"]) for r in train] == [(100, 50.0), (1100, 650.0)]


def test_resume_drops_records_past_the_resume_point_not_yet_repeated():
  # the killed attempt validated at 2000 and 3000; the resumed one (from 1000) has reached 2000 only
  rows = [_val(1000, 1.0, 0.2, wall_s=600.0), _val(2000, 2.0, 0.3, wall_s=1200.0),
          _val(3000, 3.0, 0.9, wall_s=1800.0), _val(2000, 4.0, 0.35, wall_s=1210.0)]
  c = emergence.curves(rows)
  np.testing.assert_array_equal(c["step"], [1000, 2000])
  np.testing.assert_allclose(c["fg_ari"], [0.2, 0.35])
  assert emergence.time_to_decomposition(rows)["crossings"]["0.8"] is None


def test_time_fallback_without_wall_s():
  # the clock starts at the first record (a train record at time 1000), not the first validation
  rows = [_train(100, 1000.0), _val(1000, 1300.0, 0.3), _val(2000, 1600.0, 0.6),
          _val(3000, 1900.0, 0.85)]
  c = emergence.curves(rows)
  np.testing.assert_allclose(c["wall_s"], [300.0, 600.0, 900.0])
  np.testing.assert_allclose(c["minutes"], [5.0, 10.0, 15.0])
  r = emergence.time_to_decomposition(rows)
  assert r["wall_clock"] == "time"
  assert (r["crossings"]["0.5"]["step"], r["crossings"]["0.5"]["wall_s"]) == (2000, 600.0)
  assert r["crossings"]["0.5"]["previous"]["wall_s"] == 300.0
  assert (r["crossings"]["0.8"]["step"], r["crossings"]["0.8"]["minutes"]) == (3000, 15.0)
  assert any(line.startswith("wall clock: time") for line in emergence.summary_lines(r))
  # a log begun without wall_s and resumed with it: each record uses what it has
  mixed = rows + [_val(4000, 5000.0, 0.9, wall_s=1000.0)]
  assert emergence.time_to_decomposition(mixed)["wall_clock"] == "mixed"
  np.testing.assert_allclose(emergence.curves(mixed)["wall_s"], [300.0, 600.0, 900.0, 1000.0])


def test_load_records_skips_a_truncated_last_line(tmp_path, caplog):
  path = _write(tmp_path / "metrics.jsonl", LOG[:4], tail='{"step": 3000, "kind": "val", "fg_a')
  with caplog.at_level(logging.WARNING):
    rows = emergence.load_records(path)
  assert [r["step"] for r in rows] == [100, 1000, 1100, 2000]
  assert any("line 5" in r.getMessage() and "truncated" in r.getMessage() for r in caplog.records)


def test_load_records_malformed_middle_line_raises_with_its_number(tmp_path):
  path = _write(tmp_path / "metrics.jsonl", LOG[:2], tail="not json\n" + json.dumps(LOG[2]) + "\n")
  with pytest.raises(ValueError, match=r"metrics\.jsonl line 3"):
    emergence.load_records(path)
  # valid JSON without a step is no record either
  path = _write(tmp_path / "other.jsonl", [LOG[0], {"kind": "val"}, LOG[1]])
  with pytest.raises(ValueError, match=r"other\.jsonl line 2"):
    emergence.load_records(path)


def test_load_records_keeps_a_resumed_record_appended_to_a_truncated_one(tmp_path, caplog):
  # the writer appends: a resumed run's first record lands on the killed run's truncated line
  text = "".join(json.dumps(r) + "\n" for r in LOG[:2]) + '{"step": 1100, "kind": "tr'
  text += json.dumps(LOG[2]) + "\n\n" + json.dumps(LOG[3]) + "\n"  # and a blank line
  (tmp_path / "metrics.jsonl").write_text(text)
  with caplog.at_level(logging.WARNING):
    rows = emergence.load_records(str(tmp_path / "metrics.jsonl"))
  assert rows == LOG[:4]
  assert any("line 3" in r.getMessage() for r in caplog.records)


def test_write_emergence_valid_json_and_no_temporary_files(tmp_path):
  rows = LOG[:-1] + [_val(6000, 4620.0, 0.79, wall_s=3600.0, num_val_scenes=5,
                          ari=math.nan)]
  rows[1] = {**rows[1], "attn_fg_ari": math.nan}  # NaN as the training writer logs it
  _write(tmp_path / "metrics.jsonl", rows)
  result = emergence.write_emergence(str(tmp_path))
  assert sorted(os.listdir(tmp_path)) == ["emergence.json", "metrics.jsonl"]

  def no_nan(name):
    raise AssertionError(f"{name} in emergence.json")

  with open(tmp_path / "emergence.json") as f:
    data = json.load(f, parse_constant=no_nan)  # strict JSON: no NaN / Infinity
  assert data == result
  assert data["key"] == "fg_ari" and data["thresholds"] == [0.5, 0.8]
  assert data["crossings"]["0.5"]["step"] == 3000 and data["crossings"]["0.5"]["minutes"] == 30.0
  assert data["crossings"]["0.5"]["previous"]["step"] == 2000
  assert data["crossings"]["0.8"]["step"] == 5000 and data["crossings"]["0.8"]["wall_s"] == 3000.0
  assert data["best"]["value"] == 0.81 and data["best"]["step"] == 5000
  assert data["num_val_scenes"] == 5 and data["wall_clock"] == "wall_s"
  assert data["curves"]["step"] == [1000, 2000, 3000, 4000, 5000, 6000]
  assert data["curves"]["minutes"] == [10.0, 20.0, 30.0, 40.0, 50.0, 60.0]
  assert data["curves"]["attn_fg_ari"][0] is None
  assert data["curves"]["fg_ari"] == [0.20, 0.45, 0.55, 0.48, 0.81, 0.79]
  # NV-ARI (FG-ARI + 0.1: 0.55 at 2000) reaches 0.5 before FG-ARI does
  assert data["others"]["nv_ari"]["crossings"]["0.5"]["step"] == 2000
  assert data["others"]["attn_fg_ari"]["crossings"]["0.5"] is None  # at most 0.405
  assert data["summary"][0].startswith("time to decomposition (FG-ARI ≥ 0.5): 30.0 min")


def test_write_emergence_interrupted_write_keeps_the_old_file(tmp_path, monkeypatch):
  _write(tmp_path / "metrics.jsonl", LOG)
  emergence.write_emergence(str(tmp_path))
  before = (tmp_path / "emergence.json").read_text()

  def partial_dump(obj, f, **kwargs):
    f.write('{"key": "fg')
    raise KeyboardInterrupt

  monkeypatch.setattr(emergence.json, "dump", partial_dump)
  with pytest.raises(KeyboardInterrupt):
    emergence.write_emergence(str(tmp_path))
  assert (tmp_path / "emergence.json").read_text() == before
  assert sorted(os.listdir(tmp_path)) == ["emergence.json", "metrics.jsonl"]


@pytest.mark.parametrize("with_wall", [True, False])
def test_plot_curves_command_line(tmp_path, with_wall):
  rows = LOG if with_wall else [{k: v for k, v in r.items() if k != "wall_s"} for r in LOG]
  _write(tmp_path / "metrics.jsonl", rows)
  env = {**os.environ, "MPLBACKEND": "Agg"}
  result = subprocess.run([*PLOT_CURVES, str(tmp_path)], capture_output=True,
                          text=True, timeout=300, env=env, cwd=str(tmp_path))
  assert result.returncode == 0, result.stderr
  png = tmp_path / "curves.png"
  assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  assert png.stat().st_size < 500_000
  # with wall_s: 1800 s; without: time 2799 − 1000 (the first record) = 1799 s = 30.0 min too
  assert "time to decomposition (FG-ARI ≥ 0.5): 30.0 min (step 3000" in result.stdout
  assert ("wall clock: time" in result.stdout) != with_wall
  # a metrics file named directly, with an explicit output
  out = tmp_path / "explicit.png"
  result = subprocess.run([*PLOT_CURVES, str(tmp_path / "metrics.jsonl"), str(out)],
                          capture_output=True, text=True, timeout=300, env=env)
  assert result.returncode == 0, result.stderr
  assert out.stat().st_size > 0


def test_plot_curves_names_a_missing_log_in_one_line_and_writes_nothing(tmp_path):
  result = subprocess.run([*PLOT_CURVES, str(tmp_path / "no_run")],
                          capture_output=True, text=True, timeout=300, cwd=str(tmp_path))
  assert result.returncode == 1
  assert result.stderr.strip() == (f"error: {tmp_path / 'no_run'}: neither a metrics .jsonl file "
                                   f"nor a run folder with metrics.jsonl")
  assert os.listdir(tmp_path) == []
