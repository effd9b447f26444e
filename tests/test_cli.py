"""The README's commands, run as a new user runs them: `python -m slotlifter_jax.main` in a fresh
folder with relative paths, the smoke variant in place of scene.

Train, SIGINT, resume, eval and render, checking exit codes and files. The README is read too: a
`slotlifter_jax.main` command it shows with a mode or flag this test does not run fails the test,
so the README and the commands that are known to work cannot drift apart.
"""

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MAIN = re.compile(r"\.venv/bin/python -m slotlifter_jax\.main ([^\n`]+)")
# Flags this test passes in each mode (with the README's values, where the README gives them).
RUN_FLAGS = {"train": {"--config", "--workdir"},
             "eval": {"--config", "--workdir", "--mode"},
             "render": {"--config", "--workdir", "--mode", "--scenes"},
             "edit": {"--config", "--workdir", "--mode"}}
# The multi-process flags: tests/test_distributed.py runs them (and checks the README's use of them).
DISTRIBUTED_FLAGS = {"--distributed", "--coordinator_address", "--num_processes", "--process_id"}


def readme_commands() -> list[list[str]]:
  with open(os.path.join(REPO, "README.md")) as f:
    return [shlex.split(m) for m in MAIN.findall(f.read())]


def mode_and_flags(args: list[str]) -> tuple[str, set[str]]:
  flags = {a.split("=", 1)[0] for a in args}
  mode = next((a.split("=", 1)[1] for a in args if a.startswith("--mode=")), "train")
  return mode, flags


def test_every_readme_command_is_one_this_file_runs():
  commands = readme_commands()
  assert len(commands) >= 3
  for args in commands:
    mode, flags = mode_and_flags(args)
    assert mode in RUN_FLAGS, f"README: mode {mode!r} of {' '.join(args)} is not tested here"
    # --max_scenes: see the eval step below; the multi-process flags: tests/test_distributed.py.
    untested = flags - RUN_FLAGS[mode] - {"--max_scenes"} - DISTRIBUTED_FLAGS
    assert not untested, f"README: {' '.join(args)} uses {sorted(untested)}, not tested here"
    config = next(a.split("=", 1)[1] for a in args if a.startswith("--config="))
    assert os.path.isfile(os.path.join(REPO, config.split(":")[0])), config


def _readme_command(mode: str) -> list[str]:
  """The README's first (`scene`) command of `mode`, with the smoke variant."""
  for args in readme_commands():
    if (mode_and_flags(args)[0] == mode and "configs/clevr.py:scene" in " ".join(args)
        and "--distributed" not in args):
      return [a.replace("configs/clevr.py:scene", "configs/clevr.py:smoke") for a in args]
  raise AssertionError(f"README shows no scene {mode} command")


def _main(args, cwd, **kwargs):
  return subprocess.Popen([sys.executable, "-m", "slotlifter_jax.main", *args], cwd=cwd,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **kwargs)


def _run(args, cwd) -> str:
  proc = _main(args, cwd)
  out = proc.communicate(timeout=600)[0].decode(errors="replace")
  assert proc.returncode == 0, f"{args} exited {proc.returncode}:\n{out[-3000:]}"
  return out


@pytest.mark.slow
def test_train_interrupt_resume_eval_render_from_a_fresh_folder(tmp_path):
  shutil.copytree(os.path.join(REPO, "configs"), tmp_path / "configs")  # a clone's root
  train = _readme_command("train")
  workdir = next(a.split("=", 1)[1] for a in train if a.startswith("--workdir="))
  assert not os.path.isabs(workdir)

  # SIGINT once the loop is running: the run checkpoints and exits 128 + 2, not 0.
  proc = _main(train, tmp_path)
  output = bytearray()
  def read():
    for chunk in iter(lambda: proc.stdout.read1(4096), b""):
      output.extend(chunk)
  reader = threading.Thread(target=read)
  reader.start()
  deadline = time.time() + 600
  loop_started = re.compile(rb"(^|[\r\n])train:")  # the loop's bar, not the generator's
  while not loop_started.search(output) and proc.poll() is None and time.time() < deadline:
    time.sleep(0.2)
  proc.send_signal(signal.SIGINT)
  proc.wait(timeout=600)
  reader.join()
  text = output.decode(errors="replace")
  assert proc.returncode == 128 + signal.SIGINT, text[-3000:]
  assert "checkpointing and exiting after the current step" in text
  steps = sorted(int(s) for s in os.listdir(tmp_path / workdir / "checkpoints" / "latest")
                 if s.isdigit())
  assert steps and steps[-1] < 6, steps  # the smoke run has 6 steps

  # The same command again resumes and finishes.
  out = _run(train, tmp_path)
  assert "resumed from step" in out, out[-3000:]
  steps = sorted(int(s) for s in os.listdir(tmp_path / workdir / "checkpoints" / "latest")
                 if s.isdigit())
  assert steps[-1] == 6, steps

  out = _run(_readme_command("eval"), tmp_path)
  assert os.path.isfile(tmp_path / workdir / "eval" / "test" / "metrics.json"), out[-3000:]
  with open(tmp_path / workdir / "eval" / "test" / "metrics.json") as f:
    assert json.load(f)["parameters"] == "trained"  # the README's run keeps no average
  render = _readme_command("render")
  out = _run(render, tmp_path)
  scenes = next(a.split("=", 1)[1] for a in render if a.startswith("--scenes="))
  for i in scenes.split(","):
    assert os.path.isfile(tmp_path / workdir / "render" / "test" / f"scene_{int(i):04d}_panel.png")
  out = _run(_readme_command("edit"), tmp_path)
  with open(tmp_path / workdir / "edit" / "test" / "edit_metrics.json") as f:
    edits = json.load(f)
  assert {"remove", "move"} <= set(edits), out[-3000:]


# The bad inputs that only the data or the run folder reveals, after JAX has started.
FOUND_AFTER_JAX_STARTS = ("data.root does not exist", "exists and is not a directory",
                          "data.scene_stages:", "(data.max_objects)")


@pytest.mark.parametrize("args, message", [
    (["--config=configs/nonexistent.py"], "--config=configs/nonexistent.py: cannot be loaded"),
    (["--config=configs/clevr.py:smoke", "--config.train.base_lrr=1"], 'did you mean "base_lr"'),
    (["--config=configs/room_chair.py:smoke", "--config.data.room_objects=clevr",
      "--config.data.max_objects=8"],
     "error (data.max_objects): max_objects must lie in 0..7 for the clevr family's objects"),
    (["--config=configs/clevr.py:nonvariant"], "unknown variant 'nonvariant'"),
    (["--config=configs/clevr.py:fast"], "variant 'fast' was renamed 'scene'"),
    (["--config=configs/clevr.py:smoke", "--config.data.root=/nonexistent"],
     "/nonexistent: data.root does not exist"),
    (["--config=configs/clevr.py:smoke", "--workdir=a_file"], "a_file: exists and is not a directory"),
    (["--config=configs/clevr.py:smoke", "--num_processes=2"], "--process_id need --distributed"),
    (["--config=configs/clevr.py:smoke", "--config.data.frame=camera"],
     "data.frame must be one of ('world', 'source_azimuth'), got 'camera'"),
    (["--config=configs/clevr.py:smoke", "--config.train.mask_min=0.995"],
     "train.mask_min=0.995 and train.mask_max=0.99 must satisfy 0 ≤ mask_min ≤ mask_max ≤ 1"),
    (["--config=configs/clevr.py:smoke", "--config.train.mask_min_steps=-1"],
     "train.mask_min_steps=-1 must be ≥ 0"),
    (["--config=configs/clevr.py:smoke", "--config.train.mask_min_release_steps=-5"],
     "train.mask_min_release_steps=-5 must be ≥ 0"),
    (["--config=configs/clevr.py:smoke", "--config.train.lr_cooldown_steps=7"],
     "train.lr_cooldown_steps=7 must lie in [0, train.num_steps=6]"),
    (["--config=configs/clevr.py:smoke", "--config.train.lr_cooldown_final=1.5"],
     "train.lr_cooldown_final=1.5 must lie in [0, 1]"),
    (["--config=configs/clevr.py:smoke", "--config.train.slot_attention_lr_scale=-0.5"],
     "train.slot_attention_lr_scale=-0.5 must be ≥ 0"),
    (["--config=configs/clevr.py:smoke", "--config.data.scene_stages=((0,2),(3,9))"],
     "data.scene_stages: 9 (stage from step 3) must lie in [1, 4]"),
    (["--config=configs/clevr.py:smoke", "--config.train.ray_stages=((3,8),)",
      "--config.data.sampler=device"], "train.ray_stages needs data.sampler=host"),
    (["--config=configs/clevr.py:smoke", "--config.train.select_by=fg_ari"],
     "train.select_by must be one of ('nv_ari', 'min_fg_nv', 'psnr_novel'), got 'fg_ari'"),
    (["--config=configs/clevr.py:smoke", "--config.train.restart_check_step=4"],
     "train.restart_check_step=4 must be 0 (no check) or a multiple of train.eval_every=3"),
    (["--config=configs/clevr.py:smoke", "--config.train.ema_decay=1.0"],
     "train.ema_decay is 1.0; use 0 (off) or a value in (0, 1)"),
    (["--config=configs/clevr.py:smoke", "--mode=eval", "--params=mean"],
     "flag --params=mean: value should be one of <average|trained>"),
    (["--config=configs/clevr.py:smoke", "--mode=render", "--orbit_frames=x"],
     "flag --orbit_frames=x: invalid literal for int() with base 10: 'x'"),
    (["--config=configs/clevr.py:smoke", "--config.render.supersample=0"],
     "render.supersample is 0; it must be an integer ≥ 1"),
    (["--config=configs/clevr.py:smoke", "--config.model.encoder_output_stride=3"],
     "model.encoder_output_stride is 3; it must be one of (4, 2)"),
    (["--config=configs/clevr.py:smoke", "--config.model.encoder_input_pool=3"],
     "model.encoder_input_pool is 3; data.image_size 32 must divide by it"),
    (["--config=configs/clevr.py:smoke", "--config.train.ray_chunks=3"],
     "train.rays_per_scene=32 must be a multiple of train.ray_chunks=3"),
    (["--config=configs/clevr.py:smoke", "--mode=eval", "--config.train.ema_decay=-0.1"],
     "train.ema_decay is -0.1"),
    (["--config=configs/clevr.py:smoke", "--distributed", "--num_processes=2", "--process_id=0",
      "--coordinator_address=localhost:1", "--config.data.sampler=gpu"],
     "data.sampler is 'gpu'; use one of ('host', 'device')"),
])
def test_a_bad_command_line_gets_one_line_and_creates_nothing(tmp_path, args, message):
  # Only what needs the data or the run folder waits for JAX to start; a bad flag or config field
  # is reported before (slotlifter_jax/config_checks.py).
  shutil.copytree(os.path.join(REPO, "configs"), tmp_path / "configs")
  (tmp_path / "a_file").write_text("keep me")
  if not any(a.startswith("--workdir=") for a in args):
    args = args + ["--workdir=runs/new"]
  proc = subprocess.run([sys.executable, "-m", "slotlifter_jax.main", *args], cwd=tmp_path,
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 1
  lines = [l for l in proc.stderr.splitlines() if l and not l[:1] in "IW" or l.startswith("error")]
  errors = [l for l in lines if l.startswith("error")]
  assert len(errors) == 1 and message in errors[0], proc.stderr[-3000:]
  assert "Traceback" not in proc.stderr
  if not any(m in message for m in FOUND_AFTER_JAX_STARTS):
    assert "JAX devices" not in proc.stderr, proc.stderr[-3000:]
  assert not os.path.exists(tmp_path / "runs")
  assert (tmp_path / "a_file").read_text() == "keep me"
