"""The runtime's modules import each other without loops: read from the source (every `import`/`from` statement,
inside functions too, relative imports resolved), so a loop hidden in a lazy import is found as well."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNTIME_DIR = ROOT / "runtime"
RUNTIME_PACKAGE = "gaussiantalker.runtime"


def module_names(package_dir: Path, package: str) -> dict[str, Path]:
    """Dotted name -> file of every module of the package (`__init__.py` is the package itself)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        names[".".join([package, *parts])] = path
    return names


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The package's module that loading `name` runs last: the longest prefix of it that is one (None: outside)."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        if ".".join(parts[:end]) in modules:
            return ".".join(parts[:end])
    return None


def _imports(tree: ast.AST, module: str, is_package: bool, modules: dict[str, Path]) -> set[str]:
    """The package's modules that the import statements anywhere in `tree` (inside functions too) load by name.

    `import pkg.x` and `from pkg.x import y` load pkg.x; `from pkg import x` loads pkg.x when x is a submodule,
    else the package itself. A parent package that Python imports on the way is not counted: importing any
    submodule does that, it is not a loop the code can avoid.
    """
    targets = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets.update(_resolve(alias.name, modules) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                # A relative import counts from the module's package (the module itself for an __init__.py).
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module
            for alias in node.names:
                submodule = f"{source}.{alias.name}"
                targets.add(submodule if submodule in modules else _resolve(source, modules))
    targets.discard(None)
    return targets


def import_graph(package_dir: Path, package: str) -> dict[str, set[str]]:
    """Module -> the package's modules it imports."""
    modules = module_names(package_dir, package)
    graph = {}
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        graph[module] = _imports(tree, module, path.name == "__init__.py", modules)
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (first module repeated at the end) per group of modules that import each other, however far."""
    cycles, state = [], {}  # state: 1 on the current path, 2 done

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        path.append(module)
        for target in sorted(graph.get(module, ())):
            if state.get(target) == 1:
                cycles.append(path[path.index(target):] + [target])
            elif target not in state:
                visit(target, path)
        path.pop()
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [])
    return cycles


def test_no_runtime_module_imports_one_that_imports_it_back():
    graph = import_graph(RUNTIME_DIR, RUNTIME_PACKAGE)
    assert f"{RUNTIME_PACKAGE}.head" in graph and len(graph) >= 10  # the check really read the runtime
    assert f"{RUNTIME_PACKAGE}.backend" in graph[f"{RUNTIME_PACKAGE}.head"]
    cycles = import_cycles(graph)
    assert cycles == [], "import loops in the runtime:\n" + "\n".join(" -> ".join(c) for c in cycles)


def _write_package(root: Path, files: dict[str, str]) -> Path:
    package = root / "pkg"
    for name, text in files.items():
        path = package / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return package


def test_the_check_finds_a_loop_hidden_in_a_function(tmp_path):
    """Guard against a check that cannot fail: a loop closed by a lazy relative import three modules away."""
    package = _write_package(tmp_path, {
        "__init__.py": "from .a import run\n",
        "a.py": "from .b import helper\n\ndef run():\n    return helper()\n",
        "b.py": "import pkg.c\n\ndef helper():\n    return pkg.c.value()\n",
        "c.py": "def value():\n    from . import a  # lazy: still a loop\n    return a\n",
        "d.py": "from pkg import a\n",
    })
    cycles = import_cycles(import_graph(package, "pkg"))
    assert cycles == [["pkg.a", "pkg.b", "pkg.c", "pkg.a"]]


def test_the_check_resolves_each_import_form(tmp_path):
    """`from . import x`, `from ..x import y` (from a sub-package), `import pkg.x` and `from pkg import name` (the
    package itself) each give the module they load, and a package without loops passes."""
    package = _write_package(tmp_path, {
        "__init__.py": "from .a import run\n",
        "a.py": "from . import b\nimport pkg.c\n\ndef run():\n    return b, pkg.c\n",
        "b.py": "X = 1\n",
        "c.py": "X = 2\n",
        "sub/__init__.py": "",
        "sub/e.py": "from ..b import X\nfrom pkg import run\n",
    })
    graph = import_graph(package, "pkg")
    assert graph == {"pkg": {"pkg.a"}, "pkg.a": {"pkg.b", "pkg.c"}, "pkg.b": set(), "pkg.c": set(),
                     "pkg.sub": set(), "pkg.sub.e": {"pkg.b", "pkg"}}
    assert import_cycles(graph) == []
