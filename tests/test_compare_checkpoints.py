"""experiments/compare_checkpoints.py: two run folders' saved states compared leaf by leaf."""

import os
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import train_step as step_lib

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
from experiments import compare_checkpoints as cc  # noqa: E402

KERNEL = np.linspace(-1.0, 1.0, 6, dtype=np.float32).reshape(2, 3)


def _save(workdir, *, kernel=KERNEL, step=4, bias_shape=(3,)):
  """A run folder whose latest checkpoint holds a small train state."""
  state = step_lib.TrainState(
      step=jnp.asarray(step, jnp.int32),
      params={"dense": {"kernel": jnp.asarray(kernel), "bias": jnp.zeros(bias_shape)}},
      opt_state=({"mu": jnp.full((2, 3), 0.5)},),
      nonfinite_in_row=jnp.asarray(0, jnp.int32), nonfinite_total=jnp.asarray(1, jnp.int32))
  manager = ckpt_lib.Checkpoints(str(workdir))
  manager.save(state)
  manager.wait()
  manager.close()
  return str(workdir)


def test_identical_runs_exit_0_and_one_ulp_is_found_and_measured(tmp_path, capsys):
  a, b = _save(tmp_path / "a"), _save(tmp_path / "b")
  assert cc.main([a, b]) == 0
  out = capsys.readouterr().out
  assert "6 leaves, 6 bit-identical; largest |difference| 0" in out
  assert f"A: {os.path.join(a, 'checkpoints', 'latest', '4')}" in out

  # One weight moved by one float32 ulp: found, and its difference is that ulp (not rounded to 0).
  kernel = KERNEL.copy()
  kernel[1, 2] = np.nextafter(kernel[1, 2], np.float32(2.0))
  ulp = float(kernel[1, 2]) - float(KERNEL[1, 2])
  assert ulp > 0
  c = _save(tmp_path / "c", kernel=kernel)
  assert cc.main([a, c, "--show=1"]) == 1
  out = capsys.readouterr().out
  assert "6 leaves, 5 bit-identical" in out
  assert f"['params']['dense']['kernel']: largest |difference| {ulp:.3g}" in out


def test_compare_lists_leaves_in_path_order_with_their_differences():
  a = {"w": np.array([1.0, 2.0], np.float32), "n": np.array(3, np.int32)}
  b = {"w": np.array([1.0, 2.5], np.float32), "n": np.array(3, np.int32)}
  assert cc.compare(a, b) == [("['n']", True, 0.0), ("['w']", False, 0.5)]
  # -0.0 and 0.0 are equal numbers but not the same bits: a resume that is exact keeps the bits.
  assert cc.compare({"z": np.array(0.0)}, {"z": np.array(-0.0)}) == [("['z']", False, 0.0)]


@pytest.mark.parametrize("case, message", [
    ("shape", "['params']['dense']['bias']: A is float32[3], B is float32[4]"),
    ("missing", "no checkpoints; train this run first"),
    ("step", "--checkpoint=9: no such step; saved steps: latest [4], best []"),
])
def test_what_cannot_be_compared_exits_2_with_one_line(tmp_path, capsys, case, message):
  a = _save(tmp_path / "a")
  b = {"shape": lambda: _save(tmp_path / "b", bias_shape=(4,)),
       "missing": lambda: str(tmp_path / "absent"),
       "step": lambda: _save(tmp_path / "b")}[case]()
  argv = [a, b] + (["--checkpoint=9"] if case == "step" else [])
  assert cc.main(argv) == 2
  err = capsys.readouterr().err.strip()
  assert message in err and "\n" not in err, err
  assert not os.path.exists(tmp_path / "absent")  # nothing is created for a missing run


def test_command_line(tmp_path):
  a, b = _save(tmp_path / "a"), _save(tmp_path / "b", step=5)
  proc = subprocess.run([sys.executable, "experiments/compare_checkpoints.py", a, b], cwd=REPO,
                        capture_output=True, text=True, timeout=300)
  # Another step number: the step leaf differs by 1, every other leaf is the same.
  assert proc.returncode == 1, proc.stderr[-2000:]
  assert "6 leaves, 5 bit-identical; largest |difference| 1" in proc.stdout
  assert "['step']: largest |difference| 1" in proc.stdout
