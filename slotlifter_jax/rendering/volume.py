"""Volume rendering of densities, colours and slot weights along rays (docs/method.md §1.5).

Vocabulary (docs/method.md §0): S samples per ray, K real slots (K+1 with the empty slot at index
0), C colour channels; `...` is any leading batch shape (e.g. [B, R]). Pure functions, keyword-only
arguments.

  δ_i = z_{i+1} − z_i (last δ = 0),   α_i = 1 − exp(−σ_i·δ_i·scale),
  T_i = Π_{j<i} (1 − α_j + 1e-10),   w_i = α_i·T_i,
  C = Σ w_i c_i (no background colour),   depth = Σ w_i z_i + (1 − Σ w_i)·far,
  M = Σ w_i W_i[1:] normalised over the K real slots.
"""

from __future__ import annotations

from typing import Optional

import flax.struct
import jax
import jax.numpy as jnp

# Added to every transmittance factor as in the official renderer, so T never becomes exactly zero.
TRANSMITTANCE_EPS = 1e-10
# Denominator guard when normalising the rendered slot masses over the K real slots (official 1e-6).
SEGMENTATION_EPS = 1e-6


@flax.struct.dataclass
class RenderResult:
  colour: jax.Array  # [..., C]
  depth: jax.Array  # [...]
  segmentation: Optional[jax.Array]  # [..., K] sums to ~1 over K (None without slot weights)
  weights: jax.Array  # [..., S] w_i = α_i·T_i
  opacity: jax.Array  # [...] Σ_i w_i ∈ [0, 1]
  alpha: jax.Array  # [..., S]


def _optical_depth(*, density: jax.Array, z: jax.Array, density_scale: float,
                   last_delta: Optional[jax.Array] = None) -> jax.Array:
  """σ_i·δ_i·scale with δ_i = z_{i+1} − z_i: [..., S] -> [..., S].

  The last δ is 0 (docs/method.md §1.5) unless `last_delta` [...] gives it: a window of a longer
  sample grid (slotlifter_jax.rendering.adaptive) ends at a sample whose grid successor it does
  not hold, and its last sample must keep the δ it has in the whole grid for the window to
  composite like the grid.
  """
  if last_delta is None:
    last = jnp.zeros_like(z[..., :1])
  else:
    last = jnp.broadcast_to(jnp.asarray(last_delta, z.dtype)[..., None], z[..., :1].shape)
  delta = jnp.concatenate([z[..., 1:] - z[..., :-1], last], axis=-1)  # [..., S]
  return density * delta * density_scale


def alpha_from_density(*, density: jax.Array, z: jax.Array,
                       density_scale: float = 25.0) -> jax.Array:
  """α_i = 1 − exp(−σ_i·δ_i·scale): density, z [..., S] -> [..., S].

  Written as −expm1(−x): exact for tiny x (σ = 1e-8) and, since dα/dx = exp(−x), finite with finite
  gradients for any finite x ≥ 0, including σ = 1e6 and δ = 0.
  """
  return -jnp.expm1(-_optical_depth(density=density, z=z, density_scale=density_scale))


def volume_render(*, density: jax.Array, z: jax.Array, colour: jax.Array,
                  slot_weights: Optional[jax.Array], far,
                  density_scale: float = 25.0,
                  last_delta: Optional[jax.Array] = None) -> RenderResult:
  """Composites samples along each ray (docs/method.md §1.5).

  Args:
    density: [..., S] σ ≥ 0.
    z: [..., S] sorted sample depths.
    colour: [..., S, C].
    slot_weights: [..., S, K+1] point-to-slot weights W (empty slot at index 0), or None.
    far: scalar or [...]; depth assigned to the transparent remainder 1 − Σ w (the official code uses
      the largest sample depth, which equals far at evaluation).
    density_scale: the 25 in α = 1 − exp(−25·σ·δ).
    last_delta: None (the last δ is 0) or [...] the δ of the last sample, for a window of a longer
      grid (see `_optical_depth`).

  Returns:
    RenderResult (any leading shape `...`).
  """
  optical_depth = _optical_depth(density=density, z=z, density_scale=density_scale,
                                 last_delta=last_delta)
  alpha = -jnp.expm1(-optical_depth)  # [..., S]
  # log(1 − α_j + ε) = log(exp(−x_j) + ε), evaluated stably as a logaddexp; the exclusive cumulative
  # sum then gives log T_i without an underflowing product or a division in the gradient.
  log_factor = jnp.logaddexp(-optical_depth, jnp.log(TRANSMITTANCE_EPS))  # [..., S]
  log_t = jnp.concatenate(  # exclusive cumulative sum: log T_0 = 0
      [jnp.zeros_like(log_factor[..., :1]), jnp.cumsum(log_factor[..., :-1], axis=-1)], axis=-1)
  weights = alpha * jnp.exp(log_t)  # [..., S]
  opacity = jnp.sum(weights, axis=-1)  # [...]
  rgb = jnp.einsum("...s,...sc->...c", weights, colour)  # [..., C]
  depth = jnp.sum(weights * z, axis=-1) + (1.0 - opacity) * far  # [...]
  segmentation = None
  if slot_weights is not None:
    mass = jnp.einsum("...s,...sk->...k", weights, slot_weights[..., 1:])  # [..., K]
    segmentation = mass / (jnp.sum(mass, axis=-1, keepdims=True) + SEGMENTATION_EPS)
  return RenderResult(colour=rgb, depth=depth, segmentation=segmentation, weights=weights,
                      opacity=opacity, alpha=alpha)
