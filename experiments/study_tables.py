"""The pure summaries of the study scripts (pareto.py, ablations.py, stability.py): the Pareto
front, per-variant statistics over seeds, and the markdown tables written to experiments/results/.

Plain Python on CSV rows, no JAX and no files of a run (those are study_common's); tested in
tests/test_study.py against brute force and hand-computed examples.
"""

from __future__ import annotations

import dataclasses
import math
import os
import statistics
from typing import Iterable, Optional, Sequence


def pareto_front(costs: Sequence[float], values: Sequence[float]) -> list[int]:
  """Indices of the points no other point dominates (lower cost and higher value are better),
  ordered by cost. j dominates i when cost_j ≤ cost_i and value_j ≥ value_i, one strictly; equal
  points do not dominate each other. Points with a NaN coordinate are never on the front.

  One sort and a sweep, O(n log n): among points of lower cost only the best value so far matters,
  and within one cost only the group's best value survives.
  """
  pts = [(float(c), float(v), i) for i, (c, v) in enumerate(zip(costs, values))
         if not (math.isnan(float(c)) or math.isnan(float(v)))]
  pts.sort(key=lambda p: (p[0], -p[1]))
  front, best_before = [], -math.inf  # best value among strictly cheaper points
  i = 0
  while i < len(pts):
    j = i
    while j < len(pts) and pts[j][0] == pts[i][0]:
      j += 1
    group_best = pts[i][1]  # sorted by value descending within a cost
    if group_best > best_before:
      front.extend(p[2] for p in pts[i:j] if p[1] == group_best)
      best_before = group_best
    i = j
  return front


@dataclasses.dataclass(frozen=True)
class Stat:
  """Summary of one metric over a group's runs (NaN values skipped)."""
  n: int
  mean: float
  std: float  # sample standard deviation (ddof = 1); NaN for n < 2
  min: float
  max: float


def stat(values: Iterable[float]) -> Stat:
  xs = [float(x) for x in values if x not in ("", None) and not math.isnan(float(x))]
  if not xs:
    return Stat(0, math.nan, math.nan, math.nan, math.nan)
  return Stat(len(xs), statistics.fmean(xs), statistics.stdev(xs) if len(xs) > 1 else math.nan,
              min(xs), max(xs))


def aggregate(rows: Sequence[dict], *, metrics: Sequence[str], group_by: str = "name",
              order: Optional[Sequence[str]] = None) -> list[dict]:
  """Per group: {group, runs, collapse_rate, collapsed_runs, flagged_runs, <metric>: Stat};
  collapse rate = collapsed runs / runs with a known flag (NaN when none has one). All runs enter
  the metrics, collapsed or not, as in the paper's means over seeds."""
  groups: dict[str, list[dict]] = {}
  for r in rows:
    groups.setdefault(r[group_by], []).append(r)
  names = [g for g in (order or []) if g in groups] + sorted(set(groups) - set(order or []))
  out = []
  for g in names:
    rs = groups[g]
    flags = stat(r.get("collapsed", math.nan) for r in rs)
    out.append(dict({group_by: g, "runs": len(rs), "collapse_rate": flags.mean,
                     "collapsed_runs": int(round(flags.mean * flags.n)) if flags.n else 0,
                     "flagged_runs": flags.n},
                    **{m: stat(r.get(m, math.nan) for r in rs) for m in metrics}))
  return out


def format_value(value, *, digits: int, scale: float = 1.0) -> str:
  """One CSV value (× scale) for a table cell; '–' for NaN or an empty cell."""
  try:
    value = float(value)
  except (TypeError, ValueError):
    return "–"
  return "–" if math.isnan(value) else f"{value * scale:.{digits}f}"


def format_stat(s: Stat, *, scale: float = 1.0, digits: int = 1, extremes: bool = False) -> str:
  """'mean ± std' (× scale), with ' [min, max]' when `extremes`; '–' for no value."""
  if s.n == 0:
    return "–"
  f = lambda x: f"{x * scale:.{digits}f}"
  text = f(s.mean) + (f" ± {f(s.std)}" if s.n > 1 else "")
  return text + (f" [{f(s.min)}, {f(s.max)}]" if extremes else "")


def markdown_table(groups: Sequence[dict], *, columns: Sequence[tuple[str, str, float, int]],
                   group_by: str = "name", extremes: bool = False, collapse: bool = True) -> str:
  """A markdown table: one row per group; columns = (metric, header, scale, digits); a collapse
  column 'k/n' at the end unless `collapse` is False (rows without validation flags)."""
  head = [group_by, "runs"] + [h for _, h, _, _ in columns] + (["collapse rate"] if collapse else [])
  lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
  for g in groups:
    cells = [str(g[group_by]), str(g["runs"])]
    cells += [format_stat(g[m], scale=scale, digits=digits, extremes=extremes)
              for m, _, scale, digits in columns]
    rate = g["collapse_rate"]
    if collapse:
      cells.append("–" if math.isnan(rate) else
                   f"{g['collapsed_runs']}/{g['flagged_runs']} ({rate:.0%})")
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines)


def write_text(path: str, text: str) -> None:
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    f.write(text)
  os.replace(tmp, path)
