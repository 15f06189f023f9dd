"""Self-supervised view synthesis: warping rendered frames, SSIM, min-reprojection, auto-mask, gradients (~10 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sgde_plugin.cameras import Camera, KannalaBrandt
from sgde_plugin.geometry import invert_transform
from sgde_plugin.nn import depth_rays
from sgde_plugin.nn.photometric import (
    UNSEEN,
    PhotometricConfig,
    PhotometricLoss,
    SourceView,
    edge_aware_smoothness,
    inverse_warp,
    min_reprojection,
    photometric_error,
    pixel_loss,
    ssim_distance,
)
from sgde_plugin.synth.presets import preset_cameras
from sgde_plugin.synth.render import render
from sgde_plugin.synth.world import build_world


def _kannala_brandt() -> Camera:
    base = preset_cameras("urban-fisheye", scale=0.16)[0]
    w = h = 128
    f = (w / 2 - 2) / math.radians(100)  # 200-degree circle inside the image
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    return Camera(base.name, KannalaBrandt(w, h, K, np.array([0.02, -0.01, 0.0, 0.0]), 200.0), base.sensor_to_ego)


CAMERAS = {
    "pinhole": lambda: preset_cameras("nuscenes")[0].resized(160, 90),
    "ocam": lambda: preset_cameras("urban-fisheye", scale=0.16)[0],
    "kannala_brandt": _kannala_brandt,
}


def _tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).float().div(255).permute(2, 0, 1)[None]


@pytest.fixture(scope="module")
def world():
    return build_world(0)


@pytest.mark.parametrize("kind", list(CAMERAS))
def test_warping_a_rendered_frame_with_true_depth_reproduces_it(world, kind):
    cam = CAMERAS[kind]()
    # the camera 0.1 s later (0.6 m down the street), static scene: the source is exactly the target's world
    img0, d0 = render(world, cam, world.ego_pose(0.0), 0.0, supersample=2)
    img1, d1 = render(world, cam, world.ego_pose(0.1), 0.0, supersample=2)
    c2w0, c2w1 = world.ego_pose(0.0) @ cam.sensor_to_ego, world.ego_pose(0.1) @ cam.sensor_to_ego
    T = torch.tensor(invert_transform(c2w1) @ c2w0, dtype=torch.float32)[None]
    rays, target, source = depth_rays(cam.intrinsics), _tensor(img0), _tensor(img1)
    depth = torch.from_numpy(d0)[None, None]
    warped, seen = inverse_warp(source, depth, rays, cam.intrinsics, T)
    # where both see the scene: the point is in the source's view and not hidden there (source depth agrees)
    src_depth, _ = inverse_warp(torch.from_numpy(d1)[None, None], depth, rays, cam.intrinsics, T)
    moved = (T[0, :3, :3] @ (rays * depth).reshape(3, -1) + T[0, :3, 3:]).T
    expected = cam.intrinsics.depth_torch(moved).reshape(depth.shape)
    both = seen & (depth > 0) & ((src_depth - expected).abs() < 0.02 * expected)
    assert float(both.float().mean()) > 0.3
    err = photometric_error(warped, target)[both]
    l1 = (warped - target).abs().mean(1, keepdim=True)[both]
    assert float(l1.mean()) < 0.015  # colour difference of bilinear resampling only
    assert float(err.median()) < 0.015
    # the error is a measure of depth: 30 % too far, or not warping at all, is clearly worse
    wrong = photometric_error(inverse_warp(source, depth * 1.3, rays, cam.intrinsics, T)[0], target)[both]
    assert float(wrong.median()) > 2 * float(err.median())
    assert float(photometric_error(source, target)[both].median()) > 4 * float(err.median())


def test_identity_pose_warp_is_the_identity():
    cam = CAMERAS["pinhole"]().intrinsics
    img = torch.rand(2, 3, cam.height, cam.width)
    depth = torch.rand(2, 1, cam.height, cam.width) * 30 + 1
    warped, seen = inverse_warp(img, depth, depth_rays(cam), cam, torch.eye(4).expand(2, 4, 4))
    assert bool(seen.all())
    assert torch.allclose(warped, img, atol=1e-4)


def test_ssim_against_hand_values():
    a, b = torch.full((1, 1, 5, 5), 0.2, dtype=torch.float64), torch.full((1, 1, 5, 5), 0.6, dtype=torch.float64)
    # constant windows: SSIM = (2 a b + C1) / (a^2 + b^2 + C1), the contrast term is 1
    ssim = (2 * 0.2 * 0.6 + 1e-4) / (0.04 + 0.36 + 1e-4)
    assert torch.allclose(ssim_distance(a, b), torch.full_like(a, (1 - ssim) / 2), atol=1e-6)
    x = torch.rand(1, 3, 8, 8)
    assert float(ssim_distance(x, x).abs().max()) < 1e-5
    # alpha = 0.85 mixes it with L1
    assert torch.allclose(photometric_error(a, b), torch.full_like(a, 0.85 * (1 - ssim) / 2 + 0.15 * 0.4), atol=1e-6)


def test_min_reprojection_and_automask_semantics():
    # 4 pixels, 2 sources: the minimum is taken per pixel; a pixel no source sees is dropped
    errors = torch.tensor([[[0.3, 0.1, UNSEEN, 0.5]], [[0.2, 0.4, UNSEEN, 0.05]]]).reshape(1, 2, 1, 4)
    best, use = min_reprojection(errors)
    assert torch.allclose(best.flatten(), torch.tensor([0.2, 0.1, UNSEEN, 0.05]))
    assert use.flatten().tolist() == [True, True, False, True]
    # auto-mask: pixels whose unwarped temporal error is lower (or equal: nothing moved) are dropped
    identity = torch.tensor([0.25, 0.05, 0.3, 0.05]).reshape(1, 1, 1, 4)
    _, use = min_reprojection(errors, identity)
    assert use.flatten().tolist() == [True, False, False, False]


def test_pixel_loss_keeps_masked_and_unseen_pixels_at_their_identity_error():
    errors = torch.tensor([[[0.3, 0.1, UNSEEN, 0.5]], [[0.2, 0.4, UNSEEN, 0.05]]]).reshape(1, 2, 1, 4)
    identity = torch.tensor([0.25, 0.05, 0.3, 0.05]).reshape(1, 1, 1, 4)
    loss, counted = pixel_loss(errors, identity)
    # used pixel: its best warped error; auto-masked (0.1 > 0.05, tie 0.05) and unseen: the identity error
    assert torch.allclose(loss.flatten(), torch.tensor([0.2, 0.05, 0.3, 0.05]))
    assert bool(counted.all())
    # without temporal sources only the seen pixels count
    loss, counted = pixel_loss(errors)
    assert counted.flatten().tolist() == [True, True, False, True]


def test_dropping_pixels_out_of_view_lowered_the_old_loss_and_raises_the_new():
    """The old recipe's failure mode, constructed: a mean over the pixels still used rewards a depth that
    throws badly matched pixels out of the loss (here out of view; at infinity the warp is the identity
    and the auto-mask drops them). The loss now keeps such pixels at their identity error."""
    cam = CAMERAS["pinhole"]().intrinsics
    h, w = cam.height, cam.width
    torch.manual_seed(0)
    target = torch.rand(1, 3, h, w)
    pose = torch.eye(4)[None]
    pose[0, 0, 3] = 2 * 10.0 / float(cam.K[0, 0])  # at 10 m every pixel moves by 2 px
    src = torch.zeros_like(target)
    src[..., 2:] = target[..., :-2]
    noisy_left = torch.where(torch.arange(w) < w // 2, 0.15, 0.02)  # the left half matches worse
    src = (src + torch.randn(1, 3, h, w) * noisy_left).clamp(0, 1)
    rays = depth_rays(cam)
    true = torch.full((1, 1, h, w), 10.0)
    gamed = true.clone()
    gamed[..., : w // 2] = 0.1  # the left half thrown out of the source's view

    def old(depth: torch.Tensor) -> float:
        warped, seen = inverse_warp(src, depth, rays, cam, pose)
        err = torch.where(seen, photometric_error(warped, target), torch.full_like(depth, UNSEEN))
        best, use = min_reprojection(err, photometric_error(src, target))
        return float((best * use).sum() / use.sum())

    new = PhotometricLoss(PhotometricConfig(smoothness=0.0))
    view = [SourceView(src, cam, pose, temporal=True)]
    assert old(gamed) < 0.5 * old(true)  # 0.009 < 0.038: rewarded
    assert float(new([gamed], target, rays, view)) > 3 * float(new([true], target, rays, view))  # 0.255 > 0.043


def test_loss_masks_sources_and_target():
    torch.manual_seed(0)
    cam = CAMERAS["pinhole"]().intrinsics
    h, w = cam.height, cam.width
    target = torch.rand(1, 3, h, w)
    depth = torch.full((1, 1, h, w), 10.0)
    loss = PhotometricLoss(PhotometricConfig(smoothness=0.0, automask=False))
    same = SourceView(target.clone(), cam, torch.eye(4)[None], temporal=False)
    noise = SourceView(torch.rand(1, 3, h, w), cam, torch.eye(4)[None], temporal=False)
    assert float(loss([depth], target, depth_rays(cam), [same])) < 1e-5
    assert float(loss([depth], target, depth_rays(cam), [noise])) > 0.1
    # a source masked out (ego body) is never used: only the noisy source remains
    body = torch.zeros(1, 1, h, w, dtype=bool)
    masked = SourceView(target.clone(), cam, torch.eye(4)[None], temporal=False, mask=body)
    assert float(loss([depth], target, depth_rays(cam), [masked, noise])) == pytest.approx(
        float(loss([depth], target, depth_rays(cam), [noise])), rel=1e-6)
    # target mask: only the left half counts; the right half's source is noise
    half = torch.zeros(1, 1, h, w, dtype=bool)
    half[..., : w // 2] = True
    mixed = torch.where(half, target, torch.rand(1, 3, h, w))
    src = SourceView(mixed, cam, torch.eye(4)[None], temporal=False)
    assert float(loss([depth], target, depth_rays(cam), [src], mask=half)) < 0.02
    # switching the only kind off is refused
    with pytest.raises(ValueError):
        PhotometricLoss(PhotometricConfig(spatial=False))([depth], target, depth_rays(cam), [same])


def test_gradients_reach_depth_and_point_to_the_truth(world):
    cam = CAMERAS["pinhole"]()
    img0, d0 = render(world, cam, world.ego_pose(0.0), 0.0, supersample=2)
    img1, _ = render(world, cam, world.ego_pose(0.1), 0.0, supersample=2)
    T = torch.tensor(invert_transform(world.ego_pose(0.1) @ cam.sensor_to_ego) @ world.ego_pose(0.0)
                     @ cam.sensor_to_ego, dtype=torch.float32)[None]
    gt = torch.from_numpy(np.where(d0 > 0, d0, 200.0))[None, None]
    scale = torch.tensor(1.3, requires_grad=True)
    source = SourceView(_tensor(img1), cam.intrinsics, T, temporal=True)
    loss = PhotometricLoss()([gt * scale, (gt * scale)[..., ::2, ::2]], _tensor(img0), depth_rays(cam.intrinsics),
                             [source])
    loss.backward()
    assert scale.grad is not None and math.isfinite(float(scale.grad))
    assert float(scale.grad) > 0  # too far: the loss falls as the depth shrinks towards the truth
    depth = (gt * 1.0).requires_grad_(True)
    PhotometricLoss()([depth], _tensor(img0), depth_rays(cam.intrinsics), [source]).backward()
    assert float(depth.grad.abs().sum()) > 0 and bool(torch.isfinite(depth.grad).all())


def test_edge_aware_smoothness_hand_value():
    disp = torch.tensor([[[[1.0, 3.0], [1.0, 3.0]]]])  # mean 2 -> normalised [0.5, 1.5]
    flat = torch.zeros(1, 3, 2, 2)
    # x: |1.5 - 0.5| = 1 at both rows, weight exp(0); y: 0
    assert float(edge_aware_smoothness(disp, flat)) == pytest.approx(1.0, rel=1e-5)
    edge = flat.clone()
    edge[..., 1] = 1.0  # an image edge where the disparity jumps: weight exp(-1)
    assert float(edge_aware_smoothness(disp, edge)) == pytest.approx(math.exp(-1), rel=1e-5)
