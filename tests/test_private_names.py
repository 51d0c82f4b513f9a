"""No file reaches into another's private names: a name that starts with one underscore belongs to the file that
defines it. Read from the installed package's source (every module of sdk, runtime, exporter and cli) and the
checkout's tools/:

* `from module import _name` of another module is refused;
* `something._name` is refused where another of the package's files defines `_name` and this one does not (a
  function, class, method or an attribute it assigns: `self._name = ...`), so a class's own privates, used through
  `self`, `cls` or another instance of it in the same file, stay allowed, and a private method of another file's
  class does not. (A library's internals, which no file of ours defines, are the library's business.)

Dunder names (`__version__`, `__init__`) are public by Python's own rules and not checked.
"""

from __future__ import annotations

import ast
from pathlib import Path

from test_layers import checked_roots


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _defined_here(tree: ast.AST) -> set[str]:
    """The private names a file defines: its functions, classes, assigned names and assigned attributes."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.arg):
            names.add(node.arg)
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):  # dataclass fields
            names.add(node.target.id)
    return {name for name in names if _private(name)}


def _tree(path: Path) -> ast.AST:
    return ast.parse(path.read_text(encoding="utf-8"), str(path))


def private_reaches(path: Path, ours: set[str]) -> list[str]:
    """'file:line what' for each use in `path` of a private name that another of the package's files defines
    (`ours`: every private name the package's files define)."""
    tree = _tree(path)
    own = _defined_here(tree)
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            found += [f"{path}:{node.lineno} from {'.' * node.level}{node.module or ''} import {alias.name}"
                      for alias in node.names if _private(alias.name)]
        elif isinstance(node, ast.Attribute) and _private(node.attr) and node.attr in ours - own:
            found.append(f"{path}:{node.lineno} {ast.unparse(node)}")
    return found


def test_no_file_uses_another_files_private_names():
    paths = [path for folder in checked_roots().values() for path in sorted(folder.rglob("*.py"))]
    ours = set().union(*(_defined_here(_tree(path)) for path in paths))
    found = [reach for path in paths for reach in private_reaches(path, ours)]
    assert found == [], "\n".join(found)


def test_the_check_sees_what_it_refuses(tmp_path):
    """The checker itself: each kind of reach is caught, and a file's own privates are not."""
    source = tmp_path / "sample.py"
    source.write_text(
        "from .other import _hidden, public\n"
        "class Box:\n"
        "    def __init__(self):\n"
        "        self._mine = 1\n"
        "    def _helper(self, other: 'Box'):\n"
        "        return other._mine + self._mine\n"
        "def use(head):\n"
        "    return head._run_translator(), Box()._helper(Box()), head.__class__, head._library_internal\n")
    ours = {"_hidden", "_run_translator", "_mine", "_helper"}  # what the package's files define
    assert [line.split(" ", 1)[1] for line in private_reaches(source, ours)] == [
        "from .other import _hidden", "head._run_translator"]
