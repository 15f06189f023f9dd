"""ONNX export of the prior-augmented depth nets and parity checks against onnxruntime."""

from __future__ import annotations

from .onnx import DEFAULT_OPSET, export_onnx, read_metadata
from .parity import FP16_TOLERANCE, FP32_TOLERANCE, ParityError, ParityResult, check_parity

__all__ = [
    "DEFAULT_OPSET",
    "FP16_TOLERANCE",
    "FP32_TOLERANCE",
    "ParityError",
    "ParityResult",
    "check_parity",
    "export_onnx",
    "read_metadata",
]
