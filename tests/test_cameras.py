"""Camera models: round trips, agreement with OpenCV, torch vs NumPy, gradients."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from sgde_plugin.cameras import KannalaBrandt, Ocam, Pinhole, pixel_grid
from sgde_plugin.errors import InputError
from sgde_plugin.rigfile import intrinsics_from_dict

K_PIN = np.array([[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 0.0012, -0.0009, -0.015])
K_FISH = np.array([[232.0, 0.3, 399.2], [0.0, 231.0, 383.6], [0.0, 0.0, 1.0]])
KB_DIST = np.array([0.012, -0.0045, 0.0008, -0.00006])


def ocam_220() -> Ocam:
    """An ocam camera close to a Synthetic Urban 220-degree fisheye, with inv_poly fitted to poly."""
    f = 205.0  # px per radian of incidence: 110 degrees at rho = 395 px
    rho = np.linspace(1.0, 430.0, 400)
    poly = np.polyfit(rho, -rho / np.tan(rho / f), 5)[::-1]
    z = np.polyval(poly[::-1], rho)
    theta = np.arctan2(z, rho)
    inv_poly = np.polyfit(theta, rho, 9)[::-1]
    return Ocam(800, 768, poly, inv_poly, np.array([383.7, 400.2]), np.array([1.0004, 0.0003, -0.0002]), 220.0)


CAMERAS = {
    "pinhole": Pinhole(1600, 900, K_PIN, None),
    "pinhole_dist": Pinhole(1600, 900, K_PIN, DIST),
    "kannala_brandt": KannalaBrandt(800, 768, K_FISH, KB_DIST, 220.0),
    "equidistant": KannalaBrandt(640, 640, np.array([[200.0, 0, 319.5], [0, 200.0, 319.5], [0, 0, 1]]), fov_deg=200),
    "ocam": ocam_220(),
}


@pytest.mark.parametrize("name", list(CAMERAS))
def test_round_trip_whole_image(name: str) -> None:
    cam = CAMERAS[name]
    uv = pixel_grid(cam.width, cam.height).reshape(-1, 2).numpy()
    rays, valid = cam.unproject(uv)
    assert valid.mean() > 0.5
    np.testing.assert_allclose(np.linalg.norm(rays[valid], axis=1), 1.0, atol=1e-12)
    for distance in (0.7, 13.0, 150.0):
        back, valid2 = cam.project(rays * distance)
        assert np.all(valid2[valid]), "an unprojected ray must project back as valid"
        err = np.abs(back[valid] - uv[valid]).max()
        assert err < 0.01, f"{name}: round trip error {err} px"


@pytest.mark.parametrize("name", ["kannala_brandt", "equidistant", "ocam"])
def test_fisheye_sees_beyond_90_degrees(name: str) -> None:
    cam = CAMERAS[name]
    half = math.radians(cam.fov_deg / 2) - 1e-3
    angles = np.linspace(math.radians(91), half, 50)
    az = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    A, Z = np.meshgrid(angles, az)
    rays = np.stack([np.sin(A) * np.cos(Z), np.sin(A) * np.sin(Z), np.cos(A)], -1).reshape(-1, 3)
    uv, valid = cam.project(rays * 4.0)
    inside = valid  # some may fall outside the sensor rectangle
    assert inside.sum() > 100
    back, v2 = cam.unproject(uv[inside])
    assert v2.all()
    np.testing.assert_allclose(back, rays[inside], atol=1e-6)
    # and a ray beyond the field of view is invalid
    beyond = np.array([[math.sin(half + 0.05), 0.0, math.cos(half + 0.05)]])
    assert not cam.project(beyond)[1][0]


def test_pinhole_matches_opencv() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([-8, -4, 2], [8, 4, 40], size=(2000, 3))
    uv, _ = CAMERAS["pinhole_dist"].project(pts)
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_PIN, DIST)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-3


def test_kannala_brandt_matches_opencv_fisheye() -> None:
    rng = np.random.default_rng(1)
    theta = rng.uniform(0.0, math.radians(80), 2000)
    phi = rng.uniform(0, 2 * np.pi, 2000)
    pts = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1) * 5.0
    uv, _ = CAMERAS["kannala_brandt"].project(pts)
    alpha = K_FISH[0, 1] / K_FISH[0, 0]
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_FISH, KB_DIST, alpha=alpha)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-3


@pytest.mark.parametrize("name", list(CAMERAS))
def test_torch_float32_agrees_with_numpy(name: str) -> None:
    cam = CAMERAS[name]
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(500, 2))
    rays_np, valid = cam.unproject(uv)
    rays_t, valid_t = cam.unproject_torch(torch.tensor(uv, dtype=torch.float32))
    assert np.array_equal(valid, valid_t.numpy())
    assert np.abs(rays_t.numpy()[valid] - rays_np[valid]).max() < 1e-5
    pts = rays_np[valid] * 7.0
    uv_np, _ = cam.project(pts)
    uv_t, _ = cam.project_torch(torch.tensor(pts, dtype=torch.float32))
    # 1e-5 relative to the image size: float32 carries ~7 significant digits of pixel coordinates
    assert np.abs(uv_t.numpy() - uv_np).max() / max(cam.width, cam.height) < 1e-5


@pytest.mark.parametrize("name", list(CAMERAS))
def test_gradcheck_float64(name: str) -> None:
    cam = CAMERAS[name]
    pts = torch.tensor([[0.3, -0.2, 4.0], [-1.0, 0.5, 3.0], [2.0, 1.0, 6.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: cam.project_torch(p)[0], (pts,))
    uv = torch.tensor([[100.5, 200.25], [400.0, 300.0], [700.0, 50.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: cam.unproject_torch(p)[0], (uv,))


def test_ocam_projection_converges_from_a_rough_inverse_polynomial() -> None:
    """Projection starts from inv_poly and refines on poly until its steps are at rounding level: a start pixels
    off (inv_poly shifted by 3 px) still comes back to the unprojected pixel to 1e-11 px, as an exact start does."""
    exact = CAMERAS["ocam"]
    rough_inv = np.array(exact.inv_poly, dtype=float)
    rough_inv[0] += 3.0
    rough = Ocam(exact.width, exact.height, exact.poly, rough_inv, exact.center, exact.affine, exact.fov_deg)
    uv = pixel_grid(exact.width, exact.height).reshape(-1, 2).numpy()[::7]
    rays, valid = exact.unproject(uv)
    for cam in (exact, rough):
        back, ok = cam.project(rays * 9.0)
        assert ok[valid].all() and np.abs(back[valid] - uv[valid]).max() < 1e-11


def test_ocam_gives_the_same_bits_with_and_without_gradients() -> None:
    """The polynomial runs in place when no gradient is wanted (maps) and out of place for autograd: same values."""
    cam = CAMERAS["ocam"]
    rng = np.random.default_rng(5)
    uv = torch.tensor(rng.uniform([0, 0], [cam.width - 1, cam.height - 1], size=(4000, 2)))
    with torch.no_grad():
        rays, valid = cam.unproject_torch(uv)
        plain, ok = cam.project_torch(rays * 5.0)
    pts = (rays * 5.0).requires_grad_()
    tracked, ok_tracked = cam.project_torch(pts)
    rays_tracked, _ = cam.unproject_torch(uv.clone().requires_grad_())
    assert valid.sum() > 3000 and torch.equal(ok, ok_tracked)
    assert torch.equal(plain, tracked.detach()) and torch.equal(rays, rays_tracked.detach())
    tracked[ok].sum().backward()
    assert torch.isfinite(pts.grad).all() and pts.grad.abs().sum() > 0


def test_resized_camera_sees_the_same_rays() -> None:
    for name, cam in CAMERAS.items():
        small = cam.resized(cam.width // 2, cam.height // 2)
        uv = np.array([[10.0, 20.0], [cam.width / 2, cam.height / 3]])
        rays, _ = cam.unproject(uv)
        uv_small, _ = small.project(rays)
        np.testing.assert_allclose(uv_small, (uv + 0.5) / 2 - 0.5, atol=1e-6, err_msg=name)


def test_depth_conventions() -> None:
    p = np.array([[3.0, 4.0, 12.0]])
    assert CAMERAS["pinhole"].depth(p)[0] == 12.0
    assert CAMERAS["ocam"].depth(p)[0] == 13.0
    uv, _ = CAMERAS["kannala_brandt"].project(p)
    back, ok = CAMERAS["kannala_brandt"].points_from_depth(uv, np.array([13.0]))
    assert ok[0] and np.allclose(back, p, atol=1e-9)
    uv, _ = CAMERAS["pinhole_dist"].project(p)
    back, ok = CAMERAS["pinhole_dist"].points_from_depth(uv, np.array([12.0]))
    assert ok[0] and np.allclose(back, p, atol=1e-9)


@pytest.mark.parametrize(
    "entry,key",
    [
        ({"model": "pinhole", "width": 10, "height": 10, "K": [[1, 0, 5], [0, 1, 5]]}, "K"),
        ({"model": "pinhole", "width": 10, "height": 10, "K": [[0, 0, 5], [0, 1, 5], [0, 0, 1]]}, "K"),
        ({"model": "fisheye9", "width": 10, "height": 10}, "model"),
        ({"model": "kannala_brandt", "width": 10, "height": 10, "K": np.eye(3).tolist(), "dist": [0, 0]}, "dist"),
        ({"model": "ocam", "width": 10, "height": 10, "poly": [-1], "inv_poly": [1], "center": [5, 5],
          "affine": [1, 0, 0]}, "fov_deg"),
    ],
)
def test_bad_intrinsics_name_the_key(entry: dict, key: str) -> None:
    with pytest.raises(InputError) as err:
        intrinsics_from_dict(entry, "cameras[X]")
    assert err.value.key == f"cameras[X].{key}"
