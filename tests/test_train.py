"""Training: one step end to end, the non-finite guard, gradient accumulation and the sampler's
config checks. Exact resume is in test_train_resume.py, restarts in test_restarts.py, sharding in
test_data_parallel.py: separate files, so that pytest-xdist (which hands out whole files) can run
them on different workers."""

import os

import jax
import numpy as np
import optax
import pytest

from slotlifter_jax import model as model_lib
from slotlifter_jax import schedules
from slotlifter_jax import train
from slotlifter_jax import train_step as step_lib
from train_helpers import fake_batch, load_config


def test_init_weights_are_flax_init_on_the_whole_batch_at_the_default_compile_level():
  """init_state inits on one scene and one ray, compiled at LLVM -O1 on a CPU: its weights are,
  bit for bit, flax's init of the whole batch compiled at XLA's default level, whatever keys the
  other random streams get."""
  config = load_config()
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  key = jax.random.key(3)
  state = step_lib.init_state(model, config, batch, key)
  rngs = {"params": key, **{s: jax.random.key(100 + i) for i, s in enumerate(step_lib.RNG_STREAMS)}}
  reference = jax.jit(lambda rngs, inputs: model.init(
      rngs, **inputs, slot_noise_sigma=1.0, keep_ratio=1.0, locality=True, train=False),
      # XLA's defaults, not the suite's (tests/conftest.py): level 3, the fusion emitters.
      compiler_options={"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True})(
          rngs, step_lib.model_inputs(batch, signed_colour=False))["params"]
  assert batch["ray_directions"].shape[:2] == (2, 32)  # the reference saw the whole batch
  jax.tree.map(np.testing.assert_array_equal, state.params, reference)


def test_param_groups_split_head_from_backbone():
  config = load_config()
  model = model_lib.build_model(config)
  state = step_lib.state_shapes(model, config, fake_batch(config))  # the groups need no weights
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


LEARN_STEPS = 40


def test_step_learns_and_nan_batch_is_skipped():
  """A short run on one batch: its training loss falls over the steps (the mean of the last five
  well below that of the first five), and a non-finite batch changes nothing. The target is one
  grey, which the model can fit within a few dozen steps (random colours leave mostly noise to
  fit), and the learning rate is held at its base (the smoke schedule halves it every 10 steps)."""
  config = load_config()
  config.train.decay_steps = 10**6
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  batch = dict(batch, target_rgb=np.full_like(batch["target_rgb"], 0.2))
  state = step_lib.init_state(model, config, batch, jax.random.key(0))
  step = step_lib.make_train_step(model, config, key=jax.random.key(1))
  losses = []
  for _ in range(LEARN_STEPS):
    state, m = step(state, batch)
    assert bool(m["finite"]) and np.isfinite(float(m["loss"]))
    losses.append(float(m["loss"]))
  assert int(state.step) == LEARN_STEPS
  first, last = np.mean(losses[:5]), np.mean(losses[-5:])
  assert last < 0.8 * first, np.round(losses, 4)

  bad = dict(batch, target_rgb=np.full_like(batch["target_rgb"], np.nan))
  good_params = jax.tree.map(np.array, state.params)
  good_opt = jax.tree.map(np.array, state.opt_state)
  for i in range(2):
    state, m = step(state, bad)
    assert not bool(m["finite"])
    assert int(m["nonfinite_in_row"]) == i + 1
  jax.tree.map(np.testing.assert_array_equal, good_params, jax.tree.map(np.array, state.params))
  jax.tree.map(np.testing.assert_array_equal, good_opt, jax.tree.map(np.array, state.opt_state))
  assert int(state.step) == LEARN_STEPS + 2 and int(state.nonfinite_total) == 2
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
