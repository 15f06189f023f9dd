"""Benchmark: onnxruntime (CPU) against torch eager on the same inputs, runs interleaved.

R18 reference depth net at 384x640, batch 6; the BEVDepth-style depth branch at BEVDepth's
defaults (in 512, mid 512, context 80, D 112, 256x704 input -> 16x44 features), one sample of six
cameras (six feature maps). Ratio = onnxruntime median / torch median (below 1: onnxruntime faster).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import torch

from ..export.models import build_bevdepth, build_r18
from ..export.parity import onnx_session, run_onnx
from ..export.workflow import export_spec


def _interleaved(torch_fn, ort_fn, reps: int) -> tuple[list[float], list[float]]:  # noqa: ANN001
    torch_fn()  # warm-up both (allocations, onnxruntime's first-run planning)
    ort_fn()
    t_torch, t_ort = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        torch_fn()
        t1 = time.perf_counter()
        ort_fn()
        t2 = time.perf_counter()
        t_torch.append(t1 - t0)
        t_ort.append(t2 - t1)
    return t_torch, t_ort


def _bench_spec(spec, batch: int, reps: int, workdir: Path) -> dict:  # noqa: ANN001

    path = workdir / f"{spec.name}.onnx"
    report = export_spec(spec, path)
    inputs = spec.random_inputs(batch, 0)
    session = onnx_session(path)
    module = spec.module.eval()

    def torch_fn() -> None:
        with torch.inference_mode():
            module(*inputs)

    def ort_fn() -> None:
        run_onnx(session, spec.input_names, inputs)

    t_torch, t_ort = _interleaved(torch_fn, ort_fn, reps)
    med_torch, med_ort = statistics.median(t_torch), statistics.median(t_ort)
    return {
        "input_shapes": {n: list(x.shape) for n, x in zip(spec.input_names, inputs)},
        "onnx_mib": round(report["bytes"] / 2**20, 1),
        "export_s": report["export_seconds"],
        "reps": reps,
        "torch_eager_ms": round(1000 * med_torch, 1),
        "onnxruntime_ms": round(1000 * med_ort, 1),
        "torch_eager_ms_all": [round(1000 * t, 1) for t in t_torch],
        "onnxruntime_ms_all": [round(1000 * t, 1) for t in t_ort],
        "ratio_ort_over_torch": round(med_ort / med_torch, 3),
    }


def run(fast: bool = False) -> dict:
    """Latency of both exported models in onnxruntime vs torch eager (medians, ms, and the ratio)."""
    import onnxruntime

    reps = 3 if fast else 10
    torch.manual_seed(0)
    out: dict = {"torch_threads": torch.get_num_threads(), "onnxruntime": onnxruntime.__version__,
                 "interleaved": True, "precision": "fp32"}
    with tempfile.TemporaryDirectory(prefix="sgde-bench-export-") as tmp:
        out["r18_384x640_b6"] = _bench_spec(build_r18(image_size=(384, 640)), 6, reps, Path(tmp))
        out["bevdepth_16x44_b1n6"] = _bench_spec(build_bevdepth(image_size=(256, 704), cams=6), 1, reps, Path(tmp))
    out["ratios"] = {k: out[k]["ratio_ort_over_torch"] for k in ("r18_384x640_b6", "bevdepth_16x44_b1n6")}
    out["onnxruntime_not_slower"] = all(r <= 1.0 for r in out["ratios"].values())
    return out
