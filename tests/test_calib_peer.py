"""The COLMAP peer of `sgde bench calibrate --peer colmap` (pycolmap, extra `peer`; runtime ~20 s on 2 cores)."""

import numpy as np
import pytest

pytest.importorskip("pycolmap", reason="pycolmap (extra `peer`) is not installed")

from sgde_plugin.benchmarks.colmap_peer import calibrate_colmap  # noqa: E402
from sgde_plugin.calib.simulate import box_world_rig  # noqa: E402
from sgde_plugin.pairs import relative_pose_errors  # noqa: E402
from sgde_plugin.stereo.rectify import torch_threads  # noqa: E402


@pytest.mark.slow
def test_colmap_rig_adjustment_recovers_the_box_rig():
    with torch_threads(1):
        rig_true, rig, images = box_world_rig(n_frames=3)
    ids = [f.id for f in rig.frames]
    ego = np.stack([f.ego_to_world for f in rig.frames])
    ext, facts = calibrate_colmap(list(rig.cameras), ego, lambda t, c: images[ids[t]][c], "C0")
    assert facts["registered_images"] == 18 and facts["points"] > 1000 and facts["mean_reprojection_error_px"] < 0.5
    assert abs(facts["scale"] - 1.0) < 0.01  # the ego trajectory fixes the metric scale
    assert np.allclose(ext["C0"], rig.camera("C0").sensor_to_ego)  # the reference keeps its mount
    before = [r["rotation_deg"] for r in relative_pose_errors(rig, rig_true)]
    rows = relative_pose_errors(rig.with_extrinsics(ext), rig_true)
    assert min(before) > 1.0
    assert max(r["rotation_deg"] for r in rows) < 0.2 and max(r["translation_m"] for r in rows) < 0.02
