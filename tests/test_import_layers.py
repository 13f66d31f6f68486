"""The package's layers: no module imports from a layer above its own, lazy imports inside functions included.

From the bottom: the simulator, the renderer and the shipped config files; the tasks; the environments; the
baselines; the viewer application; the measurements; the command line. Modules of one layer may import each
other. The package's ``__init__`` (which registers the env ids) and ``__main__`` are entry points, not a layer.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "suture_gym"
#: Sub-package -> layer, bottom first.
LAYERS = {"sim": 0, "render": 0, "configs": 0, "tasks": 1, "envs": 2, "baselines": 3, "viewer": 4, "measure": 5,
          "cli": 6}


def imported_modules(tree: ast.AST, module: str, is_package: bool = False) -> list[tuple[int, str]]:
    """``(line, absolute module name)`` of every import in ``tree`` (the source of ``module``, a package's
    ``__init__`` when ``is_package``), at any depth."""
    package = module.split(".") if is_package else module.split(".")[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            found.append((node.lineno, name))
            found += [(node.lineno, f"{name}.{alias.name}") for alias in node.names if name == "suture_gym"]
    return found


def layer_of(module: str) -> str | None:
    """The sub-package (a key of :data:`LAYERS`) of the dotted ``module`` name, None outside the layers."""
    parts = module.split(".")
    if parts[0] != "suture_gym" or len(parts) < 2:
        return None
    return parts[1] if parts[1] in LAYERS else None


def upward_imports() -> list[str]:
    violations = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        is_package = module.endswith(".__init__")
        if is_package:
            module = module[: -len(".__init__")]
        own = layer_of(module)
        if own is None:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for line, name in imported_modules(tree, module, is_package):
            target = layer_of(name)
            if target is not None and LAYERS[target] > LAYERS[own]:
                violations.append(f"{path.relative_to(PACKAGE.parent)}:{line} ({own}) imports {name} ({target})")
    return violations


def test_every_sub_package_has_a_layer():
    packages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert packages == set(LAYERS), f"give these a layer: {sorted(packages - set(LAYERS))}"


def test_no_module_imports_from_a_higher_layer():
    violations = upward_imports()
    assert not violations, "\n".join(violations)


@pytest.mark.parametrize(("source", "expected"), [
    ("from suture_gym.envs import SutureEnv", ["suture_gym.envs"]),
    ("def f():\n    import suture_gym.viewer.app as app", ["suture_gym.viewer.app"]),
    ("from .. import envs", ["suture_gym", "suture_gym.envs"]),
    ("from ..envs.base import SutureEnv", ["suture_gym.envs.base"]),
    ("from .geometry import PlannedArc", ["suture_gym.tasks.geometry"]),
])
def test_the_import_reader_sees_lazy_and_relative_imports(source, expected):
    names = [name for _, name in imported_modules(ast.parse(source), "suture_gym.tasks.surgeon")]
    assert names == expected
    package = [name for _, name in imported_modules(ast.parse("from .base import Task"), "suture_gym.tasks", True)]
    assert package == ["suture_gym.tasks.base"]
