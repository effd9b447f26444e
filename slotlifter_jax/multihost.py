"""Several JAX processes training one run (`python -m slotlifter_jax.main --distributed`).

Every process runs the same loop on the same replicated train state; the mesh spans the devices of
all processes and each process feeds only the scenes of the global batch that fall on its own
devices (train.py, `local_rows`). Files are written by process 0 alone (metrics, TensorBoard,
pictures, config.json, emergence.json); orbax checkpoints are saved and restored by every process
together, orbax writing each file once. With one process every helper here is a no-op or the
identity, so a single-process run computes and writes exactly what it did before.
"""

from __future__ import annotations

import itertools
from typing import Callable, TypeVar

import jax
import numpy as np

_barriers = itertools.count()
T = TypeVar("T")


def is_primary() -> bool:
  """True on the process that writes the run's files (process 0)."""
  return jax.process_index() == 0


def barrier(name: str) -> None:
  """Waits until every process reaches here (nothing with one process). Names need not be unique:
  a counter makes each call's key unique, and every process makes the same calls in order."""
  if jax.process_count() == 1:
    return
  from jax.experimental import multihost_utils
  multihost_utils.sync_global_devices(f"slotlifter:{name}:{next(_barriers)}")


def primary_first(fn: Callable[[], T], name: str) -> T:
  """`fn()` on process 0 and then, once it has returned there, on the others: e.g. generating an
  absent embedded data set, which the others then find instead of generating it in the same folder.
  With one process, `fn()`."""
  if jax.process_count() == 1:
    return fn()
  out = fn() if is_primary() else None
  barrier(name)
  return out if is_primary() else fn()


def max_over_processes(value: int) -> int:
  """The largest of every process's `value` (the value itself with one process)."""
  if jax.process_count() == 1:
    return int(value)
  from jax.experimental import multihost_utils
  return int(np.max(multihost_utils.process_allgather(np.int32(value))))


def local_rows(sharding: jax.sharding.Sharding, size: int) -> np.ndarray:
  """The indices along the leading axis (of length `size`) that `sharding` places on this process's
  devices, in the order `jax.make_array_from_process_local_data` expects its local data: the
  process's shards by increasing start."""
  spans = {(s.start or 0, size if s.stop is None else s.stop)
           for (s, *_) in sharding.addressable_devices_indices_map((size,)).values()}
  return np.concatenate([np.arange(a, b) for a, b in sorted(spans)]).astype(np.int64)


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> None:
  """jax.distributed.initialize with the given settings; those left None come from the
  environment (JAX_COORDINATOR_ADDRESS, or a SLURM / Open MPI / TPU job: jax detects them)."""
  jax.distributed.initialize(coordinator_address=coordinator_address or None,
                             num_processes=num_processes, process_id=process_id)
