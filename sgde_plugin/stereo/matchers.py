"""Stereo matchers behind one interface: rectified left, right -> left-referenced disparity, confidence.

`SGBMMatcher` (OpenCV semi-global matching, 3-way mode, internal left-right check, uniqueness and
speckle filtering) is the default. `TorchMatcher` and `OnnxMatcher` run a learned matcher loaded
from a local file (for example a RAFT-Stereo export): a TorchScript file, a state dict plus the
module that holds it (loaded with `torch.load(..., weights_only=True)`), or an ONNX file run by
onnxruntime. Learned matchers take two (1, 3, H, W) float32 RGB tensors and return a disparity map
(or a flow whose x component is minus the disparity, RAFT-Stereo's convention).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from ..errors import InputError


class Matcher(Protocol):
    """Rectified images (uint8, HxW or HxWx3, same size) -> disparity float32 (H, W), confidence [0, 1].

    Disparity is left-referenced (left x - right x, >= 0); confidence is 0 where there is no value.
    """

    def match(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """Match one rectified pair searching disparities in [0, max_disparity)."""
        ...


@dataclass(frozen=True)
class SGBMMatcher:
    """OpenCV StereoSGBM in MODE_SGBM_3WAY with uniqueness, speckle and left-right checks."""

    block_size: int = 5
    p1: int = 8
    p2: int = 32
    uniqueness: int = 10
    speckle_window: int = 100
    speckle_range: int = 2
    disp12_max_diff: int = 1
    pre_filter_cap: int = 63

    def _sgbm(self, channels: int, max_disparity: int) -> Any:
        area = channels * self.block_size * self.block_size
        return cv2.StereoSGBM_create(
            minDisparity=0,
            numDisparities=int(max_disparity),
            blockSize=self.block_size,
            P1=self.p1 * area,
            P2=self.p2 * area,
            disp12MaxDiff=self.disp12_max_diff,
            preFilterCap=self.pre_filter_cap,
            uniquenessRatio=self.uniqueness,
            speckleWindowSize=self.speckle_window,
            speckleRange=self.speckle_range,
            mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
        )

    def match(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """SGBM disparity (1/16 px resolution) and a 0/1 confidence from OpenCV's own filters."""
        if max_disparity % 16:
            raise ValueError("SGBM needs max_disparity to be a multiple of 16")
        channels = 1 if left.ndim == 2 else left.shape[2]
        raw = self._sgbm(channels, max_disparity).compute(left, right)
        disp = raw.astype(np.float32) / 16.0
        valid = raw >= 0
        disp[~valid] = 0.0
        return disp, valid.astype(np.float32)


def _as_rgb_float(image: np.ndarray) -> np.ndarray:
    """uint8 HxW or HxWx3 -> float32 (1, 3, H, W) in [0, 255]."""
    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(img.transpose(2, 0, 1)[None].astype(np.float32))


def _pad_to(batch: np.ndarray, multiple: int) -> np.ndarray:
    """Pad (1, C, H, W) at the bottom and right (edge values) to multiples of `multiple`."""
    if multiple <= 1:
        return batch
    h, w = batch.shape[2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    return np.pad(batch, ((0, 0), (0, 0), (0, ph), (0, pw)), mode="edge") if ph or pw else batch


def _disparity_from_output(out: Any, height: int, width: int, flow_output: bool) -> np.ndarray:
    """Pick the disparity out of a network's output (last of a list; channel 0 of a flow)."""
    if isinstance(out, (list, tuple)):
        out = out[-1]
    arr = out.detach().cpu().numpy() if hasattr(out, "detach") else np.asarray(out)
    arr = arr.astype(np.float32)
    while arr.ndim > 2:
        arr = arr[0]
    arr = arr[:height, :width]
    return -arr if flow_output else arr


def _learned_result(disp: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
    """Learned matchers have no own confidence: 1 where the disparity is finite and in range."""
    valid = np.isfinite(disp) & (disp >= 0) & (disp < max_disparity)
    return np.where(valid, disp, 0.0).astype(np.float32), valid.astype(np.float32)


@dataclass
class TorchMatcher:
    """A learned matcher as a torch module: forward(left, right) on (1, 3, H, W) float32 tensors."""

    module: Any
    input_scale: float = 1.0  # multiply [0, 255] pixels by this (1/255 for [0, 1] inputs)
    flow_output: bool = False  # output is a flow: disparity = -x
    pad_multiple: int = 32

    @classmethod
    def from_torchscript(cls, path: str | Path, **kwargs: Any) -> TorchMatcher:
        """Load a TorchScript file (`torch.jit.save`)."""
        import torch

        return cls(torch.jit.load(str(path), map_location="cpu").eval(), **kwargs)

    @classmethod
    def from_state_dict(cls, factory: Callable[[], Any], path: str | Path, **kwargs: Any) -> TorchMatcher:
        """Build the module with `factory()` and load a state dict with `torch.load(weights_only=True)`."""
        import torch

        state = torch.load(str(path), map_location="cpu", weights_only=True)
        if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
            state = state["state_dict"]
        module = factory()
        module.load_state_dict(state)
        return cls(module.eval(), **kwargs)

    def match(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """Run the module once on the padded pair and crop its disparity back."""
        import torch

        h, w = left.shape[:2]
        a = _pad_to(_as_rgb_float(left) * self.input_scale, self.pad_multiple)
        b = _pad_to(_as_rgb_float(right) * self.input_scale, self.pad_multiple)
        # TorchScript re-optimises for every new input shape, and canvases differ per pair: run it plainly
        with torch.inference_mode(), torch.jit.optimized_execution(False):
            out = self.module(torch.from_numpy(a), torch.from_numpy(b))
        return _learned_result(_disparity_from_output(out, h, w, self.flow_output), max_disparity)


@dataclass
class OnnxMatcher:
    """A learned matcher exported to ONNX with two image inputs, run by onnxruntime on the CPU."""

    path: str
    input_scale: float = 1.0
    flow_output: bool = False
    pad_multiple: int = 32

    def __post_init__(self) -> None:
        import onnxruntime as ort

        self._session = ort.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])
        self._inputs = [i.name for i in self._session.get_inputs()]
        if len(self._inputs) != 2:
            raise InputError(self.path, "inputs", f"a matcher takes 2 image inputs, this model has {len(self._inputs)}")

    def match(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """Run the session once on the padded pair and crop its disparity back."""
        h, w = left.shape[:2]
        a = _pad_to(_as_rgb_float(left) * self.input_scale, self.pad_multiple)
        b = _pad_to(_as_rgb_float(right) * self.input_scale, self.pad_multiple)
        out = self._session.run(None, {self._inputs[0]: a, self._inputs[1]: b})
        return _learned_result(_disparity_from_output(out, h, w, self.flow_output), max_disparity)


def _import_factory(spec: str) -> Callable[[], Any]:
    """`package.module:callable` -> the callable."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise InputError(None, "matcher_arch", f"expected 'package.module:callable', got {spec!r}")
    try:
        return getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(None, "matcher_arch", f"cannot import {spec!r} ({exc})") from None


def load_learned_matcher(
    path: str | Path, arch: str | None = None, input_scale: float = 1.0, flow_output: bool = False,
    pad_multiple: int = 32,
) -> TorchMatcher | OnnxMatcher:
    """A learned matcher from a local file: .onnx -> onnxruntime; else TorchScript, or a state dict + `arch`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "matcher file not found")
    kw = {"input_scale": input_scale, "flow_output": flow_output, "pad_multiple": pad_multiple}
    if path.suffix.lower() == ".onnx":
        return OnnxMatcher(str(path), **kw)
    if arch is not None:
        return TorchMatcher.from_state_dict(_import_factory(arch), path, **kw)
    try:
        return TorchMatcher.from_torchscript(path, **kw)
    except RuntimeError:
        raise InputError(
            path, None, "not a TorchScript file; a state dict needs its module (matcher_arch='pkg.module:factory')"
        ) from None
