"""The README's training-step example runs as written, for both supervisions, and trains the net (~5 s)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

from sgde_plugin.geometry import invert_transform
from sgde_plugin.synth.presets import preset_cameras

README = Path(__file__).resolve().parents[1] / "README.md"


def _example() -> str:
    text = README.read_text(encoding="utf-8")
    match = re.search(r"<!-- example: training-step -->\s*```python\n(.*?)```", text, re.S)
    assert match, "README lost its training-step example"
    return match.group(1)


def test_readme_training_step_runs_for_both_supervisions():
    torch.manual_seed(0)
    cams = {c.name: c.resized(96, 48) for c in preset_cameras("nuscenes")}
    camera, left, right = cams["CAM_FRONT"], cams["CAM_FRONT_LEFT"], cams["CAM_FRONT_RIGHT"]

    def to(src) -> torch.Tensor:  # target -> source at one capture, plus 0.6 m forward for the temporal ones
        return torch.tensor(invert_transform(src.sensor_to_ego) @ camera.sensor_to_ego, dtype=torch.float32)[None]

    step = torch.eye(4)
    step[2, 3] = 0.6  # a point 10 m ahead of the camera now was 10.6 m ahead at t-1
    rgb = torch.rand(1, 3, 48, 96)
    prior = torch.zeros(1, 1, 48, 96)
    prior[..., 20:30, 40:60] = 12.0
    lidar = torch.zeros(1, 1, 48, 96)
    lidar[..., 30, ::4] = 8.0
    batch = {"rgb": rgb, "prior": prior, "valid": prior > 0, "lidar": lidar,
             "rgb_prev": torch.rand(1, 3, 48, 96), "rgb_next": torch.rand(1, 3, 48, 96),
             "to_prev": step[None], "to_next": torch.linalg.inv(step)[None],
             "rgb_left": torch.rand(1, 3, 48, 96), "rgb_right": torch.rand(1, 3, 48, 96),
             "to_left": to(left), "to_right": to(right)}
    ns = {"camera": camera, "left": left, "right": right}
    exec(compile(_example(), str(README), "exec"), ns)  # noqa: S102 - the README's own code
    net = ns["net"]
    before = {k: v.clone() for k, v in net.state_dict().items()}
    for supervision in ("lidar", "self"):
        value = ns["training_step"](batch, supervision)
        assert torch.isfinite(torch.tensor(value)) and value > 0
    conv1 = net.encoder.conv1.weight
    assert not torch.equal(conv1, before["encoder.conv1.weight"])
    # the prior channel's kernel trains too (channel 3 of the widened first convolution)
    assert not torch.equal(conv1[:, 3], before["encoder.conv1.weight"][:, 3])
