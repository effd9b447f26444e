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


_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 9R14
flags\t\t: fpu sse sse2 avx fma avx2 avx512f avx512bw avx512_bf16 avx512_vnni
bogomips\t: 5200.00

processor\t: 1
model name\t: some other name
flags\t\t: fpu sse amx_tile
"""


def test_cpu_info_names_the_first_processors_model_and_its_vector_extensions():
  info = bench_common.cpu_info(_CPUINFO)
  assert info == {"cpu_model": "AMD EPYC 9R14",
                  "cpu_extensions": ["avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni"]}
  # "avx512bw" is not on the list and "avx" is only a prefix of listed names: neither counts.
  assert bench_common.cpu_info("") == {"cpu_model": "", "cpu_extensions": []}
  assert bench_common.cpu_info("model name : X\nflags : sse2 avx2\n")["cpu_extensions"] == ["avx2"]
