"""Where the visible surfaces of an embedded set lie in the model's normalised frame: the evidence
behind a config's `data.scene_z_range` (the slab `fast` samples rays in).

    python experiments/room_bounds.py [--config=configs/room_chair.py:scene] [--split=val]

Back-projects every pixel of the split's views with its stored depth and prints percentiles of the
height z of floor, wall and object points, the distance along the ray to the first surface
(against render.near and render.far), the horizontal radius of object points and the share of them
outside the locality box. Validation scenes by default: a bound chosen here reads no test scene.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from experiments import study_common  # noqa: E402
from slotlifter_jax import geometry  # noqa: E402
from slotlifter_jax.data import embedded  # noqa: E402
from slotlifter_jax.data import registry  # noqa: E402

PERCENTILES = (0, 1, 50, 99, 99.9, 100)
FLOOR_EPS = 1e-3  # normalised units: a background point this close to z = 0 is floor


def surface_points(scene) -> dict[str, np.ndarray]:
  """Per kind (floor, wall, object), the back-projected points [M, 3] and ray lengths [M]."""
  n, height, width, _ = scene.images.shape
  v, u = np.mgrid[0:height, 0:width].astype(np.float64)
  pix = np.stack([u, v], axis=-1)
  out = {k: ([], []) for k in ("floor", "wall", "object")}
  for a in range(n):
    dirs_cam = geometry.pix_to_cam(pix=pix, intrinsics=scene.intrinsics[a].astype(np.float64),
                                   xp=np)
    points_cam = dirs_cam * scene.depth[a][..., None]
    pose = scene.cam_to_world[a].astype(np.float64)
    points = points_cam @ pose[:3, :3].T + pose[:3, 3]
    lengths = np.linalg.norm(points_cam, axis=-1)
    background = scene.masks[a] == 0
    kinds = {"floor": background & (np.abs(points[..., 2]) < FLOOR_EPS),
             "wall": background & (np.abs(points[..., 2]) >= FLOOR_EPS),
             "object": scene.masks[a] > 0}
    for kind, where in kinds.items():
      out[kind][0].append(points[where])
      out[kind][1].append(lengths[where])
  return {k: (np.concatenate(p), np.concatenate(t)) for k, (p, t) in out.items()}


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--config", default="configs/room_chair.py:scene")
  parser.add_argument("--split", default="val")
  parser.add_argument("--scenes", type=int, default=100)
  args = parser.parse_args(argv)
  config = embedded.resolve_data(study_common.load_config(args.config))
  scenes = registry.load_split(config.data, args.split, max_scenes=args.scenes)
  if any(s.depth is None or s.masks is None for s in scenes):
    print(f"error: {config.data.root}: the {args.split} split has no depth or masks",
          file=sys.stderr)
    return 1
  parts = [surface_points(s) for s in scenes]
  print(f"{len(scenes)} {args.split} scenes of {config.data.root}; percentiles {PERCENTILES}")
  for kind in ("floor", "wall", "object"):
    points = np.concatenate([p[kind][0] for p in parts])
    if not len(points):
      print(f"{kind:6s}: none")
      continue
    print(f"{kind:6s} z:      {np.round(np.percentile(points[:, 2], PERCENTILES), 3)} "
          f"({len(points)} pixels)")
  lengths = np.concatenate([p[k][1] for p in parts for k in p])
  print(f"ray length: {np.round(np.percentile(lengths, PERCENTILES), 3)} "
        f"(render.near {config.render.near:.3f}, render.far {config.render.far:.3f})")
  objects = np.concatenate([p["object"][0] for p in parts])
  print(f"object radius: {np.round(np.percentile(np.linalg.norm(objects[:, :2], axis=1), PERCENTILES), 3)}; "
        f"largest |x|, |y|: {np.round(np.abs(objects[:, :2]).max(axis=0), 3)} "
        f"(model.locality_box {config.model.locality_box})")
  # The box acts on every coordinate of the points the model sees (the config's frame), where
  # only the first slots may take a point outside it while the locality steps last.
  outside = np.any(np.abs(objects) > config.model.locality_box, axis=1)
  print(f"object pixels outside the locality box (any |coordinate| > "
        f"{config.model.locality_box}, frame {config.data.frame}): {100 * outside.mean():.2f} %")
  print(f"data.scene_z_range of this config: {tuple(config.data.scene_z_range)}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
