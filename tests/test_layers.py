"""The subpackages form layers: a module imports only from its own subpackage or the ones below."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mjx_pathtrack"
#: bottom to top (docs/architecture.md)
LAYERS = ("core", "robots", "paths", "envs", "deploy", "config", "evaluation", "rl", "sweeps")


def _imported_subpackages(file: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(file.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        else:
            continue
        for module in modules:
            parts = module.split(".")
            if parts[0] == "mjx_pathtrack" and len(parts) > 1 and parts[1] in LAYERS:
                names.add(parts[1])
    return names


def test_every_subpackage_is_a_layer_and_imports_only_downwards():
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert found == set(LAYERS), f"subpackages not in LAYERS: {sorted(found ^ set(LAYERS))}"
    upward = []
    for layer in LAYERS:
        for file in sorted((PACKAGE / layer).rglob("*.py")):
            for target in _imported_subpackages(file):
                if LAYERS.index(target) > LAYERS.index(layer):
                    upward.append(f"{file.relative_to(PACKAGE)} imports mjx_pathtrack.{target}")
    assert not upward, "imports that run up a layer:\n" + "\n".join(upward)


def _module_imports() -> dict[str, set[str]]:
    """Every module of the package -> the package modules it imports, at the top or inside a
    function (a lazy import closes a circle just the same)."""
    modules = {}
    for file in PACKAGE.rglob("*.py"):
        parts = ("mjx_pathtrack",) + file.relative_to(PACKAGE).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = file
    graph = {}
    for name, file in modules.items():
        found = set()
        for node in ast.walk(ast.parse(file.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                found |= {f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                          for a in node.names}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names}
        graph[name] = {m for m in found if m in modules and m != name}
    return graph


def test_no_import_circle_between_modules():
    """No module reaches itself through the package's imports (top-level or lazy): e.g. the ball
    task and its executors, datasets and user paths once imported each other."""
    graph = _module_imports()
    assert len(graph) > 50 and "mjx_pathtrack.envs.tasks.ball_executor" in graph["mjx_pathtrack.envs.tasks.ball_on_plate"]
    circles = []
    for start in sorted(graph):
        stack, seen = [(start, (start,))], set()
        while stack:
            node, trail = stack.pop()
            for nxt in sorted(graph[node]):
                if nxt == start:
                    circles.append(" -> ".join(trail + (start,)))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, trail + (nxt,)))
    assert not circles, "import circles:\n" + "\n".join(sorted(set(circles)))


def test_no_module_over_500_lines():
    """Small modules, one concept each: none of the package's modules grows past 500 lines."""
    long = {str(f.relative_to(PACKAGE)): n for f in PACKAGE.rglob("*.py")
            if (n := len(f.read_text().splitlines())) > 500}
    assert not long, f"modules over 500 lines (split them by concept): {long}"
