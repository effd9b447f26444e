"""experiments/suite_accounting.py: its sums on hand-made records, and its hook through the command
line on two test files (one jits in an xdist worker, one in a process its test starts)."""

import json
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(REPO, "experiments"))
import suite_accounting  # noqa: E402

from slotlifter_jax import provenance  # noqa: E402

SCRIPT = os.path.join(REPO, "experiments", "suite_accounting.py")


def _row(trace=0.0, lower=0.0, compile=0.0, cache_read=0.0):
  return dict(trace=trace, lower=lower, compile=compile, cache_read=cache_read)


def test_summary_adds_phases_per_file_and_cpu_of_started_processes():
  records = [
      # a worker: its CPU is the workers', its phases go to the tests that ran in it
      dict(start_test="", cpu_s=100.0, per_test={
          "tests/test_a.py::test_one": _row(trace=1.0, compile=4.0),
          "tests/test_a.py::test_two": _row(trace=0.5, lower=0.25),
          "tests/test_b.py::test_x": _row(cache_read=2.0)}),
      # a process test_b started: its CPU is test_b's subprocess CPU
      dict(start_test="tests/test_b.py::test_x (call)", cpu_s=30.0, per_test={
          "tests/test_b.py::test_x": _row(trace=3.0, compile=8.0)}),
  ]
  summary = suite_accounting.summarise(records)
  assert summary["totals"] == dict(trace=4.5, lower=0.25, compile=12.0, cache_read=2.0,
                                   subprocess_cpu_s=30.0, worker_cpu_s=100.0)
  a, b = summary["files"]["tests/test_a.py"], summary["files"]["tests/test_b.py"]
  assert a == dict(trace=1.5, lower=0.25, compile=4.0, cache_read=0.0, subprocess_cpu_s=0.0)
  assert b == dict(trace=3.0, lower=0.0, compile=8.0, cache_read=2.0, subprocess_cpu_s=30.0)
  assert list(summary["files"]) == ["tests/test_b.py", "tests/test_a.py"]  # the larger first


def test_the_written_record_carries_provenance():
  # What --out receives, without running a suite: the summary and where it came from.
  summary = suite_accounting.summarise([])
  record = suite_accounting.result_record(["-q"], 0, 30.0, [{}, {}], summary, wall_s=31.0)
  assert record["pytest_args"] == ["-q"] and record["wall_s"] == 30.0
  assert record["processes"] == 2 and record["totals"] == summary["totals"]
  prov = provenance.of(record)
  assert prov["wall_s"] == 31.0 and prov["config"] is None
  assert {"git_commit", "cpu_model", "platform", "jax"} <= set(prov)
  json.dumps(record, allow_nan=False)


@pytest.mark.slow
def test_command_line_counts_a_jit_in_an_xdist_worker_and_in_a_started_process(tmp_path):
  jit = "import jax, jax.numpy as jnp; jax.jit(lambda x: jnp.sin(x) * 2)(jnp.ones(5))"
  (tmp_path / "test_in_worker.py").write_text(f"def test_jit():\n  exec({jit!r}, {{}})\n")
  (tmp_path / "test_in_subprocess.py").write_text(
      "import subprocess, sys\n"
      f"def test_jit():\n  subprocess.run([sys.executable, '-c', {jit!r}], check=True)\n")
  out = tmp_path / "accounting.json"
  # No compilation cache, so that both processes compile: the counts below then cannot be 0.
  env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
  env["JAX_ENABLE_COMPILATION_CACHE"] = "false"
  args = [sys.executable, SCRIPT, f"--out={out}", "--", "-q", "-n", "1", "-p", "no:cacheprovider",
          "--rootdir", str(tmp_path), str(tmp_path)]
  r = subprocess.run(args, capture_output=True, text=True, cwd=tmp_path, env=env)
  assert r.returncode == 0, r.stdout + r.stderr
  result = json.loads(out.read_text())
  assert result["returncode"] == 0 and result["processes"] >= 3  # controller, worker, started
  assert provenance.of(result)["wall_s"] >= result["wall_s"]
  rows = {name.rsplit("/", 1)[-1]: row for name, row in result["files"].items()}
  # The worker's own jit: only the worker's record can hold it.
  worker = rows["test_in_worker.py"]
  assert worker["trace"] > 0 and worker["lower"] > 0 and worker["compile"] > 0
  assert worker["subprocess_cpu_s"] == 0
  started = rows["test_in_subprocess.py"]
  assert started["compile"] > 0 and started["subprocess_cpu_s"] > 0
  # An existing file is kept: one line, nonzero exit.
  again = subprocess.run(args, capture_output=True, text=True, cwd=tmp_path, env=env)
  assert again.returncode != 0 and "exists; choose another file" in again.stderr
  assert json.loads(out.read_text()) == result
