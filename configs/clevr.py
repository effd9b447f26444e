"""CLEVR-567 (uORF folder format), or the embedded procedural clevr set when data.root is empty.

Default = the paper's settings (docs/method.md §1–2): 128×128, 1 source view, K = 8, D = 64, 96
samples, 4 scenes × 1024 rays, 250k steps, locality for 50k steps.

Run:
  python -m slotlifter_jax.main --config=configs/clevr.py:scene --workdir=runs/clevr_scene
  python -m slotlifter_jax.main --config=configs/clevr.py --config.data.root=/path/to/clevr --workdir=...
Variants: `scene` (the scene-sized headline model: many cheap steps; formerly `fast`),
`paper_cpu` (the paper's model shrunk to a CPU, which does not split scenes; formerly `quick`),
`easy` (1–3 larger objects; compose as `scene+easy`), `smoke` (about a minute, for tests).
"""

from slotlifter_jax import defaults


def get_config(variant: str = ""):
  c = defaults.base_config()
  c.data.family = "clevr"
  c.data.subset = "clevr_567"
  c.model.num_slots = 8
  # Floor at z = 0; the tallest object (a large cube, 1.6× in the easy set) ends at z ≈ 0.32 in
  # the normalised frame; a margin on both sides leaves the floor's surface inside.
  c.data.scene_z_range = (-0.05, 0.45)
  return defaults.apply_variant(c, variant)


