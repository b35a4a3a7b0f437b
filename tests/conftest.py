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


@pytest.fixture(scope="session")
def synthetic_route():
    """Factory: ``make_route(n_places, random_state=seed, **kwargs)``, made once per arguments
    in the session (the routes are read, never changed, by the tests)."""
    from flyvpr.synthetic import make_route

    made = {}

    def make(n_places, random_state=0, **kwargs):
        key = (n_places, random_state, tuple(sorted(kwargs.items())))
        if key not in made:
            made[key] = make_route(n_places, random_state=random_state, **kwargs)
        return made[key]

    return make


@pytest.fixture(scope="session")
def route_folder(tmp_path_factory, synthetic_route):
    """Factory: a synthetic route of ``n_places`` saved as image folders (one per condition,
    ``save_route``), written once per arguments in the session; tests only read it."""
    from flyvpr.synthetic import save_route

    saved = {}

    def make(n_places, random_state=0):
        key = (n_places, random_state)
        if key not in saved:
            root = tmp_path_factory.mktemp(f"route-{n_places}-{random_state}") / "route"
            save_route(synthetic_route(n_places, random_state), root)
            saved[key] = root
        return saved[key]

    return make


@pytest.fixture(scope="session")
def sliding_world():
    """40 places 8 pixels apart on a smooth random world (32x64 views), and a noisy, darker
    second traverse of the same places: (reference, query), float32 in [0, 1]."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    world = ndimage.gaussian_filter(rng.random((32, 64 + 40 * 8), dtype=np.float32), 1.5)
    world = (world - world.min()) / (world.max() - world.min())
    ref = np.stack([world[:, 8 * i : 8 * i + 64] for i in range(40)]).astype(np.float32)
    qry = np.clip(0.7 * ref + 0.1 + rng.normal(0, 0.03, ref.shape), 0, 1).astype(np.float32)
    return ref, qry


@pytest.fixture(params=["plain", "compiled"])
def cann_kernel_mode(request, monkeypatch):
    """Each CANN test twice: its kernels compiled by numba, and the same functions run
    uncompiled (``_kernels.USE_NUMBA = False``), which mutation testing also exercises."""
    from flyvpr.temporal.cann import _kernels

    monkeypatch.setattr(_kernels, "USE_NUMBA", request.param == "compiled")
    return request.param
