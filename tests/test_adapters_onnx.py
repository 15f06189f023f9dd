"""Both adapters export to ONNX and run in onnxruntime; BEVDepth layout, zero prior = none, the DCN (~10 s)."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from sgde_plugin.adapters import PriorDepthNet
from sgde_plugin.adapters.voxformer import DepthToVoxelProposals, RigDepthToVoxelProposals, VoxelGrid
from sgde_plugin.errors import InputError
from sgde_plugin.export import check_parity, export_onnx
from sgde_plugin.export.models import BEVDepthForExport, nuscenes_like_mats
from sgde_plugin.export.parity import onnx_session, run_onnx
from sgde_plugin.synth.presets import preset_cameras

AXES_B = {0: "batch"}


def _bev_inputs(b: int, n: int, seed: int, sweeps: int = 1) -> list[torch.Tensor]:
    """Inputs in BEVDepth's layout: matrices straight from its mats_dict, [B, sweeps, N, 4, 4]."""
    g = torch.Generator().manual_seed(seed)
    m = nuscenes_like_mats(b, n, (32, 64), sweeps=sweeps)
    prior = torch.where(torch.rand(b, n, 32, 64, generator=g) < 0.2, 2 + 50 * torch.rand(b, n, 32, 64, generator=g),
                        torch.zeros(b, n, 32, 64))
    return [torch.randn(b * n, 8, 2, 4, generator=g), prior, m["intrin_mats"], m["ida_mats"],
            m["sensor2ego_mats"], m["bda_mat"]]


NAMES = ["features", "prior", "intrin_mats", "ida_mats", "sensor2ego_mats", "bda_mat"]
MATS_AXES = {0: "b", 1: "sweeps", 2: "n"}
AXES = {"features": {0: "bn"}, "prior": {0: "b", 1: "n"}, "intrin_mats": MATS_AXES, "ida_mats": MATS_AXES,
        "sensor2ego_mats": MATS_AXES, "bda_mat": {0: "b"}, "depth_logits": {0: "bn"}, "context": {0: "bn"}}


class _NoPrior(torch.nn.Module):
    """The same branch exported without a prior input (the reference for 'zero prior = no prior')."""

    def __init__(self, net: PriorDepthNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, features, intrin_mats, ida_mats, sensor2ego_mats, bda_mat):
        mats = {"intrin_mats": intrin_mats, "ida_mats": ida_mats, "sensor2ego_mats": sensor2ego_mats,
                "bda_mat": bda_mat}
        out = self.net(features, mats)
        return out[:, : self.net.depth_channels], out[:, self.net.depth_channels:]


def test_bevdepth_branch_takes_bevdepths_matrices_and_zero_prior_is_no_prior_in_onnxruntime(tmp_path):
    torch.manual_seed(0)
    net = PriorDepthNet(8, 16, 4, 112).eval()
    module = BEVDepthForExport(net).eval()
    path = export_onnx(module, _bev_inputs(2, 6, 0), tmp_path / "bev.onnx", input_names=NAMES,
                       output_names=["depth_logits", "context"], dynamic_axes=AXES)
    model = onnx.load(str(path))
    dims = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    assert dims["intrin_mats"] == ["b", "sweeps", "n", 4, 4] and dims["bda_mat"] == ["b", 4, 4]
    # other batch sizes, BEVDepth's two-sweep mats_dict as it is, another camera count (fisheye virtual views)
    cases = [("random", 1, _bev_inputs(1, 6, 1)), ("random 2 sweeps", 3, _bev_inputs(3, 6, 2, sweeps=2)),
             ("random 4 cams", 2, _bev_inputs(2, 4, 3))]
    results = check_parity(path, module, cases, NAMES, ["depth_logits", "context"])
    assert len(results) == 6 and all(r.ok for r in results)
    assert max(r.relative_to_range for r in results) < 1e-4
    # an all-zero prior is exactly no prior: bit-identical to a graph exported without the prior input
    ref_path = export_onnx(_NoPrior(net).eval(), [t for i, t in enumerate(_bev_inputs(2, 6, 0)) if i != 1],
                           tmp_path / "noprior.onnx", input_names=[n for n in NAMES if n != "prior"],
                           output_names=["depth_logits", "context"], dynamic_axes=AXES)
    inputs = _bev_inputs(1, 6, 4, sweeps=2)
    inputs[1] = torch.zeros_like(inputs[1])
    zero = run_onnx(onnx_session(path), NAMES, inputs)
    none = run_onnx(onnx_session(ref_path), [n for n in NAMES if n != "prior"], inputs[:1] + inputs[2:])
    assert all(np.array_equal(a, b) for a, b in zip(zero, none))
    with torch.no_grad():  # and equal to torch without a prior, within the export tolerance
        ref = net(inputs[0], dict(zip(NAMES[2:], inputs[2:])))
    assert np.abs(zero[0] - ref[:, :112].numpy()).max() < 1e-4 * float(ref.max() - ref.min())


def test_bevdepths_deformable_convolution_exports_as_opset_19_deformconv_or_is_refused(tmp_path):
    torch.manual_seed(0)
    net = PriorDepthNet(8, 16, 4, 112, deformable=True).eval()
    with torch.no_grad():  # trained-looking offsets of about a pixel, not the all-zero start
        net.depth_conv[4].conv_offset.weight.normal_(0.0, 0.1)
    module = BEVDepthForExport(net).eval()
    with pytest.raises(InputError, match="opset >= 19") as err:
        export_onnx(module, _bev_inputs(2, 6, 0), tmp_path / "dcn17.onnx", input_names=NAMES,
                    output_names=["depth_logits", "context"], dynamic_axes=AXES, opset=17)
    assert "\n" not in str(err.value) and not (tmp_path / "dcn17.onnx").exists()
    path = export_onnx(module, _bev_inputs(2, 6, 0), tmp_path / "dcn.onnx", input_names=NAMES,
                       output_names=["depth_logits", "context"], dynamic_axes=AXES, opset=19)
    assert "DeformConv" in {n.op_type for n in onnx.load(str(path)).graph.node}
    offsets = net.depth_conv[4].conv_offset(net.depth_conv[:4](torch.randn(6, 16, 2, 4)))
    assert offsets.abs().mean().item() > 0.1  # the check below really moves the sampling points
    results = check_parity(path, module, [("random", 1, _bev_inputs(1, 6, 1)),
                                          ("random 2 sweeps", 2, _bev_inputs(2, 6, 2, sweeps=2))],
                           NAMES, ["depth_logits", "context"])
    assert all(r.ok for r in results) and max(r.relative_to_range for r in results) < 1e-4


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
