"""The benchmark's reading of an accelerator's peak memory (experiments/bench_common.py)."""

import os
import sys

import jax

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import bench_common  # noqa: E402


class _Device:
  def __init__(self, stats):
    self._stats = stats

  def memory_stats(self):
    return self._stats


def test_device_peak_bytes_reads_the_allocators_peak_and_none_where_there_is_none():
  # What a GPU backend reports (keys as jax's GPU client names them), and backends without stats.
  gpu = _Device({"bytes_in_use": 7, "peak_bytes_in_use": 3 * 2**30 + 5, "bytes_limit": 2**36})
  assert bench_common.device_peak_bytes(gpu) == 3 * 2**30 + 5
  assert bench_common.device_peak_bytes(_Device(None)) is None
  assert bench_common.device_peak_bytes(_Device({"bytes_in_use": 7})) is None
  assert bench_common.device_peak_bytes(object()) is None  # no memory_stats at all
  # This machine's XLA:CPU device keeps no allocator statistics.
  cpu = jax.local_devices()[0]
  if cpu.platform == "cpu":
    assert bench_common.device_peak_bytes(cpu) is None
