"""`sgde bench learned`: cost of a learned matcher per six-camera rig frame on this machine, load included.

No weights are shipped or downloaded, so the networks run with random weights (the cost of a forward
pass does not depend on the weights): torchvision's RAFT optical-flow models (`raft_small`,
`raft_large`, 12 updates), members of RAFT-Stereo's family, stand in for it through the `torch` matcher
path (state dict + `matcher_arch`). With `SGDE_BENCH_RAFT_STEREO=CKPT` and the official RAFT-Stereo
checkout on PYTHONPATH, the official model is measured too (`--matcher raft-stereo`, 32 iterations).

The frame: synthetic nuScenes, 6 x 1600x900, matching at scale 0.5 (the default), true extrinsics,
run as one `sgde prior --workers 1` worker does (torch threads: `torch_threads_per_worker(1)`: all CPUs when
idle, 1 on a busy machine). `--fast`: 800x450 cameras, two frames.
Reported: model load + first frame, steady seconds per frame, the matcher's share, the peak resident
memory of the process, and the load average.
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..cache.build import torch_threads_per_worker
from ..readers.detect import load_rig
from ..rig import Rig, load_frame_images, read_rig_json
from ..stereo.config import PriorConfig
from ..stereo.pipeline import PriorBuilder
from ..synth.sequence import write_synth

MODELS = {"raft_small": "torchvision.models.optical_flow:raft_small",
          "raft_large": "torchvision.models.optical_flow:raft_large"}


def _measure(rig: Rig, config: PriorConfig, frames: int) -> dict[str, Any]:
    """Model load, first-frame and steady per-frame seconds of PriorBuilder with `config`."""
    previous = torch.get_num_threads()
    torch.set_num_threads(torch_threads_per_worker(1))
    try:
        images = [load_frame_images(rig, f.id) for f in rig.frames[:frames]]
        t0 = time.perf_counter()
        builder = PriorBuilder(rig, config)
        load_s = time.perf_counter() - t0
        times, match = [], []
        for frame in images:
            t0 = time.perf_counter()
            out = builder.build(frame)
            times.append(time.perf_counter() - t0)
            match.append(builder.last_timings["match"])
        valid = int(sum(int(np.count_nonzero(m.depth)) for m in out.values()))
    finally:
        torch.set_num_threads(previous)
    steady = times[1:] or times
    return {
        "setup_and_load_s": round(load_s, 2),
        "first_frame_s": round(times[0], 2),
        "seconds_per_frame": round(sum(steady) / len(steady), 2),
        "matcher_share": round(sum(match[1:] or match) / sum(steady), 3),
        "pairs": len(builder.plans),
        "canvases": [list(p.pair.size) for p in builder.plans],
        "valid_pixels_last_frame": valid,
        "torch_threads": torch_threads_per_worker(1),
    }


def run(fast: bool = False) -> dict[str, Any]:
    """Seconds per six-camera frame of RAFT-family matchers (random weights) through the prior pipeline."""
    frames = 2 if fast else 3
    names = list(MODELS)
    result: dict[str, Any] = {"load_average_before": [round(x, 2) for x in os.getloadavg()], "frames": frames,
                              "scale": 0.5, "image_size": "1600x900" if not fast else "800x450", "models": {}}
    with tempfile.TemporaryDirectory() as tmp:
        root = write_synth("nuscenes", frames, Path(tmp) / "nus", scale=0.5 if fast else 1.0)
        true = read_rig_json(root / "rig_true.json")
        rig = load_rig(str(root)).with_extrinsics({c.name: c.sensor_to_ego for c in true.cameras})
        for name in names:
            import torchvision.models.optical_flow as flow_models

            torch.manual_seed(0)
            ckpt = Path(tmp) / f"{name}.pt"
            torch.save(getattr(flow_models, name)().state_dict(), ckpt)
            config = PriorConfig.from_settings(matcher="torch", matcher_path=str(ckpt), matcher_arch=MODELS[name],
                                               matcher_input_scale=1 / 127.5, matcher_flow_output=True)
            result["models"][name] = _measure(rig, config, frames)
        official = os.environ.get("SGDE_BENCH_RAFT_STEREO")
        if official:
            config = PriorConfig.from_settings(matcher="raft-stereo", matcher_path=official)
            result["models"]["raft-stereo (official)"] = _measure(rig, config, frames)
    result["peak_rss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 2)
    result["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    return result


__all__ = ["MODELS", "run"]
