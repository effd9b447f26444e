"""Pictures: segmentation colouring, depth colouring and image panels written as PNG."""

from __future__ import annotations

import os

import numpy as np
from PIL import Image

# A fixed palette so a slot keeps its colour across pictures; index 0 is used for slot 0 (the
# background slot when the locality constraint was on).
PALETTE = np.array([
    [70, 70, 70], [230, 25, 75], [60, 180, 75], [255, 225, 25], [0, 130, 200], [245, 130, 48],
    [145, 30, 180], [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212],
    [0, 128, 128], [220, 190, 255], [170, 110, 40], [255, 250, 200], [128, 0, 0],
], np.float32) / 255.0


def colour_labels(labels: np.ndarray) -> np.ndarray:
  """[..., ] int labels → [..., 3] RGB in [0, 1]."""
  return PALETTE[np.asarray(labels) % len(PALETTE)]


def colour_segmentation(segmentation: np.ndarray) -> np.ndarray:
  """[..., K] soft segmentation → [..., 3]: the palette mixed by the slot weights."""
  seg = np.asarray(segmentation, np.float32)
  k = seg.shape[-1]
  palette = PALETTE[np.arange(k) % len(PALETTE)]
  return np.clip(seg @ palette, 0.0, 1.0)


def colour_depth(depth: np.ndarray, *, near: float, far: float) -> np.ndarray:
  """[...] depth → [..., 3] grey, near bright, far dark."""
  d = np.clip((np.asarray(depth) - near) / max(far - near, 1e-6), 0.0, 1.0)
  return np.repeat((1.0 - d)[..., None], 3, axis=-1)


def grid(rows: list[list[np.ndarray]], *, pad: int = 2) -> np.ndarray:
  """Tiles equally sized [H, W, 3] images into one picture, rows × columns, white gaps."""
  h, w = rows[0][0].shape[:2]
  ncol = max(len(r) for r in rows)
  out = np.ones((len(rows) * (h + pad) - pad, ncol * (w + pad) - pad, 3), np.float32)
  for i, row in enumerate(rows):
    for j, img in enumerate(row):
      out[i * (h + pad):i * (h + pad) + h, j * (w + pad):j * (w + pad) + w] = img[..., :3]
  return out


def save_png(path: str, image: np.ndarray) -> None:
  """Writes a [H, W, 3] float image in [0, 1] (temp file + rename, so a reader never sees half)."""
  os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
  tmp = path + ".tmp.png"
  Image.fromarray((np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)).save(tmp)
  os.replace(tmp, path)
