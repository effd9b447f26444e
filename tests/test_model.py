"""Tests for the composed SlotLifter model (docs/method.md §1): shapes under jit, wiring, counts.

The model's switches and options, and which of them a run may change, are in test_model_options.py."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import tiny_model as tm
from tiny_model import B, H, W, R, S, K, D, jit

from slotlifter_jax import defaults
from slotlifter_jax import model as model_lib

# ---------------------------------------------------------------------------------------------
# Parameter counts against the official PyTorch model, counted from its layer list.


def _official_counts(*, d, k, c=64, ds=256, num_views=1, blocks=(3, 4, 6), widths=(64, 128, 256)):
  """Parameters of the official SlotLifter modules (model/encoder.py, slot_attn.py, transformer.py,
  nerf.py, renderer.py at commit 86b5f68), written out layer by layer."""
  conv = lambda cin, cout, ksize, bias: cin * cout * ksize * ksize + (cout if bias else 0)
  norm = lambda ch: 2 * ch  # InstanceNorm / LayerNorm affine
  linear = lambda cin, cout, bias=True: cin * cout + (cout if bias else 0)

  enc = conv(9, 64, 7, False) + norm(64)
  inplanes = 64
  for planes, n in zip(widths, blocks):
    enc += conv(inplanes, planes, 3, False) + norm(planes) + conv(planes, planes, 3, False)
    enc += norm(planes) + conv(inplanes, planes, 1, False) + norm(planes)  # downsample
    enc += (n - 1) * (2 * conv(planes, planes, 3, False) + 2 * norm(planes))
    inplanes = planes
  enc += conv(256, 128, 3, True) + norm(128) + conv(256, 128, 3, True) + norm(128)
  enc += conv(128, 64, 3, True) + norm(64) + conv(128, d, 3, True) + norm(d)
  enc += conv(d, d, 1, True)

  slot = k * ds + norm(d) + 2 * norm(ds) + linear(ds, ds, False) + 2 * linear(d, ds, False)
  slot += 2 * 3 * ds * ds + 6 * ds  # torch.nn.GRUCell: weight_ih, weight_hh, bias_ih, bias_hh
  slot += linear(ds, 4 * ds) + linear(4 * ds, ds)

  block = norm(c) + 2 * linear(c, c) + 2 * linear(ds, c)  # cross-attention
  block += norm(c) + linear(c, 4 * c) + linear(4 * c, c)  # FFN
  block += norm(c) + 3 * linear(c, c // 4) + linear(c // 4, c)  # self-attention
  block += c * c * 3 + c  # Conv1d
  alloc = 4 * block + norm(c) + ds + linear(c, c) + linear(ds, c) + linear(ds, c) + 1

  lift_in = (d + 3) * (2 if num_views > 1 else 1)
  lift_colour = linear(lift_in, c) + linear(c, 64) + 3 * linear(64, 64) + linear(64, 3)
  pos = linear(120, c)
  return dict(encoder=enc, slot_attention=slot, allocation=alloc, lift_colour=lift_colour,
              pos=pos)


def test_official_count_inventory_totals_the_published_figure():
  assert sum(_official_counts(d=64, k=8).values()) == 10_389_124


def test_parameter_counts_match_official():
  config = defaults.base_config()  # synthetic-set defaults: D = 64, K = 8, V = 1
  model = model_lib.build_model(config)
  size = 128
  spec = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)
  inputs = dict(source_images=spec(1, 1, size, size, 3), source_cam_to_world=spec(1, 1, 4, 4),
                source_intrinsics=spec(1, 1, 3, 3), ray_origins=spec(1, 5, 3),
                ray_directions=spec(1, 5, 3))
  params = jax.eval_shape(
      lambda kw: model.init(jax.random.key(0), **kw, train=False), inputs)["params"]
  count = lambda *names: sum(x.size for n in names for x in jax.tree.leaves(params[n]))
  ours = dict(encoder=count("encoder"), slot_attention=count("slot_attention"),
              allocation=count("allocation"), lift_colour=count("lift_proj", "colour_mlp"),
              pos=count("pos_proj"))
  official = _official_counts(d=64, k=8)
  total = sum(x.size for x in jax.tree.leaves(params))
  for name in official:
    print(f"{name:>15}: ours {ours[name]:>10,}  official {official[name]:>10,}")
  print(f"{'total':>15}: ours {total:>10,}  official {sum(official.values()):>10,}")
  assert total == sum(ours.values())  # no parameters outside the named parts
  for name in official:
    assert abs(ours[name] - official[name]) <= 0.01 * official[name], name
  # Exact, except the slot GRU (flax GRUCell's layout), which folds b_hr, b_hz into b_ir, b_iz:
  # 2·Ds = 512 fewer.
  expected = dict(official, slot_attention=official["slot_attention"] - 512)
  assert ours == expected
  assert abs(total - 10_389_124) <= 0.01 * 10_389_124


# ---------------------------------------------------------------------------------------------
# The model under jit: tiny_model's two configurations (V = 1 and V = 2, with and without a fine
# pass), each initialised once.


def _train_forward(model, inputs, params, keep_ratio, rngs):
  out = model.apply({"params": params}, **inputs, slot_noise_sigma=0.5, keep_ratio=keep_ratio,
                    locality=True, train=True, rngs=rngs)
  loss = jnp.mean((out.render.coarse.colour - 0.5) ** 2)
  if out.render.fine is not None:  # as in training: the mean of the coarse and fine losses
    loss = 0.5 * (loss + jnp.mean((out.render.fine.colour - 0.5) ** 2))
  return loss, out


def _check_train_output(out, *, num_views, num_fine):
  s_total = S + num_fine
  chex.assert_shape(out.render.coarse.colour, (B, R, 3))
  chex.assert_shape(out.render.coarse.segmentation, (B, R, K))
  chex.assert_shape(out.render.point_slot_weights, (B, R, s_total, K + 1))
  chex.assert_shape([out.render.z, out.render.density], (B, R, s_total))
  chex.assert_shape(out.encoded.features, (B, num_views, 5, 7, D))  # ceil(20/4) × ceil(28/4)
  chex.assert_shape(out.encoded.slots, (B, K, 24))
  chex.assert_shape(out.encoded.slot_attn, (B, K, num_views * 5 * 7))
  assert (out.render.fine is None) == (num_fine == 0)
  if num_fine:
    chex.assert_shape(out.render.fine.colour, (B, R, 3))
  assert np.all(np.diff(np.asarray(out.render.z), axis=-1) >= 0)
  chex.assert_tree_all_finite(out)


def test_train_forward_v1_under_jit():
  model, inputs, variables = tm.setup("v1")
  forward = jit(lambda rngs: _train_forward(model, inputs, variables["params"], 0.7, rngs))
  loss, out = forward(tm.rngs(1))
  assert np.isfinite(float(loss))
  _check_train_output(out, num_views=1, num_fine=0)
  assert variables["params"]["lift_proj"]["kernel"].shape == (D + 3, 16)  # V = 1: D + 3
  # Training is random (jitter, slot noise, dropout, masking) but a function of the rng streams.
  chex.assert_trees_all_equal(forward(tm.rngs(1)), (loss, out))
  _, other = forward(tm.rngs(2))
  assert np.abs(np.asarray(other.render.coarse.colour - out.render.coarse.colour)).max() > 1e-6
  assert np.abs(np.asarray(other.render.z - out.render.z)).max() > 1e-6


def test_train_gradients_v2_fine_under_jit():
  model, inputs, variables = tm.setup("v2_fine")
  params = variables["params"]
  loss_and_grad = jit(jax.value_and_grad(
      lambda p, keep: _train_forward(model, inputs, p, keep, tm.rngs(1)), has_aux=True))
  (loss, out), grads = loss_and_grad(params, 0.7)
  assert np.isfinite(float(loss))
  _check_train_output(out, num_views=2, num_fine=5)
  assert params["lift_proj"]["kernel"].shape == (2 * (D + 3), 16)  # V > 1: mean ⊕ variance
  assert {"allocation_fine", "colour_mlp_fine", "lift_proj_fine"} <= set(grads)
  chex.assert_tree_all_finite(grads)
  largest = lambda tree: max(float(jnp.abs(x).max()) for x in jax.tree.leaves(tree))
  # Every part of the model receives gradient.
  assert all(largest(sub) > 0 for sub in grads.values()), {n: largest(g) for n, g in grads.items()}
  # Random masking with keep ratio 0 cuts every ray off the lifted features, in the coarse and the
  # fine pass: both lifting Linears get exactly zero gradient, all other parts still learn.
  _, grads0 = loss_and_grad(params, 0.0)
  for name, sub in grads0.items():
    assert (largest(sub) == 0.0) == name.startswith("lift_proj"), name


def test_eval_chunks_locality_and_encode():
  """V = 1: `encode` once, then `render_rays` in chunks equals rendering all rays at once."""
  model, inputs, variables = tm.setup("v1")
  sources = tm.sources(inputs)

  @jit
  def render(encoded, origins, directions, locality):
    return model.apply(variables, encoded, **sources, ray_origins=origins,
                       ray_directions=directions, locality=locality, train=False,
                       method=model.render_rays)

  encoded = jit(lambda: model.apply(variables, **sources, train=False,
                                        method=model.encode))()
  full = render(encoded, inputs["ray_origins"], inputs["ray_directions"], False)
  # Two overlapping chunks of 6 rays (one compilation) cover all 11.
  parts = [render(encoded, inputs["ray_origins"][:, sl], inputs["ray_directions"][:, sl], False)
           for sl in (slice(0, 6), slice(5, 11))]
  glued = jax.tree.map(lambda a, b: jnp.concatenate([a, b[:, 1:]], axis=1), *parts)
  chex.assert_trees_all_close(glued, full, atol=1e-5)

  np.testing.assert_allclose(encoded.slot_attn.sum(axis=1), 1.0, atol=1e-5)
  opacity = np.asarray(full.coarse.opacity)
  seg_sum = np.asarray(full.coarse.segmentation.sum(-1))
  np.testing.assert_allclose(seg_sum[opacity > 1e-3], 1.0, atol=1e-4)
  colour = np.asarray(full.coarse.colour)
  assert np.all(colour >= 0) and np.all(colour <= 1 + 1e-6)
  np.testing.assert_allclose(full.z[0, 0], np.linspace(1.0, 3.0, S, endpoint=False), atol=1e-6)

  # The locality constraint reaches the mapping: outside the 0.64 box only slots 0 and 1 remain.
  on = render(encoded, inputs["ray_origins"], inputs["ray_directions"], True)
  z = np.asarray(on.z)
  points = (np.asarray(inputs["ray_origins"])[:, :, None]
            + np.asarray(inputs["ray_directions"])[:, :, None] * z[..., None])  # [B, R, S, 3]
  outside = np.any(np.abs(points) > 0.64, axis=-1)
  assert outside.any() and (~outside).any()
  w_on, w_off = np.asarray(on.point_slot_weights), np.asarray(full.point_slot_weights)
  assert np.all(w_on[outside][:, 2:] < 1e-30)
  np.testing.assert_allclose(w_on[outside][:, :2].sum(-1), 1.0, atol=1e-5)
  np.testing.assert_allclose(w_on[~outside], w_off[~outside], atol=1e-6)
  assert w_off[outside][:, 2:].max() > 1e-3


def test_eval_with_fine_pass():
  """V = 2 with a fine pass at evaluation: deterministic, the fine depths hold the coarse grid."""
  model, inputs, variables = tm.setup("v2_fine")
  run = jit(lambda: model.apply(variables, **inputs, train=False))
  out, again = run(), run()
  chex.assert_trees_all_equal(out, again)
  chex.assert_shape(out.render.fine.colour, (B, R, 3))
  chex.assert_shape(out.render.z, (B, R, S + 5))
  coarse_z = np.linspace(1.0, 3.0, S, endpoint=False)
  for z in np.asarray(out.render.z).reshape(-1, S + 5):
    assert np.all(np.diff(z) >= 0)
    assert np.all(np.min(np.abs(z[:, None] - coarse_z[None]), axis=0) < 1e-5)


def test_encoder_input_channels():
  inputs = tm.make_inputs(2, seed=5)
  x = np.asarray(model_lib.encoder_input(images=inputs["source_images"],
                                         cam_to_world=inputs["source_cam_to_world"],
                                         intrinsics=inputs["source_intrinsics"]))
  assert x.shape == (B, 2, H, W, 9)
  np.testing.assert_array_equal(x[..., :3], inputs["source_images"])
  centres = np.asarray(inputs["source_cam_to_world"])[:, :, None, None, :3, 3]
  np.testing.assert_allclose(x[..., 3:6], np.broadcast_to(centres, x[..., 3:6].shape), atol=1e-6)
  np.testing.assert_allclose(np.linalg.norm(x[..., 6:], axis=-1), 1.0, atol=1e-5)
  # A pixel's direction, projected back with K and the pose, lands on that pixel.
  cam = np.asarray(inputs["source_cam_to_world"], np.float64)
  k = np.asarray(inputs["source_intrinsics"], np.float64)
  d_cam = np.einsum("bvji,bvhwj->bvhwi", cam[:, :, :3, :3], x[..., 6:].astype(np.float64))
  pix = np.einsum("bvij,bvhwj->bvhwi", k, d_cam)
  pix = pix[..., :2] / pix[..., 2:]
  vv, uu = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
  np.testing.assert_allclose(pix[..., 0], np.broadcast_to(uu, pix.shape[:-1]), atol=1e-3)
  np.testing.assert_allclose(pix[..., 1], np.broadcast_to(vv, pix.shape[:-1]), atol=1e-3)


def test_build_model_and_head_prefixes():
  config = defaults.base_config()
  config.render.num_fine_samples = 64
  model = model_lib.build_model(config)
  assert model.num_slots == config.model.num_slots and model.num_fine_samples == 64
  assert all(not hasattr(v, "to_dict") for v in vars(model).values())  # plain Python fields
  spec = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)
  inputs = dict(source_images=spec(1, 2, 32, 32, 3), source_cam_to_world=spec(1, 2, 4, 4),
                source_intrinsics=spec(1, 2, 3, 3), ray_origins=spec(1, 3, 3),
                ray_directions=spec(1, 3, 3))
  params = jax.eval_shape(
      lambda kw: model.init(jax.random.key(0), **kw, train=False), inputs)["params"]
  heads = {n for n in params if n.startswith(model_lib.HEAD_MODULE_PREFIXES)}
  assert heads == {"colour_mlp", "colour_mlp_fine", "lift_proj", "lift_proj_fine", "pos_proj"}
  assert params["lift_proj"]["kernel"].shape == (2 * (64 + 3), 64)
  assert params["pos_proj"]["kernel"].shape == (120, 64)
