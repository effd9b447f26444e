"""Room-Texture (uOCF folder format: normalised `_intrinsics.txt`, background = smallest grey level).

Paper: K = 5, 128×128, 1 source view.
Run: python -m slotlifter_jax.main --config=configs/room_texture.py --config.data.root=/path/to/uocf --workdir=DIR
"""

from slotlifter_jax import defaults


def get_config(variant: str = ""):
  c = defaults.base_config()
  c.data.format = "uocf"
  c.data.family = "room"
  c.data.subset = "room_texture"
  c.model.num_slots = 5
  return defaults.apply_variant(c, variant)
