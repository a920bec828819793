"""Imports point one way: parsed from the source (ast), so a new import against the arrows fails
here.  Rules (issue "one home for the signal vocabulary"): the web service does not depend on the
CLI (``api/`` -> ``bench.commands``), the simulators do not depend on fitting (``bench/sim/`` ->
``bench.fit``), fitting does not depend on the drivers (``bench/fit/`` -> ``bench.devices``), and
the step executors do not depend on the engine module (``bench/engine/executors.py`` ->
``bench.engine.engine``)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

RULES = [   # (files, forbidden module prefix)
    ("api", "bench.commands"),
    ("bench/sim", "bench.fit"),
    ("bench/fit", "bench.devices"),
    ("bench/engine/executors.py", "bench.engine.engine"),
]


def imported_modules(path: Path, root: Path) -> list[tuple[int, str]]:
    """Every module a file imports (absolute, or relative resolved against its package), with the
    line; ``from a import b`` counts as ``a`` and ``a.b`` (``b`` may be a submodule)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def files_of(target: str, root: Path = ROOT) -> list[Path]:
    path = root / target
    return [path] if path.is_file() else sorted(path.rglob("*.py"))


def offending(target: str, forbidden: str, root: Path = ROOT) -> list[str]:
    return [f"{path.relative_to(root)}:{line} imports {module}"
            for path in files_of(target, root) for line, module in imported_modules(path, root)
            if module == forbidden or module.startswith(forbidden + ".")]


@pytest.mark.parametrize("target, forbidden", RULES)
def test_no_import_against_the_arrows(target, forbidden):
    assert files_of(target), f"{target} has no Python files (rule out of date?)"
    assert offending(target, forbidden) == []


def test_the_check_sees_every_import_form(tmp_path):
    pkg = tmp_path / "bench" / "engine"
    pkg.mkdir(parents=True)
    (pkg / "executors.py").write_text(
        "import bench.engine.engine\n"
        "from bench.engine import engine\n"
        "from .engine import Engine\n"
        "from . import engine as e\n"
        "def late():\n    from bench.engine.engine import Engine\n"
        "from bench.engine.context import StepContext\n"
        "from bench.engine.engineering import x\n")
    hits = offending("bench/engine/executors.py", "bench.engine.engine", tmp_path)
    assert sorted({int(hit.split(":")[1].split()[0]) for hit in hits}) == [1, 2, 3, 4, 6]
