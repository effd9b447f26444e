"""experiments/room_tables.py: docs/rooms.md's tables read the room runs' files as written, on
hand-made files whose numbers are known."""

import json
import os
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

import pytest  # noqa: E402

from experiments import room_tables  # noqa: E402
from experiments import table_common  # noqa: E402


@pytest.fixture
def results(tmp_path, monkeypatch):
  monkeypatch.setattr(table_common, "RESULTS", str(tmp_path))
  return tmp_path


def _write_eval(results, run, *, split="val"):
  metrics = {k: {"mean": v, "stderr": 0.01} for k, v in
             dict(fg_ari=0.5, fg_ari_multi=0.7, nv_ari=0.6, psnr_novel=18.0, psnr_source=24.04,
                  psnr_novel_seen=19.26, psnr_novel_unseen=17.14).items()}
  (results / f"{run}_val100_metrics.json").write_text(json.dumps(
      {"split": split, "checkpoint": {"step": 42000}, "parameters": "average", "metrics": metrics,
       "provenance": {"platform": "cpu", "cpu_model": "Test CPU", "cpu_count": 2}}))
  # Two scenes of one object (FG-ARI ≥ 2 undefined), two of two, one of three.
  lines = ["scene,fg_ari_multi,active_slots,num_objects", "a,nan,2,1", "b,nan,3,1",
           "c,0.5,3,2", "d,0.9,4,2", "e,0.6,5,3"]
  (results / f"{run}_val100_per_scene.csv").write_text("\n".join(lines) + "\n")


def test_val100_splits_the_scenes_by_their_object_count(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_VAL100", (("chairs", "run"),))
  _write_eval(results, "run")
  lines = room_tables.room_val100()
  row = lines[2]
  # FG-ARI ≥ 2 by count: (0.5 + 0.9) / 2 = 0.70 for two objects, 0.60 for three; one-object
  # scenes have none. Slots in use: 2.5, 3.5, 5.0.
  assert row.startswith("| chairs | step 42000, average | 0.500 ± 0.010 | 0.700 ± 0.010 |"), row
  assert "| 18.00 ± 0.01 | 24.0 / 19.3 / 17.1 | 0.70 / 0.60 | 2.5 / 3.5 / 5.0 |" in row, row
  assert "a 2-core Test CPU" in lines[4]


def test_val100_refuses_an_evaluation_of_another_split(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_VAL100", (("chairs", "run"),))
  _write_eval(results, "run", split="test")
  with pytest.raises(table_common.TableError, match="run_val100_metrics.json: split 'test'"):
    room_tables.room_val100()


def test_curves_keep_the_last_validation_of_a_step_validated_again_after_a_resume(results,
                                                                                  monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_CURVES", (("chairs", "run"),))
  row = lambda step, fg: json.dumps(dict(step=step, kind="val", fg_ari_multi=fg, nv_ari=0.3,
                                         attn_fg_ari=0.2, mf_attn_agreement=fg / 2))
  train = json.dumps(dict(step=4000, kind="train", loss=0.1))
  (results / "run_val_metrics.jsonl").write_text(
      "\n".join([row(4000, 0.1), train, row(8000, 0.4), row(8000, 0.45)]) + "\n")
  line = room_tables.room_curves()[2]
  assert line == ("| chairs | 0.10 / 0.30 / 0.20 | 0.45 / 0.30 / 0.20 | – | – | – | – | "
                  "8000: 0.45 / 0.30 / 0.20 | "
                  "– / 0.05 / – / 0.23 / – |")


def test_a_missing_file_names_itself(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_CURVES", (("chairs", "absent"),))
  with pytest.raises(table_common.TableError, match="absent_val_metrics.jsonl: cannot read"):
    room_tables.room_curves()


def _write_routing(results, name, *, split="val", step=1234, **extra):
  summary = dict(pairs=6, attention_parts=5, rendering_parts=3, both_part=3,
                 attention_parts_rendering_merges=2, merged_into_one_of_theirs=1, objects=7,
                 rendered_slot_is_attention_slot=4,
                 slot_roles=dict(attention=[[0.9, 0.1, 0, 0, 0], [0.1, 0.2, 0.3, 0.4, 0]],
                                 rendering=[[1, 0, 0, 0, 0], [0.5, 0.5, 0, 0, 0]]))
  (results / f"{name}.json").write_text(json.dumps(
      {"split": split, "step": step, "scenes": 100, "summary": summary, **extra,
       "provenance": {"platform": "cpu", "cpu_model": "Test CPU", "cpu_count": 2}}))


def test_slot_routing_reads_objects_pixels_and_the_backgrounds_slot_0(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_SLOT_ROUTING", (("seed 9", "routing"),))
  _write_routing(results, "routing")
  lines = room_tables.room_slot_routing()
  assert lines[2] == ("| seed 9 | 1234 | 5 / 3 / 3 of 6 | 2 (1 into one of theirs) | 4 of 7 | "
                      "0.10 / 0.20 / 0.30 / 0.40 / 0.00 | 0.50 / 0.50 / 0.00 / 0.00 / 0.00 | "
                      "0.90 | – |")
  assert "a 2-core Test CPU" in lines[4] and "routing.json" in lines[5]


def test_slot_routing_adds_the_same_checkpoint_rendered_without_lifted_features(
    results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_SLOT_ROUTING", (("seed 9", "routing"),))
  _write_routing(results, "routing")
  _write_routing(results, "routing_dropped", lifted="dropped")
  lines = room_tables.room_slot_routing()
  # The dropped file's rendering parts 3 of 6 pairs and gives slot 0 half the chairs' pixels.
  assert lines[2].endswith("| 0.90 | 3 of 6, 0.50 |")
  assert "routing.json" in lines[5] and "routing_dropped.json" in lines[5]
  # Another checkpoint, or a file that rendered with the lifted features, is refused by name.
  for bad in (dict(step=999, lifted="dropped"), dict(lifted="kept")):
    _write_routing(results, "routing_dropped", **bad)
    with pytest.raises(table_common.TableError, match="routing_dropped.json: not routing.json"):
      room_tables.room_slot_routing()


def test_slot_routing_refuses_another_split(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_SLOT_ROUTING", (("seed 9", "routing"),))
  _write_routing(results, "routing", split="test")
  with pytest.raises(table_common.TableError, match="routing.json: split 'test'"):
    room_tables.room_slot_routing()


def test_val100_refuses_an_evaluation_without_the_psnr_split(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_VAL100", (("chairs", "run"),))
  _write_eval(results, "run")
  path = results / "run_val100_metrics.json"
  record = json.loads(path.read_text())
  del record["metrics"]["psnr_novel_seen"]
  path.write_text(json.dumps(record))
  with pytest.raises(table_common.TableError,
                     match="run_val100_metrics.json: no psnr_novel_seen in its metrics"):
    room_tables.room_val100()


def _write_placement(results, name, *, split="val", drop=()):
  means = dict(opacity_source_bg=0.861, opacity_source_fg=0.674, depth_bias_source_bg=-0.071,
               depth_bias_source_fg=0.262, opacity_seen_bg=0.85, opacity_seen_fg=0.55,
               psnr_seen_bg=20.97, psnr_seen_fg=15.54, displacement_px_seen_bg=10.06,
               displacement_px_seen_fg=23.09, nv_ari_seen=0.558, nv_ari_unseen=0.395,
               nv_ari_seen_transported=0.714)
  for key in drop:
    del means[key]
  (results / f"{name}.json").write_text(json.dumps(
      {"split": split, "step": 50000, "parameters": "average", "scenes": 100, "means": means,
       "log_density_scale": -3.682,
       "provenance": {"platform": "cpu", "cpu_model": "Test CPU", "cpu_count": 2}}))


def test_depth_placement_reads_each_region(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_DEPTH_PLACEMENT", (("seed 9", "placement"),))
  _write_placement(results, "placement")
  lines = room_tables.room_depth_placement()
  assert lines[2] == ("| seed 9 | step 50000, average, 100 scenes | -3.68 | 0.86 / 0.67 | "
                      "-0.07 / +0.26 | "
                      "0.85 / 0.55 | 10.1 / 23.1 | 21.0 / 15.5 | 0.558 / 0.395 | 0.714 |")
  assert "a 2-core Test CPU" in lines[4] and "placement.json" in lines[5]


def test_depth_placement_refuses_another_split_and_a_missing_figure(results, monkeypatch):
  monkeypatch.setattr(room_tables, "ROOM_DEPTH_PLACEMENT", (("seed 9", "placement"),))
  _write_placement(results, "placement", split="test")
  with pytest.raises(table_common.TableError, match="placement.json: split 'test'"):
    room_tables.room_depth_placement()
  _write_placement(results, "placement", drop=("nv_ari_unseen",))
  with pytest.raises(table_common.TableError,
                     match="placement.json: no nv_ari_unseen in its means"):
    room_tables.room_depth_placement()
