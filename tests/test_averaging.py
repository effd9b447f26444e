"""The parameters' moving average (slotlifter_jax/averaging.py): the recurrence against NumPy, that
it never changes what trains, and that a trained run's evaluation reads it."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from slotlifter_jax import averaging
from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import evaluate
from slotlifter_jax import model as model_lib
from slotlifter_jax import train
from slotlifter_jax import train_step as step_lib
from train_helpers import fake_batch, final_params, load_config


@pytest.mark.parametrize("start", [0, 3])
def test_param_ema_follows_the_recurrence(start):
  """ema = θ at the first update and before `start`, then d·ema + (1 − d)·θ, θ after each
  update."""
  rng = np.random.default_rng(0)
  theta = {"a": rng.normal(size=(3, 2)).astype(np.float32), "b": np.float32(rng.normal())}
  updates = [{"a": rng.normal(size=(3, 2)).astype(np.float32), "b": np.float32(rng.normal())}
             for _ in range(7)]
  decay = 0.8
  tx = averaging.param_ema(decay, start)
  params = jax.tree.map(jnp.asarray, theta)
  state = tx.init(params)
  ref_theta = {k: np.float64(v) for k, v in theta.items()}
  ref_ema = dict(ref_theta)
  for t, u in enumerate(updates):
    out, state = tx.update(jax.tree.map(jnp.asarray, u), state, params)
    np.testing.assert_array_equal(out["a"], u["a"])  # the updates pass through untouched
    params = optax.apply_updates(params, out)
    for k in ref_theta:
      ref_theta[k] = ref_theta[k] + u[k]
      copy = t < max(start, 1)
      ref_ema[k] = ref_theta[k] if copy else decay * ref_ema[k] + (1 - decay) * ref_theta[k]
  assert int(state.count) == len(updates)
  for k in ref_ema:
    np.testing.assert_allclose(state.ema[k], ref_ema[k], rtol=1e-5, atol=1e-6)
  # Updates after the start: the average lags the parameters, it does not copy them.
  assert not np.allclose(state.ema["a"], params["a"], atol=1e-3)


@pytest.mark.parametrize("start", [0, 3])
def test_the_average_is_named_so_only_once_it_has_averaged(start):
  """chosen_params: before the first update after `start` (the first one for start 0) the
  average is a copy of the parameters, so they are named "trained"; from then on "average"."""
  import ml_collections
  from flax.training import train_state
  train_config = ml_collections.ConfigDict(dict(ema_decay=0.5, ema_start_step=start))
  tx = averaging.param_ema(0.5, start)
  params = {"w": jnp.arange(3.0)}
  state = train_state.TrainState.create(apply_fn=None, params=params, tx=tx)
  names = []
  for _ in range(5):
    names.append(averaging.chosen_params(state, train_config)[1])
    state = state.apply_gradients(grads={"w": jnp.ones(3)})
  names.append(averaging.chosen_params(state, train_config)[1])
  # Updates that copy: max(start, 1); the name changes after the first one that averages.
  copies = max(start, 1)
  assert names == ["trained"] * (copies + 1) + ["average"] * (5 - copies)
  params, name = averaging.chosen_params(state, train_config, "trained")
  assert name == "trained" and params is state.params


def test_the_average_does_not_change_what_trains():
  """The same gradients through scene's optimiser with and without the average move the parameters
  identically; only the average is added to the state."""
  config = load_config("clevr", "scene+smoke")
  rng = np.random.default_rng(1)
  params = {"encoder": {"w": jnp.asarray(rng.normal(size=(4, 3)), jnp.float32)},
            "colour_head": {"w": jnp.asarray(rng.normal(size=(3,)), jnp.float32)}}
  plain = step_lib.make_optimizer(config.train)
  config.train.ema_decay, config.train.ema_start_step = 0.9, 2
  averaged = step_lib.make_optimizer(config.train)
  p1, s1 = params, plain.init(params)
  p2, s2 = params, averaged.init(params)
  for _ in range(5):
    grads = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape), jnp.float32), params)
    u1, s1 = plain.update(grads, s1, p1)
    u2, s2 = averaged.update(grads, s2, p2)
    p1, p2 = optax.apply_updates(p1, u1), optax.apply_updates(p2, u2)
  jax.tree.map(np.testing.assert_array_equal, p1, p2)
  fresh = step_lib.TrainState(step=jnp.int32(0), params=params, opt_state=averaged.init(params),
                              nonfinite_in_row=jnp.int32(0), nonfinite_total=jnp.int32(0))
  assert averaging.eval_params(fresh, config.train) is params  # no update yet: nothing averaged
  ema = optax.tree_utils.tree_get(s2, "ema")
  assert not np.allclose(ema["encoder"]["w"], p2["encoder"]["w"])
  state = step_lib.TrainState(step=jnp.int32(5), params=p2, opt_state=s2,
                              nonfinite_in_row=jnp.int32(0), nonfinite_total=jnp.int32(0))
  assert averaging.eval_params(state, config.train) is ema
  config.train.ema_decay = 0.0
  assert averaging.eval_params(state, config.train) is p2


@pytest.mark.parametrize("decay, start", [(1.0, 0), (-0.1, 0), (0.9, -1)])
def test_bad_settings_name_the_field(decay, start, tmp_path):
  config = load_config()
  config.train.ema_decay, config.train.ema_start_step = decay, start
  field = "ema_decay" if start >= 0 else "ema_start_step"
  with pytest.raises(ValueError, match=f"train.{field} is"):
    step_lib.make_optimizer(config.train)
  with pytest.raises(train.ConfigError, match=f"train.{field} is"):
    train.train_and_evaluate(config, str(tmp_path / "run"))
  assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_run_with_the_average_is_evaluated_with_it(tmp_path):
  """A smoke run with the average on: its checkpoint holds both trees, evaluation restores the
  average (the trained parameters with params="trained"), and a config with the average off is
  refused by name rather than misread."""
  config = load_config()
  config.train.ema_decay, config.train.ema_start_step = 0.5, 2
  workdir = str(tmp_path / "run")
  train.train_and_evaluate(config, workdir)
  step, params = final_params(workdir, config)
  assert step == config.train.num_steps
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  abstract = step_lib.state_shapes(model, config, batch,
                                   sharding=jax.sharding.SingleDeviceSharding(jax.devices()[0]))
  manager = ckpt_lib.Checkpoints(workdir)
  state = manager.restore(abstract)
  manager.close()
  ema = optax.tree_utils.tree_get(state.opt_state, "ema")
  assert not all(np.allclose(a, b) for a, b in zip(jax.tree.leaves(ema), jax.tree.leaves(params)))
  run = evaluate.load_run(config, workdir, split="val", checkpoint="latest", max_scenes=1)
  jax.tree.map(np.testing.assert_array_equal, run.params, ema)
  assert run.parameters == "average"
  # --params=trained: the same checkpoint's trained parameters, for a pairing on one trajectory.
  trained = evaluate.load_run(config, workdir, split="val", checkpoint="latest", max_scenes=1,
                              params="trained")
  jax.tree.map(np.testing.assert_array_equal, trained.params, params)
  assert trained.parameters == "trained"
  with pytest.raises(evaluate.EvalSetupError, match=r"--params='mean': must be one of"):
    evaluate.load_run(config, workdir, split="val", checkpoint="latest", params="mean")
  off = load_config()
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match=r"train.ema_decay: saved 0.5"):
    evaluate.load_run(off, workdir, split="val", checkpoint="latest", max_scenes=1)
