import numpy as np
import pytest

from flyvpr import NotFittedError
from flyvpr.frontends import KenyonEncoder
from flyvpr.large import (
    CompactEncoder,
    hamming_distance,
    hamming_similarity,
    hamming_similarity_at,
)


def slow_distance(q, c):
    bits_q = np.unpackbits(q, axis=1).astype(int)
    bits_c = np.unpackbits(c, axis=1).astype(int)
    return np.array([[int(np.sum(a != b)) for b in bits_c] for a in bits_q])


@pytest.fixture(scope="module")
def codes():
    return np.random.default_rng(0).integers(0, 256, (300, 32), dtype=np.uint8)


@pytest.mark.parametrize("n_query", [1, 9])
def test_distance_matches_slow_loop(codes, n_query):
    q = codes[:n_query] ^ np.uint8(5)
    np.testing.assert_array_equal(hamming_distance(q, codes), slow_distance(q, codes))


def test_batch_kernel_matches_slow_loop():
    rng = np.random.default_rng(1)
    c = rng.integers(0, 256, (9000, 8), dtype=np.uint8)
    q = rng.integers(0, 256, (8, 8), dtype=np.uint8)
    d = hamming_distance(q, c, 100, 8300)
    np.testing.assert_array_equal(d, slow_distance(q, c[100:8300]))


def test_similarity_range_and_places_equal_full(codes):
    q = codes[[3, 7]]
    full = hamming_similarity(q, codes)
    assert full.dtype == np.float32 and full.shape == (2, 300)
    np.testing.assert_allclose(full, 1 - slow_distance(q, codes) / 256)
    np.testing.assert_array_equal(hamming_similarity(q, codes, lo=40, hi=90), full[:, 40:90])
    places = np.array([5, 0, 299, 5])
    np.testing.assert_array_equal(hamming_similarity_at(q, codes, places), full[:, places])
    assert hamming_similarity(q, codes, 10, 10).shape == (2, 0)


def test_similarity_reads_a_memmap(tmp_path, codes):
    path = tmp_path / "c.bin"
    codes.tofile(path)
    mm = np.memmap(path, dtype=np.uint8, mode="r", shape=codes.shape)
    np.testing.assert_array_equal(
        hamming_similarity(codes[0], mm, 1, 5), hamming_similarity(codes[0], codes, 1, 5)
    )


def test_hand_worked():
    c = np.zeros((3, 8), np.uint8)
    c[1, 0], c[2] = 0b1011, 255
    assert hamming_distance(c[0], c).tolist() == [[0, 3, 64]]
    assert hamming_similarity(c[1], c).tolist() == [[1 - 3 / 64, 1.0, 1 - 61 / 64]]


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda c: hamming_distance(c[:1].astype(np.int8), c), "uint8"),
        (lambda c: hamming_distance(c[:1, :7], c[:, :7]), "multiple of 8"),
        (lambda c: hamming_distance(c[:1, :16], c), "bytes per code"),
        (lambda c: hamming_distance(c[:1], c, 5, 400), "lo and hi"),
        (lambda c: hamming_distance(c[:1], c, 6, 5), "lo and hi"),
        (lambda c: hamming_similarity_at(c[:1], c, [0, 300]), "places must lie"),
        (lambda c: hamming_similarity_at(c[:1], c, [[1]]), "1-d"),
    ],
)
def test_errors(codes, call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call(codes)


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(0)
    return rng.random((20, 32, 64), dtype=np.float32)


@pytest.mark.parametrize("projection", ["pca", "simhash"])
@pytest.mark.parametrize("n_bits", [64, 256, 512])
def test_encoder_shapes_and_self_match(images, projection, n_bits):
    enc = CompactEncoder(n_bits=n_bits, projection=projection, random_state=0).fit(images)
    codes = enc.encode(images)
    assert codes.dtype == np.uint8 and codes.shape == (20, n_bits // 8)
    np.testing.assert_array_equal(codes, enc.reference_codes_)
    S = enc.score(images)
    assert S.shape == (20, 20)
    np.testing.assert_array_equal(S.argmax(axis=1), np.arange(20))
    np.testing.assert_array_equal(enc.score_range(codes, 4, 9), S[:, 4:9])
    assert enc.bytes_per_place() == n_bits / 8


def test_pca_bits_are_balanced(images):
    enc = CompactEncoder(n_bits=128, random_state=0).fit(images)
    bits = np.unpackbits(enc.reference_codes_, axis=1)
    # centred features, projected: each image sets about half its bits
    assert 0.3 < bits.mean() < 0.7


def test_seed_is_deterministic(images):
    a = CompactEncoder(random_state=3).fit(images).reference_codes_
    b = CompactEncoder(random_state=3).fit(images).reference_codes_
    np.testing.assert_array_equal(a, b)


def test_from_kenyon_shares_the_optic_lobe(images):
    ken = KenyonEncoder(random_state=0).fit(images)
    enc = CompactEncoder.from_kenyon(ken, images, n_bits=256, random_state=0)
    np.testing.assert_array_equal(enc.feature_mean_, ken.feature_mean_)
    own = CompactEncoder(random_state=0).fit(images)
    # same lobe, same mean, same seed: the same codes as fitting from the images
    np.testing.assert_array_equal(enc.reference_codes_, own.reference_codes_)
    with pytest.raises(TypeError, match="KenyonEncoder"):
        CompactEncoder.from_kenyon(own, images)
    with pytest.raises(TypeError, match="optic lobe"):
        CompactEncoder.from_kenyon(ken, images, lcn_sigma=2.0)


def test_from_kenyon_takes_the_pooling_it_used_under_a_mask(images):
    y, x = np.mgrid[0:32, 0:64]
    disc = ((y - 15.5) / 16) ** 2 + ((x - 31.5) / 16.8) ** 2 <= 1  # a fisheye's, 41%
    masked = np.where(disc, images, np.float32(0.05)).astype(np.float32)
    ken = KenyonEncoder(random_state=0).fit(masked)
    assert ken.pool_size == 4 and ken.pool_ == 2  # (fewer than half of the pixels vary)
    enc = CompactEncoder.from_kenyon(ken, masked, n_bits=256, random_state=0)
    assert enc.pool_size == 2
    np.testing.assert_array_equal(enc.feature_mean_, ken.feature_mean_)
    own = CompactEncoder(pool_size=2, random_state=0).fit(masked)
    np.testing.assert_array_equal(enc.reference_codes_, own.reference_codes_)


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"n_bits": 100}, "multiple of 64"),
        ({"n_bits": 1024}, "up to 512"),
        ({"projection": "lsh"}, "projection must be"),
    ],
)
def test_encoder_param_errors(images, params, match):
    with pytest.raises(ValueError, match=match):
        CompactEncoder(**params).fit(images)


def test_encoder_not_fitted_and_bad_codes(images):
    with pytest.raises(NotFittedError):
        CompactEncoder().encode(images)
    enc = CompactEncoder(random_state=0).fit(images)
    with pytest.raises(ValueError, match="shape"):
        enc.score_codes(np.zeros((2, 16), np.uint8))
