"""Print the project's requirements that an air-gapped GPU node lacks: all but the node's own PyTorch stack.

``make wheels`` downloads these (with constraints.txt's pins) into one folder; ``make install-offline``
installs the project from that folder alone, reusing the node's torch, torchvision, lightning, torchmetrics,
timm, OpenCV and onnxruntime.
"""

import re
import sys
from pathlib import Path

NODE_STACK = {"torch", "torchvision", "lightning", "torchmetrics", "timm", "opencv-python-headless",
              "opencv-python", "onnxruntime", "onnxruntime-gpu"}
EXTRAS = ("export",)


def requirements(pyproject: Path) -> list[str]:
    text = pyproject.read_text()
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.S | re.M)
    assert block is not None, "no [project] dependencies in pyproject.toml"
    found = re.findall(r'"([^"]+)"', block.group(1))
    for extra in EXTRAS:
        line = re.search(rf"^{extra} = \[(.*?)\]", text, re.M)
        assert line is not None, f"no optional dependency group {extra!r}"
        found += re.findall(r'"([^"]+)"', line.group(1))
    return [r for r in found if re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() not in NODE_STACK]


if __name__ == "__main__":
    print("\n".join(requirements(Path(sys.argv[1] if len(sys.argv) > 1 else "pyproject.toml"))))
