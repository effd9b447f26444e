"""The suite's own scheduling (tests/conftest.py): the heaviest files are collected first and
pytest-xdist keeps that order. A renamed file would silently drop out of HEAVIEST_FIRST and be
scheduled last again, which is what this file guards."""

import os
import subprocess
import sys
import tomllib

import conftest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_every_listed_file_exists_once():
  assert len(set(conftest.HEAVIEST_FIRST)) == len(conftest.HEAVIEST_FIRST)
  missing = [f for f in conftest.HEAVIEST_FIRST
             if not os.path.isfile(os.path.join(REPO, "tests", f))]
  assert not missing, f"tests/conftest.py HEAVIEST_FIRST names missing files: {missing}"


def test_collection_starts_with_the_heaviest_files_and_xdist_keeps_the_order():
  with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
    addopts = tomllib.load(f)["tool"]["pytest"]["ini_options"]["addopts"].split()
  assert "--dist" in addopts and addopts[addopts.index("--dist") + 1] == "loadfile"
  assert "--no-loadscope-reorder" in addopts
  out = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-n", "0",
                        "-p", "no:cacheprovider", "tests"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
  assert out.returncode == 0, out.stdout + out.stderr
  files = []
  for line in out.stdout.splitlines():
    if "::" in line:
      name = os.path.basename(line.split("::")[0])
      if not files or files[-1] != name:
        files.append(name)
  assert len(files) == len(set(files))  # each file's tests stay together
  assert files[:len(conftest.HEAVIEST_FIRST)] == list(conftest.HEAVIEST_FIRST)
