"""Export one model spec to ONNX and, optionally, prove it against torch before the file appears."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from sgde_plugin.io import atomic_path

from .models import ExportSpec
from .onnx import DEFAULT_OPSET, export_onnx
from .parity import FP16_TOLERANCE, FP32_TOLERANCE, ParityResult, check_parity

TRACE_BATCH = 2  # batch of the example inputs; checks run at 1 and 6 to prove the batch axis is dynamic
CHECK_BATCHES = (1, 6)

# Peak resident memory of `sgde export onnx` as (bytes, bytes per megapixel of the example images: one image for
# r18, all cameras for bevdepth), fitted from above to /usr/bin/time's maximum RSS (session 27, torch 2.14.1 on the
# CPU, fp32). r18: 1.16 / 1.90 / 4.55 / 15.72 GB at 0.25 / 1.05 / 4.19 / 16.8 Mpx, with --check 1.93 / 4.69 / 16.67
# GB at the first three; bevdepth (6 cameras): 1.49 / 3.53 / 9.00 GB at 1.08 / 8.65 / 25.2 Mpx, with --check
# 3.05 / 17.78 GB at the first two (the check runs batch 6 in torch and onnxruntime).
PEAK_BYTES = {
    ("r18", False): (1.0e9, 0.9e9),
    ("r18", True): (1.2e9, 3.9e9),
    ("bevdepth", False): (1.2e9, 0.32e9),
    ("bevdepth", True): (1.0e9, 2.0e9),
}
FP16_EXTRA_BYTES = 0.4e9  # r18 at 1024x1024 with --fp16: 2.22 GB against fp32's 1.90 (4.58 against 4.69 with --check)


def parity_cases(spec: ExportSpec, batches: tuple[int, ...] = CHECK_BATCHES) -> list[tuple[str, int, list[Tensor]]]:
    """Seeded random inputs and a synthetic frame at each batch size (plus another image size for r18).

    The synthetic frame is rendered by ``sgde_plugin.synth`` (labelled "rendered"), or generated
    procedurally when the renderer is unavailable (labelled "generated").
    """
    cases: list[tuple[str, int, list[Tensor]]] = []
    for i, b in enumerate(batches):
        cases.append(("random", b, list(spec.random_inputs(b, 1000 + i))))
        label, inputs = spec.synthetic_inputs(b)
        cases.append((label, b, list(inputs)))
    if spec.name == "r18":
        h, w = spec.extra["image_size"]
        other = (h + 64, max(64, w - 128))  # the image size is a dynamic axis of the R18 graph
        cases.append((f"random {other[0]}x{other[1]}", 2, _random_image_and_prior(2, other)))
    return cases


def _random_image_and_prior(batch: int, size: tuple[int, int]) -> list[Tensor]:
    """Seeded random RGB in [0, 1] and a 30 %-dense prior (1-61 m) at ``size``."""
    g = torch.Generator().manual_seed(7)
    h, w = size
    image = torch.rand(batch, 3, h, w, generator=g)
    prior = torch.where(torch.rand(batch, 1, h, w, generator=g) < 0.3,
                        1.0 + 60.0 * torch.rand(batch, 1, h, w, generator=g), torch.zeros(batch, 1, h, w))
    return [image, prior]


def estimated_peak_bytes(spec: ExportSpec, check: bool, fp16: bool = False) -> int:
    """Peak memory that exporting ``spec`` (and, with ``check``, proving it) is expected to take."""
    h, w = spec.extra["image_size"]
    megapixels = h * w * spec.extra.get("cams", 1) / 1e6
    base, per_megapixel = PEAK_BYTES[(spec.name, check)]
    return int(base + per_megapixel * megapixels + (FP16_EXTRA_BYTES if fp16 else 0))


def export_spec(
    spec: ExportSpec,
    out: str | Path,
    *,
    check: bool = False,
    fp16: bool = False,
    opset: int = DEFAULT_OPSET,
    batches: tuple[int, ...] = CHECK_BATCHES,
) -> dict[str, Any]:
    """Export ``spec`` to ``out``; with ``check`` run the parity cases first and keep no file on failure.

    Returns a report: path, size, names, timings and (with ``check``) every parity result.
    """
    out = Path(out)
    report: dict[str, Any] = {"model": spec.name, "path": str(out), "fp16": fp16, "opset": opset,
                              "inputs": list(spec.input_names), "outputs": list(spec.output_names)}
    results: list[ParityResult] = []
    with atomic_path(out) as tmp:
        t0 = time.perf_counter()
        export_onnx(spec.module, spec.random_inputs(TRACE_BATCH, 0), tmp, input_names=spec.input_names,
                    output_names=spec.output_names, dynamic_axes=spec.dynamic_axes, metadata=spec.metadata,
                    opset=opset, fp16=fp16)
        report["export_seconds"] = round(time.perf_counter() - t0, 2)
        if check:
            t0 = time.perf_counter()
            tolerance = FP16_TOLERANCE if fp16 else FP32_TOLERANCE
            results = check_parity(tmp, spec.module, parity_cases(spec, batches), spec.input_names,
                                   spec.output_names, tolerance)
            report["check_seconds"] = round(time.perf_counter() - t0, 2)
            report["tolerance"] = {"atol_fraction_of_range": tolerance[0], "rtol": tolerance[1]}
        report["bytes"] = tmp.stat().st_size
    report["parity"] = results
    return report
