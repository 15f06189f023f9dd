"""The real DDAD sample (../shared/data/ddad-sample): partial rigs, per-camera captures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.readers import load_rig

SAMPLE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ddad-sample"
pytestmark = pytest.mark.skipif(not SAMPLE.is_dir(), reason=f"{SAMPLE} is absent")


def test_scene_01_is_a_partial_rig_with_two_pairs(capsys: pytest.CaptureFixture) -> None:
    assert main(["validate", str(SAMPLE / "scene_01")]) == 0
    assert "3 cameras, 2 adjacent pairs, 3 frames" in capsys.readouterr().out
    rig = load_rig(SAMPLE / "scene_01")
    assert rig.pairs == (("CAMERA_01", "CAMERA_06"), ("CAMERA_05", "CAMERA_01")) and rig.ring is None


def test_scene_02_cameras_keep_their_datum_poses() -> None:
    rig = load_rig(SAMPLE / "scene_02")
    assert len(rig.camera_names) == 6 and rig.ring is not None
    for fr in rig.frames:
        for cam in rig.camera_names:
            cap = rig.capture(fr, cam)
            assert cap.timestamp_us == fr.timestamp_us  # DDAD's cameras are synchronised
            # the per-datum poses differ from CAMERA_01's by millimetres, not more
            assert np.abs(cap.ego_to_world[:3, 3] - fr.ego_to_world[:3, 3]).max() < 0.02
        assert set(fr.cameras) == set(rig.camera_names) - {"CAMERA_01"}
