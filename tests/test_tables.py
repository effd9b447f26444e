"""experiments/tables.py: every table between `<!-- table:NAME -->` markers in README.md and docs/
is the one its result files give, so a number typed or left stale there fails here."""

import os
import shutil
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

import pytest  # noqa: E402

from experiments import tables  # noqa: E402


def test_every_table_in_the_readme_and_docs_matches_its_result_files():
  assert tables.run(check=True) == []


def _copy_pages(tmp_path):
  shutil.copy(os.path.join(REPO, "README.md"), tmp_path / "README.md")
  shutil.copytree(os.path.join(REPO, "docs"), tmp_path / "docs",
                  ignore=shutil.ignore_patterns("*.png", "*.gif"))
  return tmp_path


def test_a_changed_number_between_markers_fails_and_a_rewrite_restores_it(tmp_path):
  repo = _copy_pages(tmp_path)
  text = (repo / "README.md").read_text(encoding="utf-8")
  start = text.index("<!-- table:fast_seeds -->")
  row = text.index("| 1 | ", start)
  changed = text[:row] + text[row:].replace("| 1 | ", "| 1 | 1", 1)  # 50000 → 150000
  (repo / "README.md").write_text(changed, encoding="utf-8")
  problems = tables.run(check=True, repo=str(repo))
  assert len(problems) == 1 and problems[0].startswith("README.md:"), problems
  assert tables.run(check=False, repo=str(repo)) == []
  assert (repo / "README.md").read_text(encoding="utf-8") == text


def test_unknown_or_unclosed_markers_are_errors(tmp_path):
  repo = _copy_pages(tmp_path)
  (repo / "docs" / "extra.md").write_text("<!-- table:nonesuch -->\n<!-- /table:nonesuch -->\n")
  with pytest.raises(tables.TableError, match="no table 'nonesuch'"):
    tables.run(check=True, repo=str(repo))
  (repo / "docs" / "extra.md").write_text("<!-- table:fast_seeds -->\n")
  with pytest.raises(tables.TableError, match="never closed"):
    tables.run(check=True, repo=str(repo))


def test_the_command_line_check_passes():
  assert tables.main(["--check"]) == 0


def test_the_held_out_table_refuses_a_headline_of_another_split(tmp_path, monkeypatch):
  import json
  # A headline file of the development split must never fill the held-out table.
  (tmp_path / tables.HEADLINE_CLEVR).write_text(json.dumps({"split": "dev", "seeds": []}))
  monkeypatch.setattr(tables, "RESULTS", str(tmp_path))
  with pytest.raises(tables.TableError, match="headline_clevr.json: split 'dev'"):
    tables.clevr_heldout()
