"""Every schedule of docs/method.md §2 as a pure function of the step `t` (traced or Python int).

Keeping them pure means the jitted train step computes them from `state.step`, a resumed run
continues them exactly, and the training metrics can report them.
"""

import jax.numpy as jnp


def backbone_lr_factor(t, *, floor: float, warmup_steps: int, decay_steps: int):
  """Encoder, slot attention, allocation transformers: floor + (1−floor)·min(1, t/warm)·0.5^(1.5·t/decay)."""
  t = jnp.asarray(t, jnp.float32)
  warm = jnp.minimum(1.0, t / max(warmup_steps, 1))
  return floor + (1.0 - floor) * warm * 0.5 ** (1.5 * t / decay_steps)


def head_lr_factor(t, *, floor: float, decay_steps: int):
  """Colour MLP, lifting Linear, positional Linear: floor + (1−floor)·0.5^(t/decay), no warm-up."""
  t = jnp.asarray(t, jnp.float32)
  return floor + (1.0 - floor) * 0.5 ** (t / decay_steps)


def cooldown_factor(t, *, num_steps: int, cooldown_steps: int, final: float):
  """1 until step num_steps − cooldown_steps, then a cosine down to `final` at num_steps.

  Not in the paper (whose rates decay over 250 000 steps): a run held near its base rate ends
  while Lion still moves every weight by ±lr a step; lowering the rate over the last steps lets
  it settle (docs/method.md §2). cooldown_steps = 0: no cooldown.
  """
  t = jnp.asarray(t, jnp.float32)
  if cooldown_steps <= 0:
    return jnp.ones_like(t)
  return final + (1.0 - final) * _cosine_after(t, num_steps - cooldown_steps, cooldown_steps)


def _cooldown(t, c):
  return cooldown_factor(t, num_steps=c.num_steps, cooldown_steps=c.get("lr_cooldown_steps", 0),
                         final=c.get("lr_cooldown_final", 0.1))


def backbone_lr(t, train_config):
  """The backbone's learning rate at step t: base_lr · backbone_lr_factor · cooldown. The one
  definition that both the optimiser (train_step.make_optimizer) and the logged `lr_backbone`
  use, so the number in the metrics is the rate that was applied."""
  c = train_config
  return c.base_lr * _cooldown(t, c) * backbone_lr_factor(
      t, floor=c.lr_floor, warmup_steps=c.warmup_steps, decay_steps=c.decay_steps)


def head_lr(t, train_config):
  """The head's learning rate at step t: base_lr · head_lr_factor · cooldown (optimiser and
  `lr_head`)."""
  c = train_config
  return c.base_lr * _cooldown(t, c) * head_lr_factor(t, floor=c.lr_floor,
                                                      decay_steps=c.decay_steps)


def has_slot_attention_group(train_config) -> bool:
  """Whether slot attention has a rate of its own (optimiser group and logged `lr_slot_attention`)."""
  return train_config.get("slot_attention_lr_scale", 1.0) != 1.0


def slot_attention_lr(t, train_config):
  """Slot attention's learning rate at step t: the backbone's times `slot_attention_lr_scale`."""
  return backbone_lr(t, train_config) * train_config.get("slot_attention_lr_scale", 1.0)


def _cosine_to_zero(t, steps: int):
  """1 at t = 0, cosine down to 0 at t = steps, 0 afterwards."""
  t = jnp.asarray(t, jnp.float32)
  if steps <= 0:
    return jnp.zeros_like(t)
  return jnp.where(t < steps, 0.5 * (jnp.cos(jnp.pi * t / steps) + 1.0), 0.0)


def _cosine_after(t, start, steps: int):
  """1 before step `start`, then cosine down to 0 over `steps` steps (at once when 0), then 0:
  the floor's release and the learning-rate cooldown."""
  t = jnp.asarray(t, jnp.float32)
  return jnp.where(t < start, 1.0, _cosine_to_zero(jnp.maximum(t - start, 0.0), steps))


def keep_ratio(t, *, mask_max: float, anneal_steps: int, mask_min: float = 0.0,
               mask_min_steps: int = 0, mask_min_release_steps: int = 0):
  """Fraction of rays that keep their lifted features (docs/method.md §1.3).

  keep(t) = 1 − m − (mask_max − m)·(cos(π t/T)+1)/2 for t < T, else 1 − m, where the floor m is
  mask_min until step mask_min_steps (0: for good), then lowered to 0 along a cosine over
  mask_min_release_steps steps (0: at once), m = mask_min·(cos(π (t − S)/R)+1)/2 for
  S ≤ t < S + R. With mask_max = 0.99 and
  mask_min = 0 (the paper's) the masking ratio anneals 0.99 → 0, i.e.
  1 − (0.495 cos(π t/30 000) + 0.495). A floor leaves that share of rays masked after the anneal,
  so the slots keep carrying their rendering; its release lets every ray use its lifted features
  for the last steps, and a gradual release hands the rays back a few at a time.
  """
  t = jnp.asarray(t, jnp.float32)
  if mask_min_steps <= 0:
    floor = mask_min
  else:
    floor = mask_min * _cosine_after(t, mask_min_steps, mask_min_release_steps)
  return 1.0 - floor - (mask_max - floor) * _cosine_to_zero(t, anneal_steps)


def slot_noise_sigma(t, *, anneal_steps: int):
  """σ of the slot initialisation noise (docs/method.md §1.2), cosine-annealed 1 → 0."""
  return _cosine_to_zero(t, anneal_steps)


def locality_on(t, *, steps: int):
  """The locality constraint (docs/method.md §1.4) holds for the first `steps` steps."""
  return jnp.asarray(t) < steps


def all_schedules(t, train_config) -> dict:
  """The schedule values for step t, as reported in the training metrics."""
  c = train_config
  rates = dict(lr_backbone=backbone_lr(t, c), lr_head=head_lr(t, c))
  if has_slot_attention_group(c):
    rates["lr_slot_attention"] = slot_attention_lr(t, c)
  return dict(
      **rates,
      keep_ratio=keep_ratio(t, mask_max=c.mask_max, anneal_steps=c.mask_anneal_steps,
                            mask_min=c.get("mask_min", 0.0),
                            mask_min_steps=c.get("mask_min_steps", 0),
                            mask_min_release_steps=c.get("mask_min_release_steps", 0)),
      slot_noise_sigma=slot_noise_sigma(t, anneal_steps=c.noise_anneal_steps),
      locality=locality_on(t, steps=c.locality_steps),
  )
