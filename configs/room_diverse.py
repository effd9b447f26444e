"""Room-Diverse (uORF folder format, 5000 training scenes). Paper: K = 5, 128×128, 1 source view.

The real set must be given: --config.data.root=/path/to/uorf_data (holding room_diverse_{train,test});
with no root the embedded procedural `room` set stands in.
Run: python -m slotlifter_jax.main --config=configs/room_diverse.py --config.data.root=... --workdir=DIR
"""

from slotlifter_jax import defaults


def get_config(variant: str = ""):
  c = defaults.base_config()
  c.data.family = "room"
  c.data.subset = "room_diverse"
  c.data.num_train_scenes = 5000
  c.model.num_slots = 5
  return defaults.apply_variant(c, variant)
