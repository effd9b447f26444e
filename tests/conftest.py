"""Shared test setup.

- The embedded-data cache goes to a per-session temporary folder.
- One persistent XLA compilation cache for the whole session (this process and the subprocesses
  the tests start): the smoke model is compiled by many tests with the same shapes, and on a 2-core
  CPU compilation, not execution, is what most of these tests spend their time on.
"""

import os
import tempfile

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:  # set before any test module imports jax
  os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="slotlifter_xla_cache_")
  os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
  os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"

import pytest  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def _data_cache(tmp_path_factory):
  old = os.environ.get("SLOTLIFTER_DATA_CACHE")
  os.environ["SLOTLIFTER_DATA_CACHE"] = str(tmp_path_factory.mktemp("data_cache"))
  yield
  if old is None:
    os.environ.pop("SLOTLIFTER_DATA_CACHE", None)
  else:
    os.environ["SLOTLIFTER_DATA_CACHE"] = old
