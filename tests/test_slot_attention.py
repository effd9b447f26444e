"""Tests for BO-QSA slot attention (docs/method.md §1.2)."""

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

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


def test_gru_recurrent_kernels_are_one_stacked_orthogonal_matrix():
  # torch.nn.init.orthogonal_ on the official weight_hh [3·Ds, Ds] (gates r, z, n) gives orthonormal
  # columns; its transpose, our three [Ds, Ds] kernels side by side, has orthonormal rows.
  ds = 256
  module = sa.SlotAttention(num_slots=8, slot_dim=ds)
  gru = jax.jit(module.init)(_key(0), jnp.zeros((1, 3, 7)))["params"]["gru"]
  kernels = [np.asarray(gru[name]["kernel"], np.float64) for name in ("hr", "hz", "hn")]
  stacked = np.concatenate(kernels, axis=1)  # [Ds, 3·Ds]
  np.testing.assert_allclose(stacked @ stacked.T, np.eye(ds), atol=1e-5)
  # Rows of unit norm over 3·Ds entries: entry std √(1/(3·Ds)) = 0.0361, not a per-gate
  # orthogonal matrix's 1/√Ds = 0.0625. 65,536 entries per gate put the sample std within ~0.3 %
  # of that (≈ 1/√(2·65536)); rtol 0.03 leaves room and is still far from the √3 wider value.
  for kernel in kernels:
    np.testing.assert_allclose(kernel.std(), np.sqrt(1.0 / (3 * ds)), rtol=0.03)
    assert kernel.std() < 0.7 / np.sqrt(ds)
  # Each gate's slice is different (the gates do not share one matrix).
  assert np.abs(kernels[0] - kernels[1]).max() > 1e-2
  assert np.abs(kernels[1] - kernels[2]).max() > 1e-2


def _torch_gru_numpy(x, h, weight_ih, weight_hh, bias_ih, bias_hh):
  """torch.nn.GRUCell's equations (PyTorch docs) on torch-layout stacked weights, gates r, z, n."""
  sigmoid = lambda a: 1.0 / (1.0 + np.exp(-a))
  gi = x @ weight_ih.T + bias_ih
  gh = h @ weight_hh.T + bias_hh
  i_r, i_z, i_n = np.split(gi, 3, axis=-1)
  h_r, h_z, h_n = np.split(gh, 3, axis=-1)
  r = sigmoid(i_r + h_r)
  z = sigmoid(i_z + h_z)
  n = np.tanh(i_n + r * h_n)
  return (1.0 - z) * n + z * h


def test_gru_matches_torch_equations_and_flax_gru_cell():
  din = 11
  rng = np.random.default_rng(0)
  x = rng.normal(size=(B, K, din)).astype(np.float32)
  h = rng.normal(size=(B, K, DS)).astype(np.float32)
  gru = sa.SlotGRU(features=DS)
  params = jax.jit(gru.init)(_key(0), jnp.asarray(h), jnp.asarray(x))
  # Random biases: the initial ones are zero and would not test their placement.
  params = jax.tree.map(
      lambda p: p + 0.3 * rng.normal(size=p.shape).astype(np.float32) if p.ndim == 1 else p,
      params)
  p = jax.tree.map(lambda a: np.asarray(a, np.float64), params["params"])
  # torch layout: weight [3·Ds, Din] = the transposed flax kernels stacked by gate; flax has no
  # b_hr, b_hz (folded into b_ir, b_iz), i.e. they are zero in torch terms.
  weight_ih = np.concatenate([p[g]["kernel"].T for g in ("ir", "iz", "in")])
  weight_hh = np.concatenate([p[g]["kernel"].T for g in ("hr", "hz", "hn")])
  bias_ih = np.concatenate([p[g]["bias"] for g in ("ir", "iz", "in")])
  bias_hh = np.concatenate([np.zeros(DS), np.zeros(DS), p["hn"]["bias"]])
  want = _torch_gru_numpy(x.astype(np.float64), h.astype(np.float64), weight_ih, weight_hh,
                          bias_ih, bias_hh)
  got, out = gru.apply(params, jnp.asarray(h), jnp.asarray(x))
  np.testing.assert_allclose(got, want, atol=1e-5)
  np.testing.assert_array_equal(got, out)
  # Same parameter tree and function as flax's GRUCell: only the initial values differ.
  cell_new, _ = nn.GRUCell(features=DS).apply(params, jnp.asarray(h), jnp.asarray(x))
  np.testing.assert_allclose(got, cell_new, atol=1e-6)
  cell_params = nn.GRUCell(features=DS).init(_key(0), jnp.asarray(h), jnp.asarray(x))
  chex.assert_trees_all_equal_shapes(cell_params, params)
