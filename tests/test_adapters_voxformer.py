"""VoxFormer-style proposals: a plane at a known distance lands in the right voxels (pinhole and fisheye)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sgde_plugin.adapters import (
    OCC3D_NUSCENES_GRID,
    VOXFORMER_GRID,
    DepthToVoxelProposals,
    VoxelGrid,
    fuse_depth_with_prior,
    proposal_depth_loss,
    proposal_indices,
)
from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.geometry import camera_mount
from sgde_plugin.stereo.virtual import virtual_pinholes
from sgde_plugin.synth.presets import preset_cameras

PLANE_X = 10.1  # a wall facing the rig at ego x = 10.1 m


def _plane_depth_pinhole(cam: Camera) -> np.ndarray:
    """Depth (z) map of the plane ego x = PLANE_X for a pinhole camera, by hand: K^-1, R, t; 0 = misses."""
    K, T = cam.intrinsics.K, cam.sensor_to_ego
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z = 1
    ego_dir = rays @ T[:3, :3].T
    with np.errstate(divide="ignore"):
        t = (PLANE_X - T[0, 3]) / ego_dir[..., 0]
    return np.where((ego_dir[..., 0] > 1e-6) & (t < 200), t, 0.0)


def _expected_voxels(cam: Camera, depth: np.ndarray, grid) -> set[tuple[int, int, int]]:
    K, T = cam.intrinsics.K, cam.sensor_to_ego
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    pts = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) * depth[..., None]
    ego = pts @ T[:3, :3].T + T[:3, 3]
    idx = np.floor((ego - np.array(grid.origin)) / grid.voxel_size).astype(int)
    ok = (depth > 0) & np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=-1)
    return {tuple(i) for i in idx[ok]}


def _occupied(occupancy: torch.Tensor) -> set[tuple[int, int, int]]:
    return {tuple(i) for i in torch.nonzero(occupancy > 0).tolist()}


def test_pinhole_plane_lands_in_the_exact_voxels():
    # a 64x48 camera 1.5 m high looking forward; VoxFormer grid: x index floor(10.1 / 0.2) = 50
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    cam = Camera("front", Pinhole(64, 48, K), camera_mount(0.0, np.array([0.0, 0.0, 1.5])))
    depth = _plane_depth_pinhole(cam)
    assert np.allclose(depth, PLANE_X)  # fronto-parallel wall: constant z
    module = DepthToVoxelProposals(rig_frame="lidar")  # the constructed rig's frame stands in for the LiDAR's
    out = module(torch.from_numpy(depth)[None, None], [cam.intrinsics],
                 torch.from_numpy(cam.sensor_to_ego)[None, None])
    occ = _occupied(out["occupancy"][0])
    assert {i[0] for i in occ} == {50}
    assert occ == _expected_voxels(cam, depth, VOXFORMER_GRID)
    # by hand, pixel (u, v) = (0, 30): ego y = 31.5 / 40 * 10.1 = 7.954 (left), z = 1.5 - 6.5 / 40 * 10.1 = -0.141
    # -> voxel (50, floor((7.954 + 25.6) / 0.2), floor((-0.141 + 2) / 0.2)) = (50, 167, 9)
    assert (50, 167, 9) in occ
    # coarse occupancy: half resolution, a coarse voxel is set exactly when it holds an occupied fine voxel;
    # without a query-proposal network there are no "proposals"
    assert out["coarse_occupancy"].shape == (1, 128, 128, 16) and "proposals" not in out
    assert _occupied(out["coarse_occupancy"][0]) == {(i // 2, j // 2, k // 2) for i, j, k in occ}
    assert proposal_indices(out["coarse_occupancy"])[0].shape == (len(_occupied(out["coarse_occupancy"][0])), 3)


def test_fisheye_virtual_views_and_raw_fisheye_place_the_plane_correctly():
    # the front 220-degree fisheye of the urban preset, small; Occ3D grid: x index floor((10.1 + 40) / 0.4) = 125
    fisheye = preset_cameras("urban-fisheye", scale=0.16)[0]
    left, right = virtual_pinholes(fisheye)
    module = DepthToVoxelProposals(OCC3D_NUSCENES_GRID)
    views = [left, right]
    h = max(v.height for v in views)
    w = max(v.width for v in views)
    views = [Camera(v.name, _recentred(v.intrinsics, w, h), v.sensor_to_ego) for v in views]
    depth = np.stack([_plane_depth_pinhole(v) for v in views])
    s2e = torch.from_numpy(np.stack([v.sensor_to_ego for v in views]))
    out = module(torch.from_numpy(depth)[None], [v.intrinsics for v in views], s2e)
    occ = _occupied(out["occupancy"][0])
    expected = _expected_voxels(views[0], depth[0], OCC3D_NUSCENES_GRID) | _expected_voxels(
        views[1], depth[1], OCC3D_NUSCENES_GRID)
    assert {i[0] for i in occ} == {125}
    assert occ == expected and len(occ) > 50

    # the raw fisheye (depth = range along the ray) gives the same wall at x index 125 and covers it fully
    rays, valid = fisheye.intrinsics.ray_grid()
    ego_dir = rays.numpy() @ fisheye.sensor_to_ego[:3, :3].T
    with np.errstate(divide="ignore"):
        rng = (PLANE_X - fisheye.sensor_to_ego[0, 3]) / ego_dir[..., 0]
    depth_f = np.where(valid.numpy() & (ego_dir[..., 0] > 0.05), rng, 0.0)
    grid = module.grid
    out_f = module(torch.from_numpy(depth_f)[None, None], [fisheye.intrinsics],
                   torch.from_numpy(fisheye.sensor_to_ego)[None, None])
    occ_f = _occupied(out_f["occupancy"][0])
    assert {i[0] for i in occ_f} == {125}
    # every (y, z) cell of the wall within +-4 m and 0..3 m height is hit (the fisheye sees all of it)
    wall = {(125, j, k) for j in range(int(36 / 0.4), int(44 / 0.4)) for k in range(int(1 / 0.4) + 1,
                                                                                   int(4 / 0.4))}
    assert wall <= occ_f
    assert grid.shape == (200, 200, 16) and np.allclose(grid.upper, (40.0, 40.0, 5.4))


def _recentred(model: Pinhole, w: int, h: int) -> Pinhole:
    """The same pinhole on a (w, h) canvas with the principal point moved to the canvas centre."""
    K = np.array(model.K, dtype=np.float64)
    K[0, 2] += (w - model.width) / 2
    K[1, 2] += (h - model.height) / 2
    return Pinhole(w, h, K, None)


def test_prior_replaces_depth_only_where_confident():
    depth = torch.full((1, 1, 2, 2), 20.0)
    prior = torch.tensor([[[[0.0, 8.0], [9.0, 10.0]]]])
    conf = torch.tensor([[[[1.0, 0.9], [0.2, 0.5]]]])
    assert fuse_depth_with_prior(depth, prior).flatten().tolist() == [20.0, 8.0, 9.0, 10.0]
    assert fuse_depth_with_prior(depth, prior, conf, 0.5).flatten().tolist() == [20.0, 8.0, 20.0, 10.0]
    # in the module the fused depth is what gets voxelised
    cam = Camera("c", Pinhole(2, 2, np.array([[8.0, 0, 0.5], [0, 8.0, 0.5], [0, 0, 1]])),
                 camera_mount(0.0, np.array([0.0, 0.0, 1.0])))
    out = DepthToVoxelProposals(rig_frame="lidar")(depth, [cam.intrinsics],
                                                   torch.from_numpy(cam.sensor_to_ego)[None, None],
                                                   prior=prior, confidence=conf)
    assert out["depth"].flatten().tolist() == [20.0, 8.0, 20.0, 10.0]
    # x indices floor(d / 0.2): 20 m -> 100 (twice), 8 m -> 40, 10 m -> 50
    assert sorted(i[0] for i in _occupied(out["occupancy"][0])) == [40, 50, 100, 100]


def test_inputs_of_the_wrong_kind_or_shape_are_one_clear_error():
    cam = Camera("c", Pinhole(4, 2, np.array([[8.0, 0, 2.0], [0, 8.0, 1.0], [0, 0, 1]])),
                 camera_mount(0.0, np.array([0.0, 0.0, 1.0])))
    stage1 = DepthToVoxelProposals(rig_frame="lidar")
    depth, pose = torch.full((1, 1, 2, 4), 10.0), torch.from_numpy(cam.sensor_to_ego)[None, None]
    assert stage1(depth, [cam.intrinsics], pose)["occupancy"].sum() > 0
    bad = [  # before: an unpacking error, torch size errors, an IndexError, a TypeError from torch.arange
        ((depth[0], [cam.intrinsics], pose), {}, ValueError,
         r"depth must be \[B, N, H, W\] metres, got shape \[1, 2, 4\]"),
        ((depth, [cam.intrinsics], pose), {"prior": torch.zeros(1, 1, 2, 2)}, ValueError,
         r"prior must have the depth's shape \[1, 1, 2, 4\], got \[1, 1, 2, 2\]"),
        ((depth, [cam.intrinsics], pose), {"confidence": [[1.0]]}, TypeError,
         "confidence must be a torch.Tensor, got list"),
        ((depth, [cam.intrinsics], pose[..., :3, :3]), {}, ValueError,
         r"sensor_to_ego must be \[1, 1, 4, 4\] or \[1, 4, 4\], got \[1, 1, 3, 3\]"),
        ((depth.numpy(), [cam.intrinsics], pose), {}, TypeError, "depth must be a torch.Tensor, got ndarray"),
    ]
    for args, kwargs, kind, message in bad:
        with pytest.raises(kind, match=message):
            stage1(*args, **kwargs)


def test_proposal_depth_loss_by_hand():
    pred = torch.tensor([[[[10.0, 12.0], [5.0, 7.0]]]])
    gt = torch.tensor([[[[11.0, 0.0], [5.5, 0.0]]]])
    prior = torch.tensor([[[[0.0, 10.0], [0.0, 0.0]]]])
    assert proposal_depth_loss(pred, gt).item() == pytest.approx((1.0 + 0.5) / 2)
    assert proposal_depth_loss(pred, gt, prior).item() == pytest.approx(0.75 + 0.005 * 2.0)


def test_grid_presets():
    assert VOXFORMER_GRID.shape == (256, 256, 32) and VOXFORMER_GRID.voxel_size == 0.2
    assert np.allclose(VOXFORMER_GRID.upper, (51.2, 25.6, 4.4))
    with pytest.raises(ValueError, match="divisible"):
        DepthToVoxelProposals(OCC3D_NUSCENES_GRID, proposal_stride=3)


def test_mock_occupancy_head_learns_from_the_proposals():
    # predicted depth off by 15 %, prior exact on the left half: proposals from the fused depth feed the head
    from mock_bev import OccupancyHead

    K = np.array([[20.0, 0, 15.5], [0, 20.0, 11.5], [0, 0, 1]])
    cam = Camera("front", Pinhole(32, 24, K), camera_mount(0.0, np.array([0.0, 0.0, 1.5])))
    grid = VoxelGrid((0.0, -8.0, -2.0), 0.5, (32, 32, 8))
    truth = torch.from_numpy(_plane_depth_pinhole(cam))[None, None].float()
    prior = truth.clone()
    prior[..., 16:] = 0.0
    module = DepthToVoxelProposals(grid)
    s2e = torch.from_numpy(cam.sensor_to_ego)[None, None].float()
    target = module(truth, [cam.intrinsics], s2e)["coarse_occupancy"]
    fused = module(truth * 1.15, [cam.intrinsics], s2e, prior=prior)
    plain = module(truth * 1.15, [cam.intrinsics], s2e)
    iou = lambda a, b: float((a * b).sum() / ((a + b) > 0).sum())  # noqa: E731
    assert iou(fused["coarse_occupancy"], target) > iou(plain["coarse_occupancy"], target)
    torch.manual_seed(0)
    head = OccupancyHead()
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        loss = OccupancyHead.loss(head(fused["coarse_occupancy"]), target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
