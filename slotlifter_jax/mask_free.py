"""The mask-free early check: whether a validation's mask-free statistics
(`validation.mask_free_statistics`) say an attempt has split, read from the model's outputs alone.

The restart check uses it on sets without masks (slotlifter_jax/restarts.py), and
`tools/early_check.py` measures it against the labelled check on validation logs. Slots in use
alone cannot tell objects from a floor spread over several slots; a spread floor shares its pixels
among them, which the per-pixel slot entropy reads (experiments/journal/2026-12.md, "A mask-free
check that reads the spread floor"). NumPy only, so the tools that read logs import no JAX.
"""

from typing import Optional

import numpy as np


def shortfall(val: dict, *, min_active_slots: float, max_pixel_entropy: float = 1.0,
              min_attn_agreement: float = -1.0) -> Optional[str]:
  """Why a validation's mask-free statistics say the attempt has not split, or None.

  Restarts when fewer than `min_active_slots` slots are in use (`mf_active_slots`), when the
  mean per-pixel slot entropy (`mf_pixel_entropy`, 0: every pixel in one slot, 1: shared evenly
  by all K) exceeds `max_pixel_entropy` (1: never), or when slot attention's grouping of the source
  view agrees with the rendered split of it less than `min_attn_agreement` (`mf_attn_agreement`,
  an adjusted Rand index; −1: never). A missing statistic (NaN: no novel view) restarts too:
  nothing says the run split."""
  used = float(val.get("mf_active_slots", np.nan))
  if not used >= min_active_slots:
    return (f"{used:.2f} slots in use on the validation views < "
            f"train.restart_min_active_slots={min_active_slots}")
  if max_pixel_entropy < 1.0:
    entropy = float(val.get("mf_pixel_entropy", np.nan))
    if not entropy <= max_pixel_entropy:
      return (f"per-pixel slot entropy {entropy:.2f} on the validation views > "
              f"train.restart_max_pixel_entropy={max_pixel_entropy}")
  if min_attn_agreement > -1.0:
    agreement = float(val.get("mf_attn_agreement", np.nan))
    if not agreement >= min_attn_agreement:
      return (f"slot attention agrees with the rendered split at {agreement:.2f} on the "
              f"validation source views < train.restart_min_attn_agreement={min_attn_agreement}")
  return None
