"""Editing a scene by its slots (docs/editing.md): remove, keep, move and swap slots, as functions
of what the model renders along rays.

Vocabulary (docs/method.md §0): `...` any leading batch shape (e.g. [B, R]), S samples per ray, K
real slots (K+1 with the empty slot s_∅ at index 0 of the point-slot weights W; the real slots are
numbered 0 … K−1 here, as in the rendered segmentation and the `--mode=render` panels).

A pass of the model over the samples of some rays gives, per sample, each real slot's share σ_k of
the density (`RenderOutput.slot_density`, Σ_k σ_k = σ: exp(s_σ)·W_k·ReLU(A_k) with slot-based
density, σ·W_k/Σ_{j≥1} W_j with `model.density_mode = "mlp"`; docs/method.md §1.4), the colour c
the colour MLP gives the sample, and the weights W. An edit takes each slot's density from one of
one or more passes, or from none (`composite`):

  σ̃ = Σ_k σ̃_k,   σ̃_k = σ_k of the pass that owns slot k (0 for a removed slot),
  c̃ = Σ_p (σ̃_p / σ̃)·c_p   with σ̃_p the density pass p contributes (c of pass 0 where σ̃ = 0),
  W̃_k = t_p·W_k of the pass p that owns slot k (0 for a removed slot), t_p = min(1, σ_p/σ̃),

with σ_p all of pass p's density at the sample, owned or not (t_p = 1 where σ̃ = 0),

then volume rendering (docs/method.md §1.5) of σ̃, c̃ and W̃ along the unchanged sample depths.
A pass's colour is one colour per sample, not one per slot (the colour MLP reads the slot mixture
F_s = Linear(W·S')), so a slot's colour reaches the picture only through its density: a removed
slot adds neither density nor colour, and a pass adds its colour in proportion to the density it
contributes.

- Remove slot k: one pass, slot k owned by none. In the space the object leaves the model renders
  what its other slots hold there: σ − σ_k, with the colour the sample had. Where the object stood
  the samples' colour came mostly from the object (the point-slot weights gave the point to slot
  k), and the points behind it lie where the source view saw the object, so their lifted features
  carry the object's colour (docs/method.md §1.3); where no other slot has density the ray stays
  transparent and renders black (no background colour, §1.5). docs/editing.md says what that
  looks like.
- Delete slot k (`Edit.delete_slot`; `Edit.moving(..., delete=True)` for the slot a move takes
  away): the plain pass decodes with slot k taken out of the slot set, so the allocation
  transformer and the point-slot weights W (a softmax over s_∅ and the slots) see only the
  others, and every point slot k held goes to the slot that matches it next, or to s_∅. This is
  the scene without the object as the model can express it: the floor under the object is held
  again by whichever slot its lifted features fit, and comes back if that is the background
  slot. Removing (zeroing σ_k) and deleting agree wherever slot k held no weight.
- Keep slots: the complement, one pass. Keeping one slot is what that slot renders alone in the
  `--mode=render` panels (rendering/pictures.render_each_slot).
- Move slot k by a rigid motion T (a translation t, optionally a turn about the vertical axis
  through a pivot): a second pass queries every sample at T⁻¹(x). Rays are rigid, so that pass is
  the model's pass along the ray T⁻¹(o) + z·R⁻¹d at the same depths z (`moved_rays`); its lifted
  features are gathered where T⁻¹(x) projects into the source views, i.e. where the source view
  saw the object before it moved. Slot k takes its density (and its share of the colour) from that
  pass, every other slot from the plain pass at x.
- Carry the background slot with a move (`carried_shares`): on the rays the moved slot covers,
  in proportion to its opacity there, the background slot comes from the moved pass too, so the
  air in front of the object stays as clear as the model rendered it where the object stood.
- Fill what an edit uncovers (`fill_uncovered`): where an edit leaves a ray more transparent than
  the unedited scene was, the background slot's own colour along the ray makes up the difference,
  as the renderer has no background colour of its own.
- Swap slot k between scenes: the second pass is another scene's (its slots and source views) at
  the same rays; slot k comes from it. With the background slot this puts one scene's objects on
  another's background.

The passes share the sample depths z, so `render_edit` runs the moved pass with
`SlotLifter.render_at_depths`, which covers coarse-only models (the synthetic sets); a model with a
fine pass (DTU, ScanNet) can remove and keep slots but not move them.

Translations are given in the model's frame; `frame_map` turns a world-space translation (the data
set's stored units and axes) into it, through data.scene_scale and data.frame.
"""

from __future__ import annotations

from typing import Callable, Optional, Sequence

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from slotlifter_jax import model as model_lib
from slotlifter_jax.rendering import volume

# Owner code of a slot that no pass renders (`Edit.owner`).
REMOVED = -1
PLAIN, MOVED = 0, 1  # pass indices in `render_edit`

# How a move decides, ray by ray, how much of the background slot it carries (`carry_fraction`):
# "winner" (the default: 1 where the moved slots win the moved pass's segmentation, else 0),
# "share" (their share of that segmentation) or "opacity" (their opacity alone). Compared on the
# validation split by experiments/moved_mask_probe.py (docs/editing.md §7).
CARRY_RULES = ("winner", "share", "opacity")
CARRY_RULE = "winner"


@flax.struct.dataclass
class SlotField:
  """What one pass of the model gives the samples of some rays."""
  slot_density: jax.Array  # [..., S, K] σ_k, each real slot's share of σ
  colour: jax.Array  # [..., S, C] the colour MLP's output
  weights: jax.Array  # [..., S, K+1] point-slot weights W, index 0 = s_∅


def field_of(out: model_lib.RenderOutput) -> SlotField:
  """The SlotField of the model's last pass (the fine one when there is one)."""
  return SlotField(slot_density=out.slot_density, colour=out.sample_colour,
                   weights=out.point_slot_weights)


def composite(fields: Sequence[SlotField], owner, *, z: jax.Array, far, density_scale: float,
              last_delta: Optional[jax.Array] = None,
              shares: Optional[Sequence[jax.Array]] = None) -> volume.RenderResult:
  """Volume rendering of slots drawn from several passes (module docstring).

  fields: P passes over the same samples; owner: [K] ints, the pass slot k comes from, or
  REMOVED; z: [..., S] the passes' common sample depths; far, density_scale, last_delta as in
  `volume.volume_render`. shares: instead of owner, P arrays broadcastable to [..., S, K], the
  share of each slot's density, weights and colour each pass gives at each sample
  (`carried_shares`); owner is the special case of one-hot shares. The segmentation is over the K
  real slots, W̃ normalised.
  """
  if shares is None:
    owner = jnp.asarray(owner, jnp.int32)  # [K]
    kept = [(owner == p).astype(f.slot_density.dtype) for p, f in enumerate(fields)]  # P × [K]
  else:
    kept = list(shares)
  per_pass = [jnp.sum(f.slot_density * m, axis=-1) for f, m in zip(fields, kept)]  # P × [..., S]
  density = sum(per_pass[1:], per_pass[0])  # [..., S]
  safe = jnp.where(density > 0, density, 1.0)
  colour = fields[0].colour
  if len(fields) > 1:
    # c_0 + Σ_{p≥1} (σ̃_p/σ̃)·(c_p − c_0) = Σ_p (σ̃_p/σ̃)·c_p, and exactly c_0 when every other pass
    # gives pass 0's colour (a move by zero).
    for p in range(1, len(fields)):
      share = jnp.where(density > 0, per_pass[p] / safe, 0.0)[..., None]  # [..., S, 1]
      colour = colour + share * (fields[p].colour - fields[0].colour)
  # W is a membership, not gated by density: the plain pass gives a point of empty air to the
  # background slot as surely as the moved pass gives the moved object's point to slot k, so the
  # plain sum of two passes' W would split the moved object's pixels with the background. Each
  # pass's W counts by min(1, σ_p/σ̃), σ_p all of that pass's density at the point: 1 with one pass
  # and on a move by zero, ~0 for a pass that is empty where another pass puts an object.
  real = jnp.zeros_like(fields[0].weights[..., 1:])  # [..., S, K]
  for f, m in zip(fields, kept):
    trust = jnp.where(density > 0, jnp.minimum(1.0, jnp.sum(f.slot_density, -1) / safe), 1.0)
    real = real + f.weights[..., 1:] * m * trust[..., None]
  weights = jnp.concatenate([fields[0].weights[..., :1], real], axis=-1)  # [..., S, K+1]
  return volume.volume_render(density=density, z=z, colour=colour, slot_weights=weights, far=far,
                              density_scale=density_scale, last_delta=last_delta)


# ---------------------------------------------------------------------------------------------
# Rigid motions of a slot
# ---------------------------------------------------------------------------------------------


@flax.struct.dataclass
class RigidMove:
  """x ↦ R(x − pivot) + pivot + translation, R the turn by `yaw` (radians, counter-clockwise
  seen from above) about the vertical (z) axis through `pivot`; all in the model's frame."""
  translation: jax.Array  # [3]
  yaw: jax.Array  # []
  pivot: jax.Array  # [3]; only its x and y matter

  @staticmethod
  def make(translation, yaw: float = 0.0, pivot=(0.0, 0.0, 0.0)) -> "RigidMove":
    return RigidMove(translation=jnp.asarray(translation, jnp.float32),
                     yaw=jnp.asarray(yaw, jnp.float32), pivot=jnp.asarray(pivot, jnp.float32))


def _turn(v: jax.Array, angle: jax.Array) -> jax.Array:
  """v [..., 3] turned by `angle` about z."""
  c, s = jnp.cos(angle), jnp.sin(angle)
  return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]],
                   axis=-1)


def apply_move(points: jax.Array, move: RigidMove) -> jax.Array:
  """T(x) for points [..., 3]."""
  return _turn(points - move.pivot, move.yaw) + move.pivot + move.translation


def inverse_move(points: jax.Array, move: RigidMove) -> jax.Array:
  """T⁻¹(x) for points [..., 3]."""
  return _turn(points - move.pivot - move.translation, -move.yaw) + move.pivot


def moved_rays(origins: jax.Array, directions: jax.Array, move: RigidMove):
  """The rays whose samples at depth z are T⁻¹ of the samples of rays [..., 3] at depth z."""
  return inverse_move(origins, move), _turn(directions, -move.yaw)


# ---------------------------------------------------------------------------------------------
# Edits of the model's rendering
# ---------------------------------------------------------------------------------------------


@flax.struct.dataclass
class Edit:
  """Which pass each real slot comes from (`composite`) and the motion of the moved pass.

  With `delete`, slot `deleted` also leaves the set the plain pass decodes with
  (`without_slot`), so the other slots' point-slot weights are normalised without it: what the
  model renders for the scene whose slot set lacks that object (module docstring, "Delete").
  """
  owner: jax.Array  # [K] int32: PLAIN, MOVED or REMOVED
  move: RigidMove
  deleted: jax.Array = 0  # [] int32: the slot the plain pass decodes without, when `delete`
  background: jax.Array = 0  # [] int32: the background slot of `carry` and `fill`
  has_move: bool = flax.struct.field(pytree_node=False, default=False)
  delete: bool = flax.struct.field(pytree_node=False, default=False)
  carry: bool = flax.struct.field(pytree_node=False, default=False)
  fill: bool = flax.struct.field(pytree_node=False, default=False)
  carry_rule: str = flax.struct.field(pytree_node=False, default=CARRY_RULE)

  def filling(self, background: Optional[int]) -> "Edit":
    """This edit with what it uncovers filled by the `background` slot's colour (`fill_uncovered`);
    unchanged when background is None or the edit removes that slot."""
    if background is None or int(np.asarray(self.owner)[int(background)]) == REMOVED:
      return self
    if self.carry and int(self.background) != int(background):
      raise ValueError(f"a move carries slot {int(self.background)} but fills with slot "
                       f"{int(background)}: one background slot serves both")
    return self.replace(background=jnp.asarray(background, jnp.int32), fill=True)

  @staticmethod
  def identity(num_slots: int) -> "Edit":
    return Edit(owner=jnp.zeros(num_slots, jnp.int32), move=RigidMove.make((0.0, 0.0, 0.0)))

  @staticmethod
  def remove(slots: Sequence[int], num_slots: int) -> "Edit":
    owner = np.zeros(num_slots, np.int32)
    owner[_check_slots(slots, num_slots)] = REMOVED
    return Edit(owner=jnp.asarray(owner), move=RigidMove.make((0.0, 0.0, 0.0)))

  @staticmethod
  def delete_slot(slot: int, num_slots: int) -> "Edit":
    """Remove `slot` by decoding without it (one slot; `remove` zeroes any number)."""
    edit = Edit.remove([slot], num_slots)
    return edit.replace(deleted=jnp.asarray(slot, jnp.int32), delete=True)

  @staticmethod
  def keep(slots: Sequence[int], num_slots: int) -> "Edit":
    owner = np.full(num_slots, REMOVED, np.int32)
    owner[_check_slots(slots, num_slots)] = PLAIN
    return Edit(owner=jnp.asarray(owner), move=RigidMove.make((0.0, 0.0, 0.0)))

  @staticmethod
  def moving(slot: int, num_slots: int, move: RigidMove, *, delete: bool = False,
             background: Optional[int] = None, carry_rule: str = CARRY_RULE) -> "Edit":
    """Move `slot`; with `delete` the other slots are decoded without it, as `delete_slot`; with
    a `background` slot other than `slot`, the move carries it along the rays the moved slot
    covers (`carried_shares`), in the fraction `carry_rule` gives (`carry_fraction`)."""
    owner = np.zeros(num_slots, np.int32)
    if carry_rule not in CARRY_RULES:
      raise ValueError(f"carry rule must be one of {CARRY_RULES}, got {carry_rule!r}")
    owner[_check_slots([slot], num_slots)] = MOVED
    carry = background is not None and int(background) != int(slot)
    if carry:
      _check_slots([background], num_slots)
    return Edit(owner=jnp.asarray(owner), move=move, has_move=True,
                deleted=jnp.asarray(slot, jnp.int32), delete=delete,
                background=jnp.asarray(background if carry else 0, jnp.int32), carry=carry,
                carry_rule=carry_rule)


# How a removal takes a slot away (docs/editing.md §4): "zero" its density and weights in the
# plain pass, or "delete" it from the slot set the plain pass decodes with.
REMOVALS = ("zero", "delete")


def removal_edit(slot: int, num_slots: int, removal: str) -> Edit:
  """Remove one slot the `removal` way (REMOVALS)."""
  _check_removal(removal)
  return Edit.delete_slot(slot, num_slots) if removal == "delete" else Edit.remove([slot],
                                                                                   num_slots)


def move_edit(slot: int, num_slots: int, move: RigidMove, removal: str,
              background: Optional[int] = None, carry_rule: str = CARRY_RULE) -> Edit:
  """Move one slot, taking it from where it stood the `removal` way (REMOVALS) and carrying the
  `background` slot along the rays it covers, if one is given (`carried_shares`)."""
  _check_removal(removal)
  return Edit.moving(slot, num_slots, move, delete=removal == "delete", background=background,
                     carry_rule=carry_rule)


def _check_removal(removal: str) -> None:
  if removal not in REMOVALS:
    raise ValueError(f"removal must be one of {REMOVALS}, got {removal!r}")


def _check_slots(slots: Sequence[int], num_slots: int) -> list[int]:
  slots = [int(k) for k in slots]
  bad = [k for k in slots if not 0 <= k < num_slots]
  if bad:
    raise ValueError(f"slot {bad[0]} out of range: the model has slots 0 … {num_slots - 1}")
  return slots


def edit_rays(render_pass: Callable, edit: Edit, *, origins: jax.Array, directions: jax.Array,
              far, density_scale: float, moved_pass: Optional[Callable] = None,
              unedited_pass: Optional[Callable] = None) -> volume.RenderResult:
  """An edited rendering of rays [..., 3] from a pass function.

  render_pass(origins, directions, z) → (SlotField, z): the field at the samples of the rays, at
  the depths z [..., S] when given and at the pass's own depths when z is None. The plain pass
  runs at its own depths; with `edit.has_move` a second pass, `moved_pass` (default
  `render_pass`), runs along `moved_rays` at the same depths. With `edit.fill` the unedited
  scene's opacity comes from `unedited_pass` at the same depths (default: the plain pass's field,
  right when the plain pass is the unedited one). Any field will do: the model's
  (`render_edit`), or a constructed one in the tests.
  """
  plain, z = render_pass(origins, directions, None)
  fields = [plain]
  shares = beta = None
  if edit.has_move:
    o, d = moved_rays(origins, directions, edit.move)
    moved, _ = (moved_pass or render_pass)(o, d, z)
    fields.append(moved)
    if edit.carry:
      # The moved pass rendered unedited: what `carry_fraction` reads, and the scene the fill
      # measures against on the carried rays.
      carried_scene = composite([moved], jnp.zeros_like(edit.owner), z=z, far=far,
                                density_scale=density_scale)
      beta = carry_fraction(edit.owner, moved, z=z, density_scale=density_scale,
                            rule=edit.carry_rule, moved_render=carried_scene)
      shares = carried_shares(edit.owner, edit.background, beta)
  edited = composite(fields, edit.owner, z=z, far=far, density_scale=density_scale,
                     shares=shares)
  if not edit.fill:
    return edited
  unedited = plain if unedited_pass is None else unedited_pass(origins, directions, z)[0]
  zeros = jnp.zeros_like(edit.owner)
  opacity_before = composite([unedited], zeros, z=z, far=far,
                             density_scale=density_scale).opacity  # [...]
  if beta is not None:
    # What a move uncovers on the rays it carries is measured against the scene it carries there:
    # the moved pass, the unedited scene where the object stood. Against the plain pass's opaque
    # floor at the new place the object's own translucency (opacity ~0.8) would read as uncovered
    # and the fill would hand its pixels to the background slot.
    opacity_before = (1.0 - beta) * opacity_before + beta * carried_scene.opacity
  only = jax.nn.one_hot(edit.background, edit.owner.shape[0], dtype=z.dtype)  # [K]
  if shares is None:
    owner = jnp.where(only > 0, edit.owner, REMOVED)
    background = composite(fields, owner, z=z, far=far, density_scale=density_scale)
  else:
    background = composite(fields, None, z=z, far=far, density_scale=density_scale,
                           shares=[sh * only for sh in shares])
  return fill_uncovered(edited, background, opacity_before=opacity_before,
                        background_slot=edit.background, far=far)


# Below this opacity a ray's background slot has no colour to fill with.
FILL_MIN_OPACITY = 1e-3


def fill_uncovered(edited: volume.RenderResult, background: volume.RenderResult, *,
                   opacity_before: jax.Array, background_slot, far) -> volume.RenderResult:
  """What an edit uncovers, filled by the background slot (docs/editing.md §1, "Fill").

  edited: the edit's rendering; background: the background slot alone in the same composite;
  opacity_before [...]: the unedited scene's opacity O₀ on the same rays. The renderer has no
  background colour (docs/method.md §1.5), so where an edit leaves a ray more transparent than
  the scene was (O₀ > O), the ray turns towards black. The trained background slot renders the
  floor opaque wherever the source view saw no object, and leaves the floor thin where one stood
  (its lifted features are the object's). The fill f = max(0, O₀ − O) takes the background slot's
  own colour along the ray, C_b / O_b, at its own depth D_b:
    C̃ = C + f·C_b/O_b,  Õ = O + f,  d̃ = d + f·(D_b − far),
    segmentation (M·O + f·e_b)/(O + f), the opacities standing in for the slot masses;
  no fill where O_b < FILL_MIN_OPACITY. Nothing changes where the edit uncovers nothing (O ≥ O₀),
  so an edit that changes nothing stays exact.
  """
  has = background.opacity >= FILL_MIN_OPACITY
  safe = jnp.where(has, background.opacity, 1.0)
  fill = jnp.where(has, jnp.maximum(0.0, opacity_before - edited.opacity), 0.0)  # [...]
  colour = edited.colour + fill[..., None] * background.colour / safe[..., None]
  depth_b = (background.depth - (1.0 - background.opacity) * far) / safe  # Σ w_b z / O_b
  depth = edited.depth + fill * (depth_b - far)
  opacity = edited.opacity + fill
  segmentation = edited.segmentation
  if segmentation is not None:
    e_b = jax.nn.one_hot(background_slot, segmentation.shape[-1], dtype=segmentation.dtype)
    mass = segmentation * edited.opacity[..., None] + fill[..., None] * e_b
    segmentation = jnp.where((fill > 0)[..., None],
                             mass / jnp.maximum(opacity, 1e-12)[..., None], segmentation)
  return edited.replace(colour=colour, depth=depth, opacity=opacity, segmentation=segmentation)


def carry_fraction(owner, moved: SlotField, *, z: jax.Array, density_scale: float,
                   rule: str = CARRY_RULE,
                   moved_render: Optional[volume.RenderResult] = None) -> jax.Array:
  """β [...]: the fraction of the background slot a move carries along each ray (`carried_shares`),
  read from the moved pass (the unedited scene at the rays moved by T⁻¹), which sees the moved
  slots (owner MOVED) where they stood:
    "winner":  1 where the moved slots together hold the largest part of the moved pass's
               segmentation (the model's own mask of the object, as `--mode=render` draws it), else 0;
    "share":   their part of that segmentation;
    "opacity": 1 − Π(1 − α) of their density alone (α as `volume`).
  Every rule gives 0 on the rays that do not see the moved slots where they stood.
  moved_render: the moved pass's own rendering (`composite([moved], all PLAIN)`), when the caller
  has it already (`edit_rays` uses it for the fill too); rendered here when None.
  """
  if rule not in CARRY_RULES:
    raise ValueError(f"carry rule must be one of {CARRY_RULES}, got {rule!r}")
  owner = jnp.asarray(owner, jnp.int32)  # [K]
  moved_mask = (owner == MOVED).astype(moved.slot_density.dtype)  # [K]
  if rule == "opacity":
    density = jnp.sum(moved.slot_density * moved_mask, axis=-1)  # [..., S]
    alpha = volume.alpha_from_density(density=density, z=z, density_scale=density_scale)
    return 1.0 - jnp.prod(1.0 - alpha, axis=-1)
  if moved_render is None:  # the moved pass rendered unedited; far does not reach the segmentation
    moved_render = composite([moved], jnp.zeros_like(owner), z=z, far=1.0,
                             density_scale=density_scale)
  segmentation = moved_render.segmentation  # [..., K]
  share = jnp.sum(segmentation * moved_mask, axis=-1)  # [...]
  if rule == "share":
    return share
  others = jnp.max(jnp.where(moved_mask > 0, -jnp.inf, segmentation), axis=-1)
  return (share > others).astype(share.dtype)


def carried_shares(owner, background, beta: jax.Array) -> list[jax.Array]:
  """The per-sample shares (`composite`) of a move that carries the background slot: [PLAIN,
  MOVED], each [..., 1, K].

  The moved slots (owner MOVED) and every other slot keep their pass; the background slot, owned
  by PLAIN, comes from the moved pass in proportion β [...] (`carry_fraction`) and from the plain
  pass in proportion 1 − β. Why: the background slot renders the floor as a haze through the
  scene slab and clears it in front of an object only where the model saw one; at the moved
  object's new place the plain pass has the haze, which hides the object and takes its pixels
  (docs/editing.md §7). On the rays the moved object covers, the background comes with it from
  where it stood: the air in front of it clear, the floor under it its own. With a move by zero
  both passes are one and the shares change nothing.
  """
  owner = jnp.asarray(owner, jnp.int32)  # [K]
  moved_mask = (owner == MOVED).astype(beta.dtype)  # [K]
  is_background = jax.nn.one_hot(background, owner.shape[0], dtype=beta.dtype)  # [K]
  plain_mask = (owner == PLAIN).astype(beta.dtype)
  carried = beta[..., None, None] * is_background  # [..., 1, K]
  return [plain_mask - carried, moved_mask + carried]


def without_slot(slots: jax.Array, slot) -> jax.Array:
  """slots [B, K, D] without slot `slot` (a traced int): [B, K−1, D], the others in order."""
  k = slots.shape[-2]
  keep = jnp.arange(k - 1) + (jnp.arange(k - 1) >= slot)  # skips `slot`
  return jnp.take(slots, keep, axis=-2)


def with_slot_restored(field: SlotField, slot) -> SlotField:
  """A field of K−1 slots (decoded `without_slot`) back on K slots, zero at `slot`."""
  def restore(x, offset):  # x [..., offset + K − 1]: the real slots start at `offset`
    k = x.shape[-1] - offset + 1
    j = jnp.arange(k)
    source = jnp.clip(j - (j > slot), 0, k - 2)
    real = jnp.where(j == slot, jnp.zeros((), x.dtype), jnp.take(x[..., offset:], source, axis=-1))
    return jnp.concatenate([x[..., :offset], real], axis=-1)
  return SlotField(slot_density=restore(field.slot_density, 0), colour=field.colour,
                   weights=restore(field.weights, 1))


def model_pass(model: model_lib.SlotLifter, params, encoded: model_lib.Encoded, sources: dict,
               *, deleted=None):
  """The render_pass of `edit_rays` for a model at evaluation: `model.render_rays`, or with z the
  coarse pass at those depths (`model.render_at_depths`, which refuses models with a fine pass).
  With `deleted` (a slot index) the model decodes without that slot and the field gets it back
  as zeros."""
  if deleted is not None:
    encoded = encoded.replace(slots=without_slot(encoded.slots, deleted))

  def render_pass(origins, directions, z):
    if z is None:
      out = model.apply({"params": params}, encoded, **sources, ray_origins=origins,
                        ray_directions=directions, train=False, method=model.render_rays)
    else:
      out = model.apply({"params": params}, encoded, **sources, ray_origins=origins,
                        ray_directions=directions, z=z, method=model.render_at_depths)
    field = field_of(out)
    return (field if deleted is None else with_slot_restored(field, deleted)), out.z
  return render_pass


def render_edit(model: model_lib.SlotLifter, params, encoded: model_lib.Encoded, sources: dict,
                edit: Edit, *, origins: jax.Array, directions: jax.Array) -> volume.RenderResult:
  """The model's rendering of rays [B, R, 3] with `edit` applied (module docstring)."""
  if edit.has_move and model.num_fine_samples > 0:
    raise ValueError(f"moving a slot needs one set of sample depths for both passes; the model "
                     f"has a fine pass (num_fine_samples={model.num_fine_samples}) whose depths "
                     f"follow each pass's own coarse weights")
  full = model_pass(model, params, encoded, sources)
  plain = model_pass(model, params, encoded, sources, deleted=edit.deleted) if edit.delete else full
  return edit_rays(plain, edit, origins=origins, directions=directions, far=model.far,
                   density_scale=model.density_scale, moved_pass=full,
                   unedited_pass=full if edit.delete else None)


def render_swap(model: model_lib.SlotLifter, params, scenes: Sequence[tuple], owner, *,
                origins: jax.Array, directions: jax.Array) -> volume.RenderResult:
  """Slots drawn from several scenes at the same rays: scenes is [(encoded, sources), …] and
  owner [K] names, per slot, the scene it comes from (or REMOVED). Each scene's pass lifts its own
  source views. A background swap: owner 1 for the background slot, 0 for the others."""
  first = model_pass(model, params, *scenes[0])
  plain, z = first(origins, directions, None)
  fields = [plain] + [model_pass(model, params, *s)(origins, directions, z)[0]
                      for s in scenes[1:]]
  return composite(fields, owner, z=z, far=model.far, density_scale=model.density_scale)


# ---------------------------------------------------------------------------------------------
# From world space to the model's frame
# ---------------------------------------------------------------------------------------------

# How far from a rotation the map between a scene's stored and model-frame cameras may be: the
# readers store poses as float32 of ten-decimal text.
FRAME_TOL = 1e-4


def frame_map(*, world_cam_to_world: np.ndarray, model_cam_to_world: np.ndarray,
              scene_scale: float) -> tuple[np.ndarray, np.ndarray]:
  """(A [3, 3], b [3]) with x_model = A·(scene_scale·x_world) + b, from one scene's cameras in
  the stored world frame ([N, 4, 4], world units) and in the model's frame ([N, 4, 4]).

  The model's frame is the world scaled by data.scene_scale and, with data.frame =
  "source_azimuth", turned about z so the source view sits at azimuth 0 (docs/method.md §3.6); A
  is that turn (the identity in the world frame). Every camera must map by the same A and b, else
  ValueError. A translation t_world moves points by scene_scale·A·t_world in the model frame; a
  turn about z stays a turn about z by the same angle when A is a turn about z.
  """
  world = np.asarray(world_cam_to_world, np.float64)
  ours = np.asarray(model_cam_to_world, np.float64)
  rot = ours[0, :3, :3] @ world[0, :3, :3].T
  shift = ours[0, :3, 3] - rot @ (scene_scale * world[0, :3, 3])
  if not np.allclose(rot @ rot.T, np.eye(3), atol=FRAME_TOL):
    raise ValueError("the model-frame cameras are not a rotation of the world-frame ones")
  for w, m in zip(world, ours):
    if not (np.allclose(rot @ w[:3, :3], m[:3, :3], atol=FRAME_TOL)
            and np.allclose(rot @ (scene_scale * w[:3, 3]) + shift, m[:3, 3],
                            atol=FRAME_TOL * max(1.0, float(np.abs(m[:3, 3]).max())))):
      raise ValueError("the scene's cameras do not all map from the world frame to the model's "
                       "by one rotation, scale and shift")
  return rot, shift


def world_translation(translation, *, rotation: np.ndarray, scene_scale: float) -> np.ndarray:
  """A world-space translation [3] (stored units and axes) in the model's frame [3]."""
  return scene_scale * (np.asarray(rotation, np.float64) @ np.asarray(translation, np.float64))

