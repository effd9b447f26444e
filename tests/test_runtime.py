"""Process set-up: allocator choice and XLA flags (no re-exec happens in tests: JAX is imported)."""

import importlib
import os
import sys

import pytest

from slotlifter_jax import runtime


def test_system_allocator_means_no_preload():
  assert runtime.allocator_env("system") == {}


def test_unknown_allocator_is_a_clear_error():
  with pytest.raises(ValueError, match="SLOTLIFTER_ALLOCATOR"):
    runtime.allocator_env("ptmalloc3")


def test_named_allocator_points_at_an_existing_library_or_explains():
  for name in ("jemalloc", "tcmalloc", "mimalloc"):
    path = runtime.find_allocator(name)
    if path is None:
      with pytest.raises(RuntimeError, match="pip install cmeel-mimalloc"):
        runtime.allocator_env(name)
    else:
      env = runtime.allocator_env(name)
      assert env["LD_PRELOAD"] == path and os.path.exists(path)
      if name == "mimalloc":  # configured to keep freed pages, as jemalloc's decay is turned off
        assert env["MIMALLOC_PURGE_DELAY"] == "-1"


def test_a_wheel_installed_mimalloc_is_found(tmp_path, monkeypatch):
  """The cmeel wheel puts the library under site-packages/cmeel.prefix/lib; that is searched."""
  lib_dir = tmp_path / "site" / "cmeel.prefix" / "lib"
  lib_dir.mkdir(parents=True)
  (lib_dir / "libmimalloc.so.3").write_bytes(b"")
  monkeypatch.setattr(runtime, "_LIB_DIRS", ())
  monkeypatch.setattr(runtime.sysconfig, "get_paths",
                      lambda: {"purelib": str(tmp_path / "site"), "platlib": str(tmp_path / "site")})
  assert runtime.find_allocator("mimalloc") == str(lib_dir / "libmimalloc.so.3")
  assert runtime.find_allocator("tcmalloc") is None


def test_the_system_malloc_is_warned_about_and_a_preloaded_one_is_not(monkeypatch):
  monkeypatch.delenv("SLOTLIFTER_ALLOCATOR_APPLIED", raising=False)
  monkeypatch.delenv("LD_PRELOAD", raising=False)
  monkeypatch.setenv("SLOTLIFTER_ALLOCATOR", "system")
  warning = runtime.slow_allocator_warning()
  assert "SLOTLIFTER_ALLOCATOR=system" in warning and "cmeel-mimalloc" in warning
  assert runtime.describe() == "allocator: system malloc"
  monkeypatch.setenv("LD_PRELOAD", "/usr/lib/libtcmalloc_minimal.so.4 /other/lib.so")
  assert runtime.slow_allocator_warning() is None
  assert runtime.describe() == "allocator: libtcmalloc_minimal.so.4"


def test_xla_flags_added_once_and_user_values_kept():
  env = {}
  runtime.set_xla_flags(env)
  runtime.set_xla_flags(env)
  for flag in runtime.XLA_CPU_FLAGS:
    assert env["XLA_FLAGS"].count(flag.split("=")[0]) == 1
  name = runtime.XLA_CPU_FLAGS[0].split("=")[0]
  user = {"XLA_FLAGS": f"--xla_dump_to=/tmp/x {name}=true"}
  runtime.set_xla_flags(user)
  assert f"{name}=true" in user["XLA_FLAGS"] and user["XLA_FLAGS"].count(name) == 1


def test_no_reexec_once_jax_is_loaded(monkeypatch):
  # The allocator of a running JAX process cannot change, so once jax is loaded nothing re-execs.
  assert importlib.import_module("jax").__name__ in sys.modules
  monkeypatch.setattr(os, "execve", lambda *a: pytest.fail("must not re-exec"))
  runtime.reexec_with_allocator()


def test_the_backend_is_decided_before_jax_starts():
  none = lambda name: None
  has_cuda = lambda name: object() if name == "jax_cuda12_plugin" else None
  gpu_files = lambda path: path == "/dev/nvidia0"
  assert runtime.expected_backend({}, find_spec=none, exists=gpu_files) == "cpu"
  assert runtime.expected_backend({}, find_spec=has_cuda, exists=gpu_files) == "gpu"
  # The plugin installed on a machine without a GPU: JAX falls back to the CPU.
  assert runtime.expected_backend({}, find_spec=has_cuda, exists=lambda p: False) == "cpu"
  assert runtime.expected_backend({"JAX_PLATFORMS": "cuda"}, find_spec=none) == "gpu"
  assert runtime.expected_backend({"JAX_PLATFORMS": "cpu"}, find_spec=has_cuda,
                                  exists=gpu_files) == "cpu"
  assert runtime.expected_backend({"JAX_PLATFORMS": "tpu,cpu"}, find_spec=none) == "tpu"
  assert runtime.expected_backend({}, find_spec=lambda n: object() if n == "libtpu" else None,
                                  exists=lambda p: False) == "tpu"


def test_cpu_flags_and_allocator_only_for_the_cpu_backend(monkeypatch):
  gpu = {"JAX_PLATFORMS": "cuda"}
  runtime.set_xla_flags(gpu)
  assert "XLA_FLAGS" not in gpu
  cpu = {"JAX_PLATFORMS": "cpu"}
  runtime.set_xla_flags(cpu)
  assert runtime.XLA_CPU_FLAGS[0] in cpu["XLA_FLAGS"]
  # No re-exec on a GPU backend even before JAX is imported.
  monkeypatch.setenv("JAX_PLATFORMS", "cuda")
  monkeypatch.delenv(runtime.MARK, raising=False)
  monkeypatch.setattr(runtime.sys, "modules", {k: v for k, v in runtime.sys.modules.items()
                                               if k != "jax"})
  monkeypatch.setattr(os, "execve", lambda *a: pytest.fail("must not re-exec on a GPU"))
  runtime.reexec_with_allocator()
