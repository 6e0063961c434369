"""benchmarks/ beside the package: the package never imports it; only dapm_lightning/training/ steps an optimiser."""

import re
from pathlib import Path

from tests.test_layers import PACKAGE, imports

REPO = PACKAGE.parent
TRAINING = PACKAGE / "training"
OWN_TRAINING_LOOP = re.compile(r"\.backward\(|torch\.optim\.(?!lr_scheduler)[A-Za-z]+\(|optimizer\.step\(")
"""What a training loop of its own writes: a backward pass, an optimiser built or stepped by hand."""


def sources(*folders: Path) -> list[Path]:
    return sorted(p for folder in folders for p in folder.rglob("*.py"))


def test_the_package_never_imports_the_benchmarks():
    found = [f"{path.relative_to(REPO)} imports {module}" for path in sources(PACKAGE)
             for module in imports(path) if module.split(".")[0] == "benchmarks"]
    assert not found, "\n".join(found)


def test_only_the_training_layer_runs_backward_or_builds_an_optimiser():
    found = [f"{path.relative_to(REPO)}:{number}: {line.strip()}"
             for path in sources(PACKAGE, REPO / "benchmarks", REPO / "scripts") if TRAINING not in path.parents
             for number, line in enumerate(path.read_text().splitlines(), 1) if OWN_TRAINING_LOOP.search(line)]
    assert not found, "train through DAPMModule in a Trainer instead:\n" + "\n".join(found)


def test_benchmarks_are_not_in_the_wheel():
    pyproject = (REPO / "pyproject.toml").read_text()
    assert 'include = ["dapm_lightning*"]' in pyproject and (REPO / "benchmarks" / "__init__.py").is_file()
