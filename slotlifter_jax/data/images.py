"""Image files on disk and the resampling every reader shares.

Vocabulary: H×W an image as stored on disk, h×w the size a reader delivers (`data.image_size`),
C channels. Pixel centres sit at integer coordinates (slotlifter_jax/__init__.py): pixel i of an
n-pixel row covers [i − ½, i + ½], so the row spans [−½, n − ½] and a resize by s = h/H maps a
coordinate x to (x + ½)·s − ½ (`cameras.scale_intrinsics` applies the same map to K).

Downsampling never invents data. Colour is area-averaged: an output pixel is the mean of the input
area it covers (a box filter when the factor is an integer; cv2's INTER_AREA), so an f×f block of
input pixels becomes exactly the output pixel whose centre the intrinsics map the block's centre to.
Labels and depth take the single input sample that contains the output pixel's centre, so a label
stays a label and a depth stays a surface depth.

Every failure to read a file raises `DataError` naming the file; nothing here ever writes.
"""

from __future__ import annotations

import contextlib
import os
from typing import Iterator, Sequence, Union

import numpy as np
from PIL import Image

from slotlifter_jax.data.types import DataError

# What PIL raises for missing, truncated or garbage image files.
_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, Image.DecompressionBombError)

ImageSize = Union[None, int, Sequence[int]]


@contextlib.contextmanager
def _opened(path: str) -> Iterator[Image.Image]:
  """Opens and fully decodes an image, turning every decoder failure into a DataError."""
  if not os.path.isfile(path):
    raise DataError(f"{path}: image file does not exist")
  try:
    with Image.open(path) as img:
      img.load()  # decode now: a truncated file fails here rather than later, half-read
      yield img
  except DataError:
    raise
  except _IMAGE_ERRORS as e:
    raise DataError(f"{path}: unreadable or corrupt image ({type(e).__name__}: {e})") from e


def stored_size(path: str) -> tuple[int, int]:
  """(H, W) from the file header alone (no decode)."""
  if not os.path.isfile(path):
    raise DataError(f"{path}: image file does not exist")
  try:
    with Image.open(path) as img:
      width, height = img.size
  except _IMAGE_ERRORS as e:
    raise DataError(f"{path}: unreadable or corrupt image ({type(e).__name__}: {e})") from e
  return height, width


def read_rgb(path: str) -> np.ndarray:
  """[H, W, 3] float32 in [0, 1]. Grey and palette images are expanded, an alpha channel dropped."""
  with _opened(path) as img:
    return np.asarray(img.convert("RGB"), dtype=np.float32) / np.float32(255.0)


def read_luma(path: str) -> np.ndarray:
  """[H, W] uint8: RGB → L with PIL's ITU-R 601-2 luma, exactly as uORF converts its masks."""
  with _opened(path) as img:
    return np.asarray(img.convert("RGB").convert("L"), dtype=np.uint8)


def read_grey_rgb(path: str) -> np.ndarray:
  """[H, W] uint8 from an RGB image whose pixels are all grey (g, g, g); anything else is an error.
  """
  with _opened(path) as img:
    rgb = np.asarray(img.convert("RGB"), dtype=np.uint8)  # [H, W, 3]
  coloured = np.any(rgb != rgb[..., :1], axis=-1)  # [H, W]
  if np.any(coloured):
    r, c = np.argwhere(coloured)[0]
    raise DataError(f"{path}: {int(coloured.sum())} pixels are not grey (first at row {r}, column "
                    f"{c}: RGB {tuple(int(x) for x in rgb[r, c])}); masks draw label l as "
                    f"(g, g, g)")
  return rgb[..., 0]


def read_labels(path: str) -> np.ndarray:
  """[H, W] int32 from a single-channel integer image (8- or 16-bit), values as stored."""
  with _opened(path) as img:
    if img.mode not in ("L", "P", "I", "I;16", "I;16B", "I;16L", "1"):
      raise DataError(f"{path}: label image has mode {img.mode!r}; expected one integer channel")
    return np.asarray(img, dtype=np.int64).astype(np.int32)


def output_size(*, requested: ImageSize, stored: tuple[int, int], path: str) -> tuple[int, int]:
  """The delivered (h, w) for `data.image_size` given the stored (H, W).

  `requested` is 0 / None (as stored), an int n (n × n; only for square images, as a square size
  for a non-square set is ambiguous), or an (h, w) pair. Readers only ever downsample.
  """
  height, width = stored
  if requested is None or (np.ndim(requested) == 0 and int(requested) == 0):
    return height, width
  if np.ndim(requested) == 0:
    n = int(requested)
    if height != width:
      raise DataError(f"{path}: data.image_size={n} asks for a square image but the stored images "
                      f"are {height}×{width} (H×W); set data.image_size to (h, w) or 0 (as stored)")
    size = (n, n)
  else:
    if len(requested) != 2:
      raise DataError(f"{path}: data.image_size={tuple(requested)} must be an int or (h, w)")
    size = (int(requested[0]), int(requested[1]))
  if size[0] <= 0 or size[1] <= 0 or size[0] > height or size[1] > width:
    raise DataError(f"{path}: data.image_size {size[0]}×{size[1]} is not within the stored size "
                    f"{height}×{width}; readers only downsample")
  return size


def _area_along(x: np.ndarray, n_out: int) -> np.ndarray:
  """Area-averages axis 0 of `x` from n_in to n_out samples: [n_in, ...] → [n_out, ...].

  Input sample i is the constant value on [i, i + 1] (edge coordinates); output sample j is its
  mean over [j·f, (j + 1)·f], f = n_in / n_out, read off the running integral, which is exactly
  linear between integer edges. No BLAS: tiny multithreaded matmuls stall on a busy host.
  """
  n_in = x.shape[0]
  integral = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0, dtype=np.float64)])
  edges = np.arange(n_out + 1, dtype=np.float64) * (n_in / n_out)  # [n_out + 1]
  left = np.minimum(np.floor(edges).astype(np.int64), n_in - 1)
  frac = (edges - left).reshape((-1,) + (1,) * (x.ndim - 1))
  at_edges = integral[left] + frac * (integral[left + 1] - integral[left])  # [n_out + 1, ...]
  return (at_edges[1:] - at_edges[:-1]) / (n_in / n_out)


def nearest_indices(n_in: int, n_out: int) -> np.ndarray:
  """[n_out] the input sample that contains each output pixel's centre.

  The centre of output pixel j lies at (j + ½)·n_in/n_out in edge coordinates; integer arithmetic
  keeps the choice exact (factor 2 picks the second of each pair, factor 3 the middle one).
  """
  j = np.arange(n_out, dtype=np.int64)
  return np.minimum(((2 * j + 1) * n_in) // (2 * n_out), n_in - 1)


def downsample_area(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """[H, W, ...] → [h, w, ...] by area averaging; returns the input unchanged when sizes match."""
  height, width = image.shape[:2]
  if (height, width) == tuple(size):
    return image
  out = _area_along(image, size[0])  # [h, W, ...]
  out = np.swapaxes(_area_along(np.swapaxes(out, 0, 1), size[1]), 0, 1)  # [h, w, ...]
  return out.astype(image.dtype)


def resample_nearest(array: np.ndarray, size: tuple[int, int]) -> np.ndarray:
  """[H, W, ...] → [h, w, ...] taking the input sample under each output centre (labels, depth).

  Also valid for enlarging (ScanNet instance images may be stored smaller than the colour frames).
  """
  height, width = array.shape[:2]
  if (height, width) == tuple(size):
    return array
  return array[nearest_indices(height, size[0])][:, nearest_indices(width, size[1])]
