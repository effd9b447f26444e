"""Collapse detection from slot usage on a fixed probe batch (docs/method.md §6).

Vocabulary (docs/method.md §0): K slots (the empty slot excluded, as in the rendered segmentation
of docs/method.md §1.5), N pixels or rays of one probe view; leading `...` dimensions are
independent views.

docs/method.md §6 names three ways a run collapses, reported for uORF, uOCF, OSRT and SlotLifter
without random masking: (1) all foreground in one slot, (2) a uniform segmentation (every pixel
shared evenly by all slots, so no slot means anything), (3) black renders. The statistics here are
cheap pure `jnp` functions of a rendered probe batch, so the trainer can log them at every
evaluation interval and flag a run, and they jit.

Thresholds and why:
- DOMINANT_SHARE = 0.9: in every synthetic set a view shows several objects (CLEVR 5–7; the room
  sets several chairs), so one slot owning > 90 % of the foreground means objects are merged.
  A view with a single object would trip it legitimately; `is_collapsed` therefore averages over
  the probe views and the probe batch should be drawn from multi-object scenes.
- MIN_ACTIVE_SLOTS = 2: fewer than two slots owning ≥ 1 % of the foreground (the docs/method.md §4
  definition of an active slot) is the same failure counted the other way.
- UNIFORM_ENTROPY = 0.9: the mean per-pixel slot entropy, normalised by log K (1 = uniform).
  A confident pixel (0.9 on one slot, rest spread) sits near 0.25 at K = 8, a pixel split evenly
  between two slots at 0.33; > 0.9 is only reached when nearly every pixel is close to 1/K.
  Uniform segmentations escape the share tests: their argmax is decided by noise.
  Early in training (slot noise and masking still annealing, docs/method.md §1.2–1.3) segmentations
  are legitimately diffuse; the flag means collapse only once those schedules have run.
- BLACK_RATIO = 0.1, MIN_TARGET_MEAN = 0.05: MSE pulls the mean colour into place first, so a
  trained renderer's mean intensity is close to the target's. A mean below a tenth of the target's
  means the density collapsed (no background colour is added, docs/method.md §1.5, so Σw ≈ 0 renders
  black). Targets darker than 0.05 on average are not judged.
"""

from __future__ import annotations

from typing import Optional

import flax
import jax
import jax.numpy as jnp

DOMINANT_SHARE = 0.9
MIN_ACTIVE_SLOTS = 2
ACTIVE_FRACTION = 0.01  # docs/method.md §4: a slot is active if it owns ≥ 1 % of the foreground
UNIFORM_ENTROPY = 0.9
BLACK_RATIO = 0.1
MIN_TARGET_MEAN = 0.05

_PROB_EPS = 1e-12  # keeps p·log p finite at p = 0 (its limit is 0)
_MASS_EPS = 1e-12  # guards divisions by an empty foreground


@flax.struct.dataclass
class SlotUsage:
  """How the foreground of each view is shared among the K slots."""

  share_per_slot: jax.Array  # [..., K] fraction of foreground pixels whose argmax is slot k
  largest_share: jax.Array  # [...] max_k share_per_slot
  active_slots: jax.Array  # [...] int32, slots with share ≥ min_fraction (and > 0)
  share_entropy: jax.Array  # [...] entropy of share_per_slot / log K, in [0, 1]
  pixel_entropy: jax.Array  # [...] mean over foreground pixels of H(M_n) / log K, 1 = uniform
  foreground_pixels: jax.Array  # [...] foreground weight Σ_n fg_n (0: view says nothing)


def settled_step(train_config) -> int:
  """From this step on, a collapse flag means collapse: before it, slot noise and masking are still
  annealing and diffuse segmentations are expected."""
  return max(int(train_config.mask_anneal_steps), int(train_config.noise_anneal_steps))


def _normalised_entropy(p: jax.Array) -> jax.Array:
  """Entropy over the last axis divided by log K (K = 1 gives 0)."""
  k = p.shape[-1]
  h = -jnp.sum(p * jnp.log(p + _PROB_EPS), axis=-1)
  return h / jnp.log(k) if k > 1 else jnp.zeros_like(h)


def slot_usage(
    *,
    segmentation: jax.Array,
    foreground_mask: Optional[jax.Array] = None,
    min_fraction: float = ACTIVE_FRACTION,
) -> SlotUsage:
  """Slot-usage statistics of rendered segmentations [..., N, K] (soft or one-hot).

  Ownership is by argmax, as in the evaluation (docs/method.md §4); rows are renormalised over the K
  real slots for the entropy. foreground_mask [..., N] (bool or {0, 1}) restricts the statistics to
  the ground-truth foreground; None uses every pixel (then the background slot counts as one of the
  slots, which is the right reading when no masks exist).
  """
  seg = jnp.asarray(segmentation, jnp.float32)
  k = seg.shape[-1]
  if foreground_mask is None:
    fg = jnp.ones(seg.shape[:-1], jnp.float32)
  else:
    fg = jnp.asarray(foreground_mask, jnp.float32)  # [..., N]
  seg = seg / jnp.maximum(seg.sum(axis=-1, keepdims=True), _MASS_EPS)
  mass = fg.sum(axis=-1)  # [...]
  safe_mass = jnp.maximum(mass, _MASS_EPS)

  owner = jax.nn.one_hot(jnp.argmax(seg, axis=-1), k, dtype=jnp.float32)  # [..., N, K]
  share = jnp.einsum("...n,...nk->...k", fg, owner) / safe_mass[..., None]  # [..., K]
  active = ((share > 0) & (share >= min_fraction)).sum(axis=-1).astype(jnp.int32)
  pixel_entropy = jnp.einsum("...n,...n->...", fg, _normalised_entropy(seg)) / safe_mass
  return SlotUsage(
      share_per_slot=share,
      largest_share=share.max(axis=-1),
      active_slots=active,
      share_entropy=_normalised_entropy(share),
      pixel_entropy=pixel_entropy,
      foreground_pixels=mass,
  )


@flax.struct.dataclass
class RenderBrightness:
  """Mean intensities of rendered and target colours per view, and the black-render flag."""

  rendered_mean: jax.Array  # [...]
  target_mean: jax.Array  # [...]
  black: jax.Array  # [...] bool


def black_render(
    *,
    rendered: jax.Array,
    target: jax.Array,
    max_ratio: float = BLACK_RATIO,
    min_target_mean: float = MIN_TARGET_MEAN,
) -> RenderBrightness:
  """Flags black renders: colours [..., N, 3] in [0, 1] (rendered vs ground truth) → per view.

  Black when the target is not itself dark (mean > min_target_mean) and the rendered mean is
  below max_ratio × the target mean.
  """
  rendered_mean = jnp.mean(jnp.asarray(rendered, jnp.float32), axis=(-2, -1))
  target_mean = jnp.mean(jnp.asarray(target, jnp.float32), axis=(-2, -1))
  black = (target_mean > min_target_mean) & (rendered_mean < max_ratio * target_mean)
  return RenderBrightness(rendered_mean=rendered_mean, target_mean=target_mean, black=black)


@flax.struct.dataclass
class CollapseVerdict:
  """Whether a run looks collapsed, with the reason(s)."""

  collapsed: jax.Array  # bool: any of the reasons below
  dominant_slot: jax.Array  # bool: one slot holds > max_share of the foreground
  too_few_active: jax.Array  # bool: fewer than min_active slots own ≥ 1 % of the foreground
  near_uniform: jax.Array  # bool: mean normalised pixel entropy > max_pixel_entropy
  black: jax.Array  # bool: renders black (False when no brightness was given)


def is_collapsed(
    usage: SlotUsage,
    *,
    brightness: Optional[RenderBrightness] = None,
    max_share: float = DOMINANT_SHARE,
    min_active: int = MIN_ACTIVE_SLOTS,
    max_pixel_entropy: float = UNIFORM_ENTROPY,
    max_ratio: float = BLACK_RATIO,
    min_target_mean: float = MIN_TARGET_MEAN,
    per_view: bool = False,
) -> CollapseVerdict:
  """Collapse verdict from slot usage (and optionally render brightness), thresholds as above.

  per_view=False (the run-level flag): the statistics are first averaged over all leading
  dimensions — the probe views — counting only views that have foreground, so a few single-object
  or empty views do not decide the verdict; brightness means are averaged over all views.
  per_view=True: one verdict per view, no averaging. The black test is re-applied here to the
  brightness means with this function's thresholds.
  """

  def view_mean(x: jax.Array, weight: jax.Array) -> jax.Array:
    return jnp.sum(x * weight) / jnp.maximum(jnp.sum(weight), _MASS_EPS)

  largest, active, entropy = usage.largest_share, usage.active_slots, usage.pixel_entropy
  has_fg = usage.foreground_pixels > 0
  if not per_view:
    weight = has_fg.astype(jnp.float32)
    largest = view_mean(largest, weight)
    active = view_mean(active.astype(jnp.float32), weight)
    entropy = view_mean(entropy, weight)
    has_fg = jnp.any(has_fg)
  dominant = has_fg & (largest > max_share)
  few = has_fg & (active < min_active)
  uniform = has_fg & (entropy > max_pixel_entropy)
  if brightness is None:
    black = jnp.zeros_like(dominant)
  else:
    rendered_mean, target_mean = brightness.rendered_mean, brightness.target_mean
    if not per_view:
      rendered_mean, target_mean = jnp.mean(rendered_mean), jnp.mean(target_mean)
    black = (target_mean > min_target_mean) & (rendered_mean < max_ratio * target_mean)
  return CollapseVerdict(
      collapsed=dominant | few | uniform | black,
      dominant_slot=dominant,
      too_few_active=few,
      near_uniform=uniform,
      black=black,
  )
