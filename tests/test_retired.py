"""Retired probe switches (slotlifter_jax/checkpoints.py, RETIRED): a run saved with one of them off
still resumes and evaluates; a run that had one on is refused in one line naming the field."""

import json

import pytest

from slotlifter_jax import checkpoints
from slotlifter_jax import defaults


def saved_with(**fields):
  """A saved config.json of today's base config plus `section__field=value` entries."""
  saved = json.loads(defaults.base_config().to_json_best_effort())
  for key, value in fields.items():
    section, name = key.split("__")
    saved[section][name] = value
  return saved


OFF = dict(model__slot_position_embedding=False, model__locality_floor=False,
           model__locality_floor_z=0.01, model__locality_attention=False,
           train__locality_attention_start=6000, train__slot_attention_lr_scale_steps=0)


def test_every_retired_field_is_gone_from_the_config():
  config = defaults.base_config()
  for field in checkpoints.RETIRED:
    section, name = field.split(".")
    assert name not in config[section], field


def test_a_run_saved_with_the_switches_off_is_read_as_today():
  config = defaults.base_config()
  saved = saved_with(**OFF)
  checkpoints.check_compatible(config, saved, "DIR")  # nothing raised
  assert checkpoints.config_changes(saved, config) == {}


@pytest.mark.parametrize("key, value", [
    ("model__slot_position_embedding", True), ("model__locality_floor", True),
    ("model__locality_attention", True), ("train__slot_attention_lr_scale_steps", 30000)])
def test_a_run_that_had_one_on_is_refused_naming_it(key, value):
  saved = saved_with(**dict(OFF, **{key: value}))
  with pytest.raises(checkpoints.CheckpointMismatchError) as e:
    checkpoints.check_compatible(defaults.base_config(), saved, "DIR")
  message = str(e.value)
  assert message.startswith(f"DIR: the run was made with {key.replace('__', '.')}={value!r}")
  assert "retired" in message and "\n" not in message
