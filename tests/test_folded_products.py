"""The decoder's folded products against NumPy in the official order (docs/method.md §1.3–1.4).

The decoder's cross-attention and point-slot mapping multiply per-scene matrices built from the
slots, and the point embedding applies its direction half once per ray
(`folded.folded_cross_attention`, `folded.folded_mapping`, `model.PointEmbedding`). Each is
checked here against the unfolded computation written in NumPy: every query projected, every head
attended, every per-point Linear applied, every sample's direction encoded. Their parameters must
be an `nn.Dense`'s (names, shapes and initial values), so runs and checkpoints are unchanged.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import train_helpers

from slotlifter_jax import decoder as dec
from slotlifter_jax import folded
from slotlifter_jax import model as model_lib

B, T, L, CQ, CKV, P, H, OUT = 2, 11, 5, 12, 7, 8, 4, 10


def _softmax(x):
  e = np.exp(x - x.max(-1, keepdims=True))
  return e / e.sum(-1, keepdims=True)


def _linear(rng, fan_in, fan_out):
  return (rng.normal(size=(fan_in, fan_out)).astype(np.float32) / np.sqrt(fan_in),
          rng.normal(size=(fan_out,)).astype(np.float32))


def _numpy_attention(x, kv, query, key, value, out, num_heads):
  """The official MultiHeadAttention: project, split heads, softmax(q·kᵀ/√dh)·v, merge, project."""
  q = x @ query[0] + query[1]  # [B, T, P]
  k = kv @ key[0] + key[1]  # [B, L, P]
  v = kv @ value[0] + value[1]
  dh = q.shape[-1] // num_heads
  merged = np.zeros(q.shape, np.float64)
  for b in range(x.shape[0]):
    for h in range(num_heads):
      cols = slice(h * dh, (h + 1) * dh)
      attn = _softmax(q[b, :, cols] @ k[b, :, cols].T / np.sqrt(dh))  # [T, L]
      merged[b, :, cols] = attn @ v[b, :, cols]
  return merged @ out[0] + out[1]  # [B, T, OUT]


def test_folded_cross_attention_matches_the_official_order_in_numpy():
  rng = np.random.default_rng(0)
  x = rng.normal(size=(B, T, CQ)).astype(np.float32)
  kv = rng.normal(size=(B, L, CKV)).astype(np.float32)
  params = dict(query=_linear(rng, CQ, P), key=_linear(rng, CKV, P), value=_linear(rng, CKV, P),
                out=_linear(rng, P, OUT))
  got = folded.folded_cross_attention(queries=jnp.asarray(x), keys_values=jnp.asarray(kv),
                                   num_heads=H, **params)
  want = _numpy_attention(x, kv, num_heads=H, **params)
  assert got.shape == (B, T, OUT)
  np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_cross_attention_has_the_parameters_of_multi_head_attention():
  """Same tree, same initial values (so the official init and old checkpoints still hold), and
  the same function as the unfolded module at those values."""
  x = jax.random.normal(jax.random.key(1), (B, T, CQ))
  kv = jax.random.normal(jax.random.key(2), (B, L, CKV))
  fold_module = folded.CrossAttention(P, OUT, H, out_gain=0.3)
  plain = dec.MultiHeadAttention(P, OUT, H, out_gain=0.3)
  key = jax.random.key(3)
  p_folded, p_plain = fold_module.init(key, x, kv), plain.init(key, x, kv)
  assert jax.tree.structure(p_folded) == jax.tree.structure(p_plain)
  for a, b in zip(jax.tree.leaves(p_folded), jax.tree.leaves(p_plain)):
    np.testing.assert_array_equal(a, b)
  # Non-zero biases, so the folded bias term b_q·k is exercised too.
  p = jax.tree.map(lambda a: a + 0.1 * jnp.cos(jnp.arange(a.size).reshape(a.shape)), p_plain)
  np.testing.assert_allclose(fold_module.apply(p, x, kv), plain.apply(p, x, kv), rtol=1e-5,
                             atol=1e-5)


@pytest.mark.parametrize("masked", [False, True])
def test_folded_mapping_matches_the_official_order_in_numpy(masked):
  rng = np.random.default_rng(4)
  c, ds, k1 = 6, 9, L  # point width, slot width, K+1
  h = rng.normal(size=(B, 3, 4, c)).astype(np.float32)
  slots = rng.normal(size=(B, k1, ds)).astype(np.float32)
  query, key, out = _linear(rng, c, c), _linear(rng, ds, c), _linear(rng, ds, c)
  # Slot indices ≥ 2 masked at every other point, as the locality constraint does.
  block = (np.arange(3 * 4).reshape(3, 4) % 2 == 0)[None, :, :, None] & (np.arange(k1) >= 2)
  mask = (lambda a: jnp.where(block, dec.MASKED_LOGIT, a)) if masked else None
  logits, weights, features = folded.folded_mapping(
      h=jnp.asarray(h), slots=jnp.asarray(slots), query=query, key=key, out=out, mask=mask)
  q = h @ query[0] + query[1]  # [B, R, S, C]
  k = slots @ key[0] + key[1]  # [B, K+1, C]
  want_logits = np.einsum("brsc,bkc->brsk", q, k) / np.sqrt(c)
  if masked:
    want_logits = np.where(block, dec.MASKED_LOGIT, want_logits)
  want_weights = _softmax(want_logits)
  mixed = np.einsum("brsk,bkd->brsd", want_weights, slots)  # W·S' [B, R, S, Ds]
  want_features = mixed @ out[0] + out[1]
  np.testing.assert_allclose(logits, want_logits, rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(weights, want_weights, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(features, want_features, rtol=1e-5, atol=1e-5)
  if masked:
    assert np.asarray(weights)[np.broadcast_to(block, weights.shape)].max() < 1e-30


def _numpy_encoding(x, num_freqs):
  """sin then cos of 2^f·x, channel-major (geometry.positional_encoding's documented order)."""
  scaled = (x[..., :, None] * 2.0 ** np.arange(num_freqs)).reshape(x.shape[:-1] + (-1,))
  return np.concatenate([np.sin(scaled), np.cos(scaled)], axis=-1)


def test_point_embedding_is_one_linear_on_the_encoded_point_and_direction():
  rng = np.random.default_rng(5)
  freqs, width = 4, 6
  points = rng.uniform(-1, 1, size=(B, 3, 5, 3)).astype(np.float32)
  dirs = rng.normal(size=(B, 3, 3)).astype(np.float32)
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
  module = model_lib.PointEmbedding(width, freqs)
  params = module.init(jax.random.key(6), points, dirs)
  # The parameters of one Dense on the 12·F-wide concatenation, with its initial values.
  dense = nn.Dense(width, kernel_init=nn.initializers.xavier_uniform())
  ref_params = dense.init(jax.random.key(6), jnp.zeros((1, 12 * freqs)))
  assert jax.tree.structure(params) == jax.tree.structure(ref_params)
  for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref_params)):
    np.testing.assert_array_equal(a, b)
  params = jax.tree.map(lambda a: a + 0.05, params)  # a non-zero bias
  kernel = np.asarray(params["params"]["kernel"])
  bias = np.asarray(params["params"]["bias"])
  per_sample_dirs = np.broadcast_to(dirs[:, :, None, :], points.shape)
  inputs = np.concatenate([_numpy_encoding(points, freqs), _numpy_encoding(per_sample_dirs, freqs)],
                          axis=-1)  # [B, R, S, 12F]
  got = module.apply(params, points, dirs)
  assert got.dtype == jnp.float32 and got.shape == (B, 3, 5, width)
  np.testing.assert_allclose(got, inputs @ kernel + bias, rtol=1e-5, atol=1e-5)


def test_the_model_switch_keeps_the_parameters_and_the_rendering():
  """`model.fold_products` reaches every fold: the same parameter tree and values, and the same
  rendering to float32 rounding, from the config the command line reads."""
  batch = train_helpers.fake_batch(train_helpers.load_config())
  models = {}
  for fold in (False, True):
    c = train_helpers.load_config()
    c.model.fold_products = fold
    models[fold] = model_lib.build_model(c)
  assert models[True].fold_products and not models[False].fold_products
  inputs = {k: jnp.asarray(v) for k, v in batch.items() if k != "target_rgb"}
  params = {fold: jax.jit(lambda m=m: m.init(jax.random.key(0), **inputs, train=False))()
            for fold, m in models.items()}
  assert jax.tree.structure(params[True]) == jax.tree.structure(params[False])
  for a, b in zip(jax.tree.leaves(params[True]), jax.tree.leaves(params[False])):
    np.testing.assert_array_equal(a, b)
  out = {fold: jax.jit(lambda p, m=m: m.apply(p, **inputs, train=False))(params[False])
         for fold, m in models.items()}
  for field in ("colour", "depth", "segmentation"):
    np.testing.assert_allclose(getattr(out[True].render.coarse, field),
                               getattr(out[False].render.coarse, field), rtol=1e-4, atol=1e-5)
