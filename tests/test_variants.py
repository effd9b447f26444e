"""Config variants: `scene` cuts the model, not the method; variants compose left to right."""

import importlib.util
import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# What makes the method the paper's: lifting, slot density, masking, loss-relevant switches.
METHOD_FIELDS = ("model.feature_lifting", "model.density_mode", "model.colour_range",
                 "train.mask_max", "train.optimizer", "data.num_source_views")
# The cuts the scene variant's docstring lists, with their values.
SCENE_CUTS = {"model.slot_dim": 32, "model.slot_mlp_dim": 64, "model.point_dim": 32,
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


def test_scene_is_the_paper_cpu_method_with_the_listed_cuts_only():
  paper_cpu, scene = clevr("paper_cpu"), clevr("scene")
  for path in METHOD_FIELDS:
    assert field(scene, path) == field(paper_cpu, path), path
  for path, value in SCENE_CUTS.items():
    assert field(scene, path) == value, path
    assert field(paper_cpu, path) != value, f"{path} is not a cut"
  # Samples only inside the scene's height range, which the CLEVR config states.
  assert tuple(scene.render.z_bounds) == tuple(scene.data.scene_z_range) != ()
  assert tuple(paper_cpu.render.z_bounds) == ()


def test_variants_compose_left_to_right():
  both = clevr("scene+easy")
  assert (both.data.min_objects, both.data.max_objects, both.data.object_scale) == (1, 3, 1.6)
  for path, value in SCENE_CUTS.items():
    assert field(both, path) == value, path
  # smoke after scene overrides scene's sizes; scene after smoke overrides smoke's.
  assert clevr("scene+smoke").model.point_dim == clevr("smoke").model.point_dim == 16
  assert clevr("smoke+scene").model.point_dim == 32
  assert clevr("easy").model.slot_dim == clevr("").model.slot_dim  # easy changes only the data


def test_unknown_variant_is_named():
  with pytest.raises(ValueError, match="unknown variant 'fsat'"):
    clevr("scene+fsat")


@pytest.mark.parametrize("old, new", [("fast", "scene"), ("quick", "paper_cpu")])
def test_a_former_variant_name_is_refused_with_its_new_one(old, new):
  for variant in (old, f"{old}+easy", f"easy+{old}"):
    with pytest.raises(ValueError) as e:
      clevr(variant)
    assert str(e.value) == f"variant {old!r} was renamed {new!r}; use the new name"


def test_scene_keeps_half_the_rays_masked_until_its_gradual_release():
  from slotlifter_jax import schedules
  scene = clevr("scene")
  t = scene.train
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
  assert (scene.data.frame, scene.data.ray_sampling) == ("source_azimuth", "contrast")


# The scene variant's schedule fields at its own budget, as they were written before they followed it.
SCENE_SCHEDULE = {"num_steps": 50_000, "warmup_steps": 500, "decay_steps": 200_000,
                 "mask_anneal_steps": 20_000, "noise_anneal_steps": 20_000,
                 "locality_steps": 20_000, "mask_min_steps": 40_000,
                 "mask_min_release_steps": 10_000, "ema_start_step": 40_000,
                 "restart_check_step": 14_000}
PAPER_CPU_SCHEDULE = {"num_steps": 6500, "warmup_steps": 200, "decay_steps": 4000,
                  "mask_anneal_steps": 3000, "noise_anneal_steps": 3000, "locality_steps": 4000}


def test_schedules_at_the_variants_own_budgets_are_unchanged():
  for variant, schedule in (("scene", SCENE_SCHEDULE), ("paper_cpu", PAPER_CPU_SCHEDULE)):
    train = clevr(variant).train
    assert {k: train[k] for k in schedule} == schedule, variant
    resolved = clevr(variant).copy_and_resolve_references().train
    assert {k: resolved[k] for k in schedule} == schedule, variant


def test_halving_the_budget_halves_every_schedule_unless_set_explicitly():
  for variant, schedule in (("scene", SCENE_SCHEDULE), ("paper_cpu", PAPER_CPU_SCHEDULE)):
    config = clevr(variant)
    config.train.num_steps = schedule["num_steps"] // 2
    halved = {k: config.train[k] for k in schedule}
    expected = {k: v // 2 for k, v in schedule.items()}
    if "restart_check_step" in schedule:
      # 7000 lies between validations (every 2000 steps): the nearest on that grid, halves up.
      assert config.train.eval_every == 2000
      expected["restart_check_step"] = 8000
    assert halved == expected, variant
  # A field set explicitly wins over its share of the budget, in either order.
  config = clevr("scene")
  config.train.mask_min_steps = 30_000
  config.train.num_steps = 60_000
  assert (config.train.mask_min_steps, config.train.ema_start_step) == (30_000, 48_000)
  # The restart check stays on the validation grid when that moves.
  config.train.eval_every = 5000
  assert config.train.restart_check_step == 15_000


def test_command_line_overrides_move_the_schedules_and_config_json_holds_numbers(tmp_path):
  import json
  import subprocess
  import sys
  script = (
      "import sys\n"
      "from absl import flags\n"
      "from ml_collections import config_flags\n"
      "config_flags.DEFINE_config_file('config')\n"
      "flags.FLAGS(sys.argv)\n"
      "print(flags.FLAGS.config.to_json_best_effort())\n")
  out = subprocess.run(
      [sys.executable, "-c", script, f"--config={REPO}/configs/clevr.py:scene",
       "--config.train.num_steps=25000", "--config.train.locality_steps=30000"],
      capture_output=True, text=True, check=True).stdout
  train = json.loads(out)["train"]
  assert (train["num_steps"], train["mask_anneal_steps"], train["mask_min_steps"],
          train["mask_min_release_steps"], train["ema_start_step"],
          train["restart_check_step"]) == (25_000, 10_000, 20_000, 5000, 20_000, 8000)
  assert train["locality_steps"] == 30_000  # set explicitly
