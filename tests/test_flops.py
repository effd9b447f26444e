"""FLOP counting on jaxprs against hand-counted multiply-adds."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from slotlifter_jax import flops


def _zeros(*shape):
  return jnp.zeros(shape, jnp.float32)


def test_matmul_and_batched_einsum():
  assert flops.count_flops(jnp.matmul, _zeros(4, 8), _zeros(8, 16)) == 2 * 4 * 8 * 16
  einsum = lambda a, b: jnp.einsum("bij,bjk->bik", a, b)
  assert flops.count_flops(einsum, _zeros(3, 4, 5), _zeros(3, 5, 6)) == 2 * 3 * 4 * 5 * 6


@pytest.mark.parametrize("groups", [1, 4])
def test_convolution(groups):
  def conv(x, w):
    return jax.lax.conv_general_dilated(x, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"),
                                        feature_group_count=groups)
  x, w = _zeros(2, 8, 8, 4), _zeros(3, 3, 4 // groups, 8)
  # Each of the 2·8·8·8 outputs sums 3·3·(4/groups) products.
  assert flops.count_flops(conv, x, w) == 2 * (2 * 8 * 8 * 8) * (3 * 3 * 4 // groups)


def test_gradient_counts_backward_matmuls():
  loss = lambda x, w: jnp.sum(jnp.tanh(x @ w))
  forward = 2 * 4 * 8 * 16
  # Backward: dx = g·wᵀ and dw = xᵀ·g, each as costly as the forward product.
  assert flops.count_flops(jax.grad(loss, argnums=(0, 1)), _zeros(4, 8), _zeros(8, 16)) == 3 * forward
  assert flops.count_flops(jax.grad(loss, argnums=1), _zeros(4, 8), _zeros(8, 16)) == 2 * forward


def test_nested_jit_scan_and_cond():
  w = _zeros(8, 8)
  step = jax.jit(lambda h: jnp.tanh(h @ w))
  def scanned(h):
    return jax.lax.scan(lambda c, _: (step(c), None), h, None, length=5)[0]
  assert flops.count_flops(scanned, _zeros(4, 8)) == 5 * 2 * 4 * 8 * 8
  def branchy(p, h):
    return jax.lax.cond(p, lambda: h @ w @ w, lambda: h @ w)
  assert flops.count_flops(branchy, True, _zeros(4, 8)) == 2 * (2 * 4 * 8 * 8)


def test_matches_xla_cost_analysis_on_a_pure_matmul_chain():
  f = lambda a, b, c: (a @ b) @ c
  args = (_zeros(16, 32), _zeros(32, 64), _zeros(64, 8))
  ours = flops.count_flops(f, *args)
  xla = jax.jit(f).lower(*args).compile().cost_analysis()
  xla = xla[0] if isinstance(xla, (list, tuple)) else xla
  np.testing.assert_allclose(ours, xla["flops"], rtol=0.02)
