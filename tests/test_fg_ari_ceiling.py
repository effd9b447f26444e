"""experiments/fg_ari_ceiling.py: its edge pixels by hand, its scores against sklearn, its command."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import fg_ari_ceiling  # noqa: E402
from slotlifter_jax.data.types import Scene  # noqa: E402

from tests import data_fixtures as fx  # noqa: E402


def test_edge_pixels_by_hand():
  labels = np.zeros((5, 6), np.int32)
  labels[1:4, 1:4] = 1  # a 3×3 object: its ring of 8 is edge, its centre is not
  labels[0:2, 5] = 2  # two pixels at the image's border: no neighbour outside the image counts
  want = np.zeros((5, 6), bool)
  want[1:4, 1:4] = True
  want[2, 2] = False
  want[0:2, 5] = True  # each has a background 4-neighbour inside the image (left or below)
  np.testing.assert_array_equal(fg_ari_ceiling.edge_pixels(labels), want)
  full = np.ones((3, 3), np.int32)  # one object filling the image has no edge
  assert not fg_ari_ceiling.edge_pixels(full).any()


def test_perturbed_variants():
  labels = np.zeros((5, 5), np.int32)
  labels[1:4, 1:4] = 2
  labels[0, 4] = 1
  one = fg_ari_ceiling.perturbed(labels, "one_pixel")
  changed = np.argwhere(one != labels)
  # The first (raster order) edge pixel of the smallest label, object 1 at (0, 4), goes to 0.
  assert changed.tolist() == [[0, 4]] and one[0, 4] == 0
  edge = fg_ari_ceiling.perturbed(labels, "edge")
  assert (edge[1:4, 1:4] == 0).sum() == 8 and edge[2, 2] == 2
  np.testing.assert_array_equal(fg_ari_ceiling.perturbed(labels, "truth"), labels)
  with pytest.raises(ValueError, match="unknown variant 'blur'"):
    fg_ari_ceiling.perturbed(labels, "blur")


def _scene(masks):
  n, h, w = masks.shape
  return Scene(name="s", images=np.zeros((n, h, w, 3), np.float32),
               cam_to_world=np.tile(np.eye(4, dtype=np.float32), (n, 1, 1)),
               intrinsics=np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), source_indices=(0,),
               masks=masks.astype(np.int32))


def _sklearn_fg(true, pred):
  on = true != 0
  return adjusted_rand_score(true[on], pred[on])


@pytest.mark.parametrize("objects", [1, 3])
def test_scene_scores_against_sklearn(objects):
  rng = np.random.default_rng(objects)
  masks = np.zeros((3, 12, 12), np.int32)
  for view in range(3):
    for label in range(1, objects + 1):
      r, c = rng.integers(0, 9, size=2)
      masks[view, r:r + 3, c:c + 3] = label
  masks[0, 0:3, 0:3] = 1  # the source view always shows object 1
  row = fg_ari_ceiling.scene_scores(_scene(masks))
  assert row["num_objects"] == len(np.unique(masks[0][masks[0] > 0]))
  for variant in fg_ari_ceiling.VARIANTS:
    pred = np.stack([fg_ari_ceiling.perturbed(v, variant) for v in masks])
    assert row[variant]["fg_ari"] == pytest.approx(_sklearn_fg(masks[0], pred[0]), abs=1e-12)
    nv = np.mean([adjusted_rand_score(masks[v].ravel(), pred[v].ravel()) for v in (1, 2)])
    assert row[variant]["nv_ari"] == pytest.approx(nv, abs=1e-12)
  assert row["truth"]["fg_ari"] == 1.0
  if row["num_objects"] == 1:
    # One object: a single pixel given to another label scores exactly 0.
    assert row["one_pixel"]["fg_ari"] == 0.0


def test_summarise_groups_by_count():
  rows = [{"num_objects": n, **{v: {"fg_ari": f, "nv_ari": 1.0 - f}
                                  for v in fg_ari_ceiling.VARIANTS}}
          for n, f in ((1, 0.0), (2, 0.5), (2, 1.0))]
  summary = fg_ari_ceiling.summarise(rows)
  assert summary["1"]["scenes"] == 1 and summary["2"]["scenes"] == 2
  assert summary["2"]["edge"]["fg_ari"] == pytest.approx(0.75)
  assert summary["all"]["truth"]["nv_ari"] == pytest.approx(0.5)


def test_command_line(tmp_path):
  root = tmp_path / "data"
  fx.write_generated_split(root / "clevr_567_val", split="val", num_scenes=2, views=4, size=(6, 6))
  out = tmp_path / "ceiling.json"
  run = subprocess.run(
      [sys.executable, "experiments/fg_ari_ceiling.py", "--config=configs/clevr.py",
       f"--set=data.root={root}", "--set=data.image_size=6", f"--out={out}"],
      cwd=REPO, capture_output=True, text=True, timeout=300)
  assert run.returncode == 0, run.stderr[-2000:]
  assert "| all | 2 | 1.000 | 1.000 |" in run.stdout
  result = json.loads(out.read_text())
  assert result["split"] == "val" and result["by_object_count"]["all"]["scenes"] == 2
  assert result["provenance"]["config"]["data"]["root"] == str(root)
  bad = subprocess.run([sys.executable, "experiments/fg_ari_ceiling.py", "--set=data.root"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
  assert bad.returncode == 2 and "--set='data.root': expected KEY=VALUE" in bad.stderr
