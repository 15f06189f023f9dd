"""Learned matchers through `sgde prior`: a stand-in with RAFT-Stereo's exact I/O imported as `core.raft_stereo`
from a "checkout" on the path, ONNX models with dynamic and fixed shapes, fingerprints of model files and
architecture code, batching, devices, workers and threads.

The RAFT-Stereo stand-in answers every rectified input with the TRUE disparity (looked up in a table the
test computes from the synthetic ground truth with the pipeline's own rectification), in RAFT's flow form,
so the prior it gives measures the conventions (sign, padding, cropping, mirroring, back-projection), not
a network. Runtime ~25 s on 2 cores.
"""

from __future__ import annotations

import json
import sys
import textwrap

import cv2
import numpy as np
import onnx
import pytest
import torch

from sgde_plugin.cache.build import build_cache, default_workers, torch_threads_per_worker, usable_cpus
from sgde_plugin.cache.fingerprints import config_document, digest
from sgde_plugin.cli import main as cli_main
from sgde_plugin.commands.prior import load_rig_with_override
from sgde_plugin.errors import InputError
from sgde_plugin.rig import load_frame_images
from sgde_plugin.stereo.matchers import OnnxMatcher, TorchMatcher, network_input
from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig
from sgde_plugin.stereo.rectify import torch_threads

STAND_IN = '''
"""Stand-in for RAFT-Stereo's core/raft_stereo.py: the official constructor and forward, true disparities."""
import os

import numpy as np
import torch

CALLS = []


def thumbnail(image):
    """(3, H, W) array -> mean of 8x8 blocks of the channel mean."""
    g = image.mean(0)
    h, w = g.shape
    return g.reshape(h // 8, 8, w // 8, 8).mean(axis=(1, 3)).ravel()


class RAFTStereo(torch.nn.Module):
    def __init__(self, args):
        super().__init__()
        self.args = args
        self.fnet = torch.nn.Conv2d(3, 8, 1)
        self.update_block = torch.nn.Conv2d(8, 2, 1)
        self.table = None

    def forward(self, image1, image2, iters=12, flow_init=None, test_mode=False):
        if self.table is None:
            t = np.load(os.environ["SGDE_TEST_ORACLE"])
            n = len([k for k in t.files if k.startswith("d")])
            self.table = [(t[f"t{i}"], t[f"d{i}"]) for i in range(n)]
        a = image1.cpu().numpy()
        CALLS.append({"shape": tuple(a.shape), "iters": iters, "test_mode": test_mode,
                      "rgb": bool(np.abs(a[:, 0] - a[:, 1]).max() > 0), "max": float(a.max())})
        out = []
        for img in a:
            key = thumbnail(img)
            fits = [(np.abs(t - key).mean(), i) for i, (t, d) in enumerate(self.table) if d.shape == img.shape[1:]]
            out.append(self.table[min(fits)[1]][1])
        disp = torch.from_numpy(np.stack(out))[:, None].float()
        flow_up = disp if getattr(self.args, "flip_sign", False) else -disp
        if test_mode:
            return flow_up[..., ::4, ::4], flow_up
        return [flow_up] * iters
'''


@pytest.fixture(autouse=True)
def _one_torch_thread():
    with torch_threads(1):
        yield


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A one-frame synthetic nuScenes rig (400x225) and its true rig."""
    synth = pytest.importorskip("sgde_plugin.synth.sequence")
    root = synth.write_synth("nuscenes", 1, tmp_path_factory.mktemp("learned") / "nus", scale=0.25)
    true_rig = str(root / "rig_true.json")
    return root, true_rig, load_rig_with_override(str(root), true_rig)


def _range_map(rig, frame_id, camera):
    """Ground-truth range (distance from the optical centre) of one camera; 0 = none."""
    cam = rig.camera(camera)
    depth = rig.load_depth(frame_id, camera)
    if cam.intrinsics.depth_is_range:
        return depth.astype(np.float32)
    rays, _ = cam.intrinsics.ray_grid()
    return (depth / np.maximum(rays[..., 2].numpy(), 1e-6)).astype(np.float32)


def _true_disparity(side, plan, ranges):
    """True rectified disparity of one side's canvas (NaN where there is no truth)."""
    rng = side.warp(ranges[side.camera], cv2.INTER_NEAREST)
    rect = plan.pair.rect_left
    rays, _ = rect.intrinsics.ray_grid()
    q_norm = 1.0 / rays[..., 2].numpy()  # |K^-1 (u, v, 1)| for a unit ray
    z = rng / q_norm
    with np.errstate(divide="ignore", invalid="ignore"):
        disp = plan.pair.focal_px * plan.pair.baseline_m / z
    return np.where(rng > 0, disp, np.nan).astype(np.float32)


@pytest.fixture(scope="module")
def checkout(scene, tmp_path_factory):
    """A fake RAFT-Stereo checkout (core/raft_stereo.py), its oracle table and a DataParallel checkpoint."""
    _, _, rig = scene
    folder = tmp_path_factory.mktemp("raft")
    (folder / "core").mkdir()
    (folder / "core" / "__init__.py").write_text("")
    (folder / "core" / "raft_stereo.py").write_text(textwrap.dedent(STAND_IN))
    builder = PriorBuilder(rig, PriorConfig())  # the same rectification as any matcher with default geometry
    table = {}
    for frame in rig.frames:
        images = load_frame_images(rig, frame.id)
        ranges = {c: _range_map(rig, frame.id, c) for c in rig.camera_names}
        for plan in builder.plans:
            left, right = plan.left.warp(images[plan.left.camera]), plan.right.warp(images[plan.right.camera])
            x0, x1 = plan.pair.core_x
            truths = [_true_disparity(plan.left, plan, ranges)[:, :x1],
                      _true_disparity(plan.right, plan, ranges)[:, x0:][:, ::-1]]
            for (a, _), truth in zip(builder.matcher_inputs(plan, left, right), truths):
                batch, (top, bottom, lft, rgt) = network_input([a])
                i = len(table) // 2
                g = batch[0].mean(0)
                table[f"t{i}"] = g.reshape(g.shape[0] // 8, 8, g.shape[1] // 8, 8).mean(axis=(1, 3)).ravel()
                table[f"d{i}"] = np.pad(truth, ((top, bottom), (lft, rgt)), mode="edge")
    np.savez(folder / "oracle.npz", **table)
    return folder


@pytest.fixture
def raft(checkout, monkeypatch):
    """The checkout on the path and a checkpoint saved as train_stereo.py saves it (DataParallel keys)."""
    monkeypatch.syspath_prepend(str(checkout))
    monkeypatch.setenv("SGDE_TEST_ORACLE", str(checkout / "oracle.npz"))
    import core.raft_stereo as stand_in

    stand_in.CALLS.clear()
    net = stand_in.RAFTStereo(None)
    ckpt = checkout / "raftstereo-standin.pth"
    torch.save({f"module.{k}": v for k, v in net.state_dict().items()}, ckpt)
    return ckpt, stand_in


def _abs_rel(root, cache, tmp_path, capsys):
    out = tmp_path / "eval.json"
    assert cli_main(["eval", str(root), "--cache", str(cache), "--json", str(out)]) == 0
    capsys.readouterr()
    return json.loads(out.read_text())["overall"]


def test_raft_stereo_checkpoint_through_the_cli_gives_the_true_prior(scene, raft, tmp_path, capsys, monkeypatch):
    import sgde_plugin.stereo.config as prior_config

    root, true_rig, rig = scene
    ckpt, stand_in = raft
    cache = tmp_path / "cache"
    argv = ["prior", str(root), "--rig", true_rig, "--workers", "1", "--matcher", "raft-stereo",
            "--matcher-path", str(ckpt)]
    loads = []
    real_load = prior_config.load_learned_matcher
    monkeypatch.setattr(prior_config, "load_learned_matcher", lambda *a, **k: loads.append(a) or real_load(*a, **k))
    assert cli_main([*argv, "--out", str(cache)]) == 0
    assert len(loads) == 1  # the build's check that the file loads gives the in-process builder its matcher
    monkeypatch.setattr(prior_config, "load_learned_matcher", real_load)
    captured = capsys.readouterr()
    assert "1 frames built" in captured.out and "warning" not in captured.err
    overall = _abs_rel(root, cache, tmp_path, capsys)
    assert overall["abs_rel"] <= 0.005, overall
    assert overall["coverage"] > 0.5, overall
    calls = stand_in.CALLS
    assert calls and all(c["iters"] == 32 and c["test_mode"] for c in calls)  # the demo's call
    assert all(c["shape"][2] % 32 == 0 and c["shape"][3] % 32 == 0 for c in calls)  # padded as InputPadder
    assert all(c["rgb"] and 1.0 < c["max"] <= 255.0 for c in calls)  # RGB in [0, 255]
    assert sum(c["shape"][0] for c in calls) == 2 * len(PriorBuilder(rig, PriorConfig()).plans)  # two per pair

    # the flow read with the wrong sign: an empty prior, one warning line naming the cause; --strict: exit 3
    flipped = [*argv, "--matcher-option", "flip_sign=true"]
    assert cli_main([*flipped, "--out", str(tmp_path / "flipped")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning: frame" in err[0] and "mostly negative" in err[0] and "flow sign" in err[0]
    assert cli_main([*flipped, "--out", str(tmp_path / "strict"), "--strict"]) == 3
    assert "stopped (--strict)" in capsys.readouterr().err


def test_raft_stereo_errors_are_one_line(scene, checkout, tmp_path, capsys, monkeypatch):
    root, true_rig, _ = scene
    ckpt = tmp_path / "raftstereo-x.pth"
    torch.save({"module.other.weight": torch.zeros(1)}, ckpt)
    base = ["prior", str(root), "--rig", true_rig, "--out", str(tmp_path / "c"), "--matcher", "raft-stereo",
            "--matcher-path", str(ckpt)]
    for name in ("core", "core.raft_stereo"):  # no checkout importable
        monkeypatch.setitem(sys.modules, name, None)
    assert cli_main(base) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "core.raft_stereo" in err[0] and "PYTHONPATH" in err[0]
    for name in ("core", "core.raft_stereo"):
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(checkout))
    monkeypatch.setenv("SGDE_TEST_ORACLE", str(checkout / "oracle.npz"))
    assert cli_main([*base, "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not fit the architecture" in err[0] and "matcher_options" in err[0]


def test_fingerprint_follows_the_checkpoint_and_the_architecture_code(raft, checkout):
    ckpt, _ = raft
    config = PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt))
    fp = digest(config_document(config))
    assert config.to_dict()["matcher_code_sha256"]
    fewer = PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt), matcher_iters=12)
    assert digest(config_document(fewer)) != fp
    source = checkout / "core" / "raft_stereo.py"
    text = source.read_text()
    try:
        source.write_text(text + "\n# iterations 32 -> 12\n")
        assert digest(config_document(config)) != fp
    finally:
        source.write_text(text)
    assert digest(config_document(config)) == fp


class RangeMatcher(torch.nn.Module):
    """A disparity stand-in that reports the search range it is given and answers half of it."""

    def __init__(self):
        super().__init__()
        self.seen: list[int] = []

    def forward(self, left, right, max_disparity: int):
        self.seen.append(max_disparity)
        return torch.full_like(left[:, :1], max_disparity / 2)


def test_search_range_batching_and_refinement_default(scene, raft):
    _, _, rig = scene
    ckpt, stand_in = raft
    images = load_frame_images(rig, rig.frames[0].id)
    one = PriorBuilder(rig, PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt), matcher_batch=1))
    four = PriorBuilder(rig, PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt), matcher_batch=4))
    stand_in.CALLS.clear()
    a = one.build(images)
    calls_one = len(stand_in.CALLS)
    b = four.build(images)
    calls_four = len(stand_in.CALLS) - calls_one
    assert calls_one == 2 * len(one.plans) and calls_four < calls_one
    for cam in a:
        assert np.array_equal(a[cam].depth, b[cam].depth)
    # the matcher sees the canvases the filters see: photometric normalisation (grey out) reaches it
    stand_in.CALLS.clear()
    gain = PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt), normalize="gain")
    PriorBuilder(rig, gain).build(images)
    assert stand_in.CALLS and not any(c["rgb"] for c in stand_in.CALLS)
    # the search range reaches a module that asks for it
    module = RangeMatcher()
    matcher = TorchMatcher(module)
    disp, conf = matcher.match(np.zeros((40, 70), np.uint8), np.zeros((40, 70), np.uint8), 48)
    assert module.seen == [48] and np.allclose(disp, 24.0) and conf.min() == 1.0
    # learned output is not "refined": with refinement on, perfect disparities get worse
    refined = PriorBuilder(
        rig, PriorConfig.from_settings(matcher="raft-stereo", matcher_path=str(ckpt), refine_iterations=1))
    gt = {c: rig.load_depth(rig.frames[0].id, c) for c in rig.camera_names}
    errors = []
    for out in (a, refined.build(images)):
        rel = [np.abs(out[c].depth - gt[c])[(out[c].depth > 0) & (gt[c] > 0)] / gt[c][(out[c].depth > 0) & (gt[c] > 0)]
               for c in gt]
        errors.append(np.concatenate(rel).mean())
    assert errors[0] < errors[1]


class TinyCost(torch.nn.Module):
    """A small cost-volume matcher (32 disparities, soft arg-min) to export to ONNX."""

    def __init__(self, sharpness: float = 2.0):
        super().__init__()
        self.sharpness = torch.nn.Parameter(torch.tensor(sharpness))

    def forward(self, left, right):
        w = left.shape[-1]
        costs = []
        for d in range(32):
            shifted = torch.nn.functional.pad(right[..., : w - d], (d, 0)) if d else right
            costs.append(torch.nn.functional.avg_pool2d((left - shifted).abs().mean(1, keepdim=True), 5, 1, 2))
        p = torch.softmax(-torch.cat(costs, 1) * self.sharpness, dim=1)
        return (p * torch.arange(32, dtype=left.dtype).view(1, -1, 1, 1)).sum(1, keepdim=True)


def _export(net, path, dynamic: bool, external: bool = False):
    example = (torch.rand(1, 3, 64, 96) * 255, torch.rand(1, 3, 64, 96) * 255)
    axes = {n: {0: "batch", 2: "height", 3: "width"} for n in ("left", "right", "disparity")} if dynamic else None
    torch.onnx.export(net, example, str(path), input_names=["left", "right"], output_names=["disparity"],
                      opset_version=17, dynamo=False, dynamic_axes=axes)
    if external:
        model = onnx.load(str(path))
        onnx.save_model(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True,
                        location=path.name + ".data", size_threshold=0)
    assert onnx.load(str(path), load_external_data=False).opset_import[0].version == 17  # the opset asked for


@pytest.mark.filterwarnings("ignore")
def test_onnx_matcher_dynamic_fixed_and_external_weights(scene, tmp_path, capsys):
    root, true_rig, _ = scene
    dyn = tmp_path / "dyn.onnx"
    _export(TinyCost(2.0), dyn, dynamic=True, external=True)
    cache = tmp_path / "cache"
    argv = ["prior", str(root), "--rig", true_rig, "--workers", "1", "--matcher", "onnx", "--matcher-path", str(dyn),
            "--scale", "0.25"]
    assert cli_main([*argv, "--out", str(cache)]) == 0
    assert "1 frames built" in capsys.readouterr().out
    overall = _abs_rel(root, cache, tmp_path, capsys)
    assert overall["coverage"] > 0.05 and overall["abs_rel"] < 0.1, overall  # a crude matcher (32 px), but a prior
    # the weights live in dyn.onnx.data: changing them alone changes the fingerprint
    config = PriorConfig.from_settings(matcher="onnx", matcher_path=str(dyn))
    fp, graph = digest(config_document(config)), dyn.read_bytes()
    tensor = next(t for t in onnx.load(str(dyn), load_external_data=False).graph.initializer if "sharpness" in t.name)
    offset = int(next((e.value for e in tensor.external_data if e.key == "offset"), 0))
    data = bytearray((tmp_path / "dyn.onnx.data").read_bytes())
    assert np.frombuffer(data[offset : offset + 4], np.float32)[0] == 2.0
    data[offset : offset + 4] = np.float32(3.0).tobytes()
    (tmp_path / "dyn.onnx.data").write_bytes(bytes(data))
    assert dyn.read_bytes() == graph and digest(config_document(config)) != fp
    assert cli_main([*argv, "--out", str(cache)]) == 2  # the cache was built with the other weights
    assert "refusing to mix" in capsys.readouterr().err
    # a fixed-shape export is refused in one line saying what to re-export
    fixed = tmp_path / "fixed.onnx"
    _export(TinyCost(2.0), fixed, dynamic=False)
    assert cli_main(["prior", str(root), "--rig", true_rig, "--out", str(tmp_path / "c2"), "--workers", "1",
                     "--matcher", "onnx", "--matcher-path", str(fixed)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fixed size 64x96" in err[0] and "dynamic height and width" in err[0]
    assert not (tmp_path / "c2").exists() or not any((tmp_path / "c2").rglob("*.done"))


def test_onnx_search_range_input(tmp_path):
    class Half(torch.nn.Module):
        def forward(self, left, right, max_disparity):
            return 0 * (left + right)[:, :1] + max_disparity.float() / 2

    path = tmp_path / "range.onnx"
    example = (torch.zeros(1, 3, 32, 32), torch.zeros(1, 3, 32, 32), torch.tensor(16))
    axes = {n: {0: "b", 2: "h", 3: "w"} for n in ("left", "right")}
    torch.onnx.export(Half(), example, str(path), input_names=["left", "right", "max_disparity"],
                      output_names=["disparity"], opset_version=17, dynamo=False, dynamic_axes=axes)
    disp, conf = OnnxMatcher(path).match(np.zeros((40, 70, 3), np.uint8), np.zeros((40, 70, 3), np.uint8), 48)
    assert disp.shape == (40, 70) and np.allclose(disp, 24.0) and conf.min() == 1.0


def test_devices_workers_and_threads(scene, tmp_path, monkeypatch):
    _, _, rig = scene
    model = tmp_path / "m.pt"
    model.write_bytes(b"x")
    learned = PriorConfig.from_settings(matcher="torch", matcher_path=str(model))
    cpus = usable_cpus()
    assert default_workers(PriorConfig()) == cpus
    monkeypatch.setattr("sgde_plugin.cache.build.available_memory", lambda: 3 * 1024**3)
    assert default_workers(learned) == 1  # 2 GiB per learned-matcher worker
    monkeypatch.setattr("sgde_plugin.cache.build.available_memory", lambda: 64 * 1024**3)
    assert default_workers(learned) == cpus
    assert default_workers(PriorConfig.from_settings(matcher="torch", matcher_path=str(model), device="cuda")) == 1
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr("os.getloadavg", lambda: (0.2, 0.2, 0.2))
    assert torch_threads_per_worker(1) == cpus and torch_threads_per_worker(cpus) == 1  # idle machine
    monkeypatch.setattr("os.getloadavg", lambda: (float(cpus), 0.0, 0.0))
    assert torch_threads_per_worker(1) == 1  # every core busy: extra OpenMP threads would only wait
    monkeypatch.setattr("os.getloadavg", lambda: (0.2, 0.2, 0.2))
    seen = []

    def compute(frame_id):
        seen.append(torch.get_num_threads())
        return {c.name: (np.zeros((c.height, c.width), np.float32), None) for c in rig.cameras}

    report = build_cache(rig, tmp_path / "cache", {"compute": "threads"}, compute=compute, workers=1)
    assert seen == [cpus] and report.frames_built == 1  # one worker: torch gets every CPU
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="cuda asked for"):
            TorchMatcher(RangeMatcher(), device="cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_cuda_matches_cpu():
    net = TinyCost(2.0)
    left = (np.random.default_rng(0).random((64, 96, 3)) * 255).astype(np.uint8)
    right = np.roll(left, -4, axis=1)
    d_cpu, _ = TorchMatcher(net, device="cpu").match(left, right, 32)
    d_gpu, _ = TorchMatcher(net, device="cuda").match(left, right, 32)
    assert np.abs(d_cpu - d_gpu).max() < 1e-3
