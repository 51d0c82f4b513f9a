"""Import floors, read from the installed package's source and the checkout's tools/: every `import` and `from`
statement (inside functions and TYPE_CHECKING blocks too, relative ones resolved), so a lazy import cannot hide a
wrong dependency.

The exporter's floors import only downwards: model < export < verify < demo | imports | voice (exporter/__init__.py
says what each holds). The service (`gaussiantalker.serve`) and batch rendering (`gaussiantalker.batch`) import
the runtime and the sdk, never the exporter nor each other, and nothing below them imports them. The console
scripts (`gaussiantalker.cli`) may import the exporter, the runtime, the service, batch and the sdk, and none of
those imports them. tools/ (the benchmarks and the browser harness, run from a checkout) may import anything;
nothing in the package imports tools/ except the two launchers that run it (`gt-bench`, `gt-web`). No two modules
of the exporter, the sdk, the runtime, the service, batch, the console scripts or tools/ import each other,
directly or around a longer loop.
"""

from __future__ import annotations

import ast
import importlib.util
from collections.abc import Iterable
from pathlib import Path

import pytest

EXPORTER = "gaussiantalker.exporter"
# Rank of each exporter floor (its sub-package; "" is the package's own __init__): a module may import modules of its
# own rank or below. demo, imports and voice share a rank; NEVER_IMPORTS keeps them apart (the voice driver uses the
# importer's audio-model checks, never the reverse).
FLOORS = {"model": 0, "export": 1, "verify": 2, "demo": 3, "imports": 3, "voice": 3, "": 4}
CLI = "gaussiantalker.cli"
SERVE = "gaussiantalker.serve"
BATCH = "gaussiantalker.batch"
TOOLS = "tools"
# (importer, imported) prefixes that must never meet, whatever the ranks say.
NEVER_IMPORTS = [
    (f"{EXPORTER}.export", f"{EXPORTER}.verify"),  # export never verifies (verify drives export's probes)
    (f"{EXPORTER}.imports", f"{EXPORTER}.demo"),
    (f"{EXPORTER}.imports", f"{EXPORTER}.voice"),
    (f"{EXPORTER}.voice", f"{EXPORTER}.demo"),
    ("gaussiantalker.sdk", "gaussiantalker.runtime"),
    ("gaussiantalker.sdk", "gaussiantalker.exporter"),
    ("gaussiantalker.runtime", "gaussiantalker.exporter"),
    ("gaussiantalker.sdk", CLI),
    ("gaussiantalker.runtime", CLI),
    ("gaussiantalker.exporter", CLI),
    ("gaussiantalker.sdk", SERVE),  # the service sits above the runtime: nothing below imports it
    ("gaussiantalker.runtime", SERVE),
    ("gaussiantalker.exporter", SERVE),
    (SERVE, "gaussiantalker.exporter"),  # a server never needs torch
    (SERVE, CLI),
    ("gaussiantalker.sdk", BATCH),  # batch sits above the runtime like the service: nothing below imports it
    ("gaussiantalker.runtime", BATCH),
    ("gaussiantalker.exporter", BATCH),
    (SERVE, BATCH),
    (BATCH, SERVE),
    (BATCH, "gaussiantalker.exporter"),  # a render worker never needs torch
    (BATCH, CLI),
]
# The package's only imports of tools/ (no other module of sdk, runtime, exporter or cli imports it): the launchers,
# after they put the checkout on sys.path (cli/checkout.py).
LAUNCHES = ["gaussiantalker.cli.bench -> tools.bench.app", "gaussiantalker.cli.web -> tools.browser.web_cli"]
# Packages that must have no import cycle among their own modules.
ACYCLIC = ["gaussiantalker.exporter", "gaussiantalker.sdk", "gaussiantalker.runtime", SERVE, BATCH, CLI, TOOLS]
CHECKOUT = Path(__file__).resolve().parents[1]


def installed_roots(names: Iterable[str] = ("sdk", "runtime", "exporter", "serve", "batch", "cli")) -> dict[str, Path]:
    """Source folder of each `gaussiantalker.<name>` the interpreter imports (found, not imported)."""
    roots = {}
    for name in names:
        spec = importlib.util.find_spec(f"gaussiantalker.{name}")
        assert spec is not None and spec.submodule_search_locations, f"gaussiantalker.{name} is not installed"
        roots[f"gaussiantalker.{name}"] = Path(next(iter(spec.submodule_search_locations)))
    return roots


def checked_roots() -> dict[str, Path]:
    """The installed package's folders and the checkout's tools/."""
    return installed_roots() | {TOOLS: CHECKOUT / "tools"}


def _modules(roots: dict[str, Path]) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (source file, whether it is a package's __init__)."""
    modules = {}
    for package, folder in roots.items():
        for path in sorted(folder.rglob("*.py")):
            relative = path.relative_to(folder).with_suffix("")
            is_package = relative.name == "__init__"
            parts = relative.parts[:-1] if is_package else relative.parts
            modules[".".join((package, *parts))] = (path, is_package)
    return modules


def import_graph(roots: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the modules under `roots` it imports (any import statement anywhere in its source)."""
    modules = _modules(roots)

    def known(name: str) -> str | None:  # the deepest module `name` is, or lies in
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in modules.items():
        package = name if is_package else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base_parts = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(base_parts + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                names = [base, *(f"{base}.{alias.name}" for alias in node.names)]
            else:
                continue
            targets.update(t for t in map(known, names) if t is not None and t != name)
        graph[name] = targets
    return graph


def floor_of(module: str, package: str = EXPORTER, floors: dict[str, int] = FLOORS) -> str:
    """The floor of one of `package`'s modules: the sub-package it is in (or is), or "" for a top-level module."""
    first = module[len(package) + 1:].split(".")[0] if module != package else ""
    return first if first in floors else ""


def subpackages(graph: dict[str, set[str]], package: str = EXPORTER) -> set[str]:
    """The names of `package`'s sub-packages (folders with modules in the graph)."""
    return {m[len(package) + 1:].split(".")[0] for m in graph if m.startswith(package + ".") and
            "." in m[len(package) + 1:]}


def floor_violations(graph: dict[str, set[str]], package: str = EXPORTER,
                     floors: dict[str, int] = FLOORS) -> list[str]:
    """'importer -> imported' for every import of a module of `package` from a higher floor (the package's own
    __init__, which Python imports before any of its modules, is not a floor: test_init_files_import_nothing)."""
    inside = sorted(m for m in graph if m == package or m.startswith(package + "."))
    found = []
    for module in inside:
        for target in sorted(graph[module]):
            low, high = floor_of(module, package, floors), floor_of(target, package, floors)
            if target in inside and target != package and floors[high] > floors[low]:
                found.append(f"{module} ({low or 'top'}) -> {target} ({high or 'top'})")
    return found


def forbidden_imports(graph: dict[str, set[str]], importer: str, imported: str) -> list[str]:
    """'a -> b' for every module under `importer` that imports one under `imported`."""
    def under(name: str, prefix: str) -> bool:
        return name == prefix or name.startswith(prefix + ".")

    return [f"{m} -> {t}" for m in sorted(graph) if under(m, importer) for t in sorted(graph[m]) if under(t, imported)]


def import_cycles(graph: dict[str, set[str]], package: str) -> list[list[str]]:
    """The import cycles among `package`'s modules: each strongly connected component of more than one module."""
    nodes = sorted(m for m in graph if m == package or m.startswith(package + "."))
    inside = set(nodes)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def connect(node: str) -> None:  # Tarjan; the package graphs are a few dozen modules deep at most
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node] & inside):
            if target not in index:
                connect(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in nodes:
        if node not in index:
            connect(node)
    return cycles


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(checked_roots())


def test_every_exporter_subpackage_is_a_floor(graph):
    found = subpackages(graph)
    assert found == set(FLOORS) - {""}, found ^ (set(FLOORS) - {""})  # and the graph really reads them all


def test_init_files_import_nothing(graph):
    """The exporter's, the console scripts' and tools/' __init__ files are one docstring each: importing a floor
    never pulls another module."""
    inits = [m for m in graph if m == EXPORTER or m.startswith(EXPORTER + ".") and m[len(EXPORTER) + 1:] in FLOORS]
    assert len(inits) == len(FLOORS)
    packages = [m for m in graph
                if m.split(".")[0] == TOOLS and CHECKOUT.joinpath(*m.split("."), "__init__.py").is_file()]
    inits += [CLI, *packages, *(f"{EXPORTER}.imports.{sub}" for sub in ("formats", "sources"))]
    assert {TOOLS, f"{TOOLS}.bench", f"{TOOLS}.browser"} <= set(packages)
    assert {m: graph[m] for m in inits if graph[m]} == {}


def test_exporter_floors_import_only_downwards(graph):
    violations = floor_violations(graph)
    assert not violations, "imports from a higher floor:\n" + "\n".join(violations)


def test_export_never_imports_verify(graph):
    assert any(t.startswith(f"{EXPORTER}.export.") for t in graph[f"{EXPORTER}.verify.bundle_verify"])  # seen at all
    assert not forbidden_imports(graph, f"{EXPORTER}.export", f"{EXPORTER}.verify")


@pytest.mark.parametrize("importer, imported", NEVER_IMPORTS)
def test_forbidden_imports(graph, importer, imported):
    found = forbidden_imports(graph, importer, imported)
    assert not found, f"{importer} must not import {imported}:\n" + "\n".join(found)


def test_module_file_names_say_which_module():
    """No two modules of the package share a file name, and none is named like its own package: a traceback, an
    import line or a docs mention names one module."""
    paths = [path for folder in installed_roots().values() for path in folder.rglob("*.py") if path.stem != "__init__"]
    seen: dict[str, list[str]] = {}
    for path in paths:
        seen.setdefault(path.name, []).append(str(path))
    assert {name: where for name, where in seen.items() if len(where) > 1} == {}
    assert [str(path) for path in paths if path.stem == path.parent.name] == []


def test_the_package_imports_tools_only_through_its_launchers(graph):
    """A wheel has no tools/: only `gt-bench` and `gt-web` reach them, once they found the checkout."""
    assert forbidden_imports(graph, "gaussiantalker", TOOLS) == LAUNCHES
    assert any(t.startswith(f"{TOOLS}.browser.") for t in graph[f"{TOOLS}.bench.lam_web"])  # tools are read too


@pytest.mark.parametrize("package", ACYCLIC)
def test_no_import_cycle(graph, package):
    cycles = import_cycles(graph, package)
    assert not cycles, f"import cycles in {package}:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_checker_sees_violations_and_cycles(tmp_path):
    """Guard against a checker that cannot fail: a tiny tree with a floor violation hidden in a function, a
    TYPE_CHECKING import and a relative-import cycle is reported in full."""
    root = tmp_path / "fake"
    files = {
        "__init__.py": "",
        "cli.py": "from .export import b\n",
        "model/__init__.py": "",
        "model/a.py": "def lazy():\n    from ..export.b import thing  # a floor violation hidden in a function\n",
        "export/__init__.py": "",
        "export/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from fake.verify import c\nx = 1\n",
        "verify/__init__.py": "",
        "verify/c.py": "from ..export import b\nimport fake.verify.d\n",
        "verify/d.py": "from . import c\n",
    }
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    fake = import_graph({"fake": root})
    assert subpackages(fake, "fake") == {"model", "export", "verify"}
    assert fake["fake.model.a"] == {"fake.export.b"}
    assert floor_violations(fake, "fake", FLOORS) == ["fake.export.b (export) -> fake.verify (verify)",
                                                      "fake.export.b (export) -> fake.verify.c (verify)",
                                              "fake.model.a (model) -> fake.export.b (export)"]
    assert forbidden_imports(fake, "fake.export", "fake.verify") == ["fake.export.b -> fake.verify",
                                                                     "fake.export.b -> fake.verify.c"]
    assert import_cycles(fake, "fake") == [["fake.export.b", "fake.verify.c", "fake.verify.d"]]
    assert import_cycles({k: v - {"fake.verify.c"} for k, v in fake.items()}, "fake") == []
