"""`sgde export onnx`: write the R18 depth net or the BEVDepth-style depth branch as one checked ONNX file."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from ..errors import InputError
from .options import integer

if TYPE_CHECKING:
    from ..export.models import ExportSpec

HELP = "export the R18 depth net or the BEVDepth-style depth branch to ONNX (optionally checked)"


# the export traces example inputs of this size (a batch of cameras): larger sides need tens of GB and are beyond any
# camera input these nets are deployed at
MAX_EXPORT_SIDE = 4096


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW, e.g. 384x640, got {text!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    if max(h, w) > MAX_EXPORT_SIDE:
        raise argparse.ArgumentTypeError(f"sides must be at most {MAX_EXPORT_SIDE} pixels, got {text!r}")
    return h, w


def _max_opset() -> int:
    """The highest opset the installed torch's (TorchScript) ONNX exporter writes."""
    try:
        from torch.onnx import _constants

        return int(getattr(_constants, "ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET", 20))
    except ImportError:  # pragma: no cover - torch without onnx support
        return 20


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `sgde export`."""
    parser.add_argument("format", choices=["onnx"], help="output format")
    parser.add_argument("--model", required=True, choices=["r18", "bevdepth"], help="which network")
    parser.add_argument("--out", required=True, metavar="FILE.onnx", help="output file")
    parser.add_argument("--checkpoint", metavar="CKPT", help="weights (torch.load weights_only=True); default: "
                        "untrained weights")
    parser.add_argument("--check", action="store_true", help="before writing, compare onnxruntime with torch "
                        "(batch 1 and 6, seeded random inputs and a frame rendered by sgde synth); fp32 must agree "
                        "within 1e-4 x output range + 1e-3 relative; a mismatch fails with the numbers, no file")
    parser.add_argument("--fp16", action="store_true", help="float16 weights and arithmetic, float32 inputs/outputs "
                        "(checked against fp32 torch within 1e-2 x output range + 1e-2 relative)")
    parser.add_argument("--image-size", type=_size, metavar="HxW", help="image size (r18 default 384x640, "
                        "bevdepth default 256x704 -> features at stride 16)")
    parser.add_argument("--cams", type=integer(1, 64), default=6, help="cameras per sample for bevdepth example inputs")
    parser.add_argument("--opset", type=integer(17, 10**6), default=17, help="ONNX opset (>= 17)")


def _size_text(args: argparse.Namespace) -> str:
    """The image size as the user gave it (or the model's default), with the cameras for bevdepth."""
    size = "the default size" if args.image_size is None else "x".join(map(str, args.image_size))
    return f"{size} x {args.cams} cameras" if args.model == "bevdepth" else size


def _check_memory(spec: ExportSpec, args: argparse.Namespace) -> None:
    """Refuse, before any tensor is made, an export the free memory cannot hold (the kernel would kill it)."""
    from ..cache.build import available_memory
    from ..export.workflow import estimated_peak_bytes

    need, have = estimated_peak_bytes(spec, args.check, args.fp16), available_memory()
    if have is not None and need > have:
        what = "the export and --check" if args.check else "the export"
        raise InputError(None, "--image-size", f"{_size_text(args)} needs about {need / 1e9:.1f} GB for {what}, "
                         f"{have / 1e9:.1f} GB is available; nothing written")


def run(args: argparse.Namespace) -> int:
    """Build the model, export it, check it when asked, print a summary."""
    from ..export.models import BUILDERS
    from ..export.parity import ParityError
    from ..export.workflow import export_spec

    top = _max_opset()
    if not 17 <= args.opset <= top:
        raise InputError(None, "--opset", f"must be between 17 and {top} (this torch's exporter), got {args.opset}")
    if args.cams < 1:
        raise InputError(None, "--cams", f"must be >= 1, got {args.cams}")
    kwargs = {} if args.image_size is None else {"image_size": args.image_size}
    if args.model == "bevdepth":
        kwargs["cams"] = args.cams
    spec = BUILDERS[args.model](args.checkpoint, **kwargs)
    _check_memory(spec, args)
    try:
        report = export_spec(spec, args.out, check=args.check, fp16=args.fp16, opset=args.opset)
    except ParityError as exc:
        print(f"sgde export: refused, nothing written to {args.out}: {exc}", file=sys.stderr)
        return 1
    except RuntimeError as exc:  # torch's allocator: the traced example batch is larger than this machine's memory
        if "allocate" not in str(exc):
            raise
        problem = f"{_size_text(args)} does not fit in memory for the trace; nothing written"
        raise InputError(None, "--image-size", problem) from None
    precision = "fp16" if args.fp16 else "fp32"
    print(f"wrote {report['path']} ({report['bytes'] / 2**20:.1f} MiB, {precision}, opset {args.opset})")
    print(f"  inputs:  {', '.join(spec.input_names)}")
    print(f"  outputs: {', '.join(spec.output_names)}")
    for result in report["parity"]:
        print("  " + result.line())
    if args.check:
        print(f"  check passed ({len(report['parity'])} comparisons, tolerance atol "
              f"{report['tolerance']['atol_fraction_of_range']:g} x range + rtol {report['tolerance']['rtol']:g})")
    return 0
