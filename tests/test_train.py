"""Training: one step end to end, the non-finite guard, exact resume, and multi-device agreement."""

import importlib.util
import json
import os
import signal
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import collapse
from slotlifter_jax import model as model_lib
from slotlifter_jax import restarts
from slotlifter_jax import schedules
from slotlifter_jax import train
from slotlifter_jax import train_step as step_lib
from slotlifter_jax import validation

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_config(name="clevr", variant="smoke"):
  spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, "configs", f"{name}.py"))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


def fake_batch(config, *, seed=0, num_scenes=None):
  """A batch of the pipeline's shapes whose rays hit the region the source camera sees."""
  rng = np.random.default_rng(seed)
  b = num_scenes or config.train.batch_scenes
  v, r, s = config.data.num_source_views, config.train.rays_per_scene, config.data.image_size
  cam = np.eye(4, dtype=np.float32)
  cam[:3, 3] = [0.0, 0.0, -1.8]  # looking down +z at the origin
  intr = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]], np.float32)
  dirs = rng.normal(size=(b, r, 3)).astype(np.float32) * [0.2, 0.2, 0.0] + [0, 0, 1]
  return dict(
      source_images=rng.uniform(size=(b, v, s, s, 3)).astype(np.float32),
      source_cam_to_world=np.broadcast_to(cam, (b, v, 4, 4)).copy(),
      source_intrinsics=np.broadcast_to(intr, (b, v, 3, 3)).copy(),
      ray_origins=np.broadcast_to(cam[:3, 3], (b, r, 3)).astype(np.float32).copy(),
      ray_directions=(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)).astype(np.float32),
      target_rgb=rng.uniform(size=(b, r, 3)).astype(np.float32),
  )


def test_param_groups_split_head_from_backbone():
  config = load_config()
  model = model_lib.build_model(config)
  state = step_lib.init_state(model, config, fake_batch(config), jax.random.key(0))
  groups = jax.tree.leaves(step_lib.param_groups(state.params))
  assert "head" in groups and "backbone" in groups
  # The head (colour MLP, lifting and positional Linear) is a small fraction of the model.
  sizes = {g: 0 for g in ("head", "backbone")}
  for g, x in zip(groups, jax.tree.leaves(state.params)):
    sizes[g] += x.size
  assert sizes["head"] < sizes["backbone"]
  # With its own schedule, slot attention's parameters (and only they) form a third group.
  split = step_lib.param_groups(state.params, split_slot_attention=True)
  assert set(jax.tree.leaves(split["slot_attention"])) == {"slot_attention"}
  assert "slot_attention" not in {g for k, v in split.items() if k != "slot_attention"
                                  for g in jax.tree.leaves(v)}


def test_step_learns_and_nan_batch_is_skipped():
  config = load_config()
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  state = step_lib.init_state(model, config, batch, jax.random.key(0))
  step = step_lib.make_train_step(model, config, key=jax.random.key(1))
  before = jax.tree.map(np.array, state.params)
  state, m = step(state, batch)
  assert bool(m["finite"]) and np.isfinite(float(m["loss"]))
  assert int(state.step) == 1
  changed = jax.tree.leaves(jax.tree.map(lambda a, b: np.any(a != b), before, state.params))
  assert any(changed)

  bad = dict(batch, target_rgb=np.full_like(batch["target_rgb"], np.nan))
  good_params = jax.tree.map(np.array, state.params)
  good_opt = jax.tree.map(np.array, state.opt_state)
  for i in range(2):
    state, m = step(state, bad)
    assert not bool(m["finite"])
    assert int(m["nonfinite_in_row"]) == i + 1
  jax.tree.map(np.testing.assert_array_equal, good_params, jax.tree.map(np.array, state.params))
  jax.tree.map(np.testing.assert_array_equal, good_opt, jax.tree.map(np.array, state.opt_state))
  assert int(state.step) == 3 and int(state.nonfinite_total) == 2
  state, m = step(state, batch)
  assert bool(m["finite"]) and int(state.nonfinite_in_row) == 0


@pytest.mark.parametrize("ray_chunks", [1, 2])
def test_gradient_accumulation_matches_mean_of_chunk_gradients(ray_chunks):
  """2 scene chunks (× ray_chunks) give the mean of the chunk gradients, each with its own key;
  chunk i holds scenes of half i // ray_chunks and rays of part i % ray_chunks."""
  config = load_config()
  config.train.batch_scenes = 4
  config.train.grad_accum_chunks = 2
  config.train.ray_chunks = ray_chunks
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  state = step_lib.init_state(model, config, batch, jax.random.key(0))
  params = jax.tree.map(np.array, state.params)
  base_key = jax.random.key(1)
  _, m = step_lib.make_train_step(model, config, key=base_key)(state, batch)

  grad_fn = jax.jit(step_lib.make_grad_fn(model, config))
  sched = schedules.all_schedules(0, config.train)
  step_key = jax.random.fold_in(base_key, 0)
  rays = config.train.rays_per_scene // ray_chunks
  chunks = []
  for half in range(2):
    for part in range(ray_chunks):
      chunks.append({k: v[2 * half:2 * half + 2, part * rays:(part + 1) * rays]
                     if k in step_lib.RAY_KEYS else v[2 * half:2 * half + 2]
                     for k, v in batch.items()})
  outs = [grad_fn(params, h, jax.random.fold_in(step_key, i), sched) for i, h in enumerate(chunks)]
  mean_grads = jax.tree.map(lambda *g: sum(g) / len(g), *[o[1] for o in outs])
  mean_loss = sum(o[0][0] for o in outs) / len(outs)
  np.testing.assert_allclose(m["loss"], mean_loss, rtol=1e-5)
  np.testing.assert_allclose(m["grad_norm"], optax.tree.norm(mean_grads), rtol=1e-4)
  # …and it is not just one chunk's gradient.
  assert abs(float(optax.tree.norm(outs[0][1])) - float(m["grad_norm"])) > 1e-3


def _final_params(workdir, config):
  model = model_lib.build_model(config)
  abstract = step_lib.init_state(model, config, fake_batch(config), jax.random.key(0))
  manager = ckpt_lib.Checkpoints(workdir)
  state = manager.restore(abstract)
  manager.close()
  return int(state.step), state.params


def _straight_and_interrupted_runs(config, tmp_path, monkeypatch, factory: str):
  """Trains `config` straight, then again with SIGINT during the 3rd call of the compiled step
  that step_lib.<factory> makes (the loop checkpoints and leaves) and a resume; checks that both
  end at step 6 with identical parameters."""
  train.train_and_evaluate(config, str(tmp_path / "straight"))
  real_make = getattr(step_lib, factory)
  def make_interrupting(*args, **kwargs):
    inner = real_make(*args, **kwargs)
    calls = {"n": 0}
    def step(state, data):
      calls["n"] += 1
      if calls["n"] == 3:
        os.kill(os.getpid(), signal.SIGINT)
      return inner(state, data)
    return step
  monkeypatch.setattr(step_lib, factory, make_interrupting)
  with pytest.raises(train.Interrupted) as interrupted:
    train.train_and_evaluate(load_config_with(config), str(tmp_path / "resumed"))
  assert (interrupted.value.signum, interrupted.value.step) == (signal.SIGINT, 3)
  assert _final_params(str(tmp_path / "resumed"), config)[0] == 3
  monkeypatch.setattr(step_lib, factory, real_make)
  train.train_and_evaluate(load_config_with(config), str(tmp_path / "resumed"))

  step_a, params_a = _final_params(str(tmp_path / "straight"), config)
  step_b, params_b = _final_params(str(tmp_path / "resumed"), config)
  assert step_a == step_b == 6
  jax.tree.map(np.testing.assert_array_equal, params_a, params_b)


@pytest.mark.slow
def test_resume_after_interrupt_is_exact(tmp_path, monkeypatch):
  config = load_config()
  config.train.num_steps = 6
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_step")

  # Resuming with another learning rate keeps the record of the first one.
  changed = load_config_with(config)
  changed.train.base_lr = config.train.base_lr * 0.5
  train.train_and_evaluate(changed, str(tmp_path / "straight"))
  with open(tmp_path / "straight" / "config_history.jsonl") as f:
    history = [json.loads(line) for line in f]
  assert [(h["step"], h["changes"]) for h in history] == [
      (6, {"train.base_lr": [config.train.base_lr, changed.train.base_lr]})]
  with open(tmp_path / "straight" / "config.json") as f:
    assert json.load(f)["train"]["base_lr"] == changed.train.base_lr


@pytest.mark.slow
def test_staged_run_changes_its_batch_and_resumes_exactly(tmp_path, monkeypatch):
  """Stages of scenes and rays that start at the interrupted step: the step compiles for the new
  ray count, and the resumed run still ends bit-identical to the straight one."""
  config = load_config()
  config.train.num_steps = 6
  config.data.scene_stages = ((0, 2), (3, config.data.num_train_scenes))
  config.train.ray_stages = ((3, 2 * config.train.rays_per_scene),)
  seen = []
  real_assemble = step_lib.assemble_batch
  def recording(batch, *args, **kwargs):
    seen.append((batch["target_rgb"].shape[1], set(batch["scene_index"].tolist())))
    return real_assemble(batch, *args, **kwargs)
  monkeypatch.setattr(step_lib, "assemble_batch", recording)
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_step")
  r = config.train.rays_per_scene
  straight = seen[:6]  # the straight run's batches come first
  assert [rays for rays, _ in straight] == [r] * 3 + [2 * r] * 3
  assert set().union(*(scenes for _, scenes in straight[:3])) <= {0, 1}


@pytest.mark.slow
def test_device_sampled_run_resumes_exactly_and_records_its_clock(tmp_path, monkeypatch):
  """data.sampler=device: batches drawn inside the step are a function of (seed, step), so an
  interrupted and resumed run ends bit-identical; every record carries the run's wall clock,
  which a resume continues, and the run writes emergence.json."""
  config = load_config()
  config.data.sampler = "device"
  config.train.num_steps = 6
  _straight_and_interrupted_runs(config, tmp_path, monkeypatch, "make_train_block")
  with open(tmp_path / "resumed" / "metrics.jsonl") as f:
    records = [json.loads(line) for line in f]
  clock = [r["wall_s"] for r in records]
  assert all(b >= a for a, b in zip(clock, clock[1:])), clock  # continues across the resume
  assert [r["step"] for r in records if r["kind"] == "val"] == [3, 6]
  with open(tmp_path / "resumed" / "emergence.json") as f:
    assert json.load(f)["num_validations"] == 2


def test_sampler_settings_are_checked_before_training(tmp_path):
  config = load_config()
  config.train.steps_per_dispatch = 2
  with pytest.raises(ValueError, match="steps_per_dispatch=2 needs data.sampler=device"):
    train.train_and_evaluate(config, str(tmp_path / "a"))
  config.data.sampler = "device"
  config.train.log_every = 3
  with pytest.raises(ValueError, match="train.log_every=3 is not a multiple of "
                                       "train.steps_per_dispatch=2"):
    train.train_and_evaluate(config, str(tmp_path / "b"))
  config.data.sampler = "disk"
  with pytest.raises(ValueError, match="data.sampler is 'disk'"):
    train.train_and_evaluate(config, str(tmp_path / "c"))
  config = load_config()
  config.data.scene_stages = ((0, 2), (3, config.data.num_train_scenes + 1))
  with pytest.raises(train.ConfigError, match=r"data.scene_stages: 5 \(stage from step 3\) must "
                                              r"lie in \[1, 4\]"):
    train.train_and_evaluate(config, str(tmp_path / "d"))
  config = load_config()
  config.train.ray_chunks = 2
  config.train.ray_stages = ((3, 9),)
  with pytest.raises(train.ConfigError, match=r"train.ray_stages: 9 \(stage from step 3\) is not "
                                              r"a multiple of 2"):
    train.train_and_evaluate(config, str(tmp_path / "e"))
  config.train.ray_stages = ((3, 8),)
  config.data.sampler = "device"
  with pytest.raises(train.ConfigError, match="train.ray_stages needs data.sampler=host"):
    train.train_and_evaluate(config, str(tmp_path / "f"))
  assert not os.listdir(tmp_path)  # no run folder is created for a config that cannot train
  (tmp_path / "file").write_text("")
  with pytest.raises(FileExistsError, match="file: exists and is not a directory"):
    train.train_and_evaluate(load_config(), str(tmp_path / "file"))


def load_config_with(config):
  return config.copy_and_resolve_references()


@pytest.mark.slow
def test_four_devices_match_one_device():
  script = textwrap.dedent(f"""
    import os, sys
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=4"
    sys.path.insert(0, {os.path.join(REPO, "tests")!r})
    import jax, numpy as np
    from test_train import load_config, fake_batch
    from slotlifter_jax import model as model_lib, train_step as step_lib
    assert len(jax.devices()) == 4
    config = load_config()
    config.train.batch_scenes = 4
    model = model_lib.build_model(config)
    batches = [fake_batch(config, seed=i) for i in range(3)]
    losses = {{}}
    for n in (1, 4):
      mesh = step_lib.make_mesh(jax.devices()[:n])
      state = step_lib.init_state(model, config, batches[0], jax.random.key(0))
      state = jax.device_put(state, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
      step = step_lib.make_train_step(model, config, key=jax.random.key(1), mesh=mesh)
      out = []
      for b in batches:
        state, m = step(state, step_lib.shard_batch(b, mesh))
        out.append(float(m["loss"]))
      losses[n] = out
    print("losses", losses)
    np.testing.assert_allclose(losses[1], losses[4], rtol=1e-4)
  """)
  result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)
  assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("trigger", ["collapsed", "score"])
def test_abandoned_attempt_is_kept_and_the_run_restarts_from_a_new_seed(trigger, tmp_path,
                                                                        monkeypatch):
  config = load_config()
  config.train.restarts = 2
  if trigger == "score":
    config.train.restart_check_step = config.train.eval_every
    config.train.restart_min_score = 0.5
  real_run = validation.Validator.run
  calls = {"n": 0}
  def run_failing_the_first_validation(self, params, step):
    result = real_run(self, params, step)
    calls["n"] += 1
    first = calls["n"] == 1  # the first validation of seed 0
    result["collapsed"] = 1.0 if first and trigger == "collapsed" else 0.0
    result["score"] = 0.4 if first else 0.9  # below, then above, restart_min_score
    return result
  monkeypatch.setattr(validation.Validator, "run", run_failing_the_first_validation)
  workdir = str(tmp_path / "run")
  assert collapse.settled_step(config.train) <= config.train.eval_every  # the first flag counts
  train.train_and_evaluate(config, workdir)

  archive = os.path.join(workdir, restarts.RESTARTED_DIR, "seed_0")
  with open(os.path.join(archive, "metrics.jsonl")) as f:
    first = [json.loads(line) for line in f]
  assert max(r["step"] for r in first) == config.train.eval_every  # stopped at that validation
  assert os.path.isdir(os.path.join(archive, "checkpoints"))  # nothing was deleted
  with open(os.path.join(archive, "restart.json")) as f:
    why = json.load(f)
  assert why["seed"] == 0 and why["step"] == config.train.eval_every
  assert why["reason"].startswith("collapsed" if trigger == "collapsed" else "selection score")
  with open(os.path.join(workdir, "config.json")) as f:
    saved = json.load(f)
  # Not seed 1: a seed's second attempt must not be another seed's first. One restart of two
  # is spent, so one is left.
  assert saved["seed"] == restarts.SEED_STRIDE and saved["train"]["restarts"] == 1
  assert _final_params(workdir, config)[0] == config.train.num_steps
  # The clock goes on across the restart: the run's wall time includes the abandoned attempt.
  with open(os.path.join(workdir, "metrics.jsonl")) as f:
    second = [json.loads(line) for line in f]
  assert min(r["wall_s"] for r in second) > max(r["wall_s"] for r in first)
  # The same command again resumes the new attempt (already finished) instead of starting over.
  train.train_and_evaluate(config, workdir)
  assert sorted(os.listdir(os.path.join(workdir, restarts.RESTARTED_DIR))) == ["seed_0"]


def test_restart_reasons_and_config_checks():
  config = load_config()
  t = config.train
  t.restart_check_step, t.restart_min_score = 2 * t.eval_every, 0.55
  settled = collapse.settled_step(t)
  ok = dict(collapsed=0.0, score=0.60)
  assert restarts.reason(t, t.restart_check_step, ok) is None
  assert restarts.reason(t, t.restart_check_step, dict(ok, score=0.55)) is None  # not below
  assert "0.540" in restarts.reason(t, t.restart_check_step, dict(ok, score=0.54))
  assert restarts.reason(t, t.eval_every, dict(ok, score=0.0)) is None  # only at the check step
  assert restarts.reason(t, settled, dict(ok, collapsed=1.0)) == "collapsed"
  if settled > 0:
    assert restarts.reason(t, settled - 1, dict(ok, collapsed=1.0)) is None
  assert restarts.config_problem(t) is None
  t.restart_check_step = t.eval_every + 1
  assert "train.restart_check_step" in restarts.config_problem(t)
  t.restart_check_step, t.restarts = 0, -1
  assert "train.restarts=-1 must be ≥ 0" in restarts.config_problem(t)


@pytest.mark.parametrize("select_by, has_masks, expected", [
    ("nv_ari", True, 0.84),
    ("min_fg_nv", True, 0.61),  # the objects merged while the scene split improved: FG-ARI rules
    ("psnr_novel", True, 26.0),
    ("min_fg_nv", False, 26.0),  # no masks, no ARI: novel-view PSNR whatever was asked
])
def test_selection_score(select_by, has_masks, expected):
  result = {"fg_ari": 0.61, "nv_ari": 0.84, "psnr_novel": 26.0}
  assert validation.selection_score(result, select_by, has_masks=has_masks) == pytest.approx(
      expected)


def test_selection_score_without_a_foreground_ranks_last():
  # FG-ARI is NaN when no validation view shows an object; min() must not drop it silently.
  result = {"fg_ari": float("nan"), "nv_ari": 0.9, "psnr_novel": 30.0}
  assert validation.selection_score(result, "min_fg_nv", has_masks=True) == -1.0
  assert validation.selection_score(result, "nv_ari", has_masks=True) == pytest.approx(0.9)


def test_each_restart_spends_one_of_the_restarts(tmp_path):
  # The loop hands the next attempt the config archive_and_reseed returns; train_and_evaluate
  # then passes it through resumed_seed with whatever config.json the folder holds.
  config = load_config()
  config.train.restarts = 2
  workdir = str(tmp_path / "run")
  ckpt_lib.save_config(config, workdir)
  attempt = config
  for seed, left in ((restarts.SEED_STRIDE, 1), (2 * restarts.SEED_STRIDE, 0)):
    nxt = restarts.archive_and_reseed(attempt, workdir, 14_000, "test")
    assert (nxt.seed, nxt.train.restarts) == (seed, left)
    attempt = restarts.resumed_seed(nxt, ckpt_lib.load_saved_config(workdir), workdir)
    assert (attempt.seed, attempt.train.restarts) == (seed, left)
    # The command line's config, run again in that folder, goes on with the same attempt.
    again = restarts.resumed_seed(config, ckpt_lib.load_saved_config(workdir), workdir)
    assert (again.seed, again.train.restarts) == (seed, left)
  archived = restarts.archived_attempts(workdir)
  assert [os.path.basename(a) for a in archived] == ["seed_0", f"seed_{restarts.SEED_STRIDE}"]
  with open(os.path.join(archived[1], "config.json")) as f:
    assert json.load(f)["train"]["restarts"] == 1  # each attempt keeps the config it ran with


def test_a_run_stopped_between_two_attempts_goes_on_with_the_next_seed(tmp_path):
  config = load_config()
  config.train.restarts = 2
  workdir = tmp_path / "run"
  os.makedirs(workdir / restarts.RESTARTED_DIR / "seed_0")
  # Nothing saved yet for the next attempt: seed 0 was abandoned, so the run is seed 1000's.
  resumed = restarts.resumed_seed(config, None, str(workdir))
  assert (resumed.seed, resumed.train.restarts) == (restarts.SEED_STRIDE, 1)
  # Saved by that attempt: its own seed and restarts left, whatever the command line says.
  saved = dict(seed=restarts.SEED_STRIDE, train=dict(restarts=1))
  resumed = restarts.resumed_seed(config, saved, str(workdir))
  assert (resumed.seed, resumed.train.restarts) == (restarts.SEED_STRIDE, 1)
  # No attempt archived: the command line's config as it is.
  assert restarts.resumed_seed(config, None, str(tmp_path / "fresh")) is config
