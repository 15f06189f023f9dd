"""COLMAP (pycolmap 4.x) as a peer of GLC: its rig-aware bundle adjustment on the same window of images.

The recipe: COLMAP's SIFT features and exhaustive matching with its two-view geometric verification on every
image of the window; a reconstruction with one rig (the reference camera is the rig frame, every other camera
a sensor whose `sensor_from_rig` starts at the starting extrinsics), one frame per time step whose
`rig_from_world` starts at the ego pose with the starting reference mount; points triangulated from these
poses; then COLMAP's bundle adjustment with the intrinsics fixed, refining `sensor_from_rig` and
`rig_from_world`. The gauge of that adjustment is free in scale, so the metric scale comes from the ego
trajectory: the refined frame centres are scaled to the ego trajectory's length. Needs the optional extra
`peer` (`pip install sgde-plugin[peer]`); nothing is downloaded.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..cameras import Camera, KannalaBrandt, Pinhole
from ..errors import InputError
from ..geometry import invert_transform
from ..io import write_image

if TYPE_CHECKING:  # pycolmap is the optional `peer` extra
    import pycolmap


def available() -> bool:
    """True when pycolmap can be imported."""
    try:
        import pycolmap  # noqa: F401
    except ImportError:
        return False
    return True


def colmap_camera(cam: Camera) -> pycolmap.Camera:
    """The pycolmap camera of one of ours (COLMAP puts the centre of the top-left pixel at (0.5, 0.5))."""
    import pycolmap

    m = cam.intrinsics
    if not isinstance(m, (Pinhole, KannalaBrandt)):
        raise InputError(None, "camera", f"camera {cam.name}: model {m.model} has no COLMAP equivalent here")
    K = np.asarray(m.K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5
    if isinstance(m, Pinhole) and (m.dist is None or not np.any(m.dist)):
        return pycolmap.Camera(model="PINHOLE", width=m.width, height=m.height, params=[fx, fy, cx, cy])
    if isinstance(m, Pinhole):
        k1, k2, p1, p2 = (list(np.asarray(m.dist, dtype=np.float64)) + [0.0] * 4)[:4]
        return pycolmap.Camera(model="OPENCV", width=m.width, height=m.height, params=[fx, fy, cx, cy, k1, k2, p1, p2])
    k = list(np.asarray(m.dist, dtype=np.float64))
    return pycolmap.Camera(model="OPENCV_FISHEYE", width=m.width, height=m.height, params=[fx, fy, cx, cy, *k])


def _rigid(T: np.ndarray):
    import pycolmap

    return pycolmap.Rigid3d(np.asarray(T, dtype=np.float64)[:3, :4])


def _matrix(r) -> np.ndarray:
    out = np.eye(4)
    out[:3, :4] = np.asarray(r.matrix())
    return out


def calibrate_colmap(
    cameras: Sequence[Camera], ego_to_world: np.ndarray, image: Callable[[int, str], np.ndarray],
    reference: str, workdir: str | Path | None = None,
) -> tuple[dict[str, np.ndarray], dict]:
    """COLMAP's rig bundle adjustment over one window; returns sensor_to_ego per camera and solver facts.

    `cameras` carry the starting extrinsics; `ego_to_world` (T, 4, 4) the window's ego poses; `image(t, name)`
    the RGB images. The reference camera keeps its starting sensor_to_ego (as in GLC).
    """
    import pycolmap

    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        root = Path(tmp)
        imgdir, db_path = root / "images", root / "database.db"
        T = ego_to_world.shape[0]
        for t in range(T):
            for cam in cameras:
                write_image(imgdir / cam.name / f"{t:04d}.png", image(t, cam.name))
        pycolmap.extract_features(db_path, imgdir, camera_mode=pycolmap.CameraMode.PER_FOLDER,
                                  device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(db_path)
        by_name = {im.name: im for im in db.read_all_images()}
        cam_id = {}
        for cam in cameras:
            im = by_name[f"{cam.name}/0000.png"]
            ours = colmap_camera(cam)
            ours.camera_id = im.camera_id
            db.update_camera(ours)
            cam_id[cam.name] = im.camera_id
        keypoints = {im.image_id: db.read_keypoints(im.image_id)[:, :2] for im in by_name.values()}
        rec = _reconstruction(cameras, ego_to_world, reference, by_name, cam_id, keypoints)
        db.clear_frames()
        db.clear_rigs()
        for rig in rec.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in rec.frames.values():
            db.write_frame(frame, use_frame_id=True)
        db.close()
        pycolmap.match_exhaustive(db_path, device=pycolmap.Device.cpu)
        rec = pycolmap.triangulate_points(rec, db_path, imgdir, root / "sparse")
        opts = pycolmap.BundleAdjustmentOptions(refine_focal_length=False, refine_principal_point=False,
                                                refine_extra_params=False, refine_sensor_from_rig=True,
                                                refine_rig_from_world=True)
        pycolmap.bundle_adjustment(rec, opts)
        return _extrinsics(rec, cameras, ego_to_world, reference, cam_id)


def _reconstruction(cameras, ego_to_world, reference, by_name, cam_id, keypoints):
    """Cameras, one rig, frames at the ego poses, images with their keypoints."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    cams = {c.name: c for c in cameras}
    for cam in cameras:
        cc = colmap_camera(cam)
        cc.camera_id = cam_id[cam.name]
        rec.add_camera(cc)
    S_ref = cams[reference].sensor_to_ego
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id[reference]))
    for cam in cameras:
        if cam.name != reference:
            cam_from_ref = invert_transform(cam.sensor_to_ego) @ S_ref
            rig.add_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, cam_id[cam.name]), _rigid(cam_from_ref))
    rec.add_rig(rig)
    for t in range(ego_to_world.shape[0]):
        frame = pycolmap.Frame(frame_id=t + 1, rig_id=1)
        images = []
        for cam in cameras:
            db_im = by_name[f"{cam.name}/{t:04d}.png"]
            im = pycolmap.Image(name=db_im.name, keypoints=keypoints[db_im.image_id], camera_id=cam_id[cam.name],
                                image_id=db_im.image_id)
            im.frame_id = t + 1
            frame.add_data_id(im.data_id)
            images.append(im)
        frame.rig_from_world = _rigid(invert_transform(ego_to_world[t] @ S_ref))
        rec.add_frame(frame)
        for im in images:
            rec.add_image(im)
    return rec


def _extrinsics(rec, cameras, ego_to_world, reference, cam_id) -> tuple[dict[str, np.ndarray], dict]:
    """sensor_to_ego from the refined rig, translations scaled to the ego trajectory."""
    cams = {c.name: c for c in cameras}
    S_ref = cams[reference].sensor_to_ego
    centres = np.array([invert_transform(_matrix(rec.frame(t + 1).rig_from_world))[:3, 3]
                        for t in range(ego_to_world.shape[0])])
    ego_centres = np.einsum("tij,j->ti", ego_to_world, S_ref[:, 3])[:, :3]
    span = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    ego_span = float(np.linalg.norm(np.diff(ego_centres, axis=0), axis=1).sum())
    scale = ego_span / span if span > 1e-9 else 1.0
    rig = rec.rig(1)
    out = {}
    for cam in cameras:
        if cam.name == reference:
            out[cam.name] = S_ref.copy()
            continue
        cam_from_ref = _matrix(rig.sensor_from_rig(pycolmap_sensor(cam_id[cam.name])))
        cam_from_ref[:3, 3] *= scale
        out[cam.name] = S_ref @ invert_transform(cam_from_ref)
    facts = {"points": int(rec.num_points3D()), "registered_images": int(rec.num_reg_images()),
             "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()), "scale": scale}
    return out, facts


def pycolmap_sensor(camera_id: int) -> pycolmap.sensor_t:
    """The sensor id of a camera."""
    import pycolmap

    return pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id)
