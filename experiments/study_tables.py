"""The pure summaries of the study scripts (pareto.py, ablations.py, stability.py): the Pareto
front, per-variant statistics over seeds, and the markdown tables written to experiments/results/
(the statistics and the table are slotlifter_jax/tools/group_stats.py's, re-exported here).

Plain Python on CSV rows, no JAX and no files of a run (those are study_common's); tested in
tests/test_study.py against brute force and hand-computed examples.
"""

from __future__ import annotations

import math
import os
from typing import Sequence

# The per-group statistics and their table live in the library, where metrics_table reads them;
# the study scripts and tests/test_study.py keep reaching them through this module.
from slotlifter_jax.tools.group_stats import (  # noqa: F401  (re-exported)
    Stat, aggregate, format_stat, format_value, markdown_table, stat)


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


def write_text(path: str, text: str) -> None:
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  tmp = path + ".tmp"
  with open(tmp, "w") as f:
    f.write(text)
  os.replace(tmp, path)
