"""Slot edits of the model's rendering (slotlifter_jax/rendering/edits.py, docs/editing.md) against
independent references: the per-slot rendering of the `--mode=render` panels, the plain render,
the plain model seen from a moved camera, a NumPy volume renderer of a constructed field, and the
camera-relative coordinates of a scene in two frames. Every model test runs for both
`model.density_mode`s; they compile a tiny model (about 30 s in all), so they are marked slow,
as tests/conftest.py's SLOW_FILES rule has it for files that compile models."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tiny_model as tm
from random_cameras import look_at
from tiny_model import K, jit

from slotlifter_jax.data import cameras
from slotlifter_jax.rendering import edits
from slotlifter_jax.rendering import pictures

MODES = ("slot", "mlp")


@functools.lru_cache(maxsize=None)
def _setup(mode):
  """A tiny one-source-view model in `mode`, its inputs, parameters and encoded scenes."""
  model = tm.tiny(density_mode=mode)
  inputs = tm.make_inputs(1)
  params = tm.init(model, inputs)["params"]
  sources = tm.sources(inputs)
  encoded = jit(lambda p: model.apply({"params": p}, **sources, train=False,
                                      method=model.encode))(params)
  return model, inputs, params, sources, encoded


def _render_edit(mode, edit, origins=None, directions=None):
  model, inputs, params, sources, encoded = _setup(mode)
  origins = inputs["ray_origins"] if origins is None else jnp.asarray(origins, jnp.float32)
  directions = inputs["ray_directions"] if directions is None else jnp.asarray(directions,
                                                                                jnp.float32)
  fn = jit(lambda p, e, o, d: edits.render_edit(model, p, encoded, sources, e, origins=o,
                                                directions=d))
  return fn(params, edit, origins, directions)


def _plain(mode, origins=None):
  model, inputs, params, sources, encoded = _setup(mode)
  origins = inputs["ray_origins"] if origins is None else jnp.asarray(origins, jnp.float32)
  return jit(lambda p, o: pictures.render_rays(model, p, encoded, sources=sources, ray_origins=o,
                                               ray_directions=inputs["ray_directions"]))(
                                                   params, origins)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_keeping_one_slot_is_the_per_slot_rendering(mode):
  model = _setup(mode)[0]
  out = _plain(mode)
  alone = pictures.render_each_slot(out, far=model.far, density_scale=model.density_scale)
  for k in range(K):
    kept = _render_edit(mode, edits.Edit.keep([k], K))
    # Removing every other slot is the same edit.
    removed = _render_edit(mode, edits.Edit.remove([j for j in range(K) if j != k], K))
    for r in (kept, removed):
      np.testing.assert_allclose(r.colour, alone.colour[..., k, :], rtol=1e-6, atol=1e-7)
      np.testing.assert_allclose(r.depth, alone.depth[..., k], rtol=1e-6, atol=1e-7)
      np.testing.assert_allclose(r.opacity, alone.opacity[..., k], rtol=1e-6, atol=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_removing_a_slot_takes_away_its_density_and_mass(mode):
  model = _setup(mode)[0]
  out = _plain(mode)
  k = 2
  r = _render_edit(mode, edits.Edit.remove([k], K))
  # NumPy reference: volume rendering of σ − σ_k with the samples' colour.
  sigma = np.asarray(out.slot_density, np.float64)
  ref = _numpy_render(sigma.sum(-1) - sigma[..., k], np.asarray(out.sample_colour, np.float64),
                      np.asarray(out.z, np.float64), far=model.far, scale=model.density_scale)
  np.testing.assert_allclose(r.colour, ref["colour"], rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(r.depth, ref["depth"], rtol=1e-5, atol=1e-6)
  # The removed slot owns nothing of the segmentation.
  np.testing.assert_array_equal(np.asarray(r.segmentation)[..., k], 0.0)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_moving_by_zero_is_the_plain_render(mode):
  out = _plain(mode)
  for k, background in ((0, None), (K - 1, None), (K - 1, 0)):  # (K − 1, 0): carrying slot 0
    r = _render_edit(mode, edits.Edit.moving(k, K, edits.RigidMove.make((0.0, 0.0, 0.0)),
                                             background=background))
    np.testing.assert_allclose(r.colour, out.coarse.colour, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r.depth, out.coarse.depth, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r.segmentation, out.coarse.segmentation, rtol=1e-5, atol=1e-6)


def _turn_z(angle):
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_a_moved_slot_alone_is_the_slot_seen_from_the_inversely_moved_camera(mode):
  """Slot k moved by T and kept alone renders what slot k alone renders along the rays T⁻¹ of the
  plain model: the same source views, the camera moved the other way."""
  model, inputs, *_ = _setup(mode)
  k = 1
  t, yaw, pivot = np.array([0.07, -0.05, 0.02]), 0.4, np.array([0.1, 0.2, 0.0])
  owner = np.full(K, edits.REMOVED, np.int32)
  owner[k] = edits.MOVED
  edit = edits.Edit(owner=jnp.asarray(owner),
                    move=edits.RigidMove.make(t, yaw=yaw, pivot=pivot), has_move=True)
  moved = _render_edit(mode, edit)
  # T⁻¹ written with a NumPy rotation matrix: x' = Rᵀ(x − pivot − t) + pivot, d' = Rᵀd.
  rot = _turn_z(yaw)
  o = np.asarray(inputs["ray_origins"], np.float64)
  d = np.asarray(inputs["ray_directions"], np.float64)
  ref = _render_edit(mode, edits.Edit.keep([k], K), origins=(o - pivot - t) @ rot + pivot,
                     directions=d @ rot)
  np.testing.assert_allclose(moved.colour, ref.colour, rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(moved.depth, ref.depth, rtol=1e-4, atol=1e-5)
  # And the move changed something: the test is not vacuous.
  still = _render_edit(mode, edits.Edit.keep([k], K))
  assert np.abs(np.asarray(still.opacity) - np.asarray(moved.opacity)).max() > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_swapping_slots_with_the_same_scene_or_all_slots_with_another(mode):
  model, inputs, params, sources, encoded = _setup(mode)
  # Scene 1 of the batch as the "other" scene, seen along scene 0's rays (both batch entries
  # rendered; batch entry b of the other scene is batch entry 1 − b of this one).
  other_sources = {k: v[::-1] for k, v in sources.items()}
  other_encoded = jax.tree.map(lambda x: x[::-1], encoded)
  run = jit(lambda p, owner, other: edits.render_swap(
      model, p, [(encoded, sources), other], owner, origins=inputs["ray_origins"],
      directions=inputs["ray_directions"]))
  plain = _plain(mode)
  same = run(params, jnp.ones(K, jnp.int32), (encoded, sources))
  np.testing.assert_allclose(same.colour, plain.coarse.colour, rtol=1e-5, atol=1e-6)
  swapped = run(params, jnp.ones(K, jnp.int32), (other_encoded, other_sources))
  ref = jit(lambda p: pictures.render_rays(model, p, other_encoded, sources=other_sources,
                                           ray_origins=inputs["ray_origins"],
                                           ray_directions=inputs["ray_directions"]))(params)
  np.testing.assert_allclose(swapped.colour, ref.coarse.colour, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(swapped.depth, ref.coarse.depth, rtol=1e-5, atol=1e-6)


def test_moving_a_slot_of_a_model_with_a_fine_pass_is_refused():
  model = tm.tiny(num_fine_samples=5)
  inputs = tm.make_inputs(2)
  with pytest.raises(ValueError, match="fine pass"):  # before any work: no parameters needed
    edits.render_edit(model, None, None, tm.sources(inputs),
                      edits.Edit.moving(0, K, edits.RigidMove.make((0.1, 0.0, 0.0))),
                      origins=inputs["ray_origins"], directions=inputs["ray_directions"])


def test_slot_indices_out_of_range_are_refused():
  for make in (lambda: edits.Edit.remove([K], K), lambda: edits.Edit.keep([-1], K),
               lambda: edits.Edit.moving(K + 3, K, edits.RigidMove.make((0.0, 0.0, 0.0)))):
    with pytest.raises(ValueError, match="out of range"):
      make()


# ---------------------------------------------------------------------------------------------
# A constructed field and a NumPy volume renderer


def _numpy_render(sigma, colour, z, *, far, scale):
  """docs/method.md §1.5 in NumPy float64: sigma [..., S], colour [..., S, 3], z [..., S]."""
  delta = np.concatenate([z[..., 1:] - z[..., :-1], np.zeros_like(z[..., :1])], axis=-1)
  alpha = 1.0 - np.exp(-sigma * delta * scale)
  trans = np.cumprod(np.concatenate([np.ones_like(alpha[..., :1]),
                                     1.0 - alpha[..., :-1] + 1e-10], axis=-1), axis=-1)
  w = alpha * trans
  return {"colour": np.einsum("...s,...sc->...c", w, colour),
          "depth": np.sum(w * z, -1) + (1.0 - w.sum(-1)) * far}


BLOB_CENTRE = np.array([0.1, -0.2, 0.15])
BLOB_AXES = np.array([0.25, 0.08, 0.12])  # anisotropic, so a turn shows


def _floor(x):  # slot 0: a slab of density around z = 0, colour from x alone
  return 30.0 * np.exp(-(x[..., 2] / 0.05) ** 2)


def _blob(x):  # slot 1: an ellipsoidal blob
  q = (x - BLOB_CENTRE) / BLOB_AXES
  return 60.0 * np.exp(-np.sum(q * q, -1))


def _colour(x):
  return 1.0 / (1.0 + np.exp(-3.0 * np.stack([x[..., 0], x[..., 1] - x[..., 2], x[..., 2]], -1)))


def _constructed_pass(num_samples=64, near=0.5, far=3.5):
  """render_pass of edits.edit_rays for the field above: 2 slots, per-point colour from both."""
  def render_pass(origins, directions, z):
    if z is None:
      z = jnp.broadcast_to(jnp.linspace(near, far, num_samples), origins.shape[:-1] +
                           (num_samples,))
    x = origins[..., None, :] + z[..., None] * directions[..., None, :]  # [..., S, 3]
    floor = 30.0 * jnp.exp(-(x[..., 2] / 0.05) ** 2)
    q = (x - BLOB_CENTRE) / BLOB_AXES
    blob = 60.0 * jnp.exp(-jnp.sum(q * q, -1))
    colour = jax.nn.sigmoid(3.0 * jnp.stack([x[..., 0], x[..., 1] - x[..., 2], x[..., 2]], -1))
    sigma = jnp.stack([floor, blob], -1)
    weights = jnp.concatenate([jnp.zeros_like(sigma[..., :1]), sigma / (sigma.sum(-1, keepdims=True)
                                                                      + 1e-9)], -1)
    return edits.SlotField(slot_density=sigma, colour=colour, weights=weights), z
  return render_pass


def _rays(seed, n=200, around=(0.0, 0.0, 0.0)):
  rng = np.random.default_rng(seed)
  origins = np.stack([np.full(n, 1.6), np.zeros(n), np.full(n, 1.2)], -1) + rng.normal(
      scale=0.05, size=(n, 3))
  targets = np.asarray(around) + rng.uniform(-0.4, 0.4, size=(n, 3)) * [1, 1, 0.3]
  d = targets - origins
  return origins, d / np.linalg.norm(d, axis=-1, keepdims=True)


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_moving_a_constructed_slot_shifts_it_exactly(yaw):
  """σ̃(x) = σ_floor(x) + σ_blob(T⁻¹x), c̃ their density-weighted colours, in NumPy."""
  origins, dirs = _rays(0)
  t, pivot = np.array([0.3, 0.15, 0.05]), np.array([-0.1, 0.2, 0.0])
  move = edits.RigidMove.make(t, yaw=yaw, pivot=pivot)
  edit = edits.Edit(owner=jnp.asarray([edits.PLAIN, edits.MOVED]), move=move, has_move=True)
  far, scale, s = 3.5, 25.0, 64
  out = edits.edit_rays(_constructed_pass(s, far=far), edit, origins=jnp.asarray(origins),
                        directions=jnp.asarray(dirs), far=far, density_scale=scale)
  z = np.broadcast_to(np.linspace(0.5, far, s), (len(origins), s))
  x = origins[:, None] + z[..., None] * dirs[:, None]
  inv = (x - pivot - t) @ _turn_z(yaw) + pivot  # Rᵀ(x − pivot − t) + pivot as row vectors
  sig_floor, sig_blob = _floor(x), _blob(inv)
  sigma = sig_floor + sig_blob
  colour = (sig_floor[..., None] * _colour(x) + sig_blob[..., None] * _colour(inv)) / np.maximum(
      sigma, 1e-300)[..., None]
  ref = _numpy_render(sigma, colour, z, far=far, scale=scale)
  np.testing.assert_allclose(out.colour, ref["colour"], rtol=1e-4, atol=1e-5)
  np.testing.assert_allclose(out.depth, ref["depth"], rtol=1e-4, atol=1e-5)


def test_a_single_slot_field_moved_by_t_is_the_field_seen_from_the_camera_moved_by_minus_t():
  origins, dirs = _rays(1)
  t = np.array([0.2, -0.25, 0.0])
  edit = edits.Edit(owner=jnp.asarray([edits.REMOVED, edits.MOVED]),
                    move=edits.RigidMove.make(t), has_move=True)
  keep_blob = edits.Edit(owner=jnp.asarray([edits.REMOVED, edits.PLAIN]),
                         move=edits.RigidMove.make((0.0, 0.0, 0.0)))
  kw = dict(far=3.5, density_scale=25.0)
  moved = edits.edit_rays(_constructed_pass(), edit, origins=jnp.asarray(origins),
                          directions=jnp.asarray(dirs), **kw)
  shifted = edits.edit_rays(_constructed_pass(), keep_blob, origins=jnp.asarray(origins - t),
                            directions=jnp.asarray(dirs), **kw)
  np.testing.assert_allclose(moved.colour, shifted.colour, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(moved.depth, shifted.depth, rtol=1e-5, atol=1e-6)
  assert float(np.asarray(moved.opacity).max()) > 0.5  # the rays do see the blob


def _membership_pass(centre):
  """A field whose W is a membership as the model's is: empty air belongs to slot 0 (the
  background: a floor at z = 0) as surely as the blob centred at `centre` belongs to slot 1."""
  def render_pass(origins, directions, z):
    if z is None:
      z = jnp.broadcast_to(jnp.linspace(0.5, 3.5, 96), origins.shape[:-1] + (96,))
    x = origins[..., None, :] + z[..., None] * directions[..., None, :]
    floor = 30.0 * jnp.exp(-(x[..., 2] / 0.05) ** 2)
    q = (x - jnp.asarray(centre, jnp.float32)) / BLOB_AXES
    inside = jnp.exp(-jnp.sum(q * q, -1))
    sigma = jnp.stack([floor, 60.0 * inside], -1)
    member = 1.0 - jnp.exp(-1000.0 * inside)  # ~1 wherever the blob has density to be seen
    weights = jnp.stack([jnp.zeros_like(inside), 1.0 - member, member], -1)
    colour = jnp.broadcast_to(jnp.asarray([0.5, 0.5, 0.5]), x.shape)
    return edits.SlotField(slot_density=sigma, colour=colour, weights=weights), z
  return render_pass


def test_a_moved_slot_owns_the_pixels_where_it_now_stands():
  """The moved blob's segmentation is that of a scene drawn with the blob at its new place, ray
  by ray wherever that scene's segmentation is clear (a margin of 0.2 between the two slots),
  although the plain pass gives the empty air there to the background slot."""
  origins, dirs = _rays(2, n=400)
  t = np.array([0.25, 0.3, 0.0])
  # Raised off the floor, so that the floor under it is not the blob's: that would be another
  # question (what is left where a slot stood, docs/editing.md §5).
  centre = BLOB_CENTRE + np.array([0.0, 0.0, 0.3])
  kw = dict(origins=jnp.asarray(origins), directions=jnp.asarray(dirs), far=3.5,
            density_scale=25.0)
  edit = edits.Edit(owner=jnp.asarray([edits.PLAIN, edits.MOVED]),
                    move=edits.RigidMove.make(t), has_move=True)
  moved = edits.edit_rays(_membership_pass(centre), edit, **kw)
  truth = edits.edit_rays(_membership_pass(centre + t), edits.Edit.identity(2), **kw)
  seg, ref = np.asarray(moved.segmentation), np.asarray(truth.segmentation)
  clear = np.abs(ref[:, 1] - ref[:, 0]) > 0.2
  on_blob = clear & (ref[:, 1] > ref[:, 0])
  assert on_blob.sum() >= 20 and (clear & ~on_blob).sum() >= 20  # both kinds of ray are tested
  np.testing.assert_array_equal(seg[clear].argmax(-1), ref[clear].argmax(-1))


def _samples_around(origins, directions, z, centre, num_samples=128):
  """(points [..., S, 3], depths z [..., S], squared horizontal distance of each point from
  `centre`) for a constructed render_pass: z is the pass's own grid when None."""
  if z is None:
    z = jnp.broadcast_to(jnp.linspace(0.5, 3.5, num_samples), origins.shape[:-1] + (num_samples,))
  x = origins[..., None, :] + z[..., None] * directions[..., None, :]
  c = jnp.asarray(centre, jnp.float32)
  return x, z, (x[..., 0] - c[0]) ** 2 + (x[..., 1] - c[1]) ** 2


def _haze_pass(centre, haze=0.1, clearing=0.5, top=0.5):
  """The background slot as the model renders it: a floor at z = 0 under a haze through the slab
  0 ≤ z ≤ `top`, cleared in a vertical cylinder of radius `clearing` around the blob centred at
  `centre` (slot 1, whose W is a membership as in `_membership_pass`)."""
  def render_pass(origins, directions, z):
    x, z, r2 = _samples_around(origins, directions, z, centre)
    c = jnp.asarray(centre, jnp.float32)
    in_slab = (x[..., 2] >= 0.0) & (x[..., 2] <= top)
    background = 30.0 * jnp.exp(-(x[..., 2] / 0.05) ** 2) + haze * in_slab * (
        1.0 - jnp.exp(-(r2 / clearing ** 2) ** 4))
    q = (x - c) / BLOB_AXES
    inside = jnp.exp(-jnp.sum(q * q, -1))
    sigma = jnp.stack([background, 60.0 * inside], -1)
    member = 1.0 - jnp.exp(-1000.0 * inside)
    weights = jnp.stack([jnp.zeros_like(inside), 1.0 - member, member], -1)
    colour = jnp.broadcast_to(jnp.asarray([0.5, 0.5, 0.5]), x.shape)
    return edits.SlotField(slot_density=sigma, colour=colour, weights=weights), z
  return render_pass


def test_a_moved_slot_carries_the_background_that_cleared_the_haze_in_front_of_it():
  """A background slot that renders the floor as a haze, cleared only around the object (as the
  trained models do, docs/editing.md §7): without carrying, the haze at the blob's new place
  takes its pixels; carrying the background along the rays the blob covers gives the
  segmentation of the scene drawn with the blob at its new place, wherever that is clear."""
  t = np.array([-0.7, 0.75, 0.0])  # out of the clearing around where it stood
  centre = BLOB_CENTRE  # on the floor, under the haze
  origins, dirs = _rays(3, n=400, around=centre + t)
  kw = dict(origins=jnp.asarray(origins), directions=jnp.asarray(dirs), far=3.5,
            density_scale=25.0)
  truth = edits.edit_rays(_haze_pass(centre + t), edits.Edit.identity(2), **kw)
  ref = np.asarray(truth.segmentation)
  clear = np.abs(ref[:, 1] - ref[:, 0]) > 0.2
  on_blob = clear & (ref[:, 1] > ref[:, 0])
  assert on_blob.sum() >= 20 and (clear & ~on_blob).sum() >= 20
  move = edits.RigidMove.make(t)
  stay = edits.edit_rays(_haze_pass(centre), edits.Edit.moving(1, 2, move), **kw)
  lost = np.asarray(stay.segmentation)[on_blob].argmax(-1) != 1
  assert lost.mean() > 0.5  # the failure carrying is for
  carried = edits.edit_rays(_haze_pass(centre), edits.Edit.moving(1, 2, move, background=0), **kw)
  np.testing.assert_array_equal(np.asarray(carried.segmentation)[clear].argmax(-1),
                                ref[clear].argmax(-1))


def _numpy_segmentation(sigma, weights, z, scale=25.0):
  """docs/method.md §1.5 in NumPy float64: the segmentation over the real slots of a field with
  slot densities sigma [..., S, K] and point-slot weights [..., S, K+1]."""
  delta = np.concatenate([z[..., 1:] - z[..., :-1], np.zeros_like(z[..., :1])], axis=-1)
  alpha = 1.0 - np.exp(-sigma.sum(-1) * delta * scale)
  trans = np.cumprod(np.concatenate([np.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1]], -1),
                     axis=-1)
  mass = np.einsum("...s,...sk->...k", alpha * trans, weights[..., 1:])
  return mass / mass.sum(-1, keepdims=True)


def test_carry_fraction_of_each_rule_against_numpy():
  """β per ray from the moved pass: the moved slot's opacity alone, its share of the moved pass's
  segmentation, and 1 where that share is the largest (two slots move here, so it is their sum
  against the largest other slot)."""
  rng = np.random.default_rng(4)
  k, s, n = 4, 12, 64
  sigma = rng.uniform(0.0, 0.3, size=(n, s, k)) * rng.uniform(0.0, 1.0, size=(n, 1, k)) ** 3
  logits = rng.normal(size=(n, s, k + 1)) * 2.0
  weights = np.exp(logits) / np.exp(logits).sum(-1, keepdims=True)
  z = np.sort(rng.uniform(0.5, 3.0, size=(n, s)), axis=-1)
  owner = np.array([edits.PLAIN, edits.MOVED, edits.MOVED, edits.REMOVED])
  field = edits.SlotField(slot_density=jnp.asarray(sigma, jnp.float32),
                          colour=jnp.zeros((n, s, 3)), weights=jnp.asarray(weights, jnp.float32))
  beta = {rule: np.asarray(edits.carry_fraction(jnp.asarray(owner), field,
                                                z=jnp.asarray(z, jnp.float32),
                                                density_scale=25.0, rule=rule))
          for rule in edits.CARRY_RULES}
  delta = np.concatenate([np.diff(z, axis=-1), np.zeros((n, 1))], -1)
  np.testing.assert_allclose(beta["opacity"],
                             1.0 - np.exp(-25.0 * np.sum(sigma[..., 1:3].sum(-1) * delta, -1)),
                             rtol=1e-5, atol=1e-6)
  seg = _numpy_segmentation(sigma, weights, z)
  share = seg[:, 1:3].sum(-1)
  np.testing.assert_allclose(beta["share"], share, rtol=1e-4, atol=1e-5)
  others = np.maximum(seg[:, 0], seg[:, 3])
  wins = share > others
  assert 10 <= wins.sum() <= n - 10  # both outcomes are tested
  decided = np.abs(share - others) > 1e-4
  np.testing.assert_array_equal(beta["winner"][decided], wins[decided].astype(np.float32))
  with pytest.raises(ValueError, match="carry rule"):
    edits.Edit.moving(1, k, edits.RigidMove.make((0.0, 0.0, 0.0)), background=0,
                      carry_rule="nearest")


def test_carried_shares_split_the_background_slot_by_beta():
  """The background slot's share is 1 − β from the plain pass and β from the moved pass; every
  other slot keeps its one pass."""
  beta = jnp.asarray([0.0, 0.3, 1.0])
  owner = jnp.asarray([edits.PLAIN, edits.MOVED, edits.PLAIN, edits.REMOVED])
  plain, moved = edits.carried_shares(owner, 0, beta)
  np.testing.assert_allclose(np.asarray(plain)[:, 0, 0], [1.0, 0.7, 0.0], atol=1e-7)
  np.testing.assert_allclose(np.asarray(moved)[:, 0, 0], [0.0, 0.3, 1.0], atol=1e-7)
  np.testing.assert_array_equal(np.asarray(plain)[:, 0, 1:], np.tile([0.0, 1.0, 0.0], (3, 1)))
  np.testing.assert_array_equal(np.asarray(moved)[:, 0, 1:], np.tile([1.0, 0.0, 0.0], (3, 1)))


FLOOR_RGB = np.array([0.6, 0.5, 0.4])


def _thin_floor_pass(centre, blob_rgb=(0.1, 0.2, 0.9), blob_density=60.0):
  """An opaque one-colour floor (slot 0) that is thin under the blob (slot 1) centred at
  `centre`, as a trained background slot is where the source view saw an object."""
  def render_pass(origins, directions, z):
    x, z, r2 = _samples_around(origins, directions, z, centre)
    c = jnp.asarray(centre, jnp.float32)
    thin = 1.0 - 0.999 * jnp.exp(-(r2 / 0.6 ** 2) ** 4)
    floor = 40.0 * jnp.exp(-(x[..., 2] / 0.05) ** 2) * thin
    q = (x - c) / np.array([0.3, 0.3, 0.12])  # rounder than BLOB_AXES, so more rays hit it
    blob = blob_density * jnp.exp(-jnp.sum(q * q, -1))
    sigma = jnp.stack([floor, blob], -1)
    share = sigma / (sigma.sum(-1, keepdims=True) + 1e-9)
    # One colour per sample, as the model's: the floor's up to z = 0.3 (beyond its tail), the
    # blob's above.
    colour = jnp.where(x[..., 2:] < 0.3, jnp.asarray(FLOOR_RGB, jnp.float32),
                       jnp.asarray(blob_rgb, jnp.float32))
    weights = jnp.concatenate([jnp.zeros_like(sigma[..., :1]), share], -1)
    return edits.SlotField(slot_density=sigma, colour=colour, weights=weights), z
  return render_pass


def test_filling_what_a_removal_uncovers_gives_back_the_opaque_floor():
  """Removing the blob leaves the thin floor under it, which renders dark (no background colour,
  docs/method.md §1.5); filled with the background slot's own colour it renders the floor as the
  scene drawn without the blob and with its whole floor does, on every ray the scene rendered
  opaque (where the thin floor showed beside the blob the scene was dark before the edit too, and
  the fill adds nothing)."""
  # Raised off the floor, so that no floor sample has the blob's colour: what the fill gives
  # back is then the floor's colour alone (a trained model's floor under an object carries some
  # of the object's colour, docs/editing.md §5).
  centre = BLOB_CENTRE + np.array([0.0, 0.0, 0.3])
  origins, dirs = _rays(5, n=800, around=centre)
  kw = dict(origins=jnp.asarray(origins), directions=jnp.asarray(dirs), far=3.5,
            density_scale=25.0)
  opaque = np.asarray(edits.edit_rays(_thin_floor_pass(centre), edits.Edit.identity(2),
                                      **kw).opacity) > 0.999
  truth = np.full((int(opaque.sum()), 3), FLOOR_RGB)  # the whole floor is opaque
  hole = np.asarray(edits.edit_rays(_thin_floor_pass(centre), edits.Edit.remove([1], 2),
                                    **kw).colour)[opaque]
  dark = np.abs(hole - truth).max(-1) > 0.1
  assert dark.sum() >= 20  # the rays that see the thin floor where the blob stood
  filled = edits.edit_rays(_thin_floor_pass(centre), edits.Edit.remove([1], 2).filling(0), **kw)
  np.testing.assert_allclose(np.asarray(filled.colour)[opaque], truth, atol=1e-4)
  np.testing.assert_allclose(np.asarray(filled.segmentation)[opaque, 0], 1.0, atol=1e-5)


def test_filling_changes_nothing_an_edit_does_not_uncover():
  origins, dirs = _rays(6, n=200)
  kw = dict(origins=jnp.asarray(origins), directions=jnp.asarray(dirs), far=3.5,
            density_scale=25.0)
  plain = edits.edit_rays(_thin_floor_pass(BLOB_CENTRE), edits.Edit.identity(2), **kw)
  for edit in (edits.Edit.identity(2).filling(0),
               edits.Edit.moving(1, 2, edits.RigidMove.make((0.0, 0.0, 0.0)),
                                 background=0).filling(0)):
    r = edits.edit_rays(_thin_floor_pass(BLOB_CENTRE), edit, **kw)
    for field in ("colour", "depth", "opacity", "segmentation"):
      np.testing.assert_allclose(getattr(r, field), getattr(plain, field), rtol=1e-5, atol=1e-6)
  # Removing the background slot itself leaves nothing to fill with.
  assert not edits.Edit.remove([0], 2).filling(0).fill


def test_a_carried_translucent_object_is_not_filled_over():
  """A translucent blob over the floor that is thin under it, moved with the background carried
  and what the edit uncovers filled: on the rays the move carries, the unedited scene is the one
  it carries (the blob where it stood), so nothing there counts as uncovered and the blob keeps
  its pixels, as in the scene drawn with the blob at its new place. Measured against the opaque
  floor at the new place instead, the blob's own translucency reads as uncovered and the fill
  gives most of its pixels to the floor."""
  centre = BLOB_CENTRE
  t = np.array([-0.9, 0.8, 0.0])
  faint = dict(blob_density=0.1)
  origins, dirs = _rays(8, n=600, around=centre + t)
  kw = dict(origins=jnp.asarray(origins), directions=jnp.asarray(dirs), far=3.5,
            density_scale=25.0)
  truth = edits.edit_rays(_thin_floor_pass(centre + t, **faint), edits.Edit.identity(2), **kw)
  ref = np.asarray(truth.segmentation)
  on_blob = ref[:, 1] > ref[:, 0] + 0.2
  assert on_blob.sum() >= 20 and np.median(np.asarray(truth.opacity)[on_blob]) < 0.9
  edit = edits.Edit.moving(1, 2, edits.RigidMove.make(t), background=0).filling(0)
  moved = edits.edit_rays(_thin_floor_pass(centre, **faint), edit, **kw)
  np.testing.assert_array_equal(np.asarray(moved.segmentation)[on_blob].argmax(-1), 1)
  # Against the plain pass's opaque floor at the new place, the blob's translucency would read as
  # uncovered on most of its rays.
  plain = edits.edit_rays(_thin_floor_pass(centre, **faint), edits.Edit.identity(2), **kw)
  assert np.median(np.asarray(plain.opacity)[on_blob] - np.asarray(moved.opacity)[on_blob]) > 0.2


# ---------------------------------------------------------------------------------------------
# World space → the model's frame


def test_world_translation_moves_points_by_t_relative_to_every_camera():
  """data.frame = "source_azimuth" and the 1/7 scale: a point p and p + t of the world, seen from
  each camera, are the model-frame points q and q + t_model seen from the same camera."""
  rng = np.random.default_rng(0)
  scale = 1.0 / 7.0
  eyes = [12.4 * np.array([np.cos(a) * np.cos(0.7), np.sin(a) * np.cos(0.7), np.sin(0.7)])
          for a in rng.uniform(0, 2 * np.pi, size=4)]
  world = np.stack([look_at(e, np.zeros(3)) for e in eyes])
  model_frame = cameras.source_azimuth_frame(cameras.scale_translation(world, scale),
                                             source_idx=0)
  rot, shift = edits.frame_map(world_cam_to_world=world, model_cam_to_world=model_frame,
                               scene_scale=scale)
  p, t = np.array([1.0, -2.0, 0.35]), np.array([0.8, 1.1, 0.0])
  t_model = edits.world_translation(t, rotation=rot, scene_scale=scale)
  for w, m in zip(world, model_frame):
    in_camera = lambda pose, x: (x - pose[:3, 3]) @ pose[:3, :3]  # camera coordinates
    q = in_camera(m, rot @ (scale * p) + shift)
    np.testing.assert_allclose(q, scale * in_camera(w, p), atol=1e-9)
    np.testing.assert_allclose(in_camera(m, rot @ (scale * p) + shift + t_model),
                               scale * in_camera(w, p + t), atol=1e-9)
  # In the world frame the map is the scale alone.
  rot, shift = edits.frame_map(world_cam_to_world=world,
                               model_cam_to_world=cameras.scale_translation(world, scale),
                               scene_scale=scale)
  np.testing.assert_allclose(rot, np.eye(3), atol=1e-12)
  np.testing.assert_allclose(shift, 0.0, atol=1e-12)
  # Cameras that no one map relates are refused.
  bad = model_frame.copy()
  bad[2, :3, 3] += 0.1
  with pytest.raises(ValueError, match="one rotation"):
    edits.frame_map(world_cam_to_world=world, model_cam_to_world=bad, scene_scale=scale)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_deleting_a_slot_is_the_render_of_the_slot_set_without_it(mode):
  model, inputs, params, sources, encoded = _setup(mode)
  for k in (0, K - 1):
    r = _render_edit(mode, edits.Edit.delete_slot(k, K))
    # Reference: the model decoding the slot set that NumPy cut slot k out of.
    cut = encoded.replace(slots=jnp.asarray(np.delete(np.asarray(encoded.slots), k, axis=1)))
    ref = jit(lambda p: pictures.render_rays(model, p, cut, sources=sources,
                                             ray_origins=inputs["ray_origins"],
                                             ray_directions=inputs["ray_directions"]))(params)
    np.testing.assert_allclose(r.colour, ref.coarse.colour, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r.depth, ref.coarse.depth, rtol=1e-5, atol=1e-6)
    seg = np.asarray(r.segmentation)
    np.testing.assert_array_equal(seg[..., k], 0.0)
    np.testing.assert_allclose(np.delete(seg, k, axis=-1), ref.coarse.segmentation, rtol=1e-5,
                               atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("mode", MODES)
def test_a_deleted_slot_leaves_no_trace_of_its_content(mode):
  model, inputs, params, sources, encoded = _setup(mode)
  k = 1
  other = encoded.replace(slots=encoded.slots.at[:, k].set(-3.0 * encoded.slots[:, k] + 1.0))
  run = lambda e: jit(lambda p: edits.render_edit(
      model, p, e, sources, edits.Edit.delete_slot(k, K), origins=inputs["ray_origins"],
      directions=inputs["ray_directions"]))(params)
  a, b = run(encoded), run(other)
  np.testing.assert_allclose(a.colour, b.colour, rtol=1e-6, atol=1e-7)
  # Whereas zeroing its density keeps what the slot did to the others' weights.
  zeroed = lambda e: jit(lambda p: edits.render_edit(
      model, p, e, sources, edits.Edit.remove([k], K), origins=inputs["ray_origins"],
      directions=inputs["ray_directions"]))(params)
  assert not np.allclose(zeroed(encoded).colour, zeroed(other).colour, rtol=1e-6, atol=1e-7)
