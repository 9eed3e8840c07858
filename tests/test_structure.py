"""The code's shape (issue 33): function and module sizes, private names, the one-way layering."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("blsm", "synth", "recovery")
LAYER = {name: i for i, name in enumerate(PACKAGES)}  # blsm <- synth <- recovery
MAX_FUNCTION_LINES = 120
MAX_MODULE_LINES = 700


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py"))


def _name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(module, imported names, line) of every import in a file, relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = _name(path) if path.name == "__init__.py" else _name(path).rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            out.append((base, [a.name for a in node.names], node.lineno))
    return out


def test_there_is_code_to_check():
    assert len(_modules()) > 50


@pytest.mark.parametrize("package", PACKAGES)
def test_functions_and_modules_are_small(package):
    long_functions, long_modules = [], []
    for path in (ROOT / package).rglob("*.py"):
        text = path.read_text()
        if text.count("\n") > MAX_MODULE_LINES:
            long_modules.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long_functions.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {n} lines")
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
    assert not long_functions, f"functions over {MAX_FUNCTION_LINES} lines: {long_functions}"


@pytest.mark.parametrize("package", PACKAGES)
def test_no_private_name_is_imported_from_another_module(package):
    found = []
    for path in (ROOT / package).rglob("*.py"):
        me = _name(path)
        for module, names, line in _imports(path):
            if module.split(".")[0] not in PACKAGES or module == me:
                continue
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            private += [p for p in module.split(".") if p.startswith("_") and not p.startswith("__")]
            if private:
                found.append(f"{path.relative_to(ROOT)}:{line} from {module} import {private}")
        found += _private_attributes(path)
    assert not found, found


def _private_attributes(path: Path) -> list[str]:
    """``module._name`` where ``module`` is one of our modules imported by name."""
    tree = ast.parse(path.read_text())
    modules = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            ours = [a for a in node.names if a.name.split(".")[0] in PACKAGES]
            modules |= {a.asname or a.name.split(".")[0] for a in ours}
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in PACKAGES:
            modules |= {a.asname or a.name for a in node.names}
    return [
        f"{path.relative_to(ROOT)}:{node.lineno} {node.value.id}.{node.attr}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules
        and node.attr.startswith("_") and not node.attr.startswith("__")
    ]


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_go_one_way(package):
    """blsm imports neither synth nor recovery; synth does not import recovery."""
    found = []
    for path in (ROOT / package).rglob("*.py"):
        for module, _, line in _imports(path):
            top = module.split(".")[0]
            if top in LAYER and LAYER[top] > LAYER[package]:
                found.append(f"{path.relative_to(ROOT)}:{line} imports {module}")
    assert not found, found
