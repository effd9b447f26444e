"""experiments/profile_step.py: the JSON it writes carries its provenance record. Assembled from
made-up timings, so that no step is compiled or profiled."""

import collections
import json
import os
import sys

from slotlifter_jax import provenance
from train_helpers import load_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import profile_step  # noqa: E402


def test_the_written_record_carries_provenance():
  config = load_config()
  by_scope = collections.Counter({("forward", "encoder"): 0.25, ("backward", "decoder"): 0.5})
  by_phase = collections.Counter({"forward": 0.25, "backward": 0.5})
  record = profile_step.result_record("A", config, wall=1.0, attributed=0.75, by_phase=by_phase,
                                      by_scope=by_scope, wall_s=40.0)
  assert record["config"] == "A" and record["attributed_s_per_step"] == 0.75
  assert record["by_phase"] == {"forward": 0.25, "backward": 0.5}
  assert record["by_scope"][0] == dict(phase="backward", scope="decoder", seconds=0.5)
  prov = provenance.of(record)
  assert prov["wall_s"] == 40.0 and prov["config"] == provenance.config_dict(config)
  assert {"git_commit", "cpu_model", "platform", "jax"} <= set(prov)
  json.dumps(record, allow_nan=False)
