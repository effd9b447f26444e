"""Whether two runs hold the same trained state, leaf by leaf: the parameters, the optimiser's
state (with the moving average of the parameters, when a run keeps one), the step and the
counters of skipped steps.

  python experiments/compare_checkpoints.py RUN_A RUN_B
  python experiments/compare_checkpoints.py RUN_A RUN_B --checkpoint=best --show=10

RUN_A and RUN_B are run folders (a training run's --workdir). --checkpoint picks the checkpoint
of each: latest (the default), best, or a step number (among the latest checkpoints, then the
best). The arrays are read as saved, with the shapes and dtypes of the checkpoint's own metadata,
so no config, model or data is read, and nothing is written.

Prints both checkpoints, the number of leaves, how many are bit-identical and the largest
absolute difference, then the --show leaves that differ most. Exit status: 0 when every leaf is
bit-identical, 1 when some differ, 2 when the two cannot be compared (a run folder or checkpoint
that is missing, or trees of other leaves, shapes or dtypes).

Why: a claim that two runs trained the same weights (a resumed run against a straight one, a
study run against the README's command with the same seed; experiments/journal/2026-11.md,
"Speed against accuracy") rests on the weights themselves, not on equal metrics.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)


class CompareError(ValueError):
  """Two checkpoints that cannot be compared leaf by leaf."""


def _leaves(tree) -> dict[str, np.ndarray]:
  import jax
  return {jax.tree_util.keystr(path): np.asarray(x)
          for path, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


def compare(a, b) -> list[tuple[str, bool, float]]:
  """(leaf path, bit-identical, largest |a − b| in float64) for every leaf of trees `a` and `b`,
  in path order. Raises CompareError when the trees have other leaves, shapes or dtypes."""
  la, lb = _leaves(a), _leaves(b)
  if la.keys() != lb.keys():
    only_a, only_b = sorted(la.keys() - lb.keys()), sorted(lb.keys() - la.keys())
    raise CompareError(f"the trees differ: only in A {only_a[:3]}, only in B {only_b[:3]}")
  rows = []
  for path in sorted(la):
    x, y = la[path], lb[path]
    if x.shape != y.shape or x.dtype != y.dtype:
      raise CompareError(f"{path}: A is {x.dtype}{list(x.shape)}, B is {y.dtype}{list(y.shape)}")
    same = x.tobytes() == y.tobytes()
    diff = 0.0 if same or x.size == 0 else float(
        np.max(np.abs(x.astype(np.float64) - y.astype(np.float64))))
    rows.append((path, same, diff))
  return rows


def main(argv: list[str] | None = None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("run_a")
  parser.add_argument("run_b")
  parser.add_argument("--checkpoint", default="latest",
                      help="latest (default), best, or a step number")
  parser.add_argument("--show", type=int, default=5, help="leaves listed when some differ")
  args = parser.parse_args(argv)
  from slotlifter_jax import checkpoints as ckpt_lib
  try:
    (a, dir_a), (b, dir_b) = (ckpt_lib.read_saved_state(run, args.checkpoint)
                              for run in (args.run_a, args.run_b))
    rows = compare(a, b)
  except (OSError, ValueError) as e:  # ckpt_lib's EvalSetupError and CompareError are ValueErrors
    print(f"error: {e}", file=sys.stderr)
    return 2
  same = sum(s for _, s, _ in rows)
  print(f"A: {dir_a}\nB: {dir_b}")
  print(f"{len(rows)} leaves, {same} bit-identical; largest |difference| "
        f"{max((d for _, _, d in rows), default=0.0):.3g}")
  differing = sorted((r for r in rows if not r[1]), key=lambda r: -r[2])
  for path, _, diff in differing[:args.show]:
    print(f"  {path}: largest |difference| {diff:.3g}")
  if len(differing) > args.show:
    print(f"  ... and {len(differing) - args.show} more")
  return 0 if same == len(rows) else 1


if __name__ == "__main__":
  sys.exit(main())
