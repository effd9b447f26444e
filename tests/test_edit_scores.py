"""The scores of slot edits (slotlifter_jax/edit_scores.py) and the edit mode's flag checks
(slotlifter_jax/edit.py) on constructed inputs, against brute-force and closed-form references."""

import dataclasses
import math

import ml_collections
import numpy as np
import pytest

from slotlifter_jax import edit
from slotlifter_jax import edit_scores
from slotlifter_jax import metrics
from slotlifter_jax.data import layout
from slotlifter_jax.data import scene_edits


def _one_hot(labels, k):
  return np.eye(k)[labels]


def test_match_slot_picks_the_best_iou_and_refuses_below_the_threshold():
  truth = np.zeros((6, 8), np.int32)
  truth[1:4, 1:5] = 3  # object 3: 12 pixels
  pred = np.zeros((6, 8), np.int64)
  pred[1:4, 1:4] = 2  # slot 2 holds 9 of them and nothing else: IoU 9/12
  pred[1:4, 4] = 1
  pred[0, :] = 1  # slot 1: 3 object pixels and 8 others: IoU 3/17
  slot, iou = edit_scores.match_slot(segmentation=_one_hot(pred, 4), labels=truth, label=3)
  assert slot == 2 and iou == pytest.approx(9 / 12)
  # The same by brute force over every slot.
  brute = [((pred == k) & (truth == 3)).sum() / ((pred == k) | (truth == 3)).sum()
           for k in range(4)]
  assert iou == pytest.approx(max(brute))
  # Two objects of 12 pixels merged in one slot with one pixel more: each has IoU 12/25.
  truth2 = np.zeros((6, 8), np.int32)
  truth2[0:2, 0:6] = 3
  truth2[3:5, 0:6] = 5
  pred2 = np.where(truth2 > 0, 2, 0)
  pred2[5, 7] = 2
  for label in (3, 5):
    slot, iou = edit_scores.match_slot(segmentation=_one_hot(pred2, 4), labels=truth2,
                                       label=label)
    assert slot is None and iou == pytest.approx(12 / 25)
  # A threshold of 0 takes the best slot whatever its IoU.
  assert edit_scores.match_slot(segmentation=_one_hot(pred2, 4), labels=truth2, label=3,
                                threshold=0.0)[0] == 2


def _spec():
  objs = []
  for label, (x, y, size) in enumerate([(0.0, 0.0, "large"), (2.5, 0.0, "small"),
                                        (-2.0, 2.0, "small")], start=1):
    r = layout.CLEVR_SIZES[size]
    part = layout.Primitive("sphere", (x, y, r), (r, r, r), 0.0)
    objs.append(layout.SceneObject(label=label, shape="sphere", colour="red",
                                   material_name="rubber", size=size, position=(x, y, r), yaw=0.0,
                                   bounding_radius=r, parts=(part,),
                                   material=layout.Material(rgb=(1, 2, 3), rgb2=(1, 2, 3))))
  return layout.SceneSpec(family="clevr", objects=tuple(objs), lights=(), ambient=(0, 0, 0),
                          floor=layout.Material(rgb=(1, 1, 1), rgb2=(1, 1, 1)), walls=None)


def test_translations_are_seeded_in_range_and_keep_the_layout_rules():
  spec = _spec()
  for label in (1, 2, 3):
    draws = []
    for _ in range(2):
      rng = edit_scores.translation_rng(data_seed=0, split="test", index=4, label=label)
      draws.append(edit_scores.draw_translation(spec, label, rng))
    np.testing.assert_array_equal(draws[0], draws[1])  # fixed by the seed
    t = draws[0]
    assert edit_scores.MOVE_DISTANCE[0] <= np.hypot(*t) <= edit_scores.MOVE_DISTANCE[1]
    obj = spec.objects[label - 1]
    xy = np.asarray(obj.position[:2]) + t
    assert max(abs(xy)) + obj.bounding_radius <= layout.CLEVR_FOOTPRINT
    for other in spec.objects:
      if other.label != label:
        assert np.hypot(*(xy - np.asarray(other.position[:2]))) >= (
            obj.bounding_radius + other.bounding_radius + layout.MIN_GAP)
  other = edit_scores.draw_translation(spec, 1, edit_scores.translation_rng(
      data_seed=0, split="val", index=4, label=1))
  assert not np.array_equal(other, draws[0])  # another split, another translation
  # An object ringed by neighbours 2.0 away, 15° apart, gets none: a move of 1 to 2 ends within
  # 1.07 of one of them, and it needs 0.7 + 0.35 + 0.25 = 1.3.
  crowded = dataclasses.replace(spec, objects=spec.objects + tuple(
      dataclasses.replace(spec.objects[1], label=10 + i,
                          position=(2.0 * math.cos(a), 2.0 * math.sin(a), 0.35))
      for i, a in enumerate(np.linspace(0, 2 * np.pi, 12, endpoint=False))))
  crowded = dataclasses.replace(crowded, objects=(crowded.objects[0],) + crowded.objects[3:])
  assert edit_scores.draw_translation(crowded, 1, np.random.default_rng(0)) is None


def test_score_edit_against_numpy():
  rng = np.random.default_rng(0)
  n, h, w, k = 2, 16, 16, 3
  rgb0 = rng.integers(0, 256, size=(n + 1, h, w, 3)).astype(np.uint8)
  rgb1 = rgb0.copy()
  rgb1[1:, 4:9, 5:12] = 17  # the edit changes a block of both novel views
  labels = np.zeros((n + 1, h, w), np.int32)
  labels[1:, 4:9, 5:12] = 2
  before = scene_edits.GroundTruth(rgb=rgb0, label=labels, depth=np.ones((n + 1, h, w)))
  after = scene_edits.GroundTruth(rgb=rgb1, label=labels, depth=np.ones((n + 1, h, w)))
  truth = rgb1[1:].astype(np.float64) / 255.0
  edited = np.clip(truth + rng.normal(scale=0.05, size=truth.shape), 0, 1)
  unedited = rgb0[1:].astype(np.float64) / 255.0
  seg = _one_hot(np.where(labels[1:] == 2, 1, 0), k)
  seen = np.zeros((n, h, w), bool)
  seen[:, :6] = True
  out = edit_scores.score_edit(edited=(edited, seg), unedited=(unedited, _one_hot(
      np.zeros((n, h, w), np.int64), k)), truth_before=before, truth_after=after, seen=seen,
      novel=[1, 2], slot=1, moved_label=2)
  changed = np.zeros((n, h, w), bool)
  changed[:, 4:9, 5:12] = True
  changed &= np.any(rgb0[1:] != rgb1[1:], -1)
  err = np.mean((edited - truth) ** 2, -1)
  psnr = lambda m: -10 * np.log10(err[m].mean())
  assert out["psnr_changed"] == pytest.approx(psnr(changed))
  assert out["psnr_changed_seen"] == pytest.approx(psnr(changed & seen))
  assert out["psnr_changed_unseen"] == pytest.approx(psnr(changed & ~seen))
  assert out["psnr"] == pytest.approx(np.mean([-10 * np.log10(err[i].mean()) for i in range(n)]))
  assert out["iou"] == 1.0 and out["iou_baseline"] == 0.0
  assert out["psnr_changed_baseline"] < out["psnr_changed"]
  assert out["changed_share"] == pytest.approx(changed.mean())


def test_summary_counts_means_and_improved_fraction():
  records = [{"psnr": 20.0, "psnr_changed": 15.0, "psnr_changed_baseline": 10.0},
             {"psnr": 22.0, "psnr_changed": 9.0, "psnr_changed_baseline": 11.0},
             {"psnr": 24.0, "psnr_changed": 12.0, "psnr_changed_baseline": 11.0},
             {"psnr": 26.0, "psnr_changed": math.nan, "psnr_changed_baseline": math.nan}]
  s = edit_scores.summarize_kind(records, skipped=3)
  assert s["num_edits"] == 4 and s["num_skipped"] == 3
  assert s["improved_fraction"] == pytest.approx(2 / 3) and s["improved_count"] == 3
  assert s["psnr"] == pytest.approx(23.0)
  assert s["psnr_stderr"] == pytest.approx(np.std([20, 22, 24, 26], ddof=1) / 2)
  assert s["psnr_changed_count"] == 3
  m = edit_scores.summarize_kind([{"iou": 0.5, "iou_baseline": 0.1, "psnr_changed": 1.0,
                                   "psnr_changed_baseline": 2.0}], skipped=0, move=True)
  assert m["iou_mean"] == 0.5 and m["iou_baseline_mean"] == 0.1 and m["num_no_translation"] == 0
  assert m["improved_fraction"] == 0.0


def test_edit_flags_are_checked_and_named():
  req = lambda **kw: edit.parse_request(num_slots=4, **{"remove_slot": None, "move_slot": None,
                                                        "by": "", **kw})
  assert req() is None
  assert req(remove_slot=3) == edit.Request("remove", 3)
  assert req(move_slot=0, by="1.5, 0,-0.25") == edit.Request("move", 0, (1.5, 0.0, -0.25))
  for kw, flag in ((dict(remove_slot=4), "--remove_slot"), (dict(move_slot=-1, by="1,0,0"),
                                                            "--move_slot"),
                   (dict(move_slot=1, by="1,2"), "--by"), (dict(move_slot=1, by="a,b,c"), "--by"),
                   (dict(move_slot=1, by="1,nan,0"), "--by"), (dict(move_slot=1), "--move_slot"),
                   (dict(by="1,0,0"), "--by"), (dict(remove_slot=1, move_slot=2, by="1,0,0"),
                                                "--remove_slot")):
    with pytest.raises(edit.EditFlagError) as e:
      req(**kw)
    assert str(e.value).startswith(f"{flag}: ") and "\n" not in str(e.value)
    assert isinstance(e.value, ValueError)
  with pytest.raises(edit.EditFlagError, match="^--scenes: "):
    edit.parse_scenes("0,x")


@pytest.mark.slow  # generates the smoke data set: 10-15 s, mostly compiling the ray caster
def test_world_translations_turn_with_the_source_azimuth_frame():
  """With data.frame = "source_azimuth" the turn `edit` finds puts the world's source camera at
  azimuth 0, where the model-frame scene has it (docs/method.md §3.6)."""
  from slotlifter_jax.data import embedded
  from slotlifter_jax.data import registry
  from train_helpers import load_config
  config = embedded.resolve_data(load_config())
  with config.unlocked():
    config.data.frame = "source_azimuth"
  scene = registry.load_split(config.data, "test", max_scenes=2)[1]
  rot = edit._world_rotation(config, "test", 1, scene)
  world = config.data.copy_and_resolve_references()
  with world.unlocked():
    world.frame = "world"
  eye = registry.load_split(world, "test", max_scenes=2)[1].cam_to_world[0, :3, 3]
  turned = rot @ eye
  assert turned[0] > 0 and abs(turned[1]) < 1e-5 and turned[2] == pytest.approx(eye[2])
  np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-5)
  np.testing.assert_allclose(turned, scene.cam_to_world[0, :3, 3], atol=1e-5)


def test_the_background_slot_is_the_one_the_locality_constraint_reserves():
  config = ml_collections.ConfigDict({"train": {"locality_steps": 50_000}})
  assert edit_scores.background_slot(config) == 0
  config.train.locality_steps = 0  # no slot was made the background: nothing to carry or fill
  assert edit_scores.background_slot(config) is None
  with pytest.raises(ValueError, match="move_background"):
    edit_scores.check_choice("move_background", "drag", edit_scores.MOVE_BACKGROUNDS)
  assert edit_scores.check_choice("uncovered", "black", edit_scores.UNCOVERED_MODES) == "black"
