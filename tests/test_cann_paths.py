"""The CANN's two ways to run its kernels (compiled by numba, plain Python) on real data."""

import numpy as np
import pytest

from flyvpr.temporal.cann import AttractorCANN as CANN
from flyvpr.temporal.cann import _kernels


def test_compiled_at_every_route_length(monkeypatch):
    assert _kernels.get_kernels()[1]
    rows = np.random.default_rng(0).random((3, 40_000), dtype=np.float32)
    cann = CANN()
    for row in rows:
        cann.step(row)
    assert cann.compiled_
    monkeypatch.setattr(_kernels, "USE_NUMBA", False)
    cann.reset()
    cann.step(rows[0])
    assert not cann.compiled_


@pytest.mark.slow
def test_compiled_and_plain_paths_agree_on_nordland(nordland_64x32, monkeypatch):
    """Pixels (SAD) scores of Nordland 64x32 summer -> winter frames 0-299, tolerance 20.

    The two paths run the same functions; they differ only in the order of floating-point
    sums, so the filtered rows agree to float32 rounding and the PR AUC to 1e-4.
    """
    from flyvpr.frontends.pixels import PixelsEncoder
    from flyvpr.images import list_images, load_images
    from flyvpr.metrics import pr_auc

    assert _kernels.get_kernels()[1]
    window = slice(0, 300)
    summer = load_images(list_images(nordland_64x32 / "summer")[window], cache=False)
    winter = load_images(list_images(nordland_64x32 / "winter")[window], cache=False)
    S = PixelsEncoder().fit(summer).score(winter)
    gt = np.abs(np.arange(300)[:, None] - np.arange(300)[None, :]) <= 20
    compiled = CANN()
    fast = compiled.filter(S)
    assert compiled.compiled_
    monkeypatch.setattr(_kernels, "USE_NUMBA", False)
    plain = CANN()
    slow = plain.filter(S)
    assert not plain.compiled_
    scale = float(np.abs(slow).max())
    assert np.abs(fast.astype(np.float64) - slow).max() <= 1e-5 * max(scale, 1.0)
    assert np.array_equal(fast.argmax(axis=1), slow.argmax(axis=1))
    assert pr_auc(fast, gt) == pytest.approx(pr_auc(slow, gt), abs=1e-4)
    assert pr_auc(fast, gt) > pr_auc(S, gt)  # the filter does something on this window
