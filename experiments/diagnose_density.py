"""Where does a run put its density? `python experiments/diagnose_density.py CONFIG RUN_DIR [SCENE [SPLIT]]`.

Example: python experiments/diagnose_density.py configs/clevr.py:paper_cpu runs/clevr_paper_cpu
Prints, for one validation scene's first novel view rendered from the run's latest checkpoint, the
mean rendered depth against the near plane (a run stuck in the "fog" solution renders everything
at the first sample, depth = near), the slot that owns each pixel, and σ, the empty-slot weight W_0
and the render weights along three rays.
"""

import importlib.util
import sys

import jax.numpy as jnp
import numpy as np

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import geometry
from slotlifter_jax import model as model_lib
from slotlifter_jax.data import embedded
from slotlifter_jax.data import registry
from slotlifter_jax.rendering import views as views_lib


def load_config(arg: str):
  path, _, variant = arg.partition(":")
  spec = importlib.util.spec_from_file_location("config", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


def main(config_arg: str, run_dir: str, scene_index: int = 0, split: str = "val") -> None:
  config = embedded.resolve_data(load_config(config_arg))
  scene = registry.load_split(config.data, split, max_scenes=scene_index + 1)[scene_index]
  model = model_lib.build_model(config)
  abstract = ckpt_lib.abstract_state(model, config, scene)  # shapes only: nothing is initialised
  manager = ckpt_lib.Checkpoints(run_dir)
  state = manager.restore(abstract)
  manager.close()
  params, view = state.params, scene.novel_indices[0]
  renderer = views_lib.SceneRenderer(model, config)
  np.set_printoptions(precision=3, suppress=True, linewidth=200)
  print(f"step {int(state.step)}, scene {scene.name}, view {view}, near {config.render.near:.3f}")
  for locality in (True, False):
    out = renderer.render(params, scene, [view], locality=locality)
    psnr = -10 * np.log10(np.mean((out.colour[0] - scene.images[view]) ** 2))
    owners = np.bincount(out.segmentation[0].argmax(-1).ravel(), minlength=config.model.num_slots)
    print(f"locality={locality}: depth mean {out.depth.mean():.3f} (min {out.depth.min():.3f}), "
          f"PSNR {psnr:.2f}, pixels per slot {owners}")
  sources = renderer.sources(scene)
  encoded = renderer._encode(params, sources)
  height, width = scene.image_size
  pix = jnp.asarray([[width / 2, height / 2], [width / 6, height / 6], [5 * width / 6, 5 * height / 6]])
  rays = geometry.pixel_rays(cam_to_world=jnp.asarray(scene.cam_to_world[view]),
                             intrinsics=jnp.asarray(scene.intrinsics[view]), pix=pix)
  out = model.apply({"params": params}, encoded, **sources, ray_origins=rays.origins[None],
                    ray_directions=rays.directions[None], keep_ratio=1.0, locality=True,
                    train=False, method=model.render_rays)
  print("z      ", np.asarray(out.z[0, 0]))
  for i in range(pix.shape[0]):
    print(f"ray {i} sigma  ", np.asarray(out.density[0, i]))
    print(f"ray {i} W_0    ", np.asarray(out.point_slot_weights[0, i, :, 0]))
    print(f"ray {i} weights", np.asarray(out.coarse.weights[0, i]))


if __name__ == "__main__":
  main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 0,
       sys.argv[4] if len(sys.argv) > 4 else "val")
