"""The two contracts of issue 54, read from the source (``ast``; nothing is imported): the dataset
package (``synth.dataset``) imports no module of the generator, and ``recovery`` reads datasets
through it alone; ``recovery predict`` imports no training module.

An import closure counts every import statement wherever it stands (module level, inside functions,
under ``if TYPE_CHECKING``), as :func:`test_imports.build_graph` builds the graph, so a lazy import
of a training module inside a function of the predictor counts as much as a top-level one.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_imports import ROOT, ImportGraph, build_graph

DATASET = "synth.dataset"
TRAINING = ("recovery.tasks", "recovery.trainer", "recovery.train", "recovery.datasets", "recovery.distributed",
            "recovery.models.losses", "recovery.models.discriminator")
"""Modules (and packages: everything under them) that exist for training only."""


def closure(graph: ImportGraph, roots: list[str]) -> set[str]:
    """Every module of the graph that ``roots`` import, directly or not (the roots included)."""
    seen: set[str] = set()
    todo = list(roots)
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.edges.get(m, ()))
    return seen


def under(module: str, prefixes: tuple[str, ...] | str) -> bool:
    prefixes = (prefixes,) if isinstance(prefixes, str) else prefixes
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def generator_modules(graph: ImportGraph, roots: list[str]) -> list[str]:
    """The ``synth`` modules outside :data:`DATASET` in the closure of ``roots``."""
    return sorted(m for m in closure(graph, roots) if under(m, "synth") and not under(m, DATASET) and m != "synth")


def training_modules(graph: ImportGraph, roots: list[str]) -> list[str]:
    return sorted(m for m in closure(graph, roots) if under(m, TRAINING))


def synth_imports_of_recovery(graph: ImportGraph) -> list[str]:
    """``"importer -> imported"`` for every import of a ``synth`` module outside the dataset package
    by a ``recovery`` module."""
    return [f"{a} -> {b}" for a, targets in sorted(graph.external.items()) if under(a, "recovery")
            for b in sorted(targets) if under(b, "synth") and not under(b, DATASET)]


@pytest.fixture(scope="module")
def graph() -> ImportGraph:
    return build_graph(ROOT)


def test_the_dataset_package_imports_no_generator_module(graph: ImportGraph) -> None:
    mods = [m for m in graph.modules if under(m, DATASET)]
    assert {"synth.dataset.images", "synth.dataset.sequences", "synth.dataset.shards"} <= set(mods)
    bad = generator_modules(graph, mods)
    assert not bad, f"the dataset package {DATASET} reaches generator modules: {bad}"


def test_recovery_reads_datasets_through_the_dataset_package_only(graph: ImportGraph) -> None:
    bad = synth_imports_of_recovery(graph)
    assert not bad, f"recovery imports synth outside {DATASET}: {bad}"


def test_recovery_predict_imports_no_training_module(graph: ImportGraph) -> None:
    bad = training_modules(graph, ["recovery.predict"])
    assert not bad, f"recovery predict's import closure holds training modules: {bad}"
    assert "recovery.models.hmr" in closure(graph, ["recovery.predict"])  # the closure is followed at all


def test_the_checks_catch_violations(tmp_path: Path) -> None:
    files = {
        "blsm/__init__.py": "",
        "synth/__init__.py": "",
        "synth/render.py": "",
        "synth/dataset/__init__.py": "",
        "synth/dataset/format.py": "",
        "synth/dataset/images.py": "from synth.dataset import format\n"
        "def f():\n    from synth.dataset.sequences import g\n",
        "synth/dataset/sequences.py": "from synth import render\n",  # the generator, two steps away
        "recovery/__init__.py": "",
        "recovery/predict.py": "from recovery import predictor\n",
        "recovery/predictor.py": "def load():\n    from recovery.tasks import hmr\n",  # a lazy import counts
        "recovery/tasks/__init__.py": "",
        "recovery/tasks/hmr.py": "from synth.render import x\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    g = build_graph(tmp_path)
    assert generator_modules(g, ["synth.dataset.images"]) == ["synth.render"]
    assert training_modules(g, ["recovery.predict"]) == ["recovery.tasks.hmr"]
    assert synth_imports_of_recovery(g) == ["recovery.tasks.hmr -> synth.render"]
