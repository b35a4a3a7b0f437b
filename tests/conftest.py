"""Shared fixtures: the real data beside the checkout, small random image stacks."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _require(path: Path) -> Path:
    if not path.exists():
        message = f"real data not found at {path} (expected ../shared/data beside the checkout)"
        if os.environ.get("CI"):
            pytest.fail(message + "; CI must have it")
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data; fails under CI when missing, skips otherwise."""
    return _require(SHARED_DATA)


@pytest.fixture(scope="session")
def nordland_64x32(shared_data) -> Path:
    return _require(shared_data / "nordland_64x32")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def random_images(rng):
    def make(n, h=32, w=64):
        return rng.random((n, h, w), dtype=np.float32)

    return make
