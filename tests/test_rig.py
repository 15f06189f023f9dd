"""sgde-rig/1 format, `sgde validate` defects, pair geometry on a hand-built ring."""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from sgde_plugin.cameras import Camera, Pinhole
from sgde_plugin.cli import main
from sgde_plugin.geometry import camera_mount
from sgde_plugin.io import write_image
from sgde_plugin.pairs import left_right, pair_geometry, rig_pair_geometry
from sgde_plugin.rig import Frame, Rig, read_rig_folder, read_rig_json, ring_pairs, write_rig_json

RING = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]
YAWS = [0.0, -55.0, -110.0, 180.0, 110.0, 55.0]
FOV = 70.0
W, H = 64, 36


def ring_camera(name: str, yaw_deg: float, width: int = W, height: int = H, fov_deg: float = FOV) -> Camera:
    """A pinhole whose image spans exactly fov_deg edge to edge, mounted 0.5 m out along its yaw."""
    f = (width / 2) / math.tan(math.radians(fov_deg / 2))
    K = np.array([[f, 0, width / 2 - 0.5], [0, f, height / 2 - 0.5], [0, 0, 1]])
    yaw = math.radians(yaw_deg)
    pos = np.array([0.5 * math.cos(yaw) + 1.0, 0.5 * math.sin(yaw), 1.6])
    return Camera(name, Pinhole(width, height, K), camera_mount(yaw, pos))


def make_rig(frames: int = 2) -> Rig:
    cams = tuple(ring_camera(n, y) for n, y in zip(RING, YAWS))
    poses = []
    for i in range(frames):
        T = np.eye(4)
        T[0, 3] = 0.8 * i
        poses.append(Frame(f"{i:06d}", 100_000 * i, T, extra={"note": f"frame {i}"}))
    return Rig(cams, ring_pairs(RING), tuple(poses), tuple(RING), extra={"dataset": "hand-built"})


def write_folder(root: Path, rig: Rig) -> None:
    write_rig_json(rig, root / "rig.json")
    rng = np.random.default_rng(0)
    for fr in rig.frames:
        for cam in rig.cameras:
            noise = rng.integers(0, 255, (cam.height, cam.width, 3), np.uint8)
            write_image(root / "frames" / fr.id / f"{cam.name}.png", noise)


def test_round_trip_identical(tmp_path: Path) -> None:
    rig = make_rig()
    write_rig_json(rig, tmp_path / "a.json")
    first = read_rig_json(tmp_path / "a.json")
    write_rig_json(first, tmp_path / "b.json")
    second = read_rig_json(tmp_path / "b.json")
    assert first == rig and second == first
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    assert second.extra["dataset"] == "hand-built" and second.frames[1].extra["note"] == "frame 1"
    for cam_a, cam_b in zip(rig.cameras, second.cameras):
        assert np.array_equal(cam_a.sensor_to_ego, cam_b.sensor_to_ego)


def test_pairs_instead_of_ring_and_defaults(tmp_path: Path) -> None:
    doc = make_rig().to_dict()
    del doc["ring"]
    doc["pairs"] = [["CAM_FRONT_RIGHT", "CAM_FRONT"]]
    for fr in doc["frames"]:
        del fr["ego_to_world"], fr["timestamp_us"]
    (tmp_path / "rig.json").write_text(json.dumps(doc))
    rig = read_rig_json(tmp_path / "rig.json")
    assert rig.pairs == (("CAM_FRONT_RIGHT", "CAM_FRONT"),) and rig.ring is None
    assert [f.timestamp_us for f in rig.frames] == [0, 1]
    assert np.array_equal(rig.frames[0].ego_to_world, np.eye(4))


def test_validate_accepts_and_prints_tables(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    write_folder(tmp_path, make_rig())
    assert main(["validate", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "6 cameras" in out and "overlap_deg" in out and "CAM_BACK_LEFT" in out
    fovs = [float(line.split()[3]) for line in out.splitlines() if line.startswith("CAM_") and "pinhole" in line]
    assert len(fovs) == 6 and all(abs(f - FOV) < 0.01 for f in fovs)  # a pinhole's horizontal field of view
    assert read_rig_folder(tmp_path, check_images=True).frames[0].images["CAM_FRONT"].exists()


def _break(doc: dict, defect: str) -> str:
    """Apply one contract defect to a rig.json document; return the key the error must name."""
    cam = doc["cameras"][1]
    if defect == "missing_key":
        del cam["width"]
        return "cameras[CAM_FRONT_RIGHT].width"
    if defect == "non_square_K":
        cam["K"] = cam["K"][:2]
        return "cameras[CAM_FRONT_RIGHT].K: is not a square"
    if defect == "singular_K":
        cam["K"] = [[0, 0, 1], [0, 0, 1], [0, 0, 1]]
        return "cameras[CAM_FRONT_RIGHT].K: is singular"
    if defect == "not_orthonormal":
        cam["sensor_to_ego"][0][0] += 1e-4
        return "cameras[CAM_FRONT_RIGHT].sensor_to_ego: rotation is not orthonormal"
    if defect == "model_not_a_name":
        cam["model"] = ["pinhole"]
        return "cameras[CAM_FRONT_RIGHT].model: unknown camera model ['pinhole']"
    if defect == "huge_rotation_entry":  # its products overflow: no warning, one line
        cam["sensor_to_ego"][0][0] = 1e308
        return "cameras[CAM_FRONT_RIGHT].sensor_to_ego: rotation has determinant -8.19e+307 (a reflection)"
    if defect == "ring_unknown_camera":
        doc["ring"][2] = "CAM_NOPE"
        return "ring: camera 'CAM_NOPE' does not exist"
    if defect == "wrong_format":
        doc["format"] = "sgde-rig/0"
        return "format"
    raise AssertionError(defect)


DEFECTS = ["bad_json", "missing_key", "non_square_K", "singular_K", "not_orthonormal", "model_not_a_name",
           "huge_rotation_entry", "ring_unknown_camera", "wrong_format", "image_size", "image_missing"]


@pytest.mark.parametrize("defect", DEFECTS)
def test_each_defect_is_one_line_and_exit_2(defect: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rig = make_rig(frames=1)
    write_folder(tmp_path, rig)
    key = defect
    if defect == "bad_json":
        (tmp_path / "rig.json").write_text((tmp_path / "rig.json").read_text()[:-40])
        key = "bad JSON"
    elif defect == "image_size":
        write_image(tmp_path / "frames" / "000000" / "CAM_BACK.png", np.zeros((H + 2, W, 3), np.uint8))
        key = "CAM_BACK.png: size: image is 64x38"
    elif defect == "image_missing":
        (tmp_path / "frames" / "000000" / "CAM_BACK.png").unlink()
        key = "000000: CAM_BACK: image missing"
    else:
        doc = json.loads((tmp_path / "rig.json").read_text())
        key = _break(doc, defect)
        (tmp_path / "rig.json").write_text(json.dumps(doc))
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning would be a second line on stderr
        assert main(["validate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert key in lines[0] and "Traceback" not in err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test_pair_geometry_hand_built_ring() -> None:
    rig = make_rig()
    geo = {(g.left, g.right): g for g in rig_pair_geometry(rig, samples=400)}
    # adjacent yaws 55 degrees apart with 70-degree images share 15 degrees; 70 apart share none
    expected = {
        ("CAM_FRONT", "CAM_FRONT_RIGHT"): 15.0,
        ("CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"): 15.0,
        ("CAM_BACK_RIGHT", "CAM_BACK"): 0.0,
        ("CAM_BACK", "CAM_BACK_LEFT"): 0.0,
        ("CAM_BACK_LEFT", "CAM_FRONT_LEFT"): 15.0,
        ("CAM_FRONT_LEFT", "CAM_FRONT"): 15.0,
    }
    assert set(geo) == set(expected), "left/right must follow the ring clockwise seen from above"
    t35, t20 = math.tan(math.radians(35)), math.tan(math.radians(20))
    frac = (t35 - t20) / (2 * t35)  # share of image columns beyond 20 degrees off-axis
    for pair, sector in expected.items():
        g = geo[pair]
        assert abs(g.sector_deg - sector) < 0.3, (pair, g.sector_deg)
        if sector > 0:
            assert abs(g.left_fraction - frac) < 0.01 and abs(g.right_fraction - frac) < 0.01
            assert abs(g.axis_angle_deg - 55.0) < 1e-9
        else:
            assert g.left_fraction < 0.01 and g.right_fraction < 0.01
        assert g.baseline_m > 0


def test_left_right_ignores_list_order() -> None:
    front, front_right = ring_camera("A", 0.0), ring_camera("B", -55.0)
    assert [c.name for c in left_right(front_right, front)] == ["A", "B"]
    assert [c.name for c in left_right(front, front_right)] == ["A", "B"]
    g = pair_geometry(front_right, front)
    assert (g.left, g.right) == ("A", "B")


def test_relative_pose_errors_measure_the_perturbation() -> None:
    from sgde_plugin.geometry import make_transform, rodrigues
    from sgde_plugin.pairs import relative_pose_errors

    rig = make_rig()
    cam = rig.camera("CAM_FRONT_RIGHT")
    bump = make_transform(rodrigues(np.radians([0.0, 0.5, 0.0])), [0.0, 0.0, 0.03])
    moved = rig.with_extrinsics({cam.name: cam.sensor_to_ego @ bump})
    errs = {e["pair"]: e for e in relative_pose_errors(moved, rig)}
    assert abs(errs["CAM_FRONT-CAM_FRONT_RIGHT"]["rotation_deg"] - 0.5) < 1e-9
    assert abs(errs["CAM_FRONT-CAM_FRONT_RIGHT"]["translation_m"] - 0.03) < 1e-9
    assert abs(errs["CAM_FRONT_RIGHT-CAM_BACK_RIGHT"]["rotation_deg"] - 0.5) < 1e-9
    assert errs["CAM_BACK-CAM_BACK_LEFT"]["rotation_deg"] < 1e-9


def test_rotation_vector_batched_and_near_pi():
    from sgde_plugin.geometry import invert_transform, make_transform, rodrigues, rotation_angle_deg, rotation_vector

    rng = np.random.default_rng(3)
    w = rng.normal(size=(5, 3))
    w *= (np.linspace(0.0, np.pi - 1e-9, 5) / np.maximum(np.linalg.norm(w, axis=1), 1e-12))[:, None]
    R = rodrigues(w)
    assert R.shape == (5, 3, 3)
    back = rotation_vector(R)
    # at pi the sign of the axis is free: compare the rotations, and the angles
    assert np.allclose(rodrigues(back), R, atol=1e-7)
    assert np.allclose(rotation_angle_deg(R), np.degrees(np.linalg.norm(w, axis=1)), atol=1e-5)
    assert isinstance(rotation_angle_deg(R[1]), float)
    T = make_transform(R, rng.normal(size=(5, 3)))
    assert np.allclose(np.einsum("nij,njk->nik", T, invert_transform(T)), np.eye(4), atol=1e-12)


def test_mean_transform_of_rotations_about_one_axis_and_of_translations():
    """The chordal mean of rotations by +a and -a (and 0) about one axis is the identity; of +a, +3a about it, a
    rotation by 2a within 1e-6 deg for small a; translations average."""
    from sgde_plugin.geometry import make_transform, mean_transform, rodrigues, rotation_angle_deg

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    a = np.radians(0.05)
    Ts = np.stack([make_transform(rodrigues(axis * k * a), np.array([k, 2.0 * k, 0.5])) for k in (-1.0, 0.0, 1.0)])
    m = mean_transform(Ts)
    np.testing.assert_allclose(m[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(m[:3, 3], [0.0, 0.0, 0.5], atol=1e-12)
    two = mean_transform(np.stack([make_transform(rodrigues(axis * k * a), np.zeros(3)) for k in (1.0, 3.0)]))
    assert abs(rotation_angle_deg(two[:3, :3].T @ rodrigues(axis * 2 * a))) < 1e-6
    assert np.isclose(np.linalg.det(m[:3, :3]), 1.0) and np.array_equal(m[3], [0.0, 0.0, 0.0, 1.0])



def test_an_unknown_frame_is_one_line_not_a_key_error() -> None:
    """A frame id the rig does not have is bad input: `Rig.frame`, `as_captured`, `load_image` and
    `PriorBuilder.build(frame=)` say so in one line (InputError) naming the key."""
    from sgde_plugin.errors import InputError
    from sgde_plugin.stereo.pipeline import PriorBuilder, PriorConfig

    rig = make_rig()
    assert rig.frame("000001").id == "000001"
    for call in (lambda: rig.frame("nope"), lambda: rig.as_captured("nope"), lambda: rig.load_image("nope", RING[0])):
        with pytest.raises(InputError) as err:
            call()
        assert err.value.line() == "frames/nope: not a frame of the rig (2 frames)"
    images = {c: np.zeros((H, W, 3), np.uint8) for c in RING}
    with pytest.raises(InputError, match="frames/nope: not a frame"):
        PriorBuilder(rig, PriorConfig(), threads=1).build(images, frame="nope")
