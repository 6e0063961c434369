"""DAPM on PyTorch Lightning: monocular metric depth and camera pose (height, pitch, roll, FoV) from UAV images."""

__version__ = "0.1.0"
