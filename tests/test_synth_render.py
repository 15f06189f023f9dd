"""Synthetic world rendering: presets, depth conventions against hand-computed geometry, moving cars.

Runtime: about 5 s on 2 cores (tiny images).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.geometry import camera_mount, rotation_angle_deg
from sgde_plugin.pairs import pair_geometry
from sgde_plugin.synth.presets import PRESETS, equidistant_ocam, preset_cameras, preset_ring
from sgde_plugin.synth.render import render
from sgde_plugin.synth.world import build_world

NUSCENES_YAWS = [0.0, -55.0, -110.0, 180.0, 110.0, 55.0]


def _empty(world, with_boxes: np.ndarray | None = None):
    """The world with no primitives but the ground (and optionally the listed boxes)."""
    keep = np.zeros(world.n_boxes, dtype=bool) if with_boxes is None else with_boxes
    fields = {k: getattr(world, k)[keep] for k in (
        "box_center", "box_half", "box_yaw", "box_velocity", "box_material", "box_color", "box_params",
        "box_tex_offset")}
    poles = {k: getattr(world, k)[:0] for k in ("pole_xy", "pole_radius", "pole_height", "pole_color")}
    return dataclasses.replace(world, **fields, **poles)


def test_preset_rings_sizes_and_yaws():
    assert preset_ring("nuscenes") == ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK",
                                       "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]
    assert preset_ring("ddad") == ["CAMERA_01", "CAMERA_06", "CAMERA_08", "CAMERA_09", "CAMERA_07", "CAMERA_05"]
    assert preset_ring("urban-fisheye") == ["F", "R", "B", "L"]
    cams = preset_cameras("nuscenes")
    assert [(c.width, c.height) for c in cams] == [(1600, 900)] * 6
    for cam, yaw in zip(cams, NUSCENES_YAWS):
        axis = cam.sensor_to_ego[:3, 2]
        assert math.degrees(math.atan2(axis[1], axis[0])) == pytest.approx(yaw if yaw != 180 else 180.0, abs=1e-9) \
            or abs(abs(math.degrees(math.atan2(axis[1], axis[0]))) - 180) < 1e-9
        assert 1.4 < cam.sensor_to_ego[2, 3] < 1.7
    fovs = [c.intrinsics.hfov_deg for c in cams]
    assert all(64 <= f <= 70 for i, f in enumerate(fovs) if i != 3)
    assert 85 <= fovs[3] <= 115
    half = preset_cameras("ddad", 0.5)
    assert (half[0].width, half[0].height) == (968, 608)
    fish = preset_cameras("urban-fisheye", 0.5)
    assert (fish[0].width, fish[0].height) == (400, 384) and fish[0].intrinsics.fov_deg == 220


@pytest.mark.parametrize("preset", PRESETS)
def test_adjacent_pairs_overlap(preset):
    cams = {c.name: c for c in preset_cameras(preset, 0.25)}
    ring = preset_ring(preset)
    sectors = [pair_geometry(cams[a], cams[b], samples=80).sector_deg for a, b in zip(ring, ring[1:] + ring[:1])]
    if preset == "urban-fisheye":
        assert all(120 <= s <= 140 for s in sectors)  # 220 - 90 degrees
    elif preset == "random":  # 5-30 degree overlaps by design (seed 0), pitch and roll widen the sector a little
        assert all(4 <= s <= 32 for s in sectors), sectors
    else:
        assert all(5 <= s <= 20 for s in sectors), sectors


def test_equidistant_ocam_is_consistent():
    model = equidistant_ocam(200, 192, 220.0)
    theta = np.radians(np.array([0.0, 30.0, 60.0, 90.0, 105.0, 109.0]))
    pts = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1) * 7.0
    uv, valid = model.project(pts)
    assert valid.all()
    rho = uv[:, 0] - (200 - 1) / 2
    f = (96 - 4.0) / math.radians(110)
    np.testing.assert_allclose(rho, f * theta, atol=0.05)  # equidistant within 0.05 px
    # the inverse polynomial alone (the Newton start) already lands within 0.05 px
    elevation = theta - math.pi / 2
    np.testing.assert_allclose(np.polynomial.polynomial.polyval(elevation, model.inv_poly), rho, atol=0.05)
    rays, ok = model.unproject(uv)
    assert ok.all()
    np.testing.assert_allclose(rays, pts / 7.0, atol=1e-9)


def test_pinhole_ground_depth_is_z():
    """A level pinhole at height h sees the ground at z = h * fy / (v - cy) below the horizon, sky above."""
    world = _empty(build_world(0))
    h = 1.5
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    cam = Camera("c", Pinhole(64, 48, K), camera_mount(0.3, np.array([0.0, 0.0, h])))
    rgb, depth = render(world, cam, np.eye(4), 0.0)
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8 and depth.dtype == np.float32
    v = np.arange(48, dtype=np.float64)
    below = v > 23.5 + 1e-9
    expected = np.where(below, h * 50.0 / np.where(below, v - 23.5, 1.0), 0.0)
    expected = np.where(expected <= 250.0, expected, 0.0)
    np.testing.assert_allclose(depth, np.repeat(expected[:, None], 64, axis=1), rtol=2e-6)
    assert (depth[:24] == 0).all() and (depth[24:] > 0).all()
    # the sky is a gradient (brighter near the horizon), never black
    assert rgb[:24].min() > 60 and rgb[0].mean() < rgb[23].mean()


def test_fisheye_ground_depth_is_range():
    """An ocam fisheye: depth is the range h / sin(depression) of the ray that hits the ground."""
    world = _empty(build_world(0))
    h = 1.6
    model = equidistant_ocam(96, 96, 220.0, margin_px=1.0)
    cam = Camera("f", model, camera_mount(-1.0, np.array([0.3, 0.2, h])))
    _, depth = render(world, cam, np.eye(4), 0.0)
    rays, valid = model.ray_grid()
    rays = rays.numpy() @ cam.sensor_to_ego[:3, :3].T
    down = valid.numpy() & (rays[..., 2] < -0.01)
    expected = h / -rays[..., 2]
    hit = down & (expected <= 250.0)
    np.testing.assert_allclose(depth[hit], expected[hit], rtol=2e-6)
    assert (depth[~valid.numpy()] == 0).all()
    assert (depth[valid.numpy() & (rays[..., 2] > 0)] == 0).all()


def test_box_face_depth_and_texture_anchoring():
    """A facade box straight ahead: pinhole depth equals the distance to its face plane; moving the
    camera sideways moves the texture in the image by exactly the parallax of that plane."""
    world = build_world(3)
    keep = np.zeros(world.n_boxes, dtype=bool)
    keep[0] = True
    world = _empty(world, keep)
    world = dataclasses.replace(
        world,
        box_center=np.array([[20.0, 0.0, 10.0]]),
        box_half=np.array([[2.0, 30.0, 10.0]]),
        box_yaw=np.zeros(1),
    )
    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    cam = Camera("c", Pinhole(64, 48, K), camera_mount(0.0, np.array([0.0, 0.0, 1.5])))
    rgb0, depth0 = render(world, cam, np.eye(4), 0.0)
    wall = depth0 > 0
    wall &= np.abs(depth0 - 18.0) < 1e-3
    assert wall[:24].all()  # the upper half (above the horizon) all sees the wall
    np.testing.assert_allclose(depth0[wall], 18.0, rtol=1e-6)
    # translate the camera 0.9 m to the left (ego +y): the wall (at 18 m) shifts by f * 0.9 / 18 = 2 px right
    moved = np.eye(4)
    moved[1, 3] = 0.9
    rgb1, depth1 = render(world, cam, moved, 0.0)
    a = rgb0[2:20, 4:56].astype(np.int32)
    b = rgb1[2:20, 6:58].astype(np.int32)
    assert np.abs(a - b).max() <= 2
    assert np.abs(rgb0[2:20, 4:56].astype(np.int32) - rgb1[2:20, 4:56]).max() > 10  # it did move


def test_moving_cars_change_place():
    world = build_world(0)
    moving = np.linalg.norm(world.box_velocity, axis=1) > 0
    assert moving.sum() >= 12  # several cars of four boxes
    np.testing.assert_allclose(world.box_centers(0.5)[~moving], world.box_center[~moving])
    assert np.all(np.linalg.norm(world.box_centers(0.5)[moving] - world.box_center[moving], axis=1) >= 2.9)
    cam = preset_cameras("nuscenes", 0.08)[0]
    pose = world.ego_pose(0.0)
    _, d0 = render(world, cam, pose, 0.0)
    _, d1 = render(world, cam, pose, 1.0)  # same ego pose, one second later
    changed = np.abs(d0 - d1) > 0.01 * np.maximum(d0, 1e-3)
    assert 0.002 < changed.mean() < 0.3


def test_ego_path_and_frame_rate():
    world = build_world(0)
    p0, p1 = world.ego_pose(0.0), world.ego_pose(0.1)
    step = np.linalg.norm(p1[:3, 3] - p0[:3, 3])
    assert step == pytest.approx(world.ego_speed * 0.1, rel=0.01)
    assert rotation_angle_deg(p0[:3, :3].T @ p1[:3, :3]) < 0.5


def test_supersampling_keeps_depth_and_smooths_colour():
    world = build_world(1)
    cam = preset_cameras("nuscenes", 0.06)[1]
    pose = world.ego_pose(0.0)
    rgb1, d1 = render(world, cam, pose, 0.0, supersample=1)
    rgb3, d3 = render(world, cam, pose, 0.0, supersample=3)
    np.testing.assert_array_equal(d1, d3)  # depth always comes from the pixel-centre ray
    diff = np.abs(rgb1.astype(int) - rgb3.astype(int))
    assert 0 < diff.mean() < 12
