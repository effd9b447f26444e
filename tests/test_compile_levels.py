"""experiments/compile_levels.py: the JSON it writes carries its provenance record, with the
configs it measured. Assembled from made-up results, so that nothing is compiled."""

import json
import os
import sys

from slotlifter_jax import provenance
from train_helpers import load_config

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import compile_levels  # noqa: E402


def test_the_written_record_carries_provenance_with_each_config():
  results = [dict(config="clevr:smoke", num_params=10, levels=[dict(level=3, init_compile_s=1.0)])]
  config = compile_levels._config("clevr:smoke")
  record = compile_levels.result_record("cpu", 3, results, {"clevr:smoke": config}, wall_s=8.0)
  assert (record["platform"], record["steps"], record["results"]) == ("cpu", 3, results)
  prov = provenance.of(record)
  assert prov["wall_s"] == 8.0
  assert prov["config"] == {"clevr:smoke": provenance.config_dict(load_config("clevr", "smoke"))}
  assert {"git_commit", "cpu_model", "platform", "jax"} <= set(prov)
  json.dumps(record, allow_nan=False)
