"""Allocation transformer, point-slot mapping, slot density and colour MLP (docs/method.md §1.4).

Shapes: B scenes, R rays per scene, S samples per ray, K slots (K+1 with the empty slot s_∅ at
index 0), Ds slot width (256), C point width (64).

Point features F_p [B, R, S, C] attend to S' = [s_∅, s_1 … s_K] [B, K+1, Ds] through 4 pre-LN
blocks; one block (the official `TransformerDecoderBlock`):

  x = CrossAttn(LN(h), S')                   4 heads, projection width C
  x = ReLU(Conv1d_k3_same(x))                along the S samples of each ray
  h = h + Dropout(x)
  h = h + Dropout(FFN(x))                    FFN = LN → C→4C ReLU → C, on the branch x (official)
  h = h + SelfAttn(LN(h))                    along the ray, projection width 16, 4 heads

then a final LayerNorm. The mapping turns the result into point-slot weights
W = softmax(q(h)·k(S')ᵀ/√C) over K+1, the slot feature F_s = Linear(W·S'), and the slot-based
density σ = exp(s_σ)·Σ_{k≥1} W_k·ReLU(A_k). The colour MLP maps F_s + E_p to RGB.

With `fold_products` (the model's `model.fold_products`, off by default) the cross-attention and
the mapping compute these functions with the per-point Linears folded into per-scene matrices
built from the K+1 slots (`folded.py`): the same parameters and
the same function to float32 rounding, with fewer per-point products, but not the same rounding,
so a run is not the run it would be without it (experiments/journal/2026-12.md, "Folded products").

`density_mode="mlp"` is the paper's "without slot-based density" ablation (docs/method.md §5): σ
comes from a small head on h instead (`mlp_density`); W, F_s and the colour are unchanged.

Initialisers follow the official code's `linear` helper: xavier-uniform kernels and zero biases;
the attention output projections and the FFN's last layer use xavier-uniform with gain
(3·num_blocks)^-½ (variance scaled by 1/12 for 4 blocks); the FFN's first layer and the colour
MLP's hidden layers are kaiming-uniform (he_uniform); the Conv1d keeps PyTorch's default init.

`remat_scan=True` runs the blocks as one `nn.scan` over stacked parameters with `nn.remat` on the
body (docs/performance.md §4: the only layout in which rematerialisation lowers memory on
XLA:CPU). Dropout is written by hand with a traced rate so the per-block rates can be scanned, and
the dropout keys are split once at the top so both layouts compute the same function with the same
randomness.

`dtype` (the model's `model.dtype`, model.py) is the computation dtype of every Linear and of the
attention and mapping products; the softmaxes (attention, W), the LayerNorm statistics, the
residual stream h and what leaves for volume rendering (W, A, σ, colour) are float32.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax.encoder import torch_default_bias_init, torch_default_kernel_init
from slotlifter_jax.folded import CrossAttention, LinearParams, folded_mapping, xavier

# PyTorch's LayerNorm default, kept to match the official model.
LAYER_NORM_EPS = 1e-5
# The locality constraint sets logits to this instead of −∞: softmax still gives exactly 0 weight
# (exp underflows) but a fully masked row, or a gradient through the masked entries, cannot
# produce NaN the way −∞ − (−∞) does.
MASKED_LOGIT = -1e9
# LeakyReLU slope of the colour MLP (PyTorch's default).
LEAKY_SLOPE = 0.01


# ---------------------------------------------------------------------------------------------
# Pure functions.


# Dropout decisions are made on 16-bit uniforms: keep iff u16 < round(keep·2^16). The keep
# probability is then exact to 2^-17 (rate 0.0667 becomes 0.06667 ± 8e-6), and one 32-bit random
# word serves two masks. Random bits were a large share of the paper-sized step on CPU
# (docs/performance.md §2).
_U16 = 1 << 16


def paired_dropout(x: jax.Array, y: jax.Array, *, rate, key: jax.Array):
  """Inverted dropout on two same-shape arrays from one draw of 32-bit words (16 bits each).

  `rate` may be traced; rate = 0 keeps everything exactly. Returns (dropout(x), dropout(y)).
  """
  keep_prob = 1.0 - rate
  threshold = jnp.round(jnp.asarray(keep_prob, jnp.float32) * _U16).astype(jnp.uint32)
  bits = jax.random.bits(key, x.shape, jnp.uint32)
  keep_x = (bits & (_U16 - 1)) < threshold
  keep_y = (bits >> 16) < threshold
  scale = _U16 / threshold.astype(jnp.float32)  # 1 / the keep probability actually used
  return (jnp.where(keep_x, x * scale, jnp.zeros_like(x)),
          jnp.where(keep_y, y * scale, jnp.zeros_like(y)))


def conv1d_taps(x: jax.Array) -> jax.Array:
  """[..., S, C] → [..., S, 3C]: [x_{s−1}, x_s, x_{s+1}] with zeros beyond the ends.

  A Dense(3C → C) on this is exactly Conv1d(C, C, kernel 3, padding 1) along S (PyTorch's tap k
  multiplies x_{s+k−1}), and avoids lax.conv, whose weight gradient is pathological inside
  nn.scan on XLA:CPU (docs/performance.md §3).
  """
  zero = jnp.zeros_like(x[..., :1, :])
  prev = jnp.concatenate([zero, x[..., :-1, :]], axis=-2)  # [..., S, C]
  nxt = jnp.concatenate([x[..., 1:, :], zero], axis=-2)
  return jnp.concatenate([prev, x, nxt], axis=-1)  # [..., S, 3C]


def dot_product_attention(*, q: jax.Array, k: jax.Array, v: jax.Array) -> jax.Array:
  """Multi-head scaled dot-product attention.

  q [..., T, H, dq], k [..., L, H, dq], v [..., L, H, dv] with equal leading dims →
  [..., T, H, dv]; softmax over the L keys, scale dq^-½. Both products run in the inputs' dtype,
  the scaling and softmax in float32.
  """
  logits = jnp.einsum("...thd,...lhd->...htl", q, k).astype(jnp.float32) / math.sqrt(
      q.shape[-1])  # [..., H, T, L]
  attn = jax.nn.softmax(logits, axis=-1)
  return jnp.einsum("...htl,...lhd->...thd", attn.astype(v.dtype), v)  # [..., T, H, dv]


def locality_mask(*, logits: jax.Array, points: jax.Array, box: float, enabled) -> jax.Array:
  """Locality constraint (docs/method.md §1.4): outside the box only s_∅ and slot 1 take a point.

  logits [..., K+1], points [..., 3] in the normalised scene frame, `enabled` a (traced) bool.
  Where enabled and any |coordinate| > box, logits of slot indices ≥ 2 become MASKED_LOGIT.
  """
  outside = jnp.any(jnp.abs(points) > box, axis=-1, keepdims=True)  # [..., 1]
  maskable = jnp.arange(logits.shape[-1]) >= 2  # [K+1]
  masked = jnp.logical_and(jnp.logical_and(enabled, outside), maskable)  # [..., K+1]
  return jnp.where(masked, jnp.asarray(MASKED_LOGIT, logits.dtype), logits)


def point_slot_weights(logits: jax.Array) -> jax.Array:
  """W = softmax over the K+1 slots (empty slot included) of the mapping logits [..., K+1]."""
  return jax.nn.softmax(logits, axis=-1)


def slot_density(*, logits: jax.Array, weights: jax.Array, log_scale: jax.Array) -> jax.Array:
  """σ = exp(s_σ)·Σ_{k=1..K} W_k·ReLU(A_k) ≥ 0 [...]; the empty slot (index 0) adds nothing."""
  per_slot = weights[..., 1:] * jax.nn.relu(logits[..., 1:])  # [..., K]
  return jnp.exp(log_scale) * jnp.sum(per_slot, axis=-1)


def slot_density_shares(*, density: jax.Array, logits: jax.Array, weights: jax.Array,
                        log_scale: jax.Array, mode: str) -> jax.Array:
  """Each real slot's share σ_k [..., K] of the density σ [...]; Σ_k σ_k = σ (to rounding).

  "slot": σ_k = exp(s_σ)·W_k·ReLU(A_k), the terms of `slot_density`. "mlp": σ comes from one
  head, not from the slots, so it is split by the point-slot weights of the real slots,
  σ_k = σ·W_k / Σ_{j≥1} W_j. What a slot renders alone (`rendering.pictures`) uses these.
  """
  real = weights[..., 1:]  # [..., K]
  if mode == "slot":
    return jnp.exp(log_scale) * real * jax.nn.relu(logits[..., 1:])
  if mode == "mlp":
    total = jnp.maximum(jnp.sum(real, axis=-1, keepdims=True), jnp.finfo(real.dtype).tiny)
    return density[..., None] * real / total
  raise ValueError(f"density_mode must be one of {DENSITY_MODES}, got {mode!r}")


def mlp_density(*, raw: jax.Array, log_scale: jax.Array) -> jax.Array:
  """σ = exp(s_σ)·softplus(o) ≥ 0 [...] from a density head's output o [..., 1].

  The "without slot-based density" ablation (docs/method.md §5). softplus, not exp: it is the smooth
  counterpart of the ReLU in `slot_density`, so σ grows linearly with the head's output as the slot
  formula does with A_k, and the learned log scale s_σ with its init `density_log_init` (which the
  paper_cpu variant lowers so a ray's first samples start transparent) means the same in both modes;
  exp(o) would make σ exponential in an unbounded output. Unlike ReLU its gradient never vanishes,
  so a head that starts negative can still grow density.
  """
  return jnp.exp(log_scale) * jax.nn.softplus(raw[..., 0])


def colour_activation(raw: jax.Array, *, mode: str) -> jax.Array:
  """'unit': tanh(o)/2 + 1/2 in [0, 1] (synthetic sets); 'signed': tanh(o) in [−1, 1] (DTU)."""
  if mode == "unit":
    return 0.5 * jnp.tanh(raw) + 0.5
  if mode == "signed":
    return jnp.tanh(raw)
  raise ValueError(f"colour_range must be 'unit' or 'signed', got {mode!r}")


def dropout_rates(num_blocks: int, max_rate: float) -> np.ndarray:
  """Per-block residual dropout rates linspace(0, max_rate, num_blocks) (official rule)."""
  return np.linspace(0.0, max_rate, num_blocks, dtype=np.float32)


# ---------------------------------------------------------------------------------------------
# Modules.


class MultiHeadAttention(nn.Module):
  """Official `MultiHeadAttention`: biased q, k, v projections to `proj_dim`, `num_heads` heads,
  output projection to `out_dim` initialised with gain `out_gain`."""
  proj_dim: int
  out_dim: int
  num_heads: int
  out_gain: float = 1.0
  dtype: Any = jnp.float32  # computation dtype of the projections and products

  @nn.compact
  def __call__(self, queries: jax.Array, keys_values: jax.Array) -> jax.Array:
    """queries [..., T, Cq], keys_values [..., L, Ckv] (same leading dims) → [..., T, out_dim]."""
    h, dh = self.num_heads, self.proj_dim // self.num_heads
    dense = lambda name: nn.Dense(self.proj_dim, kernel_init=xavier(), dtype=self.dtype,
                                  name=name)
    q = dense("query")(queries).reshape(queries.shape[:-1] + (h, dh))  # [..., T, H, dh]
    k = dense("key")(keys_values).reshape(keys_values.shape[:-1] + (h, dh))  # [..., L, H, dh]
    v = dense("value")(keys_values).reshape(keys_values.shape[:-1] + (h, dh))
    out = dot_product_attention(q=q, k=k, v=v)  # [..., T, H, dh]
    out = out.reshape(out.shape[:-2] + (self.proj_dim,))
    return nn.Dense(self.out_dim, kernel_init=xavier(self.out_gain), dtype=self.dtype,
                    name="out")(out)


class AllocationBlock(nn.Module):
  """One pre-LN allocation block on h [B, R, S, C] (see the module docstring).

  Called as (h, (rate, key), slots) → (h, None) so the same class runs in a loop or under nn.scan;
  `rate` is the block's residual dropout rate (traced under scan), `key` its dropout key (None
  unless `train`).
  """
  width: int = 64
  num_heads: int = 4
  self_attn_dim: int = 16
  ffn_dim: int = 256
  out_gain: float = 1.0
  train: bool = False
  fold_products: bool = False  # cross-attention by `folded.folded_cross_attention` (module docstring)
  dtype: Any = jnp.float32  # computation dtype; h stays float32 (see the module docstring)

  @nn.compact
  def __call__(self, h: jax.Array, rate_and_key, slots: jax.Array):
    rate, key = rate_and_key
    b, r, s, c = h.shape
    # Statistics in float32 (flax's force_float32_reductions); the output feeds a Linear.
    ln = lambda name: nn.LayerNorm(epsilon=LAYER_NORM_EPS, dtype=self.dtype, name=name)
    attention = lambda proj_dim, name: MultiHeadAttention(
        proj_dim, self.width, self.num_heads, self.out_gain, dtype=self.dtype, name=name)

    # Cross-attention from every point to S' (keys/values shared by all points of a scene).
    x = ln("cross_norm")(h).reshape(b, r * s, c)  # [B, R·S, C]
    cross = CrossAttention if self.fold_products else MultiHeadAttention
    x = cross(self.width, self.width, self.num_heads, self.out_gain, dtype=self.dtype,
              name="cross_attn")(x, slots)
    x = x.reshape(b, r, s, c)  # [B, R, S, C]
    # Conv1d(k=3, 'same') along the ray, written as one Dense over shifted copies.
    fan_in = 3 * c
    x = nn.relu(nn.Dense(c, kernel_init=torch_default_kernel_init(),
                         bias_init=torch_default_bias_init(fan_in), dtype=self.dtype,
                         name="conv")(conv1d_taps(x)))
    # The FFN takes the branch x, not h (official code).
    y = ln("ffn_norm")(x)
    y = nn.relu(nn.Dense(self.ffn_dim, kernel_init=nn.initializers.he_uniform(),
                         dtype=self.dtype, name="ffn_in")(y))
    y = nn.Dense(c, kernel_init=xavier(self.out_gain), dtype=self.dtype, name="ffn_out")(y)
    # A block whose rate is statically 0 (the first, unscanned) draws no random bits at all.
    if self.train and not (isinstance(rate, float) and rate == 0.0):
      x, y = paired_dropout(x, y, rate=rate, key=key)
    h = h + x + y  # a float32 h stays float32 (jnp promotion)
    # Self-attention among the S samples of each ray.
    z = ln("self_norm")(h)
    h = h + attention(self.self_attn_dim, "self_attn")(z, z)
    return h, None


class AllocationTransformer(nn.Module):
  """num_blocks AllocationBlocks then a final LayerNorm: [B, R, S, C] × S' → [B, R, S, C]."""
  width: int = 64
  num_blocks: int = 4
  num_heads: int = 4
  self_attn_dim: int = 16
  ffn_dim: int = 256
  max_dropout: float = 0.2
  remat_scan: bool = False
  fold_products: bool = False
  dtype: Any = jnp.float32  # computation dtype; the output, a LayerNorm's, is in it

  @nn.compact
  def __call__(self, h: jax.Array, slots: jax.Array, *, train: bool) -> jax.Array:
    n = self.num_blocks
    rates = dropout_rates(n, self.max_dropout)
    # One key per block, drawn once here so the loop and scan layouts use the same randomness.
    keys = jax.random.split(self.make_rng("dropout"), n) if train else None
    block_kwargs = dict(width=self.width, num_heads=self.num_heads,
                        self_attn_dim=self.self_attn_dim, ffn_dim=self.ffn_dim,
                        out_gain=(3.0 * n) ** -0.5, train=train,
                        fold_products=self.fold_products, dtype=self.dtype)
    if self.remat_scan:
      blocks = nn.scan(
          nn.remat(AllocationBlock, prevent_cse=False),
          variable_axes={"params": 0}, split_rngs={"params": True},
          in_axes=(0, nn.broadcast), length=n)(**block_kwargs, name="blocks")
      h, _ = blocks(h, (jnp.asarray(rates), keys), slots)
    else:
      for i in range(n):
        key = None if keys is None else keys[i]
        h, _ = AllocationBlock(**block_kwargs, name=f"block_{i}")(h, (float(rates[i]), key), slots)
    return nn.LayerNorm(epsilon=LAYER_NORM_EPS, dtype=self.dtype, name="final_norm")(h)


@flax.struct.dataclass
class Allocation:
  features: jax.Array  # [B, R, S, C] F_s = Linear(W·S'), in the computation dtype
  weights: jax.Array  # [B, R, S, K+1] point-slot weights W (index 0 = empty slot)
  logits: jax.Array  # [B, R, S, K+1] mapping logits A after the locality mask
  density: jax.Array  # [B, R, S] density σ ≥ 0 (slot-based, or the MLP head's)
  slot_densities: jax.Array  # [B, R, S, K] each real slot's share of σ (`slot_density_shares`)


def _empty_slot_init(key, shape, dtype=jnp.float32):
  """xavier_uniform_ as PyTorch applies it to the official [1, 1, Ds] parameter (fans Ds, Ds)."""
  dim = shape[-1]
  bound = math.sqrt(6.0 / (2 * dim))
  return jax.random.uniform(key, shape, dtype, -bound, bound)


DENSITY_MODES = ("slot", "mlp")


class SlotDecoder(nn.Module):
  """Allocation transformer + point-slot mapping + density (official `JointDecoder`).

  density_mode "slot" (the paper's): σ = exp(s_σ)·Σ_{k≥1} W_k·ReLU(A_k). "mlp" (the ablation
  "without slot-based density", docs/method.md §5): σ = `mlp_density` of Dense(C) → ReLU → Dense(1)
  on the transformer's output h, with the same learned s_σ; only then do `density_hidden` and
  `density_out` parameters exist.
  """
  width: int = 64
  num_blocks: int = 4
  num_heads: int = 4
  self_attn_dim: int = 16
  ffn_dim: int = 256
  max_dropout: float = 0.2
  remat_scan: bool = False
  locality_box: float = 0.64
  density_log_init: float = 0.0  # initial s_σ (official: 0)
  density_mode: str = "slot"  # "slot" | "mlp" (see the class docstring)
  fold_products: bool = False  # the products of `folded.py` (module docstring)
  dtype: Any = jnp.float32  # computation dtype (see the module docstring)

  @nn.compact
  def __call__(self, point_features: jax.Array, slots: jax.Array, points: jax.Array, *,
               locality, train: bool) -> Allocation:
    """point_features F_p [B, R, S, C], slots [B, K, Ds], points [B, R, S, 3]; `locality` a
    (traced) bool scalar switching the locality constraint."""
    b, _, ds = slots.shape
    dense = lambda width, name: nn.Dense(width, kernel_init=xavier(), dtype=self.dtype,
                                         name=name)
    empty = self.param("empty_slot", _empty_slot_init, (ds,))
    slots_all = jnp.concatenate(
        [jnp.broadcast_to(empty, (b, 1, ds)), slots], axis=1)  # [B, K+1, Ds]: S', no LayerNorm
    h = AllocationTransformer(
        width=self.width, num_blocks=self.num_blocks, num_heads=self.num_heads,
        self_attn_dim=self.self_attn_dim, ffn_dim=self.ffn_dim, max_dropout=self.max_dropout,
        remat_scan=self.remat_scan, fold_products=self.fold_products, dtype=self.dtype,
        name="transformer")(point_features, slots_all, train=train)

    mask = lambda a: locality_mask(logits=a, points=points, box=self.locality_box,
                                   enabled=locality)
    if self.fold_products:
      # The same A and F_s with the per-point Linears folded into per-scene ones.
      linear = lambda width, name: LinearParams(width, xavier(), name=name)
      logits, weights, features = folded_mapping(
          h=h, slots=slots_all, query=linear(self.width, "map_query")(self.width),
          key=linear(self.width, "map_key")(ds), out=linear(self.width, "map_out")(ds),
          mask=mask, dtype=self.dtype)
    else:
      q = dense(self.width, "map_query")(h)  # [B, R, S, C]
      k = dense(self.width, "map_key")(slots_all)  # [B, K+1, C]
      # A (the logits) feeds the softmax W and the density's ReLU(A_k): float32 after the product.
      logits = mask(jnp.einsum("brsc,bkc->brsk", q, k).astype(jnp.float32) / math.sqrt(
          self.width))  # [B, R, S, K+1]
      weights = point_slot_weights(logits)
      mixed = jnp.einsum("brsk,bkd->brsd", weights.astype(self.dtype),
                         slots_all.astype(self.dtype))  # [B, R, S, Ds]: W·S'
      features = dense(self.width, "map_out")(mixed)
    log_scale = self.param("log_density_scale", nn.initializers.constant(self.density_log_init), ())
    if self.density_mode == "slot":
      density = slot_density(logits=logits, weights=weights, log_scale=log_scale)
    elif self.density_mode == "mlp":
      hidden = nn.relu(dense(self.width, "density_hidden")(h))
      raw = dense(1, "density_out")(hidden).astype(jnp.float32)  # [B, R, S, 1]
      density = mlp_density(raw=raw, log_scale=log_scale)
    else:
      raise ValueError(f"density_mode must be one of {DENSITY_MODES}, got {self.density_mode!r}")
    shares = slot_density_shares(density=density, logits=logits, weights=weights,
                                 log_scale=log_scale, mode=self.density_mode)
    return Allocation(features=features, weights=weights, logits=logits, density=density,
                      slot_densities=shares)


class ColourMLP(nn.Module):
  """c = act(MLP(F_s + E_p)): `num_layers` hidden layers of `hidden` with LeakyReLU(0.01), → 3."""
  hidden: int = 64
  num_layers: int = 4
  colour_range: str = "unit"
  dtype: Any = jnp.float32  # computation dtype of the Linear layers; the colour is float32

  @nn.compact
  def __call__(self, x: jax.Array) -> jax.Array:  # [..., C] → [..., 3]
    for i in range(self.num_layers):
      x = nn.Dense(self.hidden, kernel_init=nn.initializers.he_uniform(), dtype=self.dtype,
                   name=f"hidden_{i}")(x)
      x = nn.leaky_relu(x, negative_slope=LEAKY_SLOPE)
    raw = nn.Dense(3, kernel_init=xavier(), dtype=self.dtype, name="out")(x)
    # tanh in float32: near 1 a bfloat16 colour would be rounded to steps of 2^-8.
    return colour_activation(raw.astype(jnp.float32), mode=self.colour_range)
