"""Matmul and convolution FLOPs of a function, counted on its jaxpr.

The count is what the model asks for (2 FLOPs per multiply-add of every dot_general and
conv_general_dilated, forward and backward when the function takes gradients), independent of
what XLA later fuses or rematerialises, so it is the numerator of model FLOP utilisation.
Elementwise work (softmax, norms, activations) is not counted, as in the usual MFU convention.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import jax


def dot_general_flops(lhs_shape, rhs_shape, dimension_numbers) -> int:
  (lhs_contract, rhs_contract), (lhs_batch, rhs_batch) = dimension_numbers
  rhs_free = [d for i, d in enumerate(rhs_shape) if i not in rhs_contract and i not in rhs_batch]
  # Every lhs element meets every free rhs column once per contraction: 2·|lhs|·|rhs free|.
  return 2 * math.prod(lhs_shape) * math.prod(rhs_free)


def conv_flops(out_shape, rhs_shape, dimension_numbers) -> int:
  out_feature_dim = dimension_numbers.rhs_spec[0]
  # rhs holds (in_features / groups) × kernel taps per output feature.
  per_output = math.prod(rhs_shape) // rhs_shape[out_feature_dim]
  return 2 * math.prod(out_shape) * per_output


def _sub_jaxprs(params: dict):
  for value in params.values():
    items = value if isinstance(value, (tuple, list)) else (value,)
    for item in items:
      if hasattr(item, "eqns"):
        yield item
      elif hasattr(item, "jaxpr") and hasattr(item.jaxpr, "eqns"):
        yield item.jaxpr


def jaxpr_flops(jaxpr) -> int:
  """Matmul + conv FLOPs of a (closed) jaxpr, through nested calls, scans (× length) and conds
  (the most expensive branch). A while loop's body is counted once (trip count unknown)."""
  jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
  total = 0
  for eqn in jaxpr.eqns:
    name = eqn.primitive.name
    if name == "dot_general":
      total += dot_general_flops(eqn.invars[0].aval.shape, eqn.invars[1].aval.shape,
                                 eqn.params["dimension_numbers"])
    elif name == "conv_general_dilated":
      total += conv_flops(eqn.outvars[0].aval.shape, eqn.invars[1].aval.shape,
                          eqn.params["dimension_numbers"])
    elif name == "cond":
      total += max(jaxpr_flops(b) for b in eqn.params["branches"])
    else:
      inner = sum(jaxpr_flops(j) for j in _sub_jaxprs(eqn.params))
      total += inner * (eqn.params["length"] if name == "scan" else 1)
  return total


def count_flops(fn: Callable, *args: Any, **kwargs: Any) -> int:
  """Matmul + conv FLOPs of one call fn(*args, **kwargs) (traced, not run)."""
  return jaxpr_flops(jax.make_jaxpr(fn)(*args, **kwargs))
