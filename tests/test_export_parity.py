"""ONNX export of the R18 depth net and the BEVDepth-style branch: parity, fp16, refusals, metadata (~40 s)."""

from __future__ import annotations

import json
import math

import onnx
import pytest
import torch

from sgde_plugin.export import ParityError, check_parity, read_metadata
from sgde_plugin.export import workflow as wf
from sgde_plugin.export.models import build_bevdepth, build_r18
from sgde_plugin.export.workflow import export_spec

SMALL_BEV = {"in_channels": 8, "mid_channels": 16, "context_channels": 4}


@pytest.fixture(scope="module")
def r18_spec():
    torch.manual_seed(0)
    return build_r18(image_size=(64, 96))


@pytest.fixture(scope="module")
def bev_spec():
    torch.manual_seed(0)
    return build_bevdepth(image_size=(32, 64), cams=6, **SMALL_BEV)


def test_r18_parity_batches_1_and_6_and_another_image_size(r18_spec, tmp_path):
    report = export_spec(r18_spec, tmp_path / "r18.onnx", check=True)
    res = report["parity"]
    # the synthetic frame is the nuScenes-like rig rendered at 176x99, cropped to 96x160
    assert {(r.case, r.batch) for r in res} == {("random", 1), ("rendered 96x160", 1), ("random", 6),
                                                 ("rendered 96x160", 6), ("random 128x64", 2)}
    assert all(r.ok for r in res)
    assert max(r.max_abs_diff / r.output_range for r in res) <= 1e-4  # traced with batch 2 at 64x96
    model = onnx.load(str(tmp_path / "r18.onnx"))
    assert max(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")) >= 17
    dims = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    assert dims == {"image": ["batch", 3, "height", "width"], "prior": ["batch", 1, "height", "width"]}
    assert [o.name for o in model.graph.output] == ["depth"]


def test_bevdepth_parity_and_metadata(bev_spec, tmp_path):
    path = tmp_path / "bev.onnx"
    report = export_spec(bev_spec, path, check=True)
    assert all(r.ok for r in report["parity"]) and len(report["parity"]) == 8
    assert {r.case for r in report["parity"]} == {"random", "rendered"}
    assert max(r.relative_to_range for r in report["parity"]) <= 1e-4
    meta = read_metadata(path)
    assert json.loads(meta["sgde.depth_range"]) == [2.0, 58.0, 0.5]
    assert json.loads(meta["sgde.prior_normalisation"])["max_depth"] == 58.0
    assert set(json.loads(meta["sgde.inputs"])) == {"features", "prior", "intrin_mats", "ida_mats",
                                                    "sensor2ego_mats", "bda_mat"}
    assert meta["sgde.training_fingerprint"].startswith("none") and len(meta["sgde.weights_sha256"]) == 64
    assert meta["sgde.precision"] == "fp32" and meta["sgde.input_layout"]
    # one self-contained file: every initializer is inline, nothing else written next to it
    model = onnx.load(str(path), load_external_data=False)
    assert all(t.data_location == onnx.TensorProto.DEFAULT for t in model.graph.initializer)
    assert [p.name for p in tmp_path.iterdir()] == ["bev.onnx"]


def test_fp16_passes_its_tolerance_and_is_refused_beyond_it(bev_spec, tmp_path, monkeypatch):
    path = tmp_path / "bev16.onnx"
    report = export_spec(bev_spec, path, check=True, fp16=True)
    assert read_metadata(path)["sgde.precision"] == "fp16"
    worst = max(r.relative_to_range for r in report["parity"])
    assert 1e-6 < worst < 1e-2  # half precision is visibly different, but within its tolerance
    # a tolerance it cannot meet: refused with the numbers, and no file is left behind
    monkeypatch.setattr(wf, "FP16_TOLERANCE", (1e-7, 0.0))
    out = tmp_path / "refused.onnx"
    with pytest.raises(ParityError, match=r"max\|diff\|") as err:
        export_spec(bev_spec, out, check=True, fp16=True)
    assert not out.exists() and not any(p.name.startswith(".refused") for p in tmp_path.iterdir())
    assert all(not r.ok for r in err.value.results if r.max_abs_diff > 1e-7)


def test_a_mismatch_is_an_error_with_numbers(bev_spec, tmp_path):
    path = tmp_path / "bev.onnx"
    export_spec(bev_spec, path)
    changed = build_bevdepth(image_size=(32, 64), cams=6, **SMALL_BEV).module  # other random weights
    with pytest.raises(ParityError) as err:
        check_parity(path, changed, [("random", 1, bev_spec.random_inputs(1, 5))], bev_spec.input_names,
                     bev_spec.output_names)
    assert "FAIL" in str(err.value) and err.value.results[0].max_abs_diff > 1e-3


def test_generated_frame_stands_in_when_the_renderer_is_missing(bev_spec, monkeypatch):
    from sgde_plugin.export import models

    monkeypatch.setattr(models, "rendered_frame", lambda: None)
    label, inputs = bev_spec.synthetic_inputs(2)
    label2, again = bev_spec.synthetic_inputs(2)
    assert label == label2 == "generated"
    assert all(torch.equal(a, b) for a, b in zip(inputs, again))  # deterministic
    prior = inputs[1]
    assert prior.shape == (2, 6, 32, 64) and 0.0 < (prior > 0).float().mean().item() < 0.4


def test_r18_with_the_factored_stem_exports_with_parity(tmp_path):
    torch.manual_seed(1)
    from sgde_plugin.nn import DepthNet

    net = DepthNet(stem="factored", validity=True)
    with torch.no_grad():  # a trained-looking low-rank prior kernel, not the all-zero start
        net.encoder.conv1.mix.weight.normal_(0.0, 0.05)
    ckpt = tmp_path / "factored.pt"
    torch.save({"state_dict": net.state_dict(), "config": {"stem": "factored", "validity": True}}, ckpt)
    spec = build_r18(ckpt, image_size=(64, 96))
    report = export_spec(spec, tmp_path / "factored.onnx", check=True)
    assert all(r.ok for r in report["parity"])
    assert max(r.max_abs_diff / r.output_range for r in report["parity"]) <= 1e-4


def test_r18_metadata_names_the_log_prior_encoding(tmp_path):
    from sgde_plugin.nn import DepthNet

    net = DepthNet(validity=True, prior_encoding="log")
    ckpt = tmp_path / "log.pt"
    torch.save({"state_dict": net.state_dict(), "config": {"validity": True, "prior_encoding": "log"}}, ckpt)
    spec = build_r18(ckpt, image_size=(64, 96))
    scheme = json.loads(spec.metadata["sgde.prior_normalisation"])["scheme"]
    assert scheme.startswith("log(clip(prior_m, 0.5, max_depth) / 10)")
    assert json.loads(build_r18(image_size=(64, 96)).metadata["sgde.prior_normalisation"])["scheme"].startswith("clip(")
    # the graph encodes as the metadata says: a 40 m prior enters as log 4
    assert float(spec.module.net.encoding(torch.full((1, 1, 1, 1), 40.0))[0, 0]) == pytest.approx(math.log(4.0))
