"""Ablations of the paper's Table 5 (docs/method.md §5) on the headline model.

  python experiments/ablations.py --dry_run     # the plan and its estimated time, nothing run
  python experiments/ablations.py               # train + evaluate, then write the table
  python experiments/ablations.py --table_only  # rewrite the table from ablations.csv

Base: configs/clevr.py:scene, the README's model, at its own budget (50 000 steps) on the embedded
clevr set. Variants (VARIANTS below), each over --seeds seeds (default 3):
  full             the method
  no_lifting       model.feature_lifting = False: point feature E_p only, views reach points only
                   through the slots
  no_masking       train.mask_max = mask_min = 0: the keep ratio is 1 at every step (no random masking)
  no_slot_density  model.density_mode = "mlp": σ from a small head on the allocation transformer's
                   output instead of the slot-based formula (decoder.mlp_density)
Every run trains --num_steps steps (default: the config's own; a variant's schedules follow the
budget, study_common.py) and is evaluated (last checkpoint) on the first --eval_scenes test scenes.
Writes experiments/results/ablations.csv (one row per run) and ablations.md: mean ± sample std
over seeds of PSNR, ARI, FG-ARI, NV-ARI, NV-FG-ARI, and the collapse rate (runs whose last
validation flags collapse, slotlifter_jax/collapse.py). Collapsed runs count in the means, as
seeds do in the paper.

The paper's figures (Room-Diverse, 128², 250k steps): without feature lifting PSNR 28.20 / NV-ARI
71.4; without random masking FG-ARI 43.6 and collapsing runs; without slot density FG-ARI 77.3.
Expected: `experiments/results/ablations_fast50k.md` (one seed each; without masking nothing
splits, without slot density the rendering falls into 2 slots, without lifting PSNR falls).
Time: 45–58 min per run alone on the 2-core reference host (journal: "Ablations"), so about 10 h
for the defaults; the earlier 600-step study on `configs/room_chair.py:paper_cpu` is
`--config=configs/room_chair.py:paper_cpu --num_steps=600 --eval_scenes=20`. Runs live in --root
(default runs/study/, shared with stability.py, which reuses the `full` runs); a finished run is
skipped, so running the script again resumes.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from experiments import study_common as sc  # noqa: E402  (no JAX import)
from experiments import study_tables as st  # noqa: E402

BASE = "configs/clevr.py:scene"
NUM_STEPS = None  # the config's own train.num_steps
EVAL_SCENES = 100
VARIANTS = {
    "full": {},
    "no_lifting": {"model.feature_lifting": False},
    "no_masking": {"train.mask_max": 0.0, "train.mask_min": 0.0},
    "no_slot_density": {"model.density_mode": "mlp"},
}
# (metric, header, scale, digits) of the table: ARIs ×100 as in the paper.
COLUMNS = (("psnr_novel", "PSNR (dB)", 1.0, 2), ("ari", "ARI", 100.0, 1),
           ("fg_ari", "FG-ARI", 100.0, 1), ("nv_ari", "NV-ARI", 100.0, 1),
           ("nv_fg_ari", "NV-FG-ARI", 100.0, 1))


def budget(config: str, num_steps: int | None) -> int:
  """`num_steps`, or with None the config's own train.num_steps."""
  return int(num_steps or sc.load_config(config).train.num_steps)


def plan(*, config: str = BASE, num_steps: int | None = NUM_STEPS, seeds=(0, 1, 2),
         variants: dict = VARIANTS) -> list[sc.Run]:
  """Seed-major order, so an interrupted study has every variant at the first seeds."""
  num_steps = budget(config, num_steps)
  return [sc.Run(name=name, config=config, overrides=overrides, seed=seed, num_steps=num_steps)
          for seed in seeds for name, overrides in variants.items()]


def table(rows: list[dict], *, config: str = BASE) -> str:
  groups = st.aggregate(rows, metrics=[c[0] for c in COLUMNS], order=list(VARIANTS))
  steps = sorted({int(r["num_steps"]) for r in rows})
  scenes = sorted({int(r["eval_scenes"]) for r in rows})
  split = sorted({str(r["eval_split"]) for r in rows})
  head = (f"# Ablations ({config}, {'/'.join(map(str, steps))} steps, {'/'.join(split)} split, "
          f"{'/'.join(map(str, scenes))} scenes per run)\n\n"
          f"Mean ± sample std over seeds; ARIs ×100; collapse = runs whose last validation flags "
          f"collapse / runs. Written by experiments/ablations.py on "
          f"{time.strftime('%Y-%m-%d %H:%M')}.\n\n")
  return head + st.markdown_table(groups, columns=COLUMNS) + "\n"


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  p.add_argument("--root", default=sc.DEFAULT_ROOT, help="where the run directories go")
  p.add_argument("--results_dir", default=sc.RESULTS_DIR, help="where ablations.csv/.md go")
  p.add_argument("--config", default=BASE)
  p.add_argument("--num_steps", type=int, default=NUM_STEPS,
                 help="training budget per run (default: the config's own train.num_steps)")
  p.add_argument("--eval_scenes", type=int, default=EVAL_SCENES, help="test scenes per run")
  p.add_argument("--eval_split", default="test")
  p.add_argument("--seeds", type=int, default=3, help="seeds 0..N-1 per variant")
  p.add_argument("--variants", default=",".join(VARIANTS), help=f"subset of {list(VARIANTS)}")
  p.add_argument("--dry_run", action="store_true", help="print the plan and estimate; run nothing")
  p.add_argument("--table_only", action="store_true", help="rewrite the table from the CSV")
  return p.parse_args(argv)


def main(argv=None) -> None:
  args = parse_args(argv)
  unknown = [n for n in args.variants.split(",") if n not in VARIANTS]
  if unknown:
    raise SystemExit(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
  runs = plan(config=args.config, num_steps=args.num_steps, seeds=range(args.seeds),
              variants={n: VARIANTS[n] for n in args.variants.split(",")})
  csv_path = os.path.join(args.results_dir, "ablations.csv")
  md_path = os.path.join(args.results_dir, "ablations.md")
  rows = sc.run_study(runs, study="ablations", root=args.root, eval_split=args.eval_split,
                      eval_scenes=args.eval_scenes, csv_path=csv_path, dry_run=args.dry_run,
                      from_csv_only=args.table_only)
  if rows is None:
    return
  text = table(rows, config=args.config)
  st.write_text(md_path, text)
  print(text)
  print(f"[ablations] wrote {csv_path} and {md_path}")


if __name__ == "__main__":
  from slotlifter_jax import runtime  # no JAX import
  if "--dry_run" not in sys.argv:
    runtime.reexec_with_allocator()
  runtime.set_xla_flags()
  main()
