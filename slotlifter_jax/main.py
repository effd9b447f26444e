"""Command line: `python -m slotlifter_jax.main --config=configs/clevr.py[:variant] --workdir=DIR`.

Modes: train (default; resumes from DIR's last checkpoint), eval, render.
"""

from absl import app, flags, logging
from ml_collections import config_flags

config_flags.DEFINE_config_file("config", None, "Config file, e.g. configs/clevr.py:quick.",
                                lock_config=True)
flags.DEFINE_string("workdir", None, "Run directory: checkpoints, metrics, pictures.")
flags.DEFINE_enum("mode", "train", ["train", "eval", "render"], "What to do.")
flags.DEFINE_bool("distributed", False, "Call jax.distributed.initialize() (multi-host runs).")
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
  import jax
  if FLAGS.distributed:
    jax.distributed.initialize()
  logging.info("JAX devices: %s (process %d of %d)", jax.devices(), jax.process_index(),
               jax.process_count())
  if FLAGS.mode == "train":
    from slotlifter_jax import train
    train.train_and_evaluate(FLAGS.config, FLAGS.workdir)
  else:
    raise app.UsageError(f"--mode={FLAGS.mode} is not implemented yet")


if __name__ == "__main__":
  app.run(main)
