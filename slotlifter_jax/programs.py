"""The jitted programs of one process, shared by every caller that asks for the same one.

`jax.jit` keeps its traces and compilations on the function object, so a program built anew (a
fresh closure per call of `train_step.make_train_step`, per `Validator`, per init) is traced and
compiled again even when it is the same program. Tracing the smoke model's train step alone takes
5–6 s on the 2-core CPU, and the persistent compilation cache only spares the XLA compile, not
the trace. A restarted attempt in one process (slotlifter_jax/restarts.py) and the tests, which
train, interrupt and resume several runs of one config in a process, paid it every time.

`shared(key, build)` returns the function built for an equal key before, else builds it. A key
names everything the program closes over: the model (a frozen dataclass, hashable and compared by
value), the config's values (`config_key`), meshes and static settings. Only the most recent
programs are kept (`MAX_PROGRAMS`), which bounds the memory their executables hold.
"""

from __future__ import annotations

import collections
import json
from typing import Any, Callable, Hashable

MAX_PROGRAMS = 16

_programs: collections.OrderedDict = collections.OrderedDict()


def config_key(config) -> str:
  """A ConfigDict's values as one canonical string: equal configs, equal keys."""
  return json.dumps(config.to_dict(), sort_keys=True, default=repr)


def shared(key: Hashable, build: Callable[[], Any]) -> Any:
  """The value built for `key` in this process (most recently used first), else `build()`."""
  if key in _programs:
    _programs.move_to_end(key)
    return _programs[key]
  value = _programs[key] = build()
  while len(_programs) > MAX_PROGRAMS:
    _programs.popitem(last=False)
  return value
