"""Process set-up: allocator choice and XLA flags (no re-exec happens in tests: JAX is imported)."""

import os

import pytest

from slotlifter_jax import runtime


def test_system_allocator_means_no_preload():
  assert runtime.allocator_env("system") == {}


def test_unknown_allocator_is_a_clear_error():
  with pytest.raises(ValueError, match="SLOTLIFTER_ALLOCATOR"):
    runtime.allocator_env("mimalloc")


def test_named_allocator_points_at_an_existing_library_or_explains():
  for name in ("jemalloc", "tcmalloc"):
    path = runtime.find_allocator(name)
    if path is None:
      with pytest.raises(RuntimeError, match="apt install"):
        runtime.allocator_env(name)
    else:
      env = runtime.allocator_env(name)
      assert env["LD_PRELOAD"] == path and os.path.exists(path)


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
  import jax  # noqa: F401  (the allocator of a running JAX process cannot change)
  monkeypatch.setattr(os, "execve", lambda *a: pytest.fail("must not re-exec"))
  runtime.reexec_with_allocator()
