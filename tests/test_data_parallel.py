"""Data parallelism: the train step sharded over four (forced host) devices computes what it
computes on one device."""

import os
import subprocess
import sys
import textwrap

import pytest

from train_helpers import REPO


@pytest.mark.slow
def test_four_devices_match_one_device():
  script = textwrap.dedent(f"""
    import os, sys
    flags = os.environ.get("XLA_FLAGS", "")  # the suite's compile level (tests/conftest.py)
    os.environ["XLA_FLAGS"] = flags + " --xla_force_host_platform_device_count=4"
    sys.path.insert(0, {os.path.join(REPO, "tests")!r})
    import jax, numpy as np
    from train_helpers import load_config, fake_batch
    from slotlifter_jax import model as model_lib, train_step as step_lib
    assert len(jax.devices()) == 4
    config = load_config()
    config.train.batch_scenes = 4
    model = model_lib.build_model(config)
    batches = [fake_batch(config, seed=i) for i in range(3)]
    losses = {{}}
    for n in (1, 4):
      mesh = step_lib.make_mesh(jax.devices()[:n])
      state = step_lib.init_state(model, config, batches[0], jax.random.key(0))
      state = jax.device_put(state, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
      step = step_lib.make_train_step(model, config, key=jax.random.key(1), mesh=mesh)
      out = []
      for b in batches:
        state, m = step(state, step_lib.shard_batch(b, mesh))
        out.append(float(m["loss"]))
      losses[n] = out
    print("losses", losses)
    np.testing.assert_allclose(losses[1], losses[4], rtol=1e-4)
  """)
  result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=600)
  assert result.returncode == 0, result.stdout + result.stderr
