"""The config checks that run before JAX starts (slotlifter_jax/config_checks.py).

The rules are the ones the fields' comments in slotlifter_jax/defaults.py state; each case below
sits on one side of a rule's boundary, so a check that moved its boundary fails here. The command
line's use of them (one line, nothing created, JAX never started) is tests/test_cli.py's.
"""

import glob
import importlib.util
import os
import subprocess
import sys

import pytest

from slotlifter_jax import config_checks

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load(path: str, variant: str = ""):
  spec = importlib.util.spec_from_file_location("config", path)
  module = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(module)
  return module.get_config(variant)


@pytest.mark.parametrize("path", sorted(glob.glob(os.path.join(REPO, "configs", "*.py"))),
                         ids=os.path.basename)
@pytest.mark.parametrize("variant", ["", "paper_cpu", "scene", "smoke", "scene+easy"])
def test_every_shipped_config_passes(path, variant):
  if "scene" in variant and os.path.basename(path) not in ("clevr.py", "room_chair.py"):
    # scene samples only inside the scene's slab, which only these sets measure: refused, never
    # silently run over the whole ray.
    with pytest.raises(ValueError, match="data.scene_z_range"):
      load(path, variant)
    return
  config_checks.check_config(load(path, variant))


def smoke(**overrides):
  """clevr.py:smoke (num_steps 6, log 2, eval 3, checkpoint 3, 2 scenes × 32 rays) with
  `section__field=value` overrides."""
  c = load(os.path.join(REPO, "configs", "clevr.py"), "smoke")
  for key, value in overrides.items():
    section, name = key.split("__")
    c[section][name] = value
  return c


@pytest.mark.parametrize("overrides", [
    dict(train__mask_min=0.99, train__mask_max=0.99),  # the floor may equal the ceiling
    dict(train__mask_min=0.0, train__mask_max=0.0),
    dict(train__lr_cooldown_steps=6),  # = num_steps
    dict(train__lr_cooldown_final=0.0), dict(train__lr_cooldown_final=1.0),
    dict(train__slot_attention_lr_scale=0.0),
    dict(train__restart_check_step=3, train__restarts=1),  # on eval_every's grid
    dict(train__restart_min_attn_agreement=-1.0), dict(train__restart_min_attn_agreement=1.0),
    dict(train__ema_decay=0.0), dict(train__ema_decay=0.999, train__ema_start_step=0),
    dict(render__supersample=3),
    dict(model__encoder_output_stride=2),
    dict(model__encoder_input_pool=2), dict(model__encoder_input_pool=4),
    dict(data__frame="source_azimuth"), dict(data__format="dtu"),
    dict(train__ray_stages=((0, 32), (4, 64))),
    dict(data__sampler="device", train__steps_per_dispatch=1, data__curriculum=((0, 1), (3, 3))),
])
def test_settings_on_the_allowed_side_pass(overrides):
  config_checks.check_config(smoke(**overrides))


@pytest.mark.parametrize("overrides, message", [
    (dict(train__mask_min=0.995), "train.mask_min=0.995 and train.mask_max=0.99 must satisfy"),
    (dict(train__mask_min=-0.01), "train.mask_min=-0.01"),
    (dict(train__mask_max=1.01), "train.mask_max=1.01"),
    (dict(train__mask_min_steps=-1), "train.mask_min_steps=-1 must be ≥ 0"),
    (dict(train__lr_cooldown_steps=7), "train.lr_cooldown_steps=7 must lie in [0, train.num_steps=6]"),
    (dict(train__lr_cooldown_final=1.01), "train.lr_cooldown_final=1.01 must lie in [0, 1]"),
    (dict(train__slot_attention_lr_scale=float("nan")), "train.slot_attention_lr_scale=nan"),
    (dict(train__select_by="fg_ari"), "train.select_by must be one of"),
    (dict(train__restart_check_step=4), "train.restart_check_step=4 must be 0 (no check) or a "
                                        "multiple of train.eval_every=3"),
    (dict(train__restarts=-1), "train.restarts=-1 must be ≥ 0"),
    (dict(train__restart_min_attn_agreement=1.5), "train.restart_min_attn_agreement=1.5 must lie "
                                                  "in [-1, 1]"),
    (dict(train__restart_min_attn_agreement=float("nan")),
     "train.restart_min_attn_agreement=nan must lie in [-1, 1]"),
    (dict(train__ema_decay=1.0), "train.ema_decay is 1.0"),
    (dict(train__ema_start_step=-1), "train.ema_start_step is -1"),
    (dict(train__grad_accum_chunks=3), "train.batch_scenes=2 must be a multiple of "
                                       "train.grad_accum_chunks=3"),
    (dict(train__ray_chunks=3), "train.rays_per_scene=32 must be a multiple of train.ray_chunks=3"),
    (dict(data__format="nerf"), "data.format must be one of ('uorf', 'uocf', 'dtu', 'scannet'), "
                                "got 'nerf'"),
    (dict(data__frame="camera"), "data.frame must be one of ('world', 'source_azimuth'), got "
                                 "'camera'"),
    (dict(data__sampler="gpu"), "data.sampler is 'gpu'; use one of ('host', 'device')"),
    (dict(train__steps_per_dispatch=2), "train.steps_per_dispatch=2 needs data.sampler=device"),
    (dict(data__curriculum=((0, 1),)), "data.curriculum needs data.sampler=device"),
    (dict(data__sampler="device", train__steps_per_dispatch=2),  # log 2, eval 3: eval is not
     "train.eval_every=3 is not a multiple of train.steps_per_dispatch=2"),
    (dict(data__sampler="device", train__steps_per_dispatch=0), "train.steps_per_dispatch is 0"),
    (dict(data__sampler="device", data__scene_stages=((0, 1),)),
     "data.scene_stages needs data.sampler=host"),
    (dict(data__sampler="device", data__curriculum=((3, 1), (0, 3))),
     "data.curriculum: start steps [3, 0] are not increasing"),
    (dict(data__sampler="device", data__curriculum=((0, 1, 2),)),
     "data.curriculum: stage (0, 1, 2) is not (start_step, max_objects)"),
    (dict(render__supersample=0), "render.supersample is 0; it must be an integer ≥ 1"),
    (dict(render__supersample=True), "render.supersample is True"),
    (dict(model__encoder_output_stride=3), "model.encoder_output_stride is 3"),
    (dict(model__encoder_input_pool=0), "model.encoder_input_pool is 0; it must be an integer ≥ 1"),
    (dict(model__encoder_input_pool=3),
     "model.encoder_input_pool is 3; data.image_size 32 must divide by it"),
    (dict(train__ray_stages=((0, 32), (0, 64))), "train.ray_stages: start steps [0, 0] must be "
                                                 "≥ 0 and strictly increasing"),
    (dict(train__ray_stages=((0, 0),)), "train.ray_stages: 0 (stage from step 0) must lie in"),
])
def test_a_setting_on_the_wrong_side_is_named(overrides, message):
  with pytest.raises(config_checks.ConfigError) as e:
    config_checks.check_config(smoke(**overrides))
  assert message in str(e.value)
  assert "\n" not in str(e.value)


def test_the_checks_and_the_command_line_load_no_jax():
  # What lets `python -m slotlifter_jax.main` report a bad field before JAX starts.
  code = ("import sys; import slotlifter_jax.config_checks, slotlifter_jax.main; "
          "print(sorted(m for m in ('jax', 'jaxlib', 'numpy', 'flax') if m in sys.modules))")
  out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                       check=True)
  assert out.stdout.strip() == "[]", out.stdout + out.stderr
