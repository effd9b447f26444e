"""Kitchen-Shiny (uOCF folder format). No ground-truth masks: segmentation metrics are never computed.

Paper: K = 5, 128×128, 1 source view; reference PSNR 32.02.
Run: python -m slotlifter_jax.main --config=configs/kitchen_shiny.py --config.data.root=/path/to/uocf --workdir=DIR
"""

from slotlifter_jax import defaults


def get_config(variant: str = ""):
  c = defaults.base_config()
  c.data.format = "uocf"
  c.data.family = "room"
  c.data.subset = "kitchen_shiny"
  c.data.has_masks = False
  c.model.num_slots = 5
  return defaults.apply_variant(c, variant)
