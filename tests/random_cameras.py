"""NumPy-only random cameras for the geometry / lifting tests (independent of the code under test)."""

import numpy as np


def look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
  """OpenCV cam2world [4, 4] at `centre` looking at `target` with world z up (x right, y down)."""
  forward = target - centre
  forward = forward / np.linalg.norm(forward)
  right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
  right = right / np.linalg.norm(right)
  down = np.cross(forward, right)
  pose = np.eye(4)
  pose[:3, :3] = np.stack([right, down, forward], axis=1)
  pose[:3, 3] = centre
  return pose


def random_cameras(rng: np.random.Generator, n: int, height: int, width: int):
  """n cameras on a sphere of radius ~1.8 looking near the origin, uORF-like intrinsics with a skew.

  Returns cam_to_world [n, 4, 4], intrinsics [n, 3, 3] (float64).
  """
  poses, ks = [], []
  for _ in range(n):
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = rng.uniform(0.3, 1.0)
    radius = rng.uniform(1.5, 2.1)
    centre = radius * np.array([np.cos(elevation) * np.cos(azimuth),
                                np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    poses.append(look_at(centre, rng.uniform(-0.2, 0.2, size=3)))
    k = np.array([[1.09375 * width * rng.uniform(0.9, 1.1), rng.uniform(-0.5, 0.5), (width - 1) / 2],
                  [0.0, 1.458333 * height * rng.uniform(0.9, 1.1), (height - 1) / 2],
                  [0.0, 0.0, 1.0]])
    ks.append(k)
  return np.stack(poses), np.stack(ks)
