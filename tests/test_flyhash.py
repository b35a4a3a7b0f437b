import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends.flyhash import FlyHash, sample_connections, winner_take_all


def test_defaults_follow_the_paper(random_images):
    fh = FlyHash(random_state=0).fit(random_images(10))
    assert fh.connections_.shape == (64, 205)  # round(0.1 * 2048)
    assert fh.n_active_ == 32  # round(0.5 * 64)
    assert fh.n_inputs_ == 2048


@pytest.mark.parametrize("ratio", [0.05, 0.1, 0.33, 0.9])
def test_each_unit_reads_exactly_its_share_of_distinct_pixels(random_images, ratio):
    fh = FlyHash(sampling_ratio=ratio, random_state=1).fit(random_images(3))
    expected = round(ratio * 2048)
    assert fh.connections_.shape[1] == expected
    for row in fh.connections_:
        assert len(np.unique(row)) == expected
        assert row.min() >= 0 and row.max() < 2048


def test_connections_are_spread_uniformly():
    conn = sample_connections(2000, 100, 10, random_state=0)
    counts = np.bincount(conn.ravel(), minlength=100)
    # each input is chosen with p = 0.1 by each of 2000 units: mean 200, sd ~13.4
    assert abs(counts.mean() - 200) < 1e-9
    assert counts.min() > 140 and counts.max() < 260


@pytest.mark.parametrize("wta", [0.05, 0.25, 0.5, 0.95])
def test_wta_leaves_exactly_k_active(random_images, wta):
    fh = FlyHash(wta_ratio=wta, random_state=2).fit(random_images(4))
    codes = fh.encode(random_images(50))
    assert codes.dtype == bool and codes.shape == (50, 64)
    assert np.all(codes.sum(axis=1) == round(wta * 64))


def test_wta_tie_rule_lowest_index_wins():
    y = np.array([[1.0, 5.0, 5.0, 5.0, 0.0], [2.0, 2.0, 2.0, 2.0, 2.0]])
    out = winner_take_all(y, 2)
    np.testing.assert_array_equal(out, [[0, 1, 1, 0, 0], [1, 1, 0, 0, 0]])


def test_wta_against_stable_sort_reference():
    rng = np.random.default_rng(3)
    y = rng.integers(0, 5, size=(200, 16)).astype(np.float32)  # many ties
    k = 6
    order = np.argsort(-y, axis=1, kind="stable")
    ref = np.zeros_like(y, dtype=bool)
    np.put_along_axis(ref, order[:, :k], True, axis=1)
    np.testing.assert_array_equal(winner_take_all(y, k), ref)


@pytest.mark.parametrize("k", [0, 17])
def test_wta_bad_k(k):
    with pytest.raises(ValueError, match="k must"):
        winner_take_all(np.zeros((2, 16)), k)


def test_black_frames_get_a_deterministic_code(random_images):
    fh = FlyHash(random_state=0).fit(random_images(3))
    code = fh.encode(np.zeros((2, 32, 64), np.float32))
    np.testing.assert_array_equal(code[0], np.arange(64) < 32)


def test_seed_reproducible_and_different(random_images):
    imgs = random_images(20)
    a = FlyHash(random_state=5).fit(imgs)
    b = FlyHash(random_state=5).fit(imgs)
    c = FlyHash(random_state=6).fit(imgs)
    np.testing.assert_array_equal(a.connections_, b.connections_)
    assert not np.array_equal(a.connections_, c.connections_)


def test_encoding_is_batch_independent(random_images):
    imgs = random_images(300)
    fh = FlyHash(random_state=0).fit(imgs[:10])
    batch = fh.encode(imgs)
    single = np.stack([fh.encode(imgs[i : i + 1])[0] for i in range(0, 300, 7)])
    np.testing.assert_array_equal(batch[::7], single)


def test_activation_matches_explicit_sum(random_images):
    imgs = random_images(4)
    fh = FlyHash(random_state=0).fit(imgs)
    y = fh.activations(imgs)
    levels = fh._levels
    flat = np.rint(imgs.reshape(4, -1) * levels)
    ref = np.stack([flat[:, c].sum(axis=1) for c in fh.connections_], axis=1)
    np.testing.assert_array_equal(y, ref)


def test_score_is_code_overlap(random_images):
    imgs = random_images(6)
    fh = FlyHash(random_state=0).fit(imgs)
    S = fh.score(imgs)
    assert S.shape == (6, 6)
    np.testing.assert_allclose(np.diag(S), 1.0)
    q = random_images(3)
    codes = fh.encode(q).astype(int)
    ref = codes @ fh.reference_codes_.T.astype(int) / 32
    np.testing.assert_allclose(fh.score(q), ref)


def test_packed_connections_are_one_bit_per_weight(random_images):
    fh = FlyHash(random_state=0).fit(random_images(2))
    packed = fh.packed_connections()
    assert packed.nbytes == 64 * 2048 // 8
    dense = np.unpackbits(packed, axis=1)
    assert np.all(dense.sum(axis=1) == 205)
    for unit in range(64):
        np.testing.assert_array_equal(np.flatnonzero(dense[unit]), fh.connections_[unit])


def test_not_fitted():
    with pytest.raises(NotFittedError, match="fit"):
        FlyHash().encode(np.zeros((1, 32, 64)))


@pytest.mark.parametrize(
    "params, match",
    [
        ({"n_hidden": 0}, "n_hidden"),
        ({"sampling_ratio": 0.0}, "sampling_ratio"),
        ({"sampling_ratio": 1.5}, "sampling_ratio"),
        ({"wta_ratio": -0.1}, "wta_ratio"),
        ({"n_hidden": 2.5}, "n_hidden"),
    ],
)
def test_bad_params(random_images, params, match):
    with pytest.raises((ValueError, TypeError), match=match):
        FlyHash(**params).fit(random_images(2))


def test_query_size_must_match(random_images):
    fh = FlyHash(random_state=0).fit(random_images(2))
    with pytest.raises(ValueError, match=r"\(32, 64\)"):
        fh.encode(random_images(2, 16, 32))


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.full((2, 32, 64), np.nan, np.float32), "NaN"),
        (np.full((2, 32, 64), 2.0, np.float32), r"\[0, 1\]"),
        (np.zeros((32, 64), np.float32), "shape"),
        (np.zeros((0, 32, 64), np.float32), "empty"),
    ],
)
def test_bad_images(bad, match):
    with pytest.raises(ValueError, match=match):
        FlyHash(random_state=0).fit(bad)


def test_get_set_params():
    fh = FlyHash()
    assert fh.get_params() == {
        "n_hidden": 64,
        "sampling_ratio": 0.1,
        "wta_ratio": 0.5,
        "random_state": None,
    }
    fh.set_params(n_hidden=32)
    assert fh.n_hidden == 32
    with pytest.raises(ValueError, match="invalid parameter"):
        fh.set_params(bogus=1)


def test_large_batch_across_encoding_blocks(random_images):
    # Encoding runs in blocks of 2048 images; codes must not depend on the block.
    fh = FlyHash(random_state=0).fit(random_images(2))
    big = np.repeat(random_images(7), 10000, axis=0)
    codes = fh.encode(big)
    assert codes.shape == (70000, 64)
    # images 60000..69999 are one repeated image, split across two blocks
    np.testing.assert_array_equal(codes[65535], codes[65536])
    assert np.all(codes.sum(axis=1) == 32)
