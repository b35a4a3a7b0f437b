"""The compiled kernels of the ``kenyon`` front end against the NumPy/SciPy computations they
replace (bit for bit, but for the Gabor filtering: to float32 rounding), and the single-frame
path against the batch path."""

import numpy as np
import pytest
from scipy import ndimage, sparse

from flyvpr.frontends import _kenyon_kernels as kk
from flyvpr.frontends.flyhash import winner_take_all
from flyvpr.frontends.kenyon import KenyonEncoder, _inverted_index, _overlap_packed
from flyvpr.frontends.optic_lobe import OpticLobe, local_contrast_normalize
from flyvpr.images import list_images, load_images
from flyvpr.localization import Localizer
from flyvpr.methods import make_method
from oracles import gabor_energy


def _bits(a):
    """float32 values as their bit patterns, so that equality means bit for bit."""
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def _scipy_lcn(x, sigma, eps):
    mean = ndimage.gaussian_filter(x, (0, sigma, sigma), mode="reflect")
    centred = x - mean
    var = ndimage.gaussian_filter(centred * centred, (0, sigma, sigma), mode="reflect")
    return (centred / np.sqrt(var + np.float32(eps * eps))).astype(np.float32)


def _scipy_lcn_masked(x, valid, sigma, eps):
    """Normalised convolution over the valid pixels, as NumPy/SciPy compute it; 0 elsewhere."""
    m = valid.astype(np.float32)
    gm = ndimage.gaussian_filter(m, sigma, mode="reflect")
    num = ndimage.gaussian_filter(x * m, (0, sigma, sigma), mode="reflect")
    with np.errstate(divide="ignore", invalid="ignore"):  # invalid pixels far from valid ones
        centred = np.where(valid, x - num / gm, np.float32(0.0))
        var = ndimage.gaussian_filter(centred * centred, (0, sigma, sigma), mode="reflect") / gm
        out = np.where(valid, centred / np.sqrt(var + np.float32(eps * eps)), np.float32(0.0))
    return out.astype(np.float32)


def _disc(h, w):
    y, x = np.mgrid[0:h, 0:w]
    return ((y - (h - 1) / 2) / (h / 2)) ** 2 + ((x - (w - 1) / 2) / (0.2625 * w)) ** 2 <= 1


def _masks(shape, seed):
    """A random mask, a disc, one valid pixel, and a block far from the corners."""
    h, w = shape
    rng = np.random.default_rng(seed)
    one = np.zeros(shape, bool)
    one[h // 2, w // 3] = True
    block = np.zeros(shape, bool)
    block[h // 4 : h // 2 + 1, w // 4 : w // 2 + 1] = True
    return [rng.random(shape) < 0.7, _disc(h, w), one, block]


def _numpy_zscore(f):
    f = f.copy()
    mean = f.mean(axis=1, keepdims=True)
    std = f.std(axis=1, keepdims=True)
    f -= mean
    np.divide(f, std, out=f, where=std > 1e-12)
    return f


def _numpy_features(x, bank, pool=4):
    """The optic lobe as NumPy and SciPy compute it: LCN, Gabor energy, max pooling, z-score."""
    n, h, w = x.shape
    energy = gabor_energy(_scipy_lcn(x, 4.0, 0.05), bank)
    pooled = energy.reshape(-1, pool).max(axis=1)
    pooled = pooled.reshape(n * len(bank) * (h // pool), pool, w // pool).max(axis=1)
    return _numpy_zscore(np.sqrt(pooled).reshape(n, -1))


def _sparse_activity(features, feature_mean, connections, n_features):
    n_kenyon, n_in = connections.shape
    weights = sparse.csr_matrix(
        (
            np.ones(n_kenyon * n_in, dtype=np.float32),
            connections.ravel(),
            np.arange(0, n_kenyon * n_in + 1, n_in),
        ),
        shape=(n_kenyon, n_features),
    )
    return np.asarray((weights @ (features - feature_mean).T).T, dtype=np.float32)


def _numpy_codes(features, feature_mean, connections, n_proj, k):
    y = _sparse_activity(features, feature_mean, connections, features.shape[1])
    bits = winner_take_all(y.reshape(len(y) * n_proj, -1), k).reshape(len(y), -1)
    return np.packbits(bits, axis=1)


@pytest.mark.parametrize("shape", [(4, 32, 64), (3, 3, 7), (2, 17, 40)])
@pytest.mark.parametrize("sigma", [1.0, 2.5, 4.0])
def test_lcn_equals_scipy_gaussian_filter_bit_for_bit(shape, sigma):
    x = np.random.default_rng(len(shape) + int(sigma)).random(shape, dtype=np.float32)
    for eps in (0.05, 1e-6):
        got = local_contrast_normalize(x, sigma=sigma, eps=eps)
        np.testing.assert_array_equal(_bits(got), _bits(_scipy_lcn(x, sigma, eps)))


@pytest.mark.parametrize("shape", [(3, 32, 64), (2, 3, 7), (2, 17, 40)])
@pytest.mark.parametrize("sigma", [1.0, 4.0])
def test_masked_lcn_equals_scipy_normalised_convolution_bit_for_bit(shape, sigma):
    x = np.random.default_rng(shape[1]).random(shape, dtype=np.float32)
    for valid in _masks(shape[1:], int(sigma)):
        for eps in (0.05, 1e-6):
            got = local_contrast_normalize(x, sigma=sigma, eps=eps, valid_pixels=valid)
            expected = _scipy_lcn_masked(x, valid, sigma, eps)
            np.testing.assert_array_equal(_bits(got), _bits(expected))
            assert np.all(got[:, ~valid] == 0) and np.isfinite(got).all()


@pytest.mark.parametrize("d", [5, 8, 100, 129, 512, 1000, 4099])
def test_zscore_equals_numpy_mean_and_std_bit_for_bit(d):
    rng = np.random.default_rng(d)
    f = (3 * rng.standard_normal((20, d)) + 1).astype(np.float32)
    f[0] = 0.25  # a constant row: std 0, the row is only centred
    got = kk.zscore_rows(f.copy(), np.float32(1e-12))
    np.testing.assert_array_equal(_bits(got), _bits(_numpy_zscore(f)))


@pytest.mark.parametrize(
    ("shape", "gabor", "pool"),
    [
        ((4, 32, 64), (4, 6.0, 11), 4),  # the defaults
        ((3, 8, 12), (6, 4.0, 7), 2),  # other orientations, wavelength and size
        ((2, 4, 8), (3, 8.0, 11), 4),  # an image smaller than the kernel
        ((1, 6, 6), (1, 3.0, 3), 3),
    ],
)
def test_direct_gabor_equals_the_fft_convolution(shape, gabor, pool):
    # The compiled optic lobe (direct separable convolution) against LCN, FFT Gabor energy,
    # max pooling, square root and z-score in NumPy/SciPy: equal to float32 rounding.
    x = np.random.default_rng(sum(shape)).random(shape, dtype=np.float32)
    lobe = OpticLobe(4.0, 0.05, *gabor, pool)
    got = lobe(x)
    n, h, w = shape
    energy = gabor_energy(_scipy_lcn(x, 4.0, 0.05), lobe.bank)
    cells = energy.reshape(n, gabor[0], h // pool, pool, w // pool, pool).max(axis=(3, 5))
    expected = _numpy_zscore(np.sqrt(cells).reshape(n, -1))
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-5)
    # the bank (built from the separable factors) is the 2-d Gabor kernel of its definition:
    # a circular envelope times a carrier along the orientation, zero mean, unit L1 norm
    n_k, wavelength, size = gabor
    r = size // 2
    y, x = np.mgrid[-r : r + 1, -r : r + 1].astype(np.float64)
    theta = np.arange(n_k)[:, None, None] * np.pi / n_k
    along = x * np.cos(theta) + y * np.sin(theta)
    envelope = np.exp(-(x**2 + y**2) / (2 * (0.56 * wavelength) ** 2))
    kernel = envelope * np.exp(2j * np.pi * along / wavelength)
    kernel -= kernel.real.sum(axis=(1, 2), keepdims=True) / envelope.sum() * envelope
    kernel /= np.abs(kernel).sum(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(lobe.bank, kernel, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("shape", "gabor", "pool"),
    [
        ((3, 32, 64), (4, 6.0, 11), 4),  # the defaults
        ((2, 8, 12), (6, 4.0, 7), 2),
        ((2, 6, 6), (1, 3.0, 3), 3),
        ((2, 8, 12), (8, 4.0, 3), 2),  # more orientations than taps
    ],
)
def test_masked_optic_lobe_equals_the_numpy_pipeline(shape, gabor, pool):
    # Masked LCN, FFT Gabor energy, max pooling, square root; the features that are not 0 in
    # every image, z-scored over these only: to float32 rounding.
    n, h, w = shape
    x = np.random.default_rng(sum(shape)).random(shape, dtype=np.float32)
    lobe = OpticLobe(4.0, 0.05, *gabor, pool)
    for valid in _masks((h, w), pool):
        energy = gabor_energy(_scipy_lcn_masked(x, valid, 4.0, 0.05), lobe.bank)
        pooled = energy.reshape(n, gabor[0], h // pool, pool, w // pool, pool).max(axis=(3, 5))
        pooled = np.sqrt(pooled).reshape(n, -1)
        expected = _numpy_zscore(pooled[:, lobe.kept_features(valid)])
        np.testing.assert_allclose(lobe(x, valid), expected, rtol=0, atol=2e-5)


@pytest.mark.parametrize(("n_kenyon", "n_proj", "k"), [(4096, 1, 205), (48, 3, 5), (24, 6, 1)])
@pytest.mark.parametrize("ties", [False, True])
def test_codes_equal_sparse_product_winner_take_all_and_packbits(n_kenyon, n_proj, k, ties):
    rng = np.random.default_rng(n_kenyon + k)
    n_features = 64
    connections = np.sort(
        np.stack([rng.choice(n_features, 6, replace=False) for _ in range(n_kenyon)]), axis=1
    ).astype(np.int32)
    f = rng.standard_normal((30, n_features)).astype(np.float32)
    if ties:  # few distinct values: many Kenyon cells tie at the k-th largest activity
        f = np.round(f).astype(np.float32)
    mean = (0.1 * rng.standard_normal(n_features)).astype(np.float32)
    out = np.empty((30, n_kenyon // 8), np.uint8)
    got = kk.kenyon_codes(f, mean, connections, n_proj, k, out)
    np.testing.assert_array_equal(got, _numpy_codes(f, mean, connections, n_proj, k))
    y = kk.kenyon_activity(f, mean, connections, np.empty((30, n_kenyon), np.float32))
    np.testing.assert_array_equal(_bits(y), _bits(_sparse_activity(f, mean, connections, 64)))


def test_kth_largest_when_the_sample_misleads():
    # every 32nd value (the sampled ones) is the largest: fewer than k values reach the
    # sample's threshold, and the selection falls back to all values
    y = np.arange(4096, dtype=np.float32) / 4096
    y[::32] = 10.0
    for k in (1, 100, 128, 129, 205, 4096):
        buf = np.empty(4096, np.float32)
        assert kk._kth_largest(y, k, buf) == np.sort(y)[-k]


@pytest.mark.parametrize("n_query", [1, 3, 12])
@pytest.mark.parametrize("n_bits", [64, 600])
def test_chunked_index_and_counters_match_a_loop(n_query, n_bits):
    # chunks of 16 places (the encoder uses 65,536); 600-bit queries about half full need
    # counters wider than 8 bits
    rng = np.random.default_rng(n_query)
    r = rng.random((50, n_bits)) < 0.3
    q = rng.random((n_query, n_bits)) < 0.5
    indptr, places = _inverted_index(np.packbits(r, axis=1), n_bits, chunk=16)
    assert indptr.shape == (4, n_bits + 1) and places.dtype == np.uint16
    got = _overlap_packed(np.packbits(q, axis=1), indptr, places, 50, 0.5, chunk=16)
    expected = np.array([[np.sum(a & b) for b in r] for a in q], dtype=np.float32) * 0.5
    np.testing.assert_array_equal(got, expected)


@pytest.fixture(scope="module")
def nordland(nordland_64x32):
    ref = load_images(list_images(nordland_64x32 / "summer")[:300], progress=False)
    qry = load_images(list_images(nordland_64x32 / "winter")[:120], progress=False)
    return ref, qry


@pytest.mark.parametrize("seed", [0, 1])
def test_codes_equal_the_numpy_scipy_pipeline_on_nordland(nordland, seed):
    ref, qry = nordland
    enc = KenyonEncoder(random_state=seed).fit(ref)
    bank = enc._optic_lobe.bank
    # The optic lobe: to float32 rounding of the FFT pipeline.
    features = enc._lobe(qry)
    fft_features = _numpy_features(qry, bank)
    np.testing.assert_allclose(features, fft_features, rtol=0, atol=2e-5)
    # From the features on, bit for bit.
    expected = _numpy_codes(features, enc.feature_mean_, enc.connections_, 1, enc.n_active_)
    np.testing.assert_array_equal(enc.encode(qry), expected)
    ref_features = enc._lobe(ref)
    np.testing.assert_array_equal(_bits(enc.feature_mean_), _bits(ref_features.mean(axis=0)))
    ref_codes = _numpy_codes(ref_features, enc.feature_mean_, enc.connections_, 1, enc.n_active_)
    np.testing.assert_array_equal(enc.reference_codes_, ref_codes)
    # The rounding flips only Kenyon cells tied with the k-th most active to within it.
    fft_codes = _numpy_codes(fft_features, enc.feature_mean_, enc.connections_, 1, enc.n_active_)
    flipped = np.unpackbits(fft_codes ^ expected, axis=1).sum(axis=1)
    assert flipped.max() <= 4 and flipped.mean() < 0.1


def test_single_frame_path_equals_batch_bit_for_bit(nordland):
    ref, qry = nordland
    enc = KenyonEncoder(random_state=0).fit(ref)
    batch = enc.encode(qry)
    one_by_one = np.concatenate([enc.encode(qry[i : i + 1]) for i in range(len(qry))])
    np.testing.assert_array_equal(one_by_one, batch)
    S = enc.score_codes(batch)  # >= 8 queries: the parallel kernel
    rows = np.concatenate([enc.score_codes(batch[i : i + 1]) for i in range(len(qry))])
    np.testing.assert_array_equal(_bits(rows), _bits(S))
    loc = Localizer(make_method("kenyon", 0)).fit(ref)
    streamed = np.stack([loc.scores(img) for img in qry])
    np.testing.assert_array_equal(_bits(streamed), _bits(S))


def test_fisheye_codes_on_nordland_equal_the_numpy_pipeline_and_ignore_the_border(nordland):
    ref, qry = nordland
    disc = _disc(32, 64)
    enc = KenyonEncoder(random_state=0).fit(np.where(disc, ref, np.float32(0.05)))
    np.testing.assert_array_equal(enc.valid_pixels_, disc)
    dark, grey = (np.where(disc, qry, np.float32(v)) for v in (0.05, 0.5))
    features = enc._lobe(dark)
    np.testing.assert_array_equal(_bits(enc._lobe(grey)), _bits(features))
    kept = enc._optic_lobe.kept_features(disc)
    energy = gabor_energy(_scipy_lcn_masked(dark, disc, 4.0, 0.05), enc._optic_lobe.bank)
    assert enc.pool_ == 2  # (41% of the pixels vary: 2x2 cells)
    pooled = energy.reshape(len(qry), 4, 16, 2, 32, 2).max(axis=(3, 5))
    expected = _numpy_zscore(np.sqrt(pooled).reshape(len(qry), -1)[:, kept])
    np.testing.assert_allclose(features, expected, rtol=0, atol=2e-5)
    codes = _numpy_codes(features, enc.feature_mean_, enc.connections_, 1, enc.n_active_)
    np.testing.assert_array_equal(enc.encode(dark), codes)
    np.testing.assert_array_equal(enc.encode(grey), codes)
    one_by_one = np.concatenate([enc.encode(grey[i : i + 1]) for i in range(len(qry))])
    np.testing.assert_array_equal(one_by_one, codes)
