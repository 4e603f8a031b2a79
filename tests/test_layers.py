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
