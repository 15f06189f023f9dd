"""Stereo matchers behind one interface: rectified left, right -> left-referenced disparity, confidence.

`SGBMMatcher` (OpenCV semi-global matching, 3-way mode, internal left-right check, uniqueness and
speckle filtering) is the default. Learned matchers load from a local file (nothing is downloaded):

- `raft-stereo`: an official RAFT-Stereo checkpoint (`raftstereo-*.pth`, keys with or without the
  `module.` prefix of DataParallel) built with the official code, imported as `core.raft_stereo`
  from the user's checkout on PYTHONPATH, with its demo's arguments (overridable) and called as
  `forward(image1, image2, iters=32, test_mode=True)`; its output is a flow, disparity = -x.
- `torch`: a `torch.export` archive (`.pt2`, height and width dynamic), a TorchScript file, or a state dict
  plus the module that holds it (`arch`, "pkg.module:factory", called with `options` as keywords).
- `onnx`: an ONNX file run by onnxruntime; height and width must be dynamic.

Learned matchers get two (B, 3, H, W) float32 RGB tensors in [0, 255] times `input_scale`, padded
(edge values, centred, as RAFT-Stereo's InputPadder does) to multiples of `pad_multiple`, and return a
disparity (or a flow whose x component is minus the disparity). The search range is passed as
`max_disparity=` to a torch module whose forward takes it, and as a third input to an ONNX model that
has one; disparities outside [0, max_disparity) count as invalid.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import importlib.util
import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import torch
from torch import Tensor, nn

from ..errors import InputError
from ..torchfiles import ExportedModule, load_exported_program, load_torchscript

# the official RAFT-Stereo demo's architecture arguments (demo.py); `matcher_options` override them
RAFT_STEREO_ARGS: dict[str, Any] = {
    "hidden_dims": [128, 128, 128],
    "corr_implementation": "reg",
    "shared_backbone": False,
    "corr_levels": 4,
    "corr_radius": 4,
    "n_downsample": 2,
    "context_norm": "batch",
    "slow_fast_gru": False,
    "n_gru_layers": 3,
    "mixed_precision": False,
}
RAFT_STEREO_MODULE = "core.raft_stereo"


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

    def _sgbm(self, channels: int, max_disparity: int) -> cv2.StereoSGBM:
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
    """uint8 HxW or HxWx3 -> float32 (3, H, W) in [0, 255]."""
    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    return np.ascontiguousarray(img.transpose(2, 0, 1).astype(np.float32))


def centred_padding(height: int, width: int, multiple: int) -> tuple[int, int, int, int]:
    """(top, bottom, left, right) padding to multiples of `multiple`, split as RAFT-Stereo's InputPadder does."""
    ph, pw = (-height) % multiple, (-width) % multiple
    return ph // 2, ph - ph // 2, pw // 2, pw - pw // 2


def _pad(batch: np.ndarray, pads: tuple[int, int, int, int]) -> np.ndarray:
    """Pad (B, C, H, W) with edge values."""
    top, bottom, left, right = pads
    if not any(pads):
        return batch
    return np.pad(batch, ((0, 0), (0, 0), (top, bottom), (left, right)), mode="edge")


def network_input(images: Sequence[np.ndarray], input_scale: float = 1.0, multiple: int = 32
                  ) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Same-size uint8 images -> the padded (B, 3, H', W') float32 batch a learned matcher gets, and the padding."""
    h, w = images[0].shape[:2]
    pads = centred_padding(h, w, multiple)
    batch = _pad(np.stack([_as_rgb_float(img) for img in images]) * np.float32(input_scale), pads)
    return np.ascontiguousarray(batch, dtype=np.float32), pads


def _output_array(out: Tensor | Sequence[Tensor] | np.ndarray) -> np.ndarray:
    """A network's output as float32 (B, H, W): the last of a list/tuple, channel 0 of a flow."""
    if isinstance(out, (list, tuple)):
        out = out[-1]
    arr = out.detach().float().cpu().numpy() if hasattr(out, "detach") else np.asarray(out, dtype=np.float32)
    arr = arr.astype(np.float32)
    if arr.ndim == 4:
        arr = arr[:, 0]
    elif arr.ndim == 2:
        arr = arr[None]
    if arr.ndim != 3:
        raise InputError(None, "matcher", f"output of shape {tuple(arr.shape)}: expected (B, H, W) or (B, C, H, W)")
    return arr


class LearnedMatcher:
    """What all learned matchers share: input layout, padding, batching, output convention, statistics.

    `counts` accumulates, over the matched pixels, how many disparities were finite, valid, and clearly
    negative (a flow read with the wrong sign gives mostly negative disparities).
    """

    def __init__(self, input_scale: float = 1.0, flow_output: bool = False, pad_multiple: int = 32,
                 batch_size: int = 2):
        self.input_scale = float(input_scale)  # multiply [0, 255] pixels by this (1/255 for [0, 1] inputs)
        self.flow_output = bool(flow_output)  # output is a flow: disparity = -x
        self.pad_multiple = max(1, int(pad_multiple))
        self.batch_size = max(1, int(batch_size))
        self.counts = {"finite": 0, "valid": 0, "negative": 0}

    def run(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> np.ndarray:
        """The network on padded (B, 3, H, W) inputs -> raw output (B, H, W)."""
        raise NotImplementedError

    def match(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """Match one rectified pair (see `match_many`)."""
        return self.match_many([(left, right)], [max_disparity])[0]

    def match_many(
        self, pairs: Sequence[tuple[np.ndarray, np.ndarray]], max_disparities: Sequence[int]
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Match several rectified pairs; inputs of the same size and search range share forward calls
        of up to `batch_size` images. Disparity and a 0/1 confidence per pair, in the order given."""
        out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(pairs)
        groups: dict[tuple, list[int]] = {}
        for i, ((left, _), d) in enumerate(zip(pairs, max_disparities)):
            groups.setdefault((left.shape[:2], int(d)), []).append(i)
        for ((h, w), d), members in groups.items():
            for k in range(0, len(members), self.batch_size):
                chunk = members[k : k + self.batch_size]
                a, pads = network_input([pairs[i][0] for i in chunk], self.input_scale, self.pad_multiple)
                b, _ = network_input([pairs[i][1] for i in chunk], self.input_scale, self.pad_multiple)
                raw = self.run(a, b, d)
                if raw.shape[0] != len(chunk) or raw.shape[1:] != a.shape[2:]:
                    raise InputError(None, "matcher", f"output of shape {tuple(raw.shape)} for inputs of shape "
                                     f"{tuple(a.shape)}: expected one full-size disparity or flow per input")
                raw = raw[:, pads[0] : pads[0] + h, pads[2] : pads[2] + w]
                for j, i in enumerate(chunk):
                    out[i] = self._result(-raw[j] if self.flow_output else raw[j], d)
        return [o for o in out if o is not None]

    def _result(self, disp: np.ndarray, max_disparity: int) -> tuple[np.ndarray, np.ndarray]:
        """Learned matchers have no own confidence: 1 where the disparity is finite and in range."""
        finite = np.isfinite(disp)
        valid = finite & (disp >= 0) & (disp < max_disparity)
        self.counts["finite"] += int(finite.sum())
        self.counts["valid"] += int(valid.sum())
        self.counts["negative"] += int((finite & (disp < -0.5)).sum())
        return np.where(valid, disp, 0.0).astype(np.float32), valid.astype(np.float32)


def _accepts(fn: Callable, name: str) -> bool:
    """True if `fn` takes a keyword argument `name` (or **kwargs)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def torch_device(device: str) -> torch.device:
    """A torch device from "cpu" / "cuda"; one line when CUDA is asked for but absent."""
    if device == "cuda" and not torch.cuda.is_available():
        raise InputError(None, "device", "cuda asked for, but torch sees no CUDA device (use --device cpu)")
    return torch.device(device)


class TorchMatcher(LearnedMatcher):
    """A learned matcher as a torch module: forward(left, right, **forward_kwargs) on (B, 3, H, W) tensors."""

    def __init__(self, module: nn.Module, *, forward_kwargs: Mapping[str, Any] | None = None, device: str = "cpu",
                 **kwargs: float):
        super().__init__(**kwargs)
        self.device = torch_device(device)
        self.module = module.to(self.device).eval()
        self.forward_kwargs = dict(forward_kwargs or {})
        self._takes_range = _accepts(getattr(module, "forward", module), "max_disparity")

    @classmethod
    def from_torchscript(cls, path: str | Path, **kwargs: float) -> TorchMatcher:
        """Load a TorchScript file (`torch.jit.save`)."""
        return cls(load_torchscript(path), **kwargs)

    @classmethod
    def from_exported(cls, path: str | Path, **kwargs: Any) -> TorchMatcher:
        """Load a `torch.export.save` archive (.pt2) whose image inputs have dynamic height and width."""
        device = kwargs.get("device", "cpu")
        program = load_exported_program(path, "cpu" if device == "cpu" else str(torch_device(device)))
        fixed = _fixed_image_sides(program)
        if fixed:
            raise InputError(path, "inputs", f"{fixed}: the rectified canvas differs per pair, so height and "
                             "width must be dynamic; re-export with dynamic_shapes={name: {2: Dim('height'), "
                             "3: Dim('width')}}")
        return cls(ExportedModule(program), **kwargs)

    @classmethod
    def from_state_dict(
        cls, factory: Callable[..., nn.Module], path: str | Path, options: Mapping[str, Any] | None = None,
        **kwargs: float,
    ) -> TorchMatcher:
        """Build the module with `factory(**options)` and load a checkpoint (`module.` prefixes stripped)."""
        try:
            module = factory(**dict(options or {}))
        except TypeError as exc:
            raise InputError(path, "matcher_arch", f"cannot build the module ({exc}); pass its arguments "
                             "as matcher_options") from None
        load_checkpoint(module, path)
        return cls(module, **kwargs)

    def run(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> np.ndarray:
        """The module on one batch (no gradients; TorchScript without per-shape re-optimisation)."""
        kwargs = dict(self.forward_kwargs)
        if self._takes_range:
            kwargs["max_disparity"] = int(max_disparity)
        a = torch.from_numpy(left).to(self.device)
        b = torch.from_numpy(right).to(self.device)
        # TorchScript re-optimises for every new input shape, and canvases differ per pair: run it plainly
        with torch.inference_mode(), torch.jit.optimized_execution(False):
            return _output_array(self.module(a, b, **kwargs))


def _fixed_image_sides(program: Any) -> str:
    """'' when the program's first two inputs have symbolic height and width; else which ones are fixed."""
    placeholders = {n.name: n for n in program.graph.nodes if n.op == "placeholder"}
    names = list(program.graph_signature.user_inputs)
    if len(names) < 2:
        return f"{len(names)} input(s), expected the left and the right image"
    fixed = []
    for name in names[:2]:
        shape = getattr(placeholders[name].meta.get("val"), "shape", ())
        if len(shape) != 4:
            return f"input {name} has {len(shape)} dimensions, expected (B, 3, H, W)"
        fixed += [f"{name} {side} {int(shape[d])}" for d, side in ((2, "height"), (3, "width"))
                  if not isinstance(shape[d], torch.SymInt)]
    return ", ".join(f"fixed {f}" for f in fixed)


def load_checkpoint(module: nn.Module, path: str | Path) -> None:
    """Load a state dict (plain, under 'state_dict' / 'model', or DataParallel's `module.` keys) into a module."""
    try:
        state = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is bad input
        raise InputError(path, None, f"not a readable torch checkpoint ({type(exc).__name__})") from None
    for key in ("state_dict", "model"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise InputError(path, None, "not a state dict")
    if state and all(k.startswith("module.") for k in state):
        state = {k[len("module.") :]: v for k, v in state.items()}
    missing, unexpected = _key_mismatch(module, state)
    if missing or unexpected:
        raise InputError(path, "state dict", f"does not fit the architecture ({len(missing)} missing keys, e.g. "
                         f"{missing[:2]}; {len(unexpected)} unexpected, e.g. {unexpected[:2]}); check matcher_options")
    module.load_state_dict(state)


def _key_mismatch(module: nn.Module, state: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    own = set(module.state_dict())
    return sorted(own - set(state)), sorted(set(state) - own)


def _onnx_providers(device: str) -> list[str]:
    import onnxruntime as ort

    if device == "cuda":
        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise InputError(None, "device", "cuda asked for, but onnxruntime has no CUDAExecutionProvider "
                             "(install onnxruntime-gpu, or use --device cpu)")
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


class OnnxMatcher(LearnedMatcher):
    """A learned matcher exported to ONNX: two image inputs (B, 3, H, W) with dynamic H and W, and an
    optional third scalar input taking the search range."""

    def __init__(self, path: str | Path, *, device: str = "cpu", **kwargs: float):
        import onnxruntime as ort

        super().__init__(**kwargs)
        self.path, self.device = str(path), device
        providers = _onnx_providers(device)
        try:
            self._session = ort.InferenceSession(self.path, providers=providers)
        except Exception as exc:  # noqa: BLE001 - onnxruntime's load errors are bad input here
            first = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            raise InputError(self.path, None, f"onnxruntime cannot load it ({first})") from None
        inputs = self._session.get_inputs()
        images = [i for i in inputs if len(i.shape) == 4]
        others = [i for i in inputs if len(i.shape) != 4]
        if len(images) != 2 or len(others) > 1 or any(len(i.shape) > 1 for i in others):
            shapes = ", ".join(f"{i.name} {list(i.shape)}" for i in inputs)
            raise InputError(self.path, "inputs", f"a matcher takes 2 image inputs (B, 3, H, W) and optionally a "
                             f"scalar search range; this model has {shapes}")
        for inp in images:
            shape = list(inp.shape)
            if isinstance(shape[2], int) or isinstance(shape[3], int):
                raise InputError(self.path, f"inputs[{inp.name}]", f"fixed size {shape[2]}x{shape[3]}: canvases "
                                 "differ per pair; re-export with dynamic height and width (torch.onnx.export(..., "
                                 "dynamic_axes={name: {2: 'height', 3: 'width'}}))")
            if shape[0] == 1:
                self.batch_size = 1
        self._names = [i.name for i in images]
        self._range = (others[0].name, np.int64 if "int64" in others[0].type else np.float32) if others else None

    def run(self, left: np.ndarray, right: np.ndarray, max_disparity: int) -> np.ndarray:
        """The session on one batch."""
        feed = {self._names[0]: left, self._names[1]: right}
        if self._range is not None:
            feed[self._range[0]] = np.array(max_disparity, dtype=self._range[1])
        try:
            out = self._session.run(None, feed)
        except Exception as exc:  # noqa: BLE001 - say which input the model could not take
            first = str(exc).splitlines()[0][:160] if str(exc) else type(exc).__name__
            raise InputError(self.path, None, f"onnxruntime failed on inputs of shape {list(left.shape)} "
                             f"(search range {max_disparity}): {first}") from None
        return _output_array(out)


def _import_factory(spec: str) -> Callable[..., nn.Module]:
    """`package.module:callable` -> the callable."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise InputError(None, "matcher_arch", f"expected 'package.module:callable', got {spec!r}")
    try:
        return getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise InputError(None, "matcher_arch", f"cannot import {spec!r} ({exc})") from None


def raft_stereo_class() -> type[nn.Module]:
    """The official RAFTStereo class from the user's checkout (`core.raft_stereo` on PYTHONPATH)."""
    try:
        return importlib.import_module(RAFT_STEREO_MODULE).RAFTStereo
    except (ImportError, AttributeError) as exc:
        raise InputError(None, "matcher raft-stereo", f"cannot import {RAFT_STEREO_MODULE}.RAFTStereo ({exc}); "
                         "put the root of a RAFT-Stereo checkout (github.com/princeton-vl/RAFT-Stereo) on PYTHONPATH"
                         ) from None


def raft_stereo_module(options: Mapping[str, Any] | None = None) -> nn.Module:
    """An official RAFTStereo built with the demo's arguments, updated by `options`."""
    args = argparse.Namespace(**{**RAFT_STEREO_ARGS, **dict(options or {})})
    return raft_stereo_class()(args)


def load_learned_matcher(
    path: str | Path, arch: str | None = None, input_scale: float = 1.0, flow_output: bool = False,
    pad_multiple: int = 32, *, kind: str | None = None, options: Mapping[str, Any] | None = None,
    iters: int | None = None, device: str = "cpu", batch_size: int = 2,
) -> TorchMatcher | OnnxMatcher:
    """A learned matcher from a local file: `kind` "raft-stereo" (official checkpoint), "onnx" (or a .onnx
    file), else a torch.export archive (.pt2), TorchScript, or a state dict + `arch`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "matcher file not found")
    kw: dict[str, Any] = {"input_scale": input_scale, "flow_output": flow_output, "pad_multiple": pad_multiple,
                          "batch_size": batch_size, "device": device}
    if kind == "onnx" or (kind != "raft-stereo" and path.suffix.lower() == ".onnx"):
        return OnnxMatcher(path, **kw)
    forward: dict[str, Any] = {} if iters is None else {"iters": int(iters)}
    if kind == "raft-stereo":
        module = raft_stereo_module(options)
        load_checkpoint(module, path)
        return TorchMatcher(module, forward_kwargs={**forward, "test_mode": True}, **kw)
    if arch is not None:
        return TorchMatcher.from_state_dict(_import_factory(arch), path, options, forward_kwargs=forward, **kw)
    if path.suffix.lower() == ".pt2":
        if forward:
            raise InputError(path, "matcher_iters", "an exported program runs the iterations it was exported with")
        return TorchMatcher.from_exported(path, **kw)
    try:
        return TorchMatcher.from_torchscript(path, forward_kwargs=forward, **kw)
    except RuntimeError:
        raise InputError(
            path, None, "not a TorchScript file; a state dict needs its module (matcher_arch='pkg.module:factory')"
        ) from None


# --- fingerprints of learned matchers -------------------------------------------------------------
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def onnx_files(path: str | Path) -> list[Path]:
    """The ONNX file and every external-data file its tensors point to."""
    import onnx
    from onnx.external_data_helper import _get_all_tensors, uses_external_data

    path = Path(path)
    try:
        model = onnx.load(str(path), load_external_data=False)
    except Exception as exc:  # noqa: BLE001 - any unreadable model is bad input
        raise InputError(path, None, f"not a readable ONNX file ({type(exc).__name__})") from None
    files = {path}
    for tensor in _get_all_tensors(model):
        if uses_external_data(tensor):
            location = next((e.value for e in tensor.external_data if e.key == "location"), None)
            if location:
                files.add(path.parent / location)
    return sorted(files)


def _source_files(module_name: str) -> list[Path]:
    """The .py files of the package that holds `module_name` (the module's own file if it has none)."""
    top = module_name.split(".")[0]
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        return []
    if spec.submodule_search_locations:
        files = sorted(p for loc in spec.submodule_search_locations for p in Path(loc).rglob("*.py"))
        if len(files) <= 2000:
            return files
    try:
        own = importlib.util.find_spec(module_name)
    except (ImportError, ValueError):
        own = None
    return [Path(own.origin)] if own is not None and own.origin and Path(own.origin).is_file() else []


def model_digests(kind: str, path: str | Path | None, arch: str | None) -> dict[str, Any]:
    """What a learned matcher's output depends on beyond the settings: SHA-256 of every model file
    (ONNX external data included) and of the architecture's source code (raft-stereo: the checkout's
    `core` package; `arch`: the package holding the factory)."""
    path = Path(path or "")
    if not path.is_file():
        raise InputError(path, None, "matcher file not found")
    files = onnx_files(path) if kind == "onnx" or (kind != "raft-stereo" and path.suffix.lower() == ".onnx") else [path]
    out: dict[str, Any] = {"matcher_sha256": _sha256(path)}
    if len(files) > 1:
        out["matcher_files_sha256"] = {
            str(f.relative_to(path.parent)): _sha256(f) if f.is_file() else None for f in files
        }
    code_module = RAFT_STEREO_MODULE if kind == "raft-stereo" else (arch.partition(":")[0] if arch else None)
    if code_module:
        sources = _source_files(code_module)
        if kind == "raft-stereo" and not sources:
            raft_stereo_class()  # raises the one-line "put the checkout on PYTHONPATH"
        h = hashlib.sha256()
        for f in sources:
            h.update(f.name.encode() + b"\0" + f.read_bytes())
        out["matcher_code_sha256"] = h.hexdigest() if sources else None
    return out


__all__ = [
    "LearnedMatcher",
    "Matcher",
    "OnnxMatcher",
    "RAFT_STEREO_ARGS",
    "SGBMMatcher",
    "TorchMatcher",
    "centred_padding",
    "load_checkpoint",
    "load_learned_matcher",
    "model_digests",
    "network_input",
    "onnx_files",
    "raft_stereo_module",
    "torch_device",
]
