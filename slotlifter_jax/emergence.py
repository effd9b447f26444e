"""Emergence curves and time to decomposition, from a run's DIR/metrics.jsonl.

How fast a run decomposes a scene into objects is read from its validation records: the
segmentation metrics (`fg_ari`, `nv_ari`, `attn_fg_ari`; `slotlifter_jax/evaluate.py`) against
training steps and against wall-clock time. "Time to decomposition" is the wall time at which the
rendered FG-ARI first reaches 0.5, and again 0.8. It has validation granularity: the true crossing
lies between the previous validation and this one, so both are reported (the previous one as the
lower bound).

Wall clock. Each record carries `wall_s`, the cumulative seconds of training of the run, summed
over resumes (validation and compile time included, the time between a kill and its resume not).
Older logs lack it; for a record without `wall_s` the clock is `time` minus the `time` of the
log's first record. That fallback misses what came before the first record (set-up, compilation,
the first logging interval) and counts the gaps between a kill and its resume; `wall_clock` in
the results says which clock was used.

Resumed runs. A run killed after its step-2000 record and resumed from its step-2000 checkpoint
logs steps 2050.. again into the same file. For each kind, a record replaces every earlier record
of that kind at the same or a later step: the last record of a repeated (kind, step) wins, and
records the killed attempt logged past the resume point go too, even those the resumed attempt has
not reached again.

Pure functions plus two I/O helpers (`load_records`, `write_emergence`); numpy and absl only, no
JAX, so the training loop and the plotting scripts can call it cheaply.
"""

from __future__ import annotations

import json
import math
import os
import secrets
from collections.abc import Sequence

import numpy as np
from absl import logging

METRICS_FILE = "metrics.jsonl"
EMERGENCE_FILE = "emergence.json"
CURVE_KEYS = ("attn_fg_ari", "fg_ari", "nv_ari", "psnr_novel")
THRESHOLDS = (0.5, 0.8)
# Names a validation record may carry its scene count under (the first present is reported).
_SCENE_COUNT_KEYS = ("num_val_scenes", "val_scenes", "eval_scenes", "num_scenes")
_LABELS = {"fg_ari": "FG-ARI", "nv_ari": "NV-ARI", "attn_fg_ari": "slot attention FG-ARI",
           "nv_fg_ari": "NV-FG-ARI", "ari": "ARI", "psnr_novel": "novel-view PSNR"}


def label(key: str) -> str:
  """A metric's display name ("fg_ari" → "FG-ARI")."""
  return _LABELS.get(key, key)


# ---------------------------------------------------------------------------------------------
# Reading the log
# ---------------------------------------------------------------------------------------------


def _parse_record(text: str):
  """The record on one line, or None when the line is not a JSON object with a step and a kind."""
  try:
    row = json.loads(text)
  except json.JSONDecodeError:
    return None
  if not isinstance(row, dict) or not isinstance(row.get("step"), int) or "kind" not in row:
    return None
  return row


def load_records(path: str) -> list[dict]:
  """The records of a metrics.jsonl in file order (blank lines skipped).

  A killed run may leave its last line truncated: it is skipped with a warning. The writer appends,
  so a resumed run's first record can land on the same line as such a truncated record; that line's
  complete trailing record is kept, with a warning. Any other line that is not a JSON object with
  `step` and `kind` raises ValueError naming the file and the line number.
  """
  with open(path) as f:
    lines = f.read().split("\n")
  numbered = [(n, line) for n, line in enumerate(lines, start=1) if line.strip()]
  records = []
  for i, (n, line) in enumerate(numbered):
    row = _parse_record(line)
    if row is None:
      start = line.rfind('{"step"')
      tail = _parse_record(line[start:]) if start > 0 else None
      if tail is not None:
        logging.warning("%s line %d: a truncated record followed by a complete one (a resumed "
                        "run appended to a killed run's last line); kept the complete one", path, n)
        row = tail
      elif i == len(numbered) - 1:
        logging.warning("%s line %d: skipped a truncated last record (a killed run)", path, n)
        continue
      else:
        raise ValueError(f"{path} line {n}: not a metrics record (a JSON object with 'step' and "
                         f"'kind'): {line[:80]!r}")
    records.append(row)
  return records


def latest_records(records: Sequence[dict], kind: str | None = None) -> list[dict]:
  """The records that survive resumes (module docstring), sorted by step; only `kind` when given.

  Walking in file order, a record of a kind drops every kept record of that kind at its step or
  later, so a repeated (kind, step) keeps its last record.
  """
  kept: dict[str, list[dict]] = {}
  for row in records:
    if kind is not None and row["kind"] != kind:
      continue
    same = kept.setdefault(row["kind"], [])
    while same and same[-1]["step"] >= row["step"]:  # steps increase within one attempt
      same.pop()
    same.append(row)
  return sorted((r for rows in kept.values() for r in rows), key=lambda r: r["step"])


def wall_seconds(records: Sequence[dict],
                 start_time: float | None = None) -> tuple[np.ndarray, str]:
  """(seconds of training at each record, which clock: "wall_s", "time", "mixed" or "none").

  A record's own `wall_s` when it has one; otherwise its `time` minus `start_time`, by default the
  `time` of `records[0]`; pass the log's first record's time when `records` is a subset (module
  docstring).
  """
  if start_time is None:
    start_time = float(records[0].get("time", math.nan)) if records else math.nan
  wall = np.asarray([float(r["wall_s"]) if "wall_s" in r
                     else float(r.get("time", math.nan)) - start_time for r in records], np.float64)
  has = {"wall_s" in r for r in records}
  clock = "mixed" if len(has) == 2 else "wall_s" if has == {True} else "time" if has else "none"
  return wall, clock


# ---------------------------------------------------------------------------------------------
# Curves and crossings
# ---------------------------------------------------------------------------------------------


def _validation(records: Sequence[dict]) -> tuple[list[dict], np.ndarray, str]:
  """(surviving validation records sorted by step, their wall seconds, clock name)."""
  val = latest_records(records, "val")
  # The fallback clock starts at the log's first record of any kind, not at its first validation.
  start = float(records[0].get("time", math.nan)) if records else math.nan
  wall, clock = wall_seconds(val, start)
  return val, wall, clock


def _value(row: dict, key: str) -> float:
  v = row.get(key)
  return math.nan if v is None else float(v)


def curves(records: Sequence[dict], keys: Sequence[str] = CURVE_KEYS) -> dict[str, np.ndarray]:
  """The validation curves: {"step", "wall_s", "minutes", *keys} as arrays of one length.

  One entry per surviving validation record (resumes resolved), sorted by step; a key a record
  lacks is NaN. `wall_s` follows `wall_seconds`; `minutes` is `wall_s / 60`.
  """
  val, wall, _ = _validation(records)
  out = {"step": np.asarray([r["step"] for r in val], np.int64), "wall_s": wall,
         "minutes": wall / 60}
  for key in keys:
    out[key] = np.asarray([_value(r, key) for r in val], np.float64)
  return out


def _point(step, wall_s) -> dict:
  return {"step": int(step), "wall_s": float(wall_s), "minutes": float(wall_s) / 60}


def time_to_decomposition(records: Sequence[dict], *, key: str = "fg_ari",
                          thresholds: Sequence[float] = THRESHOLDS) -> dict:
  """When the validation `key` first reaches each threshold, and its best value.

  Returns {
    "key": key, "thresholds": [...], "wall_clock": "wall_s" | "time" | "mixed" | "none",
    "num_validations": surviving validation records, "last_step": the last one's step or None,
    "crossings": {f"{t:g}": None when never reached, else {"step", "wall_s", "minutes", "value",
        "previous": {"step", "wall_s", "minutes"} of the validation before it, or None when it
        is the first validation (the lower bound is then the start of training)}},
    "best": {"step", "wall_s", "minutes", "value"} of the highest value (the first of ties), or
        None when no validation has a finite value,
  }
  The first crossing counts even when the value dips below the threshold later. The true
  crossing lies between "previous" and the reported validation (validation granularity).
  """
  val, wall, clock = _validation(records)
  values = np.asarray([_value(r, key) for r in val], np.float64)
  steps = [r["step"] for r in val]
  crossings = {}
  for t in thresholds:
    hit = np.flatnonzero(values >= t)  # NaN compares False: a validation without the key never hits
    if not hit.size:
      crossings[f"{t:g}"] = None
      continue
    i = int(hit[0])
    crossings[f"{t:g}"] = {**_point(steps[i], wall[i]), "value": float(values[i]),
                           "previous": _point(steps[i - 1], wall[i - 1]) if i else None}
  finite = np.flatnonzero(np.isfinite(values))
  best = None
  if finite.size:
    i = int(finite[np.argmax(values[finite])])
    best = {**_point(steps[i], wall[i]), "value": float(values[i])}
  return {"key": key, "thresholds": [float(t) for t in thresholds], "wall_clock": clock,
          "num_validations": len(val), "last_step": steps[-1] if steps else None,
          "crossings": crossings, "best": best}


def summary_lines(result: dict) -> list[str]:
  """Human-readable lines of a `time_to_decomposition` result, one per threshold, then the best."""
  name = label(result["key"])
  if not result["num_validations"]:
    return [f"time to decomposition ({name}): no validation records"]
  if result["best"] is None:
    return [f"time to decomposition ({name}): no validation record has a value of "
            f"{result['key']} (by step {result['last_step']})"]
  best = result["best"]
  best_text = f"best {name} {best['value']:.2f} at step {best['step']}"
  lines = []
  for t, c in result["crossings"].items():
    head = f"time to decomposition ({name} ≥ {t}): "
    if c is None:
      lines.append(head + f"not reached by step {result['last_step']} ({best_text})")
      continue
    prev = c["previous"]
    where = (f"previous validation {prev['step']} at {prev['minutes']:.1f} min" if prev
             else "the first validation")
    lines.append(head + f"{c['minutes']:.1f} min (step {c['step']}, {name} {c['value']:.2f}; "
                        f"{where})")
  lines.append(f"{best_text} ({best['minutes']:.1f} min)")
  if result["wall_clock"] != "wall_s":
    lines.append(f"wall clock: {result['wall_clock']} (records without wall_s count from the log's "
                 "first record's time; slotlifter_jax/emergence.py)")
  return lines


# ---------------------------------------------------------------------------------------------
# emergence.json
# ---------------------------------------------------------------------------------------------


def _jsonable(x):
  """NaN/inf → None and arrays → lists, so the file is strict JSON."""
  if isinstance(x, dict):
    return {k: _jsonable(v) for k, v in x.items()}
  if isinstance(x, (list, tuple, np.ndarray)):
    return [_jsonable(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)]
  if isinstance(x, (float, np.floating)):
    return float(x) if math.isfinite(x) else None
  if isinstance(x, np.integer):
    return int(x)
  return x


def write_json_atomically(path: str, data) -> None:
  """Writes `data` as strict JSON (NaN/inf as null, `_jsonable`) to a temporary file next to
  `path`, then renames it over `path`: a reader, or an interrupted write, never sees a partial
  file (os.replace is atomic within one file system)."""
  folder, name = os.path.split(os.path.abspath(path))
  # A fresh name in the same folder (os.replace does not cross file systems), opened exclusively;
  # not tempfile.mkstemp, whose 0600 mode would then be the result's.
  tmp = os.path.join(folder, f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
  try:
    with open(tmp, "x") as f:
      json.dump(_jsonable(data), f, indent=1, allow_nan=False)
      f.write("\n")
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except BaseException:
    if os.path.exists(tmp):
      os.remove(tmp)
    raise


def build_emergence(records: Sequence[dict], *, key: str = "fg_ari",
                    thresholds: Sequence[float] = THRESHOLDS,
                    other_keys: Sequence[str] = ("attn_fg_ari", "nv_ari", "fg_ari_multi")) -> dict:
  """The content of emergence.json (`write_emergence`) from a log's records, NaN as None."""
  out = time_to_decomposition(records, key=key, thresholds=thresholds)
  out["others"] = {k: {f: time_to_decomposition(records, key=k, thresholds=thresholds)[f]
                       for f in ("crossings", "best")} for k in other_keys}
  val = latest_records(records, "val")
  counts = [r[k] for k in _SCENE_COUNT_KEYS for r in reversed(val)
            if isinstance(r.get(k), (int, float)) and math.isfinite(r[k])]
  out["num_val_scenes"] = int(counts[0]) if counts else None
  out["summary"] = summary_lines(out)
  out["curves"] = curves(records, keys=tuple(dict.fromkeys((*CURVE_KEYS, key, *other_keys))))
  return _jsonable(out)


def write_emergence(workdir: str, **kwargs) -> dict:
  """Reads DIR/metrics.jsonl, writes DIR/emergence.json atomically and returns its content.

  Keyword arguments go to `build_emergence`. The file holds the `time_to_decomposition` fields for
  `key` (crossings, best, ...), "others" (crossings and best of attn_fg_ari, nv_ari and
  fg_ari_multi, the FG-ARI of views with two or more objects),
  "num_val_scenes" (None when no validation record carries a scene count), "summary" (the
  `summary_lines`) and "curves" (`curves` as lists); NaN is written as null.
  """
  data = build_emergence(load_records(os.path.join(workdir, METRICS_FILE)), **kwargs)
  write_json_atomically(os.path.join(workdir, EMERGENCE_FILE), data)
  return data
