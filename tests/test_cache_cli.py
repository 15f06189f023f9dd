"""`sgde prior` end to end on a small synthetic nuScenes rig, then `sgde cache info|verify` and the
refusals of a cache built with another calibration or other settings.

Runtime ~10 s on 2 cores (400x225 cameras; rendering the synthetic rig dominates).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from sgde_plugin.cache.fingerprints import fingerprint
from sgde_plugin.cache.store import PriorCache
from sgde_plugin.cli import main as cli_main
from sgde_plugin.commands.prior import load_rig_with_override

synth = pytest.importorskip("sgde_plugin.synth.sequence")


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory):
    return synth.write_synth("nuscenes", 2, tmp_path_factory.mktemp("synth") / "nus", scale=0.25)


def test_sgde_prior_builds_resumes_and_refuses_mixing(synth_dir, tmp_path, capsys):
    from sgde_plugin.stereo.pipeline import PriorConfig

    root, out = str(synth_dir), str(tmp_path / "cache")
    true_rig = str(synth_dir / "rig_true.json")
    assert cli_main(["prior", root, "--out", out, "--rig", true_rig, "--workers", "1"]) == 0
    assert "2 frames built, 0 already there" in capsys.readouterr().out

    rig = load_rig_with_override(root, true_rig)
    cache = PriorCache(out)
    assert cache.frames() == [f.id for f in rig.frames]
    assert cache.cameras() == rig.camera_names
    assert cache.fingerprint == fingerprint(rig, PriorConfig())
    errors = []
    for fid in cache.frames():
        for cam in rig.cameras:
            depth, valid = cache.get(fid, cam.name)
            assert depth.shape == (cam.height, cam.width)
            gt = rig.load_depth(fid, cam.name)
            both = valid & (gt > 0)
            errors.append(np.abs(depth[both] - gt[both]) / gt[both])
    errors = np.concatenate(errors)
    assert errors.size > 500  # the overlaps received priors
    assert np.median(errors) < 0.1  # and they are the stereo priors of this rig, not noise

    assert cli_main(["prior", root, "--out", out, "--rig", true_rig, "--workers", "1"]) == 0
    assert "0 frames built, 2 already there" in capsys.readouterr().out

    # the perturbed extrinsics of rig.json: another calibration; another matching scale: other settings
    assert cli_main(["prior", root, "--out", out, "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "built for another calibration" in err[0] and "refusing to mix" in err[0]
    assert cli_main(["prior", root, "--out", out, "--rig", true_rig, "--scale", "0.25"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other prior settings (scale 0.5 -> 0.25)" in err[0]

    assert cli_main(["cache", "verify", out]) == 0
    assert "2 frames, 26 chunks read: ok" in capsys.readouterr().out
    assert cli_main(["cache", "info", out]) == 0
    assert cache.fingerprint in capsys.readouterr().out


@pytest.fixture(scope="module")
def built(synth_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("built") / "cache"
    assert cli_main(["prior", str(synth_dir), "--out", str(out), "--workers", "1"]) == 0
    return out


def _copy_with_marker(built, tmp_path, frame: int):
    """A copy of the built cache and the path of one frame's done marker (its valid_pixels chunk)."""
    out = tmp_path / "cache"
    shutil.copytree(built, out)
    (scene,) = [p for p in out.iterdir() if p.is_dir()]
    return out, scene / "valid_pixels" / "c" / str(frame) / "0"


def test_an_unreadable_done_marker_is_one_line_for_info_and_eval(synth_dir, built, tmp_path, capsys):
    out, marker = _copy_with_marker(built, tmp_path, 1)
    data = bytearray(marker.read_bytes())
    data[2] ^= 0xFF
    marker.write_bytes(bytes(data))
    capsys.readouterr()
    assert cli_main(["cache", "info", str(out), "--json", str(tmp_path / "info.json")]) == 2
    got = capsys.readouterr()
    err = got.err.strip().splitlines()
    assert len(err) == 1 and "/000001/*: its done marker (valid_pixels) is unreadable" in err[0], err
    assert got.out == "" and not (tmp_path / "info.json").exists()
    # eval refuses the damaged frame instead of leaving it out of the result
    assert cli_main(["eval", str(synth_dir), "--cache", str(out), "--json", str(tmp_path / "e.json")]) == 2
    got = capsys.readouterr()
    err = got.err.strip().splitlines()
    assert len(err) == 1 and "/000001/*: its done marker (valid_pixels) is unreadable" in err[0], err
    assert got.out == "" and not (tmp_path / "e.json").exists()


def test_eval_of_a_partly_built_cache_says_how_many_frames_it_lacks(synth_dir, built, tmp_path, capsys):
    out, marker = _copy_with_marker(built, tmp_path, 1)
    marker.unlink()  # as a build killed before it finished the frame leaves it
    capsys.readouterr()
    assert cli_main(["eval", str(synth_dir), "--cache", str(out)]) == 0
    got = capsys.readouterr()
    err = got.err.strip().splitlines()
    assert err == [f"sgde eval: {out}: 1 of the 2 frames of {synth_dir} not in the cache (not built yet): "
                   "the result covers the other 1"], err
    assert got.out.startswith(f"{synth_dir}: 1 frames")
    assert cli_main(["eval", str(synth_dir), "--cache", str(built)]) == 0  # a complete cache: nothing on stderr
    got = capsys.readouterr()
    assert got.err == "" and got.out.startswith(f"{synth_dir}: 2 frames")
