"""The package's layers: no module imports a layer above its own (docs/architecture.md, "Layers")."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "dapm_lightning"
LAYERS = {"options": 0, "geometry": 0, "models": 1, "metrics": 1, "data": 2, "training": 3, "inference": 4, "tools": 5,
          "cli": 6}
"""Lower numbers are lower layers; a module may import its own layer and those below."""


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "dapm_lightning" or len(parts) < 2:
        return None
    return parts[1] if parts[1] in LAYERS else None


def imports(path: Path, text: str | None = None) -> list[str]:
    """Every module ``path`` imports, anywhere in it: ``from A import B`` names ``A`` and ``A.B`` (B may be a module,
    as in ``from dapm_lightning import training``); a relative import is resolved against ``path``'s package."""
    found = []
    for node in ast.walk(ast.parse(path.read_text() if text is None else text)):
        if isinstance(node, ast.ImportFrom):
            module = node.module
            if node.level:
                package = path.relative_to(PACKAGE.parent).parts[:-1]
                base = package[:len(package) - node.level + 1]
                module = ".".join((*base, *([node.module] if node.module else [])))
            if module:
                found += [module] + [f"{module}.{alias.name}" for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
    return found


def test_no_module_imports_a_higher_layer():
    violations = []
    for path in PACKAGE.rglob("*.py"):
        own = layer_of("dapm_lightning." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
        if own is None:
            continue
        for module in imports(path):
            target = layer_of(module)
            if target is not None and LAYERS[target] > LAYERS[own]:
                violations.append(f"{path.relative_to(PACKAGE)} ({own}) imports {module} ({target})")
    assert not violations, "\n".join(violations)


def test_imports_of_a_layer_by_its_package_or_a_relative_name_are_seen():
    text = "from dapm_lightning import training\nfrom ..inference import writers\nfrom . import dapm\n"
    found = imports(PACKAGE / "models" / "new.py", text)
    assert {"dapm_lightning.training", "dapm_lightning.inference.writers", "dapm_lightning.models.dapm"} <= set(found)


def test_geometry_models_and_metrics_never_import_lightning():
    for layer in ("geometry", "models", "metrics"):
        for path in (PACKAGE / layer).rglob("*.py"):
            assert not any(m.split(".")[0] in ("lightning", "pytorch_lightning") for m in imports(path)), path


def test_every_module_belongs_to_a_layer():
    top = sorted(p.name for p in PACKAGE.iterdir() if p.suffix == ".py" or (p.is_dir() and p.name != "__pycache__"))
    assert top == ["__init__.py", "__main__.py", "cli.py", "configs", "data", "geometry", "inference", "metrics",
                   "models", "options.py", "tools", "training"]


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_import_cycle_between_modules_imports_inside_functions_included():
    modules = {module_name(path): path for path in PACKAGE.rglob("*.py")}

    def resolve(name: str) -> str | None:  # `from package import module` names the module itself
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                candidates = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.Import):
                candidates = [alias.name for alias in node.names]
            else:
                continue
            for candidate in candidates:
                if candidate.startswith("dapm_lightning") and (target := resolve(candidate)) not in (None, name):
                    # a package's __init__ re-exporting its own modules is not a cycle through them
                    if not (path.name == "__init__.py" and target.startswith(name + ".")):
                        targets.add(target)
        graph[name] = targets

    cycles = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for target in sorted(graph[node]):
            if state.get(target) == 1:
                cycles.append(" -> ".join(trail[trail.index(target):] + [target]))
            elif target not in state:
                visit(target, trail + [target])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    assert not cycles, "\n".join(cycles)
