"""Process set-up that must happen before JAX starts: the memory allocator and XLA's CPU flags.

XLA:CPU allocates one temp buffer per executed step (hundreds of MB to GB). glibc returns such
blocks to the OS with munmap, so every step page-faults the whole buffer back in; a retaining
allocator (jemalloc, tcmalloc) avoids that, the largest single speed-up of the paper-sized step on
a 2-core CPU (docs/performance.md §1).
The allocator can only be swapped at exec time, so `main` and the benchmark re-execute themselves
once with LD_PRELOAD set. Nothing here changes results, only speed and memory.

SLOTLIFTER_ALLOCATOR picks it: "auto" (default: the first of AUTO_ORDER that is installed, else
the system one), "mimalloc", "tcmalloc", "jemalloc" or "system" (no preload). mimalloc comes
first: the `cmeel-mimalloc` wheel, a dependency of this package, ships it inside the virtual
environment, so `pip install` alone gives a retaining allocator, and, configured never to purge,
it serves the temp buffer as fast as tcmalloc with half tcmalloc's peak memory on the paper-sized
step (`python experiments/bench.py --configs=B,A --allocators=system,mimalloc,tcmalloc`:
experiments/journal/2026-11.md, "Train-step benchmark"; docs/performance.md §1). jemalloc with
decay off kept mapping fresh buffers on that step until the benchmark was OOM-killed
(`experiments/rss_per_step.py`).
"""

from __future__ import annotations

import glob
import importlib.util
import os
import sys
import sysconfig

ENV = "SLOTLIFTER_ALLOCATOR"
MARK = "SLOTLIFTER_ALLOCATOR_APPLIED"  # set in the re-executed process

_CANDIDATES = {
    "jemalloc": ("libjemalloc.so.2", "libjemalloc.so"),
    "tcmalloc": ("libtcmalloc_minimal.so.4", "libtcmalloc.so.4", "libtcmalloc_minimal.so"),
    "mimalloc": ("libmimalloc.so.3", "libmimalloc.so.2", "libmimalloc.so"),
}
AUTO_ORDER = ("mimalloc", "tcmalloc", "jemalloc")
ALLOCATORS = ("auto",) + AUTO_ORDER + ("system",)
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib",
             "/usr/local/lib", "/opt/homebrew/lib")

# jemalloc keeps freed pages (no decay) so the next step's temp buffer is served without faults;
# background threads would only compete for the two cores.
JEMALLOC_CONF = "dirty_decay_ms:-1,muzzy_decay_ms:-1,background_thread:false"
# The same for mimalloc: never purge (return to the OS) freed pages, so the next step's temp
# buffer is served from memory already mapped.
MIMALLOC_ENV = {"MIMALLOC_PURGE_DELAY": "-1"}

# The default XLA:CPU scheduler overlaps independent ops at the cost of more temp memory on the
# paper-sized step, for no measured speed (docs/performance.md §2).
XLA_CPU_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",)


def _lib_dirs() -> tuple[str, ...]:
  """The system library folders, then the library folder of wheels in this environment (the
  cmeel wheels install into site-packages/cmeel.prefix/lib)."""
  wheel_dirs = {os.path.join(sysconfig.get_paths()[k], "cmeel.prefix", "lib")
                for k in ("purelib", "platlib")}
  return _LIB_DIRS + tuple(sorted(wheel_dirs))


def find_allocator(name: str) -> str | None:
  """Path of the shared library of allocator `name`, or None when it is not installed."""
  for lib in _CANDIDATES[name]:
    for d in _lib_dirs():
      hits = sorted(glob.glob(os.path.join(d, lib)))
      if hits:
        return hits[0]
  return None


def allocator_env(choice: str | None = None) -> dict[str, str]:
  """The environment variables that preload the chosen allocator (empty for "system")."""
  choice = (choice or os.environ.get(ENV, "auto")).lower()
  if choice not in ALLOCATORS:
    raise ValueError(f"{ENV}={choice!r}: use one of {', '.join(ALLOCATORS)}")
  if choice == "system":
    return {}
  names = AUTO_ORDER if choice == "auto" else (choice,)
  for name in names:
    path = find_allocator(name)
    if path:
      env = {"LD_PRELOAD": path}
      if name == "jemalloc":
        env["MALLOC_CONF"] = JEMALLOC_CONF
      if name == "mimalloc":
        env.update(MIMALLOC_ENV)
      return env
  if choice != "auto":
    raise RuntimeError(f"{ENV}={choice}: lib{choice} not found in {', '.join(_lib_dirs())} "
                       f"(pip install cmeel-mimalloc; Debian/Ubuntu: apt install "
                       f"libtcmalloc-minimal4 or libjemalloc2)")
  return {}


# JAX's GPU plugins (the `cuda` extra installs the CUDA 12 one) and the device files their
# drivers create; a plugin without a device falls back to the CPU.
_GPU_PLUGINS = ("jax_cuda12_plugin", "jax_cuda13_plugin", "jax_rocm60_plugin", "jax_rocm7_plugin")
_GPU_DEVICE_FILES = ("/dev/nvidia0", "/dev/nvidiactl", "/dev/kfd")


def expected_backend(environ=os.environ, *, find_spec=importlib.util.find_spec,
                     exists=os.path.exists) -> str:
  """"cpu", "gpu" or "tpu": the backend JAX will start, decided before JAX is imported (the
  allocator can only be chosen then). JAX_PLATFORMS wins when set; else a GPU plugin with a GPU
  device means "gpu", libtpu means "tpu", anything else "cpu"."""
  platforms = environ.get("JAX_PLATFORMS", "").strip().lower()
  if platforms:
    first = platforms.split(",")[0].strip()
    return "gpu" if first in ("cuda", "rocm", "gpu") else first
  if any(_spec(find_spec, m) for m in _GPU_PLUGINS) and any(exists(f) for f in _GPU_DEVICE_FILES):
    return "gpu"
  if _spec(find_spec, "libtpu"):
    return "tpu"
  return "cpu"


def _spec(find_spec, name: str):
  try:
    return find_spec(name)
  except (ImportError, ValueError):
    return None


def set_xla_flags(environ=os.environ) -> None:
  """Adds XLA_CPU_FLAGS to XLA_FLAGS unless the user already set them (call before importing jax).

  Only for the CPU backend: on a GPU or TPU the flags would be inert, and are left out."""
  if expected_backend(environ) != "cpu":
    return
  flags = environ.get("XLA_FLAGS", "")
  for flag in XLA_CPU_FLAGS:
    if flag.split("=")[0] not in flags:
      flags = f"{flags} {flag}".strip()
  environ["XLA_FLAGS"] = flags


def reexec_with_allocator(argv: list[str] | None = None) -> None:
  """Re-executes this Python process once with the allocator preloaded; returns if nothing to do.

  `argv` is the command to run again (default: `python -m <this __main__ module>` with the same
  arguments). Does nothing when the allocator is already loaded, when JAX is already imported
  (its allocator choice is fixed by then), when JAX will not run on the CPU (a GPU keeps its
  buffers in device memory, so the host allocator does not pace a step), or when no allocator
  library is installed.
  """
  if os.environ.get(MARK) or "jax" in sys.modules or expected_backend() != "cpu":
    return
  env = allocator_env()
  preload = env.get("LD_PRELOAD")
  if not preload or preload in os.environ.get("LD_PRELOAD", ""):
    return
  new_env = dict(os.environ)
  new_env.update(env)
  new_env["LD_PRELOAD"] = " ".join(p for p in (preload, os.environ.get("LD_PRELOAD", "")) if p)
  new_env[MARK] = preload
  if argv is None:
    main_module = sys.modules["__main__"]
    spec = getattr(main_module, "__spec__", None)
    if spec is not None and spec.name:
      argv = [sys.executable, "-m", spec.name.removesuffix(".__main__")] + sys.argv[1:]
    else:
      argv = [sys.executable] + sys.argv
  sys.stdout.flush()
  sys.stderr.flush()
  os.execve(sys.executable, argv, new_env)


def loaded_allocator() -> str | None:
  """The preloaded allocator library's file name, or None for the system malloc."""
  loaded = os.environ.get(MARK) or os.environ.get("LD_PRELOAD", "")
  return os.path.basename(loaded.split()[0]) if loaded.strip() else None


def describe() -> str:
  """One line for the log: which allocator this process runs with."""
  return f"allocator: {loaded_allocator() or 'system malloc'}"


def slow_allocator_warning() -> str | None:
  """A warning for the log when no retaining allocator is loaded (None when one is)."""
  if loaded_allocator():
    return None
  how = ("SLOTLIFTER_ALLOCATOR=system is set" if os.environ.get(ENV, "").lower() == "system"
         else "none of tcmalloc, mimalloc, jemalloc was found")
  return (f"running on the system malloc ({how}): XLA:CPU maps its per-step temp buffer afresh "
          f"every step, so training runs markedly slower (docs/performance.md §1); "
          f"`pip install cmeel-mimalloc` or `apt install libtcmalloc-minimal4` fixes it")
