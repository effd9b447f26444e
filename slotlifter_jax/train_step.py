"""The train state, the optimiser of docs/method.md §2 and the jit-compiled train step.

One step = forward on a batch of B scenes × R rays, MSE in [0, 1] colour units (mean of coarse and
fine when both exist), gradients, global-norm clipping, Lion with two schedules. The step reads
every schedule from `state.step` and derives its random keys with `fold_in(key, step)`, so a
resumed run is bit-identical to an uninterrupted one. A non-finite loss or gradient leaves the
parameters and optimiser state unchanged (the step counter still advances, so the next batch is
a different one) and is counted.
"""

from __future__ import annotations

from typing import Any, Callable

import flax
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from slotlifter_jax import averaging
from slotlifter_jax import config_checks
from slotlifter_jax import model as model_lib
from slotlifter_jax import programs
from slotlifter_jax import schedules
from slotlifter_jax.data import device_sampler
from slotlifter_jax.data.types import Scene

RNG_STREAMS = ("dropout", "noise", "sample", "mask")
# Batch entries with a ray axis (axis 1), which ray chunks split; the others are per scene.
RAY_KEYS = ("ray_origins", "ray_directions", "target_rgb")

# Parameters of these submodules follow the head schedule (no warm-up); everything else follows the
# backbone schedule (docs/method.md §2).
HEAD_MODULE_PREFIXES = model_lib.HEAD_MODULE_PREFIXES
# With train.slot_attention_lr_scale ≠ 1 these follow their own schedule. A third group only then,
# so the optimiser state of runs without it keeps its structure.
SLOT_ATTENTION_MODULE_PREFIXES = model_lib.SLOT_ATTENTION_MODULE_PREFIXES


@flax.struct.dataclass
class TrainState:
  step: jax.Array  # int32 scalar
  params: Any
  opt_state: Any
  nonfinite_in_row: jax.Array  # int32 scalar
  nonfinite_total: jax.Array  # int32 scalar


def param_groups(params, *, split_slot_attention: bool = False) -> Any:
  """'head' or 'backbone' for every leaf, from the name of its top-level submodule; with
  `split_slot_attention`, 'slot_attention' for slot attention's (own schedule)."""
  def label(path, _):
    top = str(getattr(path[0], "key", path[0]))
    if top.startswith(HEAD_MODULE_PREFIXES):
      return "head"
    if split_slot_attention and top.startswith(SLOT_ATTENTION_MODULE_PREFIXES):
      return "slot_attention"
    return "backbone"
  return jax.tree_util.tree_map_with_path(label, params)


def make_optimizer(train_config) -> optax.GradientTransformation:
  c = train_config
  # Optax calls a schedule with the update count alone; the rates are those the metrics log.
  backbone_lr = lambda t: schedules.backbone_lr(t, c)
  head_lr = lambda t: schedules.head_lr(t, c)
  def lion(lr):
    # optax.lion applies decoupled weight decay scaled by the lr, as the official Lion does.
    return optax.lion(lr, b1=c.b1, b2=c.b2, weight_decay=c.weight_decay)
  def adamw(lr):
    return optax.adamw(lr, b1=c.b1, b2=c.adam_b2, weight_decay=c.weight_decay)
  optimizers = {"lion": lion, "adamw": adamw}
  if c.optimizer not in optimizers:
    raise ValueError(f"train.optimizer is {c.optimizer!r}; use one of {sorted(optimizers)}")
  make = optimizers[c.optimizer]
  groups = {"backbone": make(backbone_lr), "head": make(head_lr)}
  split = schedules.has_slot_attention_group(c)
  if split:
    groups["slot_attention"] = make(lambda t: schedules.slot_attention_lr(t, c))
  chain = [optax.clip_by_global_norm(c.grad_clip),
           optax.multi_transform(groups, lambda p: param_groups(p, split_slot_attention=split))]
  problem = config_checks.averaging_problem(c)
  if problem:
    raise ValueError(problem)
  if averaging.enabled(c):  # off, the state stays that of every earlier checkpoint
    chain.append(averaging.param_ema(float(c.ema_decay), int(c.get("ema_start_step", 0))))
  return optax.chain(*chain)


def model_inputs(batch: dict, *, signed_colour: bool) -> dict:
  """The model's keyword inputs from a pipeline batch; DTU/ScanNet models see images in [−1, 1]."""
  images = batch["source_images"]
  if signed_colour:
    images = images * 2.0 - 1.0
  return dict(
      source_images=images,
      source_cam_to_world=batch["source_cam_to_world"],
      source_intrinsics=batch["source_intrinsics"],
      ray_origins=batch["ray_origins"],
      ray_directions=batch["ray_directions"],
  )


def to_unit_colour(colour, *, signed_colour: bool):
  return (colour + 1.0) * 0.5 if signed_colour else colour


def init_batch(scene: Scene) -> dict[str, np.ndarray]:
  """A one-scene, one-ray batch with the model's input shapes (parameter shapes depend only on V
  and the image channels, not on H, W or the ray count)."""
  idx = np.asarray(scene.source_indices)
  centre = scene.cam_to_world[idx[0], :3, 3]
  return dict(
      source_images=scene.images[idx][None],  # [1, V, H, W, 3]
      source_cam_to_world=scene.cam_to_world[idx][None],  # [1, V, 4, 4]
      source_intrinsics=scene.intrinsics[idx][None],  # [1, V, 3, 3]
      ray_origins=np.broadcast_to(centre, (1, 1, 3)).astype(np.float32),
      ray_directions=scene.cam_to_world[idx[0], :3, 2][None, None].astype(np.float32),
      target_rgb=np.zeros((1, 1, 3), np.float32),
  )


def init_state(model, config, batch: dict, key: jax.Array) -> TrainState:
  """The train state at step 0: initialised weights and the optimiser's state."""
  # The program is almost all inlined threefry draws, one per weight (the forward is dead code);
  # on a CPU, LLVM at -O1 compiles it in 45–75 % of the default level's time, to the same bits
  # (experiments/compile_levels.py; experiments/journal/2026-11.md, "Compile time").
  init, args = init_program(model, config, batch, key, compiler_options=_init_options())
  return _state_from(init(*args)["params"], config)


def _init_options() -> dict | None:
  cpu = jax.default_backend() == "cpu"
  return {"xla_backend_optimization_level": 1} if cpu else None


def state_shapes(model, config, batch: dict, sharding=None) -> TrainState:
  """init_state's shapes and dtypes, placed with `sharding` if given; nothing is compiled or
  computed (a restore's target)."""
  batch_avals = tuple(sorted((k, tuple(v.shape), str(v.dtype)) for k, v in batch.items()))
  # Through init_state's own jitted init (same compiler options, so the same program object): the
  # trace made here is the one a fresh run's init_state then reuses, instead of tracing the
  # model's init twice (a few seconds of each process that starts a run).
  def build():
    key = jax.random.key(0, impl=config.train.get("prng_impl", "threefry2x32"))  # the run's kind
    init, args = init_program(model, config, batch, key, compiler_options=_init_options())
    params = jax.eval_shape(init, *args)["params"]  # a top-level trace, as init_state's call
    return jax.eval_shape(lambda p: _state_from(p, config), params)
  shapes = programs.shared(("state_shapes", model, programs.config_key(config), batch_avals),
                           build)
  if sharding is None:
    return shapes
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding), shapes)


def init_program(model, config, batch: dict, key: jax.Array, *, compiler_options=None):
  """(jitted init of the model's variables, its arguments): what init_state compiles and runs.

  The weights do not depend on the batch, so one scene and one ray stand for it: every init of a
  model is then the same program, whatever the batch and ray counts. Keys and batch are
  arguments, not constants baked into the program, so that program is one compilation (and one
  persistent-cache entry)."""
  rngs = {"params": key, **{s: jax.random.fold_in(key, i + 1) for i, s in enumerate(RNG_STREAMS)}}
  first = {k: v[:1, :1] if k in RAY_KEYS else v[:1] for k, v in batch.items()}
  inputs = model_inputs(first, signed_colour=config.model.colour_range == "signed")
  options = tuple(sorted(compiler_options.items())) if compiler_options else None
  def init_variables(rngs, inputs):
    return model.init(rngs, **inputs, slot_noise_sigma=1.0, keep_ratio=1.0, locality=True,
                      train=False)
  init = programs.shared(("init", model, options),
                         lambda: jax.jit(init_variables, compiler_options=compiler_options))
  return init, (rngs, inputs)


def _state_from(params, config) -> TrainState:
  tx = make_optimizer(config.train)
  zero = lambda: jnp.zeros((), jnp.int32)  # distinct buffers: the step donates every leaf
  return TrainState(step=zero(), params=params, opt_state=tx.init(params),
                    nonfinite_in_row=zero(), nonfinite_total=zero())


def _tree_all_finite(tree) -> jax.Array:
  leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]
  return jnp.all(jnp.stack(leaves))


def make_grad_fn(model, config) -> Callable:
  """grad_fn(params, batch, key, sched) -> ((loss, aux), grads) of one (chunk of a) batch."""
  signed = config.model.colour_range == "signed"

  def loss_fn(params, batch, step_key, sched):
    rngs = {s: jax.random.fold_in(step_key, i) for i, s in enumerate(RNG_STREAMS)}
    out = model.apply(
        {"params": params}, **model_inputs(batch, signed_colour=signed),
        slot_noise_sigma=sched["slot_noise_sigma"], keep_ratio=sched["keep_ratio"],
        locality=sched["locality"], train=True, rngs=rngs)
    target = batch["target_rgb"]  # [B, R, 3] in [0, 1]
    coarse = to_unit_colour(out.render.coarse.colour, signed_colour=signed)
    mse_coarse = jnp.mean((coarse - target) ** 2)
    loss, mse_final = mse_coarse, mse_coarse
    if out.render.fine is not None:
      fine = to_unit_colour(out.render.fine.colour, signed_colour=signed)
      mse_final = jnp.mean((fine - target) ** 2)
      loss = 0.5 * (mse_coarse + mse_final)
    return loss, dict(mse_coarse=mse_coarse, mse=mse_final)

  return jax.value_and_grad(loss_fn, has_aux=True)


def make_step_fn(model, config, *, key: jax.Array) -> Callable:
  """The pure step(state, batch) -> (state, metrics) that `make_train_step` and `make_train_block`
  compile. `key` is the run's base key; the step's keys are fold_in(key, step)."""
  tx = make_optimizer(config.train)
  scene_chunks = int(config.train.grad_accum_chunks)
  ray_chunks = int(config.train.get("ray_chunks", 1))
  chunks = scene_chunks * ray_chunks
  grad_fn = make_grad_fn(model, config)

  def split(batch):
    """[B, ...] / [B, R, ...] → [chunks, B/scene_chunks, (R/ray_chunks,) ...], scene-major."""
    def one(key, x):
      b = x.shape[0]
      x = x.reshape((scene_chunks, b // scene_chunks) + x.shape[1:])
      if key in RAY_KEYS:
        r = x.shape[2]
        x = x.reshape(x.shape[:2] + (ray_chunks, r // ray_chunks) + x.shape[3:])
        x = jnp.moveaxis(x, 2, 1)  # [scene_chunks, ray_chunks, B/sc, R/rc, ...]
      else:  # per-scene inputs are shared by the ray chunks of a scene
        x = jnp.broadcast_to(x[:, None], (scene_chunks, ray_chunks) + x.shape[1:])
      return x.reshape((chunks,) + x.shape[2:])
    return {k: one(k, v) for k, v in batch.items()}

  def grads_over_chunks(params, batch, step_key, sched):
    if chunks == 1:
      return grad_fn(params, batch, step_key, sched)
    # Gradient accumulation: the loss is a mean over equal-sized chunks, so the mean of the chunk
    # gradients is the full-batch gradient, at a fraction of the activations. Ray chunks re-run
    # the (cheap) encoder and slot attention of their scene.
    def body(acc, inputs):
      i, chunk = inputs
      (loss, aux), g = grad_fn(params, chunk, jax.random.fold_in(step_key, i), sched)
      return jax.tree.map(jnp.add, acc, ((loss, aux), g)), None

    zeros = jax.tree.map(jnp.zeros_like, ((jnp.zeros(()), dict(mse_coarse=jnp.zeros(()),
                                                                 mse=jnp.zeros(()))), params))
    total, _ = jax.lax.scan(body, zeros, (jnp.arange(chunks), split(batch)))
    return jax.tree.map(lambda x: x / chunks, total)

  def step(state: TrainState, batch: dict):
    sched = schedules.all_schedules(state.step, config.train)
    step_key = jax.random.fold_in(key, state.step)
    (loss, aux), grads = grads_over_chunks(state.params, batch, step_key, sched)
    finite = jnp.isfinite(loss) & _tree_all_finite(grads)
    updates, opt_state = tx.update(grads, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    keep = lambda new, old: jax.tree.map(lambda n, o: jnp.where(finite, n, o), new, old)
    in_row = jnp.where(finite, 0, state.nonfinite_in_row + 1)
    new_state = TrainState(
        step=state.step + 1, params=keep(params, state.params),
        opt_state=keep(opt_state, state.opt_state), nonfinite_in_row=in_row,
        nonfinite_total=state.nonfinite_total + (~finite).astype(jnp.int32))
    metrics = dict(
        loss=loss, psnr=-10.0 * jnp.log10(aux["mse"]), psnr_coarse=-10.0 * jnp.log10(aux["mse_coarse"]),
        grad_norm=optax.tree.norm(grads), param_norm=optax.tree.norm(state.params),
        finite=finite, nonfinite_in_row=in_row, **sched)
    return new_state, metrics

  return step


class _WithKeys:
  """`fn(state, data, *keys)` (jitted, lowered or compiled) used as `fn(state, data)`.

  The keys are arguments of the compiled program rather than constants in it, so runs and tests
  that differ only in their seed share one compilation (and one persistent-cache entry).
  `.lower(...).compile()` works as on a jitted function, for the benchmarks."""

  def __init__(self, fn, keys: tuple):
    self._fn, self._keys = fn, keys

  def __call__(self, state, data):
    return self._fn(state, data, *self._keys)

  def lower(self, state, data):
    return _WithKeys(self._fn.lower(state, data, *self._keys), self._keys)

  def compile(self, **kwargs):  # compiler_options=…
    return _WithKeys(self._fn.compile(**kwargs), self._keys)

  def __getattr__(self, name):  # memory_analysis, cost_analysis, as_text, …
    return getattr(self._fn, name)


def make_train_step(model, config, *, key: jax.Array, mesh: Mesh | None = None) -> Callable:
  """Returns step(state, batch) -> (state, metrics), compiled once, state donated.

  `key` is the run's base key; the step's keys are fold_in(key, step). With a mesh, the batch is
  sharded over its scene axis along mesh axis 'data' and the state is replicated.
  """
  def build():
    own = config.copy_and_resolve_references()  # a kept program must not see later edits
    def keyed(state, batch, key):
      return make_step_fn(model, own, key=key)(state, batch)
    if mesh is None:
      return jax.jit(keyed, donate_argnums=0)
    replicated = NamedSharding(mesh, P())
    return jax.jit(keyed, donate_argnums=0,
                   in_shardings=(replicated, batch_sharding(mesh), replicated),
                   out_shardings=(replicated, replicated))
  # One jitted step per (model, config, mesh) in a process: a restart or a second run of the same
  # config reuses its trace and compilation (slotlifter_jax/programs.py).
  compiled = programs.shared(("train_step", model, programs.config_key(config), mesh), build)
  return _WithKeys(compiled, (key,))


def make_train_block(model, config, *, key: jax.Array, data_key: jax.Array, num_steps: int,
                     mesh: Mesh | None = None, unroll: int | bool = 1) -> Callable:
  """Returns block(state, scenes) -> (state, metrics [num_steps]): `num_steps` train steps in one
  dispatch, each on a batch drawn on the device (data/device_sampler.py), state donated.

  Step t's batch comes from fold_in(data_key, t) and its model keys from fold_in(key, t), as in
  `make_train_step`, so a run is a pure function of (seed, step) whatever the block length, and a
  resumed run is exact. One dispatch per block pays the host's per-step costs (dispatch, metric
  transfer, the wait before the next step) once per block: with a small decoder they were as large
  as the step itself (experiments/journal/2026-11.md, "The scene-sized model").
  """
  d, t = config.data, config.train
  stages = tuple((int(a), int(b)) for a, b in d.get("curriculum", ()))
  draw = dict(batch_scenes=int(t.batch_scenes), rays_per_scene=int(t.rays_per_scene),
              novel_ray_prob=float(d.novel_ray_prob))

  def build():
    own = config.copy_and_resolve_references()  # a kept program must not see later edits

    def block(state: TrainState, scenes, key, data_key):  # keys as arguments: see _WithKeys
      step = make_step_fn(model, own, key=key)
      def body(state, _):
        limit = device_sampler.curriculum_limit(state.step, stages) if stages else None
        batch = device_sampler.sample_batch(scenes, jax.random.fold_in(data_key, state.step),
                                            max_objects=limit, **draw)
        if mesh is not None:
          batch = jax.lax.with_sharding_constraint(batch, batch_sharding(mesh))
        return step(state, batch)
      if num_steps == 1:  # no loop at all: XLA:CPU compiles a loop body's convolutions worse
        state, metrics = body(state, None)
        return state, jax.tree.map(lambda x: x[None], metrics)
      return jax.lax.scan(body, state, None, length=num_steps, unroll=unroll)

    if mesh is None:
      return jax.jit(block, donate_argnums=0)
    replicated = NamedSharding(mesh, P())
    return jax.jit(block, donate_argnums=0, in_shardings=(replicated,) * 4,
                   out_shardings=(replicated, replicated))
  compiled = programs.shared(
      ("train_block", model, programs.config_key(config), num_steps, mesh, unroll), build)
  return _WithKeys(compiled, (key, data_key))


def make_mesh(devices=None) -> Mesh:
  devices = jax.devices() if devices is None else devices
  return Mesh(np.asarray(devices), ("data",))


def batch_sharding(mesh: Mesh) -> NamedSharding:
  """Every batch array is sharded over its leading (scene) axis."""
  return NamedSharding(mesh, P("data"))


def shard_batch(batch: dict, mesh: Mesh) -> dict:
  """Puts a host batch (the same global batch on every process) onto the mesh, split over scenes."""
  sharding = batch_sharding(mesh)
  def put(x):
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])
  return {k: put(v) for k, v in batch.items()}


def assemble_batch(local: dict, mesh: Mesh, global_size: int) -> dict:
  """The global batch from this process's rows of it (`multihost.local_rows(batch_sharding(mesh),
  global_size)`, in that order). With one process those rows are the whole batch and this is
  `shard_batch`; with several, each process passes only its own rows and none holds the rest."""
  if jax.process_count() == 1:
    return shard_batch(local, mesh)
  sharding = batch_sharding(mesh)
  def put(x):
    x = np.asarray(x)
    return jax.make_array_from_process_local_data(sharding, x, (global_size,) + x.shape[1:])
  return {k: put(v) for k, v in local.items()}
