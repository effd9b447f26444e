"""The decoder's products with its per-point Linears folded into per-scene ones (docs/method.md §1.4).

The allocation transformer's cross-attention and the point-slot mapping multiply every point by
Linears of the K+1 slots S' of its scene. By associativity the per-point Linears fold into
per-scene matrices built from the slots once, and the B·R·S points meet those in plain matmuls:
the same function, from the same parameters (an `nn.Dense`'s names, shapes and initial values),
with fewer per-point products, but another rounding. `decoder.py` uses them when
`fold_products` is on (`model.fold_products`, off by default: experiments/journal/2026-12.md,
"Folded products"); tests/test_folded_products.py checks each against the unfolded order in NumPy.
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp


def xavier(gain: float = 1.0):
  """xavier-uniform with `gain`, the official `linear` helper's kernel init."""
  return nn.initializers.variance_scaling(gain * gain, "fan_avg", "uniform")


class LinearParams(nn.Module):
  """The kernel [in, out] and bias [out] of an `nn.Dense` (same names, initialisers and order of
  creation, so the same init and checkpoints), returned instead of applied: a folded product
  multiplies them with each other before it meets the per-point inputs."""
  features: int
  kernel_init: Any = nn.initializers.lecun_normal()  # nn.Dense's default

  @nn.compact
  def __call__(self, in_features: int):
    kernel = self.param("kernel", self.kernel_init, (in_features, self.features), jnp.float32)
    bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
    return kernel, bias


def folded_cross_attention(*, queries: jax.Array, keys_values: jax.Array, query, key, value, out,
                           num_heads: int, dtype=jnp.float32) -> jax.Array:
  """`MultiHeadAttention` from many queries to a few per-scene keys, with the projections folded.

  queries [B, T, Cq], keys_values [B, L, Ckv]; query … out the (kernel, bias) pairs of the four
  Linears. The same function as projecting every query (the official order), reassociated:
    qₕ·kₕₗ = x·(W_q,ₕ kₕₗ) + b_q,ₕ·kₕₗ   and   W_o(Σₗ aₕₗ vₕₗ) = Σₗ aₕₗ (vₕₗ W_o,ₕ),
  so each scene's [Cq, H·L] and [H·L, out] matrices are built from its L keys once and the T
  queries meet them in two plain matmuls: no per-query projection, no per-head batched product.
  With L = K+1 slots and H·L ≈ the projection width this is the cheaper order (with
  `folded_mapping`, 0.87–0.90× the whole train step: experiments/journal/2026-12.md, "Folded
  products").
  """
  (wq, bq), (wk, bk), (wv, bv), (wo, bo) = query, key, value, out
  b, t, _ = queries.shape
  num_keys = keys_values.shape[1]
  h, dh = num_heads, wq.shape[1] // num_heads
  cast = lambda a: a.astype(dtype)
  kv = cast(keys_values)
  k = (kv @ cast(wk) + cast(bk)).reshape(b, num_keys, h, dh)  # [B, L, H, dh]
  v = (kv @ cast(wv) + cast(bv)).reshape(b, num_keys, h, dh)
  m = jnp.einsum("chd,blhd->bchl", cast(wq).reshape(-1, h, dh), k).reshape(
      b, -1, h * num_keys)  # [B, Cq, H·L]
  c = jnp.einsum("hd,blhd->bhl", cast(bq).reshape(h, dh), k).reshape(b, 1, h * num_keys)
  logits = (jnp.einsum("btc,bcm->btm", cast(queries), m) + c).astype(jnp.float32) / math.sqrt(
      dh)  # [B, T, H·L]
  attn = jax.nn.softmax(logits.reshape(b, t, h, num_keys), axis=-1).reshape(b, t, h * num_keys)
  n = jnp.einsum("blhd,hdo->bhlo", v, cast(wo).reshape(h, dh, -1)).reshape(
      b, h * num_keys, -1)  # [B, H·L, out]
  return jnp.einsum("btm,bmo->bto", cast(attn), n) + cast(bo)  # [B, T, out]


class CrossAttention(nn.Module):
  """`MultiHeadAttention`'s parameters (query, key, value, out) computed by
  `folded_cross_attention`: queries [B, T, Cq] to per-scene keys_values [B, L, Ckv]."""
  proj_dim: int
  out_dim: int
  num_heads: int
  out_gain: float = 1.0
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, queries: jax.Array, keys_values: jax.Array) -> jax.Array:
    linear = lambda width, gain, name: LinearParams(width, xavier(gain), name=name)
    return folded_cross_attention(
        queries=queries, keys_values=keys_values,
        query=linear(self.proj_dim, 1.0, "query")(queries.shape[-1]),
        key=linear(self.proj_dim, 1.0, "key")(keys_values.shape[-1]),
        value=linear(self.proj_dim, 1.0, "value")(keys_values.shape[-1]),
        out=linear(self.out_dim, self.out_gain, "out")(self.proj_dim),
        num_heads=self.num_heads, dtype=self.dtype)


def folded_mapping(*, h: jax.Array, slots: jax.Array, query, key, out, mask=None,
                   dtype=jnp.float32):
  """The point-slot mapping (docs/method.md §1.4) with its per-point Linears folded.

  h [B, R, S, C] the transformer's output, slots S' [B, K+1, Ds]; query, key, out the (kernel,
  bias) pairs of the mapping's Linears; `mask` maps the float32 logits [B, R, S, K+1] before the
  softmax (the locality constraint). Returns (A, W, F_s):
    A = (h W_q + b_q)·(S' W_k + b_k)ᵀ/√C = (h·(W_q kᵀ) + b_q·kᵀ)/√C,
    W = softmax(A),   F_s = (W·S') W_o + b_o = W·(S' W_o) + b_o,
  so the per-point work is a [C, K+1] and a [K+1, C] product per scene instead of a query
  Linear, a product with the keys, a [K+1, Ds] product and an output Linear.
  """
  cast = lambda a: a.astype(dtype)
  (wq, bq), (wk, bk), (wo, bo) = query, key, out
  s_all = cast(slots)
  k = s_all @ cast(wk) + cast(bk)  # [B, K+1, C]
  m = jnp.einsum("cd,bkd->bck", cast(wq), k)  # [B, C, K+1]
  c = jnp.einsum("d,bkd->bk", cast(bq), k)[:, None, None, :]  # [B, 1, 1, K+1]
  # A feeds the softmax W and the density's ReLU(A_k): float32 after the product.
  logits = (jnp.einsum("brsc,bck->brsk", cast(h), m) + c).astype(jnp.float32) / math.sqrt(
      wq.shape[1])  # [B, R, S, K+1]
  if mask is not None:
    logits = mask(logits)
  weights = jax.nn.softmax(logits, axis=-1)  # W over the K+1 slots
  slot_out = s_all @ cast(wo)  # [B, K+1, C]: S' W_o
  features = jnp.einsum("brsk,bkc->brsc", cast(weights), slot_out) + cast(bo)
  return logits, weights, features
