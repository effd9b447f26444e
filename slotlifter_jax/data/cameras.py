"""NumPy camera handling on the data side: pose and intrinsics files, their conventions, projection
matrix decomposition, look-at poses, nearest-view selection and pixel rays.

Vocabulary: N views of a scene, R rays, H×W stored and h×w delivered image sizes. Conventions are
the model's (slotlifter_jax/__init__.py, docs/method.md §3.1): `cam_to_world` is a 4×4 OpenCV pose
(x right, y down, z forward), `intrinsics` a 3×3 pixel-unit K with pixel centres at integer
coordinates, so a pixel (u, v) = (column, row) back-projects to the camera ray K⁻¹[u, v, 1].

The model computes its own rays in JAX (`slotlifter_jax.geometry`); this NumPy twin exists so the
input pipeline can build batches on the host thread without touching the accelerator.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import numpy as np
import scipy.linalg

from slotlifter_jax.data.types import DataError

# A pose's rotation must satisfy |RᵀR − I| ≤ this elementwise and |det R − 1| ≤ this. Pose files are
# printed with ~6 decimals, so 1e-3 accepts honest rounding and rejects scaled or sheared matrices.
ROTATION_TOLERANCE = 1e-3
# The bottom row of a 4×4 pose must be (0, 0, 0, 1) to within this.
BOTTOM_ROW_TOLERANCE = 1e-6
# uORF renders: a 4:3 camera (350 px focal on 320×240) squeezed to a square (docs/method.md §3.1).
UORF_FOCAL_RATIO = (350.0 / 320.0, 350.0 / 240.0)  # (fx / W, fy / H)
# The official SlotLifter code builds uORF/uOCF intrinsics on a 256-pixel frustum and then scales
# them by size/256 without the half-pixel shift; `official_principal_point` reproduces that.
OFFICIAL_FRUSTUM = 256.0


def load_text_matrix(path: str, *, shapes: tuple[tuple[int, int], ...]) -> np.ndarray:
  """A whitespace-separated text matrix whose shape is one of `shapes`, float64 (may be non-finite)."""
  if not os.path.isfile(path):
    raise DataError(f"{path}: file does not exist")
  try:
    matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
  except ValueError as e:
    raise DataError(f"{path}: not a numeric text matrix ({e})") from e
  if matrix.shape not in shapes:
    expected = " or ".join(f"{a}×{b}" for a, b in shapes)
    raise DataError(f"{path}: expected a {expected} matrix, found shape {matrix.shape}")
  return matrix


def read_matrix(path: str, *, shape: tuple[int, int]) -> np.ndarray:
  """A whitespace-separated text matrix of the given shape, float64, finite."""
  matrix = load_text_matrix(path, shapes=(shape,))
  if not np.all(np.isfinite(matrix)):
    raise DataError(f"{path}: matrix has non-finite entries")
  return matrix


def check_pose(pose: np.ndarray, *, source: str) -> np.ndarray:
  """Raises DataError (naming `source`) unless `pose` is a finite rigid 4×4 with det R = +1."""
  if pose.shape != (4, 4):
    raise DataError(f"{source}: pose must be 4×4, found shape {pose.shape}")
  if not np.all(np.isfinite(pose)):
    raise DataError(f"{source}: pose has non-finite entries")
  if np.max(np.abs(pose[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > BOTTOM_ROW_TOLERANCE:
    raise DataError(f"{source}: pose bottom row is {pose[3].tolist()}, expected [0, 0, 0, 1]")
  rotation = pose[:3, :3]
  off = np.max(np.abs(rotation.T @ rotation - np.eye(3)))
  if off > ROTATION_TOLERANCE:
    raise DataError(f"{source}: rotation is not orthonormal (max |RᵀR − I| = {off:.3g} > "
                    f"{ROTATION_TOLERANCE})")
  det = np.linalg.det(rotation)
  if abs(det - 1.0) > ROTATION_TOLERANCE:
    raise DataError(f"{source}: rotation has determinant {det:.6f}, expected +1 (a reflection or "
                    f"a scaled matrix)")
  return pose


def read_pose(path: str) -> np.ndarray:
  """A validated 4×4 cam2world pose from a text file, float64 (units as stored)."""
  return check_pose(read_matrix(path, shape=(4, 4)), source=path)


def scale_translation(pose: np.ndarray, scene_scale: float) -> np.ndarray:
  """[..., 4, 4] pose with its translation times `scene_scale` (world → normalised frame)."""
  out = np.array(pose, dtype=np.float64, copy=True)
  out[..., :3, 3] *= scene_scale
  return out


def look_at_cam_to_world(eye: np.ndarray, target: np.ndarray = np.zeros(3)) -> np.ndarray:
  """OpenCV cam2world [4, 4] (x right, y down, z forward) looking from `eye` at `target`, z up."""
  forward = target - eye
  forward = forward / np.linalg.norm(forward)
  right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
  right = right / np.linalg.norm(right)
  down = np.cross(forward, right)
  m = np.eye(4)
  m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, forward, eye
  return m


def uorf_intrinsics(*, height: int, width: int,
                    official_principal_point: bool = False) -> np.ndarray:
  """The uORF camera at h×w: fx = 1.09375·w, fy = 1.458333·h, principal point ((w−1)/2, (h−1)/2).

  With `official_principal_point` the principal point is the official code's 127.5·w/256 (63.75 at
  w = 128, i.e. w/2 − 0.25), a quarter pixel off the image centre.
  """
  if official_principal_point:
    cx = (OFFICIAL_FRUSTUM - 1.0) / 2.0 * width / OFFICIAL_FRUSTUM
    cy = (OFFICIAL_FRUSTUM - 1.0) / 2.0 * height / OFFICIAL_FRUSTUM
  else:
    cx, cy = (width - 1.0) / 2.0, (height - 1.0) / 2.0
  return np.array([[UORF_FOCAL_RATIO[0] * width, 0.0, cx],
                   [0.0, UORF_FOCAL_RATIO[1] * height, cy],
                   [0.0, 0.0, 1.0]])


def read_normalised_intrinsics(path: str) -> np.ndarray:
  """A uOCF `_intrinsics.txt` (3×3, or 4×4 whose top-left 3×3 is used), validated, float64."""
  k = load_text_matrix(path, shapes=((3, 3), (4, 4)))[:3, :3]
  if not np.all(np.isfinite(k)):
    raise DataError(f"{path}: intrinsics have non-finite entries")
  if k[0, 0] <= 0 or k[1, 1] <= 0 or np.any(k[2] != np.array([0.0, 0.0, 1.0])) or k[1, 0] != 0:
    raise DataError(f"{path}: not a normalised pinhole K (need f'x, f'y > 0 and rows "
                    f"[f'x s c'x], [0 f'y c'y], [0 0 1]); found {k.tolist()}")
  return k


def intrinsics_from_normalised(k_norm: np.ndarray, *, height: int, width: int,
                               official_principal_point: bool = False) -> np.ndarray:
  """Pixel K at H×W from a normalised K (f'x = fx/W, f'y = fy/H, c'x = 2cx/W − 1, c'y = 2cy/H − 1).

  This inverts our generator's contract (docs/method.md §3.3). `official_principal_point` instead
  applies the official reader, cx = ((c'x + 1)·256 − 1)/2 · W/256, which sits W/512 px lower.
  """
  fx, fy = k_norm[0, 0] * width, k_norm[1, 1] * height
  skew = k_norm[0, 1] * width
  if official_principal_point:
    cx = ((k_norm[0, 2] + 1.0) * OFFICIAL_FRUSTUM - 1.0) / 2.0 * width / OFFICIAL_FRUSTUM
    cy = ((k_norm[1, 2] + 1.0) * OFFICIAL_FRUSTUM - 1.0) / 2.0 * height / OFFICIAL_FRUSTUM
  else:
    cx, cy = (k_norm[0, 2] + 1.0) * width / 2.0, (k_norm[1, 2] + 1.0) * height / 2.0
  return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(intrinsics: np.ndarray, *, stored: tuple[int, int],
                     size: tuple[int, int]) -> np.ndarray:
  """[..., 3, 3] K for an H×W image resized to h×w, pixel centres at integers.

  A coordinate x maps to (x + ½)·s − ½ with s = w/W (columns) or h/H (rows), so f' = f·s and
  c' = (c + ½)·s − ½; the skew scales with the column factor.
  """
  sy, sx = size[0] / stored[0], size[1] / stored[1]
  out = np.array(intrinsics, dtype=np.float64, copy=True)
  out[..., 0, 0] *= sx
  out[..., 0, 1] *= sx
  out[..., 1, 1] *= sy
  out[..., 0, 2] = (out[..., 0, 2] + 0.5) * sx - 0.5
  out[..., 1, 2] = (out[..., 1, 2] + 0.5) * sy - 0.5
  return out


@dataclasses.dataclass(frozen=True)
class ProjectionParts:
  """P ∝ K·[R | t]: x_pix ∝ K (R X + t)."""
  intrinsics: np.ndarray  # [3, 3] upper triangular, positive diagonal, K[2, 2] = 1
  rotation: np.ndarray  # [3, 3] world → camera, det +1
  translation: np.ndarray  # [3] world → camera


def decompose_projection(projection: np.ndarray) -> ProjectionParts:
  """Splits a 3×4 projection matrix (any nonzero scale, either sign) into K, R, t.

  RQ-decomposes the left 3×3 block, moves the signs of K's diagonal into R (K·D·D·R with D² = I),
  and flips the whole matrix when R came out a reflection (P and −P are the same camera).
  """
  projection = np.asarray(projection, dtype=np.float64)
  k, r = scipy.linalg.rq(projection[:, :3])
  signs = np.diag(np.where(np.diag(k) < 0, -1.0, 1.0))
  k, r = k @ signs, signs @ r
  t = np.linalg.solve(k, projection[:, 3])
  if np.linalg.det(r) < 0:  # P was given with a negative overall scale
    r, t = -r, -t
  return ProjectionParts(intrinsics=k / k[2, 2], rotation=r, translation=t)


def rigid_inverse(pose: np.ndarray) -> np.ndarray:
  """[..., 4, 4] inverse of a rigid transform: [Rᵀ | −Rᵀt]."""
  rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)
  out = np.zeros_like(pose)
  out[..., :3, :3] = rot_t
  out[..., :3, 3] = -np.einsum("...ij,...j->...i", rot_t, pose[..., :3, 3])
  out[..., 3, 3] = 1.0
  return out


def view_distances(*, cam_to_world: np.ndarray, target_idx: int) -> np.ndarray:
  """[N] 0.5·(rotation angle in rad) + 0.5·(camera-centre distance) from view `target_idx`.

  The "mix" distance of IBRNet / the official SlotLifter source selection (docs/method.md §3.4).
  """
  rotations = cam_to_world[:, :3, :3].astype(np.float64)  # [N, 3, 3]
  relative = np.einsum("ji,njk->nik", rotations[target_idx], rotations)  # R_tᵀ R_n: [N, 3, 3]
  cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0  # [N]
  angle = np.arccos(np.clip(cos, -1.0, 1.0))
  centres = cam_to_world[:, :3, 3].astype(np.float64)  # [N, 3]
  distance = np.linalg.norm(centres - centres[target_idx], axis=-1)
  return 0.5 * angle + 0.5 * distance


def nearest_sources(*, cam_to_world: np.ndarray, target_idx: int, pool: Sequence[int],
                    n: int = 4) -> tuple[int, ...]:
  """The `n` views of `pool` (the target itself excluded) nearest to the target, nearest first.

  Ties go to the lower view index, so the choice is a pure function of the poses.
  """
  candidates = np.array(sorted(set(int(i) for i in pool) - {int(target_idx)}), dtype=np.int64)
  if len(candidates) < n:
    raise ValueError(f"view {target_idx}: only {len(candidates)} candidate source views in the "
                     f"pool, {n} needed")
  dist = view_distances(cam_to_world=cam_to_world, target_idx=target_idx)[candidates]
  order = np.argsort(dist, kind="stable")[:n]
  return tuple(int(i) for i in candidates[order])


def azimuth_rotation(angle: float) -> np.ndarray:
  """[4, 4] rotation by `angle` (radians, counter-clockwise seen from above) about the world z axis."""
  c, s = np.cos(angle), np.sin(angle)
  m = np.eye(4)
  m[:2, :2] = [[c, -s], [s, c]]
  return m


def source_azimuth_frame(cam_to_world: np.ndarray, *, source_idx: int) -> np.ndarray:
  """[N, 4, 4] poses of a scene turned about the world z axis so view `source_idx` sits at
  azimuth 0 (its camera centre in the x–z half-plane with x > 0).

  The scene itself is unchanged: every camera turns by the same angle about the vertical axis
  through the scene's centre, so images, depths and masks stay valid and the floor stays at z = 0.
  What changes is the frame in which the model sees 3D positions: a direction in it now means
  the same thing relative to the source view in every scene (uORF's non-fixed locality, which
  expresses coordinates in the input view's azimuth frame, for the same reason).
  """
  poses = np.asarray(cam_to_world, dtype=np.float64)
  x, y = poses[source_idx, 0, 3], poses[source_idx, 1, 3]
  if np.hypot(x, y) < 1e-9:
    raise ValueError(f"view {source_idx}: the camera sits on the vertical axis, so it has no "
                     f"azimuth to turn to 0")
  return np.einsum("ij,njk->nik", azimuth_rotation(-np.arctan2(y, x)), poses)
