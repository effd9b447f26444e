"""experiments/slot_routing.py: majorities, pair outcomes and their counts on hand-made maps."""

import os
import sys

import numpy as np
import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import slot_routing  # noqa: E402


def _maps():
  # Objects 1, 2, 3 on a background of 0. Attention gives them slots 1, 2, 2; the rendering gives
  # object 1 slot 1 on 3 of its 4 pixels, and objects 2 and 3 both slot 3.
  mask = np.array([[1, 1, 0, 2, 2, 0],
                   [1, 1, 0, 2, 2, 0],
                   [0, 0, 0, 0, 3, 3]])
  attention = np.array([[1, 1, 0, 2, 2, 0],
                        [1, 1, 0, 2, 2, 0],
                        [0, 0, 0, 0, 2, 2]])
  rendered = np.array([[1, 1, 0, 3, 3, 0],
                       [4, 1, 0, 3, 3, 0],
                       [0, 0, 0, 0, 3, 3]])
  return mask, attention, rendered


def test_majority_slots_by_hand():
  mask, attention, rendered = _maps()
  assert slot_routing.majority_slots(mask, attention, min_pixels=1) == {
      1: (1, 1.0), 2: (2, 1.0), 3: (2, 1.0)}
  assert slot_routing.majority_slots(mask, rendered, min_pixels=1) == {
      1: (1, 0.75), 2: (3, 1.0), 3: (3, 1.0)}
  # Object 3 has 2 pixels: below min_pixels = 3 it is left out.
  assert set(slot_routing.majority_slots(mask, attention, min_pixels=3)) == {1, 2}
  # A tie goes to the lower slot.
  assert slot_routing.majority_slots(np.array([[1, 1]]), np.array([[4, 2]]),
                                     min_pixels=1) == {1: (2, 0.5)}
  with pytest.raises(ValueError, match="differ in shape"):
    slot_routing.majority_slots(mask, attention[:2], min_pixels=1)


def test_pair_outcomes_and_summary_by_hand():
  mask, attention, rendered = _maps()
  att = slot_routing.majority_slots(mask, attention, min_pixels=1)
  ren = slot_routing.majority_slots(mask, rendered, min_pixels=1)
  pairs = slot_routing.pair_outcomes(att, ren)
  by_objects = {p["objects"]: p for p in pairs}
  assert sorted(by_objects) == [(1, 2), (1, 3), (2, 3)]
  # (1, 2): both stages part them.
  assert by_objects[(1, 2)]["attention_parts"] and by_objects[(1, 2)]["rendering_parts"]
  # (2, 3): attention merges them (slot 2), the rendering too (slot 3): no "merged_into".
  assert not by_objects[(2, 3)]["attention_parts"] and not by_objects[(2, 3)]["rendering_parts"]
  assert "merged_into" not in by_objects[(2, 3)]
  # Now make the rendering merge objects 1 and 2 into object 1's attention slot.
  ren_merged = {**ren, 2: (1, 1.0)}
  merged = {p["objects"]: p for p in slot_routing.pair_outcomes(att, ren_merged)}[(1, 2)]
  assert merged["attention_parts"] and not merged["rendering_parts"]
  assert merged["merged_into"] == "one of theirs"
  # ... and into a slot attention gave neither.
  ren_other = {**ren, 1: (4, 1.0), 2: (4, 1.0)}
  other = {p["objects"]: p for p in slot_routing.pair_outcomes(att, ren_other)}[(1, 2)]
  assert other["merged_into"] == "another slot"

  for p in pairs:
    p.update(slot_cosine=0.5, key_cosine=0.25)
  objects = [dict(attention=att[o][0], rendered=ren[o][0], attention_share=att[o][1],
                  rendered_share=ren[o][1]) for o in att]
  s = slot_routing.summarise(pairs, objects)
  assert (s["pairs"], s["attention_parts"], s["rendering_parts"], s["both_part"]) == (3, 2, 2, 2)
  assert s["attention_parts_rendering_merges"] == 0
  assert s["attention_merges_rendering_parts"] == 0
  assert s["objects"] == 3 and s["rendered_slot_is_attention_slot"] == 1  # object 1 only
  assert s["rendered_purity"] == pytest.approx((0.75 + 1 + 1) / 3)
  assert s["parted_pairs_key_cosine"] == pytest.approx(0.25)
  assert np.isnan(s["merged_pairs_key_cosine"])  # no merged pair to average
