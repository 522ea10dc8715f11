"""The package's layers import downward only, no module imports itself through others, and
the trainer names no rain, NeRF or Gaussian concept (docs/architecture.md)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "rainyscape"

# Lower rank = lower layer. A module may import its own package and packages of a lower rank;
# packages of equal rank are siblings and import neither each other nor anything above.
RANKS = {
    "rainyscape": 0, "errors": 0,  # the package root holds the version only
    "imaging": 1, "cameras": 1, "formats": 1,
    "registry": 2, "scene": 2,
    "config": 3, "components": 3,
    "dataparsers": 4, "fields": 4, "rain": 4, "losses": 4, "postprocess": 4, "methods": 4,
    "engine": 5, "synth": 5, "process": 5,
    "eval": 6,
    "workflow": 7,
    "comparison": 8,
    "cli": 9,
    "testing": 10,  # helpers of tests and benchmarks: nothing in the package imports them
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Every rainyscape module ``path`` imports, at module level or inside functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rainyscape"):
            subs = {f"{node.module}.{a.name}" for a in node.names} & modules  # `from pkg import module`
            found |= subs
            if len(subs) < len(node.names):
                found.add(node.module)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("rainyscape"))
    return found & modules


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    paths = {_module_name(p): p for p in ROOT.rglob("*.py")}
    return {m: _imports(p, set(paths)) - {m} for m, p in paths.items()}


def test_every_package_has_a_layer(graph):
    unknown = sorted({_package(m) for m in graph} - set(RANKS))
    assert not unknown, f"give these packages a layer in RANKS (and docs/architecture.md): {unknown}"


def test_layers_import_downward_only(graph):
    bad = []
    for src, targets in graph.items():
        for dst in targets:
            a, b = _package(src), _package(dst)
            if a != b and RANKS[b] >= RANKS[a] and b != "rainyscape":
                bad.append(f"{src} -> {dst}")
    assert not bad, "imports that go sideways or up:\n" + "\n".join(sorted(bad))


def test_no_import_cycles(graph):
    # a module is in a cycle when it can reach itself
    def reaches(start: str) -> set[str]:
        seen, todo = set(), list(graph[start])
        while todo:
            m = todo.pop()
            if m not in seen:
                seen.add(m)
                todo.extend(graph.get(m, ()))
        return seen

    cyclic = sorted(m for m in graph if m in reaches(m))
    assert not cyclic, f"modules that import themselves through others: {cyclic}"


def test_the_trainer_names_no_rain_nerf_or_gaussian_concept():
    text = (ROOT / "engine" / "trainer.py").read_text().lower().replace("rainyscape", "")
    words = re.findall(r"\b(rain\w*|nerf\w*|gaussian\w*|langevin|warm[- ]?up|joint|streak\w*|clean)\b", text)
    assert not words, f"engine/trainer.py names: {sorted(set(words))}"
