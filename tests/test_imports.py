"""The package's import graph has no cycles.

A cycle between two modules works only while one side imports the other inside a function, and
breaks (a partly initialised module, an AttributeError at import) as soon as someone moves that
import to the top. So the graph is read from the source with `ast`, module-level and
function-level imports alike, and any cycle fails the test with its modules named in order.

Pure Python, no JAX: nothing of the package is imported.
"""

import ast
import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE = "slotlifter_jax"


def _modules(root: str, package: str) -> dict[str, str]:
  """Dotted module name → file path of every .py file of the package under `root`."""
  out = {}
  base = os.path.join(root, package)
  for folder, dirs, names in os.walk(base):
    dirs[:] = sorted(d for d in dirs if d != "__pycache__")
    for name in sorted(names):
      if not name.endswith(".py"):
        continue
      parts = os.path.relpath(os.path.join(folder, name), root)[:-3].split(os.sep)
      if parts[-1] == "__init__":
        parts = parts[:-1]
      out[".".join(parts)] = os.path.join(folder, name)
  return out


def _is_type_checking(node: ast.If) -> bool:
  test = node.test
  return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
      isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imported(tree: ast.Module, module: str, is_package: bool, known: set[str]) -> set[str]:
  """The package's modules that `module` imports anywhere in its body (functions included),
  except under `if TYPE_CHECKING:`, which never runs."""
  skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node)
          for child in node.body for n in ast.walk(child)}
  # The package a relative import counts from: the module's own for an __init__, else its parent.
  here = module.split(".") if is_package else module.split(".")[:-1]
  out = set()
  for node in ast.walk(tree):
    if id(node) in skip:
      continue
    if isinstance(node, ast.Import):
      targets = [alias.name for alias in node.names]
    elif isinstance(node, ast.ImportFrom):
      if node.level:
        anchor = here[:len(here) - node.level + 1]
        source = ".".join(anchor + ([node.module] if node.module else []))
      else:
        source = node.module or ""
      # `from a import b`: b is a submodule when a.b is one, else a name defined in a.
      targets = [f"{source}.{alias.name}" if f"{source}.{alias.name}" in known else source
                 for alias in node.names]
    else:
      continue
    for target in targets:
      # `import a.b.c` binds a but runs a.b.c: the edge goes to the deepest known module.
      parts = target.split(".")
      while parts and ".".join(parts) not in known:
        parts.pop()
      if parts and ".".join(parts) != module:
        out.add(".".join(parts))
  return out


def import_graph(root: str = REPO, package: str = PACKAGE) -> dict[str, set[str]]:
  """Module → the package modules it imports, read from the source under `root`."""
  files = _modules(root, package)
  known = set(files)
  graph = {}
  for module, path in files.items():
    with open(path, encoding="utf-8") as f:
      tree = ast.parse(f.read(), filename=path)
    graph[module] = _imported(tree, module, path.endswith("__init__.py"), known)
  return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
  """One cycle as [m0, m1, …, m0], or None. Depth-first search in sorted order, so the same graph
  always reports the same cycle."""
  state = {}  # module → 1 while on the current path, 2 when finished
  path = []

  def visit(node):
    state[node] = 1
    path.append(node)
    for nxt in sorted(graph.get(node, ())):
      if state.get(nxt) == 1:
        return path[path.index(nxt):] + [nxt]
      if nxt not in state:
        found = visit(nxt)
        if found:
          return found
    path.pop()
    state[node] = 2
    return None

  for node in sorted(graph):
    if node not in state:
      found = visit(node)
      if found:
        return found
  return None


def test_package_imports_have_no_cycle():
  graph = import_graph()
  cycle = find_cycle(graph)
  assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_graph_sees_module_and_function_level_imports():
  # Known edges of both kinds, so an empty or half-read graph cannot pass the cycle test.
  graph = import_graph()
  assert "slotlifter_jax.validation" in graph["slotlifter_jax.train"]  # module level
  assert "slotlifter_jax.data.types" in graph["slotlifter_jax.train_step"]  # `from a.b import X`
  assert "slotlifter_jax.train" in graph["slotlifter_jax.main"]  # inside main()
  assert "slotlifter_jax.data.generator" in graph["slotlifter_jax.data.embedded"]  # in a function


@pytest.mark.parametrize("source, cycle", [
    # A module-level import one way and a function-level one back: the shape of the cycles that
    # were removed (evaluate ↔ train, rendering.adaptive ↔ rendering.views).
    ({"a.py": "from pkg import b\n",
      "b.py": "def f():\n  from pkg import a\n  return a\n"}, ["pkg.a", "pkg.b", "pkg.a"]),
    ({"a.py": "import pkg.sub.c\n", "sub/__init__.py": "",
      "sub/c.py": "from ..a import x\n"}, ["pkg.a", "pkg.sub.c", "pkg.a"]),
    ({"a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n  from pkg import b\n",
      "b.py": "from pkg import a\n"}, None),
])
def test_cycle_detection_on_a_made_up_package(tmp_path, source, cycle):
  for name, text in {"__init__.py": "", **source}.items():
    path = tmp_path / "pkg" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
  assert find_cycle(import_graph(str(tmp_path), "pkg")) == cycle


def test_library_never_imports_experiments():
  # experiments/ is studies and benchmarks built on the library; a library module that reached
  # back into it would work only from a checkout with the repository root on sys.path.
  bad = []
  for module, path in _modules(REPO, PACKAGE).items():
    with open(path, encoding="utf-8") as f:
      tree = ast.parse(f.read(), filename=path)
    for node in ast.walk(tree):
      names = ([alias.name for alias in node.names] if isinstance(node, ast.Import) else
               [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
      bad += [f"{module}:{node.lineno}: imports {name}" for name in names
              if name == "experiments" or name.startswith("experiments.")]
  assert not bad, "\n".join(bad)
