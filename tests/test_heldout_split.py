"""The embedded sets' held-out test split: a seed stream of its own, the same bytes on every run,
and never opened by training, validation or the choice of a checkpoint or a restart."""

import hashlib
import json
import os
import sys

import numpy as np
import pytest

from slotlifter_jax import train
from slotlifter_jax.data import embedded
from slotlifter_jax.data import generator
from train_helpers import load_config

# The SeedSequence entry each split was drawn from before the held-out split existed: the
# generator's three splits in order. The dev split must be the former test split, scene by scene.
FORMER_STREAMS = {"train": 0, "val": 1, "test": 2}
SMALL = dict(family="clevr", num_train=1, num_val=1, num_dev=1, num_test=1, views=2,
             image_size=16, seed=5, num_workers=1, progress=False)


def _digests(folder):
  out = {}
  for name in sorted(os.listdir(folder)):
    with open(os.path.join(folder, name), "rb") as f:
      out[name] = hashlib.sha256(f.read()).hexdigest()
  return out


def _first_image(root, split):
  folder = os.path.join(root, f"clevr_567_{split}")
  name = sorted(n for n in os.listdir(folder) if n.endswith("az00.png"))[0]
  from PIL import Image
  return np.asarray(Image.open(os.path.join(folder, name)))


def test_heldout_split_has_its_own_stream_and_the_same_bytes_on_a_second_run(tmp_path):
  a, b = tmp_path / "a", tmp_path / "b"
  generator.generate_dataset(str(a), **SMALL)
  generator.generate_dataset(str(b), **SMALL)
  for split in ("train", "val", "dev", "test"):
    assert _digests(a / f"clevr_567_{split}") == _digests(b / f"clevr_567_{split}"), split
  # dev is what the former test split drew: scene 0 rendered from that stream, independently.
  family = generator.FAMILIES.index("clevr")
  rng = np.random.default_rng(np.random.SeedSequence([5, family, FORMER_STREAMS["test"], 0]))
  former_test = generator.generate_scene(rng, family="clevr", views=2, image_size=16)
  np.testing.assert_array_equal(_first_image(a, "dev"), former_test.rgb[0])
  # The held-out scene is none of the scenes any earlier stream draws at that index.
  heldout = _first_image(a, "test")
  for split in ("train", "val", "dev"):
    assert not np.array_equal(heldout, _first_image(a, split)), split
  streams = list(generator.SPLIT_STREAMS.values())
  assert len(set(streams)) == len(streams)
  assert generator.SPLIT_STREAMS["test"] not in FORMER_STREAMS.values()


@pytest.mark.slow
def test_training_validation_and_selection_never_open_the_heldout_split(tmp_path, monkeypatch):
  monkeypatch.setenv("SLOTLIFTER_DATA_CACHE", str(tmp_path / "cache"))
  config = load_config()
  root = embedded.resolve_data(config).data.root  # generated before anything is watched
  heldout = os.path.realpath(os.path.join(root, f"{config.data.subset}_test"))
  assert os.path.isfile(os.path.join(heldout, "dataset.json"))
  # A restart and a best checkpoint: every choice a run makes happens below.
  config.train.restarts = 1
  config.train.restart_check_step = config.train.eval_every
  config.train.restart_min_score = 2.0  # above any ARI: the first attempt restarts
  opened = []
  watching = {"on": False}

  def audit(event, args):
    if watching["on"] and event == "open" and isinstance(args[0], (str, bytes, os.PathLike)):
      opened.append(os.path.realpath(os.fsdecode(args[0])))
  sys.addaudithook(audit)  # cannot be removed: `watching` switches it off after the test
  watching["on"] = True
  try:
    with open(os.path.join(heldout, "dataset.json")):  # the hook sees an open of the split
      pass
    assert opened and opened[-1].startswith(heldout)
    opened.clear()
    train.train_and_evaluate(config, str(tmp_path / "run"))
  finally:
    watching["on"] = False
  assert os.path.isdir(tmp_path / "run" / "restarted")  # the check ran and chose
  # Each training session (the first attempt, the restarted one) recorded its machine.
  with open(tmp_path / "run" / "machines.jsonl") as f:
    machines = [json.loads(line) for line in f]
  assert [m["step"] for m in machines] == [0, 0] and all("cpu_model" in m for m in machines)
  assert any(p.startswith(os.path.realpath(root)) for p in opened)  # it did read the data
  assert not [p for p in opened if p.startswith(heldout)]
