"""Config variants: `fast` cuts the model, not the method; variants compose left to right."""

import importlib.util
import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# What makes the method the paper's: lifting, slot density, masking, loss-relevant switches.
METHOD_FIELDS = ("model.feature_lifting", "model.density_mode", "model.colour_range",
                 "train.mask_max", "train.optimizer", "data.num_source_views")
# The cuts the fast variant's docstring lists, with their values.
FAST_CUTS = {"model.slot_dim": 32, "model.slot_mlp_dim": 64, "model.point_dim": 32,
             "model.num_blocks": 2, "model.ffn_dim": 64, "model.colour_hidden": 32,
             "render.num_samples": 16, "train.batch_scenes": 4, "train.rays_per_scene": 128}


def clevr(variant: str):
  spec = importlib.util.spec_from_file_location("clevr", os.path.join(REPO, "configs", "clevr.py"))
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


def field(config, path: str):
  section, name = path.split(".")
  return config[section][name]


def test_fast_is_the_quick_method_with_the_listed_cuts_only():
  quick, fast = clevr("quick"), clevr("fast")
  for path in METHOD_FIELDS:
    assert field(fast, path) == field(quick, path), path
  for path, value in FAST_CUTS.items():
    assert field(fast, path) == value, path
    assert field(quick, path) != value, f"{path} is not a cut"
  # Samples only inside the scene's height range, which the CLEVR config states.
  assert tuple(fast.render.z_bounds) == tuple(fast.data.scene_z_range) != ()
  assert tuple(quick.render.z_bounds) == ()


def test_variants_compose_left_to_right():
  both = clevr("fast+easy")
  assert (both.data.min_objects, both.data.max_objects, both.data.object_scale) == (1, 3, 1.6)
  for path, value in FAST_CUTS.items():
    assert field(both, path) == value, path
  # smoke after fast overrides fast's sizes; fast after smoke overrides smoke's.
  assert clevr("fast+smoke").model.point_dim == clevr("smoke").model.point_dim == 16
  assert clevr("smoke+fast").model.point_dim == 32
  assert clevr("easy").model.slot_dim == clevr("").model.slot_dim  # easy changes only the data


def test_unknown_variant_is_named():
  with pytest.raises(ValueError, match="unknown variant 'fsat'"):
    clevr("fast+fsat")


def test_fast_keeps_half_the_rays_masked_until_its_gradual_release():
  from slotlifter_jax import schedules
  fast = clevr("fast")
  t = fast.train
  keep = lambda step: float(schedules.keep_ratio(
      step, mask_max=t.mask_max, anneal_steps=t.mask_anneal_steps, mask_min=t.mask_min,
      mask_min_steps=t.mask_min_steps, mask_min_release_steps=t.mask_min_release_steps))
  assert keep(0) == pytest.approx(0.01)  # the paper's start: 99 % of the rays masked
  assert keep(t.mask_anneal_steps) == keep(t.mask_min_steps) == pytest.approx(0.5)
  # Released gradually: a quarter of the rays masked halfway through the release, none at the end.
  assert keep(t.mask_min_steps + t.mask_min_release_steps // 2) == pytest.approx(0.75)
  assert keep(t.num_steps) == 1.0
  assert t.mask_anneal_steps < t.mask_min_steps
  assert t.mask_min_steps + t.mask_min_release_steps <= t.num_steps
  assert t.select_by == "min_fg_nv"
  assert (fast.data.frame, fast.data.ray_sampling) == ("source_azimuth", "contrast")
