"""`make wheels` collects every requirement but the node's PyTorch stack (scripts/offline_requirements.py)."""

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_offline_requirements_leave_the_node_stack_out():
    printed = subprocess.run([sys.executable, str(REPO / "scripts" / "offline_requirements.py"),
                              str(REPO / "pyproject.toml")], check=True, capture_output=True, text=True).stdout
    names = {line.split(">")[0].split("[")[0].split("=")[0] for line in printed.split()}
    assert {"albumentations", "jsonargparse", "embreex", "numpy", "matplotlib", "tensorboard", "onnx",
            "onnxscript"} <= names
    assert not names & {"torch", "torchvision", "lightning", "torchmetrics", "timm", "opencv-python-headless",
                        "onnxruntime"}
    assert "jsonargparse[signatures]>=4.32" in printed.split()  # extras and bounds kept
