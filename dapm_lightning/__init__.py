"""DAPM on PyTorch Lightning: monocular metric depth and camera pose (height, pitch, roll, FoV) from UAV images."""

import os

__version__ = "0.1.0"

# albumentations asks PyPI for a newer version as it is imported, in every process that imports it (each DDP rank,
# loader fork server, spawned worker): a request at run time, which a cluster node without internet waits on.
# Off unless the user set it (the variable is albumentations' own and reaches the processes started from here).
os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")
