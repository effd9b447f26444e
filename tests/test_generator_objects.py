"""Tests of the generator's easier CLEVR sets (min_objects / max_objects / object_scale, the
ladder of issue "Objects emerge on this CPU") against independent references (generator_refs.py).
"""

import hashlib
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from generator_refs import check_views, generate_small, read_labels, read_splits
from slotlifter_jax.data import generator


# sha256 of `_scene_digest(generate_scene(default_rng(0), family="clevr", views=2, image_size=16))`
# computed with the generator before these options existed: the default draws must not change.
DEFAULT_SCENE_DIGEST = "7d31b5c718f938860003e8a40d0d7f51e0dce6d85e345af8f06a437795d856f1"
# The model's locality box (defaults.py: model.locality_box = 0.64 in the scene frame) in world
# units: 0.64 / scene_scale.
LOCALITY_BOX_WORLD = 0.64 / generator.SCENE_SCALE


def _rounded(x):
  """Floats to 9 significant digits, so the digest does not hang on a libm's last bit."""
  if isinstance(x, float):
    return float(f"{x:.9g}")
  if isinstance(x, dict):
    return {k: _rounded(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_rounded(v) for v in x]
  return x


def _scene_digest(scene):
  """What the random draws decide: objects, cameras, lights and the number of layouts drawn."""
  d = {"objects": [o.to_json() for o in scene.spec.objects],
       "cameras": [c.to_json() for c in scene.cameras],
       "lights": [{"direction": l.direction, "intensity": l.intensity} for l in scene.spec.lights],
       "attempts": scene.attempts}
  return hashlib.sha256(json.dumps(_rounded(d), sort_keys=True).encode()).hexdigest()


def test_default_object_options_leave_output_unchanged():
  kw = dict(family="clevr", views=2, image_size=16)
  default = generator.generate_scene(np.random.default_rng(0), **kw)
  assert _scene_digest(default) == DEFAULT_SCENE_DIGEST
  explicit = generator.generate_scene(np.random.default_rng(0), min_objects=5, max_objects=7,
                                      object_scale=1.0, **kw)
  for name in ("rgb", "label", "depth", "cam_to_world"):
    np.testing.assert_array_equal(getattr(explicit, name), getattr(default, name))
  assert explicit.spec == default.spec and explicit.attempts == default.attempts


def test_object_count_is_respected():
  for i in range(40):  # layouts only: cheap
    rng = np.random.default_rng(i)
    assert len(generator.sample_clevr_layout(rng, min_objects=2, max_objects=2).objects) == 2
    n = len(generator.sample_room_layout(rng, min_objects=1, max_objects=2).objects)
    assert 1 <= n <= 2


def test_scaled_objects_fit_on_floor_apart_and_inside_locality_box():
  scale = generator.MAX_OBJECT_SCALE  # the worst case
  counts = set()
  for i in range(100):
    spec = generator.sample_clevr_layout(np.random.default_rng(i), min_objects=1, max_objects=3,
                                         object_scale=scale)
    objs = [o.to_json() for o in spec.objects]
    counts.add(len(objs))
    for o in objs:
      (part,) = o["parts"]
      r = generator.CLEVR_SIZES[o["size"]] * scale
      assert o["radius"] == pytest.approx(r) and part["half_size"] == pytest.approx([r] * 3)
      assert o["position"][2] == pytest.approx(r)  # resting on the floor
      x, y, top = abs(o["position"][0]), abs(o["position"][1]), 2 * r
      # Inside the default scenes' footprint, and well inside the locality box.
      assert max(x, y) + o["bounding_radius"] <= generator.CLEVR_FOOTPRINT + 1e-9
      assert max(x, y) + o["bounding_radius"] <= LOCALITY_BOX_WORLD - 0.4
      assert top <= LOCALITY_BOX_WORLD - 1.0
    for a in range(len(objs)):
      for b in range(a):
        gap = np.hypot(objs[a]["position"][0] - objs[b]["position"][0],
                       objs[a]["position"][1] - objs[b]["position"][1])
        assert gap >= objs[a]["bounding_radius"] + objs[b]["bounding_radius"] + generator.MIN_GAP
  assert counts == {1, 2, 3}


def test_easy_set_has_two_objects_each_1p6_times_the_default_size(tmp_path):
  generate_small(tmp_path, "clevr", num_train=2, num_val=0, num_test=0, views=2, image_size=24,
            min_objects=2, max_objects=2, object_scale=1.6)
  (path, meta), = [s for s in read_splits(tmp_path) if s[0].endswith("_train")]
  assert meta["objects"] == {"min_objects": 2, "max_objects": 2, "object_scale": 1.6}
  for scene in meta["scenes"]:
    objs = scene["objects"]
    assert [o["label"] for o in objs] == [1, 2]
    for o in objs:
      assert o["radius"] == pytest.approx(1.6 * generator.CLEVR_SIZES[o["size"]])
      shape_factor = np.sqrt(2.0) if o["shape"] == "cube" else 1.0
      assert o["bounding_radius"] == pytest.approx(o["radius"] * shape_factor)
    # The source view shows both objects, each with its own label.
    labels = read_labels(os.path.join(path, scene["views"][0]), meta["mask"]["label_grey_levels"])
    assert set(np.unique(labels)) == {0, 1, 2}
  check_views(tmp_path, "clevr")  # depths and masks agree with the (larger) geometry
  # The default set records no object options, so its dataset.json is unchanged.
  assert "objects" not in generator._split_header(
      family="clevr", split="train", seed=0, views=4, image_size=16, num_scenes=1, supersample=2,
      min_objects=5, max_objects=7)


def test_existing_split_with_other_object_options_is_not_kept(tmp_path):
  kw = dict(num_train=1, num_val=0, num_test=0, views=1, image_size=16)
  generate_small(tmp_path, "clevr", min_objects=1, max_objects=1, **kw)
  with pytest.raises(FileExistsError):  # the default set's header lacks "objects": no match
    generate_small(tmp_path, "clevr", **kw)


def test_bad_object_options_name_the_field():
  cases = [("clevr", dict(min_objects=4, max_objects=3), "min_objects"),
           ("clevr", dict(max_objects=8), "max_objects"),
           ("clevr", dict(object_scale=0.0), "object_scale"),
           ("clevr", dict(object_scale=2.5), "object_scale"),
           ("room", dict(object_scale=1.6), "object_scale")]
  for family, kw, field in cases:
    with pytest.raises(ValueError, match=field) as info:
      generator.check_object_options(family, **kw)
    assert info.value.field == field


def test_cache_name_changes_only_for_non_default_object_options():
  import ml_collections
  from slotlifter_jax import defaults
  from slotlifter_jax.data import embedded
  d = defaults.base_config().data
  default_name = os.path.basename(embedded.dataset_dir(d, seed=0))
  # train-val-dev-test counts: a folder made before the held-out test split (three counts) holds
  # another test split and must never be taken for this one.
  assert default_name == "clevr-v1-128px-4v-1000-100-100-100-s0"
  old = d.to_dict()  # a config saved before the fields existed
  for k in ("min_objects", "max_objects", "object_scale"):
    del old[k]
  assert os.path.basename(embedded.dataset_dir(ml_collections.ConfigDict(old), seed=0)) == (
      default_name)
  d.min_objects, d.max_objects = 5, 7  # explicit defaults: the same set, the same folder
  assert os.path.basename(embedded.dataset_dir(d, seed=0)) == default_name
  d.min_objects, d.max_objects, d.object_scale = 1, 3, 1.6
  assert os.path.basename(embedded.dataset_dir(d, seed=0)) == default_name + "-o1-3-x1.6"


def test_cli_rejects_min_objects_above_max_objects(tmp_path):
  cmd = [sys.executable, "-m", "slotlifter_jax.data.generate", "--family=clevr",
         f"--out={tmp_path}", "--min_objects=3", "--max_objects=2", "--noprogress"]
  result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
  assert result.returncode != 0
  last = result.stderr.strip().splitlines()[-1]
  assert last.startswith("error: --min_objects") and "max_objects" in last
  assert not os.listdir(tmp_path)


def test_plain_background_draws_the_same_rooms_without_texture():
  import numpy as np
  from slotlifter_jax.data import embedded
  from slotlifter_jax import defaults
  draw = lambda plain: generator.generate_scene(
      generator.scene_rng(seed=3, family="room", split="train", index=0), family="room", views=2,
      image_size=24, plain_background=plain)
  textured, plain = draw(False), draw(True)
  # Every random draw is the same: chairs, cameras, hence masks and depth, to the bit.
  assert plain.spec.objects == textured.spec.objects
  np.testing.assert_array_equal(plain.cam_to_world, textured.cam_to_world)
  np.testing.assert_array_equal(plain.label, textured.label)
  np.testing.assert_array_equal(plain.depth, textured.depth)
  # Only the floor and the walls lose their texture, keeping their base colour.
  assert plain.spec.floor.texture == "plain" and plain.spec.floor.rgb == textured.spec.floor.rgb
  assert all(w.texture == "plain" for w in plain.spec.walls)
  assert textured.spec.floor.texture != "plain"
  with pytest.raises(ValueError, match="plain_background") as info:
    generator.check_object_options("clevr", plain_background=True)
  assert info.value.field == "plain_background"
  d = defaults.base_config().data
  d.family, d.plain_background = "room", True
  assert os.path.basename(embedded.dataset_dir(d, seed=0)).endswith("-plainbg")


def test_plain_objects_draws_the_same_rooms_with_one_colour_chairs():
  import numpy as np
  draw = lambda plain: generator.generate_scene(
      generator.scene_rng(seed=4, family="room", split="train", index=1), family="room", views=2,
      image_size=24, plain_background=plain, plain_objects=plain)
  textured, plain = draw(False), draw(True)
  np.testing.assert_array_equal(plain.label, textured.label)
  np.testing.assert_array_equal(plain.depth, textured.depth)
  for a, b in zip(plain.spec.objects, textured.spec.objects):
    assert a.parts == b.parts and a.material.rgb == b.material.rgb
    assert a.material.texture == a.leg_material.texture == "plain"
    assert a.leg_material.rgb == a.material.rgb == a.material.rgb2
  with pytest.raises(ValueError, match="plain_objects"):
    generator.check_object_options("clevr", plain_objects=True)


def test_no_walls_draws_the_same_rooms_without_walls():
  import numpy as np
  draw = lambda no_walls: generator.generate_scene(
      generator.scene_rng(seed=4, family="room", split="train", index=1), family="room", views=2,
      image_size=24, no_walls=no_walls)
  walled, open_room = draw(False), draw(True)
  assert open_room.spec.walls is None and walled.spec.walls is not None
  assert open_room.spec.objects == walled.spec.objects
  # The walls never stand in front of a chair (the near ones are culled): the same chair masks.
  np.testing.assert_array_equal(open_room.label, walled.label)
  # Where the walls were, the floor or the sky now shows, farther away.
  assert np.all(open_room.depth[walled.label == 0] >= walled.depth[walled.label == 0] - 1e-4)
  with pytest.raises(ValueError, match="no_walls"):
    generator.check_object_options("clevr", no_walls=True)


def _corners(part):
  """[8, 3] world corners of a yawed box primitive."""
  import itertools
  import numpy as np
  c, s = np.cos(part.yaw), np.sin(part.yaw)
  rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
  signs = np.array(list(itertools.product((-1, 1), repeat=3)), np.float64)
  return np.asarray(part.centre) + (signs * np.asarray(part.half_size)) @ rot.T


def _inside(points, box, tol=1e-9):
  """Whether world points lie inside a yawed box primitive (its own frame, by hand)."""
  import numpy as np
  c, s = np.cos(box.yaw), np.sin(box.yaw)
  local = (points - np.asarray(box.centre)) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
  return bool(np.all(np.abs(local) <= np.asarray(box.half_size) + tol))


@pytest.mark.parametrize("form", ["solid", "boxes"])
def test_room_objects_draw_the_same_rooms_with_filled_in_chairs(form):
  import numpy as np
  from slotlifter_jax.data import embedded
  from slotlifter_jax import defaults
  # Scene 2 of this stream draws four chairs.
  draw = lambda f: generator.generate_scene(
      generator.scene_rng(seed=5, family="room", split="train", index=2), family="room", views=2,
      image_size=32, room_objects=f)
  chairs, shaped = draw("chairs"), draw(form)
  # The same scenes: cameras, lights, floor, walls, and each object's place, yaw and size.
  np.testing.assert_array_equal(shaped.cam_to_world, chairs.cam_to_world)
  assert shaped.spec.lights == chairs.spec.lights and shaped.spec.floor == chairs.spec.floor
  assert shaped.spec.walls == chairs.spec.walls and shaped.attempts == chairs.attempts
  for a, b in zip(shaped.spec.objects, chairs.spec.objects):
    assert (a.label, a.position, a.yaw, a.size, a.bounding_radius) == (
        b.label, b.position, b.yaw, b.size, b.bounding_radius)
    w, d, height = b.size
    if form == "boxes":
      (box,) = a.parts
      np.testing.assert_allclose(box.half_size, (w / 2, d / 2, height / 2), rtol=0, atol=1e-12)
      assert box.centre[2] == pytest.approx(height / 2)
    else:
      assert len(a.parts) == 2 and a.parts[1] == b.parts[1]  # the same back
      base = a.parts[0]
      # The block reaches from the floor to the seat's top, under the whole seat.
      seat_top = b.parts[0].centre[2] + b.parts[0].half_size[2]
      assert base.centre[2] - base.half_size[2] == pytest.approx(0.0, abs=1e-12)
      assert base.centre[2] + base.half_size[2] == pytest.approx(seat_top)
    # Every corner of every part of the chair lies inside the new shape: it only fills in.
    for part in b.parts:
      assert any(_inside(_corners(part), p) for p in a.parts), part
  # Filling in only adds surface: every pixel where some chair shows, some object shows.
  assert np.all(shaped.label[chairs.label > 0] > 0)
  with pytest.raises(ValueError, match="room_objects") as info:
    generator.check_object_options("clevr", room_objects=form)
  assert info.value.field == "room_objects"
  with pytest.raises(ValueError, match="room_objects"):
    generator.check_object_options("room", room_objects="tables")
  d = defaults.base_config().data
  d.family, d.room_objects = "room", form
  assert os.path.basename(embedded.dataset_dir(d, seed=0)).endswith("-" + form)


def test_room_object_scale_shrinks_every_chair_dimension_and_keeps_chairs_on_the_floor():
  import numpy as np
  from slotlifter_jax.data import embedded
  from slotlifter_jax import defaults
  scale = 0.6
  for index in range(6):
    rng = lambda: generator.scene_rng(seed=3, family="room", split="train", index=index)
    spec = generator.sample_room_layout(rng(), object_scale=scale)
    for obj in spec.objects:
      w, d, height = obj.size
      # The default draws scaled: seat 1.3–2.0 square, seat height 1.1–1.7 plus back 1.0–1.8.
      assert 1.3 * scale - 1e-9 <= w <= 2.0 * scale + 1e-9
      assert 1.3 * scale - 1e-9 <= d <= 2.0 * scale + 1e-9
      assert 2.1 * scale - 1e-9 <= height <= 3.5 * scale + 1e-9
      assert obj.bounding_radius == pytest.approx(np.hypot(w / 2, d / 2))
      lows = [p.centre[2] - p.half_size[2] for p in obj.parts]
      highs = [p.centre[2] + p.half_size[2] for p in obj.parts]
      assert min(lows) == pytest.approx(0.0, abs=1e-12)  # the legs stand on the floor
      assert max(highs) == pytest.approx(height)
      # Still inside the default positions' range: x, y ~ U(-3, 3).
      assert max(abs(obj.position[0]), abs(obj.position[1])) <= generator.ROOM_XY_RANGE
  with pytest.raises(ValueError, match="object_scale") as info:
    generator.check_object_options("room", object_scale=1.2)
  assert info.value.field == "object_scale"
  d = defaults.base_config().data
  d.family, d.object_scale, d.room_objects = "room", scale, "boxes"
  assert os.path.basename(embedded.dataset_dir(d, seed=0)).endswith("-o1-4-x0.6-boxes")


def test_grey_floor_draws_the_same_rooms_on_the_clevr_floor():
  import numpy as np
  from slotlifter_jax.data import embedded
  from slotlifter_jax import defaults
  draw = lambda **kw: generator.generate_scene(
      generator.scene_rng(seed=5, family="room", split="train", index=2), family="room", views=2,
      image_size=32, room_objects="boxes", no_walls=True, **kw)
  own, grey = draw(), draw(grey_floor=True)
  # Only the floor differs: cameras, lights, objects and their labels and depths are the same.
  np.testing.assert_array_equal(grey.cam_to_world, own.cam_to_world)
  assert grey.spec.objects == own.spec.objects and grey.spec.lights == own.spec.lights
  np.testing.assert_array_equal(grey.label, own.label)
  np.testing.assert_array_equal(grey.depth, own.depth)
  clevr = generator.sample_clevr_layout(np.random.default_rng(0))
  assert grey.spec.floor == clevr.floor and own.spec.floor != clevr.floor
  # Object pixels away from an object's outline (where supersamples mix in the floor) keep their
  # colour; only background pixels change.
  from scipy import ndimage
  window = dict(size=(1, 3, 3), mode="constant", cval=-1)  # outside the image counts as no label
  interior = (own.label > 0) & (
      ndimage.minimum_filter(own.label, **window) == ndimage.maximum_filter(own.label, **window))
  assert interior.sum() > 20
  np.testing.assert_array_equal(grey.rgb[interior], own.rgb[interior])
  assert np.any(grey.rgb[grey.label == 0] != own.rgb[own.label == 0])
  with pytest.raises(ValueError, match="grey_floor") as info:
    generator.check_object_options("clevr", grey_floor=True)
  assert info.value.field == "grey_floor"
  d = defaults.base_config().data
  d.family, d.room_objects, d.grey_floor = "room", "boxes", True
  assert os.path.basename(embedded.dataset_dir(d, seed=0)).endswith("-boxes-greyfloor")


def test_a_room_holding_clevr_objects_keeps_its_room_and_renders_them_as_the_clevr_family_does():
  import dataclasses
  from slotlifter_jax.data import embedded, layout, writer
  from slotlifter_jax import defaults
  rng = lambda: generator.scene_rng(seed=5, family="room", split="train", index=2)
  chairs = generator.sample_room_layout(rng())
  spec = generator.sample_room_layout(rng(), room_objects="clevr")
  # The room's own draws do not move: floor, walls, lights and ambient are the chairs' room's.
  assert (spec.floor, spec.walls, spec.lights, spec.ambient) == (
      chairs.floor, chairs.walls, chairs.lights, chairs.ambient)
  # CLEVR's objects by CLEVR's tables, 5–7 of them unless the count options say otherwise.
  assert 5 <= len(spec.objects) <= 7
  assert [o.label for o in spec.objects] == list(range(1, len(spec.objects) + 1))
  for o in spec.objects:
    assert o.shape in generator.CLEVR_SHAPES and o.colour in generator.CLEVR_COLOURS
    assert o.position[2] == pytest.approx(o.parts[0].half_size[2])  # resting on the floor
  two = generator.sample_room_layout(rng(), room_objects="clevr", min_objects=2, max_objects=2)
  assert len(two.objects) == 2 and two.floor == chairs.floor
  # A pixel shows the same object as when the clevr family renders the same objects: the room's
  # walls and textured floor hide none of them, and spheres and cylinders keep their shapes.
  scene = generator.generate_scene(rng(), family="room", views=2, image_size=32,
                                   room_objects="clevr")
  as_clevr = dataclasses.replace(scene.spec, family="clevr", floor=layout.CLEVR_GROUND,
                                 walls=None)
  _, label, depth = writer.render_scene(as_clevr, scene.cam_to_world, image_size=32)
  np.testing.assert_array_equal(scene.label, label)
  objects = scene.label > 0
  np.testing.assert_allclose(scene.depth[objects], depth[objects], rtol=1e-5)
  assert {o.shape for o in scene.spec.objects} & {"sphere", "cylinder"}
  # Up to CLEVR's seven objects; the mask's grey levels follow.
  with pytest.raises(ValueError, match="max_objects") as info:
    generator.check_object_options("room", max_objects=8, room_objects="clevr")
  assert info.value.field == "max_objects"
  with pytest.raises(ValueError, match="plain_objects") as info:
    generator.check_object_options("room", plain_objects=True, room_objects="clevr")
  assert info.value.field == "plain_objects"
  header = writer._split_header(family="room", split="train", seed=0, views=2, image_size=32,
                                num_scenes=1, supersample=1, room_objects="clevr")
  assert header["mask"]["max_objects"] == 7 and header["objects"]["max_objects"] == 7
  d = defaults.base_config().data
  d.family, d.room_objects = "room", "clevr"
  assert os.path.basename(embedded.dataset_dir(d, seed=0)).endswith("-o5-7-x1.0-clevr")
