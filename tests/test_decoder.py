"""Allocation transformer, point-slot mapping, slot density, colour MLP (docs/method.md §1.4)."""

import chex
import flax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import decoder as dec

B, R, S, K, C, DS = 2, 3, 7, 5, 16, 12


def _key(seed):
  # 'rbg' keys: the modules do not care, and they compile much faster than threefry on XLA:CPU.
  return jax.random.key(seed, impl="rbg")


def _init(module, *args, **kw):
  return jax.jit(lambda key: module.init(key, *args, **kw))(_key(0))


def _decoder(num_blocks=3, **kw):
  return dec.SlotDecoder(width=C, num_blocks=num_blocks, num_heads=4, self_attn_dim=8, ffn_dim=24,
                         max_dropout=0.2, locality_box=0.64, **kw)


def _inputs(seed=0, scale=0.3):
  k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
  feats = jax.random.normal(k1, (B, R, S, C))
  slots = jax.random.normal(k2, (B, K, DS))
  points = scale * jax.random.normal(k3, (B, R, S, 3))
  return feats, slots, points


def test_conv1d_taps_dense_is_conv1d_same():
  rng = np.random.default_rng(0)
  x = rng.normal(size=(2, S, 5)).astype(np.float32)
  w = rng.normal(size=(4, 5, 3)).astype(np.float32)  # PyTorch Conv1d layout [out, in, k]
  kernel = np.concatenate([w[:, :, t].T for t in range(3)], axis=0)  # [3·in, out]
  got = dec.conv1d_taps(jnp.asarray(x)) @ kernel
  xp = np.pad(x, ((0, 0), (1, 1), (0, 0)))
  want = np.stack([np.einsum("btc,oct->bo", xp[:, s:s + 3], w) for s in range(S)], axis=1)
  np.testing.assert_allclose(got, want, atol=1e-4)


def test_dot_product_attention_matches_numpy():
  rng = np.random.default_rng(1)
  q = rng.normal(size=(2, 5, 3, 4)).astype(np.float32)
  k = rng.normal(size=(2, 7, 3, 4)).astype(np.float32)
  v = rng.normal(size=(2, 7, 3, 6)).astype(np.float32)
  got = dec.dot_product_attention(q=jnp.asarray(q), k=jnp.asarray(k), v=jnp.asarray(v))
  want = np.zeros((2, 5, 3, 6))
  for b in range(2):
    for h in range(3):
      logits = q[b, :, h] @ k[b, :, h].T / 2.0
      a = np.exp(logits - logits.max(-1, keepdims=True))
      want[b, :, h] = (a / a.sum(-1, keepdims=True)) @ v[b, :, h]
  np.testing.assert_allclose(got, want, atol=1e-5)


def test_locality_mask():
  rng = np.random.default_rng(2)
  logits = jnp.asarray(rng.normal(size=(4, K + 1)).astype(np.float32) * 5)
  points = jnp.asarray([[0.1, -0.2, 0.6], [0.7, 0.0, 0.0], [0.0, -0.65, 0.1], [0.3, 0.3, 0.3]])
  masked = dec.locality_mask(logits=logits, points=points, box=0.64, enabled=jnp.asarray(True))
  w = np.asarray(dec.point_slot_weights(masked))
  outside = np.array([False, True, True, False])
  assert np.all(w[outside][:, 2:] < 1e-30)
  np.testing.assert_allclose(w[outside][:, :2].sum(-1), 1.0, atol=1e-6)
  np.testing.assert_array_equal(np.asarray(masked)[~outside], np.asarray(logits)[~outside])
  np.testing.assert_array_equal(np.asarray(masked)[outside][:, :2],
                                np.asarray(logits)[outside][:, :2])
  off = dec.locality_mask(logits=logits, points=points, box=0.64, enabled=jnp.asarray(False))
  np.testing.assert_array_equal(off, logits)
  # Finite masking: gradients stay finite even through the masked entries.
  g = jax.grad(lambda l: jnp.sum(dec.point_slot_weights(dec.locality_mask(
      logits=l, points=points, box=0.64, enabled=True)) ** 2))(logits)
  assert np.all(np.isfinite(np.asarray(g)))


def test_slot_density_excludes_empty_slot():
  rng = np.random.default_rng(3)
  logits = rng.normal(size=(6, K + 1)).astype(np.float32) * 3
  weights = np.asarray(dec.point_slot_weights(jnp.asarray(logits)))
  sigma = dec.slot_density(logits=jnp.asarray(logits), weights=jnp.asarray(weights),
                           log_scale=jnp.asarray(0.5))
  want = np.exp(0.5) * np.sum(weights[:, 1:] * np.maximum(logits[:, 1:], 0), axis=-1)
  np.testing.assert_allclose(sigma, want, rtol=1e-5)
  assert np.all(np.asarray(sigma) >= 0)
  # Changing only the empty slot's logit/weight leaves σ unchanged.
  logits2, weights2 = logits.copy(), weights.copy()
  logits2[:, 0] += 10.0
  weights2[:, 0] = 0.9
  sigma2 = dec.slot_density(logits=jnp.asarray(logits2), weights=jnp.asarray(weights2),
                            log_scale=jnp.asarray(0.5))
  np.testing.assert_allclose(sigma2, sigma, rtol=1e-6)


def test_colour_activation_ranges():
  raw = jnp.linspace(-30.0, 30.0, 101)
  unit = dec.colour_activation(raw, mode="unit")
  signed = dec.colour_activation(raw, mode="signed")
  assert float(unit.min()) >= 0.0 and float(unit.max()) <= 1.0
  assert float(signed.min()) >= -1.0 and float(signed.max()) <= 1.0
  np.testing.assert_allclose(unit, (np.tanh(raw) + 1) / 2, atol=1e-6)
  with pytest.raises(ValueError):
    dec.colour_activation(raw, mode="sigmoid")


def test_paired_dropout_traced_rate():
  x, y = jnp.ones((20000,)), 2.0 * jnp.ones((20000,))
  f = jax.jit(lambda rate: dec.paired_dropout(x, y, rate=rate, key=jax.random.key(0)))
  for a, b in zip(f(0.0), (x, y)):  # rate 0 is exactly the identity (the scanned first block)
    np.testing.assert_array_equal(a, b)
  dx, dy = (np.asarray(v) for v in f(0.2))
  keep = round(0.8 * 2**16) / 2**16
  np.testing.assert_allclose(np.unique(dx), [0.0, 1.0 / keep], rtol=1e-6)
  np.testing.assert_allclose(np.unique(dy), [0.0, 2.0 / keep], rtol=1e-6)
  drop_x, drop_y = dx == 0, dy == 0
  # Binomial(20000, 0.2): the standard deviation of the dropped fraction is 0.0028.
  assert abs(drop_x.mean() - 0.2) < 0.012 and abs(drop_y.mean() - 0.2) < 0.012
  # The two masks come from different halves of each random word: independent, not equal.
  assert abs((drop_x & drop_y).mean() - 0.04) < 0.008
  # Inverted dropout keeps the expectation.
  assert abs(dx.mean() - 1.0) < 0.03


def test_slot_decoder_shapes_weights_density_and_jit():
  feats, slots, points = _inputs(scale=1.0)
  module = _decoder()
  params = _init(module, feats, slots, points, locality=True, train=False)
  apply = jax.jit(lambda p, locality: module.apply(p, feats, slots, points, locality=locality,
                                                    train=False))
  out = apply(params, True)
  chex.assert_shape(out.features, (B, R, S, C))
  chex.assert_shape([out.weights, out.logits], (B, R, S, K + 1))
  chex.assert_shape(out.density, (B, R, S))
  np.testing.assert_allclose(out.weights.sum(-1), 1.0, atol=1e-5)
  assert np.all(np.asarray(out.density) >= 0)
  outside = np.any(np.abs(np.asarray(points)) > 0.64, axis=-1)
  assert outside.any() and (~outside).any()
  assert np.all(np.asarray(out.weights)[outside][:, 2:] < 1e-30)
  off = apply(params, False)
  np.testing.assert_allclose(np.asarray(off.logits)[~outside], np.asarray(out.logits)[~outside],
                             atol=1e-6)
  assert np.asarray(off.weights)[outside][:, 2:].max() > 1e-3
  eager = module.apply(params, feats, slots, points, locality=True, train=False)
  chex.assert_trees_all_close(eager, out, atol=1e-5)
  # Density only through the real slots: the log-scale parameter starts at 0, i.e. scale 1.
  assert float(params["params"]["log_density_scale"]) == 0.0


def test_rays_do_not_interact():
  feats, slots, points = _inputs(seed=1)
  module = _decoder()
  params = _init(module, feats, slots, points, locality=True, train=False)
  out = module.apply(params, feats, slots, points, locality=True, train=False)
  # Change ray 1 only (a random change: a constant shift would vanish in the pre-LN blocks).
  feats2 = feats.at[:, 1].add(jax.random.normal(jax.random.key(7), (B, S, C)))
  out2 = module.apply(params, feats2, slots, points, locality=True, train=False)
  np.testing.assert_allclose(out2.weights[:, [0, 2]], out.weights[:, [0, 2]], atol=1e-6)
  assert np.abs(np.asarray(out2.weights[:, 1] - out.weights[:, 1])).max() > 1e-4


def _stack_blocks(params, num_blocks):
  """Loop layout {block_i: tree} → scan layout {blocks: tree stacked on axis 0}."""
  p = flax.core.unfreeze(params)
  tr = p["params"]["transformer"]
  blocks = [tr.pop(f"block_{i}") for i in range(num_blocks)]
  tr["blocks"] = jax.tree.map(lambda *xs: jnp.stack(xs), *blocks)
  return p


@pytest.mark.parametrize("train", [False, True])
def test_remat_scan_layout_is_the_same_function(train):
  feats, slots, points = _inputs(seed=2, scale=1.0)
  loop, scan = _decoder(2, remat_scan=False), _decoder(2, remat_scan=True)
  p_loop = _init(loop, feats, slots, points, locality=True, train=False)
  p_scan_init = jax.eval_shape(lambda: scan.init(_key(0), feats, slots, points, locality=True,
                                                 train=False))
  p_scan = _stack_blocks(p_loop, 2)
  chex.assert_trees_all_equal_shapes(p_scan, p_scan_init)
  count = lambda t: sum(x.size for x in jax.tree.leaves(t))
  assert count(p_loop) == count(p_scan_init)
  rngs = {"dropout": _key(5)}

  def run(module, params):
    def f(p, x):
      out = module.apply(p, x, slots, points, locality=True, train=train, rngs=rngs)
      return jnp.sum(out.features * out.density[..., None]), out
    # Tiny programs whose compilation dominates: skip XLA's backend optimisations.
    return jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True),
                   compiler_options={"xla_backend_optimization_level": 0})(params, feats)

  (v_loop, out_loop), (g_loop, gx_loop) = run(loop, p_loop)
  (v_scan, out_scan), (g_scan, gx_scan) = run(scan, p_scan)
  chex.assert_trees_all_close(out_scan, out_loop, atol=1e-5, rtol=1e-5)
  chex.assert_trees_all_close(_stack_blocks(g_loop, 2), g_scan, atol=1e-4, rtol=1e-4)
  np.testing.assert_allclose(gx_scan, gx_loop, atol=1e-5, rtol=1e-4)
  if train:  # dropout is active: a train run differs from the deterministic one
    det = loop.apply(p_loop, feats, slots, points, locality=True, train=False)
    assert np.abs(np.asarray(det.features - out_loop.features)).max() > 1e-3


def test_output_projection_gain():
  feats, slots, points = _inputs()
  module = dec.SlotDecoder(width=64, num_blocks=4, num_heads=4, self_attn_dim=16, ffn_dim=256)
  params = _init(module, jnp.zeros((1, 2, 5, 64)), slots[:1], points[:1, :2, :5], locality=False,
                 train=False)["params"]["transformer"]["block_0"]
  gain = 12 ** -0.5
  def bound(kernel, g=1.0):
    return g * np.sqrt(6.0 / (kernel.shape[0] + kernel.shape[1]))
  for name, g in [(("cross_attn", "out"), gain), (("self_attn", "out"), gain),
                  (("ffn_out",), gain), (("cross_attn", "query"), 1.0)]:
    kern = params
    for n in name:
      kern = kern[n]
    kern = np.asarray(kern["kernel"])
    assert np.abs(kern).max() <= bound(kern, g) + 1e-7
    assert np.abs(kern).max() > 0.9 * bound(kern, g)


def test_colour_mlp():
  x = jax.random.normal(jax.random.key(0), (B, R, S, C)) * 10
  for mode, lo in [("unit", 0.0), ("signed", -1.0)]:
    mlp = dec.ColourMLP(hidden=C, num_layers=4, colour_range=mode)
    params = _init(mlp, x)
    out = mlp.apply(params, x)
    chex.assert_shape(out, (B, R, S, 3))
    assert float(out.min()) >= lo and float(out.max()) <= 1.0
    assert len(params["params"]) == 5


# ---------------------------------------------------------------------------------------------
# The "without slot-based density" ablation (docs/method.md §5).


def test_mlp_density_matches_numpy_and_stays_finite():
  raw = np.array([-200.0, -30.0, -1.0, 0.0, 0.7, 30.0, 200.0], np.float32)[:, None]  # [7, 1]
  sigma = np.asarray(dec.mlp_density(raw=jnp.asarray(raw), log_scale=jnp.asarray(-3.0)))
  want = np.exp(-3.0) * np.logaddexp(0.0, raw[:, 0].astype(np.float64))  # softplus
  np.testing.assert_allclose(sigma, want, rtol=1e-5, atol=1e-30)
  assert sigma.shape == (7,) and np.all(sigma >= 0) and np.all(np.isfinite(sigma))
  grad = jax.grad(lambda r: jnp.sum(dec.mlp_density(raw=r, log_scale=jnp.asarray(0.0))))(
      jnp.asarray(raw))
  assert np.all(np.isfinite(np.asarray(grad))) and np.all(np.asarray(grad)[1:-1] > 0)


def test_mlp_density_mode_adds_a_head_and_leaves_the_mapping_alone():
  feats, slots, points = _inputs(seed=4, scale=1.0)
  mlp = _decoder(density_mode="mlp", density_log_init=-1.5)
  params = _init(mlp, feats, slots, points, locality=True, train=False)
  p = params["params"]
  assert p["density_hidden"]["kernel"].shape == (C, C)
  assert p["density_out"]["kernel"].shape == (C, 1)
  assert float(p["log_density_scale"]) == -1.5
  out = jax.jit(lambda v: mlp.apply(v, feats, slots, points, locality=True, train=False))(params)
  chex.assert_shape(out.density, (B, R, S))
  density = np.asarray(out.density)
  assert np.all(np.isfinite(density)) and np.all(density >= 0)
  # Not the slot formula on the same logits and weights.
  slot_formula = np.asarray(dec.slot_density(logits=out.logits, weights=out.weights,
                                             log_scale=p["log_density_scale"]))
  assert np.abs(density - slot_formula).max() > 1e-3
  # The same parameters without the head, in the paper's mode: W, A and F_s are identical and σ
  # is the slot formula, so the switch changes the density only.
  slot = _decoder(density_log_init=-1.5)
  shared = {"params": {k: v for k, v in p.items() if not k.startswith("density_")}}
  assert jax.tree.structure(shared) == jax.tree.structure(
      _init(slot, feats, slots, points, locality=True, train=False))
  ref = slot.apply(shared, feats, slots, points, locality=True, train=False)
  for name in ("weights", "logits", "features"):
    np.testing.assert_allclose(getattr(ref, name), getattr(out, name), atol=1e-6, err_msg=name)
  np.testing.assert_allclose(ref.density, slot_formula, rtol=1e-5, atol=1e-7)
  with pytest.raises(ValueError, match="density_mode"):
    _init(_decoder(density_mode="nerf"), feats, slots, points, locality=True, train=False)


def test_slot_density_shares_match_numpy_in_both_modes():
  """Slot mode: the terms exp(s_σ)·W_k·ReLU(A_k) of σ. MLP mode: σ split by W_k / Σ_{j≥1} W_j.
  Either way the K shares sum to σ, so the per-slot renders of both modes add up to the model."""
  rng = np.random.default_rng(2)
  logits = jnp.asarray(rng.normal(size=(2, 7, 11, 6)).astype(np.float32))  # [B, R, S, K+1]
  weights = dec.point_slot_weights(logits)
  log_scale = jnp.float32(0.3)
  a = np.asarray(logits, np.float64)
  w = np.exp(a - a.max(-1, keepdims=True))
  w /= w.sum(-1, keepdims=True)

  sigma = dec.slot_density(logits=logits, weights=weights, log_scale=log_scale)
  shares = dec.slot_density_shares(density=sigma, logits=logits, weights=weights,
                                   log_scale=log_scale, mode="slot")
  assert shares.shape == (2, 7, 11, 5)
  np.testing.assert_allclose(shares, np.exp(0.3) * w[..., 1:] * np.maximum(a[..., 1:], 0),
                             rtol=1e-5, atol=1e-7)
  np.testing.assert_allclose(shares.sum(-1), sigma, rtol=1e-5, atol=1e-7)

  head = jnp.asarray(rng.uniform(0.0, 5.0, size=(2, 7, 11)).astype(np.float32))  # any σ ≥ 0
  shares = dec.slot_density_shares(density=head, logits=logits, weights=weights,
                                   log_scale=log_scale, mode="mlp")
  want = np.asarray(head)[..., None] * w[..., 1:] / w[..., 1:].sum(-1, keepdims=True)
  np.testing.assert_allclose(shares, want, rtol=1e-5, atol=1e-7)
  np.testing.assert_allclose(shares.sum(-1), head, rtol=1e-5)
  # A point that only the empty slot takes has no real slot to share σ with: no NaN.
  only_empty = jnp.asarray([[80.0, -80.0, -80.0]])
  safe = dec.slot_density_shares(density=jnp.asarray([2.0]), logits=only_empty,
                                 weights=dec.point_slot_weights(only_empty), log_scale=log_scale,
                                 mode="mlp")
  assert np.all(np.isfinite(np.asarray(safe)))


def test_the_decoder_returns_shares_that_sum_to_its_density_in_both_modes():
  feats, slots, points = _inputs(seed=4, scale=1.0)
  for mode in ("slot", "mlp"):
    model = _decoder(density_mode=mode)
    params = _init(model, feats, slots, points, locality=True, train=False)
    out = jax.jit(lambda v: model.apply(v, feats, slots, points, locality=True,
                                        train=False))(params)
    chex.assert_shape(out.slot_densities, (B, R, S, out.weights.shape[-1] - 1))
    np.testing.assert_allclose(np.asarray(out.slot_densities).sum(-1), out.density, rtol=1e-5,
                               atol=1e-6, err_msg=mode)
