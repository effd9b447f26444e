"""Shared test setup.

- The embedded-data cache goes to a per-session temporary folder.
- One persistent XLA compilation cache for the whole session (this process and the subprocesses
  the tests start): the smoke model is compiled by many tests with the same shapes, and on a 2-core
  CPU compilation, not execution, is what most of these tests spend their time on.
- XLA's CPU backend compiles at -O0, with its older loop emitters, for the whole session,
  subprocesses included.
- The heaviest files are collected first (HEAVIEST_FIRST).
- Whole files that build and compile models are marked slow (SLOW_FILES): `pytest -m "not slow"`
  is the fast tier.
"""

import os
import tempfile

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:  # set before any test module imports jax
  os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="slotlifter_xla_cache_")
  os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
  os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"

# The suite compiles far more than it computes (smoke models, a few steps each), and LLVM's passes
# are most of a compilation: at -O0 the smoke train step compiles in 60 % of the default time and
# still runs in milliseconds (experiments/compile_levels.py). The code is IEEE arithmetic either
# way (XLA's CPU backend has no fast-math), but the last bits can differ from the default level's,
# so no test compares against numbers saved from a run; resume and multi-device tests compare runs
# of this same setting.
# Subprocesses inherit it through the environment.
_LEVEL = "--xla_backend_optimization_level"
if _LEVEL not in os.environ.get("XLA_FLAGS", ""):
  os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_LEVEL}=0".strip()
# XLA:CPU's older loop emitters instead of its MLIR fusion emitters: at -O0 the smoke train step
# compiles in 14.0 s instead of 21.1 s (2026-12-01's AVX2 host). Not for training: at the default
# level they compile the `scene` step in 82–94 s instead of 30–34 s and run it no faster
# (experiments/journal/2026-11.md, "Compile time").
_EMITTERS = "--xla_cpu_use_fusion_emitters"
if _EMITTERS not in os.environ["XLA_FLAGS"]:
  os.environ["XLA_FLAGS"] += f" {_EMITTERS}=false"

import pytest  # noqa: E402

# pytest-xdist (`--dist loadfile`) hands out whole files, in collection order, to whichever worker
# asks next. Its default order (most tests first) put the few files that train whole runs last,
# where one of them kept a worker busy for minutes while the others had nothing left to do. Started
# first (heaviest first: longest-processing-time scheduling), they run beside the many light files,
# which fill the gaps. Order from the per-file sums of `pytest --durations=60` on the 2-core CPU
# (2026-11-27); files not listed follow in their usual order. pyproject.toml passes
# --no-loadscope-reorder so that xdist keeps this order.
HEAVIEST_FIRST = (
    "test_train_resume.py", "test_train.py", "test_cli.py", "test_evaluate.py",
    "test_distributed.py", "test_device_sampler.py", "test_model.py", "test_model_options.py",
    "test_data_parallel.py", "test_bf16.py", "test_decoder.py", "test_restarts.py",
    "test_fork_run.py", "test_averaging.py", "test_adaptive.py", "test_study.py",
)


# The fast tier (`pytest -m "not slow"`, the README's day-to-day command) leaves out, besides the
# tests marked @pytest.mark.slow, every test of the files below: each trains, evaluates or compiles
# whole models (smoke-sized, but a compile is 10–60 s of one core at -O0), or starts processes that
# do. Chosen from the per-file compile and subprocess times of experiments/suite_accounting.py
# (experiments/results/suite_accounting_cpu_20261202_amx.json: every file here spends 10 s or more
# there) and, for files it predates, from what they build. The full suite (`pytest -q`, CI) runs
# them all.
SLOW_FILES = frozenset(HEAVIEST_FIRST) | {
    "test_notebook.py", "test_generator.py", "test_encoder.py",
    "test_programs.py", "test_slot_attention.py", "test_study_workdirs.py",
    "test_suite_accounting.py", "test_suite_order.py", "test_ab_step.py",
}


def pytest_collection_modifyitems(items):
  rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
  items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: ties keep their order
  for item in items:
    if item.path.name in SLOW_FILES:
      item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session", autouse=True)
def _data_cache(tmp_path_factory):
  old = os.environ.get("SLOTLIFTER_DATA_CACHE")
  os.environ["SLOTLIFTER_DATA_CACHE"] = str(tmp_path_factory.mktemp("data_cache"))
  yield
  if old is None:
    os.environ.pop("SLOTLIFTER_DATA_CACHE", None)
  else:
    os.environ["SLOTLIFTER_DATA_CACHE"] = old
