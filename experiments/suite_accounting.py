"""Where the test suite's time goes: tracing, lowering, XLA compiles and cache reads, per test file.

    python experiments/suite_accounting.py --out=experiments/results/suite_accounting_cpu.json
    python experiments/suite_accounting.py --out=/tmp/a.json -- -n 0 tests/test_distributed.py

Runs pytest (the arguments after `--`; by default the README's `-q`) with a `sitecustomize` hook on
PYTHONPATH, so that every Python process of the run (the xdist workers and each process a test
starts, which inherit the environment) records, under the test that was running:
- trace: seconds in top-level `jax.jit` tracing (nested jits are inside their parent's time);
- lower: seconds lowering jaxprs to MLIR (`/jax/core/compile/jaxpr_to_mlir_module_duration`);
- compile: seconds in XLA compiles (`/jax/core/compile/backend_compile_duration`), i.e. misses of
  the persistent compilation cache;
- cache_read: seconds reading executables from that cache;
and, for each process a test started, its CPU seconds. All are wall seconds inside one process
except the CPU figure, so on a busy machine they overstate the CPU a phase used; they tell where
the time goes, not how fast a phase is. The hook reads a JAX internal (`jax._src.pjit.
_trace_for_jit`); with a JAX that renames it, trace stays 0 and the other columns still count.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import subprocess
import sys
import tempfile
import time

HOOK = r'''
import atexit, json, os, resource, sys, threading, time
_dir = os.environ["SUITE_ACCOUNTING_DIR"]
_start_test = os.environ.get("PYTEST_CURRENT_TEST", "")
_per = {}
_written = [0.0]
def _add(kind, seconds):
  test = os.environ.get("PYTEST_CURRENT_TEST", _start_test).rsplit(" ", 1)[0]
  row = _per.setdefault(test, dict.fromkeys(("trace", "lower", "compile", "cache_read"), 0.0))
  row[kind] += seconds
  if time.time() - _written[0] > 2.0:  # xdist's workers can end without atexit or os._exit
    _report()
def _install(pjit):
  from jax._src import monitoring
  depth = threading.local()
  original = getattr(pjit, "_trace_for_jit", None)
  if original is not None:
    def traced(*args, **kwargs):
      d = getattr(depth, "d", 0)
      depth.d, start = d + 1, time.perf_counter()
      try:
        return original(*args, **kwargs)
      finally:
        depth.d = d
        if d == 0:
          _add("trace", time.perf_counter() - start)
    pjit._trace_for_jit = traced
  events = {"jaxpr_to_mlir_module_duration": "lower", "backend_compile_duration": "compile",
            "cache_retrieval_time_sec": "cache_read"}
  def listener(event, duration, **_):
    kind = events.get(event.rsplit("/", 1)[-1])
    if kind:
      _add(kind, duration)
  monitoring.register_event_duration_secs_listener(listener)
class _AfterPjit:  # installs the hook once jax._src.pjit has been executed, importing nothing
  def find_spec(self, name, path=None, target=None):
    if name != "jax._src.pjit":
      return None
    sys.meta_path.remove(self)
    import importlib.util
    spec = importlib.util.find_spec(name)
    run = spec.loader.exec_module
    def exec_module(module):
      run(module)
      _install(module)
    spec.loader.exec_module = exec_module
    return spec
sys.meta_path.insert(0, _AfterPjit())
def _report():
  usage = resource.getrusage(resource.RUSAGE_SELF)
  record = dict(pid=os.getpid(), argv=" ".join(sys.argv)[:300], start_test=_start_test,
                cpu_s=usage.ru_utime + usage.ru_stime, per_test=_per)
  path = os.path.join(_dir, f"{os.getpid()}.json")
  with open(path + ".tmp", "w") as f:
    json.dump(record, f)
  os.replace(path + ".tmp", path)
  _written[0] = time.time()
atexit.register(_report)
_exit = os._exit
def _exit_reporting(code):  # xdist's workers may leave through os._exit, which skips atexit
  try:
    _report()
  finally:
    _exit(code)
os._exit = _exit_reporting
'''

KINDS = ("trace", "lower", "compile", "cache_read")


def summarise(records: list[dict]) -> dict:
  """Per test file: the four phases (all processes) and the CPU of the processes tests started."""
  files = collections.defaultdict(lambda: dict.fromkeys(KINDS + ("subprocess_cpu_s",), 0.0))
  totals = dict.fromkeys(KINDS + ("subprocess_cpu_s", "worker_cpu_s"), 0.0)
  for r in records:
    started_by = r["start_test"].rsplit(" ", 1)[0].split("::")[0]
    if started_by:  # a process a test started (a worker starts before any test)
      files[started_by]["subprocess_cpu_s"] += r["cpu_s"]
      totals["subprocess_cpu_s"] += r["cpu_s"]
    else:
      totals["worker_cpu_s"] += r["cpu_s"]
    for test, row in r["per_test"].items():
      name = test.split("::")[0] or "(outside a test)"
      for kind in KINDS:
        files[name][kind] += row[kind]
        totals[kind] += row[kind]
  ordered = dict(sorted(files.items(), key=lambda kv: -sum(kv[1].values())))
  return dict(totals=totals, files=ordered)


def result_record(pytest_args: list[str], returncode: int, wall: float, records: list[dict],
                  summary: dict, *, wall_s: float) -> dict:
  """The JSON --out receives: the pytest call, its wall seconds, the processes and summarise()'s
  totals and files, with the provenance record of this call (commit, machine, jax version; no
  config: the suite builds its own)."""
  from slotlifter_jax import provenance
  return dict(pytest_args=pytest_args, returncode=returncode, wall_s=wall,
              processes=len(records), **summary,
              **{provenance.KEY: provenance.collect(None, wall_s=wall_s)})


def main(argv=None):
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out", required=True, help="JSON file to write (refuses to overwrite)")
  parser.add_argument("--top", type=int, default=25, help="files to print")
  parser.add_argument("pytest_args", nargs="*", default=["-q"])
  args = parser.parse_args(argv)
  t_start = time.time()
  if os.path.exists(args.out):
    parser.error(f"--out={args.out}: exists; choose another file")
  with tempfile.TemporaryDirectory(prefix="suite_accounting_") as tmp:
    hook_dir, record_dir = os.path.join(tmp, "hook"), os.path.join(tmp, "records")
    os.makedirs(hook_dir)
    os.makedirs(record_dir)
    with open(os.path.join(hook_dir, "sitecustomize.py"), "w") as f:
      f.write(HOOK)
    env = dict(os.environ, SUITE_ACCOUNTING_DIR=record_dir,
               PYTHONPATH=os.pathsep.join(p for p in (hook_dir, os.environ.get("PYTHONPATH"))
                                          if p))
    start = time.time()
    rc = subprocess.call([sys.executable, "-m", "pytest", *args.pytest_args], env=env)
    wall = time.time() - start
    records = [json.load(open(p)) for p in sorted(glob.glob(os.path.join(record_dir, "*.json")))]
  summary = summarise(records)
  result = result_record(args.pytest_args, rc, wall, records, summary,
                         wall_s=time.time() - t_start)
  t = summary["totals"]
  print(f"pytest {' '.join(args.pytest_args)}: rc {rc}, {wall:.0f} s wall, {len(records)} processes")
  print("totals (s): " + ", ".join(f"{k} {v:.0f}" for k, v in t.items()))
  print(f"{'file':45s} " + " ".join(f"{k:>10s}" for k in KINDS + ("sub_cpu",)))
  for name, row in list(summary["files"].items())[:args.top]:
    print(f"{name:45s} " + " ".join(f"{row[k]:10.1f}" for k in KINDS + ("subprocess_cpu_s",)))
  os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
  with open(args.out, "w") as f:
    json.dump(result, f, indent=1)
  print(f"wrote {args.out}")
  return rc


if __name__ == "__main__":
  sys.exit(main())
