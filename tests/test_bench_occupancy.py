"""Occupancy IoU / precision / recall of the train-effect bench: hand values on a 4x4-pixel camera."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgde_plugin.adapters import VoxelGrid, occupancy_scores
from sgde_plugin.benchmarks.occupancy import benchmark_grids, occupancy_eval, occupancy_table, rig_occupancy_scores
from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.geometry import camera_mount
from sgde_plugin.nn.sequence import RigSequence

# 4x4 pixels, f = 4: at 10.1 m the pixel rays are 2.5 m apart, so every pixel lands in its own 0.5 m voxel
CAM = Camera("front", Pinhole(4, 4, np.array([[4.0, 0, 1.5], [0, 4.0, 1.5], [0, 0, 1]])),
             camera_mount(0.0, np.array([0.0, 0.0, 0.0])))
GRID = {"toy": (VoxelGrid((0.0, -5.0, -5.0), 0.5, (40, 20, 20)), np.eye(4))}


def test_scores_by_hand():
    truth = np.full((1, 1, 4, 4), 10.1)
    assert rig_occupancy_scores(truth, truth, [CAM], GRID) == {
        "occ_toy_iou": 1.0, "occ_toy_precision": 1.0, "occ_toy_recall": 1.0}
    pred = truth.copy()
    pred[..., 2:] = 12.1  # half the pixels 2 m too far: 8 of 16 voxels right, 8 wrong
    s = rig_occupancy_scores(pred, truth, [CAM], GRID)
    assert s["occ_toy_iou"] == pytest.approx(8 / 24) and s["occ_toy_precision"] == 0.5 and s["occ_toy_recall"] == 0.5
    pred[0, 0, 0, 0] = 0.0  # a pixel without a value predicts nothing: 8 right of 15 predicted
    truth2 = truth.copy()
    truth2[0, 0, 3, 3] = 0.0  # sky in the truth, predicted at 12.1 m: a false positive (already wrong)
    s = rig_occupancy_scores(pred, truth2, [CAM], GRID)
    assert s["occ_toy_precision"] == pytest.approx(7 / 15) and s["occ_toy_recall"] == pytest.approx(7 / 15)
    assert s["occ_toy_iou"] == pytest.approx(7 / (15 + 15 - 7))
    # pooled over frames: a second, perfect frame adds 16 true positives
    both = rig_occupancy_scores(np.concatenate([pred, truth]), np.concatenate([truth2, truth]), [CAM], GRID)
    assert both["occ_toy_recall"] == pytest.approx((7 + 16) / (15 + 16))
    # the generic scorer agrees, and says nan where nothing is predicted
    assert occupancy_scores(np.array([1, 1, 0, 0]), np.array([1, 0, 1, 0]))["iou"] == pytest.approx(1 / 3)
    assert math.isnan(occupancy_scores(np.zeros(4), np.ones(4))["precision"])


class _Oracle:
    """A stand-in net whose prediction is the ground truth of the frame it is given (by its images)."""

    use_prior = False

    def __init__(self, seq: RigSequence, scale: float = 1.0) -> None:
        self.seq, self.scale = seq, scale

    def eval(self) -> None:
        pass

    def predict(self, rgb: torch.Tensor, prior: None, valid: None) -> torch.Tensor:
        k = int(rgb[0, 0, 0, 0] * 255 + 0.5)  # the frame index is written into the images
        return torch.from_numpy(self.seq.depth[k] * self.scale)[:, None]


def test_occupancy_eval_on_the_benchmark_grids():
    frames, n = 3, 2
    cams = [CAM, Camera("back", CAM.intrinsics, camera_mount(np.pi, np.array([0.0, 0.0, 0.0])))]
    depth = np.stack([np.full((n, 4, 4), 10.1 + k, np.float32) for k in range(frames)])
    images = np.zeros((frames, n, 4, 4, 3), np.uint8)
    images[..., 0] = np.arange(frames)[:, None, None, None]
    zeros = np.zeros_like(depth)
    seq = RigSequence(cams, [("front", "back")], images, depth, zeros, zeros, zeros > 0, zeros > 0)
    scores = occupancy_eval(_Oracle(seq), seq, [1, 2])
    assert set(scores) == {f"occ_{g}_{m}" for g in benchmark_grids() for m in ("iou", "precision", "recall")}
    assert scores["occ_occ3d_iou"] == 1.0 and scores["occ_voxformer_iou"] == 1.0
    # the frames are matched to their own truth: scoring frame 1's depth against frame 2's truth fails
    shifted = rig_occupancy_scores(depth[[1]], depth[[2]], cams)
    assert shifted["occ_occ3d_iou"] < 0.5
    table = occupancy_table({"oracle": scores})
    assert "| oracle | 1.000 | 1.000 | 1.000 | 1.000 | 1.000 | 1.000 |" in table
    # a net 50 % too far, with an exact prior on the left half of every image: pasting the prior (as the
    # VoxFormer adapter's fuse_depth_with_prior does) recovers exactly the left half's voxels
    seq.prior[:], seq.valid[..., :2] = seq.depth, True
    far = occupancy_eval(_Oracle(seq, 1.5), seq, [1, 2])
    pasted = occupancy_eval(_Oracle(seq, 1.5), seq, [1, 2], paste_prior=True)
    assert far["occ_occ3d_recall"] == 0.0 and pasted["occ_occ3d_recall"] == pytest.approx(0.5)
    # Occ3D's z range [-1, 5.4] m keeps the two upper pixel rows of the truth (16 true positives over two frames
    # and two cameras); of the far right halves only row 1 stays inside (row 0 rises above 5.4 m): 8 wrong
    assert pasted["occ_occ3d_precision"] == pytest.approx(16 / 24)
