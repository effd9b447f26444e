"""Tests for the model's switches (the ablations of docs/method.md §5, the sample slab, slot
positions, the encoder's stride): what each changes in the model, and which of them a run may change
on resume."""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tiny_model as tm
from random_cameras import random_cameras
from tiny_model import B, H, W, K, D, jit

from slotlifter_jax import defaults
from slotlifter_jax import model as model_lib

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
  model = tm.tiny(feature_lifting=False)
  inputs = tm.make_inputs(1, seed=3)
  variables = tm.init(model, inputs)
  assert "lift_proj" not in variables["params"]
  assert {"encoder", "slot_attention"} <= set(variables["params"])
  other_pixels = dict(inputs, source_images=jnp.asarray(
      np.random.default_rng(9).uniform(0, 1, size=inputs["source_images"].shape), jnp.float32))

  @jit
  def encode_and_render(variables, encode_from, render_from):
    encoded = model.apply(variables, **tm.sources(encode_from), train=False, method=model.encode)
    out = model.apply(variables, encoded, **tm.sources(render_from),
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
  model_on, inputs_on, variables_on = tm.setup("v1")
  render_on = jit(lambda images: model_on.apply(
      variables_on, model_on.apply(variables_on, **tm.sources(inputs_on), train=False,
                                   method=model_on.encode),
      **dict(tm.sources(inputs_on), source_images=images), ray_origins=inputs_on["ray_origins"],
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
  inputs = tm.make_inputs(1)
  model = tm.tiny()
  params = tm.init(model, inputs)
  run = lambda m: jit(lambda p: m.apply(p, **inputs, train=False))(params)
  plain, wide = run(model), run(tm.tiny(z_bounds=(-100.0, 100.0)))
  for a, b in zip(jax.tree.leaves(plain.render), jax.tree.leaves(wide.render)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  tight = run(tm.tiny(z_bounds=(-0.2, 0.2))).render
  height = inputs["ray_origins"][..., None, 2] + tight.z * inputs["ray_directions"][..., None, 2]
  hits = np.asarray(jnp.any(jnp.abs(height) <= 0.2 + 1e-5, axis=-1))  # rays that reach the slab
  assert hits.any()
  inside = np.asarray(jnp.all(jnp.abs(height) <= 0.2 + 1e-5, axis=-1))
  np.testing.assert_array_equal(inside[hits], True)


def test_encoder_output_stride_2_gives_slot_attention_the_finer_grid():
  """model.encoder_output_stride = 2: features on ceil(H/2)×ceil(W/2) cells, slot attention over
  all of them, and source-pixel labels at full size."""
  from slotlifter_jax.rendering import views
  model = tm.tiny(encoder_output_stride=2)
  inputs = tm.make_inputs(1)
  sources = tm.sources(inputs)
  variables = tm.init(model, inputs)
  encoded = jit(lambda: model.apply(variables, **sources, train=False, method=model.encode))()
  h, w = -(-H // 2), -(-W // 2)
  chex.assert_shape(encoded.features, (B, 1, h, w, D))
  chex.assert_shape(encoded.slot_attn, (B, K, h * w))
  np.testing.assert_allclose(encoded.slot_attn.sum(axis=1), 1.0, atol=1e-5)
  labels = views.source_attention_labels(encoded, (H, W))
  assert labels.shape == (1, H, W)


def test_pooled_encoder_input_is_the_box_filtered_view_and_its_centre_rays():
  """model.encoder_input_pool = p: RGB and origin are the p×p block means (NumPy), and the
  direction is the ray through the block's centre pixel coordinate, to O((p/focal)²)."""
  rng = np.random.default_rng(4)
  cams, ks = random_cameras(rng, 2, H, W)
  images = rng.uniform(0, 1, size=(2, H, W, 3)).astype(np.float32)
  x = np.asarray(model_lib.encoder_input(images=jnp.asarray(images), cam_to_world=jnp.asarray(
      cams, jnp.float32), intrinsics=jnp.asarray(ks, jnp.float32)))  # [2, H, W, 9]
  pooled = np.asarray(model_lib.pooled_encoder_input(jnp.asarray(x), 2))
  assert pooled.shape == (2, H // 2, W // 2, 9)
  block_mean = images.reshape(2, H // 2, 2, W // 2, 2, 3).mean(axis=(2, 4))
  np.testing.assert_allclose(pooled[..., :3], block_mean, atol=1e-6)
  np.testing.assert_allclose(pooled[..., 3:6], np.broadcast_to(
      cams[:, None, None, :3, 3], pooled[..., 3:6].shape), atol=1e-5)
  # The ray through the block centre (u, v) = (2j + 0.5, 2i + 0.5), by hand: R K⁻¹ (u, v, 1).
  v, u = np.meshgrid(2 * np.arange(H // 2) + 0.5, 2 * np.arange(W // 2) + 0.5, indexing="ij")
  pix = np.stack([u, v, np.ones_like(u)], axis=-1)  # [H/2, W/2, 3]
  for n in range(2):
    d = pix @ np.linalg.inv(ks[n]).T @ cams[n, :3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    np.testing.assert_allclose(pooled[n, ..., 6:9], d, atol=2e-4)
  np.testing.assert_array_equal(model_lib.pooled_encoder_input(jnp.asarray(x), 1), x)
  with pytest.raises(ValueError, match=r"model.encoder_input_pool is 3; the source views' 20×28"):
    model_lib.pooled_encoder_input(jnp.asarray(x), 3)


def test_encoder_input_pool_feeds_the_encoder_the_pooled_view_and_lifts_full_size_colour():
  """With pool 2 and stride 2 the feature map is H/4×W/4, equal to the pool-1 encoder run on the
  pooled input by hand; the parameters are the same tree; lifting still reads full-size RGB."""
  base = tm.tiny(encoder_output_stride=2)
  pooled_model = tm.tiny(encoder_output_stride=2, encoder_input_pool=2)
  inputs = tm.make_inputs(1, seed=5)
  sources = tm.sources(inputs)
  variables = tm.init(base, inputs)
  encoded = jit(lambda: pooled_model.apply(variables, **sources, train=False,
                                           method=pooled_model.encode))()
  chex.assert_shape(encoded.features, (B, 1, H // 4, W // 4, D))
  chex.assert_shape(encoded.slot_attn, (B, K, (H // 4) * (W // 4)))
  x = model_lib.encoder_input(images=sources["source_images"],
                              cam_to_world=sources["source_cam_to_world"],
                              intrinsics=sources["source_intrinsics"])[:, 0]  # [B, H, W, 9]
  by_hand = np.asarray(x).reshape(B, H // 2, 2, W // 2, 2, 9).mean(axis=(2, 4))
  by_hand[..., 6:9] /= np.linalg.norm(by_hand[..., 6:9], axis=-1, keepdims=True)
  reference = jit(lambda z: base.apply(variables, z, method=lambda m, z: m.encoder(z)))(
      jnp.asarray(by_hand))
  np.testing.assert_allclose(encoded.features[:, 0], reference, atol=1e-4)
  # Lifting reads the full-size view: swapping the two columns of every 2×2 block leaves the
  # pooled view, and so the features, as they were, but not the colours the points gather.
  swapped = np.asarray(inputs["source_images"]).reshape(B, 1, H, W // 2, 2, 3)[..., ::-1, :]
  other = dict(inputs, source_images=jnp.asarray(swapped.reshape(B, 1, H, W, 3)))
  run = jit(lambda i: pooled_model.apply(variables, **i, train=False))
  out, out_swapped = run(inputs), run(other)
  np.testing.assert_allclose(out_swapped.encoded.features, out.encoded.features, atol=1e-6)
  assert np.abs(np.asarray(out_swapped.render.coarse.colour - out.render.coarse.colour)).max() > 1e-3


def test_drop_lifted_renders_as_the_model_without_lifting():
  """render_rays(drop_lifted=True) zeroes F_lift, so F_p = E_p: the same render as the model built
  without feature lifting (which never computes F_lift) on the same parameters."""
  model, inputs, variables = tm.setup("v2_fine")
  without = tm.tiny(num_fine_samples=model.num_fine_samples, feature_lifting=False)
  params = {k: v for k, v in variables["params"].items() if not k.startswith("lift_proj")}
  assert set(params) < set(variables["params"])  # the lifting Linears are what is left out

  def render(module, variables, drop_lifted):
    def run(variables):
      encoded = module.apply(variables, **tm.sources(inputs), train=False, method=module.encode)
      return module.apply(variables, encoded, **tm.sources(inputs),
                          ray_origins=inputs["ray_origins"],
                          ray_directions=inputs["ray_directions"], train=False,
                          drop_lifted=drop_lifted, method=module.render_rays)
    return jit(run)(variables)

  dropped = render(model, variables, True)
  reference = render(without, {"params": params}, False)
  chex.assert_trees_all_close(dropped, reference, rtol=1e-5, atol=1e-6)
  kept = render(model, variables, False)
  assert np.abs(np.asarray(kept.fine.colour - dropped.fine.colour)).max() > 1e-5
