"""bf16 compute with float32 parameters (`model.dtype = "bfloat16"`, model.py "Numerics").

The bf16 model runs with the float32 model's parameters, on the smoke model at 64 px, and is
compared with it on what it renders, on its gradients and on a short training run. The tolerances
come from the precision of bfloat16, not from today's outputs:

- bfloat16 keeps 8 significant bits, so one rounding has relative error at most u = 2^-8 ≈ 3.9e-3
  (uniform, rms u/√3). A bf16 Linear or convolution rounds its input, its weights and its output:
  about u rms relative error per layer.
- Layers are normalised (LayerNorm, InstanceNorm), so each passes on the error it receives with
  gain about 1 and independent errors add in quadrature: after L layers in series about √L·u.
  The longest chain from a source pixel to a rendered pixel in the smoke model is 44 bf16
  products: 12 convolutions in the encoder, the lifting Linear, 2 decoder blocks of 11 (two
  attentions of 4: projection, q·k, weights·v, output; the Conv1d; the FFN's 2), the mapping's 4,
  the colour MLP's 5. So what the network gives each sample (σ, the logits of W, the colour before
  its tanh) carries ε ≈ √44·u ≈ 2.6e-2 relative error.
- Volume rendering is float32 and adds no rounding of its own. It composites S = 7 samples:
  α = 1 − e^(−x) moves by x·e^(−x)·ε ≤ ε/e for a relative change ε of σ, transmittance passes that
  on to the later samples, and the colour, the depth (in units of far − near) and the slot masses
  are sums over the samples of weights in [0, 1] times values in [0, 1]. S independent errors of
  ε/e add to √S·ε/e ≈ 2.5e-2 of the range; the colour's own error (½·tanh′ ≤ ½) adds less. The
  segmentation divides the slot masses by their sum: on rays whose mass is at least 1/2 that at
  most doubles their error, but the part common to all slots (a change of opacity) cancels, and W
  is a float32 softmax, moved by at most ¼ of its logits' error. Hence RENDER_RMS_TOL = 3e-2 for
  all three.
Single rays may differ more (volume rendering turns a small change of σ into a change of which
sample a ray stops at), so the bound is on the rms over rays, not on the worst ray. Gradients and
training are compared against float32 runs from the parameters rounded to bf16 (see their tests):
at a random init both are too sensitive to any rounding for a fixed bound.

Why 64 px and not the smoke set's 32 px: the encoder's deepest map is H/16, 2×2 at 32 px, and an
InstanceNorm over 4 cells divides by their spread, which amplifies rounding by |mean|/std of the
4 values (one random init in six rendered 4× worse than the others at 32 px); at 64 px the map is
4×4. The paper's 128 px gives 8×8.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import traverse_util

from slotlifter_jax import defaults
from slotlifter_jax import model as model_lib
from slotlifter_jax import schedules
from slotlifter_jax import train_step as step_lib
from train_helpers import fake_batch, load_config

# bfloat16 unit roundoff: 8 significant bits.
U_BF16 = 2.0 ** -8
# Rms over rays of |bf16 − fp32|, as a fraction of the quantity's range (module docstring).
RENDER_RMS_TOL = 3e-2
# Segmentation is compared on rays whose float32 slot mass reaches this (rays that hit something).
MIN_SLOT_MASS = 0.5
# The encoder's features go through 12 bf16 convolutions in series, each ~u rms: √12·u ≈ 1.4e-2
# relative rms expected, twice that allowed. At least a fraction of one rounding shows that bf16
# really ran: float32 rounding (2^-24 ≈ 6e-8) or a silently float32 model falls far below it.
MAX_FEATURE_DIFF = 2 * np.sqrt(12) * U_BF16
MIN_FEATURE_DIFF = U_BF16 / 8
# Compilation, not execution, is what these tests spend their time on: skip XLA's backend
# optimisations (as tests/tiny_model.py does); it changes no dtype.
jit = functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 0})


def _config(dtype="float32"):
  config = load_config()  # configs/clevr.py:smoke
  config.data.image_size = 64  # the deepest encoder map 4×4 (module docstring)
  config.train.rays_per_scene = 63  # distinct odd sizes: B 2, R 63, S 7, K+1 5
  config.render.num_samples = 7
  config.model.dtype = dtype
  return config


@pytest.fixture(scope="module")
def setup():
  """The float32 and bf16 models, one batch and the float32 model's initial train state."""
  config32, config16 = _config("float32"), _config("bfloat16")
  models = {"float32": model_lib.build_model(config32),
            "bfloat16": model_lib.build_model(config16)}
  batch = fake_batch(config32)
  # 'rbg' keys: initialising compiles several times faster than with threefry (tiny_model.py).
  state = step_lib.init_state(models["float32"], config32, batch, jax.random.key(0, impl="rbg"))
  return dict(configs={"float32": config32, "bfloat16": config16}, models=models, batch=batch,
              state=state)


def _forward(model, batch):
  inputs = step_lib.model_inputs(batch, signed_colour=False)
  return lambda params: model.apply({"params": params}, **inputs, train=False)


def _grad_fn(model, config):
  """(params, batch, step) → ((loss, aux), grads) of the train step (step_lib.make_grad_fn)."""
  grad_fn = step_lib.make_grad_fn(model, config)
  return jit(lambda params, batch, step: grad_fn(
      params, batch, jax.random.fold_in(jax.random.key(1), step),
      schedules.all_schedules(step, config.train)))


def _eqns(jaxpr):
  """Every equation of a (closed) jaxpr, through nested calls, scans, remats and conds."""
  jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
  for eqn in jaxpr.eqns:
    yield eqn
    for value in eqn.params.values():
      for item in value if isinstance(value, (tuple, list)) else (value,):
        if hasattr(item, "eqns") or hasattr(getattr(item, "jaxpr", None), "eqns"):
          yield from _eqns(item)


def _matmul_flops_by_dtype(jaxpr) -> dict:
  """{operand dtype: FLOPs} of the dot_generals and convolutions (2 per multiply-add)."""
  flops = {}
  for eqn in _eqns(jaxpr):
    name = eqn.primitive.name
    if name not in ("dot_general", "conv_general_dilated"):
      continue
    lhs, rhs = (v.aval for v in eqn.invars[:2])
    assert lhs.dtype == rhs.dtype, eqn  # no mixed-precision product hides in the model
    # Multiply-adds per output element: the contracted size (a convolution's kernel taps × its
    # input features per output feature).
    if name == "dot_general":
      (lhs_contract, _), _ = eqn.params["dimension_numbers"]
      per_out = int(np.prod([lhs.shape[d] for d in lhs_contract]))
    else:
      per_out = rhs.size // rhs.shape[eqn.params["dimension_numbers"].rhs_spec[0]]
    key = str(lhs.dtype)
    flops[key] = flops.get(key, 0) + 2 * eqn.outvars[0].aval.size * per_out
  return flops


def test_float32_is_the_default_and_other_dtypes_are_refused():
  assert defaults.base_config().model.dtype == "float32"
  config = load_config()
  assert model_lib.build_model(config).dtype == jnp.float32
  del config.model["dtype"]  # a run saved before the field existed builds the float32 model
  assert model_lib.build_model(config).dtype == jnp.float32
  config.model.dtype = "float16"
  with pytest.raises(ValueError, match="model.dtype"):
    model_lib.build_model(config)


def test_bf16_products_run_in_bf16_and_softmax_and_norms_in_float32(setup):
  """On the traced forward pass: nearly every matmul FLOP has bf16 operands (what is left is the
  float32 geometry: rays, projections, and volume rendering's sums over samples), every softmax
  exp and norm rsqrt is float32, and the float32 model contains no bf16 value at all."""
  params, batch = setup["state"].params, setup["batch"]
  jaxprs = {d: jax.make_jaxpr(_forward(m, batch))(params) for d, m in setup["models"].items()}

  flops = _matmul_flops_by_dtype(jaxprs["bfloat16"])
  assert set(flops) == {"bfloat16", "float32"}, flops
  # The float32 products are the geometry's 3×3 and 3×4 transforms per sample and the sums over
  # samples per ray, O(10) multiply-adds per sample against O(C²) = 256 per Linear of the
  # network (C = 16 in the smoke model): below 1 %.
  assert flops["bfloat16"] / sum(flops.values()) > 0.99, flops
  # Every convolution (they are all the encoder's, and its only kernels) is bf16.
  convs = [e for e in _eqns(jaxprs["bfloat16"]) if e.primitive.name == "conv_general_dilated"]
  encoder_kernels = [k for k in traverse_util.flatten_dict(params["encoder"]) if k[-1] == "kernel"]
  assert len(convs) == len(encoder_kernels) > 10
  assert all(e.invars[0].aval.dtype == jnp.bfloat16 for e in convs)

  for name in ("exp", "rsqrt"):  # softmax (also σ's exp(s_σ)); LayerNorm and InstanceNorm
    dtypes = [e.invars[0].aval.dtype for e in _eqns(jaxprs["bfloat16"]) if e.primitive.name == name]
    assert dtypes and all(d == jnp.float32 for d in dtypes), (name, dtypes)

  dtypes32 = {v.aval.dtype for e in _eqns(jaxprs["float32"]) for v in e.outvars
              if hasattr(v.aval, "dtype")}
  assert jnp.dtype(jnp.bfloat16) not in dtypes32


def _slot_mass(render) -> np.ndarray:
  """Σ_k of the rendered slot masses Σ_i w_i W_ik over the real slots k ≥ 1: [B, R]."""
  weights = np.asarray(render.coarse.weights, np.float64)  # [B, R, S]
  slot_weights = np.asarray(render.point_slot_weights, np.float64)[..., 1:]  # [B, R, S, K]
  return np.einsum("brs,brsk->br", weights, slot_weights)


def _rms(x, y) -> float:
  return float(np.sqrt(np.mean((np.asarray(x, np.float64) - np.asarray(y, np.float64)) ** 2)))


def test_bf16_render_is_within_tolerance_of_float32(setup):
  """Same parameters: the rms over rays of the colour, depth and segmentation differences is below
  RENDER_RMS_TOL of their range (module docstring), and not zero: bf16 really ran.

  The segmentation is compared on the rays whose float32 slot mass is at least MIN_SLOT_MASS: it
  is the slot masses divided by their sum, and on a ray that passes (almost) through empty space
  that divides ~0 by ~0, so any rounding can move it anywhere in [0, 1].
  """
  params, batch, config = setup["state"].params, setup["batch"], setup["configs"]["float32"]
  out = {d: jit(_forward(m, batch))(params) for d, m in setup["models"].items()}
  a, b = out["float32"].render, out["bfloat16"].render
  hit = _slot_mass(a) >= MIN_SLOT_MASS  # [B, R]
  assert hit.mean() > 0.25  # enough rays to compare the segmentation on
  depth_range = config.render.far - config.render.near
  for name, unit, rays in (("colour", 1.0, ...), ("depth", depth_range, ...),
                           ("segmentation", 1.0, hit)):
    x, y = getattr(a.coarse, name), getattr(b.coarse, name)
    assert y.dtype == jnp.float32 and y.shape == x.shape, name  # rendering stays float32
    rms = _rms(np.asarray(x)[rays], np.asarray(y)[rays]) / unit
    assert 0.0 < rms < RENDER_RMS_TOL, (name, rms)
  # Encoded features: float32 at the module boundary, as far from float32 as 12 bf16 layers make
  # them.
  fa, fb = (np.asarray(o.encoded.features, np.float64) for o in out.values())
  assert out["bfloat16"].encoded.features.dtype == jnp.float32
  feature_diff = _rms(fa, fb) / np.sqrt(np.mean(fa ** 2))
  assert MIN_FEATURE_DIFF < feature_diff < MAX_FEATURE_DIFF, feature_diff


@pytest.fixture(scope="module")
def grad_fns(setup):
  return {d: _grad_fn(setup["models"][d], setup["configs"][d]) for d in setup["models"]}


def _flat(tree) -> np.ndarray:
  return np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)]).astype(np.float64)


def _round_to_bf16(params):
  """The float32 parameters rounded to the nearest bf16 (what a bf16 product multiplies by)."""
  return jax.tree.map(lambda x: x.astype(jnp.bfloat16).astype(jnp.float32), params)


@pytest.mark.parametrize("step", [0, 5])  # 0: masking, slot noise, locality on; 5: all off
def test_bf16_gradients_are_finite_float32_and_as_close_as_rounding_the_weights(
    grad_fns, setup, step):
  """jax.grad of the training loss through the bf16 model: every leaf finite and float32 (the
  parameters' dtype), and as close to the float32 gradient as bf16 rounding allows here.

  The reference for "as close" is independent of the bf16 code path: the float32 model's gradient
  at the parameters rounded to bf16. At a random init this gradient is ill-conditioned (a 1e-3
  relative change of the weights can turn it by 45°), so no fixed tolerance derived from u alone
  would hold; the rounded weights show what one bf16 rounding per layer does to it. The bf16
  model rounds each layer's weights the same way and also its inputs and outputs, three
  independent roundings of the same size instead of one: √3 times the reference's distance
  expected, 2√3 allowed. Its gradient must also still descend the float32 loss (positive inner
  product with the float32 gradient).
  """
  params, batch = setup["state"].params, setup["batch"]
  (loss16, _), g16 = grad_fns["bfloat16"](params, batch, step)
  (_, _), g32 = grad_fns["float32"](params, batch, step)
  rounded = _round_to_bf16(params)
  (_, _), g_rounded = grad_fns["float32"](rounded, batch, step)
  assert loss16.dtype == jnp.float32 and np.isfinite(float(loss16))
  assert jax.tree.structure(g16) == jax.tree.structure(params)
  for path, g in jax.tree_util.tree_leaves_with_path(g16):
    assert g.dtype == jnp.float32, jax.tree_util.keystr(path)
    assert np.all(np.isfinite(np.asarray(g))), jax.tree_util.keystr(path)
  flat16, flat32, flat_rounded = _flat(g16), _flat(g32), _flat(g_rounded)
  assert np.linalg.norm(flat16) > 0 and flat16 @ flat32 > 0
  distance = np.linalg.norm(flat16 - flat32)
  reference = np.linalg.norm(flat_rounded - flat32)
  assert 0.0 < distance < 2.0 * np.sqrt(3.0) * reference, (distance, reference)


# Training comparison: smoke schedules (warm-up 2, masking and slot noise over 3 steps) with a
# learning rate 20× the paper's so that 15 steps on one batch visibly lower the loss.
TRAIN_STEPS = 15
TRAIN_LR = 1e-3


def test_bf16_training_loss_tracks_float32(grad_fns, setup):
  """TRAIN_STEPS steps of the train step without its non-finite guard (step_lib.make_grad_fn,
  step_lib.make_optimizer, the step's schedules and keys) on one batch from the same init, in float32
  and in bf16, and in float32 from the init rounded to bf16 (the reference).

  - Both losses are finite and fall (the last three steps below 0.8 of the first).
  - Step 0 renders one and the same model: MSE losses of two renders whose colours differ by rms e
    satisfy |L' − L| ≤ e·(2√L + e) (Cauchy–Schwarz on mean((c' − c)(c' + c − 2t))), with
    e = RENDER_RMS_TOL.
  - Later steps: the parameters part ways, as they do between any two runs that differ by a
    rounding (Lion moves every weight by ±lr, so a gradient component near 0 that flips sign moves
    its weight by 2·lr). The reference measures how far a float32 run drifts from one bf16
    rounding of its init; the bf16 run rounds three times per layer at every step, √3 times as
    far expected and 2√3 allowed (as for the gradients), in rms over the steps.
  """
  batch, state = setup["batch"], setup["state"]
  config = setup["configs"]["float32"].copy_and_resolve_references()
  config.train.base_lr = TRAIN_LR
  tx = step_lib.make_optimizer(config.train)

  @jit
  def apply(params, opt_state, grads):
    updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state

  rounded = _round_to_bf16(state.params)
  runs = {"float32": (grad_fns["float32"], state.params),
          "bfloat16": (grad_fns["bfloat16"], state.params),
          "reference": (grad_fns["float32"], rounded)}
  losses = {}
  for name, (grad_fn, params) in runs.items():
    opt_state = tx.init(params)
    curve = []
    for step in range(TRAIN_STEPS):
      (loss, _), grads = grad_fn(params, batch, step)
      params, opt_state = apply(params, opt_state, grads)
      curve.append(float(loss))
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(params)), name
    losses[name] = np.asarray(curve)
  l32, l16, ref = losses["float32"], losses["bfloat16"], losses["reference"]
  for curve in (l32, l16):
    assert np.all(np.isfinite(curve)) and curve[-3:].mean() < 0.8 * curve[0], curve
  e = RENDER_RMS_TOL
  assert abs(l16[0] - l32[0]) <= e * (2.0 * np.sqrt(l32[0]) + e), (l16[0], l32[0])
  drift = _rms(l16, l32)
  drift_reference = _rms(ref, l32)
  assert 0.0 < drift < 2.0 * np.sqrt(3.0) * drift_reference, (drift, drift_reference,
                                                                np.stack([l32, l16, ref]))


def test_bf16_traces_with_every_model_switch():
  """The other layouts (fine pass, decoder blocks under nn.scan + remat, MLP density, two
  source views) trace in bf16 (nn.scan needs its carry h to keep its
  dtype, float32) and give float32 renders and gradients; shapes only, nothing compiled."""
  config = _config("bfloat16")
  config.render.num_fine_samples = 5
  config.model.remat_scan = True
  config.model.density_mode = "mlp"
  config.data.num_source_views = 2
  model = model_lib.build_model(config)
  batch = fake_batch(config)
  params = step_lib.state_shapes(model, config, batch).params
  grad_fn = step_lib.make_grad_fn(model, config)
  (loss, _), grads = jax.eval_shape(lambda p: grad_fn(
      p, batch, jax.random.key(1), schedules.all_schedules(0, config.train)), params)
  assert loss.dtype == jnp.float32
  assert all(g.dtype == jnp.float32 for g in jax.tree.leaves(grads))
  out = jax.eval_shape(_forward(model, batch), params)
  for render in (out.render.coarse, out.render.fine):
    assert render.colour.dtype == render.depth.dtype == render.segmentation.dtype == jnp.float32
