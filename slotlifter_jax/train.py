"""`train_and_evaluate`: the training loop around the jitted step.

Per step the loop only feeds the prefetched batch and, every `log_every` steps, reads the metrics
back. Everything the loop owns is resumable: the batch is a function of (seed, step), the keys are
fold_in(key, step), and the state is checkpointed with orbax; SIGINT/SIGTERM save before exiting.

Several processes (`--distributed`, slotlifter_jax/multihost.py) run this same loop: each gathers
only its own scenes of every batch, all of them take part in every checkpoint save and restore and
compute the same validation, and process 0 alone writes files and logs progress.
"""

from __future__ import annotations

import json
import os
import signal
import time

import jax
import ml_collections
import numpy as np
from absl import logging
from tqdm import tqdm

from slotlifter_jax import averaging
from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import collapse
from slotlifter_jax import config_checks
from slotlifter_jax.config_checks import ConfigError
from slotlifter_jax import model as model_lib
from slotlifter_jax import multihost
from slotlifter_jax import provenance
from slotlifter_jax import restarts
from slotlifter_jax import train_step as step_lib
from slotlifter_jax import emergence
from slotlifter_jax import validation
from slotlifter_jax.data import device_sampler
from slotlifter_jax.data import embedded
from slotlifter_jax.data import pipeline
from slotlifter_jax.data import registry


class NonFiniteError(RuntimeError):
  """Too many non-finite steps in a row."""


class Interrupted(Exception):
  """Training stopped on SIGINT/SIGTERM after checkpointing; the run resumes where it stopped.
  The command line exits with 128 + the signal's number, as a shell does for a killed job."""

  def __init__(self, signum: int, step: int):
    super().__init__(f"interrupted by signal {signum} at step {step}; checkpointed, run the same "
                     f"command again to resume")
    self.signum, self.step = signum, step


class _StopFlag:
  """Turns SIGINT/SIGTERM into a flag the loop checks, so it can checkpoint before leaving."""

  def __init__(self):
    self.signal = None
    self._old = {}

  def __enter__(self):
    for s in (signal.SIGINT, signal.SIGTERM):
      self._old[s] = signal.signal(s, self._handle)
    return self

  def _handle(self, signum, frame):
    if self.signal is not None:  # a second signal: leave now
      raise KeyboardInterrupt
    self.signal = signum
    # The flag is read between steps; the first step (or block) compiles before it runs.
    logging.warning("signal %d: checkpointing and exiting after the current step (after it "
                    "compiles, if it is the first); send it again to leave at once", signum)

  def __exit__(self, *exc):
    for s, h in self._old.items():
      signal.signal(s, h)


class MetricWriter:
  """Metrics as JSON lines (DIR/metrics.jsonl) and TensorBoard events (DIR/tb)."""

  def __init__(self, workdir: str):
    from tensorboardX import SummaryWriter
    self._jsonl = open(os.path.join(workdir, "metrics.jsonl"), "a")
    self._tb = SummaryWriter(os.path.join(workdir, "tb"))

  def write(self, step: int, kind: str, values: dict) -> None:
    clean = {k: (float(v) if np.ndim(v) == 0 else np.asarray(v).tolist()) for k, v in values.items()}
    self._jsonl.write(json.dumps({"step": step, "kind": kind, "time": time.time(), **clean}) + "\n")
    self._jsonl.flush()
    for k, v in clean.items():
      if isinstance(v, float):
        self._tb.add_scalar(f"{kind}/{k}", v, step)

  def close(self):
    self._jsonl.close()
    self._tb.close()


class _NoWriter:
  """The MetricWriter of the processes other than process 0: they write nothing."""

  def write(self, step: int, kind: str, values: dict) -> None:
    pass

  def close(self):
    pass


def _on_device(config, train_scenes) -> bool:
  """True for data.sampler=device (config_checks has vetted its fields), after checking its
  object-count curriculum against the training scenes."""
  if config.data.get("sampler", "host") != "device":
    return False
  device_sampler.check_curriculum(config.data.get("curriculum", ()), train_scenes)
  return True


class _RunClock:
  """Wall-clock seconds of training of a run, summed over its resumes and restarts (the `wall_s`
  of metrics.jsonl): a resumed run continues from the last `wall_s` it logged, a new attempt
  from the last one its abandoned attempt logged."""

  def __init__(self, workdir: str):
    archived = restarts.latest_archived_log(workdir)
    self._offset = max(_last_logged_wall_s(os.path.join(workdir, "metrics.jsonl")),
                       _last_logged_wall_s(archived) if archived else 0.0)
    self._start = time.time()

  def elapsed(self) -> float:
    return self._offset + time.time() - self._start


def _last_logged_wall_s(path: str) -> float:
  last = 0.0
  if not os.path.exists(path):
    return last
  with open(path) as f:
    for line in f:
      try:
        record = json.loads(line)
      except json.JSONDecodeError:  # a line cut by a kill: the records before it stand
        continue
      if "wall_s" in record:
        last = float(record["wall_s"])
  return last


def _record_emergence(workdir: str) -> None:
  """Writes DIR/emergence.json (time to decomposition, the curves) and logs its summary. A bad
  metrics log must not turn a finished run into a failed one, so errors become a warning."""
  try:
    result = emergence.write_emergence(workdir)
  except (OSError, ValueError) as e:
    logging.warning("emergence.json not written: %s", e)
    return
  for line in result.get("summary", []):
    logging.info("%s", line)


MACHINES_FILE = "machines.jsonl"


def _record_machine(workdir: str, step: int) -> None:
  """Appends where this session of the run trains (CPU, its extensions, JAX's device, the commit)
  to DIR/machines.jsonl: a run's wall time means little without its hosts, and a resumed or
  restarted run may have trained on several. The file stays in the run folder across restarts,
  as the wall clock does."""
  record = dict(step=int(step), time=time.time(), **provenance.cpu_info(),
                **provenance.device_info(), git_commit=provenance.git_commit())
  with open(os.path.join(workdir, MACHINES_FILE), "a") as f:
    f.write(json.dumps(record) + "\n")


def _process_local(tree):
  """This process's copy of a replicated tree: with several processes, validation renders on the
  local device alone (the same program and numbers as on one process, with no cross-process step
  in it); with one process, the tree itself, as before."""
  if jax.process_count() == 1:
    return tree
  return jax.tree.map(lambda x: x.addressable_data(0), tree)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str) -> dict:
  """Trains (or resumes) the run in `workdir`; returns the last validation metrics.

  With `train.restarts` > 0, an attempt that validation finds collapsed once the schedules have
  settled, or scoring below `train.restart_min_score` at `train.restart_check_step`, is moved to
  workdir/restarted/seed_<seed>/ and trained again from a new seed (slotlifter_jax/restarts.py).
  """
  # Nothing is created until the config and the data are known to be good.
  if os.path.exists(workdir) and not os.path.isdir(workdir):
    raise FileExistsError(f"{workdir}: exists and is not a directory; choose another --workdir")
  config_checks.check_config(config)
  saved = ckpt_lib.load_saved_config(workdir)
  ckpt_lib.check_compatible(config, saved, workdir)
  # After a restart the folder holds an attempt with another seed: resuming continues it exactly.
  config = restarts.resumed_seed(config, saved, workdir)
  # Process 0 generates an absent embedded set and the others then read it. The barrier in it also
  # means that every process has read config.json (above) before process 0 rewrites it (below).
  config = multihost.primary_first(lambda: embedded.resolve_data(config), "data")
  train_scenes = registry.load_split(config.data, "train")
  val_scenes = registry.load_split(config.data, "val")
  logging.info("data: %d train / %d val scenes from %s", len(train_scenes), len(val_scenes),
               config.data.root)

  mesh = step_lib.make_mesh()
  n_dev = mesh.devices.size
  if config.train.batch_scenes % n_dev:
    raise ConfigError(f"train.batch_scenes={config.train.batch_scenes} must be a multiple of the "
                     f"{n_dev} devices")
  try:
    sampler = pipeline.BatchSampler(
        train_scenes, num_source_views=config.data.num_source_views,
        batch_scenes=config.train.batch_scenes, rays_per_scene=config.train.rays_per_scene,
        novel_ray_prob=config.data.novel_ray_prob, seed=config.seed,
        ray_sampling=config.data.ray_sampling, contrast_mix=config.data.contrast_mix,
        scene_stages=config.data.get("scene_stages", ()),
        ray_stages=config.train.get("ray_stages", ()))  # vetted by check_config above
  except ValueError as e:
    raise ConfigError(str(e)) from e
  on_device = _on_device(config, train_scenes)
  if multihost.is_primary():
    ckpt_lib.save_config(config, workdir, step=ckpt_lib.latest_step_on_disk(workdir))
  model = model_lib.build_model(config)
  key = jax.random.key(config.seed, impl=config.train.prng_impl)
  first_batch = sampler.batch(0)
  replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
  shapes = step_lib.state_shapes(model, config, first_batch, sharding=replicated)
  num_params = sum(x.size for x in jax.tree.leaves(shapes.params))
  logging.info("model: %s parameters", f"{num_params:,}")

  # Every process opens the managers (orbax creates the folders on process 0 and waits for it).
  checkpoints = ckpt_lib.Checkpoints(workdir, keep=config.train.keep_checkpoints)
  if checkpoints.latest_step() is not None:  # restored straight into the replicated layout
    # Into shapes, not into initialised weights: a resume compiles and runs no init.
    state = checkpoints.restore(shapes)
    logging.info("resumed from step %d", int(state.step))
  else:
    state = jax.device_put(
        step_lib.init_state(model, config, first_batch, jax.random.fold_in(key, 0)), replicated)
  block = int(config.train.get("steps_per_dispatch", 1))
  if on_device:
    device_scenes = jax.device_put(
        device_sampler.to_device_scenes(train_scenes, num_source_views=config.data.num_source_views),
        replicated)
    blocks = {}  # block length → compiled block (a resume off the block grid needs length 1 once)
    def run_block(state, n):
      if n not in blocks:
        blocks[n] = step_lib.make_train_block(
            model, config, key=jax.random.fold_in(key, 1), data_key=jax.random.fold_in(key, 2),
            num_steps=n, mesh=mesh)
      return blocks[n](state, device_scenes)
  else:
    train_step = step_lib.make_train_step(model, config, key=jax.random.fold_in(key, 1), mesh=mesh)
  # Each process gathers only its scenes of every batch (all of them when it is the only one).
  rows = None if jax.process_count() == 1 else multihost.local_rows(
      step_lib.batch_sharding(mesh), config.train.batch_scenes)
  primary = multihost.is_primary()
  validator = validation.Validator(model, config, val_scenes[:config.train.eval_scenes], workdir,
                                   write_pictures=primary)
  writer = MetricWriter(workdir) if primary else _NoWriter()

  start = int(state.step)
  total = config.train.num_steps
  if primary:
    _record_machine(workdir, start)
  last_val = {}
  restart = None  # why this attempt gives way to a new seed
  interrupted = None
  batches = None if on_device else pipeline.prefetch(
      (sampler.batch(s, rows) for s in range(start, total)), size=2)
  clock = _RunClock(workdir)
  t_log = time.time()
  done = start
  try:
    with _StopFlag() as stop, tqdm(total=total, initial=start, desc="train", unit="step",
                                   dynamic_ncols=True, disable=not primary) as bar:
      while done < total:
        if on_device:
          n = block if done % block == 0 and done + block <= total else 1
          state, stacked = run_block(state, n)
          metrics = jax.tree.map(lambda x: x[-1], stacked)
          in_row_max = stacked["nonfinite_in_row"]
        else:
          n = 1
          batch = step_lib.assemble_batch(next(batches), mesh, config.train.batch_scenes)
          state, metrics = train_step(state, batch)
          in_row_max = metrics["nonfinite_in_row"]
        # Waiting for the new state before dispatching the next step keeps XLA from allocating
        # the next step's temp buffer while the last one is alive, which doubles RSS
        # (docs/performance.md §1).
        jax.block_until_ready(state.step)
        done += n
        bar.update(n)
        if done % config.train.log_every == 0 or done == total:
          m = jax.device_get(metrics)
          now = time.time()
          m["steps_per_sec"] = config.train.log_every / max(now - t_log, 1e-9)
          t_log = now
          m["wall_s"] = clock.elapsed()
          writer.write(done, "train", m)
          bar.set_postfix(loss=f"{m['loss']:.4f}", psnr=f"{m['psnr']:.2f}")
        in_row = int(np.max(jax.device_get(in_row_max)))
        if in_row:
          logging.warning("step %d: non-finite loss or gradient, update skipped (%d in a row)",
                          done, in_row)
          if in_row >= config.train.max_nonfinite_in_row:
            raise NonFiniteError(
                f"{in_row} non-finite steps in a row at step {done}; stopping. The last good "
                f"checkpoint in {workdir}/checkpoints is intact.")
        if done % config.train.eval_every == 0 or done == total:
          last_val = validator.run(
              _process_local(averaging.eval_params(state, config.train)), done)
          last_val["wall_s"] = clock.elapsed()
          last_val["num_val_scenes"] = len(validator.scenes)
          writer.write(done, "val", last_val)
          checkpoints.save_best(state, last_val["score"])
          if last_val.get("collapsed") == 1.0 and done >= collapse.settled_step(config.train):
            reasons = [k.removeprefix("collapse_") for k in ("collapse_dominant_slot",
                       "collapse_too_few_active", "collapse_near_uniform", "collapse_black")
                       if last_val.get(k) == 1.0]
            logging.warning("step %d: validation flags the run as collapsed (%s; largest slot "
                            "share %.2f, %.1f active slots)", done, ", ".join(reasons),
                            last_val.get("probe_largest_share", np.nan),
                            last_val.get("probe_active_slots", np.nan))
          if config.train.restarts > 0:
            restart = restarts.reason(config.train, done, last_val,
                                      has_masks=validator.has_masks)
            if restart:
              break
        if done % config.train.checkpoint_every == 0 or done == total:
          checkpoints.save(state)
        # A signal may reach one process only, or each at another step: all stop at the same step.
        signum = multihost.max_over_processes(stop.signal or 0)
        if signum:
          logging.warning("signal %d: checkpointing at step %d and exiting", signum, done)
          checkpoints.save(state, force=True)
          interrupted = Interrupted(signum, done)
          break
  finally:
    checkpoints.wait()
    checkpoints.close()
    writer.close()
    if batches is not None:
      batches.close()
  if primary:
    _record_emergence(workdir)
  if interrupted is not None:
    raise interrupted
  if restart:
    return train_and_evaluate(restarts.archive_and_reseed(config, workdir, done, restart), workdir)
  if last_val.get("collapsed") == 1.0:
    logging.warning("the run ends flagged as collapsed (see 'collapsed' in %s/metrics.jsonl)", workdir)
  return last_val
