"""Seed stability (issue #6, docs/method.md §6): one config over N seeds, collapse rate, spread.

  python experiments/stability.py --dry_run     # the plan and its estimated time, nothing run
  python experiments/stability.py               # train + evaluate, then write the table
  python experiments/stability.py --config=configs/clevr.py:paper_cpu --seeds=5
  python experiments/stability.py --config=configs/clevr.py:scene --eval_scenes=100 \
      --workdirs=runs/scene_s0,runs/scene_s1,...   # seeds trained with slotlifter_jax.main

Trains --config (default configs/clevr.py:scene, the base of ablations.py) with seeds 0..N-1
(default 5) for --num_steps steps each (default: the config's own; a variant's schedules follow
the budget, study_common.py),
evaluates each run's last checkpoint on the first --eval_scenes test scenes and writes
experiments/results/stability.csv (one row per seed) and stability.md: per metric the mean ±
sample std, min and max over seeds, the collapse rate (runs whose last validation flags collapse,
slotlifter_jax/collapse.py) and a per-seed table.

With the defaults, the run directories are exactly those of ablations.py's `full` variant (the
directory name is a hash of the config, its overrides, seed and budget: study_common.run_id), so
after ablations.py only seeds 3 and 4 are new.

Time: 46–64 min per seed alone on the 2-core reference host with the defaults (docs/fast_model.md);
the earlier 600-step study (`--config=configs/room_chair.py:paper_cpu --num_steps=600
--eval_scenes=20`) took 11 min for seeds 3 and 4 after ablations.py; --dry_run prints an estimate.
A finished run is skipped, so running the script again resumes where it stopped.

With --workdirs the script trains nothing: it summarises finished runs of --config, one per seed,
that were trained with `python -m slotlifter_jax.main --config=... --config.seed=N --workdir=DIR`.
Each must match --config in every field that changes training and have trained its full budget;
its evaluation is reused or written (experiments/study_workdirs.py says what is checked). A run
that restarted (`train.restarts`) counts as the seed its command named; the per-seed table shows
the seed it ended with and its number of attempts. `--checkpoint=best` summarises instead the
checkpoint that `python -m slotlifter_jax.main --mode=eval` evaluates by default (the best by
validation; its rows go to the same CSV and its table to stability_best.md).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import ablations  # noqa: E402  (the shared defaults; no JAX import)
from experiments import study_common as sc  # noqa: E402
from experiments import study_tables as st  # noqa: E402
from experiments import study_workdirs as sw  # noqa: E402

COLUMNS = ablations.COLUMNS + (("active_slots", "active slots", 1.0, 2),)


def plan(*, config: str = ablations.BASE, num_steps: int | None = ablations.NUM_STEPS,
         seeds=range(5)) -> list[sc.Run]:
  num_steps = ablations.budget(config, num_steps)
  # Named like ablations.py's unmodified variant, so a shared run reads the same in both tables.
  return [sc.Run(name="full", config=config, overrides={}, seed=seed, num_steps=num_steps)
          for seed in seeds]


def table(rows: list[dict], *, config: str = ablations.BASE, checkpoint: str = "latest") -> str:
  groups = st.aggregate(rows, metrics=[c[0] for c in COLUMNS])
  steps = sorted({int(r["num_steps"]) for r in rows})
  scenes = sorted({int(r["eval_scenes"]) for r in rows})
  which = ("the best checkpoint by validation (checkpoint step per seed below)"
           if checkpoint == "best" else "the last checkpoint")
  out = [f"# Seed stability ({config}, {'/'.join(map(str, steps))} steps, "
         f"{'/'.join(map(str, scenes))} test scenes per run)\n",
         f"Each run evaluated at {which}. Mean ± sample std [min, max] over seeds; ARIs ×100; "
         f"collapse = runs whose validation at that checkpoint flags collapse / runs. Written by "
         f"experiments/stability.py on {time.strftime('%Y-%m-%d %H:%M')}.\n",
         st.markdown_table(groups, columns=COLUMNS, extremes=True), "",
         "Per seed:\n"]
  head = (["seed"] + [h for _, h, _, _ in COLUMNS] +
          ["collapsed", "attempts", "checkpoint step", "parameters", "train s", "run"])
  out.append("| " + " | ".join(head) + " |")
  out.append("|" + "---|" * len(head))
  for r in sorted(rows, key=_command_seed):
    # A run that restarted (--workdirs) shows the command's seed and the one it ended with.
    seed, first = int(r["seed"]), _command_seed(r)
    cells = [str(seed) if first == seed else f"{first} → {seed}"]
    cells += [st.format_value(r.get(m, math.nan), digits=digits, scale=scale)
              for m, _, scale, digits in COLUMNS]
    flag = r.get("collapsed", math.nan)
    cells.append("–" if flag in ("", None) or math.isnan(float(flag)) else
                 ("yes" if float(flag) == 1.0 else "no"))
    attempts = r.get("attempts", "")
    cells.append("–" if attempts in ("", None) else str(int(float(attempts))))
    step = r.get("checkpoint_step", "")
    cells += ["–" if step in ("", None) else str(int(float(step))),
              # Which parameters the evaluation read (study_workdirs); unknown for older rows.
              str(r.get("parameters") or "–"),
              f"{float(r['train_s']):.0f}", str(r["run_id"])]
    out.append("| " + " | ".join(cells) + " |")
  return "\n".join(out) + "\n"


def _command_seed(row: dict) -> int:
  first = row.get("command_seed", "")
  return int(float(row["seed"] if first in ("", None) else first))


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--root", default=sc.DEFAULT_ROOT, help="where the run directories go")
  p.add_argument("--results_dir", default=sc.RESULTS_DIR, help="where stability.csv/.md go")
  p.add_argument("--config", default=ablations.BASE)
  p.add_argument("--num_steps", type=int, default=ablations.NUM_STEPS,
                 help="budget per run (default: the config's own train.num_steps)")
  p.add_argument("--eval_scenes", type=int, default=ablations.EVAL_SCENES)
  p.add_argument("--eval_split", default="test")
  p.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1")
  p.add_argument("--dry_run", action="store_true", help="print the plan and estimate; run nothing")
  p.add_argument("--table_only", action="store_true", help="rewrite the table from the CSV")
  p.add_argument("--workdirs", default="",
                 help="comma-separated finished runs of --config trained with slotlifter_jax.main "
                      "(one per seed): summarise them instead of training --seeds runs")
  p.add_argument("--checkpoint", default="latest", choices=("latest", "best"),
                 help="with --workdirs: evaluate each run's last checkpoint, or its best by "
                      "validation (what `slotlifter_jax.main --mode=eval` reports)")
  args = p.parse_args(argv)
  if args.checkpoint != "latest" and not args.workdirs:
    p.error("--checkpoint=best needs --workdirs (the study runner evaluates last checkpoints)")
  return args


def main(argv=None) -> None:
  args = parse_args(argv)
  if args.workdirs:
    return main_workdirs(args)
  runs = plan(config=args.config, num_steps=args.num_steps, seeds=range(args.seeds))
  csv_path = os.path.join(args.results_dir, "stability.csv")
  md_path = os.path.join(args.results_dir, "stability.md")
  rows = sc.run_study(runs, study="stability", root=args.root, eval_split=args.eval_split,
                      eval_scenes=args.eval_scenes, csv_path=csv_path, dry_run=args.dry_run,
                      from_csv_only=args.table_only)
  if rows is None:
    return
  text = table(rows, config=args.config)
  st.write_text(md_path, text)
  print(text)
  print(f"[stability] wrote {csv_path} and {md_path}")


def main_workdirs(args) -> None:
  """--workdirs: the same table for runs trained with the entry point."""
  dirs = [d for d in args.workdirs.split(",") if d]
  csv_path = os.path.join(args.results_dir, "stability.csv")
  md_name = "stability.md" if args.checkpoint == "latest" else f"stability_{args.checkpoint}.md"
  md_path = os.path.join(args.results_dir, md_name)
  try:
    if args.dry_run:
      for d in dirs:
        config = sw.check_workdir(d, args.config)
        attempts, seed = sw.attempts_and_command_seed(d, int(config.seed))
        tried = f" (attempt {attempts}: seed {config.seed})" if attempts > 1 else ""
        print(f"  seed {seed}{tried}  {d}  trained {config.train.num_steps} steps")
      print(f"{len(dirs)} finished runs; only their evaluations (if missing) would run")
      return
    if args.table_only:
      ids = {sw.workdir_id(d, args.checkpoint) for d in dirs}
      rows = [r for r in sc.read_csv(csv_path) if r.get("run_id") in ids]
    else:
      rows = sw.workdir_rows(dirs, config_spec=args.config, study="stability", name="full",
                             eval_split=args.eval_split, eval_scenes=args.eval_scenes,
                             checkpoint=args.checkpoint)
      sc.upsert_csv(csv_path, rows)
  except (sc.StudyError, FileNotFoundError) as e:
    raise SystemExit(f"[stability] {e}")
  text = table(rows, config=args.config, checkpoint=args.checkpoint)
  st.write_text(md_path, text)
  print(text)
  print(f"[stability] wrote {csv_path} and {md_path}")


if __name__ == "__main__":
  from slotlifter_jax import runtime  # no JAX import
  if "--dry_run" not in sys.argv:
    runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  main()
