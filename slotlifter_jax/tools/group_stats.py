"""Mean ± sample standard deviation of metrics over groups of runs, and the markdown table of them:
metrics_table.py's rows and the study scripts' (experiments/study_tables.py re-exports these).

Plain Python on dict rows (CSV rows or metrics.json means), no JAX and no files; tested in
tests/test_study.py against hand-computed examples.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Iterable, Optional, Sequence


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
