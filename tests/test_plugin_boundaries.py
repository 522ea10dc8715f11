"""Code outside a plugin asks it through the interfaces of rainyscape/components.py: no module
tests for a concrete plugin class (``isinstance`` / ``issubclass`` of a registered
component's class) or looks a loss up by its registered name, except the plugin's own module
(docs/architecture.md, "Components report through their interfaces")."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / "rainyscape"
KINDS = ("dataparsers", "fields", "rain_heads", "losses", "postprocess")


def _registered() -> dict[str, dict[str, str]]:
    """Entry-point group suffix -> {registered name: "module:Class"} from pyproject.toml."""
    groups = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["entry-points"]
    return {kind: groups[f"rainyscape.{kind}"] for kind in KINDS}


def _module(path: Path) -> str:
    return ".".join(path.relative_to(REPO).with_suffix("").parts)


def _names(node: ast.AST) -> list[str]:
    """Class names a class argument of isinstance / issubclass spells (a name, a dotted
    name's last part, or a tuple of them)."""
    if isinstance(node, ast.Tuple):
        return [n for e in node.elts for n in _names(e)]
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, ast.Attribute):
        return [node.attr]
    return []


def _loss_lookups(tree: ast.AST, losses: set[str]) -> list[tuple[int, str]]:
    """Where a loss's registered name is compared against, used as a subscript, or handed to
    the registry: looking a loss up by name."""
    found = []
    for node in ast.walk(tree):
        consts: list[ast.AST] = []
        if isinstance(node, ast.Compare):
            consts = [node.left, *node.comparators]
            consts += [e for c in node.comparators if isinstance(c, (ast.Tuple, ast.List, ast.Set)) for e in c.elts]
        elif isinstance(node, ast.Subscript):
            consts = [node.slice]
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr in ("load", "get"):
            consts = list(node.args)
        found += [(node.lineno, c.value) for c in consts
                  if isinstance(c, ast.Constant) and isinstance(c.value, str) and c.value in losses]
    return found


def _violations() -> tuple[list[str], list[str]]:
    plugins = {target.split(":")[1]: target.split(":")[0]
               for group in _registered().values() for target in group.values()}
    losses = set(_registered()["losses"])
    concrete, by_name = [], []
    for path in sorted(ROOT.rglob("*.py")):
        module = _module(path)
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id in ("isinstance", "issubclass") and len(node.args) == 2):
                for name in _names(node.args[1]):
                    if name in plugins and plugins[name] != module:
                        concrete.append(f"{module}:{node.lineno}: {node.func.id}(..., {name})")
        # a method's recipe names its losses (that is what a recipe is); the config layer
        # reads recipes; a loss's own module may name itself
        if module.startswith(("rainyscape.methods", "rainyscape.config", "rainyscape.losses")):
            continue
        by_name += [f"{module}:{line}: '{name}'" for line, name in _loss_lookups(tree, losses)]
    return concrete, by_name


def test_the_checks_see_what_they_forbid():
    code = ast.parse("if isinstance(p, RainMaskFusion) or cfg.name == 'agr': x = terms['agr']")
    assert _names(code.body[0].test.values[0].args[1]) == ["RainMaskFusion"]
    assert [name for _, name in _loss_lookups(code, {"agr"})] == ["agr", "agr"]
    assert "RainMaskFusion" in {t.split(":")[1] for g in _registered().values() for t in g.values()}


def test_no_isinstance_of_a_concrete_plugin_outside_its_module():
    concrete, _ = _violations()
    assert not concrete, ("ask the component through an interface of components.py (a Protocol it "
                          "implements), not its class:\n" + "\n".join(concrete))


def test_no_loss_looked_up_by_name_outside_its_module():
    _, by_name = _violations()
    assert not by_name, ("a loss reports what others need through an interface of components.py "
                         "(e.g. MeasuresRainAngles), not by its name:\n" + "\n".join(by_name))
