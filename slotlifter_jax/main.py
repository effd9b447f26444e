"""Command line: `python -m slotlifter_jax.main --config=configs/clevr.py[:variant] --workdir=DIR`.

Modes: train (default; resumes from DIR's last checkpoint), eval (metrics of a split into
DIR/eval/<split>/), render (panels and orbit GIFs of chosen scenes into DIR/render/<split>/).
  --mode=eval --split=test --checkpoint=best|latest|<step> [--overwrite] [--max_scenes=N]
              [--lpips_quirk] [--nv_ari_last_view] [--params=average|trained]
  --mode=render --split=test --scenes=0,3,5 --orbit_frames=24
  --mode=edit --split=test [--max_scenes=N] [--overwrite]  (object edits scored, docs/editing.md)
  --mode=edit --scenes=0,3 --remove_slot=K | --move_slot=K --by=dx,dy,dz  (pictures of one edit)
Several processes (one per host or per GPU): the same command on each, with --distributed and
  --coordinator_address=HOST:PORT --num_processes=N --process_id=I (or JAX_COORDINATOR_ADDRESS;
  under SLURM or Open MPI jax finds all three itself); process 0 writes the files.
"""

import sys

from absl import app, flags, logging
from ml_collections import config_flags

from slotlifter_jax import config_checks
from slotlifter_jax import runtime

config_flags.DEFINE_config_file("config", None, "Config file, e.g. configs/clevr.py:paper_cpu.",
                                lock_config=True)
flags.DEFINE_string("workdir", None, "Run directory: checkpoints, metrics, pictures.")
flags.DEFINE_enum("mode", "train", ["train", "eval", "render", "edit"], "What to do.")
flags.DEFINE_bool("distributed", False, "Call jax.distributed.initialize(): one of several "
                  "processes training one run (slotlifter_jax/multihost.py).")
flags.DEFINE_string("coordinator_address", None, "--distributed: HOST:PORT of process 0's "
                    "coordinator (default: $JAX_COORDINATOR_ADDRESS, or detected by jax).")
flags.DEFINE_integer("num_processes", None, "--distributed: number of processes (default: "
                     "detected by jax, e.g. under SLURM).")
flags.DEFINE_integer("process_id", None, "--distributed: this process's index, 0 … N−1 "
                     "(default: detected by jax).")
flags.DEFINE_enum("split", "test", ["train", "val", "dev", "test"], "eval/render: which split "
                  "(dev: the embedded sets' development split; test: held out).")
flags.DEFINE_string("checkpoint", "", "eval/render: best, latest or a step (default: best if "
                    "the run has one, else latest).")
flags.DEFINE_bool("overwrite", False, "eval: replace an existing DIR/eval/<split>/metrics.json.")
flags.DEFINE_integer("max_scenes", None, "eval: only the first N scenes of the split.")
flags.DEFINE_bool("lpips_quirk", False, "eval: feed [0, 1] images to LPIPS as the official code "
                  "does (docs/method.md §8).")
flags.DEFINE_bool("nv_ari_last_view", False, "eval: NV-ARI from the last novel view only, as "
                  "uORF (docs/method.md §8).")
flags.DEFINE_enum("params", "average", ["average", "trained"], "eval/render: a run that keeps "
                  "an average of its parameters (train.ema_decay > 0) is evaluated with the "
                  "average unless this says trained.")
flags.DEFINE_string("scenes", "0", "render: comma-separated scene indices into the split.")
flags.DEFINE_integer("orbit_frames", 24, "render: frames of the orbit GIF (at most 64).")
flags.DEFINE_integer("remove_slot", None, "edit: render the chosen --scenes without this slot "
                     "(0 … K-1) instead of scoring the split's object edits.")
flags.DEFINE_integer("move_slot", None, "edit: render the chosen --scenes with this slot moved "
                     "by --by.")
flags.DEFINE_string("by", "", "edit: --move_slot's translation dx,dy,dz in the data set's world "
                    "units and axes.")
flags.DEFINE_enum("removal", None, ["zero", "delete"], "edit: how a removed or moved slot "
                  "leaves its place: zero its density, or delete it from the slot set the "
                  "others are decoded with (default: edit_scores.REMOVAL; docs/editing.md §4).")
flags.DEFINE_enum("move_background", None, ["stay", "carry"], "edit: whether a moved slot "
                  "carries the background slot along the rays it covers (default: "
                  "edit_scores.MOVE_BACKGROUND; docs/editing.md §4).")
flags.DEFINE_enum("uncovered", None, ["black", "background"], "edit: what an edit shows where "
                  "it uncovers space the scene held opaque: the background slot's colour, or "
                  "black (default: edit_scores.UNCOVERED; docs/editing.md §4).")
flags.mark_flags_as_required(["config", "workdir"])
FLAGS = flags.FLAGS


def _quiet_orbax():
  """Orbax logs every file of every save at INFO through absl; keep only its warnings."""
  import logging as py_logging
  class _DropOrbaxInfo(py_logging.Filter):
    def filter(self, record):
      return record.levelno >= py_logging.WARNING or "/orbax/" not in record.pathname
  logging.get_absl_handler().addFilter(_DropOrbaxInfo())


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  _quiet_orbax()
  try:  # ml_collections defers a config file's load error to the first access
    FLAGS.config.keys()
  except Exception as e:  # noqa: BLE001
    sys.exit(f"error: --config={FLAGS['config'].config_filename}: cannot be loaded ({_one_line(e)})")
  if not FLAGS.distributed and any(
      FLAGS[f].present for f in ("coordinator_address", "num_processes", "process_id")):
    sys.exit("error: --coordinator_address, --num_processes and --process_id need --distributed")
  stray = [f for f in ("remove_slot", "move_slot", "by", "removal", "move_background",
                       "uncovered") if FLAGS[f].present]
  if stray and FLAGS.mode != "edit":
    sys.exit(f"error: --{stray[0]}: only with --mode=edit")
  # Before JAX starts (seconds on a CPU) and before the processes of a --distributed launch
  # connect: a bad field is reported at once, and by every process alike.
  try:
    config_checks.check_config(FLAGS.config)
  except config_checks.ConfigError as e:
    sys.exit(f"error (ConfigError): {e}")
  import jax
  if FLAGS.distributed:
    from slotlifter_jax import multihost
    multihost.initialize(FLAGS.coordinator_address, FLAGS.num_processes, FLAGS.process_id)
    if jax.process_index() != 0:  # process 0 logs the progress; the others only their warnings
      logging.set_verbosity(logging.WARNING)
  logging.info("JAX devices: %s (process %d of %d); %s", jax.devices(), jax.process_index(),
               jax.process_count(), runtime.describe())
  warning = runtime.slow_allocator_warning()
  if warning and jax.default_backend() == "cpu":
    logging.warning("%s", warning)
  from slotlifter_jax import checkpoints
  from slotlifter_jax.data.layout import ObjectOptionError
  from slotlifter_jax.data.types import DataError
  if FLAGS.mode == "train":
    from slotlifter_jax import train
    try:
      train.train_and_evaluate(FLAGS.config, FLAGS.workdir)
    except train.Interrupted as e:
      # Not a success: a script chaining `train && eval` must not go on.
      logging.warning("%s", e)
      sys.exit(128 + e.signum)
    except ObjectOptionError as e:  # the embedded set's options, read when it is generated
      sys.exit(f"error (data.{e.field}): {e}")
    except (train.ConfigError, checkpoints.CheckpointMismatchError, DataError,
            FileExistsError) as e:
      sys.exit(f"error ({type(e).__name__}): {e}")
    return
  from slotlifter_jax import evaluate
  from slotlifter_jax.rendering import pictures
  from slotlifter_jax import multihost
  say = print if multihost.is_primary() else (lambda *a: None)  # one table, not one per process
  try:
    if FLAGS.mode == "eval":
      result = evaluate.evaluate_split(
          FLAGS.config, FLAGS.workdir, split=FLAGS.split, checkpoint=FLAGS.checkpoint,
          overwrite=FLAGS.overwrite, max_scenes=FLAGS.max_scenes, lpips_quirk=FLAGS.lpips_quirk,
          nv_ari_last_view=FLAGS.nv_ari_last_view, params=FLAGS.params)
      say(evaluate.format_table(result))
    elif FLAGS.mode == "edit":
      from slotlifter_jax import edit, edit_eval
      try:
        say(edit_eval.run(FLAGS.config, FLAGS.workdir, split=FLAGS.split, scenes=FLAGS.scenes,
                          remove_slot=FLAGS.remove_slot, move_slot=FLAGS.move_slot, by=FLAGS.by,
                          checkpoint=FLAGS.checkpoint, params=FLAGS.params,
                          max_scenes=FLAGS.max_scenes, overwrite=FLAGS.overwrite,
                          orbit_frames=FLAGS.orbit_frames,
                          **({"removal": FLAGS.removal} if FLAGS.removal else {}),
                          **({"move_background": FLAGS.move_background}
                             if FLAGS.move_background else {}),
                          **({"uncovered": FLAGS.uncovered} if FLAGS.uncovered else {})))
      except edit.EditFlagError as e:
        sys.exit(f"error: {e}")  # the message starts with the flag
    else:
      for files in pictures.render_scenes(
          FLAGS.config, FLAGS.workdir, split=FLAGS.split,
          scene_indices=pictures.parse_scene_indices(FLAGS.scenes),
          checkpoint=FLAGS.checkpoint, num_orbit_frames=FLAGS.orbit_frames, params=FLAGS.params):
        say(f"scene {files.scene_index} ({files.scene_name}): {files.panel}\n  {files.orbit}")
  except ObjectOptionError as e:
    sys.exit(f"error (data.{e.field}): {e}")
  except (evaluate.EvalSetupError, checkpoints.CheckpointMismatchError, DataError,
          FileExistsError, FileNotFoundError) as e:
    # Expected mistakes get their message, not a traceback.
    sys.exit(f"error ({type(e).__name__}): {e}")


def _one_line(e: BaseException) -> str:
  """`e`'s most informative message in one line: ml_collections chains and escapes its messages
  (an override typo's "Did you mean …" sits in the middle of three)."""
  chain = [e]
  while chain[-1].__cause__ is not None or chain[-1].__context__ is not None:
    chain.append(chain[-1].__cause__ or chain[-1].__context__)
  clean = lambda x: " ".join(str(x).replace("\\n", " ").replace("\\'", "'").strip("'\"").split())
  if isinstance(e, flags.IllegalFlagValueError) and not str(e).startswith("flag --config"):
    # absl's own message names the flag and the value ("flag --params=mean: value should be …");
    # the innermost one does not. (--config's overrides keep ml_collections' chain, below.)
    return f"{type(e).__name__}: {' '.join(str(e).split())}"
  # The innermost message, unless it is ml_collections' bare KeyError behind the "Did you mean".
  best = next(x for x in reversed(chain) if not (isinstance(x, KeyError) and x is not chain[0]))
  return f"{type(chain[-1]).__name__}: {clean(best).replace(chr(39) + ' Did you', ' - did you')}"


def _parse_flags(argv):
  """absl's flag parsing, with a bad command line (an unknown variant, an override of a field
  that does not exist) reported in one line instead of chained tracebacks."""
  try:
    return FLAGS(argv)
  except Exception as e:  # noqa: BLE001 -- everything raised here comes from the command line
    sys.exit(f"error: bad command line ({_one_line(e)})")


if __name__ == "__main__":
  # Before JAX loads: a retaining allocator and XLA's CPU flags (slotlifter_jax/runtime.py).
  runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  app.run(main, flags_parser=_parse_flags)
