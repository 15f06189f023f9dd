"""Matchers: SGBM recovers known shifts, sub-pixel refinement removes pixel locking, and the learned-matcher
adapter runs a tiny stand-in network as a state dict, TorchScript, ONNX and a torch.export archive with identical
results.

Runtime: about 8 s on 2 cores.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from cache_fixtures import tiny_rig
from stereo_scene import _texture

from sgde_plugin.cache.build import build_cache
from sgde_plugin.errors import InputError
from sgde_plugin.stereo.filters import refine_disparity
from sgde_plugin.stereo.matchers import OnnxMatcher, SGBMMatcher, TorchMatcher, load_learned_matcher
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.rectify import torch_threads


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Element-wise camera maths gains nothing from threads, and OpenMP threads crawl on a busy machine."""
    with torch_threads(1):
        yield


class TinyMatcher(torch.nn.Module):
    """Stand-in learned matcher: box-filtered absolute-difference cost volume and a soft arg-min."""

    def __init__(self, disparities: int = 16):
        super().__init__()
        self.disparities = disparities
        self.sharpness = torch.nn.Parameter(torch.tensor(1.0))

    def disparity(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        w = left.shape[-1]
        costs = []
        for d in range(self.disparities):
            shifted = F.pad(right[..., : w - d], (d, 0)) if d else right
            costs.append(F.avg_pool2d((left - shifted).abs().mean(1, keepdim=True), 5, 1, 2))
        cost = torch.cat(costs, 1)
        p = torch.softmax(-cost * self.sharpness * 4.0, dim=1)
        return (p * torch.arange(self.disparities, dtype=left.dtype).view(1, -1, 1, 1)).sum(1, keepdim=True)

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
        return self.disparity(left, right)


class TinyFlowMatcher(TinyMatcher):
    """The same, answering like RAFT-Stereo: a list of flows whose x component is minus the disparity."""

    def forward(self, left: torch.Tensor, right: torch.Tensor) -> list[torch.Tensor]:
        d = self.disparity(left, right)
        return [torch.cat([-d, torch.zeros_like(d)], 1)]


def tiny_factory() -> TinyMatcher:
    """Factory for `matcher_arch` (imported by name in the test)."""
    return TinyMatcher(16)


def _pair(shift: float, h: int = 64, w: int = 96, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A textured left image and the right image seeing it `shift` px further left (disparity = shift)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(float)

    def img(dx: float) -> np.ndarray:
        acc = np.zeros((h, w))
        for i in range(4):
            for j in range(4):  # 4x4 supersampling of the pixel area
                acc += _texture((xs + (i + 0.5) / 4 - 0.5 + dx) * 0.05, (ys + (j + 0.5) / 4 - 0.5) * 0.05, seed)
        return np.clip(acc / 16 * 255 + 0.5, 0, 255).astype(np.uint8)

    return img(0.0), img(shift)


@pytest.mark.parametrize("shift", [6.0, 11.0])
def test_sgbm_recovers_integer_shifts(shift):
    left, right = _pair(shift, 80, 160)
    disp, conf = SGBMMatcher().match(left, right, 32)
    ok = conf > 0
    ok[:, :40] = False  # the first numDisparities columns have no full search range
    assert ok.sum() > 0.5 * ok[:, 40:].size
    assert abs(np.median(disp[ok]) - shift) < 0.05
    assert np.all(disp[~(conf > 0)] == 0)
    with pytest.raises(ValueError):
        SGBMMatcher().match(left, right, 20)


@pytest.mark.parametrize("shift", [8.3, 8.75])
def test_refinement_removes_pixel_locking(shift):
    left, right = _pair(shift, 80, 160)
    disp, conf = SGBMMatcher().match(left, right, 32)
    ok = conf > 0
    ok[:, :40] = False
    ok[:, -8:] = False
    bias_before = (disp[ok] - shift).mean()
    refined = refine_disparity(left.astype(np.float32), right.astype(np.float32), disp, ok, -1, 0, iterations=1)
    err = refined[ok] - shift
    assert abs(bias_before) > 0.08  # SGBM alone is pulled towards the integer
    assert abs(err.mean()) < 0.02 and np.abs(err).mean() < 0.5 * np.abs(disp[ok] - shift).mean()


@pytest.fixture(scope="module")
def tiny_files(tmp_path_factory):
    """The stand-in network as a state dict, a TorchScript file and an ONNX file."""
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("matchers")
    net = TinyMatcher(16).eval()
    with torch.no_grad():
        net.sharpness.fill_(2.0)  # a trained value the state dict must carry
    torch.save(net.state_dict(), folder / "tiny.pt")
    example = (torch.rand(1, 3, 64, 96) * 255, torch.rand(1, 3, 64, 96) * 255)
    torch.jit.trace(net, example).save(str(folder / "tiny_script.pt"))
    axes = {name: {0: "batch", 2: "height", 3: "width"} for name in ("left", "right", "disp")}
    torch.onnx.export(net, example, str(folder / "tiny.onnx"), input_names=["left", "right"], output_names=["disp"],
                      opset_version=17, dynamo=False, dynamic_axes=axes)
    return folder


def test_learned_matcher_adapter_state_dict_torchscript_and_onnx_agree(tiny_files):
    left, right = _pair(5.0)
    from_state = TorchMatcher.from_state_dict(tiny_factory, tiny_files / "tiny.pt")
    assert float(from_state.module.sharpness.detach()) == 2.0
    scripted = load_learned_matcher(tiny_files / "tiny_script.pt")
    onnx = load_learned_matcher(tiny_files / "tiny.onnx")
    assert isinstance(scripted, TorchMatcher) and isinstance(onnx, OnnxMatcher)
    results = [m.match(left, right, 16) for m in (from_state, scripted, onnx)]
    d0 = results[0][0]
    inner = np.s_[:, 20:-4]
    assert abs(np.median(d0[inner]) - 5.0) < 0.1
    for d, c in results[1:]:
        assert np.abs(d - d0).max() < 1e-3
        assert c.min() >= 0 and c.max() == 1.0
    # grey input is replicated to three channels: RGB of the same grey gives the same answer
    rgb = scripted.match(np.repeat(left[..., None], 3, 2), np.repeat(right[..., None], 3, 2), 16)[0]
    assert np.abs(rgb - d0).max() < 1e-4
    # an image that needs padding (to multiples of 32) is cropped back
    assert scripted.match(left[:50, :70], right[:50, :70], 16)[0].shape == (50, 70)
    via_arch = load_learned_matcher(tiny_files / "tiny.pt", arch="test_stereo_matchers:tiny_factory")
    assert np.abs(via_arch.match(left, right, 16)[0] - d0).max() < 1e-5


def test_flow_output_convention_and_refusals(tiny_files):
    left, right = _pair(4.0)
    flow = TorchMatcher(TinyFlowMatcher(16).eval(), flow_output=True)
    d, _ = flow.match(left, right, 16)
    assert abs(np.median(d[:, 20:-4]) - 4.0) < 0.1
    with pytest.raises(InputError, match="state dict"):
        load_learned_matcher(tiny_files / "tiny.pt")
    with pytest.raises(InputError, match="not found"):
        load_learned_matcher(tiny_files / "missing.onnx")


def test_prior_builder_runs_a_learned_matcher(tiny_files, tmp_path):
    from test_stereo_prior import pinhole_scene

    rig, images, depths = pinhole_scene()
    path = tmp_path / "wide.pt"
    example = (torch.rand(1, 3, 64, 128) * 255, torch.rand(1, 3, 64, 128) * 255)
    torch.jit.trace(TinyMatcher(48).eval(), example).save(str(path))  # the pair searches 48 px
    config = PriorConfig.from_settings(matcher="torch", matcher_path=str(path))
    assert config.to_dict()["matcher_sha256"]
    with torch_threads(1):  # OpenMP threads crawl when the machine is busy (see rectify.torch_threads)
        out = PriorBuilder(rig, config).build(images)
    prior, gt = out["FRONT"].depth, depths["FRONT"]
    ok = (prior > 0) & (gt > 0)
    assert ok.sum() > 1000
    assert np.median(np.abs(prior[ok] - gt[ok]) / gt[ok]) < 0.02


def test_a_torch_export_archive_runs_like_the_module_and_a_bad_one_is_one_line(tiny_files, tmp_path):
    torch.manual_seed(0)
    net = TinyMatcher(16).eval()
    with torch.no_grad():
        net.sharpness.fill_(2.0)
    example = (torch.rand(2, 3, 128, 96) * 255, torch.rand(2, 3, 128, 96) * 255)
    height, width = torch.export.Dim("height", min=96, max=4096), torch.export.Dim("width", min=64, max=4096)
    sides = {0: torch.export.Dim("batch", max=16), 2: height, 3: width}
    torch.export.save(torch.export.export(net, example, dynamic_shapes={"left": sides, "right": sides}),
                      tmp_path / "tiny.pt2")
    left, right = _pair(5.0, 128, 96)
    exported = load_learned_matcher(tmp_path / "tiny.pt2")
    d, c = exported.match(left, right, 16)
    d0 = TorchMatcher(net).match(left, right, 16)[0]
    assert np.abs(d - d0).max() < 1e-4 and abs(np.median(d[:, 20:-4]) - 5.0) < 0.1 and c.max() == 1.0
    assert exported.match(left[:100, :70], right[:100, :70], 16)[0].shape == (100, 70)  # another canvas size
    with pytest.raises(InputError, match="refuses inputs of shape"):  # 64 rows: under the exported minimum
        exported.match(left[:64], right[:64], 16)
    with pytest.raises(InputError, match="exported with"):
        load_learned_matcher(tmp_path / "tiny.pt2", iters=4)
    torch.export.save(torch.export.export(net, example), tmp_path / "fixed.pt2")
    with pytest.raises(InputError, match="fixed left height 128.*must be dynamic"):
        load_learned_matcher(tmp_path / "fixed.pt2")
    data = (tmp_path / "tiny.pt2").read_bytes()
    (tmp_path / "cut.pt2").write_bytes(data[: len(data) // 2])
    (tmp_path / "script.pt2").write_bytes((tiny_files / "tiny_script.pt").read_bytes())  # a zip, not an archive
    for bad, problem in (("cut.pt2", "not a zip file"), ("script.pt2", "not a readable torch.export archive")):
        with pytest.raises(InputError, match=problem) as err:
            load_learned_matcher(tmp_path / bad)
        assert bad in str(err.value) and "\n" not in str(err.value)
    # a cache build refuses a matcher file that does not load before the cache exists
    for bad in ("fixed.pt2", "cut.pt2"):
        config = PriorConfig.from_settings(matcher="torch", matcher_path=str(tmp_path / bad))
        with pytest.raises(InputError, match=bad):
            build_cache(tiny_rig(1), tmp_path / f"cache_{bad}", config, show_progress=False)
        assert not (tmp_path / f"cache_{bad}").exists()
