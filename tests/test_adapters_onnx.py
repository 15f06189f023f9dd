"""Both adapters export to ONNX (opset 17) and run in onnxruntime: no blocking operator (~5 s)."""

from __future__ import annotations

import numpy as np
import torch

from sgde_plugin.adapters import PriorDepthNet
from sgde_plugin.adapters.voxformer import DepthToVoxelProposals, RigDepthToVoxelProposals, VoxelGrid
from sgde_plugin.export import check_parity, export_onnx
from sgde_plugin.export.models import BEVDepthForExport, nuscenes_like_mats
from sgde_plugin.synth.presets import preset_cameras

AXES_B = {0: "batch"}


def _bev_inputs(b: int, n: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    m = nuscenes_like_mats(b, n, (32, 64))
    prior = torch.where(torch.rand(b, n, 32, 64, generator=g) < 0.2, 2 + 50 * torch.rand(b, n, 32, 64, generator=g),
                        torch.zeros(b, n, 32, 64))
    return [torch.randn(b * n, 8, 2, 4, generator=g), prior, m["intrin_mats"], m["ida_mats"],
            m["sensor2ego_mats"], m["bda_mat"]]


def test_bevdepth_branch_exports_and_matches_in_onnxruntime(tmp_path):
    torch.manual_seed(0)
    module = BEVDepthForExport(PriorDepthNet(8, 16, 4, 112)).eval()
    names = ["features", "prior", "intrin_mats", "ida_mats", "sensor2ego_mats", "bda_mat"]
    axes = {"features": {0: "bn"}, "prior": {0: "b", 1: "n"}, "intrin_mats": {0: "b", 1: "n"},
            "ida_mats": {0: "b", 1: "n"}, "sensor2ego_mats": {0: "b", 1: "n"}, "bda_mat": {0: "b"},
            "depth_logits": {0: "bn"}, "context": {0: "bn"}}
    path = export_onnx(module, _bev_inputs(2, 6, 0), tmp_path / "bev.onnx", input_names=names,
                       output_names=["depth_logits", "context"], dynamic_axes=axes)
    # other batch sizes and another camera count than at export (4 = a fisheye rig's virtual views)
    cases = [("random", 1, _bev_inputs(1, 6, 1)), ("random", 3, _bev_inputs(3, 6, 2)),
             ("random 4 cams", 2, _bev_inputs(2, 4, 3))]
    results = check_parity(path, module, cases, names, ["depth_logits", "context"])
    assert len(results) == 6 and all(r.ok for r in results)
    assert max(r.relative_to_range for r in results) < 1e-4


def _vox_inputs(cams, b: int, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    n, h, w = len(cams), cams[0].height, cams[0].width
    depth = 1 + 9 * torch.rand(b, n, h, w, generator=g)
    s2e = torch.from_numpy(np.stack([c.sensor_to_ego for c in cams])).float().expand(b, n, 4, 4).clone()
    prior = torch.where(torch.rand(b, n, h, w, generator=g) < 0.3, 1 + 9 * torch.rand(b, n, h, w, generator=g),
                        torch.zeros(b, n, h, w))
    return [depth, s2e, prior, torch.rand(b, n, h, w, generator=g)]


def test_voxformer_proposals_export_for_fisheye_and_pinhole_rigs(tmp_path):
    grid = VoxelGrid((-10.0, -10.0, -2.0), 0.5, (40, 40, 8))
    names = ["depth", "sensor_to_ego", "prior", "confidence"]
    for preset, scale in (("urban-fisheye", 0.05), ("nuscenes", 0.04)):
        cams = preset_cameras(preset, scale)
        module = RigDepthToVoxelProposals(DepthToVoxelProposals(grid), [c.intrinsics for c in cams])
        path = export_onnx(module, _vox_inputs(cams, 2, 0), tmp_path / f"{preset}.onnx", input_names=names,
                           output_names=["occupancy", "coarse_occupancy"],
                           dynamic_axes={k: AXES_B for k in (*names, "occupancy", "coarse_occupancy")})
        cases = [("random", 1, _vox_inputs(cams, 1, 1)), ("random", 3, _vox_inputs(cams, 3, 2))]
        results = check_parity(path, module, cases, names, ["occupancy", "coarse_occupancy"])
        assert all(r.max_abs_diff == 0.0 for r in results)  # same voxels, exactly
        assert all(r.output_range == 1.0 for r in results)  # and not an empty grid
