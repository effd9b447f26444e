"""Scene generation and the data-set writer of the embedded generator (docs/method.md §3.2, §3.3,
§3.5): draw a layout and cameras until every object shows in the source view, render it, and write
a data set in the uORF folder format (see `generate_dataset`): per view `NNNNN_scSSSS_azAA.png`,
`_RT.txt` (OpenCV cam2world, world units), `_intrinsics.txt` (normalised K), `_depth.npy`
(camera-z depth, world units), `_mask.png` (label l drawn in grey `LABEL_GREY_STEP·l`), and per
split a `dataset.json`.

Everything that fixes which scene a file holds and its exact bytes outside the renderer lives here:
the per-scene random streams (so the output does not depend on the number of workers), the file
encodings, the dataset.json header and the multiprocessing pool. It is the top of the generator's
import graph: it uses `layout.py` (scenes, cameras) and the ray caster (`raycaster.py`,
`shading.py`), and nothing of them imports it.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import shutil
import time
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

from slotlifter_jax.data.layout import (BACKGROUND_LABEL, CAMERA_ELEVATION_DEG, CLEVR_SHAPES,
                                        CAMERA_ELEVATION_JITTER_DEG, CAMERA_RADIUS,
                                        CAMERA_RADIUS_JITTER, FAMILIES, GENERATOR_VERSION,
                                        LABEL_GREY_STEP, MAX_OBJECTS, ROOM_HALF_SIZE, SCENE_SCALE,
                                        SPLIT_STREAMS, SPLITS, SUBSETS, CameraSpec, SceneSpec,
                                        camera_to_world,
                                        check_object_options, is_default_objects,
                                        label_grey_levels, min_visible_pixels,
                                        normalised_intrinsics, num_source_views_for,
                                        object_count_range, object_family, sample_cameras,
                                        sample_clevr_layout,
                                        sample_room_layout, uorf_intrinsics)
from slotlifter_jax.data.raycaster import render_options, scene_arrays
from slotlifter_jax.data.shading import render_centre, render_views


# =============================================================================================
# One scene: sample, check visibility in the source view, render
# =============================================================================================


@dataclasses.dataclass(frozen=True)
class GeneratedScene:
  spec: SceneSpec
  cameras: tuple[CameraSpec, ...]
  cam_to_world: np.ndarray  # [N, 4, 4] float64, world units
  intrinsics: np.ndarray  # [3, 3] float64, pixels
  rgb: np.ndarray  # [N, H, W, 3] uint8
  label: np.ndarray  # [N, H, W] int32
  depth: np.ndarray  # [N, H, W] float32
  attempts: int  # layouts drawn before every object was visible in the source view


def scene_rng(*, seed: int, family: str, split: str, index: int) -> np.random.Generator:
  """Independent stream per (seed, family, split, scene index): order of workers cannot matter."""
  return np.random.default_rng(
      np.random.SeedSequence([seed, FAMILIES.index(family), SPLIT_STREAMS[split], index]))


def generate_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
                   supersample: int = 2, max_attempts: int = 100, min_objects: int = 0,
                   max_objects: int = 0, object_scale: float = 1.0,
                   plain_background: bool = False,
                   plain_objects: bool = False, no_walls: bool = False,
                   room_objects: str = "chairs", grey_floor: bool = False) -> GeneratedScene:
  """Samples layouts and cameras until every object covers enough pixels of view 0, then renders.

  `min_objects`, `max_objects` (0: the family's default count) and `object_scale` (room: ≤ 1)
  select an easier set; see `sample_clevr_layout`. `plain_background`, `plain_objects` (room
  only): the same scenes with untextured floor and walls, or chairs; `no_walls` (room only):
  without the walls; `room_objects` (room only): chairs, solid chairs or boxes
  (`sample_room_layout`).

  Renders on the CPU backend, so the files do not depend on the accelerator (if any) of the
  calling process, and a training process never shares its accelerator memory with the generator.
  A process started without a CPU backend (`JAX_PLATFORMS=cuda`) renders on its default device.
  """
  with jax.default_device(_cpu_device()):
    return _generate_scene(rng, family=family, views=views, image_size=image_size,
                           supersample=supersample, max_attempts=max_attempts,
                           min_objects=min_objects, max_objects=max_objects,
                           object_scale=object_scale, plain_background=plain_background,
                           plain_objects=plain_objects, no_walls=no_walls,
                           room_objects=room_objects, grey_floor=grey_floor)


def _cpu_device():
  """The first CPU device, or None (JAX's default device) where JAX_PLATFORMS leaves no CPU."""
  try:
    return jax.local_devices(backend="cpu")[0]
  except RuntimeError:
    return None


def draw_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
               supersample: int = 2, max_attempts: int = 100, min_objects: int = 0,
               max_objects: int = 0, object_scale: float = 1.0,
               plain_background: bool = False, plain_objects: bool = False,
               no_walls: bool = False, room_objects: str = "chairs", grey_floor: bool = False):
  """The layout and cameras `generate_scene` draws from `rng`, without the final render:
  (spec, cameras, cam_to_world [N, 4, 4], attempts). Scene edits (data/scene_edits.py) re-draw
  a stored scene's SceneSpec with it, from the seed its dataset.json records."""
  with jax.default_device(_cpu_device()):
    return _draw_scene(rng, family=family, views=views, image_size=image_size,
                       supersample=supersample, max_attempts=max_attempts,
                       min_objects=min_objects, max_objects=max_objects,
                       object_scale=object_scale, plain_background=plain_background,
                       plain_objects=plain_objects, no_walls=no_walls,
                       room_objects=room_objects, grey_floor=grey_floor)


def render_scene(spec: SceneSpec, cam_to_world: np.ndarray, *, image_size: int,
                 supersample: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """(rgb [N, H, W, 3] uint8, label [N, H, W] int32, depth [N, H, W] float32) of `spec` seen by
  the cameras cam_to_world [N, 4, 4] (world units): the arrays `generate_scene` stores."""
  with jax.default_device(_cpu_device()):
    return _render_scene(spec, cam_to_world, image_size=image_size, supersample=supersample)


def _draw_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
                supersample: int, max_attempts: int, min_objects: int, max_objects: int,
                object_scale: float, plain_background: bool = False,
                plain_objects: bool = False, no_walls: bool = False,
                room_objects: str = "chairs", grey_floor: bool = False):
  check_object_options(family, min_objects, max_objects, object_scale, plain_background,
                       plain_objects, no_walls, room_objects, grey_floor)
  options = render_options(family, supersample, walls=not no_walls,
                           clevr_objects=object_family(family, room_objects) == "clevr")
  k32 = jnp.asarray(uorf_intrinsics(image_size), jnp.float32)
  threshold = min_visible_pixels(image_size)
  for attempt in range(1, max_attempts + 1):
    if family == "clevr":
      spec = shaped = sample_clevr_layout(rng, min_objects=min_objects,
                                          max_objects=max_objects, object_scale=object_scale)
    else:
      # Visibility is judged on the chairs in every form, and the form is drawn from a twin of
      # the chairs' random state: a box hides more of its neighbours and shows more of itself,
      # so judging each form on its own would redraw different scenes for different forms.
      # CLEVR's objects are judged on themselves: they are not a form of the room's chairs.
      state = rng.bit_generator.state
      spec = sample_room_layout(rng, min_objects=min_objects, max_objects=max_objects,
                                plain_background=plain_background,
                                plain_objects=plain_objects, no_walls=no_walls,
                                object_scale=object_scale, grey_floor=grey_floor,
                                room_objects="clevr" if room_objects == "clevr" else "chairs")
      shaped = spec
      if room_objects not in ("chairs", "clevr"):
        twin = np.random.Generator(type(rng.bit_generator)())
        twin.bit_generator.state = state
        shaped = sample_room_layout(twin, min_objects=min_objects, max_objects=max_objects,
                                    plain_background=plain_background,
                                    plain_objects=plain_objects, no_walls=no_walls,
                                    room_objects=room_objects, object_scale=object_scale,
                                    grey_floor=grey_floor)
    cameras = tuple(sample_cameras(rng, views))
    c2w = np.stack([camera_to_world(c) for c in cameras])
    arrays = scene_arrays(spec)
    # All N views, although only view 0 is checked: the same shape as render_views' centre pass,
    # so nothing extra is compiled.
    labels, _ = render_centre(arrays, cam_to_world=jnp.asarray(c2w, jnp.float32),
                              intrinsics=k32, image_size=image_size, options=options)
    counts = np.bincount(np.asarray(labels[0]).ravel(), minlength=len(spec.objects) + 1)
    if np.all(counts[1:len(spec.objects) + 1] >= threshold):
      return shaped, cameras, c2w, attempt
  raise RuntimeError(f"no {family} layout with every object visible after {max_attempts} tries")


def _render_scene(spec: SceneSpec, cam_to_world: np.ndarray, *, image_size: int,
                  supersample: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  out = render_views(scene_arrays(spec), cam_to_world=jnp.asarray(cam_to_world, jnp.float32),
                     intrinsics=jnp.asarray(uorf_intrinsics(image_size), jnp.float32),
                     image_size=image_size,
                     options=render_options(spec.family, supersample,
                                            walls=spec.walls is not None,
                                            clevr_objects=any(o.shape in CLEVR_SHAPES
                                                              for o in spec.objects)))
  rgb = np.asarray(out.rgb, np.float32)
  return (np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8),
          np.asarray(out.label, np.int32), np.asarray(out.depth, np.float32))


def _generate_scene(rng: np.random.Generator, *, family: str, views: int, image_size: int,
                    supersample: int, max_attempts: int, min_objects: int, max_objects: int,
                    object_scale: float, plain_background: bool = False,
                    plain_objects: bool = False, no_walls: bool = False,
                    room_objects: str = "chairs", grey_floor: bool = False) -> GeneratedScene:
  spec, cameras, c2w, attempts = _draw_scene(
      rng, family=family, views=views, image_size=image_size, supersample=supersample,
      max_attempts=max_attempts, min_objects=min_objects, max_objects=max_objects,
      object_scale=object_scale, plain_background=plain_background, plain_objects=plain_objects,
      no_walls=no_walls, room_objects=room_objects, grey_floor=grey_floor)
  rgb, label, depth = _render_scene(spec, c2w, image_size=image_size, supersample=supersample)
  return GeneratedScene(spec=spec, cameras=cameras, cam_to_world=c2w,
                        intrinsics=uorf_intrinsics(image_size), rgb=rgb, label=label, depth=depth,
                        attempts=attempts)


# =============================================================================================
# Writing a data set (uORF folder format, docs/method.md §3.2 / §3.3)
# =============================================================================================

PNG_COMPRESS_LEVEL = 6  # fixed so files are byte-identical between runs


def _save_png(path: str, array: np.ndarray) -> None:
  Image.fromarray(array, "RGB").save(path, format="PNG", compress_level=PNG_COMPRESS_LEVEL)


def mask_to_grey_rgb(label: np.ndarray) -> np.ndarray:
  """[H, W] labels → [H, W, 3] uint8 grey (17·l, 17·l, 17·l)."""
  grey = (label.astype(np.int32) * LABEL_GREY_STEP).astype(np.uint8)
  return np.repeat(grey[..., None], 3, axis=-1)


def view_stem(*, image_index: int, scene_index: int, view: int) -> str:
  return f"{image_index:05d}_sc{scene_index:04d}_az{view:02d}"


@dataclasses.dataclass(frozen=True)
class _SceneTask:
  family: str
  split: str
  index: int  # within the split (seeds the scene)
  global_index: int  # SSSS in the file names
  views: int
  image_size: int
  seed: int
  supersample: int
  folder: str
  min_objects: int = 0
  max_objects: int = 0
  object_scale: float = 1.0
  plain_background: bool = False
  plain_objects: bool = False
  no_walls: bool = False
  room_objects: str = "chairs"
  grey_floor: bool = False


def _write_scene(task: _SceneTask) -> dict:
  """Renders one scene and writes its files; returns its dataset.json entry."""
  rng = scene_rng(seed=task.seed, family=task.family, split=task.split, index=task.index)
  scene = generate_scene(rng, family=task.family, views=task.views, image_size=task.image_size,
                         supersample=task.supersample, min_objects=task.min_objects,
                         max_objects=task.max_objects, object_scale=task.object_scale,
                         plain_background=task.plain_background,
                         plain_objects=task.plain_objects, no_walls=task.no_walls,
                         room_objects=task.room_objects, grey_floor=task.grey_floor)
  k_norm = normalised_intrinsics(scene.intrinsics, task.image_size)
  stems = []
  for a in range(task.views):
    stem = view_stem(image_index=task.index * task.views + a, scene_index=task.global_index,
                     view=a)
    base = os.path.join(task.folder, stem)
    _save_png(base + ".png", scene.rgb[a])
    _save_png(base + "_mask.png", mask_to_grey_rgb(scene.label[a]))
    # "+ 0.0" turns −0.0 into 0.0 so the text never shows "-0.0000000000".
    np.savetxt(base + "_RT.txt", scene.cam_to_world[a] + 0.0, fmt="%.10f")
    np.savetxt(base + "_intrinsics.txt", k_norm + 0.0, fmt="%.10f")
    np.save(base + "_depth.npy", scene.depth[a])
    stems.append(stem)
  return {"name": f"sc{task.global_index:04d}", "index": task.index, "views": stems,
          "objects": [o.to_json() for o in scene.spec.objects],
          "cameras": [c.to_json() for c in scene.cameras],
          "lights": [dataclasses.asdict(l) for l in scene.spec.lights],
          "layout_attempts": scene.attempts}


def _worker_init() -> None:
  # Workers render on the CPU only (no accelerator start-up or memory reservation per worker), with
  # one XLA thread each: the pool already uses every core. Unpickling this function imported jax,
  # which read an inherited JAX_PLATFORMS (e.g. "cuda") already: the environment variable alone
  # would come too late, the config option still counts until the first backend starts.
  os.environ["JAX_PLATFORMS"] = "cpu"
  jax.config.update("jax_platforms", "cpu")
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                             " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")


def _split_header(*, family: str, split: str, seed: int, views: int, image_size: int,
                  num_scenes: int, supersample: int, min_objects: int = 0, max_objects: int = 0,
                  object_scale: float = 1.0, plain_background: bool = False,
                  plain_objects: bool = False, no_walls: bool = False,
                  room_objects: str = "chairs", grey_floor: bool = False) -> dict:
  k = uorf_intrinsics(image_size)
  max_labels = MAX_OBJECTS[object_family(family, room_objects)]
  header = {
      "format": "slotlifter_jax.generated", "generator_version": GENERATOR_VERSION,
      "family": family, "subset": SUBSETS[family], "split": split, "seed": seed,
      "num_scenes": num_scenes, "image_size": [image_size, image_size], "views_per_scene": views,
      "num_source_views": num_source_views_for(views), "scene_scale": SCENE_SCALE,
      "supersample": supersample,
      "camera": {"convention": "opencv_cam2world", "world_up": "z", "units": "world",
                 "look_at": [0.0, 0.0, 0.0], "radius": CAMERA_RADIUS,
                 "radius_jitter": CAMERA_RADIUS_JITTER, "elevation_deg": CAMERA_ELEVATION_DEG,
                 "elevation_jitter_deg": CAMERA_ELEVATION_JITTER_DEG, "azimuth": "uniform",
                 "intrinsics_pixels": {"fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2],
                                       "cy": k[1, 2], "width": image_size,
                                       "height": image_size}},
      "background": {"floor_z": 0.0,
                     "wall_half_size": ROOM_HALF_SIZE if family == "room" and not no_walls
                     else None},
      "depth": {"kind": "camera_z", "units": "world", "dtype": "float32",
                "sample": "pixel centre", "no_hit": 0.0},
      "mask": {"background_label": BACKGROUND_LABEL, "max_objects": max_labels,
               "label_grey_levels": label_grey_levels(max_labels),
               "encoding": "RGB PNG, label l drawn as (g, g, g) with g = label_grey_levels[l]",
               "sample": "pixel centre", "views": "all"},
  }
  # Only non-default sets record their object options, so default dataset.json files are unchanged
  # (and _existing_split_matches tells the two apart by the key's presence).
  if not is_default_objects(family, min_objects, max_objects, object_scale, plain_background,
                            plain_objects, no_walls, room_objects, grey_floor):
    lo, hi = object_count_range(family, min_objects, max_objects, room_objects)
    header["objects"] = {"min_objects": lo, "max_objects": hi,
                         "object_scale": float(object_scale)}
    if plain_background:
      header["objects"]["plain_background"] = True
    if plain_objects:
      header["objects"]["plain_objects"] = True
    if no_walls:
      header["objects"]["no_walls"] = True
    if room_objects != "chairs":
      header["objects"]["room_objects"] = room_objects
    if grey_floor:
      header["objects"]["grey_floor"] = True
  return header


def _existing_split_matches(path: str, header: dict) -> bool:
  try:
    with open(os.path.join(path, "dataset.json")) as f:
      old = json.load(f)
  except (OSError, ValueError):
    return False
  # The same keys too: a set with object options must not pass for a default one, or vice versa.
  header = json.loads(json.dumps(header))
  return set(old) - {"scenes"} == set(header) and all(old.get(k) == v for k, v in header.items())


def generate_dataset(out_dir: str, *, family: str, num_train: int, num_val: int, num_test: int,
                     num_dev: Optional[int] = None, views: int = 4, image_size: int = 128,
                     seed: int = 0,
                     num_workers: Optional[int] = None, progress: bool = True,
                     overwrite: bool = False, supersample: int = 2, min_objects: int = 0,
                     max_objects: int = 0, object_scale: float = 1.0,
                     plain_background: bool = False, plain_objects: bool = False,
                     no_walls: bool = False, room_objects: str = "chairs",
                     grey_floor: bool = False) -> dict:
  """Writes <out_dir>/<subset>_{train,val,dev,test} and returns a summary (seconds per split).

  `num_dev` (None: as many as `num_test`) scenes of the development split, the former test split
  (layout.SPLITS says why); `num_test` scenes of the held-out test split.

  `min_objects`, `max_objects` (0: the family's default count) and `object_scale` (room: ≤ 1)
  select an easier set (`sample_clevr_layout`); its dataset.json headers record them under
  "objects", and each scene's entry lists its objects. The folder names stay the family's.
  `plain_background`, `plain_objects` (room only) draw the same scenes with untextured floor and
  walls, or chairs; `no_walls` (room only) without the walls; `room_objects` (room only) with
  solid chairs or boxes in place of the chairs (layout.ROOM_OBJECTS).

  A split whose folder already holds a dataset.json with the same generation parameters is kept
  as it is (this resumes an interrupted run); any other non-empty split folder is an error unless
  `overwrite`. Each split is written to a temporary sibling folder and renamed into place only
  when complete. Scene s of a split is seeded by (seed, family, split, s), so the files do not
  depend on `num_workers`; SSSS in the file names counts scenes over train, val, dev, test in
  turn, so the dev split's files keep the names the former test split's had.
  """
  from tqdm import tqdm

  if family not in FAMILIES:
    raise ValueError(f"unknown family {family!r}; choose one of {FAMILIES}")
  if views < 1 or image_size < 8:
    raise ValueError(f"need views ≥ 1 and image_size ≥ 8, got {views}, {image_size}")
  check_object_options(family, min_objects, max_objects, object_scale, plain_background,
                       plain_objects, no_walls, room_objects, grey_floor)
  objects = dict(min_objects=min_objects, max_objects=max_objects, object_scale=object_scale,
                 plain_background=plain_background, plain_objects=plain_objects,
                 no_walls=no_walls, room_objects=room_objects, grey_floor=grey_floor)
  subset = SUBSETS[family]
  if num_dev is None:
    num_dev = num_test
  counts = {"train": num_train, "val": num_val, "dev": num_dev, "test": num_test}
  headers = {s: _split_header(family=family, split=s, seed=seed, views=views,
                              image_size=image_size, num_scenes=n, supersample=supersample,
                              **objects)
             for s, n in counts.items()}
  paths = {s: os.path.join(out_dir, f"{subset}_{s}") for s in SPLITS}
  todo = []
  for s in SPLITS:
    p = paths[s]
    if os.path.isdir(p) and os.listdir(p) and not overwrite:
      if _existing_split_matches(p, headers[s]):
        continue
      raise FileExistsError(f"{p} exists and is not empty (and was generated with other "
                            f"parameters); pass overwrite=True / --overwrite to replace it")
    todo.append(s)
  os.makedirs(out_dir, exist_ok=True)
  if num_workers is None:
    num_workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (
        os.cpu_count() or 1)
  total = sum(counts[s] for s in todo)
  num_workers = max(1, min(num_workers, total))
  pool = None
  if num_workers > 1:
    # spawn, not fork: the parent may already hold an initialised XLA runtime.
    pool = multiprocessing.get_context("spawn").Pool(num_workers, initializer=_worker_init)
  summary = {"out_dir": out_dir, "family": family, "subset": subset, "num_workers": num_workers,
             "splits": {}}
  start_all = time.perf_counter()
  try:
    offsets = {"train": 0, "val": num_train, "dev": num_train + num_val,
               "test": num_train + num_val + num_dev}
    for s in SPLITS:
      if s not in todo:
        summary["splits"][s] = {"path": paths[s], "num_scenes": counts[s], "seconds": 0.0,
                                "kept_existing": True}
        continue
      start = time.perf_counter()
      tmp = paths[s] + ".partial"
      if os.path.exists(tmp):
        shutil.rmtree(tmp)  # left by an interrupted run
      os.makedirs(tmp)
      tasks = [_SceneTask(family=family, split=s, index=i, global_index=offsets[s] + i,
                          views=views, image_size=image_size, seed=seed,
                          supersample=supersample, folder=tmp, **objects)
               for i in range(counts[s])]
      results = pool.imap(_write_scene, tasks, chunksize=2) if pool else map(_write_scene, tasks)
      scenes = list(tqdm(results, total=len(tasks), desc=f"{subset}_{s}", unit="scene",
                         disable=not progress, dynamic_ncols=True))
      dataset = dict(headers[s], scenes=scenes)
      with open(os.path.join(tmp, "dataset.json"), "w") as f:
        json.dump(dataset, f, sort_keys=True, indent=1)
        f.write("\n")
      if os.path.exists(paths[s]):
        shutil.rmtree(paths[s])  # empty, or overwrite was asked for
      os.rename(tmp, paths[s])
      seconds = time.perf_counter() - start
      summary["splits"][s] = {"path": paths[s], "num_scenes": counts[s],
                              "num_images": counts[s] * views, "seconds": seconds,
                              "scenes_per_second": counts[s] / seconds if seconds > 0 else 0.0}
  except BaseException:
    if pool is not None:
      pool.terminate()  # an interrupted run stops its workers; the .partial folder is not renamed
    raise
  finally:
    if pool is not None:
      pool.close()
      pool.join()
  summary["seconds"] = time.perf_counter() - start_all
  return summary
