"""The repository's import graph, read from the sources (ast: nothing is imported): no circle, the layers, and
drivers that use only python-can's and canopen's public names.

Every import counts, a deferred one inside a function included. A module of a package is named by its dotted
path; a file of tests/ or benchmarks/ (directories put on sys.path, not packages) by its stem.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("acquisition", "calib", "drivers", "sim_backend")
SCRIPT_DIRS = ("tests", "benchmarks")
THIRD_PARTY = ("can", "canopen")  # the drivers use only their public names


def modules(root: Path) -> dict[str, Path]:
    """{module name: file} of the packages and script directories under ``root``."""
    found = {}
    for pkg in PACKAGES:
        for f in sorted((root / pkg).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = f
    for d in SCRIPT_DIRS:
        for f in sorted((root / d).glob("*.py")):
            found[f.stem] = f
    return found


def imported(tree: ast.Module, name: str, is_package: bool) -> list[str]:
    """The dotted names a module imports: ``import a.b`` gives a.b, ``from a import b`` gives a.b (b may be a
    module or a name in a); relative imports are resolved against ``name``."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = name.split(".") if is_package else name.split(".")[:-1]
                parts = parts[:len(parts) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            out.extend(f"{base}.{a.name}" for a in node.names)
    return out


def import_graph(root: Path) -> dict[str, set[str]]:
    """{module: the modules of the repository it imports}."""
    mods = modules(root)
    graph = {}
    for name, f in mods.items():
        edges = set()
        for target in imported(ast.parse(f.read_text(), str(f)), name, f.name == "__init__.py"):
            while target and target not in mods:  # 'from pkg.mod import function' -> pkg.mod
                target = target.rpartition(".")[0]
            if target and target != name:
                edges.add(target)
        graph[name] = edges
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def layer_breaches(graph: dict[str, set[str]]) -> list[str]:
    """Imports against the layers: calib/ and drivers/ import neither sim_backend/ nor acquisition/, calib/ no
    drivers/."""
    forbidden = {"calib": ("sim_backend", "acquisition", "drivers"), "drivers": ("sim_backend", "acquisition")}
    return [f"{m} imports {t}" for m, targets in sorted(graph.items()) for t in sorted(targets)
            if t.split(".")[0] in forbidden.get(m.split(".")[0], ())]


def _private(name: str) -> bool:
    return name.startswith("_") and name not in ("__name__", "__doc__", "__version__")


def private_third_party_uses(root: Path, package: str = "drivers") -> list[str]:
    """Where a module of ``package`` imports a private (underscore) name of python-can or canopen, reaches one
    through a name bound to them (``can.Message.__new__``, ``canopen.network._x``), or reads an underscore
    attribute that no module of ``package`` defines (``bus._check_if_open()``: another library's internals)."""
    files = sorted((root / package).rglob("*.py"))
    trees = {f: ast.parse(f.read_text(), str(f)) for f in files}
    own = set()  # underscore names the package defines: functions, classes, assigned attributes and names
    for tree in trees.values():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                own.add(node.name)
            elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
                own.add(node.attr)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                own.add(node.id)
    found = []
    for f, tree in trees.items():
        where = f.relative_to(root)
        bound = set()  # names bound to python-can or canopen, or to something imported from them
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in THIRD_PARTY:
                        bound.add(a.asname or a.name.split(".")[0])
                        if any(_private(p) for p in a.name.split(".")):
                            found.append(f"{where}:{node.lineno} imports {a.name}")
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module.split(".")[0] in THIRD_PARTY:
                for a in node.names:
                    bound.add(a.asname or a.name)
                    if any(_private(p) for p in [*node.module.split("."), a.name]):
                        found.append(f"{where}:{node.lineno} imports {a.name} from {node.module}")
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute) or not _private(node.attr):
                continue
            chain, base = [node.attr], node.value
            while isinstance(base, ast.Attribute):
                chain.append(base.attr)
                base = base.value
            if isinstance(base, ast.Name) and base.id in bound:
                found.append(f"{where}:{node.lineno} uses {base.id}.{'.'.join(reversed(chain))}")
            elif node.attr not in own and not node.attr.startswith("__"):
                found.append(f"{where}:{node.lineno} reads .{node.attr}, which {package}/ does not define")
    return found


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph(ROOT)


def test_the_walk_sees_the_repository(graph):
    assert {"drivers.can_bus", "drivers.open", "sim_backend.backend", "acquisition.startup", "calib.robot",
            "test_canopen_drive", "bench_sim"} <= set(graph)
    assert "drivers.can_bus" in graph["drivers.canopen_node"]
    assert "drivers.open" in graph["acquisition.connect"]  # a deferred import inside connect()
    assert "test_canopen_drive" in graph["test_swivel_encoder"]


def test_no_import_circle(graph):
    assert circles(graph) == []


def test_calib_and_drivers_stay_below_the_simulator_and_the_acquisition(graph):
    assert layer_breaches(graph) == []


def test_drivers_use_only_public_names_of_python_can_and_canopen():
    assert private_third_party_uses(ROOT) == []


def test_each_rule_catches_what_it_forbids(tmp_path):
    """The same checks on a small tree that breaks every rule once."""
    files = {
        "drivers/__init__.py": "",
        "drivers/a.py": "from drivers.b import thing\nimport can\nfrom can.interfaces.virtual import _x\n"
                        "def f(bus):\n    bus._check_if_open()\n    return can.Message.__new__(can.Message)\n",
        "drivers/b.py": "def thing():\n    from drivers import a\n    return a\n",
        "calib/__init__.py": "",
        "calib/m.py": "import drivers.a\n",
        "sim_backend/__init__.py": "",
        "acquisition/__init__.py": "from sim_backend import *\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    for d in SCRIPT_DIRS:
        (tmp_path / d).mkdir()
    g = import_graph(tmp_path)
    assert circles(g) == [["drivers.a", "drivers.b"]]
    assert layer_breaches(g) == ["calib.m imports drivers.a"]
    assert private_third_party_uses(tmp_path) == [
        "drivers/a.py:3 imports _x from can.interfaces.virtual",
        "drivers/a.py:5 reads ._check_if_open, which drivers/ does not define",
        "drivers/a.py:6 uses can.Message.__new__",
    ]
