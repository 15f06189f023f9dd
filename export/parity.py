"""Parity of an exported ONNX file against its torch module, run in onnxruntime on the CPU.

Criterion per output: |onnx - torch| <= atol + rtol * |torch| everywhere, with atol a fraction of
the torch output's range (max - min). fp32: atol = 1e-4 * range, rtol = 1e-3. fp16 (float16
weights and arithmetic, float32 I/O) is compared with the float32 torch module, so its tolerance
covers half-precision rounding through the whole net: atol = 1e-2 * range, rtol = 1e-2. A failed
comparison raises ParityError carrying every measured number.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

if TYPE_CHECKING:  # onnxruntime loads only when a session is made
    import onnxruntime as ort

FP32_TOLERANCE = (1e-4, 1e-3)  # (atol as a fraction of the output range, rtol)
FP16_TOLERANCE = (1e-2, 1e-2)


@dataclass(frozen=True)
class ParityResult:
    """One output of one case: measured differences against the tolerance."""

    case: str
    batch: int
    output: str
    max_abs_diff: float
    output_range: float
    atol: float
    rtol: float
    worst_excess: float  # max of |diff| - (atol + rtol |ref|); <= 0 means within tolerance
    ok: bool

    @property
    def relative_to_range(self) -> float:
        """max |diff| / output range."""
        return self.max_abs_diff / self.output_range if self.output_range > 0 else float(self.max_abs_diff > 0)

    def line(self) -> str:
        """One human-readable line."""
        verdict = "ok" if self.ok else "FAIL"
        return (f"{self.case:>10} batch {self.batch:<2} {self.output:<13} max|diff| {self.max_abs_diff:.3g} "
                f"range {self.output_range:.3g} ({self.relative_to_range:.2e} of range; "
                f"tol atol {self.atol:.3g} + rtol {self.rtol:g}) {verdict}")


class ParityError(RuntimeError):
    """ONNX and torch outputs differ beyond tolerance; ``results`` hold all the numbers."""

    def __init__(self, results: Sequence[ParityResult]) -> None:
        self.results = list(results)
        bad = [r for r in self.results if not r.ok]
        super().__init__("ONNX output differs from torch beyond tolerance:\n" + "\n".join(r.line() for r in bad))


def onnx_session(path: str | Path, threads: int | None = None) -> ort.InferenceSession:
    """A CPU onnxruntime session for ``path``."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads is not None:
        opts.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


def run_onnx(session: ort.InferenceSession, names: Sequence[str], inputs: Sequence[Tensor]) -> list[np.ndarray]:
    """Run a session on torch inputs (fed by name, in order) -> numpy outputs."""
    return session.run(None, {n: x.detach().cpu().numpy() for n, x in zip(names, inputs)})


def run_torch(module: nn.Module, inputs: Sequence[Tensor]) -> list[np.ndarray]:
    """Run a module in eval mode without gradients -> numpy outputs (a tuple output becomes a list)."""
    with torch.no_grad():
        out = module.eval()(*inputs)
    outs = [out] if isinstance(out, Tensor) else list(out)
    return [o.detach().float().cpu().numpy() for o in outs]


def compare(
    case: str, batch: int, names: Sequence[str], reference: Sequence[np.ndarray], candidate: Sequence[np.ndarray],
    tolerance: tuple[float, float] = FP32_TOLERANCE,
) -> list[ParityResult]:
    """Compare candidate outputs with the reference ones, output by output."""
    results = []
    frac, rtol = tolerance
    for name, ref, cand in zip(names, reference, candidate):
        if ref.shape != cand.shape:
            raise ParityError([ParityResult(case, batch, f"{name} shape {cand.shape} != {ref.shape}",
                                            float("inf"), 0.0, 0.0, rtol, float("inf"), False)])
        ref64, cand64 = ref.astype(np.float64), cand.astype(np.float64)
        diff = np.abs(cand64 - ref64)
        rng = float(ref64.max() - ref64.min()) if ref64.size else 0.0
        atol = frac * rng
        excess = float((diff - (atol + rtol * np.abs(ref64))).max()) if diff.size else 0.0
        finite = bool(np.isfinite(cand64).all())
        results.append(ParityResult(case, batch, name, float(diff.max()) if diff.size else 0.0, rng, atol, rtol,
                                    excess, finite and excess <= 0.0))
    return results


def check_parity(
    path: str | Path,
    module: nn.Module,
    cases: Sequence[tuple[str, int, Sequence[Tensor]]],
    input_names: Sequence[str],
    output_names: Sequence[str],
    tolerance: tuple[float, float] = FP32_TOLERANCE,
    raise_on_failure: bool = True,
) -> list[ParityResult]:
    """Run ``path`` in onnxruntime and ``module`` in torch on every (case, batch, inputs).

    Raises ParityError (with all the numbers) if any output of any case is out of tolerance.
    """
    session = onnx_session(path)
    results: list[ParityResult] = []
    for case, batch, inputs in cases:
        ref = run_torch(module, inputs)
        got = run_onnx(session, input_names, inputs)
        results += compare(case, batch, output_names, ref, got, tolerance)
    if raise_on_failure and not all(r.ok for r in results):
        raise ParityError(results)
    return results
