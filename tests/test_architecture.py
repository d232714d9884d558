"""The import architecture, checked on the source text (``ast``; nothing is imported).

Every ``.py`` module under ``nkf_model/``, ``benchmarks/`` and ``nkf_blender/`` is parsed and every
import in it resolved: module-level imports and the ones inside functions, relative imports against
the module's package, ``from pkg import name`` as ``pkg.name`` when ``pkg/name.py`` or ``pkg/name/``
exists (else as ``pkg``), and ``importlib.import_module("literal")``. The tests then require

* no import cycle among ``nkf_model`` modules (a cycle closed only through a function-local import
  counts too). Edges from a package's ``__init__`` to its own submodules are left out: re-exporting
  a child is not a dependency of the child on the package;
* the allowed directions: nothing in ``nkf_model`` imports ``benchmarks``, ``nkf_blender`` or
  ``bpy``; the core (``nkf_model`` less ``nkf_model.train``, ``nkf_model.cli`` and
  ``nkf_model.__main__``) imports neither ``nkf_model.train`` nor ``nkf_model.cli``; ``nkf_blender``
  imports neither ``nkf_model.train``, ``nkf_model.cli`` nor ``benchmarks``.

The last tests run the checker on small module trees written to a temporary folder, so that it is
seen to fail when it should.
"""

from __future__ import annotations

import ast
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TOP_PACKAGES = ("nkf_model", "benchmarks", "nkf_blender")


@dataclass(frozen=True)
class Module:
    name: str  # dotted, a package by its own name ("nkf_model.fit" for nkf_model/fit/__init__.py)
    path: Path
    is_package: bool


@dataclass(frozen=True)
class Edge:
    source: str
    target: str  # dotted; a module of the tree or anything else ("numpy", "bpy.props")
    path: Path
    line: int
    function: str | None  # the enclosing function of a function-local import, else None

    def where(self, root: Path) -> str:
        try:
            shown = self.path.relative_to(root)
        except ValueError:
            shown = self.path
        local = f", inside {self.function}()" if self.function else ""
        return f"{shown}:{self.line}{local}"


def within(name: str, package: str) -> bool:
    """Whether ``name`` is ``package`` or lies under it."""
    return name == package or name.startswith(package + ".")


def discover(root: Path, packages=TOP_PACKAGES) -> dict[str, Module]:
    """The modules of ``packages`` under ``root``, by dotted name."""
    modules = {}
    for top in packages:
        base = root / top
        if not base.is_dir():
            continue
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(root)
            if "__pycache__" in rel.parts:
                continue
            parts = list(rel.with_suffix("").parts)
            is_package = parts[-1] == "__init__"
            if is_package:
                parts.pop()
            name = ".".join(parts)
            modules[name] = Module(name, path, is_package)
    return modules


class _ImportVisitor(ast.NodeVisitor):
    def __init__(self, module: Module, known: dict[str, Module]):
        self.module = module
        self.known = known
        self.package = module.name if module.is_package else module.name.rpartition(".")[0]
        self.functions: list[str] = []
        self.edges: list[Edge] = []
        self.problems: list[str] = []

    def _add(self, target: str, node: ast.AST):
        function = ".".join(self.functions) if self.functions else None
        self.edges.append(Edge(self.module.name, target, self.module.path, node.lineno, function))

    def _function(self, node):
        self.functions.append(node.name)
        self.generic_visit(node)
        self.functions.pop()

    visit_FunctionDef = _function
    visit_AsyncFunctionDef = _function

    def _relative_base(self, level: int, node: ast.AST) -> str | None:
        parts = self.package.split(".") if self.package else []
        if level - 1 > len(parts) - 1:
            self.problems.append(f"{self.module.path}:{node.lineno}: relative import beyond the top-level package")
            return None
        return ".".join(parts[: len(parts) - (level - 1)])

    def visit_Import(self, node: ast.Import):
        for alias in node.names:
            self._add(alias.name, node)

    def visit_ImportFrom(self, node: ast.ImportFrom):
        if node.level:
            base = self._relative_base(node.level, node)
            if base is None:
                return
            if node.module:
                base = f"{base}.{node.module}" if base else node.module
        else:
            base = node.module
        for alias in node.names:
            sub = f"{base}.{alias.name}"
            self._add(sub if alias.name != "*" and sub in self.known else base, node)

    def visit_Call(self, node: ast.Call):
        # importlib.import_module("name") / import_module(".name", __name__) with a literal name.
        f = node.func
        called = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
        if called == "import_module" and node.args:
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                name = arg.value
                if name.startswith("."):
                    level = len(name) - len(name.lstrip("."))
                    base = self._relative_base(level, node)
                    if base is not None:
                        rest = name.lstrip(".")
                        self._add(f"{base}.{rest}" if rest else base, node)
                else:
                    self._add(name, node)
        self.generic_visit(node)


def import_edges(modules: dict[str, Module]) -> tuple[list[Edge], list[str]]:
    """Every import of every module, resolved; and the imports that could not be resolved."""
    edges, problems = [], []
    for module in modules.values():
        tree = ast.parse(module.path.read_text(encoding="utf-8"), filename=str(module.path))
        visitor = _ImportVisitor(module, modules)
        visitor.visit(tree)
        edges += visitor.edges
        problems += visitor.problems
    return edges, problems


def _strongly_connected(nodes, graph) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative)."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for start in nodes:
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    out.append(sorted(component))
    return out


def _shortest_cycle(start: str, members: set[str], graph) -> list[str]:
    """A shortest path start -> ... -> start inside ``members``."""
    previous = {}
    frontier = [start]
    while frontier:
        following = []
        for v in frontier:
            for w in sorted(graph.get(v, ())):
                if w not in members:
                    continue
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(previous[path[-1]])
                    return [start, *reversed(path[:-1]), start] if v != start else [start, start]
                if w not in previous:
                    previous[w] = v
                    following.append(w)
        frontier = following
    return [start]


def find_cycles(modules: dict[str, Module], edges: list[Edge], package: str = "nkf_model",
                root: Path = REPO) -> list[str]:
    """One readable message per import cycle among the modules of ``package``."""
    graph: dict[str, set[str]] = {}
    where: dict[tuple[str, str], list[Edge]] = {}
    for e in edges:
        if not (within(e.source, package) and within(e.target, package) and e.target in modules):
            continue
        if modules[e.source].is_package and e.target != e.source and within(e.target, e.source):
            continue  # a package's __init__ importing (re-exporting) its own submodules
        graph.setdefault(e.source, set()).add(e.target)
        where.setdefault((e.source, e.target), []).append(e)
    nodes = sorted(m for m in modules if within(m, package))
    messages = []
    for component in _strongly_connected(nodes, graph):
        members = set(component)
        if len(component) == 1 and component[0] not in graph.get(component[0], ()):
            continue
        cycle = _shortest_cycle(component[0], members, graph)
        lines = [" -> ".join(cycle)]
        if len(members) > len(cycle) - 1:
            lines.append(f"  (one of the cycles among {len(members)} modules: {', '.join(component)})")
        for a, b in zip(cycle, cycle[1:]):
            found = "; ".join(dict.fromkeys(e.where(root) for e in where[(a, b)]))
            lines.append(f"  {a} imports {b} at {found}")
        messages.append("\n".join(lines))
    return messages


def _is_core(name: str) -> bool:
    return (within(name, "nkf_model") and not within(name, "nkf_model.train")
            and name not in ("nkf_model.cli", "nkf_model.__main__"))


# (which importing modules, forbidden targets, why)
RULES = [
    (lambda m: within(m, "nkf_model"), ("benchmarks", "nkf_blender", "bpy"),
     "nkf_model must not depend on benchmarks, the Blender add-on or bpy"),
    (_is_core, ("nkf_model.train", "nkf_model.cli"),
     "the core of nkf_model must not depend on the training or the command line"),
    (lambda m: within(m, "nkf_blender"), ("nkf_model.train", "nkf_model.cli", "benchmarks"),
     "the add-on must not depend on the training, the command line or benchmarks"),
]


def forbidden_imports(edges: list[Edge], root: Path = REPO) -> list[str]:
    """One readable message per import that goes against :data:`RULES`."""
    messages = []
    for e in edges:
        for applies, targets, why in RULES:
            if applies(e.source) and any(within(e.target, t) for t in targets):
                messages.append(f"{e.source} imports {e.target} at {e.where(root)}: {why}")
    return messages


def check(root: Path) -> tuple[list[str], list[str], list[str]]:
    """(cycles, forbidden imports, unresolvable imports) of the tree at ``root``."""
    modules = discover(root)
    edges, problems = import_edges(modules)
    return find_cycles(modules, edges, root=root), forbidden_imports(edges, root=root), problems


# --- the project ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def project():
    modules = discover(REPO)
    edges, problems = import_edges(modules)
    return modules, edges, problems


def test_the_checker_sees_the_project(project):
    modules, edges, problems = project
    assert not problems, "\n".join(problems)
    for name in ("nkf_model", "nkf_model.cli", "nkf_model.pipeline.reconstruct", "nkf_model.train.metrics",
                 "benchmarks.scenes", "nkf_blender.job"):
        assert name in modules
    pairs = {(e.source, e.target) for e in edges}
    assert ("nkf_model.__main__", "nkf_model.cli") in pairs
    # Function-local imports are seen (the add-on loads nkf_model on first use only).
    assert any(e.source.startswith("nkf_blender.") and within(e.target, "nkf_model") and e.function
               for e in edges)


def test_no_import_cycles_in_nkf_model(project):
    modules, edges, _ = project
    cycles = find_cycles(modules, edges)
    assert not cycles, f"{len(cycles)} import cycle(s) among nkf_model modules:\n" + "\n".join(cycles)


def test_imports_go_only_in_the_allowed_directions(project):
    _, edges, _ = project
    bad = forbidden_imports(edges)
    assert not bad, f"{len(bad)} forbidden import(s):\n" + "\n".join(bad)


# --- the checker on synthetic trees --------------------------------------------------------------


def write_tree(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text), encoding="utf-8")
    return root


def test_resolution_of_relative_and_from_imports(tmp_path):
    write_tree(tmp_path, {
        "nkf_model/__init__.py": "from . import errors\nfrom .fit import thing\n",
        "nkf_model/errors.py": "",
        "nkf_model/fit/__init__.py": "thing = 1\nfrom . import solve\n",
        "nkf_model/fit/solve.py": (
            "from .. import errors\n"
            "from ..points import clean, not_a_module\n"
            "from . import augment as aug\n"
            "import numpy.linalg\n"
            "def f():\n"
            "    from nkf_model.fit import solve\n"
            "    import importlib\n"
            "    return importlib.import_module('..points.clean', __package__)\n"
        ),
        "nkf_model/fit/augment.py": "",
        "nkf_model/points/__init__.py": "",
        "nkf_model/points/clean.py": "",
    })
    modules = discover(tmp_path)
    edges, problems = import_edges(modules)
    assert not problems
    got = {(e.source, e.target, e.function) for e in edges}
    assert got == {
        ("nkf_model", "nkf_model.errors", None),
        ("nkf_model", "nkf_model.fit", None),  # thing is no module
        ("nkf_model.fit", "nkf_model.fit.solve", None),  # "from ." in a package's __init__
        ("nkf_model.fit.solve", "nkf_model.errors", None),
        ("nkf_model.fit.solve", "nkf_model.points.clean", None),
        ("nkf_model.fit.solve", "nkf_model.points", None),
        ("nkf_model.fit.solve", "nkf_model.fit.augment", None),
        ("nkf_model.fit.solve", "numpy.linalg", None),
        ("nkf_model.fit.solve", "nkf_model.fit.solve", "f"),
        ("nkf_model.fit.solve", "importlib", "f"),
        ("nkf_model.fit.solve", "nkf_model.points.clean", "f"),
    }


def test_checker_finds_a_cycle_closed_by_a_function_local_import(tmp_path):
    write_tree(tmp_path, {
        "nkf_model/__init__.py": "",
        "nkf_model/fit/__init__.py": "",
        "nkf_model/fit/solve.py": "from ..surface.mesh import triangulate\n",
        "nkf_model/surface/__init__.py": "",
        "nkf_model/surface/mesh.py": "import numpy as np\n\n\ndef triangulate():\n    from ..fit import solve\n",
        "nkf_model/surface/colors.py": "from . import mesh\n",
    })
    cycles, bad, problems = check(tmp_path)
    assert not bad and not problems
    assert len(cycles) == 1, cycles
    message = cycles[0]
    assert message.splitlines()[0] == "nkf_model.fit.solve -> nkf_model.surface.mesh -> nkf_model.fit.solve"
    assert "nkf_model/surface/mesh.py:5, inside triangulate()" in message


def test_package_reexports_are_no_cycle_but_cycles_through_a_package_are(tmp_path):
    files = {
        "nkf_model/__init__.py": "from .errors import Error\nfrom . import fit\n",
        "nkf_model/errors.py": "class Error(Exception):\n    pass\n",
        "nkf_model/fit/__init__.py": "from .solve import fit\n",
        "nkf_model/fit/solve.py": "from nkf_model import Error\nfrom nkf_model.fit import helper\n",
        "nkf_model/fit/helper.py": "",
    }
    cycles, bad, problems = check(write_tree(tmp_path / "ok", files))
    assert not cycles and not bad and not problems
    # A package's __init__ that imports a module outside it which imports the package back is a cycle.
    files["nkf_model/fit/__init__.py"] += "from ..points import clean\n"
    files["nkf_model/points/__init__.py"] = ""
    files["nkf_model/points/clean.py"] = "def f():\n    from nkf_model.fit import fit\n"
    cycles, _, _ = check(write_tree(tmp_path / "bad", files))
    assert [c.splitlines()[0] for c in cycles] == ["nkf_model.fit -> nkf_model.points.clean -> nkf_model.fit"]


def test_checker_finds_forbidden_imports(tmp_path):
    write_tree(tmp_path, {
        "nkf_model/__init__.py": "",
        "nkf_model/__main__.py": "from .cli import main\n",
        "nkf_model/cli.py": "from .train import metrics\n",
        "nkf_model/fit/__init__.py": "",
        "nkf_model/fit/solve.py": "def f():\n    from ..train.metrics import chamfer_l1\n",
        "nkf_model/io/__init__.py": "",
        "nkf_model/io/files.py": "def g():\n    import bpy\n",
        "nkf_model/train/__init__.py": "",
        "nkf_model/train/metrics.py": "from ..io import files\n\n\ndef h():\n    from benchmarks import scenes\n",
        "benchmarks/__init__.py": "",
        "benchmarks/scenes.py": "from nkf_model.train import metrics\nfrom nkf_model import cli\n",
        "nkf_blender/__init__.py": "import bpy\n",
        "nkf_blender/job.py": "import nkf_model\n\n\ndef run():\n    from nkf_model import train\n",
    })
    cycles, bad, problems = check(tmp_path)
    assert not cycles and not problems
    pairs = sorted(m.split(" at ")[0] for m in bad)
    assert pairs == [
        "nkf_blender.job imports nkf_model.train",
        "nkf_model.fit.solve imports nkf_model.train.metrics",
        "nkf_model.io.files imports bpy",
        "nkf_model.train.metrics imports benchmarks.scenes",
    ]
    assert any("nkf_model/fit/solve.py:2, inside f()" in m for m in bad)
