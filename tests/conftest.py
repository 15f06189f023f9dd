"""Shared fixtures: the devices and float dtypes the torch geometry core is checked on.

Shared set-up helpers live in modules beside the tests (`cache_fixtures.py`, `stereo_scene.py`,
`mock_bev.py`); this file holds the fixtures that parametrise tests.
"""

from __future__ import annotations

import os

import cv2
import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
FLOAT_DTYPES = [torch.float32, torch.float64]


@pytest.fixture(params=DEVICES)
def device(request: pytest.FixtureRequest) -> torch.device:
    """Every available torch device (CPU always; CUDA when present)."""
    return torch.device(request.param)


@pytest.fixture(params=FLOAT_DTYPES, ids=lambda d: str(d).removeprefix("torch."))
def float_dtype(request: pytest.FixtureRequest) -> torch.dtype:
    """The float dtypes the geometry core computes in."""
    return request.param


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (`make test` runs one worker per core), one torch and one OpenCV thread per worker.

    Two workers with a thread per core each would oversubscribe the machine, and idle OpenMP threads
    spin; tests that need other counts set them in a scope of their own.
    """
    if os.environ.get("PYTEST_XDIST_WORKER"):
        torch.set_num_threads(1)
        cv2.setNumThreads(1)
