"""Shared fixtures: the embedded-data cache goes to a per-session temporary folder."""

import os

import pytest


@pytest.fixture(scope="session", autouse=True)
def _data_cache(tmp_path_factory):
  old = os.environ.get("SLOTLIFTER_DATA_CACHE")
  os.environ["SLOTLIFTER_DATA_CACHE"] = str(tmp_path_factory.mktemp("data_cache"))
  yield
  if old is None:
    os.environ.pop("SLOTLIFTER_DATA_CACHE", None)
  else:
    os.environ["SLOTLIFTER_DATA_CACHE"] = old
