"""`sgde bench stem`: cost of the prior channel on ResNet-18 at 384x640.

FLOPs are counted with ``torch.utils.flop_counter.FlopCounterMode`` (convolutions and matrix
products; 1 multiply-add = 2 FLOPs) and checked against the analytic count of the widened first
convolution. Time is forward + backward of R18 with and without the prior channel, interleaved
(A, B, A, B, ...) so drifts in machine load hit both alike; the ratio of medians is reported.
"""

from __future__ import annotations

import copy
import statistics
import time

import torch
import torchvision
from torch.utils.flop_counter import FlopCounterMode

from ..nn import DepthNet, PriorEncoding, widen_first_conv


def count_flops(fn, *args) -> int:
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


def run(fast: bool = False, height: int = 384, width: int = 640, repeats: int | None = None,
        batch: int = 1) -> dict:
    """FLOPs and interleaved forward + backward timing of R18 with / without the prior channel."""
    repeats = repeats or (3 if fast else 12)
    torch.manual_seed(0)
    base = torchvision.models.resnet18(weights=None)
    wide = widen_first_conv(copy.deepcopy(base))
    x3 = torch.rand(batch, 3, height, width)
    encode = PriorEncoding(80.0)
    prior = torch.rand(batch, 1, height, width) * 80.0

    def wide_forward(rgb: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        return wide(torch.cat([rgb, encode(p)], dim=1))

    flops_base = count_flops(base, x3)
    flops_wide = count_flops(wide_forward, x3, prior)
    analytic = conv1_extra_flops(height, width) * batch
    # the encoding is elementwise (divide, clamp, compare, multiply): ~4 FLOPs per pixel, not counted above
    encoding_flops = 4 * batch * height * width

    # the full reference depth net (encoder + monodepth2 decoder), for context
    net_base = DepthNet(use_prior=False)
    net_wide = DepthNet.with_prior_from(net_base)
    flops_net_base = count_flops(net_base.predict, x3)
    flops_net_wide = count_flops(net_wide.predict, x3, prior)

    x4 = torch.cat([x3, encode(prior)], dim=1)
    base.train()
    wide.train()
    for _ in range(2):  # warm-up
        _time_step(base, x3)
        _time_step(wide, x4)
    t_base, t_wide = [], []
    for _ in range(repeats):
        t_base.append(_time_step(base, x3))
        t_wide.append(_time_step(wide, x4))
    med_base, med_wide = statistics.median(t_base), statistics.median(t_wide)
    extra = flops_wide - flops_base
    return {
        "input_hw": [height, width],
        "batch": batch,
        "r18_gflops": round(flops_base / 1e9, 4),
        "r18_with_prior_gflops": round(flops_wide / 1e9, 4),
        "stem_extra_gflops": round(extra / 1e9, 4),
        "stem_extra_analytic_gflops": round(analytic / 1e9, 4),
        "stem_extra_pct_of_r18": round(100.0 * (extra + encoding_flops) / flops_base, 3),
        "encoding_only_pct_of_r18": round(100.0 * encoding_flops / flops_base, 4),
        "depthnet_gflops": round(flops_net_base / 1e9, 4),
        "stem_extra_pct_of_depthnet": round(100.0 * (flops_net_wide - flops_net_base + encoding_flops)
                                            / flops_net_base, 3),
        "target_flops_pct": 0.5,
        "target_flops_met": bool(100.0 * (extra + encoding_flops) / flops_base <= 0.5),
        "fwd_bwd_s_r18": round(med_base, 4),
        "fwd_bwd_s_r18_prior": round(med_wide, 4),
        "fwd_bwd_ratio": round(med_wide / med_base, 4),
        "timing": f"median of {repeats} interleaved forward+backward steps after 2 warm-ups, train mode",
        "target_ratio": 1.03,
        "target_ratio_met": bool(med_wide / med_base <= 1.03),
    }


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(fast="--fast" in sys.argv), indent=2))
