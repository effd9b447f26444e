"""Schedules against the closed forms of docs/method.md §1–2 (independent NumPy formulas)."""

import numpy as np
import pytest

from slotlifter_jax import defaults, schedules


@pytest.mark.parametrize("t", [0, 1, 2500, 9999, 10_000, 30_000, 77_777, 250_000])
def test_lr_factors_match_spec(t):
  backbone = schedules.backbone_lr_factor(t, floor=0.02, warmup_steps=10_000, decay_steps=50_000)
  head = schedules.head_lr_factor(t, floor=0.02, decay_steps=50_000)
  np.testing.assert_allclose(backbone, 0.02 + 0.98 * min(1, t / 10_000) * 0.5 ** (1.5 * t / 50_000),
                             rtol=1e-5)
  np.testing.assert_allclose(head, 0.02 + 0.98 * 0.5 ** (t / 50_000), rtol=1e-5)


@pytest.mark.parametrize("t", [0, 1, 7_500, 15_000, 29_999, 30_000, 100_000])
def test_keep_ratio_and_noise_match_spec(t):
  keep = schedules.keep_ratio(t, mask_max=0.99, anneal_steps=30_000)
  expected = 1 - (0.495 * np.cos(np.pi * t / 30_000) + 0.495) if t < 30_000 else 1.0
  np.testing.assert_allclose(keep, expected, atol=1e-6)
  sigma = schedules.slot_noise_sigma(t, anneal_steps=30_000)
  np.testing.assert_allclose(sigma, 0.5 * (1 + np.cos(np.pi * t / 30_000)) if t < 30_000 else 0.0,
                             atol=1e-6)


@pytest.mark.parametrize("t, expected", [
    (0, 0.01),  # masked share 0.99
    (10_000, 1 - (0.3 + 0.69 * 0.5)),  # halfway: masked share midway between 0.99 and 0.3
    (5_000, 1 - (0.3 + 0.69 * (np.cos(np.pi / 4) + 1) / 2)),
    (20_000, 0.7), (60_000, 0.7)])  # after the anneal the masked share stays at mask_min
def test_keep_ratio_with_a_masking_floor(t, expected):
  keep = schedules.keep_ratio(t, mask_max=0.99, anneal_steps=20_000, mask_min=0.3)
  np.testing.assert_allclose(keep, expected, atol=1e-6)


@pytest.mark.parametrize("t, release, expected", [
    (29_999, 30_000, 0.7),  # the floor holds until its release step…
    (30_000, 30_000, 1.0), (45_000, 30_000, 1.0),  # …and from then on no ray is masked
    (10_000, 5_000, 1 - 0.99 * 0.5),  # released inside the anneal: the paper's schedule there
    (0, 5_000, 0.01)])
def test_keep_ratio_floor_release(t, release, expected):
  keep = schedules.keep_ratio(t, mask_max=0.99, anneal_steps=20_000, mask_min=0.3,
                              mask_min_steps=release)
  np.testing.assert_allclose(keep, expected, atol=1e-6)


@pytest.mark.parametrize("t, expected", [
    (49_999, 0.5),  # held at 0.5 until the release starts
    (50_000, 0.5),  # the cosine starts at the floor itself: no jump
    (52_500, 1 - 0.5 * (np.cos(np.pi / 4) + 1) / 2),
    (55_000, 0.75),  # halfway through the release: half the floor
    (60_000, 1.0), (70_000, 1.0)])  # released in full after mask_min_release_steps
def test_keep_ratio_gradual_release(t, expected):
  keep = schedules.keep_ratio(t, mask_max=0.99, anneal_steps=20_000, mask_min=0.5,
                              mask_min_steps=50_000, mask_min_release_steps=10_000)
  np.testing.assert_allclose(keep, expected, atol=1e-6)


def test_gradual_release_needs_a_release_step():
  # Without a release step the floor holds for good, whatever the release length says.
  keep = schedules.keep_ratio(80_000, mask_max=0.99, anneal_steps=20_000, mask_min=0.5,
                              mask_min_release_steps=10_000)
  np.testing.assert_allclose(keep, 0.5, atol=1e-6)


def test_endpoints_and_locality():
  np.testing.assert_allclose(schedules.keep_ratio(0, mask_max=0.99, anneal_steps=30_000), 0.01,
                             atol=1e-6)
  assert float(schedules.slot_noise_sigma(0, anneal_steps=30_000)) == 1.0
  assert bool(schedules.locality_on(49_999, steps=50_000))
  assert not bool(schedules.locality_on(50_000, steps=50_000))
  assert not bool(schedules.locality_on(0, steps=0))


def test_all_schedules_reports_every_value():
  c = defaults.base_config().train
  s = schedules.all_schedules(12_345, c)
  assert set(s) == {"lr_backbone", "lr_head", "keep_ratio", "slot_noise_sigma", "locality"}
  np.testing.assert_allclose(s["lr_head"], 5e-5 * (0.02 + 0.98 * 0.5 ** (12_345 / 50_000)),
                             rtol=1e-5)


@pytest.mark.parametrize("name", ["lion", "adamw"])
def test_optimizer_matches_optax_with_each_group_schedule(name):
  """make_optimizer against optax's own Lion / AdamW run by hand on each parameter group with its
  own learning-rate schedule (head 1.0, backbone 0.02 at step 0, so a swapped group fails)."""
  import jax.numpy as jnp
  import optax
  from slotlifter_jax import train_step

  c = defaults.base_config().train
  c.optimizer = name
  c.warmup_steps, c.decay_steps = 3, 7
  params = {"colour_mlp": {"w": jnp.arange(5.0)}, "encoder": {"w": -jnp.arange(3.0)}}
  grads = {"colour_mlp": {"w": jnp.linspace(-2, 3, 5)}, "encoder": {"w": jnp.array([4.0, -1, 2])}}
  tx = train_step.make_optimizer(c)
  state = tx.init(params)
  clipped = optax.clip_by_global_norm(c.grad_clip).update(grads, optax.EmptyState())[0]
  for group, factor in (("colour_mlp", schedules.head_lr_factor(0, floor=c.lr_floor,
                                                                  decay_steps=c.decay_steps)),
                        ("encoder", schedules.backbone_lr_factor(
                            0, floor=c.lr_floor, warmup_steps=c.warmup_steps,
                            decay_steps=c.decay_steps))):
    lr = c.base_lr * float(factor)
    ref = (optax.lion(lr, b1=c.b1, b2=c.b2, weight_decay=c.weight_decay) if name == "lion" else
           optax.adamw(lr, b1=c.b1, b2=c.adam_b2, weight_decay=c.weight_decay))
    expected, _ = ref.update(clipped[group], ref.init(params[group]), params[group])
    got, _ = tx.update(grads, state, params)
    np.testing.assert_allclose(got[group]["w"], expected["w"], rtol=1e-6, atol=1e-12)
  c.optimizer = "sgd"
  with pytest.raises(ValueError, match="train.optimizer"):
    train_step.make_optimizer(c)


def test_slot_attention_follows_the_backbone_rate_times_its_scale():
  import jax
  import jax.numpy as jnp
  import optax
  from slotlifter_jax import train_step

  c = defaults.base_config().train
  c.warmup_steps, c.decay_steps, c.slot_attention_lr_scale = 3, 7, 0.5
  params = {"colour_mlp": {"w": jnp.arange(5.0)}, "encoder": {"w": -jnp.arange(3.0)},
            "slot_attention": {"w": jnp.array([0.5, -2.0])}}
  grads = {"colour_mlp": {"w": jnp.linspace(-2, 3, 5)}, "encoder": {"w": jnp.array([4.0, -1, 2])},
           "slot_attention": {"w": jnp.array([-1.0, 3.0])}}
  tx = train_step.make_optimizer(c)
  state = tx.init(params)
  clipped = optax.clip_by_global_norm(c.grad_clip).update(grads, optax.EmptyState())[0]
  backbone = c.base_lr * float(schedules.backbone_lr_factor(
      0, floor=c.lr_floor, warmup_steps=c.warmup_steps, decay_steps=c.decay_steps))
  head = c.base_lr * float(schedules.head_lr_factor(0, floor=c.lr_floor, decay_steps=c.decay_steps))
  got, _ = tx.update(grads, state, params)
  for group, lr in (("colour_mlp", head), ("encoder", backbone), ("slot_attention", 0.5 * backbone)):
    ref = optax.lion(lr, b1=c.b1, b2=c.b2, weight_decay=c.weight_decay)
    expected, _ = ref.update(clipped[group], ref.init(params[group]), params[group])
    np.testing.assert_allclose(got[group]["w"], expected["w"], rtol=1e-6, atol=1e-12)
  s = schedules.all_schedules(0, c)
  assert s["lr_slot_attention"] == pytest.approx(0.5 * backbone, rel=1e-6)
  c.slot_attention_lr_scale = 1.0  # the paper's: one backbone group, nothing extra logged
  assert "lr_slot_attention" not in schedules.all_schedules(0, c)
  assert set(jax.tree.leaves(train_step.param_groups(params))) == {"head", "backbone"}


def test_a_resume_that_would_drop_or_add_slot_attentions_group_refuses_naming_the_field():
  """The optimiser state has slot attention's group exactly when the scale is not 1, so a resume
  may move the scale between values other than 1 (the state trees are equal) but not across 1
  (they differ): check_compatible refuses that case in one line per direction, before restoring."""
  import json
  import jax
  import jax.numpy as jnp
  from slotlifter_jax import checkpoints, train_step

  params = {"colour_mlp": {"w": jnp.arange(5.0)}, "encoder": {"w": -jnp.arange(3.0)},
            "slot_attention": {"w": jnp.array([0.5, -2.0])}}
  def run_config(scale):
    config = defaults.base_config()
    config.train.slot_attention_lr_scale = scale
    return config
  def state_structure(scale):
    return jax.tree.structure(train_step.make_optimizer(run_config(scale).train).init(params))
  saved = json.loads(run_config(2.0).to_json_best_effort())
  assert state_structure(1.0001) == state_structure(2.0)
  checkpoints.check_compatible(run_config(1.0001), saved, "run")  # no error
  assert state_structure(1.0) != state_structure(2.0)
  with pytest.raises(checkpoints.CheckpointMismatchError,
                     match=r"train.slot_attention_lr_scale: saved 2.0, requested 1.0 \(the "
                           r"checkpoint holds slot attention's own optimiser group"):
    checkpoints.check_compatible(run_config(1.0), saved, "run")
  with pytest.raises(checkpoints.CheckpointMismatchError,
                     match=r"saved 1.0, requested 0.5 \(the checkpoint has no optimiser group"):
    checkpoints.check_compatible(run_config(0.5), json.loads(run_config(1.0).to_json_best_effort()),
                                 "run")


@pytest.mark.parametrize("t, expected", [
    (0, 1.0), (49_999, 1.0),  # full rate until the cooldown starts…
    (50_000, 1.0),  # …and the cosine starts at 1: no jump
    (52_500, 0.1 + 0.9 * (np.cos(np.pi / 4) + 1) / 2),
    (55_000, 0.55),  # halfway: midway between 1 and the final 0.1
    (60_000, 0.1), (65_000, 0.1)])  # the final factor at num_steps and beyond
def test_cooldown_factor(t, expected):
  factor = schedules.cooldown_factor(t, num_steps=60_000, cooldown_steps=10_000, final=0.1)
  np.testing.assert_allclose(factor, expected, atol=1e-6)


def test_cooldown_scales_both_rates():
  c = defaults.base_config().train
  c.num_steps, c.lr_cooldown_steps, c.lr_cooldown_final = 60_000, 10_000, 0.1
  t = 55_000
  backbone = 5e-5 * (0.02 + 0.98 * 0.5 ** (1.5 * t / 50_000))
  head = 5e-5 * (0.02 + 0.98 * 0.5 ** (t / 50_000))
  np.testing.assert_allclose(schedules.backbone_lr(t, c), 0.55 * backbone, rtol=1e-5)
  np.testing.assert_allclose(schedules.head_lr(t, c), 0.55 * head, rtol=1e-5)
  c.lr_cooldown_steps = 0  # off: the paper's rates
  np.testing.assert_allclose(schedules.backbone_lr(t, c), backbone, rtol=1e-5)
