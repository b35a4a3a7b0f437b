"""Tests of the raw-pixel front end: patch normalisation, SAD matrix, PixelsEncoder."""

from __future__ import annotations

import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends import pixels
from flyvpr.frontends.pixels import PixelsEncoder, patch_normalize, sad_matrix


def _slow_patch_normalize(images, p):
    out = np.zeros(images.shape, dtype=np.float64)
    for n in range(images.shape[0]):
        for i in range(0, images.shape[1], p):
            for j in range(0, images.shape[2], p):
                patch = images[n, i : i + p, j : j + p].astype(np.float64)
                std = patch.std()
                if std > 0:
                    out[n, i : i + p, j : j + p] = (patch - patch.mean()) / std
    return out


def _slow_sad(query, reference):
    out = np.zeros((len(query), len(reference)))
    for i, q in enumerate(query):
        for j, r in enumerate(reference):
            out[i, j] = sum(abs(float(a) - float(b)) for a, b in zip(q, r, strict=True))
    return out


# -- patch_normalize -------------------------------------------------------------------------
@pytest.mark.parametrize("patch_size", [2, 4, 8, 16])
def test_patch_normalize_each_patch_has_zero_mean_unit_std(random_images, patch_size):
    images = random_images(3)
    out = patch_normalize(images, patch_size)
    assert out.shape == images.shape
    assert out.dtype == np.float32
    patches = out.reshape(3, 32 // patch_size, patch_size, 64 // patch_size, patch_size)
    np.testing.assert_allclose(patches.mean(axis=(2, 4)), 0.0, atol=1e-5)
    np.testing.assert_allclose(patches.std(axis=(2, 4)), 1.0, atol=1e-4)


def test_patch_normalize_matches_slow_loop(random_images):
    images = random_images(2, 16, 24)
    np.testing.assert_allclose(
        patch_normalize(images, 8), _slow_patch_normalize(images, 8), atol=1e-5
    )


def test_patch_normalize_flat_patches_become_zero(random_images):
    images = random_images(2)
    images[0, :8, :8] = 0.3  # a flat patch inside a textured image
    images[1] = 0.7  # a flat image
    out = patch_normalize(images, 8)
    assert np.all(out[0, :8, :8] == 0.0)
    assert np.all(out[1] == 0.0)
    assert np.isfinite(out).all()
    # the textured patches beside the flat one are still normalised
    np.testing.assert_allclose(out[0, :8, 8:16].std(), 1.0, atol=1e-4)


def test_patch_normalize_ignores_brightness_and_contrast_per_patch(random_images):
    images = random_images(2) * 0.5
    changed = 0.2 + 1.5 * images  # stays inside [0, 1]
    np.testing.assert_allclose(patch_normalize(changed), patch_normalize(images), atol=1e-4)


@pytest.mark.parametrize(
    ("patch_size", "error", "match"),
    [
        (3, ValueError, "patch_size must divide"),
        (1, ValueError, "patch_size"),
        (0, ValueError, "patch_size"),
        (8.0, TypeError, "patch_size"),
    ],
)
def test_patch_normalize_rejects_bad_patch_size(random_images, patch_size, error, match):
    with pytest.raises(error, match=match):
        patch_normalize(random_images(1), patch_size)


def test_patch_normalize_rejects_bad_images():
    with pytest.raises(ValueError, match="images"):
        patch_normalize(np.zeros((32, 64)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        patch_normalize(np.full((1, 32, 64), 2.0))


# -- sad_matrix ------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["auto", "numba", "scipy"])
@pytest.mark.parametrize(
    ("n_query", "n_reference", "n_features"), [(7, 5, 33), (1, 9, 4), (13, 1, 70)]
)
def test_sad_matrix_matches_slow_loop(rng, backend, n_query, n_reference, n_features):
    if backend == "numba":
        pytest.importorskip("numba")
    query = rng.standard_normal((n_query, n_features)).astype(np.float32)
    reference = rng.standard_normal((n_reference, n_features)).astype(np.float32)
    out = sad_matrix(query, reference, backend=backend)
    assert out.shape == (n_query, n_reference)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, _slow_sad(query, reference), rtol=1e-5, atol=1e-4)
    normalized = sad_matrix(query, reference, normalize=True, backend=backend)
    np.testing.assert_allclose(normalized, out / n_features, rtol=1e-6)


def test_sad_matrix_hand_worked():
    out = sad_matrix([[0.0, 1.0], [2.0, 2.0]], [[0.0, 0.0], [1.0, 1.0]])
    np.testing.assert_array_equal(out, [[1.0, 1.0], [4.0, 2.0]])


def test_sad_matrix_auto_is_the_numba_kernel(rng, monkeypatch):
    query = rng.random((9, 10), dtype=np.float32)
    reference = rng.random((3, 10), dtype=np.float32)
    calls = []
    kernel = pixels._kernels().sad_kernel

    def spy(*args):
        calls.append(args[2])  # the block of queries per work item
        return kernel(*args)

    monkeypatch.setattr(pixels._kernels(), "sad_kernel", spy)
    np.testing.assert_array_equal(
        sad_matrix(query, reference), sad_matrix(query, reference, backend="numba")
    )
    assert len(calls) == 2 and calls[0] >= 4
    sad_matrix(query, reference, backend="scipy")
    assert len(calls) == 2  # scipy's cdist, not the kernel


def test_sad_matrix_same_bits_for_any_batch_and_thread_count(rng):
    numba = pytest.importorskip("numba")
    query = rng.standard_normal((67, 2048)).astype(np.float32)
    reference = rng.standard_normal((9, 2048)).astype(np.float32)
    whole = sad_matrix(query, reference)
    one_by_one = np.concatenate([sad_matrix(q[None], reference) for q in query])
    np.testing.assert_array_equal(one_by_one, whole)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        np.testing.assert_array_equal(sad_matrix(query, reference), whole)
    finally:
        numba.set_num_threads(before)


_SAD_BITS = """
import hashlib, numpy as np
from flyvpr.frontends.pixels import sad_matrix
rng = np.random.default_rng(0)
q = rng.standard_normal((70, 2048)).astype(np.float32)
r = rng.standard_normal((50, 2048)).astype(np.float32)
print(hashlib.sha1(sad_matrix(q, r).tobytes()).hexdigest())
"""


def test_sad_matrix_same_bits_compiled_and_cached(tmp_path):
    """The run that compiles the kernel and the runs that load it from numba's disk cache give
    the same bits (a ``parallel=True`` kernel with reassociation did not: its cached code
    summed in another order)."""
    import os
    import subprocess
    import sys

    pytest.importorskip("numba")
    import flyvpr

    path = os.pathsep.join([os.path.dirname(os.path.dirname(flyvpr.__file__)), *sys.path])
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "PYTHONPATH": path}
    runs = [
        subprocess.run(
            [sys.executable, "-c", _SAD_BITS], env=env, capture_output=True, text=True, check=True
        ).stdout
        for _ in range(2)
    ]
    assert any(tmp_path.rglob("*.nbi")), "the first run wrote no cache"
    assert runs[0] == runs[1]


@pytest.mark.parametrize(
    ("query", "reference", "error", "match"),
    [
        (np.zeros((2, 3)), np.zeros((2, 4)), ValueError, "same number of features"),
        (np.zeros(3), np.zeros((2, 3)), ValueError, "query_codes must have shape"),
        (np.zeros((2, 3)), np.zeros((0, 3)), ValueError, "reference_codes is empty"),
        (np.array([[0.0, np.nan]]), np.zeros((1, 2)), ValueError, "NaN"),
        (np.array([["a", "b"]]), np.zeros((1, 2)), TypeError, "numeric"),
    ],
)
def test_sad_matrix_errors(query, reference, error, match):
    with pytest.raises(error, match=match):
        sad_matrix(query, reference)


def test_sad_matrix_rejects_unknown_backend():
    with pytest.raises(ValueError, match="backend"):
        sad_matrix(np.zeros((1, 2)), np.zeros((1, 2)), backend="gpu")


# -- PixelsEncoder ---------------------------------------------------------------------------
def test_pixels_encoder_scores_minus_mean_absolute_difference(random_images):
    reference = random_images(6)
    query = random_images(4)  # non-square score matrix
    encoder = PixelsEncoder().fit(reference)
    S = encoder.score(query)
    assert S.shape == (4, 6)
    assert S.dtype == np.float32
    q = patch_normalize(query).reshape(4, -1)
    r = patch_normalize(reference).reshape(6, -1)
    expected = -np.abs(q[:, None, :] - r[None, :, :]).mean(axis=2)
    np.testing.assert_allclose(S, expected, rtol=1e-5, atol=1e-6)


def test_pixels_encoder_finds_the_same_place_under_lighting_change(random_images):
    reference = random_images(8) * 0.5
    query = 0.1 + 1.6 * reference[::-1]  # brighter, more contrast, reversed order
    S = PixelsEncoder().fit(reference).score(query)
    np.testing.assert_array_equal(S.argmax(axis=1), np.arange(8)[::-1])
    np.testing.assert_allclose(S.max(axis=1), 0.0, atol=1e-4)


def test_pixels_encoder_encode_and_attributes(random_images):
    encoder = PixelsEncoder(patch_size=4).fit(random_images(3))
    assert encoder.reference_codes_.shape == (3, 2048)
    assert encoder.encode(random_images(2)).shape == (2, 2048)
    assert encoder.encode(random_images(2)).dtype == np.float32
    assert encoder.n_reference_ == 3
    assert encoder.image_shape_ == (32, 64)
    assert encoder.train_accuracy_ is None
    assert encoder.footprint() == {"layers": 0, "params": 0, "neurons": 0}
    assert encoder.get_params() == {"patch_size": 4}
    assert repr(encoder) == "PixelsEncoder(patch_size=4)"
    assert PixelsEncoder.name == "pixels"


def test_pixels_encoder_not_fitted(random_images):
    encoder = PixelsEncoder()
    with pytest.raises(NotFittedError, match="fit"):
        encoder.score(random_images(1))
    with pytest.raises(NotFittedError, match="fit"):
        encoder.encode(random_images(1))
    with pytest.raises(NotFittedError, match="fit"):
        encoder.footprint()


def test_pixels_encoder_errors(random_images):
    with pytest.raises(ValueError, match="patch_size"):
        PixelsEncoder(patch_size=5).fit(random_images(2))
    encoder = PixelsEncoder().fit(random_images(2))
    with pytest.raises(ValueError, match="image size"):
        encoder.score(random_images(1, 16, 64))
    with pytest.raises(ValueError, match="2048 features"):
        encoder.score_codes(np.zeros((1, 100)))


def test_jit_refuses_a_parallel_kernel_with_reassociation():
    # its disk-cached code may sum in another order than the code compiled in the process
    pytest.importorskip("numba")
    from flyvpr._numba import jit

    with pytest.raises(ValueError, match=r"parallel=True with fastmath=True"):
        jit(lambda x: x, parallel=True, fastmath=True)
    assert jit(lambda x: x + 1, fastmath=True)(1) == 2
