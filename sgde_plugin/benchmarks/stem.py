"""`sgde bench stem`: cost of the prior channel on ResNet-18 at 384x640, for the paper's full widening
of conv1 and the factored and low-rank stems (``sgde_plugin.nn.stem``).

FLOPs are counted with ``torch.utils.flop_counter.FlopCounterMode`` (convolutions and matrix
products; 1 multiply-add = 2 FLOPs) and checked against the analytic count of the widened first
convolution. Time is forward + backward of R18 with and without the prior channel, interleaved
(A, B, A, B, ...) so drifts in machine load hit both alike; the ratio of medians is reported.
"""

from __future__ import annotations

import copy
import os
import statistics
import time
from collections.abc import Callable

import torch
import torchvision
from torch.utils.flop_counter import FlopCounterMode

from ..nn import DepthNet, PriorEncoding, widen_first_conv

TARGET_FLOPS_PCT = 0.5
TARGET_RATIO = 1.03


def count_flops(fn: Callable[..., object], *args: torch.Tensor) -> int:
    """Total FLOPs of one call of ``fn(*args)`` as counted by torch's FLOP counter."""
    with FlopCounterMode(display=False) as counter:
        fn(*args)
    return int(counter.get_total_flops())


def conv1_extra_flops(height: int, width: int, extra_channels: int = 1) -> int:
    """Analytic FLOPs added by widening ResNet's 7x7/2, 64-channel conv1 by ``extra_channels`` inputs."""
    h_out, w_out = (height + 2 * 3 - 7) // 2 + 1, (width + 2 * 3 - 7) // 2 + 1
    return 2 * h_out * w_out * 64 * 7 * 7 * extra_channels


def _time_step(model: torch.nn.Module, x: torch.Tensor) -> float:
    t0 = time.perf_counter()
    out = model(x)
    out.float().sum().backward()
    dt = time.perf_counter() - t0
    model.zero_grad(set_to_none=True)
    return dt


def elementwise_flops(batch: int, height: int, width: int, mode: str, out_channels: int = 64) -> int:
    """FLOPs the counter does not see: the prior encoding (~4 per pixel); for the factored stem the
    fold's multiply-add into three RGB channels; for both cheap stems the add of the low-rank term to
    conv1's output."""
    flops = 4 * batch * height * width
    if mode == "factored":
        flops += 2 * 3 * batch * height * width
    if mode in ("factored", "lowrank"):
        flops += batch * out_channels * ((height + 1) // 2) * ((width + 1) // 2)
    return flops


def run(fast: bool = False, height: int = 384, width: int = 640, repeats: int | None = None,
        batch: int = 1) -> dict:
    """FLOPs and interleaved forward + backward timing of R18 without / with the prior channel, for
    the paper's full widening and the factored and low-rank stems (at their default rank, as
    ``DepthNet(stem=...)`` builds them)."""
    repeats = repeats or (3 if fast else 31)
    torch.manual_seed(0)
    base = torchvision.models.resnet18(weights=None)
    wide = {"full": widen_first_conv(copy.deepcopy(base)),
            "factored": widen_first_conv(copy.deepcopy(base), mode="factored"),
            "lowrank": widen_first_conv(copy.deepcopy(base), mode="lowrank")}
    x3 = torch.rand(batch, 3, height, width)
    encode = PriorEncoding(80.0)
    prior = torch.rand(batch, 1, height, width) * 80.0
    x4 = torch.cat([x3, encode(prior)], dim=1)

    flops_base = count_flops(base, x3)
    result: dict = {"input_hw": [height, width], "batch": batch,
                    "factored_rank": wide["factored"].conv1.mix.in_channels,
                    "r18_gflops": round(flops_base / 1e9, 4),
                    "full_extra_analytic_gflops": round(conv1_extra_flops(height, width) * batch / 1e9, 4)}
    # the full reference depth net (encoder + monodepth2 decoder), for context
    net_base = DepthNet(use_prior=False)
    flops_net_base = count_flops(net_base.predict, x3)
    result["depthnet_gflops"] = round(flops_net_base / 1e9, 4)
    for mode, model in wide.items():
        extra = count_flops(model, x4) - flops_base + elementwise_flops(batch, height, width, mode)
        net_wide = DepthNet.with_prior_from(net_base, stem=mode)
        extra_net = count_flops(net_wide.predict, x3, prior) - flops_net_base + elementwise_flops(
            batch, height, width, mode)
        result[mode] = {"extra_gflops": round(extra / 1e9, 4),
                        "extra_pct_of_r18": round(100.0 * extra / flops_base, 3),
                        "extra_pct_of_depthnet": round(100.0 * extra_net / flops_net_base, 3)}

    models = {"r18": (base, x3), **{mode: (model, x4) for mode, model in wide.items()}}
    for m, _ in models.values():
        m.train()
    for _ in range(2):  # warm-up
        for m, x in models.values():
            _time_step(m, x)
    times: dict[str, list[float]] = {k: [] for k in models}
    for _ in range(repeats):
        for k, (m, x) in models.items():
            times[k].append(_time_step(m, x))
    med = {k: statistics.median(v) for k, v in times.items()}
    result["fwd_bwd_s"] = {k: round(v, 4) for k, v in med.items()}
    for mode in wide:
        # the median of per-round ratios: each round times the models back to back, so a change of
        # machine load between rounds cancels out
        paired = statistics.median(a / b for a, b in zip(times[mode], times["r18"], strict=True))
        result[mode]["fwd_bwd_ratio"] = round(paired, 4)
        result[mode]["fwd_bwd_ratio_of_medians"] = round(med[mode] / med["r18"], 4)
        result[mode]["meets_targets"] = bool(result[mode]["extra_pct_of_r18"] <= TARGET_FLOPS_PCT
                                             and result[mode]["fwd_bwd_ratio"] <= TARGET_RATIO)
    result["timing"] = (f"{repeats} rounds of forward+backward steps (r18, full, factored, lowrank) after 2 "
                        "warm-ups, train mode; ratio = median over rounds of the per-round ratio")
    result["targets"] = {"extra_pct_of_r18": TARGET_FLOPS_PCT, "fwd_bwd_ratio": TARGET_RATIO}
    result["load_average"] = round(os.getloadavg()[0], 2)
    return result


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(fast="--fast" in sys.argv), indent=2))
