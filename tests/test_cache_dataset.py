"""PriorDataset: image + prior + valid + gt at the network input size, augmentation, DataLoader workers.

Runtime ~5 s on 2 cores (the 2-worker DataLoader start-up).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from cache_fixtures import ALGO, CONFIG, tiny_rig
from torch.utils.data import DataLoader

from sgde_plugin.cache.build import build_cache
from sgde_plugin.cache.dataset import PriorDataset
from sgde_plugin.cache.resample import ida_matrix
from sgde_plugin.cache.store import PriorCache
from sgde_plugin.cache.synthetic import SyntheticPriorCompute
from sgde_plugin.errors import InputError
from sgde_plugin.io import write_depth_png, write_image
from sgde_plugin.rig import read_rig_folder, write_rig_json

SIZE = (20, 32)


@pytest.fixture(scope="module")
def rig_and_cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("rig")
    rig = tiny_rig(3)
    write_rig_json(rig, root / "rig.json")
    rng = np.random.default_rng(0)
    for fr in rig.frames:
        for cam in rig.cameras:
            write_image(root / "frames" / fr.id / f"{cam.name}.png",
                        rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8))
            gt = rng.uniform(2, 60, (cam.height, cam.width)).astype(np.float32)
            gt[rng.random(gt.shape) < 0.5] = 0
            write_depth_png(root / "depth" / fr.id / f"{cam.name}.png", gt)
    rig = read_rig_folder(root, check_images=True)
    cache = root.parent / "cache"
    build_cache(rig, cache, CONFIG, compute=SyntheticPriorCompute(rig), algo_version=ALGO, show_progress=False)
    return rig, str(cache)


def test_sample_is_resized_consistently(rig_and_cache):
    rig, cache = rig_and_cache
    ds = PriorDataset(rig, cache, SIZE, with_gt=True)
    assert len(ds) == 3 * 3
    s = ds[1]  # frame 0, camera B
    assert (s["frame_id"], s["camera"]) == ("000000", "B")
    assert s["image"].shape == (3, *SIZE) and s["image"].dtype == torch.float32
    for key in ("prior", "valid", "confidence", "gt"):
        assert s[key].shape == (1, *SIZE)
    # 64x40 -> 32x20 is an exact 2x reduction: area-averaged image, min-pooled prior and ground truth
    img = rig.load_image("000000", "B")
    np.testing.assert_allclose(s["image"].numpy().transpose(1, 2, 0) * 255,
                               cv2.resize(img, (32, 20), interpolation=cv2.INTER_AREA), atol=1e-3)
    depth, valid = PriorCache(cache).get("000000", "B", size=SIZE)
    np.testing.assert_array_equal(s["prior"][0].numpy(), depth)
    np.testing.assert_array_equal(s["valid"][0].numpy(), valid)
    gt = rig.load_depth("000000", "B")
    blocks = np.where(gt > 0, gt, np.inf).reshape(20, 2, 32, 2).min(axis=(1, 3))
    np.testing.assert_array_equal(s["gt"][0].numpy(), np.where(np.isfinite(blocks), blocks, 0))
    assert torch.all(s["confidence"][~s["valid"]] == 0) and s["confidence"][s["valid"]].min() > 0
    small = ds[2]  # camera C (48x32) resized to the same input size
    assert small["camera"] == "C" and small["prior"].shape == (1, *SIZE)


def test_augmentation_matrix_applies_to_image_and_prior(rig_and_cache):
    rig, cache = rig_and_cache
    plain = PriorDataset(rig, cache, SIZE)

    def flipped(frame_id, camera, src_hw, out_hw):
        return ida_matrix((out_hw[1] / src_hw[1], out_hw[0] / src_hw[0]), flip=True, out_hw=out_hw)

    aug = PriorDataset(rig, cache, SIZE, ida=flipped)
    a, b = plain[4], aug[4]
    np.testing.assert_array_equal(b["prior"].numpy(), a["prior"].numpy()[..., ::-1])
    np.testing.assert_allclose(b["image"].numpy(), a["image"].numpy()[..., ::-1], atol=1e-6)
    assert b["ida"][0, 0] < 0  # the matrix used is returned (for BEVDepth's ida_mats)


def test_grouped_frames_and_dataloader_workers_agree(rig_and_cache):
    rig, cache = rig_and_cache
    ds = PriorDataset(rig, cache, SIZE, group_cameras=True, with_gt=True)
    assert len(ds) == 3
    item = ds[0]
    assert item["image"].shape == (3, 3, *SIZE) and item["camera"] == ["A", "B", "C"]
    serial = list(DataLoader(ds, batch_size=2, num_workers=0))
    parallel = list(DataLoader(ds, batch_size=2, num_workers=2))
    assert len(serial) == len(parallel) == 2
    for x, y in zip(serial, parallel):
        assert x["frame_id"] == y["frame_id"]
        for key in ("image", "prior", "valid", "confidence", "gt", "ida"):
            assert torch.equal(x[key], y[key])


def test_dataset_refuses_a_cache_of_another_calibration(rig_and_cache):
    _, cache = rig_and_cache
    with pytest.raises(InputError, match="another calibration"):
        PriorDataset(tiny_rig(3, shift_m=0.05), cache, SIZE)
