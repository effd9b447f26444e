"""Evaluation and pictures (docs/method.md §4, §8) end to end on a smoke run: the eval and render
modes, what they write, and their refusals. Their pure functions on made-up renderings (per-scene
aggregation against sklearn/NumPy references, orbit cameras) are in test_evaluate_functions.py; the
metric functions themselves (ARI, SSIM, LPIPS, mBO, …) in test_metrics.py.
"""

import csv
import json
import math
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from slotlifter_jax import checkpoints as ckpt_lib
from slotlifter_jax import emergence
from slotlifter_jax import evaluate
from slotlifter_jax import train
from slotlifter_jax import validation
from slotlifter_jax.data import embedded
from slotlifter_jax.data import registry
from slotlifter_jax.data.types import DataError
from slotlifter_jax.rendering import pictures
from slotlifter_jax.rendering import volume
from train_helpers import load_config

# ---------------------------------------------------------------------------------------------
# End to end on a smoke run (one training shared by the tests below)
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
  workdir = str(tmp_path_factory.mktemp("eval_run"))
  train.train_and_evaluate(load_config(), workdir)
  return workdir


@pytest.mark.slow
def test_eval_writes_metrics_and_refuses_to_overwrite(run_dir):
  config = load_config()
  result = evaluate.evaluate_split(config, run_dir, split="test", progress=False)
  path = os.path.join(run_dir, "eval", "test", "metrics.json")
  assert result.metrics_path == path
  with open(path) as f:
    report = json.load(f)

  # The best checkpoint holds the run's highest validation score, as its metrics log records it
  # (the score is train.select_by's, logged with each validation).
  validations = [r for r in emergence.load_records(os.path.join(run_dir, "metrics.jsonl"))
                 if r.get("kind") == "val"]
  assert len(validations) >= 2, validations  # a choice between checkpoints was made
  score = {int(r["step"]): r["score"] for r in validations}
  assert score[report["checkpoint"]["step"]] == max(score.values()), (report["checkpoint"], score)
  # Where the numbers came from (slotlifter_jax/provenance.py).
  record = report["provenance"]
  assert record["config"]["model"] == json.loads(config.model.to_json_best_effort())
  assert record["jax"] == jax.__version__ and record["wall_s"] > 0
  assert record["platform"] == jax.devices()[0].platform
  num_scenes = config.data.num_test_scenes
  assert report["num_scenes"] == num_scenes
  assert report["quirks"] == {"lpips_quirk": False, "nv_ari_last_view": False}
  assert report["lpips_net"] == "alex"
  assert report["differs_from_training"] == {}
  ranges = {"psnr_source": (0, 100), "psnr_novel": (0, 100), "ssim": (-1, 1), "lpips": (0, 2),
            "ari": (-1, 1), "fg_ari": (-1, 1), "nv_ari": (-1, 1), "nv_fg_ari": (-1, 1),
            "mbo": (0, 1), "miou": (0, 1), "nv_mbo": (0, 1), "nv_miou": (0, 1),
            "active_slots": (0, config.model.num_slots), "num_objects": (1, 7),
            # The embedded set stores depth, so novel PSNR is also split by source visibility.
            "psnr_novel_seen": (0, 100), "psnr_novel_unseen": (0, 100),
            "unseen_pixel_share": (0, 1), "unseen_error_share": (0, 1),
            "psnr_novel_fg": (0, 100), "psnr_novel_bg": (0, 100), "fg_error_share": (0, 1),
            "psnr_novel_border": (0, 100), "psnr_novel_bg_far": (0, 100),
            "border_pixel_share": (0, 1), "border_error_share": (0, 1)}
  for name, (lo, hi) in ranges.items():
    m = report["metrics"][name]
    assert m["count"] == num_scenes, name
    assert lo <= m["mean"] <= hi and math.isfinite(m["stderr"]), (name, m)
    assert name in report["definitions"]
  assert report["timing"]["total_s"] > 0

  with open(os.path.join(run_dir, "eval", "test", "per_scene.csv")) as f:
    rows = list(csv.DictReader(f))
  scenes = registry.load_split(embedded.resolve_data(load_config()).data, "test")
  assert [r["scene"] for r in rows] == [s.name for s in scenes]
  for name in ranges:  # the JSON means are the means of the CSV rows
    assert report["metrics"][name]["mean"] == pytest.approx(
        np.mean([float(r[name]) for r in rows]))

  with open(path, "rb") as f:
    before = f.read()
  mtime = os.stat(path).st_mtime_ns
  with pytest.raises(FileExistsError, match="--overwrite"):
    evaluate.evaluate_split(config, run_dir, split="test", progress=False)
  with open(path, "rb") as f:
    assert f.read() == before
  assert os.stat(path).st_mtime_ns == mtime

  # Rendered with other settings than it was trained with: the file says so.
  other = load_config()
  other.render.num_samples = config.render.num_samples + 8
  other.render.chunk = config.render.chunk // 2  # the same samples, computed in smaller pieces
  other.model.slot_iters = config.model.slot_iters + 2  # shapes no parameter: allowed, recorded
  evaluate.evaluate_split(other, run_dir, split="test", overwrite=True, max_scenes=1,
                          checkpoint="latest", lpips_quirk=True, nv_ari_last_view=True,
                          progress=False)
  with open(path) as f:
    again = json.load(f)
  assert again["differs_from_training"] == {
      "render.num_samples": [config.render.num_samples, config.render.num_samples + 8],
      "model.slot_iters": [config.model.slot_iters, config.model.slot_iters + 2]}
  assert again["num_scenes"] == 1 and again["metrics"]["nv_ari"]["count"] == 1
  assert again["quirks"] == {"lpips_quirk": True, "nv_ari_last_view": True}
  assert again["checkpoint"]["step"] == config.train.num_steps
  assert "last novel view" in again["definitions"]["nv_ari"]
  with open(os.path.join(run_dir, "eval", "test", "per_scene.csv")) as f:
    assert len(list(csv.DictReader(f))) == 1


@pytest.mark.slow
def test_eval_takes_the_workdir_relative_to_the_current_folder(run_dir, monkeypatch):
  """The README's commands pass `--workdir=runs/…`; orbax refuses relative checkpoint paths."""
  monkeypatch.chdir(os.path.dirname(run_dir))
  # The train split: the other tests of this run expect no eval/val or eval/test output yet.
  result = evaluate.evaluate_split(load_config(), os.path.basename(run_dir), split="train",
                                   max_scenes=1, overwrite=True, progress=False)
  assert os.path.isfile(os.path.join(run_dir, "eval", "train", "metrics.json"))
  assert result.checkpoint_step > 0


def test_eval_refuses_other_model_config(run_dir):
  config = load_config()
  config.model.num_slots = 5
  with pytest.raises(ckpt_lib.CheckpointMismatchError, match="model.num_slots"):
    evaluate.evaluate_split(config, run_dir, split="val", progress=False)


def test_eval_refuses_bad_render_settings_before_any_work(run_dir):
  config = load_config()
  config.render.supersample = 0
  with pytest.raises(evaluate.EvalSetupError, match="render.supersample is 0"):
    evaluate.evaluate_split(config, run_dir, split="val", progress=False)
  config = load_config()
  config.render.update(supersample=2, adaptive=True, z_bounds=())
  with pytest.raises(evaluate.EvalSetupError, match="render.supersample=2 is not supported"):
    evaluate.evaluate_split(config, run_dir, split="val", progress=False)


@pytest.mark.slow
def test_checkpoint_of_other_shapes_names_the_parameter(run_dir, tmp_path):
  # A run whose config.json was edited after training: the config check passes, the checkpoint
  # does not fit; the error names a slot-shaped parameter instead of an orbax traceback.
  copy = str(tmp_path / "edited")
  shutil.copytree(run_dir, copy)
  config = load_config()
  config.model.num_slots = 5
  saved = ckpt_lib.load_saved_config(copy)
  saved["model"]["num_slots"] = 5
  with open(ckpt_lib.config_path(copy), "w") as f:
    json.dump(saved, f)
  k, d = load_config().model.num_slots, config.model.slot_dim
  with pytest.raises(ckpt_lib.CheckpointMismatchError,
                     match=rf"checkpoint \({k}, {d}\), model \(5, {d}\)"):
    evaluate.evaluate_split(config, copy, split="val", progress=False)


@pytest.mark.slow
def test_eval_refuses_unknown_split_checkpoint_and_empty_folder(run_dir, tmp_path):
  config = load_config()
  with pytest.raises(evaluate.EvalSetupError, match="holdout"):
    evaluate.evaluate_split(config, run_dir, split="holdout", progress=False)
  with pytest.raises(evaluate.EvalSetupError, match="no such step"):
    evaluate.evaluate_split(config, run_dir, split="val", checkpoint="12345", progress=False)
  with pytest.raises(FileNotFoundError, match="config.json"):
    evaluate.evaluate_split(config, str(tmp_path / "never_trained"), progress=False)
  empty = tmp_path / "empty_data"
  (empty / f"{config.data.subset}_test").mkdir(parents=True)
  config.data.root = str(empty)
  with pytest.raises(DataError):  # overwrite: the other test may have written test/metrics.json
    evaluate.evaluate_split(config, run_dir, split="test", overwrite=True, progress=False)


@pytest.mark.slow
def test_per_slot_rendering_is_consistent_with_the_model(run_dir):
  run = evaluate.load_run(load_config(), run_dir, split="test", max_scenes=1)
  scene, model = run.scenes[0], run.model
  sources = pictures.SlotRenderer(model, run.config).sources(scene)
  rng = np.random.default_rng(3)
  centre = np.asarray(scene.cam_to_world[1, :3, 3])  # rays from a novel camera towards the scene
  dirs = -centre + rng.normal(scale=0.2, size=(1, 13, 3))
  dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)

  @jax.jit  # compiled: a quarter of the time of running the model op by op
  def render_rays(params):
    encoded = model.apply({"params": params}, **sources, train=False, method=model.encode)
    return pictures.render_rays(
        model, params, encoded, sources=sources,
        ray_origins=jnp.asarray(np.broadcast_to(centre, (1, 13, 3)), jnp.float32),
        ray_directions=jnp.asarray(dirs, jnp.float32))

  out = render_rays(run.params)
  # The per-sample colour and density the model returns are what it composited.
  again = volume.volume_render(density=out.density, z=out.z, colour=out.sample_colour,
                               slot_weights=out.point_slot_weights, far=model.far,
                               density_scale=model.density_scale)
  np.testing.assert_allclose(again.colour, out.coarse.colour, atol=1e-6)
  np.testing.assert_allclose(out.slot_density.sum(-1), out.density, rtol=1e-5, atol=1e-6)
  alone = pictures.render_each_slot(out, far=model.far, density_scale=model.density_scale)
  assert alone.colour.shape == (1, 13, model.num_slots, 3)
  # A slot alone is never more opaque than all slots together.
  assert np.all(np.asarray(alone.opacity) <= np.asarray(out.coarse.opacity)[..., None] + 1e-6)


@pytest.mark.slow
def test_pictures_writes_panel_and_orbit(run_dir):
  config = load_config()
  frames = 5
  files = pictures.render_scenes(config, run_dir, split="test", scene_indices=[1],
                                 num_orbit_frames=frames, progress=False)
  assert [f.scene_index for f in files] == [1]
  assert files[0].panel.endswith(os.path.join("render", "test", "scene_0001_panel.png"))
  s, k, views = config.data.image_size, config.model.num_slots, config.data.views_per_scene
  pad, header, footer = pictures.PAD, pictures.HEADER, pictures.FOOTER
  label, scale = pictures.LABEL_WIDTH, pictures.SCALE_WIDTH
  columns = 6 + k  # source, truth, mask, rendering, depth, overlay, one per slot
  panel = np.asarray(Image.open(files[0].panel).convert("RGB"), np.float32) / 255.0
  body = views * (s + pad) - pad
  assert panel.shape == (header + body + footer, label + pad + columns * (s + pad) + scale, 3)

  def tile_x(column):  # left edge of a tile column; the depth scale follows column 4 (depth)
    return label + pad + column * (s + pad) + (scale + pad if column > 4 else 0)

  def has_ink(area):  # text or a bar drawn on the white background
    return area.size > 0 and area.min() < 0.5

  # The row labels: text in each row's part of the label column, "source" differing from "novel 1".
  rows = [panel[header + i * (s + pad):header + i * (s + pad) + s, :label] for i in range(views)]
  assert all(has_ink(r) for r in rows)
  assert np.abs(rows[0] - rows[1]).max() > 0.5
  # The footer names the checkpoint and step; the header the columns.
  assert has_ink(panel[header + body:]) and has_ink(panel[:header])
  # The depth scale: a grey-framed bar from white (near, top) to black (far, bottom) over all
  # rows, and its two values printed beside it.
  x = tile_x(4) + s + pad
  bar = panel[header + 1:header + body - 1, x + pictures.DEPTH_BAR // 2, 0]
  assert bar[0] > 0.99 and bar[-1] < 0.01 and np.all(np.diff(bar) <= 1e-6)
  np.testing.assert_allclose(panel[header:header + body, x], pictures.FRAME_GREY, atol=1 / 255)
  values = panel[header:header + body, x + pictures.DEPTH_BAR:x + scale]
  assert has_ink(values[:pictures.TEXT_HEIGHT]) and has_ink(values[-pictures.TEXT_HEIGHT:])

  gif = Image.open(files[0].orbit)
  assert gif.n_frames == frames
  f = -(-pictures.ORBIT_TILE // s)  # whole enlargement factor: tiles of at least ORBIT_TILE px
  assert f * s >= pictures.ORBIT_TILE
  top = pictures.ORBIT_HEADER
  assert gif.size == (2 * f * s + pictures.ORBIT_PAD, top + f * s + pictures.BAR)
  gif.seek(0)
  frame = np.asarray(gif.convert("RGB"), np.float32) / 255.0
  # Titles above both tiles.
  assert has_ink(frame[:top, :f * s]) and has_ink(frame[:top, f * s + pictures.ORBIT_PAD:])
  # Nearest-neighbour enlargement: every rendered pixel is an f×f block of one colour.
  tiles = frame[top:top + f * s]
  blocks = tiles.reshape(s, f, 2 * f * s + pictures.ORBIT_PAD, 3)
  assert np.all(blocks == blocks[:, :1])
  rendering = tiles[::f, :f * s].reshape(s, s, f, 3)
  assert np.all(rendering == rendering[:, :, :1])
  # Frame 0 is taken from the source camera, so its rendering is the panel's source-view
  # rendering (row 0, column 3), up to the GIF's 256-colour palette.
  tile = panel[header:header + s, tile_x(3):tile_x(3) + s]
  assert np.mean(np.abs(rendering[:, :, 0] - tile)) < 0.03

  with pytest.raises(evaluate.EvalSetupError, match="out of range"):
    pictures.render_scenes(config, run_dir, split="test", scene_indices=[99], progress=False)
  with pytest.raises(evaluate.EvalSetupError, match="orbit_frames"):
    pictures.render_scenes(config, run_dir, scene_indices=[0], num_orbit_frames=65,
                           progress=False)


@pytest.mark.slow
def test_validator_flags_a_constructed_collapsed_model_and_not_a_healthy_split(run_dir):
  run = evaluate.load_run(load_config(), run_dir, split="val", max_scenes=2)
  # Constant mapping queries and keys: every point gets the same logit c > 0 for all K+1 slots, so
  # W is uniform (no slot means anything) while σ = (K/(K+1))·c keeps the renders opaque.
  params = jax.tree.map(lambda x: x, run.params)
  for name in ("map_query", "map_key"):
    layer = params["allocation"][name]
    layer["kernel"] = jnp.zeros_like(layer["kernel"])
    layer["bias"] = jnp.ones_like(layer["bias"])
  validator = validation.Validator(run.model, run.config, run.scenes, run_dir, num_pictures=0)
  # Past the locality switch-off: the constraint would hand every outside point to slot 1.
  collapsed = validator.run(params, run.config.train.locality_steps)
  assert collapsed["collapsed"] == 1.0 and collapsed["collapse_near_uniform"] == 1.0
  assert collapsed["collapse_black"] == 0.0
  assert collapsed["probe_pixel_entropy"] > 0.99
  # The trained smoke model is not judged here (it learnt nothing); the ground truth is the healthy
  # decomposition: each object in a slot of its own (labels folded onto the K slots).
  k = run.config.model.num_slots
  seg, fg, rgb = [], [], []
  for scene in run.scenes:
    novel = list(scene.novel_indices)
    labels = scene.masks[novel].reshape(len(novel), -1)
    seg.append(np.eye(k, dtype=np.float32)[np.maximum(labels - 1, 0) % k])
    fg.append(labels > 0)
    rgb.append(scene.images[novel].reshape(len(novel), -1, 3))
  healthy = validation.collapse_statistics(
      segmentation=np.concatenate(seg), rendered=np.concatenate(rgb), target=np.concatenate(rgb),
      foreground=np.concatenate(fg))
  assert healthy["collapsed"] == 0.0 and healthy["probe_active_slots"] >= 2
  # All foreground in one slot (another collapse of docs/method.md §6): the same function flags it.
  one = np.zeros_like(np.concatenate(seg))
  one[..., 0] = 1.0
  merged = validation.collapse_statistics(segmentation=one, rendered=np.concatenate(rgb),
                                          target=np.concatenate(rgb), foreground=np.concatenate(fg))
  assert merged["collapsed"] == 1.0 and merged["collapse_dominant_slot"] == 1.0
