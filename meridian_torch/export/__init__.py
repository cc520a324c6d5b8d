"""ONNX export checked against eager torch, onnxruntime sessions, and the local model manifest.

Submodules import onnx/onnxruntime only inside their functions, so importing this package is cheap.
"""
