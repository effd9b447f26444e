"""Every reference in the repository's text points at something a user of the repository can open.

Comments, docstrings and markdown cite the method as `docs/method.md §N` and the CPU performance
notes as `docs/performance.md §N`. Notes kept outside the repository (a sibling `shared` folder and
the specification and performance files in it) were cited before; nobody with only the repository
can read them, so any mention of them fails here, naming file and line. Every cited section must
exist as a numbered heading of the page it names, and every markdown link into a docs page must
name an existing heading anchor.

Pure Python, no JAX: the files are those `git ls-files` lists (or, without git, a walk that skips
.venv and .git), read as UTF-8; binary files are skipped.
"""

import os
import re
import subprocess

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SKIP_DIRS = {".git", ".venv", "__pycache__", ".ipynb_checkpoints", "runs", "build", "dist"}
DOCS = {"method": "docs/method.md", "performance": "docs/performance.md"}

# Written in pieces so this file does not match itself.
FORBIDDEN = [
    re.compile(r"\b" + "SP" + r"EC\b"),  # the outside specification, with or without a section
    re.compile("PERF" + "_NOTES"),
    re.compile(re.escape("../" + "shared")),
]

HEADING = re.compile(r"^#{2,4}\s+(\d+(?:\.\d+)*)\.?\s+\S")
DOC_MENTION = re.compile(r"docs/(method|performance)\.md")
SECTION = re.compile(r"§\s*(\d+(?:\.\d+)*)(?:\s*[–-]\s*(\d+(?:\.\d+)*))?")
DOC_LINK = re.compile(r"\]\(((?:\.\./)*)docs/(method|performance)\.md#([^)\s]+)\)")


def _tracked_files() -> list[str]:
  try:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True)
    paths = [p for p in out.stdout.decode("utf-8").split("\0") if p]
  except (OSError, subprocess.CalledProcessError):
    paths = []
    for root, dirs, names in os.walk(REPO):
      dirs[:] = [d for d in dirs if d not in SKIP_DIRS]
      paths += [os.path.relpath(os.path.join(root, n), REPO) for n in names]
  return sorted(p for p in paths
                if not set(p.split("/")[:-1]) & SKIP_DIRS and os.path.isfile(os.path.join(REPO, p)))


def _text_files() -> dict[str, list[str]]:
  """Relative path → lines of every tracked file that decodes as UTF-8 and holds no NUL byte."""
  texts = {}
  for path in _tracked_files():
    with open(os.path.join(REPO, path), "rb") as f:
      data = f.read()
    if b"\0" in data:
      continue
    try:
      texts[path] = data.decode("utf-8").splitlines()
    except UnicodeDecodeError:
      continue
  return texts


def _slug(heading: str) -> str:
  """GitHub's anchor for a markdown heading: lower case, punctuation dropped, spaces to '-'."""
  return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _sections(lines: list[str]) -> tuple[set[str], set[str]]:
  """(section numbers, heading anchors) of a docs page."""
  numbers, anchors = set(), set()
  for line in lines:
    if line.startswith("#"):
      anchors.add(_slug(line.lstrip("#")))
      m = HEADING.match(line)
      if m:
        numbers.add(m.group(1))
  return numbers, anchors


def _citations(path: str, lines: list[str]):
  """(line number, page, section) of every § that follows a docs page's name on its line; inside
  a docs page a § with no page named before it on the line refers to that page itself."""
  own = next((k for k, v in DOCS.items() if v == path), None)
  for n, line in enumerate(lines, 1):
    mentions = [(m.end(), m.group(1)) for m in DOC_MENTION.finditer(line)]
    for m in SECTION.finditer(line):
      before = [page for end, page in mentions if end <= m.start()]
      page = before[-1] if before else own
      if page is None:
        continue
      for number in m.groups():
        if number:
          yield n, page, number


def test_docs_pages_exist_with_unique_numbered_sections():
  for page, rel in DOCS.items():
    path = os.path.join(REPO, rel)
    assert os.path.isfile(path), f"{rel} is missing"
    with open(path, encoding="utf-8") as f:
      numbers = [m.group(1) for m in map(HEADING.match, f.read().splitlines()) if m]
    assert numbers, f"{rel} has no numbered section headings"
    duplicates = sorted({x for x in numbers if numbers.count(x) > 1})
    assert not duplicates, f"{rel}: section numbers used twice: {duplicates}"


def test_no_reference_to_notes_outside_the_repository():
  bad = [f"{path}:{n}: {line.strip()[:120]}"
         for path, lines in _text_files().items()
         for n, line in enumerate(lines, 1)
         if any(p.search(line) for p in FORBIDDEN)]
  assert not bad, ("references to notes outside the repository (cite docs/method.md or "
                   "docs/performance.md instead):\n" + "\n".join(bad))


def test_every_cited_section_exists():
  texts = _text_files()
  sections = {page: _sections(texts[rel]) for page, rel in DOCS.items()}
  bad, count = [], 0
  for path, lines in texts.items():
    for n, page, number in _citations(path, lines):
      count += 1
      if number not in sections[page][0]:
        bad.append(f"{path}:{n}: {DOCS[page]} §{number} has no such section heading")
  assert count > 0, "no citation of docs/method.md found: the scan is broken"
  assert not bad, "\n".join(bad)


def test_every_link_into_docs_names_an_existing_anchor():
  texts = _text_files()
  anchors = {page: _sections(texts[rel])[1] for page, rel in DOCS.items()}
  bad = [f"{path}:{n}: #{m.group(3)} is not a heading of {DOCS[m.group(2)]}"
         for path, lines in texts.items()
         for n, line in enumerate(lines, 1)
         for m in DOC_LINK.finditer(line)
         if m.group(3) not in anchors[m.group(2)]]
  assert not bad, "\n".join(bad)
