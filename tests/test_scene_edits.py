"""Ground truth for scene edits (slotlifter_jax/data/scene_edits.py, docs/editing.md): re-drawing a
written scene gives its files byte for byte, an edit asking for nothing renders the same bytes,
and an edited render lies, pixel by pixel, on the surfaces of the edited objects as exact signed
distance functions written from dataset.json's parts (tests/generator_refs.py, no ray caster)."""

import dataclasses
import functools
import json
import math
import os

import numpy as np
import pytest
from generator_refs import SURFACE_TOL, background_sdf, object_sdf, pixel_rays
from PIL import Image

from slotlifter_jax.data import generator
from slotlifter_jax.data import layout
from slotlifter_jax.data import scene_edits

SIZE = 24


@functools.lru_cache(maxsize=None)
def _written(root):
  generator.generate_dataset(root, family="clevr", num_train=1, num_val=1, num_test=2, views=3,
                             image_size=SIZE, seed=7, num_workers=1, progress=False)
  return root


@pytest.fixture(scope="module")
def clevr_root(tmp_path_factory):
  return _written(str(tmp_path_factory.mktemp("edit_gt")))


def _splits(root):
  for name in sorted(os.listdir(root)):
    folder = os.path.join(root, name)
    yield folder, scene_edits.read_manifest(folder)


def _stored(folder, entry):
  """The written views of a scene: rgb uint8, labels (grey / 17), depth."""
  rgb, label, depth = [], [], []
  for stem in entry["views"]:
    base = os.path.join(folder, stem)
    rgb.append(np.asarray(Image.open(base + ".png").convert("RGB")))
    label.append(np.asarray(Image.open(base + "_mask.png").convert("L")).astype(np.int32)
                 // layout.LABEL_GREY_STEP)
    depth.append(np.load(base + "_depth.npy"))
  return np.stack(rgb), np.stack(label), np.stack(depth)


def test_redrawing_a_written_scene_gives_its_files_byte_for_byte(clevr_root):
  count, listed = 0, 0
  for folder, manifest in _splits(clevr_root):
    listed += manifest["num_scenes"]
    for entry in manifest["scenes"]:
      drawn = scene_edits.redraw(manifest, entry["name"])
      truth = scene_edits.render(drawn)
      rgb, label, depth = _stored(folder, entry)
      np.testing.assert_array_equal(truth.rgb, rgb)
      np.testing.assert_array_equal(truth.label, label)
      np.testing.assert_array_equal(truth.depth, depth)
      scene_edits.check_redraw(truth, images=rgb.astype(np.float32) / 255.0, masks=label,
                               name=entry["name"])
      # An edit that asks for nothing renders the same bytes.
      label_1 = drawn.spec.objects[0].label
      still = scene_edits.render(drawn, scene_edits.translate_object(drawn.spec, label_1,
                                                                     (0.0, 0.0)))
      np.testing.assert_array_equal(still.rgb, rgb)
      np.testing.assert_array_equal(still.depth, depth)
      count += 1
  assert count == listed >= 4  # train 1, val 1, test 2 (and a development split where written)
  # A stored image that differs is noticed.
  wrong = rgb.astype(np.float32) / 255.0
  wrong[0, 0, 0, 0] = 1.0 - wrong[0, 0, 0, 0]
  with pytest.raises(scene_edits.RedrawError, match="differ"):
    scene_edits.check_redraw(truth, images=wrong, masks=None, name=entry["name"])


def _test_scene(root):
  folder = [f for f, _ in _splits(root) if f.endswith("_test")][0]
  manifest = scene_edits.read_manifest(folder)
  return manifest, manifest["scenes"][0]


def _check_surfaces(drawn, truth, objects):
  """Every pixel's back-projected depth lies on the surface its label names (SDFs of `objects`,
  dataset.json-style dicts), and no object is cut into."""
  k = generator.uorf_intrinsics(SIZE)
  vs, us = np.meshgrid(np.arange(SIZE, dtype=np.float64), np.arange(SIZE, dtype=np.float64),
                       indexing="ij")
  for c2w, labels, depth in zip(drawn.cam_to_world, truth.label, truth.depth):
    origins, dirs = pixel_rays(c2w, k, us, vs)
    points = origins + depth[..., None].astype(np.float64) * dirs
    sdfs = np.stack([object_sdf(o, points) for o in objects])  # [O, H, W]
    assert set(np.unique(labels)) <= {0} | {o["label"] for o in objects}
    for o, sdf in zip(objects, sdfs):
      on = labels == o["label"]
      assert np.all(np.abs(sdf[on]) < SURFACE_TOL), o["label"]
    bg = labels == 0
    assert np.all(np.abs(background_sdf(points[bg], None)) < SURFACE_TOL)
    assert np.all(sdfs[:, bg] > -SURFACE_TOL)


def test_removed_object_is_gone_and_nothing_it_did_not_hide_changes(clevr_root):
  manifest, entry = _test_scene(clevr_root)
  drawn = scene_edits.redraw(manifest, entry["name"])
  before = scene_edits.render(drawn)
  gone = entry["objects"][1]["label"]
  after = scene_edits.render(drawn, scene_edits.remove_object(drawn.spec, gone))
  _check_surfaces(drawn, after, [o for o in entry["objects"] if o["label"] != gone])
  assert not np.any(after.label == gone) and np.any(before.label == gone)
  # Taking an object away occludes nothing: another object's pixels keep their label and depth.
  other = (before.label != gone) & (before.label > 0)
  np.testing.assert_array_equal(after.label[other], before.label[other])
  np.testing.assert_array_equal(after.depth[other], before.depth[other])
  with pytest.raises(scene_edits.UnknownObjectError, match="object 99"):
    scene_edits.remove_object(drawn.spec, 99)


def _free_translation(spec, label):
  """A translation of object `label` that keeps every layout rule, found by brute force over a
  grid (the rules checked here in NumPy, not by the code under test)."""
  obj = next(o for o in spec.objects if o.label == label)
  half = layout.CLEVR_FOOTPRINT
  for r in (1.5, 1.0, 2.0, 0.6):
    for a in np.linspace(0, 2 * np.pi, 24, endpoint=False):
      t = np.array([r * np.cos(a), r * np.sin(a)])
      xy = np.asarray(obj.position[:2]) + t
      if max(abs(xy[0]), abs(xy[1])) + obj.bounding_radius > half:
        continue
      if all(np.hypot(*(xy - np.asarray(o.position[:2]))) >= obj.bounding_radius
             + o.bounding_radius + layout.MIN_GAP for o in spec.objects if o.label != label):
        return t
  raise AssertionError("no free translation on the grid")


def test_translated_object_lies_on_its_shifted_surfaces(clevr_root):
  manifest, entry = _test_scene(clevr_root)
  drawn = scene_edits.redraw(manifest, entry["name"])
  label = entry["objects"][0]["label"]
  t = _free_translation(drawn.spec, label)
  after = scene_edits.render(drawn, scene_edits.translate_object(drawn.spec, label, t))
  shifted = json.loads(json.dumps(entry["objects"]))
  for o in shifted:
    if o["label"] == label:
      for part in o["parts"]:
        part["centre"] = [part["centre"][0] + t[0], part["centre"][1] + t[1], part["centre"][2]]
  _check_surfaces(drawn, after, shifted)
  assert np.any(after.label == label)


def test_translations_that_collide_or_leave_the_footprint_are_refused(clevr_root):
  manifest, entry = _test_scene(clevr_root)
  spec = scene_edits.redraw(manifest, entry["name"]).spec
  a, b = spec.objects[0], spec.objects[1]
  need = a.bounding_radius + b.bounding_radius + layout.MIN_GAP
  # Towards b until the circles are exactly MIN_GAP apart, then a little further.
  gap = np.asarray(b.position[:2]) - np.asarray(a.position[:2])
  dist = np.linalg.norm(gap)
  unit = gap / dist
  into = (dist - need + 1e-3) * unit
  with pytest.raises(scene_edits.CollisionError, match=f"collides with object {b.label}") as e:
    scene_edits.translate_object(spec, a.label, into)
  assert isinstance(e.value, ValueError) and "\n" not in str(e.value)
  # Far outside the footprint, in the direction away from the centre.
  out = np.sign(a.position[:2]) * layout.CLEVR_FOOTPRINT * 2
  with pytest.raises(scene_edits.FootprintError, match="footprint") as e:
    scene_edits.translate_object(spec, a.label, out)
  assert "\n" not in str(e.value)
  with pytest.raises(scene_edits.SceneEditError, match="dz must be 0"):
    scene_edits.translate_object(spec, a.label, (0.1, 0.0, 0.2))
  # A circle tangent to the footprint's edge, clear of the others, is accepted (the rule is ≤).
  half = layout.CLEVR_FOOTPRINT
  lone = dataclasses.replace(spec, objects=(a,))
  lone = scene_edits.translate_object(lone, a.label, (-a.position[0], -a.position[1]))
  edge = half - a.bounding_radius
  moved = scene_edits.translate_object(lone, a.label, (edge, 0.0))
  assert math.isclose(moved.objects[0].position[0], edge)
  with pytest.raises(scene_edits.FootprintError):
    scene_edits.translate_object(lone, a.label, (edge + 1e-6, 0.0))
