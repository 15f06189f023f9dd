"""`sgde export onnx`: checkpoints (weights_only), --check, --fp16, bad input (~30 s)."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
import textwrap

import numpy as np
import torch

from sgde_plugin.adapters import PriorDepthNet
from sgde_plugin.cli import main
from sgde_plugin.export import read_metadata

SMALL = {"in_channels": 8, "mid_channels": 16, "context_channels": 4, "depth_channels": 112}


def _checkpoint(path, **extra):
    torch.manual_seed(3)
    net = PriorDepthNet(**SMALL)
    torch.save({"state_dict": net.state_dict(), "config": dict(SMALL), "fingerprint": "cache-fp-1234", **extra},
               path)
    return net


def test_bevdepth_from_checkpoint_with_check(tmp_path, capsys):
    ckpt = tmp_path / "bev.pt"
    net = _checkpoint(ckpt)
    out = tmp_path / "bev.onnx"
    code = main(["export", "onnx", "--model", "bevdepth", "--checkpoint", str(ckpt), "--image-size", "32x64",
                 "--out", str(out), "--check"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "check passed (8 comparisons" in text and "depth_logits" in text
    meta = read_metadata(out)
    assert meta["sgde.training_fingerprint"] == "cache-fp-1234"
    from sgde_plugin.export.models import state_dict_sha256

    assert meta["sgde.weights_sha256"] == state_dict_sha256(net)  # the checkpoint's weights went in


def test_r18_fp16_with_check(tmp_path, capsys):
    out = tmp_path / "r18.onnx"
    code = main(["export", "onnx", "--model", "r18", "--image-size", "64x96", "--out", str(out), "--fp16", "--check"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "fp16" in text and "check passed" in text
    assert read_metadata(out)["sgde.precision"] == "fp16"


def test_bad_checkpoints_are_refused_with_one_line(tmp_path, capsys):
    out = tmp_path / "x.onnx"
    base = ["export", "onnx", "--model", "bevdepth", "--image-size", "32x64", "--out", str(out), "--checkpoint"]
    # a pickle that needs arbitrary code (not weights only)
    evil = tmp_path / "evil.pt"
    torch.save({"state_dict": {"w": torch.zeros(1)}, "config": dict(SMALL), "hook": np.random.default_rng(0)}, evil)
    assert main([*base, str(evil)]) == 2
    assert "not a weights-only torch checkpoint" in capsys.readouterr().err
    # a bare protocol-4 pickle naming a global: torch warns about the protocol before refusing; one line only
    evil.write_bytes(pickle.dumps({"hook": print}, protocol=4))
    assert main([*base, str(evil)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a weights-only torch checkpoint" in err[0], err
    # weights that do not fit the model
    wrong = tmp_path / "wrong.pt"
    torch.save({"state_dict": {"reduce_conv.0.weight": torch.zeros(3, 3)}, "config": dict(SMALL)}, wrong)
    assert main([*base, str(wrong)]) == 2
    err = capsys.readouterr().err
    assert "wrong.pt" in err and len(err.strip().splitlines()) == 1
    assert main([*base, str(tmp_path / "missing.pt")]) == 2
    assert "checkpoint file not found" in capsys.readouterr().err
    assert not out.exists()


def test_a_bevdepth_checkpoint_with_its_dcn_exports_at_opset_19_and_is_refused_at_17(tmp_path, capsys):
    from mock_bev import bevdepth_depthnet_state

    # BEVDepth's LightningModule layout: model.backbone.depth_net.* among the detector's other weights
    ckpt = tmp_path / "bevdepth.ckpt"
    state = {f"model.backbone.depth_net.{k}": v for k, v in bevdepth_depthnet_state(8, 16, 4, 112).items()}
    torch.save({"state_dict": state | {"model.head.conv.weight": torch.zeros(2, 2)}}, ckpt)
    out = tmp_path / "bev.onnx"
    base = ["export", "onnx", "--model", "bevdepth", "--checkpoint", str(ckpt), "--image-size", "32x64",
            "--out", str(out)]
    assert main(base) == 2  # default opset 17
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "opset >= 19" in err and "deformable" in err and not out.exists()
    assert main([*base, "--opset", "19", "--check"]) == 0
    text = capsys.readouterr().out
    assert "check passed (8 comparisons" in text and "opset 19" in text
    meta = read_metadata(out)
    assert json.loads(meta["sgde.inputs"])["intrin_mats"].startswith("float32 [B,S,N,4,4]")


def test_exported_file_runs_in_a_fresh_onnxruntime_process(tmp_path):
    # export, keep torch's outputs, then run the file in a new interpreter that imports no project code
    from sgde_plugin.export.models import build_bevdepth
    from sgde_plugin.export.parity import run_torch
    from sgde_plugin.export.workflow import export_spec

    spec = build_bevdepth(image_size=(32, 64), cams=6, in_channels=8, mid_channels=16, context_channels=4)
    path = tmp_path / "bev.onnx"
    export_spec(spec, path)
    inputs = spec.random_inputs(3, 11)
    np.savez(tmp_path / "io.npz", **{n: x.numpy() for n, x in zip(spec.input_names, inputs)},
             **{f"ref_{n}": y for n, y in zip(spec.output_names, run_torch(spec.module, inputs))})
    script = textwrap.dedent(f"""
        import json, sys
        import numpy as np
        import onnxruntime as ort
        sess = ort.InferenceSession({str(path)!r}, providers=["CPUExecutionProvider"])
        data = np.load({str(tmp_path / "io.npz")!r})
        feeds = {{i.name: data[i.name] for i in sess.get_inputs()}}
        outs = sess.run(None, feeds)
        diffs = {{o.name: float(np.abs(v - data["ref_" + o.name]).max()) for o, v in zip(sess.get_outputs(), outs)}}
        meta = sess.get_modelmeta().custom_metadata_map
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("torch", "sgde_plugin"))
        print(json.dumps({{"diffs": diffs, "loaded": loaded, "model": meta.get("sgde.model"),
                          "shapes": [list(v.shape) for v in outs]}}))
    """)
    res = subprocess.run([sys.executable, "-I", "-c", script], capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    got = json.loads(res.stdout)
    assert got["loaded"] == [] and got["model"] == "bevdepth"
    assert got["shapes"] == [[18, 112, 2, 4], [18, 4, 2, 4]]
    assert max(got["diffs"].values()) < 1e-4


def test_sizes_beyond_memory_are_one_line_and_write_nothing(tmp_path, capsys, monkeypatch):
    out = tmp_path / "big.onnx"
    assert main(["export", "onnx", "--model", "r18", "--image-size", "100000x100000", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sides must be at most 4096 pixels" in err[0] and not out.exists()

    def no_memory(*args, **kwargs):  # what torch's CPU allocator raises for a batch larger than the machine
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] DefaultCPUAllocator: can't allocate memory: you "
                           "tried to allocate 240000000000 bytes")

    monkeypatch.setattr("sgde_plugin.export.workflow.export_spec", no_memory)
    monkeypatch.setattr("sgde_plugin.cache.build.available_memory", lambda: 10**15)  # past the estimate
    assert main(["export", "onnx", "--model", "r18", "--image-size", "4096x4096", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--image-size: 4096x4096 does not fit in memory for the trace" in err[0], err
    assert not out.exists()


def test_an_export_larger_than_free_memory_is_refused_before_it_starts(tmp_path, capsys, monkeypatch):
    from sgde_plugin.export.models import build_bevdepth, build_r18
    from sgde_plugin.export.workflow import estimated_peak_bytes

    # the estimate grows with the pixels, the cameras and the check; the default sizes need 1-2 GB (measured 1.16
    # GB for r18 and 1.49 GB for bevdepth's 6 cameras; 1.93 and 3.05 GB with --check)
    r18, big = build_r18(), build_r18(image_size=(2048, 2048))
    assert 1.0e9 < estimated_peak_bytes(r18, False) < 1.4e9 < estimated_peak_bytes(r18, True) < 2.4e9
    assert estimated_peak_bytes(big, True) > 3 * estimated_peak_bytes(big, False)
    assert estimated_peak_bytes(r18, False, fp16=True) > estimated_peak_bytes(r18, False)
    six, twelve = build_bevdepth(), build_bevdepth(cams=12)
    assert 1.2e9 < estimated_peak_bytes(six, False) < 1.8e9 and 2.5e9 < estimated_peak_bytes(six, True) < 3.6e9
    assert estimated_peak_bytes(twelve, False) > estimated_peak_bytes(six, False)

    called = []
    def fake_export(spec, path, **kwargs):
        called.append(path)
        return {"path": str(path), "bytes": 0, "parity": []}

    monkeypatch.setattr("sgde_plugin.export.workflow.export_spec", fake_export)
    monkeypatch.setattr("sgde_plugin.cache.build.available_memory", lambda: 2 * 10**9)
    out = tmp_path / "big.onnx"
    args = ["export", "onnx", "--model", "bevdepth", "--image-size", "1024x1408", "--cams", "12", "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--image-size: 1024x1408 x 12 cameras needs about 6.7 GB for the export, 2.0 GB is " \
        "available; nothing written" in err[0], err
    assert main(["export", "onnx", "--model", "r18", "--check", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the default size needs about 2.2 GB for the export and --check" in err[0], err
    assert not called and not out.exists()
    monkeypatch.setattr("sgde_plugin.cache.build.available_memory", lambda: None)  # unknown: not refused
    assert main(["export", "onnx", "--model", "r18", "--out", str(out)]) == 0 and called == [str(out)]
