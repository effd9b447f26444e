"""The in-memory scene structure every reader returns.

One `Scene` holds all N views of a scene in the *normalised scene frame* (docs/method.md §3.1):
positions already multiplied by the data set's scene scale (1/7 for the uORF-style sets), cameras
OpenCV cam2world, intrinsics in pixels of the stored image size.

Two kinds of scene share the structure:
- fixed sources (uORF/uOCF sets and our generated sets): `source_indices` are the model's input
  views and every view is a target (`target_indices` None);
- pooled sources (DTU, ScanNet training scenes): `source_indices` is empty, `target_indices` lists
  the views that may be targets and `source_pool` the views from which each target's sources are
  chosen, the nearest ones by `cameras.nearest_sources`. `pipeline.per_target_scenes` turns such a
  scene into fixed-source scenes (sources + one target) for evaluation.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np


class DataError(ValueError):
  """Bad input on disk; the message always names the offending file and what is wrong."""


class DataConfigError(DataError):
  """A `data.*` field whose value no reader accepts; the message names the field. A DataError, so
  every mode reports it in one line as it does a bad file."""


@dataclasses.dataclass(frozen=True)
class Scene:
  name: str
  images: np.ndarray  # [N, H, W, 3] float32 in [0, 1]
  cam_to_world: np.ndarray  # [N, 4, 4] float32, OpenCV convention, normalised scene frame
  intrinsics: np.ndarray  # [N, 3, 3] float32, pixel units of `images`
  source_indices: tuple[int, ...]  # which views are source views (uORF sets: (0,))
  masks: Optional[np.ndarray] = None  # [N, H, W] int32, 0 = background, None when the set has none
  mask_views: Optional[np.ndarray] = None  # [N] bool, which views have a ground-truth mask
  depth: Optional[np.ndarray] = None  # [N, H, W] float32 camera-z depth in the normalised frame
  objects: Optional[list] = None  # per-object metadata from dataset.json (positions in world units)
  target_indices: Optional[tuple[int, ...]] = None  # views that may be targets; None: all views
  source_pool: Optional[tuple[int, ...]] = None  # pooled sources (DTU/ScanNet); None: fixed sources
  view_names: Optional[tuple[str, ...]] = None  # the file stem of each view, for messages

  @property
  def num_views(self) -> int:
    return self.images.shape[0]

  @property
  def image_size(self) -> tuple[int, int]:
    return self.images.shape[1], self.images.shape[2]

  @property
  def novel_indices(self) -> tuple[int, ...]:
    targets = range(self.num_views) if self.target_indices is None else self.target_indices
    return tuple(i for i in targets if i not in self.source_indices)
