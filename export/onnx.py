"""Export a torch module to one self-contained ONNX file with SGDE metadata."""

from __future__ import annotations

import contextlib
import copy
import io
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor, nn

from sgde_plugin.errors import InputError
from sgde_plugin.io import atomic_path

DEFAULT_OPSET = 17
DEFORM_CONV_OPSET = 19  # ONNX DeformConv exists from opset 19 on
MAX_SINGLE_FILE_BYTES = 2 * 1024**3  # protobuf's limit: above it ONNX needs an external-data file


class HalfPrecision(nn.Module):
    """Run ``module`` in float16 with float32 inputs and outputs (casts at the graph boundary)."""

    def __init__(self, module: nn.Module) -> None:
        super().__init__()
        self.module = copy.deepcopy(module).half()

    def forward(self, *inputs: Tensor) -> Tensor | tuple[Tensor, ...]:
        """Cast floating inputs to half, run, cast floating outputs back to float."""
        out = self.module(*[x.half() if x.is_floating_point() else x for x in inputs])
        if isinstance(out, Tensor):
            return out.float()
        return tuple(o.float() for o in out)


def _deform_conv_symbolic(g, input, weight, offset, mask, bias, stride_h, stride_w, pad_h, pad_w,  # noqa: ANN001, ANN202, A002
                          dil_h, dil_w, n_weight_grps, n_offset_grps, use_mask):
    """torchvision::deform_conv2d -> ONNX DeformConv (opset 19); offsets (dy, dx) per kernel point in both."""
    from torch.onnx import symbolic_helper as sh

    def const(v: torch.Value, name: str) -> int:
        return int(sh._get_const(v, "i", name))

    if sh._maybe_get_const(use_mask, "b"):
        raise ValueError("modulated deformable convolution (with a mask) has no ONNX export here")
    return g.op("DeformConv", input, weight, offset, bias,
                strides_i=[const(stride_h, "stride_h"), const(stride_w, "stride_w")],
                pads_i=[const(pad_h, "pad_h"), const(pad_w, "pad_w")] * 2,
                dilations_i=[const(dil_h, "dil_h"), const(dil_w, "dil_w")],
                group_i=const(n_weight_grps, "groups"), offset_group_i=const(n_offset_grps, "offset_groups"))


@contextlib.contextmanager
def _deform_conv_export(opset: int) -> Iterator[None]:
    """Within the block, torchvision's deform_conv2d exports as DeformConv (only for opset >= 19)."""
    if opset < DEFORM_CONV_OPSET:
        yield
        return
    name = "torchvision::deform_conv2d"
    torch.onnx.register_custom_op_symbolic(name, _deform_conv_symbolic, DEFORM_CONV_OPSET)
    try:
        yield
    finally:
        torch.onnx.unregister_custom_op_symbolic(name, DEFORM_CONV_OPSET)


def _trace_to_bytes(
    module: nn.Module,
    example_inputs: tuple[Tensor, ...],
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Mapping[int, str]] | None,
    opset: int,
) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings(), _deform_conv_export(opset):
        # the legacy (TorchScript) exporter warns that it is legacy and about traced shape casts
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            example_inputs,
            buf,
            dynamo=False,
            opset_version=opset,
            input_names=list(input_names),
            output_names=list(output_names),
            dynamic_axes={k: dict(v) for k, v in (dynamic_axes or {}).items()},
            do_constant_folding=True,
        )
    return buf.getvalue()


def export_onnx(
    module: nn.Module,
    example_inputs: Sequence[Tensor],
    path: str | Path,
    *,
    input_names: Sequence[str],
    output_names: Sequence[str],
    dynamic_axes: Mapping[str, Mapping[int, str]] | None = None,
    metadata: Mapping[str, str] | None = None,
    opset: int = DEFAULT_OPSET,
    fp16: bool = False,
) -> Path:
    """Export ``module`` (in eval mode) to ``path``: one ONNX file, checked, with metadata_props.

    Uses the TorchScript-based exporter (``dynamo=False``), which handles the dynamic batch and image
    sizes of these nets. ``fp16`` stores and computes in float16 but keeps float32 inputs/outputs.
    The file is written atomically and ``onnx.checker`` must accept it; returns the path.
    """
    import onnx

    if opset < 17:
        raise ValueError(f"opset must be >= 17, got {opset}")
    if opset < DEFORM_CONV_OPSET and has_deform_conv(module):
        raise InputError(None, "opset", f"{opset}: the deformable convolution exports as ONNX DeformConv, which needs "
                         f"opset >= {DEFORM_CONV_OPSET} (onnxruntime runs it); export with opset "
                         f"{DEFORM_CONV_OPSET}, or build the net with deformable=False")
    module = module.eval()
    inputs = tuple(example_inputs)
    if fp16:
        module = HalfPrecision(module).eval()
    with torch.no_grad():
        data = _trace_to_bytes(module, inputs, input_names, output_names, dynamic_axes, opset)
    model = onnx.load_from_string(data)
    props = {"sgde.precision": "fp16" if fp16 else "fp32", "sgde.opset": str(opset), **(metadata or {})}
    onnx.helper.set_model_props(model, {str(k): str(v) for k, v in props.items()})
    data = model.SerializeToString()
    if len(data) >= MAX_SINGLE_FILE_BYTES:
        raise ValueError(f"model is {len(data) / 2**30:.2f} GiB: too large for one self-contained ONNX file")
    onnx.checker.check_model(model, full_check=True)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def has_deform_conv(module: nn.Module) -> bool:
    """Whether ``module`` holds a deformable convolution (exported as ONNX DeformConv, opset >= 19)."""
    return any(type(m).__name__ == "DeformConv3x3" for m in module.modules())


def read_metadata(path: str | Path) -> dict[str, str]:
    """The metadata_props of an ONNX file as a dict."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}
