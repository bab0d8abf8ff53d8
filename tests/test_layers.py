"""The layers of the code and its import graph, checked from the source (``ast``: nothing is imported).

Layers, inner to outer:

- core: every module of ``dcrad`` except ``dcrad.cli``, ``dcrad.wire`` and the generated ``dcrad.v1``;
- wire: ``dcrad.wire`` and ``dcrad.v1`` (may import core);
- service: the ``coordinator`` and ``worker`` packages (may import wire and core);
- app: ``dcrad.cli`` (may import anything).

Rules: core imports neither wire, service, app nor ``grpc`` / ``google.protobuf``; wire imports
neither service nor app; service does not import app (an import through a module of no layer,
``scenes``, counts as the importer's own); and the modules of ``dcrad`` import one another
without a cycle.  Every import statement counts, at any depth: a function's lazy import runs
too.  An import under ``if TYPE_CHECKING:`` never runs: it is left out of the cycle rule (an
annotation may name an outer module's type), not out of the layers.

The checker's functions are tested on a small synthetic project below, so that each rule is
seen to fail when it should.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: the packages scanned: the installed ones (pyproject.toml's packages.find)
PACKAGES = ("dcrad", "coordinator", "worker", "scenes")

#: what each layer may import of the project's layers
MAY_IMPORT = {
    "core": {"core"},
    "wire": {"core", "wire"},
    "service": {"core", "wire", "service"},
    "app": {"core", "wire", "service", "app"},
}

#: third-party modules a layer may not import: a prefix of the dotted name ("grpc" covers
#: grpc.aio and the grpc_* packages: grpc_health, grpc_tools, ...)
FORBIDDEN_EXTERNAL = {"core": ("grpc", "google.protobuf")}


@dataclass(frozen=True)
class Import:
    """One imported name: ``target`` is absolute and dotted, ``from P import x`` giving ``P.x``."""

    source: str  #: the importing module
    target: str  #: what it imports
    file: str  #: the importing file, from the root
    line: int
    type_checking: bool  #: under ``if TYPE_CHECKING:``

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.source} imports {self.target}"


def module_name(path: Path, root: Path) -> tuple[str, bool]:
    """(dotted module name, is a package) of a .py file under ``root``."""
    parts = path.relative_to(root).with_suffix("").parts
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def _is_type_checking(test: ast.expr) -> bool:
    return ((isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
            or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"))


def imports_in(source: str, module: str, is_package: bool, file: str) -> list[Import]:
    """Every import in one file's source, at any depth (module level, functions, classes, try, if),
    with relative imports resolved; ``importlib.import_module("name")`` with a literal counts too."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    found: list[Import] = []

    def base_of(node: ast.ImportFrom) -> str:
        if not node.level:
            return node.module or ""
        if node.level - 1 > len(package) - 1:
            raise ValueError(f"{file}:{node.lineno}: relative import beyond the top-level package")
        parts = package[: len(package) - (node.level - 1)]
        return ".".join(parts + ([node.module] if node.module else []))

    def walk(node: ast.AST, tc: bool) -> None:
        if isinstance(node, ast.Import):
            found.extend(Import(module, a.name, file, node.lineno, tc) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = base_of(node)
            found.extend(Import(module, base if a.name == "*" else f"{base}.{a.name}", file, node.lineno, tc)
                         for a in node.names)
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                walk(child, True)
            for child in node.orelse:
                walk(child, tc)
            return
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str) and not node.args[0].value.startswith(".")
              and ((isinstance(node.func, ast.Attribute) and node.func.attr == "import_module")
                   or (isinstance(node.func, ast.Name) and node.func.id == "import_module"))):
            found.append(Import(module, node.args[0].value, file, node.lineno, tc))
        for child in ast.iter_child_nodes(node):
            walk(child, tc)

    walk(ast.parse(source, filename=file), False)
    return found


def scan(root: Path = ROOT, packages: tuple[str, ...] = PACKAGES) -> tuple[set[str], list[Import]]:
    """(the project's module names, every import of every .py file of ``packages`` under ``root``)."""
    modules: set[str] = set()
    imports: list[Import] = []
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            name, is_package = module_name(path, root)
            modules.add(name)
            imports += imports_in(path.read_text(), name, is_package, path.relative_to(root).as_posix())
    return modules, imports


def module_of(target: str, modules: set[str]) -> str | None:
    """The project module an imported name is in (its longest dotted prefix that is one), or None."""
    parts = target.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if name in modules:
            return name
    return None


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def layer_of(name: str) -> str | None:
    """The layer of a module (or of a name in it); None: not in a layer (scenes, third-party)."""
    if _under(name, "dcrad.cli"):
        return "app"
    if _under(name, "dcrad.wire") or _under(name, "dcrad.v1"):
        return "wire"
    if _under(name, "dcrad"):
        return "core"
    if _under(name, "coordinator") or _under(name, "worker"):
        return "service"
    return None


def _forbidden(layer: str, target: str) -> str | None:
    """Why ``layer`` may not import ``target``, or None."""
    to = layer_of(target)
    if to is not None and to not in MAY_IMPORT[layer]:
        return f"{layer} may not import {to}"
    for prefix in FORBIDDEN_EXTERNAL.get(layer, ()):
        if _under(target, prefix) or (prefix == "grpc" and target.startswith("grpc_")):
            return f"{layer} may not import {prefix}"
    return None


def layer_violations(modules: set[str], imports: list[Import]) -> list[str]:
    """Each import that breaks a layer rule, as ``file:line`` lines; an import of a project module
    in no layer (``scenes``) is followed into that module's own imports."""
    by_source: dict[str, list[Import]] = defaultdict(list)
    for imp in imports:
        by_source[imp.source].append(imp)
    problems = []
    for imp in imports:
        layer = layer_of(imp.source)
        if layer is None:
            continue
        seen: set[str] = set()
        stack: list[tuple[Import, tuple[Import, ...]]] = [(imp, ())]
        while stack:
            step, via = stack.pop()
            why = _forbidden(layer, step.target)
            if why:
                problems.append(" -> ".join(map(str, (*via, step))) + f" ({why})")
                continue
            inner = module_of(step.target, modules)
            if inner is not None and layer_of(inner) is None and inner not in seen:
                seen.add(inner)
                stack += [(nxt, (*via, step)) for nxt in by_source[inner]]
    return sorted(set(problems))


def import_cycles(modules: set[str], imports: list[Import], within: str = "dcrad") -> list[list[Import]]:
    """The import cycles through modules of ``within``: in each strongly connected group of modules
    that holds one, the shortest cycle through each of its modules (each edge its first import
    statement); imports under TYPE_CHECKING left out."""
    edges: dict[str, dict[str, Import]] = defaultdict(dict)
    for imp in imports:
        to = module_of(imp.target, modules)
        if not imp.type_checking and to is not None and to != imp.source:
            edges[imp.source].setdefault(to, imp)

    # Tarjan's strongly connected components
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            groups.append(group)

    for v in sorted(modules):
        if v not in index:
            visit(v)

    cycles: list[list[Import]] = []
    seen: set[frozenset[Import]] = set()
    for group in groups:
        members = set(group)
        if len(group) < 2 or not any(_under(m, within) for m in group):
            continue
        for start in sorted(group):  # the shortest way round through each module of the group
            prev: dict[str, Import] = {}
            frontier = [start]
            while frontier and start not in prev:
                nxt = []
                for u in frontier:
                    for w, imp in sorted(edges[u].items()):
                        if w in members and w not in prev:
                            prev[w] = imp
                            nxt.append(w)
                frontier = nxt
            path, node = [], start
            while True:
                imp = prev[node]
                path.append(imp)
                node = imp.source
                if node == start:
                    break
            if frozenset(path) not in seen:
                seen.add(frozenset(path))
                cycles.append(path[::-1])
    return cycles


# -- the project ----------------------------------------------------------------------------

def test_the_scan_sees_the_project():
    modules, imports = scan()
    assert len(modules) > 50 and {"dcrad", "dcrad.solving.solver", "dcrad.cli", "dcrad.v1.dcrad_pb2",
                                  "coordinator.jobs", "worker.server", "scenes.cornell"} <= modules
    got = {(i.source, module_of(i.target, modules), i.type_checking) for i in imports}
    assert ("dcrad.pipeline", "dcrad.solving.solver", False) in got  # a module-level import
    assert ("dcrad.cli", "dcrad.pipeline", False) in got  # a function's (the command's lazy imports)
    assert ("dcrad.outputs.report", "dcrad.solving.stiffness", True) in got  # under TYPE_CHECKING
    assert ("dcrad", "dcrad.api", False) in got  # the package's lazy attributes (PEP 562)
    assert ("worker.server", "dcrad.v1.dcrad_pb2", False) in got
    assert {layer_of(m) for m in ("dcrad", "dcrad.solving.solver", "dcrad.wire", "dcrad.v1.dcrad_pb2_grpc", "dcrad.cli",
                                  "coordinator.jobs", "worker.server", "scenes.cornell", "numpy")} == {
        "core", "wire", "app", "service", None}


def test_each_layer_imports_only_inner_layers():
    problems = layer_violations(*scan())
    assert not problems, "imports that break the layers (core < wire < service < app):\n  " + "\n  ".join(problems)


def test_the_package_has_no_import_cycles():
    cycles = import_cycles(*scan())
    assert not cycles, "import cycles among dcrad's modules (TYPE_CHECKING imports aside):\n" + "\n".join(
        "  " + "\n    -> ".join(map(str, cycle)) for cycle in cycles)


# -- the checker, on synthetic projects ---------------------------------------------------------

#: every layer rule broken once, and imports of each form (relative, lazy, TYPE_CHECKING, importlib)
LAYERED = {
    "dcrad/__init__.py": "def __getattr__(name):\n    from . import a\n    return a\n",
    "dcrad/a.py": "import numpy as np\n",
    "dcrad/b.py": "def f():\n    from .a import x\n    return x\n",
    "dcrad/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .a import T\n    import grpc\n",
    "dcrad/grpc_user.py": "try:\n    import grpc.aio\nexcept ImportError:\n    pass\n",
    "dcrad/health.py": "import grpc_health.v1\n",
    "dcrad/proto.py": "from google import protobuf\n",
    "dcrad/to_wire.py": "import importlib\nwire = importlib.import_module('dcrad.wire')\n",
    "dcrad/sub/__init__.py": "",
    "dcrad/sub/deep.py": "from ..cli import main\nfrom .. import a\n",
    "dcrad/gen.py": "import scenes\n",  # core -> scenes -> the service: through a module of no layer
    "dcrad/wire.py": "from dcrad import a\nfrom coordinator.jobs import J\n",
    "dcrad/v1/__init__.py": "",
    "dcrad/v1/pb2.py": "import grpc\nfrom dcrad.wire import w\nfrom ..cli import main\n",
    "dcrad/cli.py": "from coordinator import jobs\nfrom dcrad import wire\nimport grpc\n",
    "coordinator/__init__.py": "",
    "coordinator/jobs.py": "import grpc\nfrom dcrad.v1 import pb2\nfrom dcrad import a\n\n\ndef run():\n"
                           "    from dcrad.cli import main\n",
    "scenes/__init__.py": "from .gen import g\n",
    "scenes/gen.py": "from coordinator import jobs\n",
}

#: cycles: through a lazy import, and through a module outside dcrad; none through TYPE_CHECKING,
#: and one that holds no dcrad module
CYCLIC = {
    "dcrad/__init__.py": "",
    "dcrad/a.py": "from . import b\n",
    "dcrad/b.py": "def f():\n    from .a import x\n    return x\n",
    "dcrad/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .f import T\n",
    "dcrad/f.py": "from .e import U\n",
    "dcrad/g.py": "import scenes.h\n",
    "scenes/__init__.py": "",
    "scenes/h.py": "from dcrad import g\n",
    "coordinator/__init__.py": "",
    "coordinator/x.py": "from . import y\n",
    "coordinator/y.py": "from . import x\n",
}


def _write(tmp_path: Path, files: dict[str, str]) -> tuple[set[str], list[Import]]:
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    return scan(tmp_path)


def test_the_checker_resolves_relative_and_lazy_imports(tmp_path):
    modules, imports = _write(tmp_path, LAYERED)
    got = {(i.source, i.target, i.line, i.type_checking) for i in imports}
    assert ("dcrad", "dcrad.a", 2, False) in got  # in a function of a package's __init__
    assert ("dcrad.b", "dcrad.a.x", 2, False) in got and module_of("dcrad.a.x", modules) == "dcrad.a"
    assert ("dcrad.sub.deep", "dcrad.cli.main", 1, False) in got and ("dcrad.sub.deep", "dcrad.a", 2, False) in got
    assert ("dcrad.v1.pb2", "dcrad.cli.main", 3, False) in got
    assert ("dcrad.e", "dcrad.a.T", 3, True) in got and ("dcrad.e", "grpc", 4, True) in got
    assert ("dcrad.to_wire", "dcrad.wire", 2, False) in got


def test_the_checker_finds_each_layer_violation(tmp_path):
    problems = layer_violations(*_write(tmp_path, LAYERED))
    where = sorted(p.split(": ", 1)[0] for p in problems)
    assert where == sorted([
        "dcrad/e.py:4",  # core -> grpc (under TYPE_CHECKING still counts for the layers)
        "dcrad/grpc_user.py:2",  # core -> grpc.aio (inside a try)
        "dcrad/health.py:1",  # core -> grpc_health
        "dcrad/proto.py:1",  # core -> google.protobuf
        "dcrad/to_wire.py:2",  # core -> wire (importlib)
        "dcrad/sub/deep.py:1",  # core -> app (relative, from a subpackage)
        "dcrad/gen.py:1",  # core -> scenes -> scenes.gen -> service
        "dcrad/wire.py:2",  # wire -> service
        "dcrad/v1/pb2.py:3",  # wire -> app
        "coordinator/jobs.py:7",  # service -> app (a function's import)
    ]), "\n".join(problems)
    chain = next(p for p in problems if p.startswith("dcrad/gen.py"))
    assert "scenes/__init__.py:1" in chain and "scenes/gen.py:1: scenes.gen imports coordinator.jobs" in chain
    assert "(core may not import service)" in chain


def test_the_checker_finds_a_cycle_through_a_lazy_import_and_not_through_type_checking(tmp_path):
    cycles = sorted([str(i) for i in c] for c in import_cycles(*_write(tmp_path, CYCLIC)))
    assert cycles == [
        ["dcrad/a.py:1: dcrad.a imports dcrad.b", "dcrad/b.py:2: dcrad.b imports dcrad.a.x"],
        ["dcrad/g.py:1: dcrad.g imports scenes.h", "scenes/h.py:1: scenes.h imports dcrad.g"],
    ]  # not e <-> f (TYPE_CHECKING), nor coordinator.x <-> coordinator.y (no dcrad module in it)
    assert len(import_cycles(*scan(tmp_path), within="coordinator")) == 1
    # e -> f at run time: a third cycle
    (tmp_path / "dcrad/e.py").write_text("from .f import T\n")
    assert len(import_cycles(*scan(tmp_path))) == 3
