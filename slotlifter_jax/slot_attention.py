"""Slot attention with BO-QSA initialisation and the bi-level gradient (docs/method.md §1.2).

Shapes: B scenes, N = V·h·w input feature vectors per scene, D feature width, K slots,
Ds slot width (256).

Per iteration (Locatello et al. 2020, Alg. 1; BO-QSA, Jia et al. 2023):
  A = softmax_K(q(LN(slots)) · k(inputs)ᵀ / √Ds)      competition: slots compete for each input
  U = (A / (Σ_N A + ε)) · v(inputs)                      weighted mean, ε = 1 (official code)
  slots = GRU(U, slots);  slots += DropPath(MLP(LN(slots)))
The slots start from learned queries μ (plus scaled noise in training); after each non-final
iteration they are replaced by stop_gradient(slots) + μ − stop_gradient(μ) (BO-QSA's bi-level
optimisation): the gradient flows through the last iteration only, plus a straight-through path
to μ.

Initialisers follow the official code: xavier-uniform projections, a kaiming-uniform first MLP
layer, and μ drawn with the bound PyTorch's xavier_uniform_ gives the official [1, K, Ds] tensor
(fans K·Ds and Ds), which is ~3× smaller than flax's xavier on a [K, Ds] matrix. The GRU's
recurrent kernels are likewise cut from ONE orthogonal matrix over all three gates, as
torch.nn.init.orthogonal_ on the official stacked weight_hh [3·Ds, Ds] (entry std √(1/(3·Ds))),
not one orthogonal matrix per gate as flax's GRUCell draws them (std 1/√Ds, √3 wider); see
`SlotGRU`.

`dtype` (the model's `model.dtype`, model.py) is the computation dtype of the projections, the
GRU's and MLP's Linear layers, the q·k logits and the weighted mean; the softmax over slots, the
LayerNorm statistics and the slots themselves (the GRU state, which starts from the float32 μ)
stay float32.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp


# PyTorch's LayerNorm default, kept to match the official model.
LAYER_NORM_EPS = 1e-5


@flax.struct.dataclass
class Competition:
  attn: jax.Array  # [B, K, N] softmax over the K slots: Σ_K attn = 1 for every input
  updates: jax.Array  # [B, K, Ds] weighted mean of the values per slot


@flax.struct.dataclass
class Iteration:
  slots: jax.Array  # [B, K, Ds] slots after one iteration
  attn: jax.Array  # [B, K, N] that iteration's softmax-over-slots attention


@flax.struct.dataclass
class SlotAttentionResult:
  slots: jax.Array  # [B, K, Ds]
  attn: jax.Array  # [B, K, N] the last iteration's softmax-over-slots attention
  mu: jax.Array  # [K, Ds] the learned initial slots


def slot_competition(*, logits: jax.Array, values: jax.Array, eps: float) -> Competition:
  """Softmax over slots, then a weighted mean of the inputs per slot.

  Args:
    logits: [B, K, N] scaled query·key products.
    values: [B, N, Ds]; the weighted mean runs in their dtype (the model's computation dtype).
    eps: added to each slot's total attention before dividing; the official ε = 1 damps slots
      that win almost no inputs (their update shrinks towards 0 instead of amplifying noise).
  """
  # The softmax and the normalisation over N are reductions: float32 whatever the logits' dtype.
  attn = jax.nn.softmax(logits.astype(jnp.float32), axis=-2)  # [B, K, N]: over slots
  weights = attn / (jnp.sum(attn, axis=-1, keepdims=True) + eps)  # [B, K, N]
  updates = jnp.einsum("bkn,bnd->bkd", weights.astype(values.dtype), values)  # [B, K, Ds]
  return Competition(attn=attn, updates=updates)


def drop_path(x: jax.Array, *, rate: float, key: jax.Array) -> jax.Array:
  """Stochastic depth (timm DropPath): zero a whole sample's residual with probability `rate`.

  x: [B, ...]; one Bernoulli draw per leading index, survivors rescaled by 1/(1 − rate) so the
  expectation is unchanged.
  """
  keep_prob = 1.0 - rate
  mask = jax.random.bernoulli(key, keep_prob, (x.shape[0],) + (1,) * (x.ndim - 1))
  return jnp.where(mask, x / keep_prob, jnp.zeros_like(x))


def _mu_init(key, shape, dtype=jnp.float32):
  """xavier_uniform_ as PyTorch applies it to the official [1, K, Ds] parameter."""
  num_slots, dim = shape
  bound = math.sqrt(6.0 / (num_slots * dim + dim))
  return jax.random.uniform(key, shape, dtype, -bound, bound)


def _gate_slice_init(stacked_key: Optional[jax.Array], gate: int, num_gates: int = 3):
  """Initialiser for gate `gate`'s recurrent kernel: its slice of one stacked orthogonal draw.

  Flax hands every Dense its own rng key, so per-gate orthogonal draws would be independent and
  their concatenation not orthogonal. All gates therefore ignore their own key and draw the same
  [Ds_in, num_gates·Ds] orthogonal matrix from the shared `stacked_key` (same key → same matrix),
  then keep columns gate·Ds … (gate+1)·Ds. That matrix is the transpose of torch's stacked
  weight_hh [num_gates·Ds, Ds_in]: torch's orthonormal columns become orthonormal rows here.
  """
  def init(key, shape, dtype=jnp.float32):
    # Outside init (stacked_key None) flax only evaluates the initialiser abstractly, to check a
    # stored parameter's shape; the Dense's own key serves for that.
    fan_in, width = shape
    draw_key = key if stacked_key is None else stacked_key
    stacked = nn.initializers.orthogonal()(draw_key, (fan_in, num_gates * width), dtype)
    return stacked[:, gate * width:(gate + 1) * width]
  return init


class SlotGRU(nn.Module):
  """flax's GRUCell with torch's stacked orthogonal initialisation of the recurrent kernels.

  Same parameters (ir, iz, in with bias; hr, hz without; hn with bias — flax folds torch's b_hr,
  b_hz into b_ir, b_iz) and the same equations as `flax.linen.GRUCell`, which are torch's GRUCell
  equations:
    r = σ(W_ir x + b_ir + W_hr h)
    z = σ(W_iz x + b_iz + W_hz h)
    n = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn))
    h' = (1 − z) ⊙ n + z ⊙ h
  Only the initial values of W_hr, W_hz, W_hn differ: see `_gate_slice_init`.
  """
  features: int
  kernel_init: Any = nn.initializers.lecun_normal()  # input kernels, one per gate
  dtype: Any = jnp.float32  # computation dtype of the six Linear maps

  @nn.compact
  def __call__(self, carry: jax.Array, inputs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """carry h [..., Ds] and inputs x [..., Din] → (h', h'), as GRUCell."""
    h = carry
    # Draws a key only while the parameters are being created; `apply` needs no 'params' rng.
    stacked_key = self.make_rng("params") if self.is_initializing() else None
    dense_i = lambda name: nn.Dense(self.features, kernel_init=self.kernel_init,
                                    dtype=self.dtype, name=name)
    dense_h = lambda name, gate, use_bias=False: nn.Dense(
        self.features, use_bias=use_bias, kernel_init=_gate_slice_init(stacked_key, gate),
        dtype=self.dtype, name=name)
    r = nn.sigmoid(dense_i("ir")(inputs) + dense_h("hr", 0)(h))
    z = nn.sigmoid(dense_i("iz")(inputs) + dense_h("hz", 1)(h))
    n = jnp.tanh(dense_i("in")(inputs) + r * dense_h("hn", 2, use_bias=True)(h))
    new_h = (1.0 - z) * n + z * h  # the dtype of h: float32 slots stay float32
    return new_h, new_h


class SlotAttention(nn.Module):
  """BO-QSA slot attention: [B, N, D] features → K slots of width `slot_dim`."""
  num_slots: int = 8
  slot_dim: int = 256
  num_iters: int = 3
  mlp_dim: int = 1024
  eps: float = 1.0
  drop_path_rate: float = 0.2
  dtype: Any = jnp.float32  # computation dtype (see the module docstring)

  def setup(self):
    d = self.slot_dim
    self.mu = self.param("mu", _mu_init, (self.num_slots, d))
    # Statistics in float32 (flax's force_float32_reductions); the output feeds a Linear.
    norm = lambda: nn.LayerNorm(epsilon=LAYER_NORM_EPS, dtype=self.dtype)
    self.norm_inputs = norm()
    self.norm_slots = norm()
    self.norm_mlp = norm()
    project = lambda: nn.Dense(d, use_bias=False, kernel_init=nn.initializers.xavier_uniform(),
                               dtype=self.dtype)
    self.project_q = project()
    self.project_k = project()
    self.project_v = project()
    # PyTorch's xavier on the stacked [3·Ds, Ds] input kernel has variance 2/(Ds + 3·Ds); flax keeps
    # one [Ds, Ds] kernel per gate, so the same variance needs scale (Ds + Ds)/(Ds + 3·Ds) = 1/2.
    # The GRU has 512 fewer bias parameters than PyTorch's (it merges b_ir+b_hr, b_iz+b_hz). Its
    # recurrent kernels are slices of one orthogonal [Ds, 3·Ds] matrix, as torch's weight_hh.
    self.gru = SlotGRU(
        features=d, kernel_init=nn.initializers.variance_scaling(0.5, "fan_avg", "uniform"),
        dtype=self.dtype)
    # he_uniform = torch's kaiming_uniform_(nonlinearity='relu'), as the official first MLP layer.
    self.mlp_in = nn.Dense(self.mlp_dim, kernel_init=nn.initializers.he_uniform(),
                           dtype=self.dtype)
    self.mlp_out = nn.Dense(d, kernel_init=nn.initializers.xavier_uniform(), dtype=self.dtype)

  def initial_slots(self, batch: int, *, noise_sigma, train: bool) -> jax.Array:
    """μ + z·σ·stop_gradient(μ) with z from rng stream 'noise' in training; μ at evaluation."""
    mu = jnp.broadcast_to(self.mu, (batch,) + self.mu.shape)  # [B, K, Ds]
    if not train:
      return mu
    z = jax.random.normal(self.make_rng("noise"), mu.shape, mu.dtype)
    return mu + z * noise_sigma * jax.lax.stop_gradient(mu)

  def keys_values(self, inputs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """[B, N, D] features → keys and values [B, N, Ds].

    No positional embedding is added (docs/method.md §1.2)."""
    x = self.norm_inputs(inputs)
    return self.project_k(x), self.project_v(x)

  def update(self, slots: jax.Array, keys: jax.Array, values: jax.Array, *,
             train: bool) -> Iteration:
    """One iteration of slot attention from slots [B, K, Ds] given keys and values [B, N, Ds]."""
    q = self.project_q(self.norm_slots(slots))  # [B, K, Ds]
    # The product runs in the computation dtype; scaled and softmaxed in float32.
    logits = jnp.einsum("bkd,bnd->bkn", q, keys).astype(jnp.float32) / math.sqrt(
        self.slot_dim)  # [B, K, N]
    comp = slot_competition(logits=logits, values=values, eps=self.eps)
    new_slots, _ = self.gru(slots, comp.updates)  # carry = previous slots, input = updates
    residual = self.mlp_out(nn.relu(self.mlp_in(self.norm_mlp(new_slots))))
    if train and self.drop_path_rate > 0.0:
      residual = drop_path(residual, rate=self.drop_path_rate, key=self.make_rng("dropout"))
    return Iteration(slots=new_slots + residual, attn=comp.attn)

  def __call__(self, inputs: jax.Array, *, noise_sigma=0.0,
               train: bool = False) -> SlotAttentionResult:
    """inputs [B, N, D]; noise_sigma a (traced) scalar used only when `train`."""
    init = self.initial_slots(inputs.shape[0], noise_sigma=noise_sigma, train=train)
    keys, values = self.keys_values(inputs)
    slots = init
    attn: Optional[jax.Array] = None
    for i in range(self.num_iters):
      step = self.update(slots, keys, values, train=train)
      slots, attn = step.slots, step.attn
      if i < self.num_iters - 1:
        # Bi-level gradient. `init − stop_gradient(init)` is zero in value and passes the gradient
        # to μ unchanged (the noise term holds stop_gradient(μ)), i.e. it is μ − stop_gradient(μ).
        slots = jax.lax.stop_gradient(slots) + init - jax.lax.stop_gradient(init)
    return SlotAttentionResult(slots=slots, attn=attn, mu=self.mu)
