"""Tests of slotlifter_jax.rendering.volume against a plain NumPy for-loop renderer and at
extreme densities."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax.rendering import volume

B, R, S, K, C = 2, 7, 11, 5, 3
SCALE = 25.0
FAR = 3.5


def _numpy_render(density, z, colour, slot_weights, far, scale):
  """docs/method.md §1.5 written ray by ray, sample by sample, in float64."""
  lead = density.shape[:-1]
  out_c = np.zeros(lead + (colour.shape[-1],))
  out_d, out_o = np.zeros(lead), np.zeros(lead)
  out_w = np.zeros(density.shape)
  out_m = np.zeros(lead + (slot_weights.shape[-1] - 1,))
  for idx in np.ndindex(lead):
    transmittance = 1.0
    for i in range(density.shape[-1]):
      delta = z[idx][i + 1] - z[idx][i] if i + 1 < density.shape[-1] else 0.0
      alpha = 1.0 - np.exp(-density[idx][i] * delta * scale)
      w = alpha * transmittance
      transmittance *= 1.0 - alpha + 1e-10
      out_w[idx][i] = w
      out_c[idx] += w * colour[idx][i]
      out_d[idx] += w * z[idx][i]
      out_m[idx] += w * slot_weights[idx][i, 1:]
    out_o[idx] = out_w[idx].sum()
    out_d[idx] += (1.0 - out_o[idx]) * far
    out_m[idx] = out_m[idx] / (out_m[idx].sum() + 1e-6)
  return out_c, out_d, out_w, out_o, out_m


def _random_inputs(seed, density_scale=1.0):
  rng = np.random.default_rng(seed)
  z = np.sort(rng.uniform(0.9, 2.9, size=(B, R, S)), axis=-1)
  density = rng.exponential(density_scale, size=(B, R, S))
  density[0, 0] = 0.0  # an empty ray
  density[1, 2, 3] = 1e4  # an opaque sample mid-ray
  colour = rng.uniform(size=(B, R, S, C))
  logits = rng.normal(size=(B, R, S, K + 1))
  slot_weights = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
  return density, z, colour, slot_weights


def _render(density, z, colour, slot_weights, **kwargs):
  f32 = lambda a: None if a is None else jnp.asarray(a, jnp.float32)
  return volume.volume_render(density=f32(density), z=f32(z), colour=f32(colour),
                              slot_weights=f32(slot_weights), far=FAR, density_scale=SCALE,
                              **kwargs)


@pytest.mark.parametrize("density_scale", [0.05, 1.0])
def test_volume_render_matches_numpy_loop(density_scale):
  density, z, colour, slot_weights = _random_inputs(0, density_scale)
  out = _render(density, z, colour, slot_weights)
  chex.assert_shape(out.colour, (B, R, C))
  chex.assert_shape([out.depth, out.opacity], (B, R))
  chex.assert_shape([out.weights, out.alpha], (B, R, S))
  chex.assert_shape(out.segmentation, (B, R, K))
  ref_c, ref_d, ref_w, ref_o, ref_m = _numpy_render(density, z, colour, slot_weights, FAR, SCALE)
  np.testing.assert_allclose(np.asarray(out.weights), ref_w, atol=1e-6)
  np.testing.assert_allclose(np.asarray(out.colour), ref_c, atol=1e-5)
  np.testing.assert_allclose(np.asarray(out.depth), ref_d, atol=1e-5)
  np.testing.assert_allclose(np.asarray(out.opacity), ref_o, atol=1e-5)
  np.testing.assert_allclose(np.asarray(out.segmentation), ref_m, atol=1e-5)
  alpha = volume.alpha_from_density(density=jnp.asarray(density, jnp.float32),
                                    z=jnp.asarray(z, jnp.float32), density_scale=SCALE)
  np.testing.assert_allclose(np.asarray(alpha), np.asarray(out.alpha), rtol=1e-6)


def test_weights_bounded_and_special_rays():
  density, z, colour, slot_weights = _random_inputs(1, 3.0)
  out = _render(density, z, colour, slot_weights)
  w = np.asarray(out.weights)
  assert np.all(w >= 0) and np.all(w.sum(-1) <= 1 + 1e-6)
  assert np.all(np.asarray(out.opacity) <= 1 + 1e-6)
  # Empty ray: nothing rendered, depth at far, segmentation zero (not NaN).
  np.testing.assert_array_equal(np.asarray(out.colour[0, 0]), 0.0)
  np.testing.assert_allclose(float(out.depth[0, 0]), FAR, rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(out.segmentation[0, 0]), 0.0)
  # Last δ = 0: the last sample never gets weight.
  np.testing.assert_array_equal(w[..., -1], 0.0)
  # Segmentation of non-empty rays sums to 1 over the K real slots.
  np.testing.assert_allclose(np.asarray(out.segmentation[1]).sum(-1), 1.0, atol=1e-4)


def test_opaque_first_sample_takes_everything():
  rng = np.random.default_rng(2)
  z = np.sort(rng.uniform(1, 2, size=(R, S)), axis=-1)
  density = rng.uniform(size=(R, S))
  density[:, 0] = 1e6
  colour = rng.uniform(size=(R, S, C))
  slot_weights = rng.dirichlet(np.ones(K + 1), size=(R, S))
  out = _render(density, z, colour, slot_weights)
  np.testing.assert_allclose(np.asarray(out.colour), colour[:, 0], rtol=1e-5)
  np.testing.assert_allclose(np.asarray(out.depth), z[:, 0], rtol=1e-5)
  seg = slot_weights[:, 0, 1:] / slot_weights[:, 0, 1:].sum(-1, keepdims=True)
  np.testing.assert_allclose(np.asarray(out.segmentation), seg, rtol=1e-4)


def test_no_slot_weights_gives_no_segmentation():
  density, z, colour, _ = _random_inputs(3)
  out = _render(density, z, colour, None)
  assert out.segmentation is None
  chex.assert_shape(out.colour, (B, R, C))


@pytest.mark.parametrize("value", [0.0, 1e-8, 1.0, 1e3, 1e6])
def test_finite_values_and_gradients_at_extreme_densities(value):
  rng = np.random.default_rng(4)
  z = np.sort(rng.uniform(1, 2, size=(R, S)), axis=-1)
  z[:, 4] = z[:, 3]  # a zero-length interval (δ = 0) mid-ray
  z = jnp.asarray(z, jnp.float32)
  colour = jnp.asarray(rng.uniform(size=(R, S, C)), jnp.float32)
  slot_weights = jax.nn.softmax(jnp.asarray(rng.normal(size=(R, S, K + 1)), jnp.float32))
  density = jnp.full((R, S), value, jnp.float32)

  def loss(density, colour, slot_weights):
    out = volume.volume_render(density=density, z=z, colour=colour, slot_weights=slot_weights,
                               far=FAR, density_scale=SCALE)
    return (out.colour.sum() + out.depth.sum() + out.segmentation.sum() + out.weights.sum()
            + out.alpha.sum())

  out = volume.volume_render(density=density, z=z, colour=colour, slot_weights=slot_weights,
                             far=FAR)
  for leaf in jax.tree.leaves(out):
    assert np.all(np.isfinite(np.asarray(leaf)))
  grads = jax.grad(loss, argnums=(0, 1, 2))(density, colour, slot_weights)
  for g in grads:
    assert np.all(np.isfinite(np.asarray(g)))
  alpha_grad = jax.grad(
      lambda d: volume.alpha_from_density(density=d, z=z).sum())(density)
  assert np.all(np.isfinite(np.asarray(alpha_grad)))
  # Colour gradient equals the weights, which must also be finite and non-negative.
  np.testing.assert_allclose(np.asarray(grads[1][..., 0]), np.asarray(out.weights), atol=1e-6)


def test_alpha_small_density_is_exact():
  z = jnp.array([1.0, 1.5, 2.5])
  alpha = volume.alpha_from_density(density=jnp.full((3,), 1e-8), z=z, density_scale=SCALE)
  # 1 − exp(−x) ≈ x for tiny x; a naive 1 − exp(−x) in float32 would return 0.
  np.testing.assert_allclose(np.asarray(alpha), [1e-8 * 0.5 * SCALE, 1e-8 * 1.0 * SCALE, 0.0],
                             rtol=1e-5)


def test_jit_and_vmap_agree():
  density, z, colour, slot_weights = _random_inputs(5)
  args = [jnp.asarray(a, jnp.float32) for a in (density, z, colour, slot_weights)]

  def f(d, zz, c, sw):
    return volume.volume_render(density=d, z=zz, colour=c, slot_weights=sw, far=FAR)

  eager, jitted, mapped = f(*args), jax.jit(f)(*args), jax.vmap(f)(*args)
  for other in (jitted, mapped):
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(other)):
      np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
