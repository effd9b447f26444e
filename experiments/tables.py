"""Every table that README.md and docs/ show, generated from result files under experiments/results/.

  python experiments/tables.py               # rewrite the tables in place between their markers
  python experiments/tables.py --check       # exit 1, naming each table whose page differs
  python experiments/tables.py --print=NAME  # one table on stdout

A page holds table NAME between the lines `<!-- table:NAME -->` and `<!-- /table:NAME -->`; this
script owns everything between them (the table and the lines under it that say which files, which
split and which host). A number typed into a page goes stale when a result is evaluated again;
here it is read from the file each time, and tests/test_tables.py fails when a page and its
files disagree. A marker naming no table here, or a table placed in no page, is an error too.

Standard library only (no JAX): the tables are means and standard errors already stored in
`--mode=eval`'s metrics.json files and slotlifter_jax/tools/paired_eval.py's JSON files.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
from typing import Callable

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(REPO, "experiments", "results")
PAGES = ("README.md", "docs")  # README.md and every docs/*.md
MARKER = re.compile(r"^<!-- (/?)table:([A-Za-z0-9_]+) -->$")

# The five seeds of `configs/clevr.py:scene` through the README's training command, each evaluated
# at its best checkpoint by validation: (seed label, the average of the parameters, the trained
# parameters, the paired validation comparison of the two at the last checkpoint). Seed 0 failed
# the step-14 000 check and the command trained seed 1000; seeds 1 and 2 ended on their best. The
# headline files (average parameters, development split), `clevr_scene_seed<N>_dev_metrics.json`,
# are named by the seed the command was given, so seed 0's holds the run trained as seed 1000.
FAST_SEEDS = (
    ("0 → 1000", "clevr_scene_seed0_dev_metrics.json",
     "clevr_fast50k_ema_seed1000_best_trained_test_metrics.json",
     "clevr_fast50k_ema_seed1000_latest_val_paired.json"),
    ("1", "clevr_scene_seed1_dev_metrics.json",
     "clevr_fast50k_ema_seed1_latest_trained_test_metrics.json",
     "clevr_fast50k_ema_seed1_latest_val_paired.json"),
    ("2", "clevr_scene_seed2_dev_metrics.json",
     "clevr_fast50k_seed2_today_trained_test_metrics.json",
     "clevr_fast50k_seed2_today_val_paired.json"),
    ("3", "clevr_scene_seed3_dev_metrics.json",
     "clevr_fast50k_seed3_today_best_trained_test_metrics.json",
     "clevr_fast50k_seed3_today_val_paired.json"),
    ("4", "clevr_scene_seed4_dev_metrics.json",
     "clevr_fast50k_seed4_today_best_trained_test_metrics.json",
     "clevr_fast50k_seed4_today_val_paired.json"),
)
# Those evaluations ran on the split then called "test". Recipe choices were made by reading it,
# so it is the development split ("dev") now; the held-out split's numbers go to
# experiments/results/headline_clevr.json once evaluated.
DEV_SPLIT = ("development split (the former test split), which informed recipe choices; 100 scenes; "
             "held-out numbers: `experiments/results/headline_clevr.json` once evaluated")
# Files written before slotlifter_jax/provenance.py record no machine; the journal names it
# (experiments/journal/2026-11.md, "Thirtieth round" to "Thirty-second round").
LEGACY_HOSTS = {name: "a 2-core AMD EPYC virtual machine (mimalloc)"
                for _, *files in FAST_SEEDS for name in files}


class TableError(Exception):
  pass


def _load(name: str) -> dict:
  path = os.path.join(RESULTS, name)
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except OSError as e:
    raise TableError(f"experiments/results/{name}: cannot read ({e.strerror})") from None


def _mean(data: dict, metric: str) -> float:
  return float(data["metrics"][metric]["mean"])


def _stderr(data: dict, metric: str) -> float:
  return float(data["metrics"][metric]["stderr"])


def host(names) -> str:
  """The machine the files were computed on: their provenance records' CPU (or GPU) and core
  count, else LEGACY_HOSTS; one description, or each one's where they differ."""
  hosts = []
  for name in names:
    record = _load(name).get("provenance") or {}
    if record.get("platform") not in (None, "cpu"):
      described = f"{record.get('device_kind') or record['platform']}"
    elif record.get("cpu_model"):
      described = f"a {record.get('cpu_count')}-core {record['cpu_model']}"
    else:
      described = LEGACY_HOSTS.get(name, "not recorded")
    if described not in hosts:
      hosts.append(described)
  return "; ".join(hosts)


def _files_line(names) -> str:
  return "Files: " + ", ".join(f"`experiments/results/{n}`" for n in names) + "."


def _std_row(values: list[float], fmt: str) -> str:
  return f"{fmt.format(statistics.mean(values))} ± {fmt.format(statistics.stdev(values))}"


def fast_seeds() -> list[str]:
  """README: the five seeds at their best checkpoints, with the average of the parameters."""
  rows = ["| seed | best step | FG-ARI | NV-ARI | novel PSNR (dB) |", "|---|---|---|---|---|"]
  cols = {m: [] for m in ("fg_ari", "nv_ari", "psnr_novel")}
  names = [average for _, average, _, _ in FAST_SEEDS]
  for (seed, _, _, _), name in zip(FAST_SEEDS, names):
    d = _load(name)
    for m in cols:
      cols[m].append(_mean(d, m))
    rows.append(f"| {seed} | {d['checkpoint']['step']} | "
                f"{_mean(d, 'fg_ari'):.3f} ± {_stderr(d, 'fg_ari'):.3f} | "
                f"{_mean(d, 'nv_ari'):.3f} ± {_stderr(d, 'nv_ari'):.3f} | "
                f"{_mean(d, 'psnr_novel'):.2f} ± {_stderr(d, 'psnr_novel'):.2f} |")
  rows.append(f"| mean ± std | | {_std_row(cols['fg_ari'], '{:.3f}')} | "
              f"{_std_row(cols['nv_ari'], '{:.3f}')} | {_std_row(cols['psnr_novel'], '{:.2f}')} |")
  return rows + ["", f"Split: {DEV_SPLIT}. ± after a seed's number: the standard error over the "
                 f"scenes; in the last row: the sample standard deviation over the seeds. Seed 0 "
                 f"failed the step-14 000 check and was trained again as seed 1000 (row 0 → 1000; "
                 f"its file is named seed 0). Measured on {host(names)}.", _files_line(names)]


def fast_seeds_trained() -> list[str]:
  """docs/fast_model.md: the same checkpoints with the average and with the trained parameters."""
  rows = ["| seed | best step | average: FG-ARI / NV-ARI / PSNR | trained: FG-ARI / NV-ARI / PSNR |",
          "|---|---|---|---|"]
  names = []
  for seed, average, trained, _ in FAST_SEEDS:
    a, t = _load(average), _load(trained)
    if a["checkpoint"]["step"] != t["checkpoint"]["step"]:
      raise TableError(f"{average} and {trained}: different checkpoints")
    names += [average, trained]
    cells = [f"{_mean(d, 'fg_ari'):.3f} / {_mean(d, 'nv_ari'):.3f} / {_mean(d, 'psnr_novel'):.2f}"
             for d in (a, t)]
    rows.append(f"| {seed} | {a['checkpoint']['step']} | {cells[0]} | {cells[1]} |")
  return rows + ["", f"Split: {DEV_SPLIT}. PSNR: novel views, dB. Measured on {host(names)}.",
                 _files_line(names)]


def fast_average_paired() -> list[str]:
  """docs/fast_model.md: the average against the trained parameters, paired per validation scene."""
  rows = ["| seed | FG-ARI | NV-ARI | novel PSNR (dB) |", "|---|---|---|---|"]
  names = []
  for seed, _, _, paired in FAST_SEEDS:
    d = _load(paired)
    other = d["others"][0]
    if d["baseline"].get("parameters") != "trained" or other.get("parameters") != "average":
      raise TableError(f"{paired}: not trained (baseline) against average")
    names.append(paired)
    cells = [f"{other['rows'][m]['difference']:+.3f} ± {other['rows'][m]['stderr']:.3f}"
             for m in ("fg_ari", "nv_ari")]
    psnr = other["rows"]["psnr_novel"]
    rows.append(f"| {seed} | {cells[0]} | {cells[1]} | "
                f"{psnr['difference']:+.2f} ± {psnr['stderr']:.2f} |")
  return rows + ["", "Average − trained ± the standard error of the paired difference, on the "
                 "100 validation scenes at the last checkpoint (slotlifter_jax/tools/paired_eval.py). "
                 f"Measured on {host(names)}.", _files_line(names)]


TABLES: dict[str, Callable[[], list[str]]] = {
    "fast_seeds": fast_seeds,
    "fast_seeds_trained": fast_seeds_trained,
    "fast_average_paired": fast_average_paired,
}


def pages(repo: str = REPO) -> list[str]:
  """README.md and docs/*.md, relative to `repo`."""
  out = ["README.md"]
  docs = os.path.join(repo, "docs")
  out += sorted(f"docs/{n}" for n in os.listdir(docs) if n.endswith(".md"))
  return [p for p in out if os.path.isfile(os.path.join(repo, p))]


def render(text: str, page: str, tables: dict[str, list[str]]) -> tuple[str, list[str]]:
  """`text` with every marked table replaced by its generated lines, and the names found."""
  lines, out, found, open_name = text.split("\n"), [], [], None
  for n, line in enumerate(lines, 1):
    m = MARKER.match(line.strip())
    if open_name is None:
      out.append(line)
      if m and not m.group(1):
        name = m.group(2)
        if name not in tables:
          raise TableError(f"{page}:{n}: no table {name!r} (known: {', '.join(sorted(tables))})")
        out += [""] + tables[name] + [""]
        open_name, found = name, found + [name]
      elif m:
        raise TableError(f"{page}:{n}: {line.strip()} closes no table")
    elif m and m.group(1) and m.group(2) == open_name:
      out.append(line)
      open_name = None
    elif m:
      raise TableError(f"{page}:{n}: {line.strip()} inside table {open_name!r}")
  if open_name is not None:
    raise TableError(f"{page}: table {open_name!r} is never closed")
  return "\n".join(out), found


def run(*, check: bool, repo: str = REPO) -> list[str]:
  """Rewrites (or, with `check`, compares) every page's tables; returns the problems found."""
  tables = {name: make() for name, make in TABLES.items()}
  problems, placed = [], []
  for page in pages(repo):
    path = os.path.join(repo, page)
    with open(path, encoding="utf-8") as f:
      text = f.read()
    new, found = render(text, page, tables)
    placed += found
    if new != text:
      if check:
        old_lines, new_lines = text.split("\n"), new.split("\n")
        first = next((i for i, (a, b) in enumerate(zip(old_lines, new_lines)) if a != b),
                     min(len(old_lines), len(new_lines)))
        shown = old_lines[first] if first < len(old_lines) else "(end of file)"
        problems.append(f"{page}:{first + 1}: differs from its generated table: {shown!r} "
                        f"(run python experiments/tables.py)")
      else:
        with open(path, "w", encoding="utf-8") as f:
          f.write(new)
  for name in tables:
    if name not in placed:
      problems.append(f"table {name!r} is placed in no page (add <!-- table:{name} --> "
                      f"<!-- /table:{name} --> to README.md or a docs page)")
  return problems


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--check", action="store_true", help="compare only; exit 1 on a difference")
  parser.add_argument("--print", dest="name", help="print one table and exit")
  args = parser.parse_args(argv)
  try:
    if args.name:
      if args.name not in TABLES:
        raise TableError(f"no table {args.name!r} (known: {', '.join(sorted(TABLES))})")
      print("\n".join(TABLES[args.name]()))
      return 0
    problems = run(check=args.check)
  except TableError as e:
    print(f"tables.py: {e}", file=sys.stderr)
    return 1
  for p in problems:
    print(p, file=sys.stderr)
  if not problems:
    print("every table matches its result files" if args.check else "tables written")
  return 1 if problems else 0


if __name__ == "__main__":
  sys.exit(main())
