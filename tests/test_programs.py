"""The process's shared jitted programs (slotlifter_jax/programs.py): equal requests get the same
function, different ones do not, and only the most recent are kept."""

import jax

from slotlifter_jax import model as model_lib
from slotlifter_jax import programs
from slotlifter_jax import train_step as step_lib
from train_helpers import fake_batch, load_config

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


def test_init_state_after_state_shapes_does_not_trace_the_init_again():
  """A fresh run asks for the state's shapes (the restore target) and then for the state: the
  model's init is traced once, by the first. Counted with JAX's own trace events."""
  traced = []
  def listener(event, duration, **kwargs):
    if event == "/jax/core/compile/jaxpr_trace_duration":
      traced.append(kwargs.get("fun_name"))
  jax.monitoring.register_event_duration_secs_listener(listener)
  try:
    config = load_config()
    config.model.slot_mlp_dim = 48  # models no other test builds: nothing is traced yet
    batch = fake_batch(config)
    model = model_lib.build_model(config)
    shapes = step_lib.state_shapes(model, config, batch)
    assert traced.count("init_variables") == 1
    state = step_lib.init_state(model, config, batch, jax.random.key(3))
    assert traced.count("init_variables") == 1
    assert jax.tree.structure(shapes) == jax.tree.structure(state)
    assert [(s.shape, s.dtype) for s in jax.tree.leaves(shapes)] == [
        (x.shape, x.dtype) for x in jax.tree.leaves(state)]
    # Without state_shapes first, init_state traces it (so the count above can tell).
    config.model.slot_mlp_dim = 40
    step_lib.init_state(model_lib.build_model(config), config, batch, jax.random.key(3))
    assert traced.count("init_variables") == 2
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)
