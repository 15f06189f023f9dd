"""End to end on a small synthetic rig: the demo's whole chain runs and its figures say what they claim."""

from __future__ import annotations

import json
from pathlib import Path

from sgde_plugin.demo import DemoSettings, run_demo


def test_demo_end_to_end_small(tmp_path: Path) -> None:
    settings = DemoSettings(frames=3, scale=0.3, net_size=(64, 96), train_steps=3, self_steps=3)
    summary = run_demo(tmp_path, settings, log=lambda _line: None)
    for name in ("report.md", "summary.json", "priors.png", "bev_points.png", "depth_r18_prior.onnx",
                 "rig_glc.json", "rig_none.json"):
        assert (tmp_path / name).stat().st_size > 0, name
    assert json.loads((tmp_path / "summary.json").read_text())["settings"]["frames"] == 3
    priors = {row["extrinsics"]: row for row in summary["priors"]}
    # with the true extrinsics the prior is metric and accurate; the noisy dataset poses are far worse
    assert priors["true (reference)"]["abs_rel"] < 0.05 and priors["true (reference)"]["coverage"] > 0.3
    assert priors["none"]["abs_rel"] > 2 * priors["true (reference)"]["abs_rel"] or priors["none"]["coverage"] < 0.2
    assert summary["export"]["comparisons"] >= 4
    assert "## Calibration" in (tmp_path / "report.md").read_text()
    # the network stage: baseline, prior net, and the self-supervised prior net at its own size
    assert [row["model"] for row in summary["network"]] == [
        "baseline (RGB)", "+ prior input & L1", "self-supervised + prior input & L1 (80x48)"]
    assert all(0 < row["abs_rel"] < 10 for row in summary["network"])
