"""The module map of docs/architecture.md holds: every module of the package
is on a floor, imports only from its floor or below, and no import circle
exists (imports inside functions and under TYPE_CHECKING count too)."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "prkmk_jax"


def _floors() -> dict[str, int]:
    """Top-level module or package name → floor, from the page's table."""
    floors = {}
    for line in (ROOT / "docs" / "architecture.md").read_text().splitlines():
        row = re.match(r"\| (\d) \| (.+?) \|", line)
        if row:
            for name in re.findall(r"`(\w+)`", row.group(2)):
                floors[name] = int(row.group(1))
    return floors


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The package's modules that `path` imports, as dotted names: for
    `from x import y`, the module x.y where y is one, else x."""
    own = _module_name(path).split(".")
    package = own if path.name == "__init__.py" else own[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            for alias in node.names:
                found.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in modules else target)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return found & modules


def _graph() -> dict[str, set[str]]:
    paths = {_module_name(path): path for path in PACKAGE.rglob("*.py")}
    return {name: _imports(path, set(paths)) - {name} for name, path in paths.items()}


def _top(name: str) -> str:
    """The name the map gives a module: its top-level module or package."""
    parts = name.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def test_every_module_is_on_a_floor_and_imports_only_downwards():
    floors, graph = _floors(), _graph()
    unplaced = sorted({_top(name) for name in graph} - set(floors))
    assert not unplaced, f"modules missing from docs/architecture.md: {unplaced}"
    upward = [(source, target) for source, targets in graph.items() for target in targets if floors[_top(target)] > floors[_top(source)]]
    assert not upward, f"imports of a higher floor: {upward}"


def test_no_import_circle():
    graph = _graph()
    state: dict[str, int] = {}
    circles = []

    def visit(node, path):
        state[node] = 1
        for target in sorted(graph[node]):
            if state.get(target) == 1:
                circles.append(path[path.index(target) :] + [target])
            elif target not in state:
                visit(target, path + [target])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not circles, f"import circles: {circles}"


def test_the_drivers_and_gradients_name_no_concrete_method():
    """integrate, the diffrax solver and the gradient code know a method only
    through `AbstractMethod`."""
    concrete = {"PRKMK", "Adjoint", "Symmetrized", "Composition", "Splitting", "AbstractMadeOfSteps"}
    for name in ("_integrate.py", "_solver.py", "_gradients.py", "_reversible_adjoint.py", "_loop.py"):
        source = (PACKAGE / name).read_text()
        named = {node.id for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Name)} | {
            alias.asname or alias.name for node in ast.walk(ast.parse(source)) if isinstance(node, ast.ImportFrom) for alias in node.names
        }
        assert not named & concrete, f"{name} names {named & concrete}"
