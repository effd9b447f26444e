"""The study runner of issue #6 (experiments/study_common.py) and the scripts' pure summaries
(experiments/study_tables.py).

One smoke training (configs/clevr.py:smoke, 6 steps) is shared by the runner tests through a
module-scoped fixture; everything else is pure Python on small inputs.
"""

import csv
import itertools
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import ablations  # noqa: E402
from experiments import diagnose_slots  # noqa: E402
from experiments import pareto  # noqa: E402
from experiments import stability  # noqa: E402
from experiments import study_common as sc  # noqa: E402
from experiments import study_tables as st  # noqa: E402
from slotlifter_jax import evaluate  # noqa: E402
from slotlifter_jax import schedules  # noqa: E402
from slotlifter_jax import collapse  # noqa: E402
from slotlifter_jax import config_checks  # noqa: E402
from slotlifter_jax import train  # noqa: E402

SMOKE = "configs/clevr.py:smoke"


# ---------------------------------------------------------------------------------------------
# The runner on one smoke run.


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
  root = str(tmp_path_factory.mktemp("study"))
  csv_path = os.path.join(root, "results", "study.csv")
  # The "without random masking" ablation, so the override path is exercised end to end;
  # 'unsafe_rbg' keys compile faster than threefry on XLA:CPU (compilation is most of this run).
  run = sc.Run(name="no_masking", config=SMOKE,
               overrides={"train.mask_max": 0.0, "train.prng_impl": "unsafe_rbg"}, seed=0,
               num_steps=6)
  kwargs = dict(root=root, study="test", eval_split="test", eval_scenes=1, csv_path=csv_path,
                progress=False)
  row = sc.execute(run, **kwargs)
  return run, row, kwargs


def _csv_rows(path):
  with open(path, newline="") as f:
    return list(csv.DictReader(f))


def test_runner_trains_evaluates_and_records(smoke_run):
  run, row, kwargs = smoke_run
  run_dir = row["run_dir"]
  assert os.path.dirname(run_dir) == kwargs["root"] and os.path.basename(run_dir) == row["run_id"]
  assert row["run_id"].startswith("clevr-smoke-s0-n6-")
  # Trained to the budget with the override applied, then evaluated on the capped split.
  with open(os.path.join(run_dir, "config.json")) as f:
    saved = json.load(f)
  assert saved["train"]["mask_max"] == 0.0 and saved["train"]["num_steps"] == 6
  assert saved["seed"] == 0
  assert sc.checkpoint_step(run_dir) == 6 and row["checkpoint_step"] == 6
  assert row["eval_scenes"] == 1 and row["eval_split"] == "test"
  # Timing: one training segment, stored in the run directory, and a per-view render time.
  with open(os.path.join(run_dir, sc.TIMING_FILE)) as f:
    timing = json.load(f)
  assert len(timing["segments"]) == 1 and timing["segments"][0]["to_step"] == 6
  assert row["train_s"] == timing["train_s"] > 0 and row["train_segments"] == 1
  assert 0 < row["render_per_view_s"] < row["eval_s"]
  assert row["step_s"] > 0
  # Metrics from evaluate_split, and the collapse flag of the last validation (step 6).
  for k in ("psnr_novel", "ari", "nv_ari", "active_slots"):
    assert math.isfinite(row[k]), k
  assert -1.0 <= row["ari"] <= 1.0 and row["psnr_novel"] > 0
  assert row["collapsed"] in (0.0, 1.0) and row["collapse_step"] == 6
  with open(os.path.join(run_dir, "metrics.jsonl")) as f:
    last_val = [json.loads(l) for l in f if '"val"' in l][-1]
  assert row["collapsed"] == last_val["collapsed"]  # 6 ≥ the settled step of the smoke config
  # The result JSON and exactly one CSV row.
  with open(sc.result_path(run_dir, "test", 1)) as f:
    assert json.load(f)["run_id"] == row["run_id"]
  rows = _csv_rows(kwargs["csv_path"])
  assert len(rows) == 1 and rows[0]["run_id"] == row["run_id"]
  assert float(rows[0]["psnr_novel"]) == pytest.approx(row["psnr_novel"])
  assert json.loads(rows[0]["overrides"]) == dict(run.overrides)


def test_finished_run_is_skipped_and_trained_run_only_evaluated(smoke_run, monkeypatch):
  run, row, kwargs = smoke_run
  run_dir = row["run_dir"]
  result = sc.result_path(run_dir, "test", 1)
  mtime = os.stat(result).st_mtime_ns
  calls = {"train": 0, "eval": 0}
  real_eval = evaluate.evaluate_split

  def no_training(*a, **k):
    calls["train"] += 1
    raise AssertionError("retrained a finished run")

  def counting_eval(*a, **k):
    calls["eval"] += 1
    return real_eval(*a, **k)

  monkeypatch.setattr(train, "train_and_evaluate", no_training)
  monkeypatch.setattr(evaluate, "evaluate_split", counting_eval)
  again = sc.execute(run, **kwargs)
  assert calls == {"train": 0, "eval": 0}
  assert os.stat(result).st_mtime_ns == mtime
  assert again["train_s"] == row["train_s"] and again["psnr_novel"] == row["psnr_novel"]
  assert len(_csv_rows(kwargs["csv_path"])) == 1  # upserted, not appended twice

  # Trained but not evaluated (the result lost): only the evaluation runs again.
  os.remove(result)
  redone = sc.execute(run, **kwargs)
  assert calls == {"train": 0, "eval": 1}
  assert redone["train_s"] == row["train_s"] and redone["train_segments"] == 1
  assert redone["psnr_novel"] == pytest.approx(row["psnr_novel"], abs=1e-4)
  assert len(_csv_rows(kwargs["csv_path"])) == 1


def test_signal_during_training_stops_the_study_with_one_line(tmp_path, monkeypatch):
  # Training stands in for a run a user stops with ^C at step 4: train.train_and_evaluate raises
  # Interrupted after its checkpoint, as the real loop does (tests/test_train_resume.py covers
  # that part).
  def interrupted_training(config, workdir):
    os.makedirs(os.path.join(workdir, "checkpoints", "latest", "4"))
    raise train.Interrupted(2, 4)

  def no_eval(*a, **k):
    raise AssertionError("evaluated a run whose training was interrupted")

  monkeypatch.setattr(train, "train_and_evaluate", interrupted_training)
  monkeypatch.setattr(evaluate, "evaluate_split", no_eval)
  run = sc.Run(name="full", config=SMOKE, overrides={}, seed=0, num_steps=6)
  root, csv_path = str(tmp_path / "runs"), str(tmp_path / "results" / "study.csv")
  with pytest.raises(SystemExit) as stopped:
    sc.run_study([run], study="ablations", root=root, eval_split="test", eval_scenes=1,
                 csv_path=csv_path, dry_run=False, from_csv_only=False)
  message = str(stopped.value.code)
  run_dir = os.path.join(root, sc.run_id(run))
  assert message.startswith(f"[ablations] {run_dir}: interrupted by signal 2 at step 4")
  assert "\n" not in message and "run the same command again" in message
  # The interrupted segment is on the clock, and nothing claims the run finished.
  timing = sc.read_timing(run_dir)
  assert [(s["from_step"], s["to_step"]) for s in timing["segments"]] == [(0, 4)]
  assert not os.path.exists(sc.result_path(run_dir, "test", 1)) and not os.path.exists(csv_path)


# ---------------------------------------------------------------------------------------------
# Configs and bad input (no training).


def test_bad_input_names_the_problem(tmp_path):
  bad = lambda **kw: sc.Run(**dict(dict(name="x", config=SMOKE, overrides={}, seed=0,
                                        num_steps=6), **kw))
  with pytest.raises(sc.StudyError, match="'model.no_such_field'.*no field 'no_such_field'"):
    sc.run_config(bad(overrides={"model.no_such_field": 1}))
  with pytest.raises(sc.StudyError, match="'modell.num_slots'.*no section 'modell'"):
    sc.run_config(bad(overrides={"modell.num_slots": 4}))
  with pytest.raises(sc.StudyError, match="'seedx'"):
    sc.run_config(bad(overrides={"seedx": 1}))
  with pytest.raises(sc.StudyError, match="configs/nope.py"):
    sc.run_config(bad(config="configs/nope.py:paper_cpu"))
  with pytest.raises(sc.StudyError, match="unknown variant 'quik'"):
    sc.run_config(bad(config="configs/clevr.py:quik"))
  with pytest.raises(sc.StudyError, match="budget"):
    sc.run_config(bad(overrides={"train.num_steps": 10}))
  with pytest.raises(sc.StudyError, match="train.rays_per_scene"):
    sc.run_config(bad(overrides={"train.rays_per_scene": "many"}))
  # Nothing was created for a bad request.
  with pytest.raises(sc.StudyError):
    sc.execute(bad(overrides={"model.no_such_field": 1}), root=str(tmp_path))
  assert os.listdir(tmp_path) == []


def test_budget_scales_the_schedules_and_run_ids_follow_the_config():
  paper_cpu = sc.load_config("configs/room_chair.py:paper_cpu").train
  half = int(paper_cpu.num_steps) // 2
  run = sc.Run(name="full", config="configs/room_chair.py:paper_cpu", overrides={}, seed=0,
               num_steps=half)
  c = sc.run_config(run)
  t = c.train
  fields = ("warmup_steps", "decay_steps", "mask_anneal_steps", "noise_anneal_steps",
            "locality_steps")
  # Half the budget, half of every schedule (the paper_cpu variant's are even numbers of steps).
  assert [t[f] for f in fields] == [int(paper_cpu[f]) // 2 for f in fields]
  assert (t.num_steps, t.eval_every) == (half, half // 2)
  assert collapse.settled_step(t) < t.num_steps  # the last flag means collapse
  assert c.data.family == "room" and c.model.num_slots == 5 and c.data.image_size == 64
  # An override equal to the config's own value is the same run (stability.py shares
  # ablations.py's `full`); another seed, budget or a real change is not.
  rid = sc.run_id(run)
  same = sc.Run(name="other", config=run.config, overrides={"model.feature_lifting": True},
                seed=0, num_steps=half)
  assert sc.run_id(same) == rid
  assert stability.plan(seeds=[0])[0] == ablations.plan(seeds=[0])[0]
  for other in (sc.Run(**dict(vars(run), seed=1)), sc.Run(**dict(vars(run), num_steps=999)),
                sc.Run(**dict(vars(run), overrides={"train.mask_max": 0.0}))):
    assert sc.run_id(other) != rid
  assert sc.run_id(run, num_validations=3) != rid
  with pytest.raises(sc.StudyError, match="no_such"):
    sc.run_id(sc.Run(**dict(vars(run), overrides={"model.no_such": 1})))


def test_ablation_variants_switch_what_they_name():
  configs = {r.name: sc.run_config(r) for r in ablations.plan(seeds=[0])}
  assert set(configs) == {"full", "no_lifting", "no_masking", "no_slot_density"}
  full = configs["full"]
  assert full.model.feature_lifting and full.model.density_mode == "slot"
  assert full.train.mask_max == 0.99
  assert not configs["no_lifting"].model.feature_lifting
  assert configs["no_slot_density"].model.density_mode == "mlp"
  # Without random masking: the keep ratio is exactly 1 at every step of the run and beyond.
  t = configs["no_masking"].train
  steps = np.arange(0, t.num_steps + 10)
  keep = np.asarray(schedules.keep_ratio(steps, mask_max=t.mask_max,
                                         anneal_steps=t.mask_anneal_steps, mask_min=t.mask_min,
                                         mask_min_steps=t.mask_min_steps,
                                         mask_min_release_steps=t.mask_min_release_steps))
  assert np.all(keep == 1.0)
  assert schedules.keep_ratio(0, mask_max=full.train.mask_max,
                              anneal_steps=full.train.mask_anneal_steps) < 0.02
  # Each variant differs from the full method in its named field only.
  flat = lambda c: {f"{s}.{k}": v for s, d in c.to_dict().items() if isinstance(d, dict)
                    for k, v in d.items()}
  # (An override may restate the base's own value, e.g. no_masking's mask_min = 0 on a base
  # without a masking floor.)
  for name, overrides in ablations.VARIANTS.items():
    diff = {k for k, v in flat(configs[name]).items() if flat(full)[k] != v}
    assert diff == {k for k, v in overrides.items() if flat(full)[k] != v}, name
    assert bool(diff) == (name != "full"), name


# ---------------------------------------------------------------------------------------------
# Pure summaries.


def _front_brute_force(costs, values):
  ok = [i for i in range(len(costs)) if not (math.isnan(costs[i]) or math.isnan(values[i]))]
  front = []
  for i in ok:
    dominated = any(costs[j] <= costs[i] and values[j] >= values[i]
                    and (costs[j] < costs[i] or values[j] > values[i]) for j in ok)
    if not dominated:
      front.append(i)
  return sorted(front, key=lambda i: (costs[i], -values[i], i))


def test_pareto_front_matches_brute_force():
  rng = np.random.default_rng(0)
  for trial in range(300):
    n = int(rng.integers(0, 13))
    # Small integer grids make ties in cost, in value and whole duplicate points common.
    costs = rng.integers(0, 5, n).astype(float)
    values = rng.integers(0, 5, n).astype(float)
    if trial % 3 == 0:
      costs, values = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    if n and trial % 5 == 0:
      values[rng.integers(n)] = math.nan
    got = st.pareto_front(list(costs), list(values))
    want = _front_brute_force(list(costs), list(values))
    assert sorted(got) == sorted(want), (costs, values)
    assert [costs[i] for i in got] == sorted(costs[i] for i in got)  # ordered by cost
  assert st.pareto_front([3.0, 1.0, 2.0], [1.0, 0.5, 2.0]) == [1, 2]


def test_ablation_aggregation_against_a_hand_computed_example():
  nan = math.nan
  rows = [
      dict(name="full", psnr_novel=20.0, fg_ari=0.50, collapsed=0.0),
      dict(name="full", psnr_novel=22.0, fg_ari=nan, collapsed=1.0),
      dict(name="full", psnr_novel=24.0, fg_ari=0.70, collapsed=0.0),
      dict(name="no_masking", psnr_novel=18.0, fg_ari=0.10, collapsed=1.0),
      dict(name="no_masking", psnr_novel=19.0, fg_ari=0.30, collapsed=""),  # flag unknown
  ]
  groups = st.aggregate(rows, metrics=["psnr_novel", "fg_ari"], order=["no_masking", "full"])
  assert [g["name"] for g in groups] == ["no_masking", "full"]
  nm, full = groups
  # full: PSNR 20, 22, 24 → mean 22, sample std 2; FG-ARI NaN skipped → 0.6 ± 0.1414 (n = 2).
  assert full["psnr_novel"] == st.Stat(3, 22.0, 2.0, 20.0, 24.0)
  assert full["fg_ari"].n == 2 and full["fg_ari"].mean == pytest.approx(0.6)
  assert full["fg_ari"].std == pytest.approx(math.sqrt(0.02))
  assert full["collapse_rate"] == pytest.approx(1 / 3) and full["collapsed_runs"] == 1
  assert nm["collapse_rate"] == 1.0 and (nm["collapsed_runs"], nm["flagged_runs"]) == (1, 1)
  assert nm["psnr_novel"].mean == 18.5 and nm["psnr_novel"].std == pytest.approx(0.70710678)
  table = st.markdown_table(groups, columns=[("psnr_novel", "PSNR", 1.0, 2),
                                             ("fg_ari", "FG-ARI", 100.0, 1)])
  lines = table.splitlines()
  assert lines[0] == "| name | runs | PSNR | FG-ARI | collapse rate |"
  assert lines[2] == "| no_masking | 2 | 18.50 ± 0.71 | 20.0 ± 14.1 | 1/1 (100%) |"
  assert lines[3] == "| full | 3 | 22.00 ± 2.00 | 60.0 ± 14.1 | 1/3 (33%) |"
  assert st.format_stat(st.stat([5.0]), digits=1) == "5.0"  # one run: no spread
  assert st.format_stat(st.stat([nan]), digits=1) == "–"
  assert st.format_stat(full["psnr_novel"], digits=0, extremes=True) == "22 ± 2 [20, 24]"


def test_study_tables_and_figure_from_rows(tmp_path):
  """ablations.md / stability.md / pareto.png from synthetic rows (no training)."""
  rng = np.random.default_rng(1)
  rows = []
  for i, (name, _) in enumerate(itertools.product(ablations.VARIANTS, range(3))):
    rows.append(dict(name=name, seed=i % 3, num_steps=1000, eval_scenes=20, eval_split="test",
                     run_id=f"r{i}", train_s=float(100 + 10 * i), step_s=0.3,
                     render_per_view_s=float(rng.uniform(0.1, 1)),
                     psnr_novel=float(rng.uniform(15, 25)), ari=0.5, fg_ari=0.4, nv_ari=0.45,
                     nv_fg_ari=0.3, active_slots=3.0, collapsed=float(i % 4 == 0)))
  text = ablations.table(rows)
  assert "| full | 3 |" in text and "| no_slot_density | 3 |" in text
  assert text.index("| full |") < text.index("| no_lifting |")  # the paper's order
  assert "50.0 ± 0.0" in text  # ARI ×100
  text = stability.table([r for r in rows if r["name"] == "full"])
  assert "[" in text and text.count("\n| ") >= 1 + 3 + 1
  out = str(tmp_path / "pareto.png")
  pareto.plot(rows[:7], out)
  assert os.path.getsize(out) > 10_000
  points = [dict(r, name=n, overrides=json.dumps(o))  # overrides as the CSV holds them
            for r, (n, o) in zip(rows, pareto.POINTS.items())]
  points[1].update(train_s=50.0, psnr_novel=30.0)  # cheapest and best: alone on the PSNR front
  lines = pareto.table(points).splitlines()
  body = [l for l in lines if l.startswith("| ") and not l.startswith("| point")]
  assert len(body) == len(pareto.POINTS)
  assert "| rays512 | train.rays_per_scene=512 | 50 |" in body[1] and "30.00*" in body[1]
  assert not any("*" in l.split("|")[6] for l in body if l is not body[1])


def test_upsert_csv_is_keyed_by_run_id(tmp_path):
  path = str(tmp_path / "r" / "x.csv")
  sc.upsert_csv(path, [dict(run_id="a", psnr_novel=1.0), dict(run_id="b", psnr_novel=2.0)])
  sc.upsert_csv(path, [dict(run_id="b", psnr_novel=3.0, extra="e")])
  rows = sc.read_csv(path)
  assert [(r["run_id"], r["psnr_novel"]) for r in rows] == [("a", 1.0), ("b", 3.0)]
  assert rows[1]["extra"] == "e" and not os.path.exists(path + ".tmp")


def test_mean_pairwise_cosine_against_reference():
  rng = np.random.default_rng(3)
  x = rng.normal(size=(6, 7))
  pairs = [np.dot(x[i], x[j]) / np.linalg.norm(x[i]) / np.linalg.norm(x[j])
           for i, j in itertools.combinations(range(6), 2)]
  assert diagnose_slots.mean_pairwise_cosine(x) == pytest.approx(np.mean(pairs), abs=1e-12)
  assert diagnose_slots.mean_pairwise_cosine(np.ones((3, 4))) == pytest.approx(1.0)


def test_cell_ceiling_takes_each_cells_majority_label():
  mask = np.zeros((8, 8), np.int32)  # a 2×2 feature map of 4×4-pixel cells (align-corners)
  mask[0:4, 0:4] = 3  # a whole cell: kept
  mask[4:6, 4:8] = 5  # half a cell: a tie with the floor, the lower label wins
  mask[0:3, 4:8] = 7  # 12 of a cell's 16 pixels: the whole cell becomes 7
  got = diagnose_slots.cell_ceiling_labels(mask, feature_hw=(2, 2))
  want = np.zeros((8, 8), np.int32)
  want[0:4, 0:4], want[0:4, 4:8] = 3, 7
  np.testing.assert_array_equal(got, want)
  # A mask that is constant on cells is its own ceiling.
  np.testing.assert_array_equal(diagnose_slots.cell_ceiling_labels(want, feature_hw=(2, 2)), want)


def test_colour_kmeans_separates_distinct_colours():
  rng = np.random.default_rng(0)
  mask = rng.integers(0, 4, size=(12, 10))
  palette = np.array([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
  image = palette[mask] + rng.normal(scale=0.01, size=(12, 10, 3))
  labels = diagnose_slots.colour_kmeans_labels(image, num_clusters=4)
  assert adjusted_rand_score(mask.ravel(), labels.ravel()) == pytest.approx(1.0)


def test_diagnose_slots_runs_on_a_trained_run(smoke_run, capsys):
  _, row, _ = smoke_run
  diagnose_slots.main([f"--workdir={row['run_dir']}", "--split=test", "--scenes=1",
                       "--checkpoint=latest"])
  out = capsys.readouterr().out
  assert "step 6, 1 test scenes, K = 4" in out and "2D FG-ARI" in out and "key cosine" in out
  assert "cell ceiling (8×8 cells)" in out and "colour k-means (4 clusters)" in out


def test_slot_routing_command_on_a_trained_run(smoke_run, tmp_path):
  _, row, _ = smoke_run
  out = tmp_path / "routing.json"
  done = subprocess.run(
      [sys.executable, "experiments/slot_routing.py", f"--workdir={row['run_dir']}",
       "--split=test", "--scenes=1", "--checkpoint=latest", "--min_pixels=1", f"--out={out}"],
      cwd=REPO, capture_output=True, text=True, timeout=300)
  assert done.returncode == 0, done.stderr[-2000:]
  assert "step 6" in done.stdout and "slot roles" in done.stdout
  record = json.loads(out.read_text())
  s = record["summary"]
  # Every object of the one scene is in the objects list, and every pair of them in pairs.
  assert s["objects"] >= 2 and s["pairs"] == s["objects"] * (s["objects"] - 1) // 2
  assert s["both_part"] <= min(s["attention_parts"], s["rendering_parts"])
  for stage in ("attention", "rendering"):
    shares = np.asarray(s["slot_roles"][stage])  # [region, K]: each region's pixels over K slots
    assert shares.shape == (2, 4) and np.allclose(shares.sum(-1), 1.0)
  assert record["split"] == "test" and record["step"] == 6
  assert record["provenance"]["config"]["model"]["num_slots"] == 4
  assert record["lifted"] == "kept"
  # The same objects, rendered with no lifted features: the record says which rendering it read.
  from experiments import slot_routing
  dropped = tmp_path / "routing_dropped.json"
  slot_routing.main([f"--workdir={row['run_dir']}", "--split=test", "--scenes=1",
                     "--checkpoint=latest", "--min_pixels=1", "--lifted=dropped",
                     f"--out={dropped}"])
  other = json.loads(dropped.read_text())
  assert other["lifted"] == "dropped" and other["summary"]["objects"] == s["objects"]
  assert other["summary"]["slot_roles"]["attention"] == s["slot_roles"]["attention"]
  # A run folder without config.json: a one-line error naming the file.
  bad = subprocess.run([sys.executable, "experiments/slot_routing.py", f"--workdir={tmp_path}"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
  assert bad.returncode != 0 and "config.json: not found" in bad.stderr


# ---------------------------------------------------------------------------------------------
# pareto.py's grid at scene's budget. (stability.py --workdirs: tests/test_study_workdirs.py.)


def test_pareto_scene_grid_plans_one_axis_of_scene_at_its_own_budget(tmp_path, capsys):
  pareto.main(["--grid=scene", "--dry_run", f"--root={tmp_path}", "--points=base,samples8"])
  lines = capsys.readouterr().out.splitlines()
  assert len(lines) == 3 and lines[-1].startswith("2 runs;")
  runs = pareto.plan(config="configs/clevr.py:scene", num_steps=50_000,
                     points={k: pareto.SCENE_POINTS[k] for k in ("base", "samples8")})
  base, samples8 = (sc.run_config(r) for r in runs)
  # scene's own budget: nothing rescaled, and only the named axis moves.
  scene = sc.load_config("configs/clevr.py:scene")
  assert base.train.mask_min_steps == scene.train.mask_min_steps == 40_000
  assert (base.render.num_samples, samples8.render.num_samples) == (16, 8)
  assert samples8.train.rays_per_scene == base.train.rays_per_scene == 128
  # scene restarts a failing seed; a study's run is one attempt (its two validations would not
  # even fall on scene's check step), and the config it trains must pass train's checks.
  assert scene.train.restarts > 0 and scene.train.restart_check_step % scene.train.eval_every == 0
  assert (base.train.restarts, base.train.restart_check_step) == (0, 0)
  config_checks.check_config(base)
  # The grid's base is the scene ablation study's `full` run: one training serves both.
  assert sc.run_id(runs[0]) == sc.run_id(
      ablations.plan(config="configs/clevr.py:scene", num_steps=50_000, seeds=range(1),
                     variants={"full": ablations.VARIANTS["full"]})[0])
  with pytest.raises(SystemExit, match=r"unknown points \['rays512'\] for --grid=scene"):
    pareto.main(["--grid=scene", "--dry_run", "--points=rays512"])
