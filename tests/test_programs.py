"""The process's shared jitted programs (slotlifter_jax/programs.py): equal requests get the same
function, different ones do not, and only the most recent are kept."""

import jax

from slotlifter_jax import model as model_lib
from slotlifter_jax import programs
from slotlifter_jax import train_step as step_lib
from train_helpers import load_config

def test_equal_keys_share_one_build_and_the_oldest_is_dropped():
  tag = "lru-test"  # keys no other test uses
  builds = []
  def build(name):
    builds.append(name)
    return object()
  first = programs.shared((tag, 0), lambda: build(0))
  assert programs.shared((tag, 0), lambda: build("again")) is first
  assert builds == [0]
  # Fill the cache with newer keys, then touch (tag, 0): the next new key evicts (tag, 1).
  programs.shared((tag, 1), lambda: build(1))
  for i in range(2, programs.MAX_PROGRAMS):
    programs.shared((tag, i), lambda i=i: build(i))
  programs.shared((tag, 0), lambda: build("again"))
  programs.shared((tag, "newest"), lambda: build("newest"))
  assert programs.shared((tag, 0), lambda: build("again")) is first
  programs.shared((tag, 1), lambda: build("rebuilt"))
  assert builds == list(range(programs.MAX_PROGRAMS)) + ["newest", "rebuilt"]


def test_config_key_tells_configs_apart_by_value():
  a, b = load_config(), load_config()
  assert a is not b and programs.config_key(a) == programs.config_key(b)
  b.train.base_lr = a.train.base_lr * 0.5
  assert programs.config_key(a) != programs.config_key(b)


def test_train_step_of_an_equal_model_and_config_is_the_same_jitted_function():
  """A second run of one config in a process (a restart, a resume in a test) reuses the trace
  and compilation; a run of another config does not."""
  config = load_config()
  config.train.base_lr = 1.25e-4  # a config no other test builds
  step = lambda c, seed: step_lib.make_train_step(model_lib.build_model(c), c,
                                                  key=jax.random.key(seed))
  a = step(config, 0)
  # An equal config (another object), another seed: the keys are arguments, one program.
  assert step(config.copy_and_resolve_references(), 1)._fn is a._fn
  other = config.copy_and_resolve_references()
  other.train.warmup_steps += 1
  assert step(other, 0)._fn is not a._fn
