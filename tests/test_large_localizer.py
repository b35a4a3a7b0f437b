"""LargeLocalizer: the windowed CANN on a large map, re-seeded from an index when lost."""

import numpy as np
import pytest

from flyvpr.large import ExhaustiveIndex, LargeLocalizer, MultiIndexHash


def _map(n=20000, n_bytes=32, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(n, n_bytes), dtype=np.uint8)


def _query(codes, place, rng, flip=0.3):
    bits = np.unpackbits(codes[place])
    return np.packbits(bits ^ (rng.random(bits.size) < flip))


def _drive(loc, codes, places, rng, flip=0.3):
    return [loc.update_code(_query(codes, p, rng, flip)) for p in places]


@pytest.mark.parametrize("index", [ExhaustiveIndex(), MultiIndexHash(radius=2)])
def test_finds_the_route_from_anywhere_and_tracks_it(index):
    codes = _map()
    rng = np.random.default_rng(1)
    loc = LargeLocalizer(codes, index.build(codes), window=512)
    truth = 15000 + np.arange(120)
    fixes = _drive(loc, codes, truth, rng)
    right = np.array([abs(f.place - t) <= 2 for f, t in zip(fixes, truth, strict=True)])
    assert right[30:].all()
    assert fixes[-1].state == "localized" and fixes[-1].confidence > 0.9
    lo, hi = loc.filter_.window_
    assert lo <= truth[-1] < hi
    # tracked frames do not ask the index (only the checks' frames do)
    searches = loc.n_searches_
    _drive(loc, codes, 15120 + np.arange(50), rng)
    assert loc.n_searches_ - searches <= loc.pool


def test_relocates_after_a_kidnap():
    codes = _map()
    rng = np.random.default_rng(2)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    assert abs(loc.filter_.place_ - 3059) <= 2
    reseeds = loc.n_reseeds_
    after = 17000 + np.arange(80)
    fixes = _drive(loc, codes, after, rng)
    right = [
        abs(f.place - t) <= 2 and f.state == "localized" for f, t in zip(fixes, after, strict=True)
    ]
    assert any(right[:40])
    assert all(right[-20:])
    assert loc.n_reseeds_ > reseeds


def test_odometry_and_images_need_what_they_need():
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    rng = np.random.default_rng(3)
    truth = 2000 + 2 * np.arange(60)
    fixes = [
        loc.update_code(_query(codes, p, rng), velocity=None if t == 0 else 2.0)
        for t, p in enumerate(truth)
    ]
    assert abs(fixes[-1].place - truth[-1]) <= 2
    with pytest.raises(ValueError, match="encoder"):
        loc.update(np.zeros((32, 64), np.float32))


def test_errors():
    codes = _map(n=1000)
    index = ExhaustiveIndex().build(codes)
    with pytest.raises(ValueError, match="1000 codes"):
        LargeLocalizer(codes, ExhaustiveIndex().build(codes[:10]))
    with pytest.raises(TypeError, match="CandidateIndex"):
        LargeLocalizer(codes, object())
    with pytest.raises(ValueError, match="multiple of 8"):
        LargeLocalizer(codes[:, :5], index)
    with pytest.raises(ValueError, match="k"):
        LargeLocalizer(codes, index, k=0)
    with pytest.raises(ValueError, match="reseed_after"):
        LargeLocalizer(codes, index, reseed_after=0)
    loc = LargeLocalizer(codes, index, window=128)
    with pytest.raises(ValueError, match=r"code must be uint8 of shape \(32,\)"):
        loc.update_code(np.zeros(16, np.uint8))
    with pytest.raises(ValueError, match="code must be uint8"):
        loc.update_code(np.zeros(32, np.int64))
