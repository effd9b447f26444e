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
`--mode=eval`'s metrics.json files and slotlifter_jax/tools/paired_eval.py's JSON files, the
benchmark JSON of experiments/bench.py, and the files of experiments/gpu_figures.sh.
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
if REPO not in sys.path:  # run as a script: experiments/ is a package of the repository root
  sys.path.insert(0, REPO)

from experiments import room_tables  # noqa: E402
from experiments.table_common import RESULTS, TableError, described_host, load_json  # noqa: E402
from experiments.table_common import files_line as _files_line  # noqa: E402
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
# so it is the development split ("dev") now; the held-out split's numbers are clevr_heldout's.
DEV_SPLIT = ("development split (the former test split), which informed recipe choices; "
             "100 scenes")
# Files written before slotlifter_jax/provenance.py record no machine; the journal names it
# (experiments/journal/2026-11.md, "Thirtieth round" to "Thirty-second round").
LEGACY_HOSTS = {name: "a 2-core AMD EPYC virtual machine (mimalloc)"
                for _, *files in FAST_SEEDS for name in files}


def _load(name: str) -> dict:
  return load_json(name, RESULTS)  # RESULTS read at call time, so tests may point it elsewhere


def _mean(data: dict, metric: str) -> float:
  return float(data["metrics"][metric]["mean"])


def _stderr(data: dict, metric: str) -> float:
  return float(data["metrics"][metric]["stderr"])


def host(names) -> str:
  """The machine the files were computed on: their provenance records' CPU (or GPU) and core
  count, else LEGACY_HOSTS; one description, or each one's where they differ."""
  hosts = []
  for name in names:
    described = (described_host(_load(name).get("provenance") or {})
                 or LEGACY_HOSTS.get(name, "not recorded"))
    if described not in hosts:
      hosts.append(described)
  return "; ".join(hosts)


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


def _bench(name: str = "bench_cpu.json") -> dict:
  return _load(name)["configs"]


def _bench_entry(configs: dict, key: str) -> dict:
  if key not in configs:
    raise TableError(f"experiments/results/bench_cpu.json: no configuration {key!r}")
  return configs[key]


def _seconds(value: float) -> str:
  return f"{value:.3f}" if value < 1 else f"{value:.2f}"


def _measured(configs: dict, keys) -> str:
  """'KEY, KEY: DATE (ALLOCATOR); …' from each bench entry's `measured` record."""
  groups: dict[str, list[str]] = {}
  for key in keys:
    record = configs[key].get("measured") or {}
    allocator = (record.get("allocator") or "allocator not recorded").removeprefix("allocator: ")
    groups.setdefault(f"{record.get('date', 'date not recorded')[:10]} ({allocator})", []).append(key)
  return "; ".join(f"{', '.join(ks)}: {when}" for when, ks in groups.items())


ALLOCATORS = (("system", "system (glibc)"), ("mimalloc", "mimalloc"), ("tcmalloc", "tcmalloc"))


def bench_allocators() -> list[str]:
  """docs/performance.md §1: configs B and A with each allocator, side by side in one run."""
  configs = _bench()
  rows = ["| config | allocator | s/step | peak RSS GB |", "|---|---|---|---|"]
  keys = []
  for config in ("B", "A"):
    for allocator, label in ALLOCATORS:
      key = f"{config}@{allocator}"
      d = _bench_entry(configs, key)
      keys.append(key)
      rows.append(f"| {config} | {label} | {_seconds(d['step_s_median'])} | "
                  f"{d['train_peak_rss_gb']:.2f} |")
  note = (f"s/step: the median of the timed steps; peak RSS: the process's peak while training. "
          f"Measured on the project's 2-core CPU, {_measured(configs, keys)}. "
          f"File: `experiments/results/bench_cpu.json`, keys {', '.join(keys)}.")
  return ["  " + line for line in rows] + ["", "  " + note]


def bench_memory() -> list[str]:
  """docs/performance.md §4: time and memory of the step for A, the paper's batch, A with scan and
  remat, and B."""
  configs = _bench()
  a, paper, lowmem, b = (_bench_entry(configs, k) for k in ("A", "paper_batch", "A_lowmem", "B"))
  labels = (
      ("A", a, f"A ({a['batch_scenes']} × {a['rays_per_scene']} rays, {a['num_samples']} samples)",
       " (one doubled step, §1)"),
      ("paper_batch", paper, f"paper_batch ({paper['batch_scenes']} × {paper['rays_per_scene']} "
       f"rays, {paper['grad_accum_chunks']} scene chunks)", ""),
      ("A_lowmem", lowmem, f"A_lowmem (scan + remat, {lowmem['grad_accum_chunks']} scene × "
       f"{lowmem['ray_chunks']} ray chunks)", ""),
      ("B", b, f"B ({b['batch_scenes']} × {b['rays_per_scene']} rays, {b['num_samples']} samples)",
       ""),
  )
  rows = ["| config | s/step | XLA temp GB | peak RSS GB |", "|---|---|---|---|"]
  for _, d, label, rss_note in labels:
    rows.append(f"| {label} | {_seconds(d['step_s_median'])} | {d['xla_temp_gb']:.2f} | "
                f"{d['train_peak_rss_gb']:.2f}{rss_note} |")
  keys = [k for k, *_ in labels]
  return rows + ["", "s/step: the median of the timed steps; XLA temp: the step's temporary buffer; "
                 "peak RSS: the process's peak while training. Measured on the project's 2-core "
                 f"CPU, {_measured(configs, keys)}. File: `experiments/results/bench_cpu.json`, keys "
                 f"{', '.join(keys)}."]


QUICK = "clevr_quick_test_metrics.json"
QUICK_COLUMNS = (("psnr_novel", "{:.2f}"), ("ssim", "{:.3f}"), ("lpips", "{:.3f}"),
                 ("psnr_source", "{:.2f}"), ("ari", "{:.3f}"), ("fg_ari", "{:.3f}"),
                 ("nv_ari", "{:.3f}"), ("nv_fg_ari", "{:.3f}"), ("mbo", "{:.3f}"))
QUICK_HEADER = ("| run | novel-view PSNR | SSIM | LPIPS (alex) | source PSNR | ARI | FG-ARI | "
                "NV-ARI | NV-FG-ARI | mBO | active slots / objects |")


def quick_model() -> list[str]:
  """docs/quick_model.md: `paper_cpu` at its best checkpoint on the embedded clevr set."""
  d = _load(QUICK)
  cells = [f"{fmt.format(_mean(d, m))} ± {fmt.format(_stderr(d, m))}" for m, fmt in QUICK_COLUMNS]
  rows = [QUICK_HEADER, "|---|---|---|---|---|---|---|---|---|---|---|",
          f"| paper_cpu, 6500 steps (current; best checkpoint, step {d['checkpoint']['step']}) | "
          f"{' | '.join(cells)} | {_mean(d, 'active_slots'):.2f} / {_mean(d, 'num_objects'):.2f} |"]
  return rows + ["", f"Split: `{d['split']}` as it was then named, now the development split; "
                 f"{d['num_scenes']} scenes, {d['image_size'][0]} px. ± : the standard error over "
                 "the scenes. Measured on the project's 2-core CPU (the file records no machine).",
                 _files_line([QUICK])]


GPU_FIGURES = "gpu_h100_figures.txt"
GPU_RUNS = (("paper config through `main` (host batches, validation of 20 scenes every 500 steps)",
             "gpu_h100_paper_metrics.jsonl"),
            ("`scene` through `main` (the README's training command)", "gpu_h100_fast_metrics.jsonl"))


def _gpu_bench_row() -> tuple[list[str], list[str]]:
  """The device lines and the paper_batch row of experiments/gpu_figures.sh's summary."""
  path = os.path.join(RESULTS, GPU_FIGURES)
  try:
    with open(path, encoding="utf-8") as f:
      lines = [line.strip() for line in f]
  except OSError as e:
    raise TableError(f"experiments/results/{GPU_FIGURES}: cannot read ({e.strerror})") from None
  rows = [line for line in lines if line.startswith("| paper_batch |")]
  if len(rows) != 1:
    raise TableError(f"experiments/results/{GPU_FIGURES}: not one paper_batch row")
  return lines[1:3], [c.strip() for c in rows[0].strip("|").split("|")]


def _gpu_run(name: str) -> str:
  """Steps per second between validations and the last logged step of a run's metrics.jsonl."""
  path = os.path.join(RESULTS, name)
  try:
    with open(path, encoding="utf-8") as f:
      records = [json.loads(line) for line in f if line.strip()]
  except OSError as e:
    raise TableError(f"experiments/results/{name}: cannot read ({e.strerror})") from None
  train = [r for r in records if r["kind"] == "train"]
  validated = {r["step"] for r in records if r["kind"] == "val"}
  # The first window holds the compile; a window that follows a validation holds that validation.
  rates = [r["steps_per_sec"] for r in train[1:] if r["step"] - (train[1]["step"] - train[0]["step"])
           not in validated]
  low, *_, high = statistics.quantiles(rates, n=10)
  minutes, seconds = divmod(round(train[-1]["wall_s"]), 60)
  return (f"{low:.1f}–{high:.1f} steps/s between validations (10th–90th percentile over "
          f"{len(rates)} windows of 50 steps); step {train[-1]['step']} logged after {minutes} min "
          f"{seconds} s, the first {train[0]['step']} steps (compile included) "
          f"{train[0]['wall_s']:.0f} s")


def gpu_figures() -> list[str]:
  """docs/usage.md: one H100 against the 2-core CPU, from experiments/gpu_figures.sh's files."""
  device, cells = _gpu_bench_row()
  step_s, rays_s, peak, mfu = float(cells[1]), int(cells[3]), float(cells[6]), cells[7]
  cpu = _bench_entry(_bench(), "paper_batch")
  rays = f"{rays_s:,}".replace(",", " ")
  rows = ["| what | H100 | the 2-core CPU |", "|---|---|---|",
          f"| paper step (`bench.py --configs=paper_batch`: {cpu['batch_scenes']} scenes × "
          f"{cpu['rays_per_scene']} rays × {cpu['num_samples']} samples) | **{step_s:.4f} s** "
          f"({1 / step_s:.1f} steps/s, {rays} rays/s, MFU {mfu} of a measured "
          f"{peak / 1000:.1f} TFLOP/s fp32 matmul) | {cpu['step_s_median']:.2f} s "
          f"(`results/bench_cpu.json`, {cpu['measured']['date'][:10]}) |"]
  rows += [f"| {what} | {_gpu_run(name)} | — |" for what, name in GPU_RUNS]
  names = [GPU_FIGURES] + [name for _, name in GPU_RUNS] + ["bench_cpu.json"]
  return rows + ["", f"Device, memory, driver: {device[0]}; {device[1]}.", _files_line(names)]


HEADLINE_CLEVR = "headline_clevr.json"


def clevr_heldout() -> list[str]:
  """README: the README command's run(s) on the held-out test split (tools/headline.py's file)."""
  d = _load(HEADLINE_CLEVR)
  if d.get("split") != "test":
    raise TableError(f"experiments/results/{HEADLINE_CLEVR}: split {d.get('split')!r}, not the "
                     f"held-out 'test'")
  rows = ["| seed | attempts | best step | FG-ARI | NV-ARI | novel PSNR (dB) | training (min) |",
          "|---|---|---|---|---|---|---|"]
  hosts = []
  for r in d["seeds"]:
    seed = str(r["seed"]) if r["seed"] == r["final_seed"] else f"{r['seed']} → {r['final_seed']}"
    cells = [f"{r[k]:.3f} ± {r[k + '_stderr']:.3f}" for k in ("fg_ari", "nv_ari")]
    rows.append(f"| {seed} | {r['attempts']} | {r['checkpoint'].get('step', '?')} | {cells[0]} | "
                f"{cells[1]} | {r['psnr_novel']:.2f} ± {r['psnr_novel_stderr']:.2f} | "
                f"{r['wall_minutes']} |")
    hosts += [h for h in r["hosts"] if h not in hosts]
  if d["num_seeds"] > 1:
    s = d["summary"]
    rows.append(f"| mean ± std | | | {s['fg_ari']['mean']:.3f} ± {s['fg_ari']['std']:.3f} | "
                f"{s['nv_ari']['mean']:.3f} ± {s['nv_ari']['std']:.3f} | "
                f"{s['psnr_novel']['mean']:.2f} ± {s['psnr_novel']['std']:.2f} | |")
  return rows + ["", "Split: the held-out test split (100 scenes from a seed stream no choice "
                 "read). ± : the standard error over the scenes. Attempts: 1 + the restarts the "
                 "step-14 000 check made; training minutes include them, not the data set's generation "
                 "(once per host). "
                 f"Trained on {', '.join(hosts) or 'a host not recorded'} (2 cores).",
                 _files_line([HEADLINE_CLEVR])]


EDIT_CLEVR = "edit_clevr.json"
# The same model and command with --move_background=stay --uncovered=black: the composite before
# the background was carried and the uncovered filled (docs/editing.md §4).
EDIT_CLEVR_PLAIN = "edit_clevr_stay_black.json"


def _edit_cell(s: dict, key: str, fmt: str = "{:.2f}") -> str:
  mean = s.get(f"{key}_mean" if key.startswith("iou") else key)
  if mean is None:
    return "–"
  return f"{fmt.format(mean)} ± {fmt.format(s[key + '_stderr'])}"


def edit_clevr() -> list[str]:
  """docs/editing.md §7, README: `--mode=edit` of the README model on the held-out clevr scenes,
  with the default settings and, below them, the composite without carrying or filling."""
  rows = ["| edit | move: background / uncovered | edits (no slot) | edited better than "
          "unedited | PSNR changed region: edited / unedited | seen by the source / unseen "
          "(edited) | whole novel view: edited / unedited | IoU moved mask: edited / unmoved | "
          "commit |",
          "|---|---|---|---|---|---|---|---|---|"]
  files = (EDIT_CLEVR, EDIT_CLEVR_PLAIN)
  for name in files:
    d = _load(name)
    commit = d["provenance"]["git_commit"]
    commit = commit[:7] + ("-dirty" if commit.endswith("-dirty") else "")
    settings = d["settings"]
    how = settings.get("move_background", "stay")
    if how == "carry":  # the rule β was read by (rendering/edits.py, carry_fraction)
      how += f" ({settings.get('carry_rule', 'opacity')})"
    how += f" / {settings.get('uncovered', 'black')}"
    for kind in ("remove", "move"):
      s = d[kind]
      iou = (f"{_edit_cell(s, 'iou', '{:.3f}')} / {_edit_cell(s, 'iou_baseline', '{:.3f}')}"
             if kind == "move" else "–")
      rows.append(f"| {kind} | {how} | {s['num_edits']} "
                  f"({s['num_skipped']}) | {s['improved_fraction']:.1%} of {s['improved_count']} | "
                  f"{_edit_cell(s, 'psnr_changed')} / {_edit_cell(s, 'psnr_changed_baseline')} | "
                  f"{_edit_cell(s, 'psnr_changed_seen')} / {_edit_cell(s, 'psnr_changed_unseen')} "
                  f"| {_edit_cell(s, 'psnr')} / {_edit_cell(s, 'psnr_baseline')} | {iou} "
                  f"| {commit} |")
  d = _load(EDIT_CLEVR)
  checkpoint = d["checkpoint"]
  return rows + ["", f"Split: `{d['split']}`, {d['num_scenes']} scenes, {d['image_size'][0]} px; "
                 f"checkpoint `{checkpoint['name']}` (step {checkpoint['step']}), "
                 f"{d['parameters']} parameters; removal `{d['settings']['removal']}` (the "
                 "slot is decoded out of the slot set). ± : the standard error over edits. PSNR "
                 "in dB on the novel views against the edited ground truth; 'unedited' renders "
                 "the scene as it was (the baseline an edit must beat). Move: background "
                 "`carry` takes the background slot along the rays the moved slot covers (by the rule "
                 "in brackets: `winner` where the moved slot wins its own pass's segmentation, "
                 "`opacity` in proportion to its opacity alone), "
                 "`stay` leaves it; uncovered `background` fills what an edit uncovers with the "
                 "background slot's colour, `black` leaves it to the renderer's empty ray (the "
                 "defaults, `carry / background`, chosen on the validation split). Commit: the "
                 f"code that scored the file. Measured on {host(list(files))}.",
                 _files_line(list(files))]


TABLES: dict[str, Callable[[], list[str]]] = {
    "fast_seeds": fast_seeds,
    "fast_seeds_trained": fast_seeds_trained,
    "fast_average_paired": fast_average_paired,
    "bench_allocators": bench_allocators,
    "bench_memory": bench_memory,
    "quick_model": quick_model,
    "gpu_figures": gpu_figures,
    "clevr_heldout": clevr_heldout,
    "edit_clevr": edit_clevr,
    **room_tables.TABLES,
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
