"""Inference: inputs, post-processing, writers, the Python API and ONNX, on top of the training layer."""
