"""What experiments/tables.py and the table modules beside it share: the results folder, the error
a table raises, and how a result file's provenance names its machine. Standard library only."""

from __future__ import annotations

import json
import os

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(REPO, "experiments", "results")


class TableError(Exception):
  pass


def load_json(name: str, results: str | None = None) -> dict:
  path = os.path.join(RESULTS if results is None else results, name)
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except OSError as e:
    raise TableError(f"experiments/results/{name}: cannot read ({e.strerror})") from None


def described_host(record: dict) -> str | None:
  """'a 2-core CPU MODEL', or the accelerator's kind, from a provenance record
  (slotlifter_jax/provenance.py); None when it names no machine."""
  if record.get("platform") not in (None, "cpu"):
    return f"{record.get('device_kind') or record['platform']}"
  if record.get("cpu_model"):
    return f"a {record.get('cpu_count')}-core {record['cpu_model']}"
  return None


def files_line(names) -> str:
  return "Files: " + ", ".join(f"`experiments/results/{n}`" for n in names) + "."
