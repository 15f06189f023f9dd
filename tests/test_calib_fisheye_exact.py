"""Exact fisheye extrinsics stay exact under the default settings (issue #17 item 2; about 15 s on 2 cores).

The urban-fisheye preset (four 220-degree Ocam fisheyes) at half resolution, seed 0, 7 frames, calibrated from
the true extrinsics as one window: the default ("auto") runs the keypoint refinement on this rig, and the
adjacent relative poses come back within issue #17's bounds. Measured: median 0.0190 deg, max 0.0211 deg,
translation 0.57 cm; with the refinement off (the default before session 8) the median is 0.023 deg, over the
bound, so this test fails if "auto" stops resolving to on for fisheye rigs.
"""

import numpy as np
import pytest

from sgde_plugin.calib import calibrate
from sgde_plugin.pairs import relative_pose_errors
from sgde_plugin.synth.sequence import synth_sequence


@pytest.mark.slow
def test_exact_fisheye_poses_stay_within_the_bounds_by_default():
    seq = synth_sequence("urban-fisheye", 7, seed=0, scale=0.5)
    out, block = calibrate(seq.rig_true, lambda f, c: seq.images[f][c], window=7, show_progress=False)
    assert block["keypoint_refinement"] is True and block["windows"][0]["accepted"]
    rows = relative_pose_errors(out, seq.rig_true)
    rot = np.array([r["rotation_deg"] for r in rows])
    trans = np.array([r["translation_m"] for r in rows])
    assert len(rows) == 4
    assert np.median(rot) <= 0.02 and rot.max() <= 0.05 and trans.max() <= 0.02, (rot, trans)
