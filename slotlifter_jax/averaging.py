"""An exponential moving average of the parameters, kept in the optimiser state (not in the paper).

With `train.ema_decay` = d > 0, `param_ema` ends the optimiser chain (train_step.make_optimizer).
Each applied update sets

    ema ← θ                        at the first update and before `train.ema_start_step`,
    ema ← d · ema + (1 − d) · θ    from then on,

where θ are the parameters after the update, so the average covers about the last 1 / (1 − d)
updates from its start on. Validation (and with it the best checkpoint and the restart check),
evaluation and rendering read `eval_params`: the average when it is on, the trained parameters
otherwise (`--params=trained` evaluates or renders the trained ones of a run that keeps both). A skipped (non-finite) step keeps the old optimiser state (train_step), so it leaves
the average as it was.

Why: over the release of `scene`'s masking floor, validation FG-ARI moves by up to 0.06 between
checkpoints 2000 steps apart (experiments/journal/2026-11.md, "the 50 000-step schedule on seed 0,
and which checkpoint is evaluated"), so which one the run ends on decides much of its last
checkpoint's score. An average of the weights is the
usual way to end on a settled model (Polyak & Juditsky 1992; the EMA of Tarvainen & Valpola 2017).

Off (d = 0), nothing is added to the optimiser state, so every checkpoint written without it
restores as before; turning it on or off for an existing run changes the state's structure, which
`checkpoints.check_compatible` refuses with the field's name.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax


class ParamEmaState(NamedTuple):
  count: jax.Array  # int32 scalar: updates applied so far
  ema: Any  # the average, a tree like the parameters


def enabled(train_config) -> bool:
  """Whether the run keeps the average; configs saved before the field existed read as off."""
  return float(train_config.get("ema_decay", 0.0)) > 0.0


def copied_updates(start_step: int) -> int:
  """How many first updates set the average to a copy of the parameters (module docstring)."""
  return max(int(start_step), 1)


def param_ema(decay: float, start_step: int = 0) -> optax.GradientTransformation:
  """Leaves the updates as they are and keeps the average of the parameters they lead to."""

  def init(params):
    # Its own buffers (the first update overwrites them): a tree sharing the parameters' buffers
    # would be donated twice by the train step.
    return ParamEmaState(count=jnp.zeros([], jnp.int32), ema=jax.tree.map(jnp.zeros_like, params))

  def update(updates, state, params=None):
    if params is None:
      raise ValueError("param_ema needs the parameters: call update(updates, state, params)")
    new = optax.apply_updates(params, updates)
    d = jnp.where(state.count < copied_updates(start_step), 0.0, decay).astype(jnp.float32)
    ema = jax.tree.map(lambda e, p: (d * e + (1.0 - d) * p).astype(e.dtype), state.ema, new)
    return updates, ParamEmaState(count=state.count + 1, ema=ema)

  return optax.GradientTransformation(init, update)


PARAMS = ("average", "trained")


def eval_params(state, train_config, which: str = "average") -> Any:
  """The parameters that validation, evaluation and rendering use (module docstring)."""
  return chosen_params(state, train_config, which)[0]


def chosen_params(state, train_config, which: str = "average") -> tuple[Any, str]:
  """(parameters, "average" | "trained": which of the two they are).

  which: "average" (the average when the run keeps one and has averaged, else the trained
  parameters) or "trained" (the trained parameters always). Until an update after the copied
  ones (`copied_updates`) the average is a copy of the parameters, so those are "trained". Both
  come from one training trajectory, since the average never changes what trains, so evaluating
  both on one checkpoint pairs them exactly.
  """
  if which not in PARAMS:
    raise ValueError(f"params={which!r}: must be one of {', '.join(PARAMS)}")
  if which == "trained" or not enabled(train_config):
    return state.params, "trained"
  (found,) = [x for x in jax.tree.leaves(state.opt_state,
                                         is_leaf=lambda x: isinstance(x, ParamEmaState))
              if isinstance(x, ParamEmaState)]
  # Before the first update the average holds nothing at all, and until the count passes the
  # copied updates nothing but the parameters.
  # (Read from this process's copy: in a multi-process run the replicated count is a global array.)
  count = int(jax.device_get(found.count.addressable_data(0)))
  averaged = count > copied_updates(train_config.get("ema_start_step", 0))
  return (found.ema, "average") if averaged else (state.params, "trained")
