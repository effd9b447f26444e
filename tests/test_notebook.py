"""experiments/inspect.ipynb runs top to bottom on the smoke config, so it never rots."""

import os
import re

import nbformat
import pytest
from nbclient import NotebookClient

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOK = os.path.join(REPO, "experiments", "inspect.ipynb")


@pytest.mark.slow
def test_inspect_notebook_executes(monkeypatch):
  # The kernel inherits this process's environment: conftest's SLOTLIFTER_DATA_CACHE (a
  # per-session folder) and no workdir, so the notebook inspects a freshly initialised model.
  assert os.environ.get("SLOTLIFTER_DATA_CACHE")
  monkeypatch.setenv("SLOTLIFTER_WORKDIR", "")
  nb = nbformat.read(NOTEBOOK, as_version=4)
  assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), \
      "store the notebook without outputs"
  NotebookClient(nb, timeout=600, kernel_name="python3",
                 resources={"metadata": {"path": REPO}}).execute()  # raises on any cell error

  text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                 for o in c.outputs if o.output_type == "stream")
  images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code"
               for o in c.outputs)
  assert images >= 8
  # The notebook's own volume rendering of the captured samples reproduces the model's.
  match = re.search(r"max \|difference\| to the model's rendering: (\S+)", text)
  assert match and float(match.group(1)) < 1e-5
