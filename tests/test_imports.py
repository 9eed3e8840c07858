"""Import structure of the repository: no cycles, one dependency direction, no private cross-package names.

The graph is built from the source alone (``ast``; nothing is imported), counting every import
statement wherever it stands: module level, inside functions and under ``if TYPE_CHECKING``.
An edge goes to the most specific module an import names (``from blsm import render`` is an edge
to ``blsm.render``); importing ``a.b.c`` does not add edges to the packages ``a`` and ``a.b``,
although Python runs their ``__init__`` first, because every module would then close a loop
through its own package.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ("blsm", "synth", "recovery")
"""Top-level packages, lowest first: a package may import only itself and those before it."""
SCRIPT_FOLDERS = ("experiments", "benchmarks", "scripts")
"""Folders of scripts beside the packages: they import the packages, never the other way."""


@dataclass
class ImportGraph:
    """Modules of some top-level packages and the imports among them.

    Attributes:
        edges: importer -> imported modules (both in ``modules``).
        private: ``(importer, "name", line)`` for every underscore name taken from another
            top-level package, by ``from ... import _x``, ``import a._m`` or ``mod._x``.
        external: importer -> every dotted name it imports, whether or not it is in ``modules``.
    """

    modules: dict[str, Path]
    edges: dict[str, set[str]] = field(default_factory=dict)
    private: list[tuple[str, str, int]] = field(default_factory=list)
    external: dict[str, set[str]] = field(default_factory=dict)


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_private(name: str) -> bool:
    return any(p.startswith("_") and not (p.startswith("__") and p.endswith("__")) for p in name.split("."))


def build_graph(root: Path, packages: tuple[str, ...] = LAYERS) -> ImportGraph:
    """Parses every ``.py`` file of ``packages`` under ``root`` and links their imports.

    Args:
        root: Repository root (the folder that holds the packages).
        packages: Top-level package names; missing ones are skipped.

    Returns:
        The :class:`ImportGraph`.
    """
    files = [p for pkg in packages if (root / pkg).is_dir() for p in sorted((root / pkg).rglob("*.py"))]
    graph = ImportGraph(modules={_module_name(p, root): p for p in files})
    for name, path in graph.modules.items():
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        imported: set[str] = set()
        aliases: dict[str, str] = {}  # local name -> module it is bound to

        def foreign(target: str, importer: str = name) -> bool:
            return target.split(".")[0] in packages and target.split(".")[0] != importer.split(".")[0]

        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    imported.add(a.name)
                    aliases[a.asname or a.name.split(".")[0]] = a.name if a.asname else a.name.split(".")[0]
                    if foreign(a.name) and _is_private(a.name):
                        graph.private.append((name, a.name, node.lineno))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                for a in node.names:
                    full = f"{src}.{a.name}"
                    if full in graph.modules:
                        imported.add(full)
                        aliases[a.asname or a.name] = full
                    else:
                        imported.add(src)
                    if foreign(src) and _is_private(full):
                        graph.private.append((name, full, node.lineno))
        # ``render._x`` after ``from blsm import render`` (or ``blsm.render._x`` after ``import blsm``).
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute):
                chain, cur = [node.attr], node.value
                while isinstance(cur, ast.Attribute):
                    chain.append(cur.attr)
                    cur = cur.value
                if isinstance(cur, ast.Name) and cur.id in aliases:
                    dotted = ".".join([aliases[cur.id], *reversed(chain)])
                    if foreign(dotted) and _is_private(dotted):
                        graph.private.append((name, dotted, node.lineno))
        graph.external[name] = imported
        graph.edges[name] = {m for m in imported if m in graph.modules and m != name}
    return graph


def find_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
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
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def layer_violations(graph: ImportGraph, layers: tuple[str, ...] = LAYERS) -> list[str]:
    """``"importer -> imported"`` for every import of a higher layer by a lower one."""
    rank = {pkg: i for i, pkg in enumerate(layers)}
    bad = []
    for importer, targets in sorted(graph.external.items()):
        for target in sorted(targets):
            top = target.split(".")[0]
            if top in rank and rank[top] > rank[importer.split(".")[0]]:
                bad.append(f"{importer} -> {target}")
    return bad


def script_imports(graph: ImportGraph, folders: tuple[str, ...] = SCRIPT_FOLDERS) -> list[str]:
    """``"importer -> imported"`` for every import of a script folder's module by a package."""
    return [f"{importer} -> {target}" for importer, targets in sorted(graph.external.items())
            for target in sorted(targets) if target.split(".")[0] in folders]


@pytest.fixture(scope="module")
def graph() -> ImportGraph:
    return build_graph(ROOT)


def test_graph_sees_the_packages(graph: ImportGraph) -> None:
    assert "blsm.render" in graph.modules and "synth.render" in graph.modules
    assert "blsm.camera" in graph.edges["synth.camera"]
    assert "blsm.learn.evaluation.fit" in graph.edges["blsm.learn.evaluation.evaluate"]


def test_no_import_cycles(graph: ImportGraph) -> None:
    cycles = find_cycles(graph.edges)
    assert not cycles, f"import cycles (each a set of modules that import each other): {cycles}"


def test_dependency_direction(graph: ImportGraph) -> None:
    bad = layer_violations(graph)
    assert not bad, f"imports against the direction {' <- '.join(LAYERS)}: {bad}"


def test_no_private_names_across_packages(graph: ImportGraph) -> None:
    assert not graph.private, f"private names used across packages (module, name, line): {graph.private}"


def test_packages_do_not_import_scripts(graph: ImportGraph) -> None:
    bad = script_imports(graph)
    assert not bad, f"package modules importing {', '.join(SCRIPT_FOLDERS)} (experiments and tools stay outside): {bad}"


def test_checks_catch_violations(tmp_path: Path) -> None:
    files = {
        "blsm/__init__.py": "",
        "blsm/a.py": "def f():\n    from blsm import b\n",  # a -> b -> a, the import inside a function
        "blsm/b.py": "from blsm.a import f\n",
        "blsm/c.py": "import synth.x\n",  # blsm must not import synth
        "synth/__init__.py": "",
        "synth/x.py": "from blsm.a import _hidden\nfrom . import y\n",
        "synth/y.py": "from blsm import a\nimport blsm\nv = a._private + blsm.a._other\n"
        "from recovery import w\n",
        "recovery/__init__.py": "",
        "recovery/w.py": "",
        "recovery/z.py": "from synth.x import ok\nfrom ..synth import y\n",
        "recovery/v.py": "def f():\n    from experiments.transfer import rows\n    import benchmarks.report\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    g = build_graph(tmp_path)
    assert find_cycles(g.edges) == [["blsm.a", "blsm.b"]]
    assert g.edges["synth.x"] == {"blsm.a", "synth.y"}
    assert g.edges["recovery.z"] == {"synth.x", "synth.y"}
    assert layer_violations(g) == ["blsm.c -> synth.x", "synth.y -> recovery.w"]
    assert script_imports(g) == ["recovery.v -> benchmarks.report", "recovery.v -> experiments.transfer"]
    assert sorted((m, n) for m, n, _ in g.private) == [
        ("synth.x", "blsm.a._hidden"),
        ("synth.y", "blsm.a._other"),
        ("synth.y", "blsm.a._private"),
    ]
