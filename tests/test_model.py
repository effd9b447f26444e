"""Tests for the composed SlotLifter model (docs/method.md §1): shapes under jit, wiring, counts."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from random_cameras import random_cameras

from slotlifter_jax import defaults
from slotlifter_jax import model as model_lib

B, H, W, R, S, K = 2, 20, 28, 11, 7, 5
D = 13
STREAMS = ("dropout", "noise", "sample", "mask")
# The model is indifferent to the key implementation; 'rbg' keys compile several times faster than
# threefry on XLA:CPU (initialising the tiny model: ~7 s instead of ~32 s), which keeps this file fast.
KEY_IMPL = "rbg"
# Compilation dominates this file's run time and the programs are tiny: skip XLA's backend
# optimisations (about half the compile time) for the jitted calls made here.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


def _tiny(**kw):
  args = dict(feature_dim=D, encoder_stem_width=8, encoder_widths=(8, 12, 16),
              encoder_blocks=(1, 1, 1), num_slots=K, slot_dim=24, slot_mlp_dim=32, point_dim=16,
              num_blocks=2, ffn_dim=24, self_attn_dim=8, colour_hidden=16, num_samples=S,
              near=1.0, far=3.0)
  args.update(kw)
  return model_lib.SlotLifter(**args)


def _inputs(num_views, seed=0, num_rays=R):
  """Source views around the origin and rays from another camera through points near the origin."""
  rng = np.random.default_rng(seed)
  cams, ks = random_cameras(rng, B * (num_views + 1), H, W)
  cams = cams.reshape(B, num_views + 1, 4, 4)
  ks = ks.reshape(B, num_views + 1, 3, 3)
  origins = np.broadcast_to(cams[:, -1, None, :3, 3], (B, num_rays, 3))
  targets = rng.uniform(-0.5, 0.5, size=(B, num_rays, 3))
  dirs = targets - origins
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
  f32 = lambda x: jnp.asarray(x, jnp.float32)
  return dict(source_images=f32(rng.uniform(0, 1, size=(B, num_views, H, W, 3))),
              source_cam_to_world=f32(cams[:, :num_views]),
              source_intrinsics=f32(ks[:, :num_views]),
              ray_origins=f32(origins), ray_directions=f32(dirs))


def _key(seed):
  return jax.random.key(seed, impl=KEY_IMPL)


def _rngs(seed):
  return {s: jax.random.fold_in(_key(seed), i) for i, s in enumerate(STREAMS)}


def _init(model, inputs):
  return jit(lambda: model.init(_key(0), **inputs, train=False))()


def _sources(inputs):
  return {k: v for k, v in inputs.items() if k.startswith("source_")}


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
# The model under jit. Two tiny configurations cover V = 1 and V = 2, with and without a fine pass;
# each is initialised once (compilation dominates the run time of this file).

CONFIGS = {"v1": dict(num_views=1, num_fine=0), "v2_fine": dict(num_views=2, num_fine=5)}


@functools.lru_cache(maxsize=None)
def _setup(name):
  cfg = CONFIGS[name]
  model = _tiny(num_fine_samples=cfg["num_fine"])
  inputs = _inputs(cfg["num_views"])
  return model, inputs, _init(model, inputs)


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
  model, inputs, variables = _setup("v1")
  forward = jit(lambda rngs: _train_forward(model, inputs, variables["params"], 0.7, rngs))
  loss, out = forward(_rngs(1))
  assert np.isfinite(float(loss))
  _check_train_output(out, num_views=1, num_fine=0)
  assert variables["params"]["lift_proj"]["kernel"].shape == (D + 3, 16)  # V = 1: D + 3
  # Training is random (jitter, slot noise, dropout, masking) but a function of the rng streams.
  chex.assert_trees_all_equal(forward(_rngs(1)), (loss, out))
  _, other = forward(_rngs(2))
  assert np.abs(np.asarray(other.render.coarse.colour - out.render.coarse.colour)).max() > 1e-6
  assert np.abs(np.asarray(other.render.z - out.render.z)).max() > 1e-6


def test_train_gradients_v2_fine_under_jit():
  model, inputs, variables = _setup("v2_fine")
  params = variables["params"]
  loss_and_grad = jit(jax.value_and_grad(
      lambda p, keep: _train_forward(model, inputs, p, keep, _rngs(1)), has_aux=True))
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
  model, inputs, variables = _setup("v1")
  sources = _sources(inputs)

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
  model, inputs, variables = _setup("v2_fine")
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
  inputs = _inputs(2, seed=5)
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


# ---------------------------------------------------------------------------------------------
# Ablation switches (docs/method.md §5). Their defaults are the paper's method.


def _config_params(config, size):
  model = model_lib.build_model(config)
  spec = lambda *shape: jax.ShapeDtypeStruct(shape, jnp.float32)
  inputs = dict(source_images=spec(1, 1, size, size, 3), source_cam_to_world=spec(1, 1, 4, 4),
                source_intrinsics=spec(1, 1, 3, 3), ray_origins=spec(1, 3, 3),
                ray_directions=spec(1, 3, 3))
  return jax.eval_shape(
      lambda kw: model.init(jax.random.key(0), **kw, train=False), inputs)["params"]


def _tree_signature(params):
  """Sorted (path of module names, shape) of every parameter."""
  return sorted((tuple(str(k.key) for k in p), tuple(x.shape))
                for p, x in jax.tree_util.tree_flatten_with_path(params)[0])


def test_ablation_defaults_leave_the_model_unchanged():
  """The switches default to the paper's method: the same parameter tree as before they existed
  (leaf and parameter counts of configs/clevr.py:smoke taken from the code without them)."""
  config = defaults.base_config()
  assert config.model.feature_lifting is True and config.model.density_mode == "slot"
  assert config.train.mask_max == 0.99
  defaults.smoke(config)
  params = _config_params(config, config.data.image_size)
  signature = _tree_signature(params)
  assert len(signature) == 152 and sum(x.size for x in jax.tree.leaves(params)) == 48_020
  assert not any({"density_hidden", "density_out"} & set(path) for path, _ in signature)
  for name, value in (("feature_lifting", False), ("density_mode", "mlp"),
                      ("encoder_output_stride", 2)):
    other = config.copy_and_resolve_references()
    other.model[name] = value
    model = model_lib.build_model(other)
    assert getattr(model, name) == value  # wired through build_model
    changed = _tree_signature(_config_params(other, config.data.image_size))
    extra, missing = set(changed) - set(signature), set(signature) - set(changed)
    if name == "feature_lifting":  # only the lifting Linear goes
      assert not extra and {p[0] for p, _ in missing} == {"lift_proj"}
    elif name == "encoder_output_stride":  # only the encoder's last two stages come
      assert not missing and {p[:2] for p, _ in extra} == {("encoder", "upconv1"),
                                                             ("encoder", "iconv1")}
    else:  # only the density head comes
      assert not missing and {p[:2] for p, _ in extra} == {
          ("allocation", "density_hidden"), ("allocation", "density_out")}


def test_without_feature_lifting_points_see_the_views_only_through_the_slots():
  model = _tiny(feature_lifting=False)
  inputs = _inputs(1, seed=3)
  variables = _init(model, inputs)
  assert "lift_proj" not in variables["params"]
  assert {"encoder", "slot_attention"} <= set(variables["params"])
  other_pixels = dict(inputs, source_images=jnp.asarray(
      np.random.default_rng(9).uniform(0, 1, size=inputs["source_images"].shape), jnp.float32))

  @jit
  def encode_and_render(variables, encode_from, render_from):
    encoded = model.apply(variables, **_sources(encode_from), train=False, method=model.encode)
    out = model.apply(variables, encoded, **_sources(render_from),
                      ray_origins=inputs["ray_origins"], ray_directions=inputs["ray_directions"],
                      train=False, method=model.render_rays)
    return encoded.slots, out

  slots, out = encode_and_render(variables, inputs, inputs)
  chex.assert_tree_all_finite(out)
  # Slots held fixed, the source pixels (and hence features) changed: the render is the same.
  _, same = encode_and_render(variables, inputs, other_pixels)
  chex.assert_trees_all_equal(same, out)
  # …but the slots still come from the pixels, so the full model does see them.
  other_slots, changed = encode_and_render(variables, other_pixels, other_pixels)
  assert np.abs(np.asarray(other_slots - slots)).max() > 1e-4
  assert np.abs(np.asarray(changed.coarse.colour - out.coarse.colour)).max() > 1e-6
  # With lifting on (the paper's model), the same pixel change moves the render at fixed slots.
  model_on, inputs_on, variables_on = _setup("v1")
  render_on = jit(lambda images: model_on.apply(
      variables_on, model_on.apply(variables_on, **_sources(inputs_on), train=False,
                                   method=model_on.encode),
      **dict(_sources(inputs_on), source_images=images), ray_origins=inputs_on["ray_origins"],
      ray_directions=inputs_on["ray_directions"], train=False, method=model_on.render_rays))
  a, b = render_on(inputs_on["source_images"]), render_on(other_pixels["source_images"])
  assert np.abs(np.asarray(a.coarse.colour - b.coarse.colour)).max() > 1e-6


def test_runs_saved_before_the_switches_still_load():
  """A run's saved config.json from before the switches lacks them: it reads as the defaults."""
  from slotlifter_jax import checkpoints as ckpt_lib
  import json
  config = defaults.base_config()
  saved = json.loads(config.to_json_best_effort())
  for name in ("feature_lifting", "density_mode"):
    del saved["model"][name]
  ckpt_lib.check_compatible(config, saved, "old_run")  # no error
  ablated = config.copy_and_resolve_references()
  ablated.model.density_mode = "mlp"
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match="model.density_mode"):
    ckpt_lib.check_compatible(ablated, saved, "old_run")
  # What evaluation records and a resume logs reads the missing fields the same way: no change
  # where the request keeps the default, the saved default against the new value where not.
  del saved["data"]["scene_stages"]
  assert ckpt_lib.config_changes(saved, config) == {}
  ablated.data.scene_stages = ((100, 4),)
  assert ckpt_lib.config_changes(saved, ablated) == {
      "model.density_mode": [config.model.density_mode, "mlp"],
      "data.scene_stages": [[], [[100, 4]]]}


def test_a_run_may_change_its_compute_dtype_but_not_its_shapes():
  """model.dtype changes only the precision of the products (parameters stay float32 with the same
  shapes), so a float32 run loads in bfloat16; a changed width still refuses, naming the field."""
  from slotlifter_jax import checkpoints as ckpt_lib
  import json
  config = defaults.base_config()
  saved = json.loads(config.to_json_best_effort())
  bf16 = config.copy_and_resolve_references()
  bf16.model.dtype = "bfloat16"
  ckpt_lib.check_compatible(bf16, saved, "fp32_run")  # no error
  bf16.model.slot_dim = 32
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match="model.slot_dim") as err:
    ckpt_lib.check_compatible(bf16, saved, "fp32_run")
  assert "model.dtype" not in str(err.value)


def test_a_run_may_change_its_slot_iterations():
  """Every slot attention iteration applies the same parameters, so the parameter tree does not
  depend on their number and a run loads with another one (evaluation with more iterations);
  a changed K still refuses, naming only that field."""
  from slotlifter_jax import checkpoints as ckpt_lib
  import json
  config = defaults.base_config()
  defaults.smoke(config)
  saved = json.loads(config.to_json_best_effort())
  more = config.copy_and_resolve_references()
  more.model.slot_iters = config.model.slot_iters + 2
  size = config.data.image_size
  assert _tree_signature(_config_params(more, size)) == _tree_signature(_config_params(config, size))
  ckpt_lib.check_compatible(more, saved, "run")  # no error
  more.model.num_slots = config.model.num_slots + 1
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match="model.num_slots") as err:
    ckpt_lib.check_compatible(more, saved, "run")
  assert "slot_iters" not in str(err.value)


def test_a_run_keeps_its_scene_frame():
  """The weights are tied to the frame positions are given in (data.frame, docs/method.md §3.6):
  another frame refuses, naming the field; a run saved before the field existed reads as "world"."""
  from slotlifter_jax import checkpoints as ckpt_lib
  import json
  config = defaults.base_config()
  saved = json.loads(config.to_json_best_effort())
  turned = config.copy_and_resolve_references()
  turned.data.frame = "source_azimuth"
  with pytest.raises(ckpt_lib.CheckpointMismatchError,
                     match=r"data.frame: saved 'world', requested 'source_azimuth'"):
    ckpt_lib.check_compatible(turned, saved, "world_run")
  del saved["data"]["frame"]
  ckpt_lib.check_compatible(config, saved, "old_run")  # no error
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match="data.frame"):
    ckpt_lib.check_compatible(turned, saved, "old_run")
  resized = config.copy_and_resolve_references()
  resized.data.image_size = 32  # other data fields are not tied to the weights
  ckpt_lib.check_compatible(resized, json.loads(config.to_json_best_effort()), "world_run")


def test_z_bounds_that_hold_every_ray_render_as_the_unbounded_grid():
  """A slab that contains all of [near, far] of every ray changes nothing; a tight slab puts every
  sample inside it."""
  inputs = _inputs(1)
  model = _tiny()
  params = _init(model, inputs)
  run = lambda m: jit(lambda p: m.apply(p, **inputs, train=False))(params)
  plain, wide = run(model), run(_tiny(z_bounds=(-100.0, 100.0)))
  for a, b in zip(jax.tree.leaves(plain.render), jax.tree.leaves(wide.render)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  tight = run(_tiny(z_bounds=(-0.2, 0.2))).render
  height = inputs["ray_origins"][..., None, 2] + tight.z * inputs["ray_directions"][..., None, 2]
  hits = np.asarray(jnp.any(jnp.abs(height) <= 0.2 + 1e-5, axis=-1))  # rays that reach the slab
  assert hits.any()
  inside = np.asarray(jnp.all(jnp.abs(height) <= 0.2 + 1e-5, axis=-1))
  np.testing.assert_array_equal(inside[hits], True)


def test_slot_position_embedding_adds_a_linear_map_of_the_cell_grid_to_the_slot_inputs():
  """The option adds Dense((x, y, 1−x, 1−y)) to slot attention's input only: with that Dense
  zeroed the slots equal the paper model's (same other weights); with it they differ."""
  from slotlifter_jax.slot_attention import position_grid
  grid = np.asarray(position_grid(2, 3))  # hand-computed corners and middle
  np.testing.assert_allclose(grid[0, 0], [0, 0, 1, 1])
  np.testing.assert_allclose(grid[1, 2], [1, 1, 0, 0])
  np.testing.assert_allclose(grid[0, 1], [0.5, 0, 0.5, 1])

  inputs = _inputs(1)
  sources = _sources(inputs)
  paper, with_pos = _tiny(), _tiny(slot_position_embedding=True)
  variables = _init(with_pos, inputs)
  proj = variables["params"]["slot_pos_proj"]
  assert proj["kernel"].shape == (4, D) and proj["bias"].shape == (D,)
  without = {"params": {k: v for k, v in variables["params"].items() if k != "slot_pos_proj"}}
  zeroed = {"params": {**variables["params"],
                       "slot_pos_proj": jax.tree.map(jnp.zeros_like, proj)}}
  # XLA's default fusion emitters, not the suite's loop emitters (tests/conftest.py): with those
  # the two programs' encoders round differently in the last bits.
  default_jit = functools.partial(jax.jit, compiler_options={
      "xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": True})
  encode = lambda m, v: default_jit(lambda: m.apply(v, **sources, train=False, method=m.encode))()
  ref = encode(paper, without)
  chex.assert_trees_all_close(encode(with_pos, zeroed).slots, ref.slots, atol=1e-6)
  moved = encode(with_pos, variables)
  assert float(jnp.max(jnp.abs(moved.slots - ref.slots))) > 1e-3
  # The lifted features are the encoder's, untouched by the embedding.
  chex.assert_trees_all_close(moved.features, ref.features, atol=0)


def test_encoder_output_stride_2_gives_slot_attention_and_the_locality_box_the_finer_grid():
  """model.encoder_output_stride = 2: features on ceil(H/2)×ceil(W/2) cells, slot attention over
  all of them, the background cells of the locality box on the same grid (their centres as in
  `background_cells`), and source-pixel labels at full size."""
  from slotlifter_jax.rendering import views
  model = _tiny(encoder_output_stride=2, locality_attention=True)
  inputs = _inputs(1)
  sources = _sources(inputs)
  variables = _init(model, inputs)
  encoded = jit(lambda: model.apply(variables, **sources, locality=True, train=False,
                                    method=model.encode))()
  h, w = -(-H // 2), -(-W // 2)
  chex.assert_shape(encoded.features, (B, 1, h, w, D))
  chex.assert_shape(encoded.slot_attn, (B, K, h * w))
  np.testing.assert_allclose(encoded.slot_attn.sum(axis=1), 1.0, atol=1e-5)
  cells = model.apply(variables, source_cam_to_world=sources["source_cam_to_world"],
                      source_intrinsics=sources["source_intrinsics"], image_size=(H, W),
                      feature_size=(h, w), method=model.background_cells)
  chex.assert_shape(cells, (B, 1, h, w))
  # While locality holds, a background-only cell's attention goes to the first slot alone.
  background = np.asarray(cells).reshape(B, -1)
  attn = np.asarray(encoded.slot_attn)
  assert background.any()
  np.testing.assert_allclose(attn[:, 0][background], 1.0, atol=1e-5)
  labels = views.source_attention_labels(encoded, (H, W))
  assert labels.shape == (1, H, W)
