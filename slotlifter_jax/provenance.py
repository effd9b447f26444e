"""Where a result came from: the record every `--mode=eval` metrics.json and every benchmark JSON
carries under "provenance".

A number without its config, commit and machine cannot be compared with another one: the same
`scene` step took 2.4× as long on two hosts of one cloud, and a recipe changes between commits.
`collect` gathers

- `config`: the resolved config the result was computed with (as `config.json` stores it);
- `git_commit`: the commit of the checkout the code was imported from, with "-dirty" appended when
  tracked files differ from it; None when the package does not sit in a git checkout (an
  installed wheel) or git cannot be run;
- the machine: `cpu_model`, `cpu_flags` (all of /proc/cpuinfo's), `cpu_extensions` (those of
  CPU_EXTENSIONS, which change XLA:CPU's kernels), `platform` and `device_kind` of JAX's first
  device (the GPU's name on a GPU), `num_devices`, `cpu_count`;
- `jax`: jax's version; `python`: Python's;
- `wall_s`: the caller's wall time for the result (None when it gives none).

No JAX import at module level: benchmark drivers import this before choosing their XLA flags.
Readers take the record with `of(result)`, which is {} for files written before it existed.
"""

from __future__ import annotations

import json
import os
import platform as platform_lib
import subprocess
from typing import Any, Optional

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KEY = "provenance"

# Vector and matrix extensions that change XLA:CPU's kernels, so the same step can take 2.4× as
# long on two hosts of one cloud (experiments/journal/2026-11.md, "Train-step benchmark").
CPU_EXTENSIONS = ("avx2", "fma", "avx512f", "avx512_bf16", "avx512_vnni", "amx_tile", "amx_bf16")


def _cpuinfo_fields(cpuinfo: Optional[str]) -> dict[str, str]:
  if cpuinfo is None:
    try:
      with open("/proc/cpuinfo", encoding="utf-8") as f:
        cpuinfo = f.read()
    except OSError:
      cpuinfo = ""
  fields = {}
  for line in cpuinfo.splitlines():
    key, sep, value = line.partition(":")
    if sep and key.strip() not in fields:  # the first processor's entry
      fields[key.strip()] = value.strip()
  return fields


def cpu_info(cpuinfo: Optional[str] = None) -> dict:
  """The CPU's model name and which of CPU_EXTENSIONS it has, from /proc/cpuinfo's text (read
  when `cpuinfo` is None; empty on systems without it)."""
  fields = _cpuinfo_fields(cpuinfo)
  flags = set(fields.get("flags", "").split())
  return dict(cpu_model=fields.get("model name", ""),
              cpu_extensions=[e for e in CPU_EXTENSIONS if e in flags])


def cpu_flags(cpuinfo: Optional[str] = None) -> list[str]:
  """Every flag of the first processor in /proc/cpuinfo, sorted ([] without it)."""
  return sorted(set(_cpuinfo_fields(cpuinfo).get("flags", "").split()))


def _git(*args: str, cwd: str) -> Optional[str]:
  try:
    out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=30)
  except (OSError, subprocess.SubprocessError):
    return None
  return out.stdout.strip() if out.returncode == 0 else None


def git_commit(root: str = REPO) -> Optional[str]:
  """HEAD of the git checkout whose top level is `root`, + "-dirty" when tracked files differ
  from it (untracked files, such as run folders, do not count); None when `root` is not the top
  of a checkout (e.g. the package installed from a wheel lies inside another repository or none)."""
  top = _git("rev-parse", "--show-toplevel", cwd=root)
  if top is None or os.path.realpath(top) != os.path.realpath(root):
    return None
  commit = _git("rev-parse", "HEAD", cwd=root)
  if not commit:
    return None
  status = _git("status", "--porcelain", "--untracked-files=no", cwd=root)
  return commit + ("-dirty" if status else "")


def device_info() -> dict:
  """JAX's backend as this process sees it: platform, the first device's kind (the GPU's name on
  a GPU; the CPU's is `cpu_model`), the number of devices and jax's version."""
  import jax  # here, not at import: the caller may still be choosing XLA flags
  dev = jax.devices()[0]
  return dict(platform=dev.platform, device_kind=getattr(dev, "device_kind", ""),
              num_devices=jax.device_count(), jax=jax.__version__)


def config_dict(config: Any) -> Optional[dict]:
  """A ConfigDict (or a mapping) as plain JSON values, as DIR/config.json stores it."""
  if config is None:
    return None
  # A non-finite float stays readable as its name: metrics.json is written with allow_nan=False.
  if hasattr(config, "to_json_best_effort"):
    return json.loads(config.to_json_best_effort(), parse_constant=str)
  return json.loads(json.dumps(dict(config), default=str), parse_constant=str)


def collect(config: Any = None, *, wall_s: Optional[float] = None, root: str = REPO) -> dict:
  """The provenance record of a result computed with `config` in `wall_s` seconds (module doc)."""
  return dict(config=config_dict(config), git_commit=git_commit(root),
              **cpu_info(), cpu_flags=cpu_flags(), cpu_count=os.cpu_count(),
              **device_info(), python=platform_lib.python_version(),
              wall_s=None if wall_s is None else float(wall_s))


def of(result: dict) -> dict:
  """The provenance record of a loaded result file; {} for one written before records existed."""
  record = result.get(KEY) if isinstance(result, dict) else None
  return record if isinstance(record, dict) else {}
