"""`experiments/stability.py --workdirs`: seeds trained with the entry point, summarised without
training them again (experiments/study_workdirs.py).

Each run directory is written by hand as `slotlifter_jax.main` leaves it (config.json, checkpoint
folders, metrics.jsonl, an evaluation with chosen numbers): the checks and the rows read only
these files, so nothing trains here.
"""

import csv
import json
import math
import os
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import stability  # noqa: E402
from experiments import study_common as sc  # noqa: E402
from slotlifter_jax import restarts  # noqa: E402

SMOKE = "configs/clevr.py:smoke"


def _csv_rows(path):
  with open(path, newline="") as f:
    return list(csv.DictReader(f))


def _finished_run(path, *, seed, fg_ari, psnr, step=6, collapsed=0.0, scenes=2, spec=SMOKE,
                  archived=(), best_step=None, eval_step=None, **changes):
  """A run directory as `slotlifter_jax.main` leaves it after the smoke budget, with evaluation
  numbers chosen by hand (no training: the checks and the row read only these files); `archived`
  names the seeds of attempts that restarted, kept as DIR/restarted/seed_<seed>/; `best_step`
  adds a best checkpoint and `eval_step` the step its evaluation read (default: the last)."""
  from slotlifter_jax import checkpoints
  from slotlifter_jax.data import embedded
  config = sc.load_config(spec)
  config.seed = seed
  for s in archived:
    os.makedirs(path / restarts.RESTARTED_DIR / f"seed_{s}" / "checkpoints")
  for key, value in changes.items():
    section, field = key.split("__")
    config[section][field] = value
  checkpoints.save_config(embedded.resolve_data(config), str(path))
  os.makedirs(path / "checkpoints" / "latest" / str(step))
  if best_step is not None:
    os.makedirs(path / "checkpoints" / "best" / str(best_step))
  log = [{"step": 2, "kind": "train", "steps_per_sec": 4.0, "wall_s": 1.0},
         {"step": 4, "kind": "train", "steps_per_sec": 2.0, "wall_s": 2.0},
         {"step": 4, "kind": "val", "collapsed": 0.0, "probe_active_slots": 2.0,
          "probe_largest_share": 0.7, "wall_s": 2.2},
         {"step": 6, "kind": "train", "steps_per_sec": 5.0, "wall_s": 2.5},
         {"step": 6, "kind": "val", "collapsed": collapsed, "probe_active_slots": 3.0,
          "probe_largest_share": 0.5, "wall_s": 3.0}]
  (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in log))
  metrics = {"psnr_novel": psnr, "fg_ari": fg_ari, "ari": 0.9, "nv_ari": 0.8}
  evaluation = {"split": "test", "num_scenes": scenes,
                "checkpoint": {"step": step if eval_step is None else eval_step},
                "metrics": {k: {"mean": v} for k, v in metrics.items()},
                "timing": {"render_per_view_s": 0.05, "total_s": 7.0}}
  os.makedirs(path / "eval" / "test")
  (path / "eval" / "test" / "metrics.json").write_text(json.dumps(evaluation))
  return path


def test_workdir_rows_read_the_runs_and_refuse_what_is_not_one_config(tmp_path):
  from experiments import study_workdirs as sw
  from slotlifter_jax.data import embedded
  a = _finished_run(tmp_path / "a", seed=0, fg_ari=0.6, psnr=20.0)
  # Another validation cadence and best-checkpoint rule do not change the trained parameters.
  b = _finished_run(tmp_path / "b", seed=3, fg_ari=0.8, psnr=22.0, collapsed=1.0,
                    train__eval_every=2, train__select_by="nv_ari")
  kwargs = dict(config_spec=SMOKE, study="stability", name="full", eval_split="test",
                eval_scenes=2)
  row_a, row_b = sw.workdir_rows([str(a), str(b)], **kwargs)
  assert (row_a["seed"], row_b["seed"]) == (0, 3) and row_a["num_steps"] == 6
  assert row_a["fg_ari"] == 0.6 and row_b["psnr_novel"] == 22.0 and math.isnan(row_a["ssim"])
  assert row_a["train_s"] == 3.0 and row_a["step_s"] == pytest.approx(1 / 4.0)  # median rate
  assert (row_a["collapsed"], row_b["collapsed"]) == (0.0, 1.0)  # step 6 ≥ smoke's settled step
  assert row_a["checkpoint_step"] == 6 and row_a["eval_scenes"] == 2
  assert row_a["run_id"] != row_b["run_id"] and row_a["run_id"].startswith("a-")

  def refused(match, dirs, **kw):
    with pytest.raises(sc.StudyError, match=match):
      sw.workdir_rows([str(d) for d in dirs], **dict(kwargs, **kw))

  refused(r"/c: trained with model.num_slots=3, but configs/clevr.py:smoke has",
          [a, _finished_run(tmp_path / "c", seed=1, fg_ari=0.5, psnr=20.0, model__num_slots=3)])
  refused(r"/d: last checkpoint is step 4, not the budget 6",
          [_finished_run(tmp_path / "d", seed=1, fg_ari=0.5, psnr=20.0, step=4)])
  refused(r"/a and .*/e are both seed 0",
          [a, _finished_run(tmp_path / "e", seed=0, fg_ari=0.5, psnr=20.0)])
  refused(r"/f: no config.json", [os.makedirs(tmp_path / "f") or tmp_path / "f"])
  # The same embedded set generated under another cache root ($SLOTLIFTER_DATA_CACHE) is the
  # same data; a set of another size under that root is not.
  root = embedded.resolve_data(sc.load_config(SMOKE)).data.root
  moved = str(tmp_path / "other_cache" / os.path.basename(root))
  (row,) = sw.workdir_rows([str(_finished_run(tmp_path / "g", seed=1, fg_ari=0.5, psnr=20.0,
                                              data__root=moved))], **kwargs)
  assert row["seed"] == 1
  refused(r"/h: trained with data.root='.*other_cache/.*-s1', but configs/clevr.py:smoke has",
          [_finished_run(tmp_path / "h", seed=1, fg_ari=0.5, psnr=20.0,
                         data__root=moved[:-1] + "1")])
  # An evaluation of other scenes is refused, not overwritten.
  before = (a / "eval" / "test" / "metrics.json").read_text()
  refused(r"a/eval/test/metrics.json: evaluates step 6 on 2 scenes, not .* 6 on 3", [a],
          eval_scenes=3)
  assert (a / "eval" / "test" / "metrics.json").read_text() == before


def test_workdir_rows_of_the_best_checkpoint(tmp_path):
  """--checkpoint=best: the evaluation `main --mode=eval` leaves by default (the best checkpoint,
  here step 4 of 6) is a row of its own; the last checkpoint's row refuses it."""
  from experiments import study_workdirs as sw
  kwargs = dict(config_spec=SMOKE, study="stability", name="full", eval_split="test",
                eval_scenes=2)
  a = _finished_run(tmp_path / "a", seed=0, fg_ari=0.7, psnr=21.0, best_step=4, eval_step=4)
  (row,) = sw.workdir_rows([str(a)], checkpoint="best", **kwargs)
  assert row["checkpoint_step"] == 4 and row["fg_ari"] == 0.7
  # The validation at step 4 chose it: its probe, not the later one at step 6.
  assert row["collapse_step"] == 4 and row["probe_active_slots"] == 2.0
  assert row["run_id"] == sw.workdir_id(str(a)) + "-best"
  with pytest.raises(sc.StudyError, match=r"evaluates step 4 on 2 scenes, not the last "
                                          r"checkpoint 6 on 2"):
    sw.workdir_rows([str(a)], **kwargs)
  # A run whose best checkpoint is its last: one state, so the last step's evaluation serves.
  b = _finished_run(tmp_path / "b", seed=1, fg_ari=0.8, psnr=22.0, best_step=6)
  (row,) = sw.workdir_rows([str(b)], checkpoint="best", **kwargs)
  assert row["checkpoint_step"] == 6 and row["collapse_step"] == 6
  with pytest.raises(sc.StudyError, match=r"/c: no best checkpoint"):
    sw.workdir_rows([str(_finished_run(tmp_path / "c", seed=2, fg_ari=0.5, psnr=20.0))],
                    checkpoint="best", **kwargs)


def test_runs_are_read_with_the_parameters_they_kept(tmp_path):
  """The moving average (`train.ema_decay`) never changes what trains: a run kept without it is
  one of a config that keeps it, and the other way round; each is evaluated with what its
  checkpoint holds (the config handed to the evaluation has the run's own setting), and its row
  says which parameters its evaluation used."""
  from experiments import study_workdirs as sw
  kwargs = dict(study="stability", name="full", eval_split="test", eval_scenes=2)
  plain = _finished_run(tmp_path / "plain", seed=0, fg_ari=0.8, psnr=20.0)
  averaged = _finished_run(tmp_path / "avg", seed=1, fg_ari=0.7, psnr=21.0,
                           train__ema_decay=0.99, train__ema_start_step=3)
  (path := averaged / "eval" / "test" / "metrics.json").write_text(
      json.dumps(dict(json.loads(path.read_text()), parameters="average")))
  configs = [sw.check_workdir(str(d), SMOKE) for d in (plain, averaged)]
  assert [(c.train.ema_decay, c.train.ema_start_step) for c in configs] == [(0.0, 0), (0.99, 3)]
  # `scene` keeps the average; a run of it trained without one is read without one.
  scene = "configs/clevr.py:scene+smoke"
  assert sc.load_config(scene).train.ema_decay > 0
  old = _finished_run(tmp_path / "old", seed=3, fg_ari=0.8, psnr=20.0, spec=scene,
                      train__ema_decay=0.0)
  assert sw.check_workdir(str(old), scene).train.ema_decay == 0.0
  rows = sw.workdir_rows([str(plain), str(averaged)], config_spec=SMOKE, **kwargs)
  assert [r["parameters"] for r in rows] == ["trained", "average"]
  table = stability.table(rows, config=SMOKE)
  assert "| 6 | trained |" in table and "| 6 | average |" in table  # checkpoint step, parameters
  # Any other training field still has to match.
  with pytest.raises(sc.StudyError, match=r"/lr: trained with train.base_lr=0.5"):
    sw.check_workdir(str(_finished_run(tmp_path / "lr", seed=2, fg_ari=0.5, psnr=20.0,
                                       train__ema_decay=0.99, train__base_lr=0.5)), SMOKE)


def test_a_restarted_run_counts_as_its_command_seed(tmp_path):
  """`train.restarts`: seed 1's first attempt was abandoned and seed 1001 trained the run, which
  then had one of scene's two restarts left."""
  from experiments import study_workdirs as sw
  spec = "configs/clevr.py:scene+smoke"
  kwargs = dict(config_spec=spec, study="stability", name="full", eval_split="test",
                eval_scenes=2)
  plain = _finished_run(tmp_path / "s0", seed=0, fg_ari=0.8, psnr=20.0, spec=spec)
  restarted = _finished_run(tmp_path / "s1", seed=1001, fg_ari=0.6, psnr=22.0, spec=spec,
                            archived=(1,), train__restarts=1)
  rows = sw.workdir_rows([str(plain), str(restarted)], **kwargs)
  assert [(r["seed"], r["command_seed"], r["attempts"]) for r in rows] == [(0, 0, 1),
                                                                           (1001, 1, 2)]
  table = stability.table(rows, config=spec)
  assert "| 1 → 1001 | 22.00 |" in table and "| no | 2 |" in table and "| 0 | 20.00 |" in table

  def refused(match, dirs):
    with pytest.raises(sc.StudyError, match=match):
      sw.workdir_rows([str(d) for d in dirs], **kwargs)

  # An archived attempt that did not spend a restart is not a run of this command.
  refused(r"/s2: trained with train.restarts=2, but configs/clevr.py:scene\+smoke has 1",
          [_finished_run(tmp_path / "s2", seed=1002, fg_ari=0.5, psnr=20.0, spec=spec,
                         archived=(2,))])
  # A plain seed-1 run beside the restarted one would count seed 1 twice.
  refused(r"/s1 and .*/s1b are both seed 1",
          [restarted, _finished_run(tmp_path / "s1b", seed=1, fg_ari=0.5, psnr=20.0, spec=spec)])


def test_stability_cli_summarises_workdirs(tmp_path):
  import subprocess
  dirs = [_finished_run(tmp_path / f"seed{s}", seed=s, fg_ari=fg, psnr=p)
          for s, fg, p in ((0, 0.6, 20.0), (1, 0.8, 24.0))]
  results = tmp_path / "results"
  args = [sys.executable, "experiments/stability.py", f"--config={SMOKE}", "--eval_scenes=2",
          f"--results_dir={results}", "--workdirs=" + ",".join(map(str, dirs))]
  proc = subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-2000:]
  table = (results / "stability.md").read_text()
  # FG-ARI ×100: mean 70, sample std √((10² + 10²) / 1) = 14.1; PSNR 22 ± 2.83.
  assert "| full | 2 | 22.00 ± 2.83 [20.00, 24.00] |" in table
  assert "70.0 ± 14.1 [60.0, 80.0]" in table and "0/2 (0%)" in table
  assert len(_csv_rows(results / "stability.csv")) == 2
  # A run of another config: one line naming it, exit status 1, the table left as it was.
  bad = _finished_run(tmp_path / "bad", seed=2, fg_ari=0.1, psnr=10.0, render__num_samples=4)
  proc = subprocess.run(args[:-1] + [f"--workdirs={dirs[0]},{bad}"], cwd=REPO,
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 1 and (results / "stability.md").read_text() == table
  assert proc.stderr.strip().splitlines()[-1].startswith(f"[stability] {bad}: trained with "
                                                         f"render.num_samples=4")
  # --checkpoint=best: what `main --mode=eval` reported, in its own table beside the last one's.
  best = [_finished_run(tmp_path / f"best{s}", seed=s, fg_ari=fg, psnr=22.0, best_step=4,
                        eval_step=4) for s, fg in ((0, 0.9), (1, 0.7))]
  proc = subprocess.run(args[:-1] + ["--checkpoint=best", "--workdirs=" + ",".join(map(str, best))],
                        cwd=REPO, capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-2000:]
  assert (results / "stability.md").read_text() == table
  best_table = (results / "stability_best.md").read_text()
  assert "at the best checkpoint" in best_table and "80.0 ± 14.1 [70.0, 90.0]" in best_table
  assert len(_csv_rows(results / "stability.csv")) == 4
  proc = subprocess.run(args[:-1] + ["--checkpoint=best"], cwd=REPO, capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 2 and "--checkpoint=best needs --workdirs" in proc.stderr
