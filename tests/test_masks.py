"""Static ego-body masks: estimation against a rendered body with exact truth, the CLI, user-mask precedence."""

from __future__ import annotations

import numpy as np
import pytest

from sgde_plugin.cli import main
from sgde_plugin.io import read_mask, write_image
from sgde_plugin.masks import attach_masks, estimate_static_mask, spread_frames
from sgde_plugin.rig import read_rig_folder
from sgde_plugin.synth.ego_body import body_mask
from sgde_plugin.synth.presets import preset_cameras, preset_world
from sgde_plugin.synth.render import render, rig_lod
from sgde_plugin.threads import torch_threads

TIMES = (0.0, 0.5, 1.0)  # three frames while the car drives 6 m


@pytest.mark.parametrize("camera", ["CAMERA_06", "CAMERA_09"])
def test_mask_of_a_rendered_ego_body(camera):
    """Three frames of a DDAD-like camera with the glossy body: the estimate covers the true body (IoU >= 0.85)
    and almost nothing else (< 1 % of the image); the same camera without a body gets no mask."""
    cams = preset_cameras("ddad", 0.25)
    cam = next(c for c in cams if c.name == camera)
    lod = rig_lod(cams)
    with torch_threads(1):
        for with_body in (True, False):
            world = preset_world("ddad", 0, ego_body=with_body)
            frames = [render(world, cam, world.ego_pose(t), t, lod=lod)[0] for t in TIMES]
            body = ~estimate_static_mask(frames)
            if with_body:
                truth = body_mask(world.ego_body, cam)
                assert 0.1 < truth.mean() < 0.4
                iou = (body & truth).sum() / (body | truth).sum()
                assert iou >= 0.85, iou
                assert (body & ~truth).mean() < 0.01
            else:
                assert body.mean() < 0.01


def test_spread_frames():
    assert spread_frames(3, 8) == [0, 1, 2]
    assert spread_frames(11, 3) == [0, 5, 10]
    assert spread_frames(100, 8)[0] == 0 and spread_frames(100, 8)[-1] == 99 and len(spread_frames(100, 8)) == 8


def test_masks_cli_user_masks_win_and_prior_honours_them(tmp_path, capsys):
    """`sgde synth --ego-body` + `sgde masks`: a user's mask is copied unchanged, the others are estimated
    (mostly inside the true body), one-frame input is refused with exit 2, and the rig takes the folder."""
    root = tmp_path / "r"
    assert main(["synth", "--preset", "ddad", "--seed", "3", "--frames", "3", "--scale", "0.3", "--ego-body",
                 "--pose-noise-deg", "0", "--pose-noise-m", "0", "--out", str(root)]) == 0
    rig = read_rig_folder(root)
    first = rig.camera_names[0]
    cam = rig.camera(first)
    user = np.full((cam.height, cam.width), 255, np.uint8)
    user[: cam.height // 3] = 0
    write_image(root / "masks" / f"{first}.png", user)
    out = tmp_path / "m"
    assert main(["masks", str(root), "--out", str(out)]) == 0
    table = capsys.readouterr().out
    assert "user" in table and "estimated" in table
    np.testing.assert_array_equal(read_mask(out / f"{first}.png"), user > 0)
    assert "ground motion" in table  # the rig's poses are used: the car drove 1.2 m
    for name in rig.camera_names[1:]:
        est_body = ~read_mask(out / f"{name}.png")
        truth = ~read_mask(root / "masks_true" / f"{name}.png")
        assert (est_body & ~truth).mean() < 0.03, name
        assert (est_body & truth).sum() / truth.sum() > 0.85, name
    with_masks = attach_masks(read_rig_folder(root), out)
    assert with_masks.masks[first] == root / "masks" / f"{first}.png"  # the rig's own mask wins
    assert set(with_masks.masks) == set(rig.camera_names)
    one = tmp_path / "one"
    assert main(["synth", "--preset", "random", "--seed", "3", "--frames", "1", "--scale", "0.1",
                 "--out", str(one)]) == 0
    assert main(["masks", str(one), "--out", str(tmp_path / "m1")]) == 2
    assert "at least 2" in capsys.readouterr().err
    # a damaged image found during the work: one line, exit 2, and no (empty) --out folder left behind
    victim = root / "frames" / rig.frames[0].id / f"{rig.camera_names[1]}.png"
    victim.write_bytes(victim.read_bytes()[:300])
    assert main(["masks", str(root), "--out", str(tmp_path / "m2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "truncated PNG" in err[0], err
    assert not (tmp_path / "m2").exists()
