"""Two processes on jax.distributed (`python -m slotlifter_jax.main --distributed`, CPU collectives
over gloo, one CPU device per process) train, resume and evaluate one smoke run.

One two-process run and one single-process run with two devices (the same global batch on the same
two-device mesh) start together and are compared:
- the final parameters are bit-identical. No tolerance is needed: each device runs the same
  compiled program on the same scenes of the same batch, and the only cross-device reductions
  (the gradient and the loss means) add two partial results, one per device. IEEE addition is
  commutative, so gloo's all-reduce between processes and XLA's in-process one return the same
  bits, whichever order they add in. A tolerance would hide a process feeding the wrong scenes;
  with more than two devices the order of a sum could differ, and this exactness would not hold;
- the metric records (training and validation) are the same, written once, by process 0;
- the checkpoint is complete and a resume by two processes continues from its step;
- `--mode=eval` by two processes writes the numbers one process writes.
"""

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMOKE = "configs/clevr.py:smoke"
# The flags that make a process one of several; the README's multi-process command may use them.
DISTRIBUTED_FLAGS = {"--distributed", "--coordinator_address", "--num_processes", "--process_id"}
TIMEOUT_S = 600


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("localhost", 0))
    return s.getsockname()[1]


def _launch(workdir, extra, *, processes: int, logs: str) -> list[tuple[subprocess.Popen, str]]:
  """Starts `processes` processes of one run (2: distributed, one device each; 1: two devices)."""
  port = _free_port()
  env = dict(os.environ, JAX_PLATFORMS="cpu",
             XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} "
                       f"--xla_force_host_platform_device_count={1 if processes > 1 else 2}")
  started = []
  for i in range(processes):
    args = [sys.executable, "-m", "slotlifter_jax.main", f"--config={SMOKE}",
            f"--workdir={workdir}", *extra]
    if processes > 1:
      args += ["--distributed", f"--coordinator_address=localhost:{port}",
               f"--num_processes={processes}", f"--process_id={i}"]
    log = f"{logs}.process{i}.log"
    with open(log, "w") as out:  # a file, not a pipe: a full pipe would stall its process
      started.append((subprocess.Popen(args, cwd=REPO, env=env, stdout=out,
                                       stderr=subprocess.STDOUT), log))
  return started


def _finish(*groups) -> list[list[str]]:
  """Waits for every process; returns each group's logs. Any failure kills the rest (a process
  whose partner died would otherwise wait for it until jax's heartbeat gives up)."""
  procs = [p for group in groups for p, _ in group]
  try:
    for p in procs:
      p.wait(timeout=TIMEOUT_S)
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
        p.wait()
  logs = [[open(log, errors="replace").read() for _, log in group] for group in groups]
  for group, texts in zip(groups, logs):
    for (p, _), text in zip(group, texts):
      assert p.returncode == 0, f"{p.args} exited {p.returncode}:\n{text[-4000:]}"
  return logs


def _records(workdir) -> list[dict]:
  """metrics.jsonl without the fields that measure time."""
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    records = [json.loads(line) for line in f]
  return [{k: v for k, v in r.items() if k not in ("time", "wall_s", "steps_per_sec")}
          for r in records]


def _state(workdir, step):
  """The checkpointed train state of `step`, restored on this process's one device."""
  sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
  import jax
  from train_helpers import fake_batch, load_config
  from slotlifter_jax import checkpoints as ckpt_lib
  from slotlifter_jax import model as model_lib
  from slotlifter_jax import train_step as step_lib
  config = load_config()
  device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
  abstract = step_lib.state_shapes(model_lib.build_model(config), config, fake_batch(config),
                                   sharding=device)
  manager = ckpt_lib.Checkpoints(workdir)
  try:
    return manager.restore(abstract, step=step)
  finally:
    manager.close()


def _steps(workdir, which="latest") -> list[int]:
  folder = os.path.join(workdir, "checkpoints", which)
  return sorted(int(s) for s in os.listdir(folder) if s.isdigit())


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  """The smoke run trained by two processes and by one process with two devices, side by side."""
  root = tmp_path_factory.mktemp("distributed")
  # The embedded set is generated here, once: two processes generating one folder would race.
  sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
  from train_helpers import load_config
  from slotlifter_jax.data import embedded
  embedded.resolve_data(load_config())
  two, one = str(root / "two"), str(root / "one")
  logs_two, logs_one = _finish(_launch(two, [], processes=2, logs=two),
                               _launch(one, [], processes=1, logs=one))
  return dict(root=root, two=two, one=one, logs_two=logs_two, logs_one=logs_one)


@pytest.fixture(scope="module")
def followups(runs):
  """On copies of the two-process run, side by side: a two-process resume to step 9, and
  `--mode=eval` by two processes and by one."""
  root = runs["root"]
  paths = {name: str(root / name) for name in ("resumed", "eval_two", "eval_one")}
  for path in paths.values():
    shutil.copytree(runs["two"], path)
  resumed, eval_two, eval_one = _finish(
      _launch(paths["resumed"], ["--config.train.num_steps=9"], processes=2,
              logs=paths["resumed"]),
      _launch(paths["eval_two"], ["--mode=eval"], processes=2, logs=paths["eval_two"]),
      _launch(paths["eval_one"], ["--mode=eval"], processes=1, logs=paths["eval_one"]))
  return dict(paths=paths, resumed=resumed, eval_two=eval_two, eval_one=eval_one)


@pytest.mark.slow
def test_two_processes_train_what_one_process_with_two_devices_trains(runs):
  assert "process 0 of 2" in runs["logs_two"][0] and "process 0 of 1" in runs["logs_one"][0]
  assert _steps(runs["two"]) == _steps(runs["one"]) == [3, 6]
  a, b = _state(runs["two"], 6), _state(runs["one"], 6)
  assert int(a.step) == int(b.step) == 6
  import jax
  diffs = jax.tree.leaves(jax.tree.map(
      lambda x, y: float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)))),
      (a.params, a.opt_state), (b.params, b.opt_state)))
  print(f"largest |difference| over {len(diffs)} parameter and optimiser leaves: {max(diffs)}")
  jax.tree.map(np.testing.assert_array_equal, (a.params, a.opt_state), (b.params, b.opt_state))
  # Training and validation records (validation: every process renders, process 0 writes).
  records = _records(runs["two"])
  assert records == _records(runs["one"])
  assert [(r["step"], r["kind"]) for r in records] == [
      (2, "train"), (3, "val"), (4, "train"), (6, "train"), (6, "val")]


@pytest.mark.slow
def test_process_zero_alone_writes_and_the_checkpoint_is_complete(runs):
  two = runs["two"]
  assert sorted(os.listdir(two)) == sorted(os.listdir(runs["one"])) == [
      "checkpoints", "config.json", "emergence.json", "machines.jsonl", "metrics.jsonl", "tb",
      "val"]
  # One of each file: no per-process copies, no temporary leftovers.
  for name in ("metrics.jsonl", "config.json", "emergence.json", "machines.jsonl"):
    found = [os.path.join(d, f) for d, _, files in os.walk(two) for f in files if f == name]
    assert found == [os.path.join(two, name)], found
  assert len(os.listdir(os.path.join(two, "tb"))) == 1
  with open(os.path.join(two, "machines.jsonl")) as f:  # process 0's one training session
    assert len(f.readlines()) == 1
  assert sorted(os.listdir(os.path.join(two, "val"))) == ["step_0000003.png", "step_0000006.png"]
  with open(os.path.join(two, "config.json")) as f, \
      open(os.path.join(runs["one"], "config.json")) as g:
    assert json.load(f) == json.load(g)
  assert not os.path.exists(os.path.join(two, "config_history.jsonl"))
  leftovers = [os.path.join(d, n) for d, dirs, files in os.walk(two) for n in dirs + files
               if "tmp" in n]
  assert not leftovers, leftovers
  for which, steps in (("latest", [3, 6]), ("best", _steps(two, "best"))):
    assert steps and _steps(two, which) == steps
    for step in steps:
      folder = os.path.join(two, "checkpoints", which, str(step))
      for marker in ("_CHECKPOINT_METADATA", "commit_success.txt",
                     os.path.join("default", "_METADATA"),
                     os.path.join("default", "commit_success.txt")):
        assert os.path.isfile(os.path.join(folder, marker)), (folder, marker)
  # Process 1 logs neither progress bar nor information lines, only warnings, if any.
  other = runs["logs_two"][1]
  assert "train:" not in other and "resumed" not in other
  assert not re.search(r"^I\d{4} .*(train|registry)\.py", other, re.M), other[-2000:]


@pytest.mark.slow
def test_two_processes_resume_from_the_checkpoint_step(runs, followups):
  resumed, log0 = followups["paths"]["resumed"], followups["resumed"][0]
  assert "resumed from step 6" in log0, log0[-3000:]
  assert _steps(resumed) == [3, 6, 9]
  assert int(_state(resumed, 9).step) == 9
  records = _records(resumed)
  assert records[:5] == _records(runs["two"])  # appended to, once
  assert [(r["step"], r["kind"]) for r in records[5:]] == [(8, "train"), (9, "train"), (9, "val")]
  with open(os.path.join(resumed, "config_history.jsonl")) as f:
    history = [json.loads(line) for line in f]
  assert [(h["step"], h["changes"]) for h in history] == [(6, {"train.num_steps": [6, 9]})]


@pytest.mark.slow
def test_two_processes_evaluate_as_one_does(followups):
  results = {}
  for name in ("eval_two", "eval_one"):
    path = os.path.join(followups["paths"][name], "eval", "test", "metrics.json")
    assert "wrote " + path in followups[name][0]
    with open(path) as f:
      results[name] = json.load(f)
  assert "wrote" not in followups["eval_two"][1]  # one table, from process 0
  two, one = results["eval_two"], results["eval_one"]
  assert two["metrics"] == one["metrics"]
  assert two["checkpoint"]["step"] == one["checkpoint"]["step"]


def test_the_readme_multi_process_commands_use_flags_run_here():
  with open(os.path.join(REPO, "README.md")) as f:
    commands = [shlex.split(m) for m in re.findall(
        r"\.venv/bin/python -m slotlifter_jax\.main ([^\n`]+)", f.read())]
  distributed = [c for c in commands if "--distributed" in c]
  assert distributed, "README shows no --distributed command"
  for args in distributed:
    flags = {a.split("=", 1)[0] for a in args}
    assert flags <= {"--config", "--workdir"} | DISTRIBUTED_FLAGS, args



class _Addressable:
  """A stand-in for a sharding seen from one process: its devices' slices of the leading axis."""

  def __init__(self, *spans):
    self.spans = spans

  def addressable_devices_indices_map(self, shape):
    return {f"device{i}": (slice(a, b),) for i, (a, b) in enumerate(self.spans)}


def test_each_process_feeds_the_rows_on_its_devices():
  """`multihost.local_rows`: every row on one process; else the rows of the process's devices, in
  the order of their starts (jax.make_array_from_process_local_data's order for local data)."""
  from slotlifter_jax import multihost
  from slotlifter_jax import train_step as step_lib
  sharding = step_lib.batch_sharding(step_lib.make_mesh())
  np.testing.assert_array_equal(multihost.local_rows(sharding, 4), np.arange(4))
  np.testing.assert_array_equal(multihost.local_rows(_Addressable((2, 4)), 4), [2, 3])
  np.testing.assert_array_equal(multihost.local_rows(_Addressable((6, 8), (0, 2)), 8), [0, 1, 6, 7])
  # Devices holding the same rows (a replicated axis) feed them once.
  np.testing.assert_array_equal(multihost.local_rows(_Addressable((0, 2), (0, 2)), 4), [0, 1])
