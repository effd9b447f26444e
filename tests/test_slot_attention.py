"""Tests for BO-QSA slot attention (SPEC §1.2)."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import slot_attention as sa

B, N, D, K, DS = 2, 23, 13, 5, 16


def _module(**kw):
  return sa.SlotAttention(num_slots=K, slot_dim=DS, mlp_dim=32, **kw)


def _key(seed):
  # 'rbg' keys: the module does not care, and they compile much faster than threefry on XLA:CPU.
  return jax.random.key(seed, impl="rbg")


def _setup(seed=0, **kw):
  inputs = jax.random.normal(_key(seed), (B, N, D))
  module = _module(**kw)
  params = jax.jit(module.init)(_key(seed + 1), inputs)
  return module, params, inputs


def test_slot_competition_matches_numpy():
  rng = np.random.default_rng(0)
  logits = rng.normal(size=(B, K, N)).astype(np.float32) * 3
  values = rng.normal(size=(B, N, DS)).astype(np.float32)
  got = sa.slot_competition(logits=jnp.asarray(logits), values=jnp.asarray(values), eps=1.0)
  e = np.exp(logits - logits.max(axis=1, keepdims=True))
  attn = e / e.sum(axis=1, keepdims=True)
  want = np.zeros((B, K, DS))
  for b in range(B):
    for k in range(K):
      want[b, k] = (attn[b, k, :, None] * values[b]).sum(0) / (attn[b, k].sum() + 1.0)
  np.testing.assert_allclose(got.attn, attn, atol=1e-5)
  np.testing.assert_allclose(got.updates, want, atol=1e-5)


def test_shapes_softmax_over_slots_and_jit():
  module, params, inputs = _setup()
  out = module.apply(params, inputs)
  chex.assert_shape(out.slots, (B, K, DS))
  chex.assert_shape(out.attn, (B, K, N))
  chex.assert_shape(out.mu, (K, DS))
  np.testing.assert_allclose(out.attn.sum(axis=1), np.ones((B, N)), atol=1e-5)
  jitted = jax.jit(lambda p, x: module.apply(p, x))(params, inputs)
  np.testing.assert_allclose(jitted.slots, out.slots, atol=1e-5)
  np.testing.assert_allclose(jitted.attn, out.attn, atol=1e-5)


def test_mu_init_scale_matches_official_tensor():
  # PyTorch xavier_uniform_ on [1, K, Ds]: bound √(6/(K·Ds + Ds)).
  module = sa.SlotAttention(num_slots=8, slot_dim=256)
  params = jax.jit(module.init)(_key(0), jnp.zeros((1, 3, 7)))
  mu = np.asarray(params["params"]["mu"])
  bound = np.sqrt(6.0 / (8 * 256 + 256))
  assert np.abs(mu).max() <= bound
  assert np.abs(mu).max() > 0.95 * bound


def test_slot_permutation_equivariance():
  module, params, inputs = _setup(seed=3)
  perm = np.array([3, 0, 4, 1, 2])
  permuted = jax.tree.map(lambda x: x, params)
  permuted["params"]["mu"] = params["params"]["mu"][perm]
  out = module.apply(params, inputs)
  out_p = module.apply(permuted, inputs)
  np.testing.assert_allclose(out_p.slots, out.slots[:, perm], atol=1e-5)
  np.testing.assert_allclose(out_p.attn, out.attn[:, perm], atol=1e-5)
  assert not np.allclose(out_p.slots, out.slots, atol=1e-3)  # the permutation is not trivial


def _reference(module, params, inputs, *, bilevel):
  """Slots from the module's own keys/values/update, iterations chained by hand."""
  def call(method, *args, **kw):
    return module.apply(params, *args, method=method, **kw)
  keys, values = call(module.keys_values, inputs)
  mu = jnp.broadcast_to(params["params"]["mu"], (B, K, DS))
  slots = mu
  for _ in range(2):
    slots = call(module.update, slots, keys, values, train=False).slots
  if bilevel:
    slots = jax.lax.stop_gradient(slots) + mu - jax.lax.stop_gradient(mu)
  return call(module.update, slots, keys, values, train=False).slots


def test_bilevel_gradient_flows_through_last_iteration_only():
  module, params, inputs = _setup(seed=5)
  cot = jax.random.normal(jax.random.key(9), (B, K, DS))

  def loss(p, x, fn):
    return jnp.sum(fn(p, x) * cot)

  model_fn = lambda p, x: module.apply(p, x).slots
  bilevel_fn = lambda p, x: _reference(module, p, x, bilevel=True)
  full_fn = lambda p, x: _reference(module, p, x, bilevel=False)

  np.testing.assert_allclose(model_fn(params, inputs), full_fn(params, inputs), atol=1e-5)
  g_model = jax.grad(loss, argnums=(0, 1))(params, inputs, model_fn)
  g_ref = jax.grad(loss, argnums=(0, 1))(params, inputs, bilevel_fn)
  g_full = jax.grad(loss, argnums=(0, 1))(params, inputs, full_fn)
  chex.assert_trees_all_close(g_model, g_ref, atol=1e-5, rtol=1e-4)
  # The reference itself must differ from full back-propagation, or the test proves nothing.
  assert np.abs(np.asarray(g_full[1] - g_ref[1])).max() > 1e-4
  assert np.abs(np.asarray(g_full[0]["params"]["mu"] - g_ref[0]["params"]["mu"])).max() > 1e-4


def test_noise_and_drop_path_only_in_training():
  module, params, inputs = _setup(seed=7)
  evaluated = module.apply(params, inputs, noise_sigma=1.0, train=False)
  rngs = {"noise": _key(1), "dropout": _key(2)}
  quiet = _module(drop_path_rate=0.0).apply(params, inputs, noise_sigma=0.0, train=True,
                                            rngs=rngs)
  np.testing.assert_allclose(quiet.slots, evaluated.slots, atol=1e-5)
  noisy = _module(drop_path_rate=0.0).apply(params, inputs, noise_sigma=1.0, train=True,
                                            rngs=rngs)
  assert np.abs(np.asarray(noisy.slots - evaluated.slots)).max() > 1e-3
  # The noise is relative to μ and σ·z·stop_gradient(μ) carries no gradient to μ.
  def init_sum(p):
    return jnp.sum(module.apply(p, B, noise_sigma=2.0, train=True, rngs=rngs,
                                method=module.initial_slots))
  g = jax.grad(init_sum)(params)
  np.testing.assert_allclose(g["params"]["mu"], np.full((K, DS), B), atol=1e-6)


def test_drop_path_is_per_sample_and_unbiased():
  x = jnp.ones((4000, 3, 5))
  y = np.asarray(sa.drop_path(x, rate=0.2, key=jax.random.key(0)))
  per_sample = y.reshape(4000, -1)
  # Each sample is either dropped entirely or kept and rescaled by 1/(1 − rate).
  assert set(np.unique(per_sample.min(1))) <= {0.0, 1.25}
  np.testing.assert_array_equal(per_sample.min(1), per_sample.max(1))
  assert abs(per_sample.mean() - 1.0) < 0.05
  assert 0.17 < np.mean(per_sample[:, 0] == 0) < 0.23
