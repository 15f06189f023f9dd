"""Synthetic Urban / OmniMVS reader: config.yaml + cam%d/%04d.png + two-page inverse-depth TIFFs."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sgde_plugin.cli import main
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount
from sgde_plugin.io import write_image
from sgde_plugin.readers import list_scenes, load_rig
from sgde_plugin.readers.omnimvs import panorama_rays, read_inverse_depth_tiff

W, H = 800, 768
POLY = [-196.0, 0.0, 3.0e-3, -9.5e-6, 2.2e-8]  # cam2world, ascending powers of rho
CENTER = [383.2, 399.6]  # row, col
AFFINE = [1.0005, 0.0002, -0.0003]
# cam_id: pose [rx, ry, rz, tx, ty, tz] camera-to-rig, and the same mounting in our ego frame
POSES = {
    1: ([0.0, 0.0, 0.0, 0.0, 0.0, 0.6], camera_mount(0.0, np.array([0.6, 0.0, 0.0]))),
    2: ([0.0, math.pi / 2, 0.0, 0.6, 0.0, 0.0], camera_mount(-math.pi / 2, np.array([0.0, -0.6, 0.0]))),
    # back camera rolled by 0.02 rad about its optical axis: R_y(pi) @ R_z(0.02) as a rotation vector
    3: ([*Rotation.from_euler("YZ", [math.pi, 0.02]).as_rotvec().tolist(), 0.0, 0.0, -0.6],
        camera_mount(math.pi, np.array([-0.6, 0.0, 0.0]), roll=0.02)),
    4: ([0.0, -math.pi / 2, 0.0, -0.6, 0.0, 0.0], camera_mount(math.pi / 2, np.array([0.0, 0.6, 0.0]))),
}


def inv_poly() -> list[float]:
    """world2cam: rho as a polynomial of theta = atan2(poly(rho), rho), fitted like OCamCalib does."""
    rho = np.linspace(0.0, 420.0, 400)
    theta = np.arctan2(np.polyval(POLY[::-1], rho), rho)
    return np.polyfit(theta, rho, 11)[::-1].tolist()


def write_config(folder: Path, frames: tuple[int, int] | None = (1, 2)) -> None:
    lines = ["# OmniMVS-style config", "config:", "  omnimvs_sweep_min_depth: 1.65", "dataset:",
             '  img_fmt: "cam%d/%04d.png"']
    if frames:
        lines += [f"  start: {frames[0]}", "  step: 1", f"  end: {frames[1]}"]
    lines.append("cameras:")
    inv = inv_poly()
    for cam_id, (pose, _) in POSES.items():
        lines += [f"  - cam_id: {cam_id}", f'    img_dir: "cam{cam_id}"', '    model: "ocam"',
                  f"    poly: {json.dumps([len(POLY), *POLY])}", f"    inv_poly: {json.dumps([len(inv), *inv])}",
                  f"    center: {json.dumps(CENTER)}", f"    affine: {json.dumps(AFFINE)}",
                  f"    image_size: [{H}, {W}]", f'    invalid_mask: "mask{cam_id}.png"',
                  f"    pose: {json.dumps(pose)}", "    max_fov: 220.0"]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.yaml").write_text("\n".join(lines) + "\n")


def write_panorama(path: Path, inv_depth: np.ndarray) -> None:
    thumb = np.full((inv_depth.shape[0] // 2, inv_depth.shape[1] // 2, 3), 128, np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwritemulti(str(path), [thumb, inv_depth.astype(np.float32)])


def sphere_panorama(h: int = 80, w: int = 320, radius: float = 10.0) -> np.ndarray:
    inv = np.full((h, w), 1.0 / radius, np.float32)
    inv[:3] = 0.0  # sky rows
    return inv


@pytest.fixture(scope="module")
def urban(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("sunny")
    write_config(folder)
    img = np.zeros((H, W, 3), np.uint8)
    for cam_id in POSES:
        for idx in (1, 2):
            write_image(folder / f"cam{cam_id}" / f"{idx:04d}.png", img)
    write_panorama(folder / "omnidepth_gt_320" / "00001.tiff", sphere_panorama())
    return folder


def test_exact_intrinsics_extrinsics_ring_and_frames(urban: Path) -> None:
    rig = load_rig(urban, check_images=True)
    assert rig.ring == ("cam1", "cam2", "cam3", "cam4") and len(rig.pairs) == 4
    inv = inv_poly()
    for cam_id, (_, T) in POSES.items():
        cam = rig.camera(f"cam{cam_id}")
        d = cam.intrinsics.to_dict()
        assert d == {"model": "ocam", "width": W, "height": H, "poly": POLY, "inv_poly": inv, "center": CENTER,
                     "affine": AFFINE, "fov_deg": 220.0}
        np.testing.assert_allclose(cam.sensor_to_ego, T, rtol=0, atol=1e-9)
    assert [(f.id, f.timestamp_us) for f in rig.frames] == [("0001", 1), ("0002", 2)]
    assert rig.frames[1].images["cam3"] == urban / "cam3" / "0002.png"
    assert set(rig.frames[0].depths) == {"cam1", "cam2", "cam3", "cam4"} and not rig.frames[1].depths
    assert list_scenes(urban) == [urban.name]


def test_pixel_ray_maths_match_omnimvs_formulas(urban: Path) -> None:
    """Our Ocam on the config's numbers == OmniMVS's pixelToRay / rayToPixel written out by hand."""
    cam = load_rig(urban).camera("cam1").intrinsics
    c, d, e = AFFINE
    cols, rows = np.meshgrid(np.linspace(20, 780, 9), np.linspace(20, 740, 9))
    dr, dc = rows.ravel() - CENTER[0], cols.ravel() - CENTER[1]
    a = (dr - d * dc) / (c - d * e)
    b = (-e * dr + c * dc) / (c - d * e)
    rho = np.hypot(a, b)
    omni = np.stack([b, a, -np.polyval(POLY[::-1], rho)], axis=-1)  # x = column part, y = row part
    omni /= np.linalg.norm(omni, axis=-1, keepdims=True)
    ours, valid = cam.unproject(np.stack([cols.ravel(), rows.ravel()], axis=-1))
    np.testing.assert_allclose(ours, omni, atol=1e-12)
    # rayToPixel with inv_poly only: theta measured from the xy plane towards -z
    pts = omni[valid] * 7.0
    norm = np.hypot(pts[:, 0], pts[:, 1])
    r = np.polyval(inv_poly()[::-1], np.arctan2(-pts[:, 2], norm))
    x, y = pts[:, 1] / norm * r, pts[:, 0] / norm * r
    omni_uv = np.stack([x * e + y + CENTER[1], x * c + y * d + CENTER[0]], axis=-1)
    uv, ok = cam.project(pts)
    assert ok.all() and np.abs(uv - omni_uv).max() < 0.02


def test_panorama_ground_truth_to_camera_range(urban: Path) -> None:
    rig = load_rig(urban)
    inv = read_inverse_depth_tiff(rig.frames[0].depths["cam2"])
    assert inv.dtype == np.float32 and inv.shape == (80, 320)
    # panorama rays: column W/2 looks forward (ego +x), column W/4 to the left (+y), top row is up
    rays = panorama_rays(80, 320)
    np.testing.assert_allclose(rays[40, 160] * [1, 1, 0] / np.linalg.norm(rays[40, 160, :2]), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rays[40, 80, :2] / np.linalg.norm(rays[40, 80, :2]), [0, 1], atol=1e-12)
    assert rays[0, 0, 2] == pytest.approx(math.sin(math.radians(45.0)))
    cam = rig.camera("cam2")
    depth = rig.load_depth("0001", "cam2")
    assert depth.shape == (H, W) and depth.dtype == np.float32
    v, u = np.nonzero(depth)
    assert len(u) > 2000
    rays_cam, _ = cam.intrinsics.unproject(np.stack([u, v], axis=-1).astype(np.float64))
    dirs = rays_cam @ cam.sensor_to_ego[:3, :3].T
    centre = cam.sensor_to_ego[:3, 3]
    b = dirs @ centre
    expected = -b + np.sqrt(b * b - centre @ centre + 100.0)  # range to the 10 m sphere around the rig
    np.testing.assert_allclose(depth[v, u], expected, atol=5e-3)
    up = (dirs[:, 2] / np.linalg.norm(dirs, axis=-1))
    assert up.max() < math.sin(math.radians(45.5))  # nothing above the panorama's band
    assert rig.load_depth("0002", "cam2") is None


def test_frames_listed_without_range(tmp_path: Path, urban: Path) -> None:
    shutil.copytree(urban, tmp_path / "u")
    write_config(tmp_path / "u", frames=None)
    (tmp_path / "u" / "cam1" / "0007.png").write_bytes((urban / "cam1" / "0001.png").read_bytes())
    assert [f.id for f in load_rig(tmp_path / "u").frames] == ["0001", "0002", "0007"]


def test_config_defects(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_config(tmp_path)
    text = (tmp_path / "config.yaml").read_text()
    (tmp_path / "config.yaml").write_text(text.replace("poly: [5, ", "poly: [6, ", 1))
    with pytest.raises(InputError, match=r"cameras\[0\]\.poly: first entry must be the number of coefficients"):
        load_rig(tmp_path)
    (tmp_path / "config.yaml").write_text(text.replace("max_fov: 220.0", "max_fov: 400.0", 1))
    with pytest.raises(InputError, match=r"cameras\[0\]\.max_fov: missing or not in \(0, 360\)"):
        load_rig(tmp_path)
    (tmp_path / "config.yaml").write_text(text.replace("pose: [0.0, 0.0, 0.0, 0.0, 0.0, 0.6]", "pose: [0.0, 0.6]"))
    with pytest.raises(InputError, match=r"cameras\[0\]\.pose: has 2 values, expected 6"):
        load_rig(tmp_path)
    (tmp_path / "config.yaml").write_text(text.replace("cameras:", "cameras: [", 1))
    assert main(["validate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "config.yaml: bad YAML at line" in err
    (tmp_path / "config.yaml").write_text(text)
    assert main(["validate", str(tmp_path)]) == 2  # no images at all
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cam1/0001.png: image of camera cam1 is missing" in err
