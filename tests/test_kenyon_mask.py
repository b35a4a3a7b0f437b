"""Static pixels in the ``kenyon`` front end: found at fit time, left out of the codes."""

import json

import numpy as np
import pytest
from scipy.signal import convolve2d

from flyvpr.frontends import _kenyon_kernels as kk
from flyvpr.frontends.kenyon import KenyonEncoder, balanced_connections
from flyvpr.frontends.optic_lobe import (
    OpticLobe,
    _pixel_std,
    local_contrast_normalize,
    optic_lobe,
    pool_for_mask,
    varying_pixels,
)
from flyvpr.methods import make_method
from flyvpr.modelio import ModelFileError, _write_archive, load_method, save_method


def _disc():
    """The fisheye's image circle in a 32x64 frame (848 pixels)."""
    y, x = np.mgrid[0:32, 0:64]
    return ((y - 15.5) / 16) ** 2 + ((x - 31.5) / 16.8) ** 2 <= 1


def _with_border(images, valid, value):
    return np.where(valid, images, np.float32(value)).astype(np.float32)


@pytest.fixture(scope="module")
def route(sliding_world):
    return sliding_world


# -- varying_pixels ---------------------------------------------------------------
def test_varying_pixels_marks_a_constant_border():
    x = np.random.default_rng(1).random((30, 8, 12), dtype=np.float32)
    x[:, :2] = 0.05
    x[:, :, -3:] = np.linspace(0.2, 0.9, 8, dtype=np.float32)[:, None]  # constant in time
    expected = np.zeros((8, 12), bool)
    expected[2:, :-3] = True
    got = varying_pixels(x)
    assert got.dtype == np.bool_
    np.testing.assert_array_equal(got, expected)


def test_varying_pixels_threshold_is_exactly_five_percent_of_the_90th_percentile():
    # two frames: every pixel's standard deviation is exact.  18 pixels spread by 5/32, so
    # the 90th percentile is 5/32 and the threshold 5% of it, 1/128
    half = np.full(20, 5 / 32)
    half[0] = 1 / 128  # exactly at the threshold: static
    half[1] = 1 / 128 + 1 / 1024  # just above: varying
    x = np.stack([0.5 - half, 0.5 + half])[:, None, :].astype(np.float32)
    np.testing.assert_array_equal(_pixel_std(x)[0], half)
    expected = np.ones((1, 20), bool)
    expected[0, 0] = False
    np.testing.assert_array_equal(varying_pixels(x), expected)


def test_varying_pixels_against_numpy_std_and_percentile():
    # spreads log-uniform over three decades: pixels on both sides of, and close to, the
    # threshold; 600 frames run over the blocks of 256 frames
    rng = np.random.default_rng(2)
    scale = 10 ** rng.uniform(-3.4, -0.4, (32, 64))
    x = (0.5 + scale * rng.uniform(-1, 1, (600, 32, 64))).astype(np.float32)
    sd = x.astype(np.float64).std(axis=0)
    np.testing.assert_allclose(_pixel_std(x), sd, rtol=1e-12, atol=0)
    got = varying_pixels(x)
    np.testing.assert_array_equal(got, sd > 0.05 * np.percentile(sd, 90))
    assert 100 < (~got).sum() < 1000
    for share, q in ((0.04, 90), (0.06, 90), (0.05, 85), (0.05, 95)):  # the test has teeth
        assert not np.array_equal(got, sd > share * np.percentile(sd, q))


def test_varying_pixels_when_nothing_or_little_varies():
    flat = varying_pixels(np.full((3, 4, 8), 0.2))  # nothing to tell apart
    assert flat.dtype == np.bool_ and flat.shape == (4, 8) and flat.all()
    assert varying_pixels(np.random.default_rng(0).random((1, 4, 8))).all()  # one frame
    # 2 of 32 pixels vary: the 90th percentile is 0, and only the constant ones are static
    x = np.full((5, 4, 8), 0.3)
    x[:, 1, 2] = x[:, 3, 7] = np.linspace(0, 1, 5)
    expected = np.zeros((4, 8), bool)
    expected[1, 2] = expected[3, 7] = True
    np.testing.assert_array_equal(varying_pixels(x), expected)


def test_varying_pixels_bad_input():
    with pytest.raises(ValueError, match="images"):
        varying_pixels(np.zeros((4, 8)))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        varying_pixels(np.full((2, 4, 8), 2.0))


# -- the optic lobe under a mask -----------------------------------------------------
def _kept_by_loop(valid, n_orientations, size, pool):
    """Features whose cell has a valid pixel within ``size // 2`` rows and columns."""
    h, w = valid.shape
    r = size // 2
    kept = [
        valid[max(0, a - r) : a + pool + r, max(0, b - r) : b + pool + r].any()
        for a in range(0, h, pool)
        for b in range(0, w, pool)
    ]
    return np.flatnonzero(np.tile(kept, n_orientations))


@pytest.mark.parametrize(("n_orientations", "size", "pool"), [(4, 11, 4), (2, 3, 2), (3, 7, 4)])
def test_kept_features_are_those_within_reach_of_a_valid_pixel(n_orientations, size, pool):
    lobe = OpticLobe(4.0, 0.05, n_orientations, 6.0, size, pool)
    rng = np.random.default_rng(size)
    masks = [_disc(), rng.random((32, 64)) < 0.01, np.zeros((32, 64), bool)]
    masks[2][20, 40] = True
    for valid in masks:
        kept = lobe.kept_features(valid)
        assert kept.dtype == np.uint32
        np.testing.assert_array_equal(kept, _kept_by_loop(valid, n_orientations, size, pool))


def test_dropped_features_are_zero_in_every_image_and_kept_ones_vary():
    # the Gabor energies by direct convolution (exact sums of zeros) of the masked LCN
    x = np.random.default_rng(6).random((3, 32, 64), dtype=np.float32)
    lobe = OpticLobe(4.0, 0.05, 4, 6.0, 11, 4)
    disc = _disc()
    lcn = local_contrast_normalize(x, valid_pixels=disc).astype(np.float64)
    energy = np.abs([[convolve2d(img, kernel, mode="same") for kernel in lobe.bank] for img in lcn])
    pooled = energy.reshape(3, 4, 8, 4, 16, 4).max(axis=(3, 5)).reshape(3, -1)
    kept = lobe.kept_features(disc)
    assert np.all(np.delete(pooled, kept, axis=1) == 0)
    assert pooled[:, kept].min() > 1e-4 and np.all(pooled[0, kept] != pooled[1, kept])


def test_kept_features_at_the_edge_of_reach():
    # 16 x 16, cells of 4, kernels of 11 (reach 5): one valid pixel at row 9, column 10
    valid = np.zeros((16, 16), bool)
    valid[9, 10] = True
    lobe = OpticLobe(4.0, 0.05, 2, 6.0, 11, 4)
    # rows 4-15 and columns 5-15 are in reach: cell rows 1-3, cell columns 1-3; (orientation,
    # row, column) order
    cells = [4 * a + b for a in (1, 2, 3) for b in (1, 2, 3)]
    np.testing.assert_array_equal(lobe.kept_features(valid), cells + [16 + c for c in cells])
    assert len(OpticLobe(4.0, 0.05, 4, 6.0, 11, 4).kept_features(_disc())) == 368
    with pytest.raises(ValueError, match="pool_size must divide"):
        lobe.kept_features(np.ones((6, 8), bool))


def test_masked_lcn_ignores_the_invalid_pixels():
    x = np.random.default_rng(3).random((2, 32, 64), dtype=np.float32)
    disc = _disc()
    got = local_contrast_normalize(x, valid_pixels=disc)
    assert got.dtype == np.float32 and got.shape == x.shape
    assert np.all(got[:, ~disc] == 0) and np.all(got[:, disc] != 0)
    again = local_contrast_normalize(_with_border(x, disc, 0.9), valid_pixels=disc)
    np.testing.assert_array_equal(again, got)
    # unlike the unmasked normalisation, which sees the border
    plain = local_contrast_normalize(_with_border(x, disc, 0.9))
    assert np.abs(plain - local_contrast_normalize(x))[:, disc].max() > 0.5
    # an all-valid mask is no mask, bit for bit
    everything = local_contrast_normalize(x, valid_pixels=np.ones((32, 64), bool))
    np.testing.assert_array_equal(everything, local_contrast_normalize(x))


def test_masked_lcn_of_a_flat_region_is_zero():
    x = np.full((1, 16, 16), 0.4, np.float32)
    valid = np.zeros((16, 16), bool)
    valid[4:12, 4:12] = True
    x[0, ~valid] = 0.9  # a bright surround that the mask hides
    assert np.abs(local_contrast_normalize(x, valid_pixels=valid)).max() < 1e-5
    assert np.abs(local_contrast_normalize(x)).max() > 1


@pytest.mark.parametrize("fn", [local_contrast_normalize, optic_lobe, varying_pixels])
def test_bad_images(fn):
    with pytest.raises(
        ValueError, match=r"^images must have shape \(N, H, W\); got shape \(4, 8\)"
    ):
        fn(np.zeros((4, 8)))


@pytest.mark.parametrize(
    ("params", "error", "match"),
    [
        ({"sigma": -1.0}, ValueError, r"^sigma must be in \[0\.25, 1000000\.0\] pixels; got -1\.0"),
        (
            {"sigma": 1e308},
            ValueError,
            r"^sigma must be in \[0\.25, 1000000\.0\] pixels; got 1e\+308",
        ),
        ({"eps": 0.0}, ValueError, r"^eps must be in \[1e-08, 1\.0\]; got 0\.0"),
        ({"eps": 1e-30}, ValueError, r"^eps must be in \[1e-08, 1\.0\]; got 1e-30"),
        ({"sigma": "4"}, TypeError, "^sigma must be a number of pixels; got str"),
    ],
)
def test_lcn_bad_parameters(params, error, match):
    x = np.zeros((1, 8, 8), np.float32)
    with pytest.raises(error, match=match):
        local_contrast_normalize(x, **params)
    with pytest.raises(error, match=match):
        local_contrast_normalize(x, valid_pixels=np.ones((8, 8), bool), **params)


def test_lcn_defaults_are_sigma_4_and_eps_005():
    x = np.random.default_rng(7).random((2, 32, 64), dtype=np.float32)
    disc = _disc()
    np.testing.assert_array_equal(
        local_contrast_normalize(x, valid_pixels=disc),
        local_contrast_normalize(x, 4.0, 0.05, valid_pixels=disc),
    )
    np.testing.assert_array_equal(
        local_contrast_normalize(x), local_contrast_normalize(x, 4.0, 0.05)
    )


@pytest.mark.parametrize("fn", [local_contrast_normalize, optic_lobe])
def test_bad_masks(fn):
    x = np.random.default_rng(4).random((2, 32, 64), dtype=np.float32)
    with pytest.raises(TypeError, match="valid_pixels must be a bool array; got dtype uint8"):
        fn(x, valid_pixels=np.ones((32, 64), np.uint8))
    with pytest.raises(ValueError, match=r"image size \(32, 64\); got shape \(64, 32\)"):
        fn(x, valid_pixels=np.ones((64, 32), bool))


def test_masked_optic_lobe():
    x = np.random.default_rng(5).random((3, 32, 64), dtype=np.float32)
    disc = _disc()
    f = optic_lobe(x, valid_pixels=disc)
    assert f.shape == (3, 368) and f.dtype == np.float32
    np.testing.assert_allclose(f.mean(axis=1), 0, atol=1e-5)
    np.testing.assert_allclose(f.std(axis=1), 1, atol=1e-4)
    np.testing.assert_array_equal(optic_lobe(_with_border(x, disc, 0.7), valid_pixels=disc), f)
    np.testing.assert_array_equal(
        optic_lobe(x, valid_pixels=np.ones((32, 64), bool)), optic_lobe(x)
    )
    few = np.zeros((32, 64), bool)
    with pytest.raises(
        ValueError, match="^valid_pixels must mark at least one valid pixel; got none$"
    ):
        optic_lobe(x, valid_pixels=few)
    few[0, 0] = True  # in reach of the cells of rows and columns 0-5: 2 x 2 cells
    assert optic_lobe(x, valid_pixels=few).shape == (3, 16)
    # the lobe keeps the last mask's set-up, and takes a new mask when it changes
    lobe = OpticLobe(4.0, 0.05, 4, 6.0, 11, 4)
    np.testing.assert_array_equal(lobe(x, disc), f)
    assert lobe(x, few).shape == (3, 16)
    np.testing.assert_array_equal(lobe(x, disc), f)


# -- the pooling under a mask ----------------------------------------------------------
def _columns(n):
    """A 32x64 mask with its first ``n`` columns valid (a share of n / 64)."""
    valid = np.zeros((32, 64), bool)
    valid[:, :n] = True
    return valid


@pytest.mark.parametrize(
    ("valid", "pool", "expected"),
    [
        (np.ones((32, 64), bool), 4, 4),  # every pixel valid: the setting itself
        (_disc(), 4, 2),  # 41%: 4 * sqrt(0.41) = 2.6, nearer 2 than 4 in ratio
        (_columns(40), 4, 4),  # 62.5%: 3.2, nearer 4
        (_columns(32), 4, 4),  # exactly half: 2 * sqrt(2), as far from 2 as from 4: the larger
        (_columns(31), 4, 2),  # just under half
        (_columns(9), 4, 2),  # 14%: 1.5, nearer 2 than 1 in ratio (2 / 1.5 < 1.5 / 1)
        (_columns(7), 4, 1),  # 11%: 1.32, nearer 1
        (_columns(16), 6, 3),  # 25%: exactly 3, a divisor of 6 that is not a power of two
        (_columns(8), 6, 2),  # 12.5%: 2.12, nearer 2 than 3
        (_columns(1), 1, 1),
        (_columns(64), 8, 8),
        # exact ties, decided in integers: the larger side (in floating point these three
        # fell either way)
        (_columns(32), 14, 14),  # 14 / sqrt(2): 7 * sqrt(2), as far from 7 as from 14
        (_columns(8), 28, 14),  # 28 / sqrt(8) = 7 * sqrt(2), between 7 and 14
        (_columns(8), 4, 2),  # an eighth: sqrt(2), between 1 and 2
    ],
)
def test_pool_for_mask_keeps_about_a_whole_frames_cells(valid, pool, expected):
    got = pool_for_mask(valid, pool)
    assert type(got) is int and got == expected and pool % got == 0


def test_pool_for_mask_against_exact_fractions():
    # every share k / 256 and side 1-32: the divisor nearest in ratio, ties to the larger
    from fractions import Fraction

    mask = np.zeros((16, 16), bool)
    for k in range(1, 257):
        mask.flat[k - 1] = True
        for pool in range(1, 33):
            sides = [d for d in range(pool, 0, -1) if pool % d == 0]

            def far(d, k=k, pool=pool):
                a, b = d * d * 256, pool * pool * k
                return Fraction(max(a, b), min(a, b))

            assert pool_for_mask(mask, pool) == min(sides, key=lambda d: (far(d), -d))


def test_pool_for_mask_bad_input():
    with pytest.raises(ValueError, match="at least one valid pixel"):
        pool_for_mask(np.zeros((4, 8), bool), 4)
    with pytest.raises(ValueError, match="at least one valid pixel"):
        pool_for_mask(np.zeros((0, 8), bool), 4)
    with pytest.raises(ValueError, match=r"2-d \(H, W\); got shape \(8,\)"):
        pool_for_mask(np.ones(8, bool), 4)
    with pytest.raises(TypeError, match="bool array; got dtype float64"):
        pool_for_mask(np.full((4, 8), 0.5), 4)
    with pytest.raises(ValueError, match="pool_size must be >= 1; got 0"):
        pool_for_mask(_disc(), 0)
    with pytest.raises(TypeError, match="pool_size"):
        pool_for_mask(_disc(), 2.0)


# -- the encoder -------------------------------------------------------------------
def test_ordinary_frames_give_the_unmasked_codes_bit_for_bit(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    assert enc.valid_pixels_.dtype == np.bool_ and enc.valid_pixels_.shape == (32, 64)
    assert enc.valid_pixels_.all() and enc.n_features_ == 512
    # the pipeline without any mask: optic lobe, centring on the reference mean, Kenyon cells
    features = optic_lobe(ref)
    connections = balanced_connections(4096, 512, 10, random_state=0)
    np.testing.assert_array_equal(enc.connections_, connections)
    mean = features.mean(axis=0)
    np.testing.assert_array_equal(enc.feature_mean_, mean)

    def codes(x):
        out = np.empty((len(x), 512), np.uint8)
        return kk.kenyon_codes(x, mean, connections.astype(np.uint32), 1, 205, out)

    np.testing.assert_array_equal(enc.reference_codes_, codes(features))
    np.testing.assert_array_equal(enc.encode(qry), codes(optic_lobe(qry)))
    assert enc._optic_lobe._mask == (None, None)  # the masked computation never ran


def test_fisheye_border_is_learned_and_its_value_does_not_matter(route):
    ref, qry = route
    disc = _disc()
    enc = KenyonEncoder(random_state=0).fit(_with_border(ref, disc, 0.05))
    np.testing.assert_array_equal(enc.valid_pixels_, disc)
    # 41% of the pixels vary: 2x2 cells, 1376 of the 2048 features see one
    assert enc.pool_ == 2 and enc._optic_lobe.pool == 2
    assert enc.n_features_ == 1376 and enc.feature_mean_.shape == (1376,)
    assert enc.connections_.max() == 1375
    assert enc.footprint()["neurons"] == 1376 + 4096
    other = KenyonEncoder(random_state=0).fit(_with_border(ref, disc, 0.8))
    assert other.pool_ == 2
    for name in ("valid_pixels_", "connections_", "feature_mean_", "reference_codes_"):
        np.testing.assert_array_equal(getattr(other, name), getattr(enc, name))
    codes = enc.encode(_with_border(qry, disc, 0.05))
    np.testing.assert_array_equal(enc.encode(_with_border(qry, disc, 0.3)), codes)
    np.testing.assert_array_equal(enc.encode(qry), codes)  # the scene outside never enters
    np.testing.assert_array_equal(np.unpackbits(codes, axis=1).sum(axis=1), 205)
    y = enc.kenyon_activity(_with_border(qry, disc, 0.3))
    for row, bits in zip(y, np.unpackbits(codes, axis=1).astype(bool), strict=True):
        assert row[bits].min() >= row[~bits].max()
    # unmasked, the border's value changes every code
    plain = KenyonEncoder(random_state=0).fit(ref)
    a = plain.encode(_with_border(qry, disc, 0.05))
    b = plain.encode(_with_border(qry, disc, 0.3))
    assert np.all(np.unpackbits(a ^ b, axis=1).sum(axis=1) > 20)


def test_fisheye_places_are_recognised(route):
    ref, qry = route
    disc = _disc()
    S = KenyonEncoder(random_state=0).fit(_with_border(ref, disc, 0.05))
    S = S.score(_with_border(qry, disc, 0.05))
    assert np.mean(S.argmax(axis=1) == np.arange(40)) >= 0.9


def test_a_static_chassis_is_dropped(route):
    ref, qry = route
    chassis = np.ones((32, 64), bool)
    chassis[20:, 10:54] = False  # the robot's bonnet, 12 rows high
    # no varying pixel within 5 pixels of the bottom row of cells (rows 28-31) in columns
    # 16-47 (cells 4-11): 8 cells per orientation are 0 in every image
    enc = KenyonEncoder(random_state=0).fit(_with_border(ref, chassis, 0.2))
    np.testing.assert_array_equal(enc.valid_pixels_, chassis)
    assert enc.n_features_ == 4 * (128 - 8)
    np.testing.assert_array_equal(
        enc.encode(_with_border(qry, chassis, 0.6)), enc.encode(_with_border(qry, chassis, 0.2))
    )


def test_too_few_varying_features(route):
    ref, _ = route
    window = np.zeros((32, 64), bool)
    window[13:15, 29:31] = True  # 2 x 2 pixels, in reach of 3 x 3 cells: 36 features
    frames = _with_border(ref, window, 0.5)
    at4 = {"random_state": 0, "mask_pooling": False}
    assert KenyonEncoder(**at4).fit(frames).n_features_ == 36
    KenyonEncoder(n_inputs=36, **at4).fit(frames)
    with pytest.raises(ValueError, match=r"features \(36 of 512 see pixels that vary.*got 37"):
        KenyonEncoder(n_inputs=37, **at4).fit(frames)
    # with the pooling under a mask, 4 of 2048 pixels vary: 1x1 cells, 9 x 9 x 4 features
    enc = KenyonEncoder(random_state=0).fit(frames)
    assert enc.pool_ == 1 and enc.n_features_ == 576


def test_model_file_keeps_cells_of_one_pixel(route, tmp_path):
    ref, qry = route
    window = np.zeros((32, 64), bool)
    window[13:15, 29:31] = True  # 4 of 2048 pixels vary: 1x1 cells
    model = make_method("kenyon", 0).fit(_with_border(ref, window, 0.5))
    again = load_method(save_method(model, tmp_path / "k.npz"))
    assert again.frontend.pool_ == 1 and again.frontend.n_features_ == 576
    frames = _with_border(qry, window, 0.5)
    np.testing.assert_array_equal(again.score(frames), model.score(frames))


def test_memory_checks_ask_for_what_fit_and_the_lobe_need(route, monkeypatch):
    from flyvpr.frontends import kenyon as kenyon_module
    from flyvpr.frontends import optic_lobe as lobe_module

    calls = []
    monkeypatch.setattr(kenyon_module, "check_memory", lambda n, what: calls.append((n, what)))
    monkeypatch.setattr(lobe_module, "check_memory", lambda n, what: calls.append((n, what)))
    disc = _disc()
    ref = _with_border(np.concatenate([route[0], route[1]])[:65], disc, 0.05)
    enc = KenyonEncoder(n_kenyon=1024, n_inputs=6, random_state=0).fit(ref)
    # the Gabor kernels (complex128) and two temporaries of their size
    kernels = (48 * 4 * 11 * 11, "n_orientations=4 with kernel_size=11")

    def lobe(pool):
        return [
            kernels,
            # once per image size: the compiled filter's float32 buffers (2 per orientation
            # and 5 more, of the frame widened by the kernels' radius, 5) and one frame's
            # features twice
            (
                4 * (2 * 4 + 5) * (32 + 10) * (64 + 10) + 8 * 4 * (32 // pool) * (64 // pool),
                "n_orientations=4 with kernel_size=11 on images of 32x64",
            ),
            # the LCN's taps and border indices (radius 16), padded lines (float64) and images
            (
                64 * (32 + 32 + 64) + 8 * (32 + 32) * 64 + 20 * 32 * 64,
                "lcn_sigma=4 on images of 32x64",
            ),
        ]

    fit = [
        (1024 * 6 * 16 + 65 * 1024 * 9, "n_kenyon=1024 with n_inputs=6"),
        kernels,  # the lobe of the settings (4x4 cells), then the one of the mask (2x2)
        *lobe(2),
        (65 * 1376 * 4, "optic_lobe on 65 images of 32x64"),  # the features kept
        (32 * 1024 * 6 + 16 * 1376, "n_kenyon=1024 with n_inputs=6"),  # drawing the connections
    ]
    assert calls == fit
    calls.clear()
    KenyonEncoder(n_kenyon=1024, n_inputs=6, random_state=0, mask_pooling=False).fit(ref)
    assert calls == [
        fit[0],
        *lobe(4),
        (65 * 368 * 4, "optic_lobe on 65 images of 32x64"),
        (32 * 1024 * 6 + 16 * 368, "n_kenyon=1024 with n_inputs=6"),
    ]
    calls.clear()
    enc.encode(ref[:64])  # up to 64 images, a lobe set up for the size: no check
    assert calls == []
    optic_lobe(ref)
    assert calls == [*lobe(4), (65 * 512 * 4, "optic_lobe on 65 images of 32x64")]


# -- model files -----------------------------------------------------------------
def _rewrite(path, out, edit):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    edit(meta["frontend"]["state"], arrays)
    return _write_archive(out, meta, arrays)


def _drop_mask(state, arrays):
    del state["valid_pixels_"], arrays["frontend/valid_pixels_"]


def test_model_file_keeps_the_mask(route, tmp_path):
    ref, qry = route
    disc = _disc()
    model = make_method("kenyon+cann", 0).fit(_with_border(ref, disc, 0.05))
    again = load_method(save_method(model, tmp_path / "k.npz"))
    front = again.frontend
    assert front.valid_pixels_.dtype == np.bool_
    np.testing.assert_array_equal(front.valid_pixels_, disc)
    assert front.n_features_ == 1376 and front.pool_ == 2 and front._optic_lobe.pool == 2
    frames = _with_border(qry, disc, 0.3)
    np.testing.assert_array_equal(again.score(frames), model.score(frames))


def test_model_file_from_before_the_mask_loads_with_every_pixel_valid(route, tmp_path):
    ref, qry = route
    model = make_method("kenyon", 0).fit(ref)
    old = _rewrite(save_method(model, tmp_path / "k.npz"), tmp_path / "old.npz", _drop_mask)
    again = load_method(old)
    valid = again.frontend.valid_pixels_
    assert valid.dtype == np.bool_ and valid.shape == (32, 64) and valid.all()
    np.testing.assert_array_equal(again.score(qry), model.score(qry))


def test_mask_pooling_off_pools_at_pool_size(route):
    ref, qry = route
    disc = _disc()
    frames = _with_border(ref, disc, 0.05)
    at4 = KenyonEncoder(random_state=0, mask_pooling=False).fit(frames)
    assert at4.pool_ == 4 and at4.n_features_ == 368
    # the same lobe as an encoder whose pooling is 2 by its setting: the same codes
    at2 = KenyonEncoder(random_state=0, pool_size=2, mask_pooling=False).fit(frames)
    auto = KenyonEncoder(random_state=0).fit(frames)
    assert at2.pool_ == auto.pool_ == 2
    np.testing.assert_array_equal(auto.reference_codes_, at2.reference_codes_)
    q = _with_border(qry, disc, 0.05)
    np.testing.assert_array_equal(auto.encode(q), at2.encode(q))
    assert (auto.encode(q) != at4.encode(q)).any()
    with pytest.raises(TypeError, match="mask_pooling must be True or False; got int"):
        KenyonEncoder(mask_pooling=1).fit(frames)


def test_model_file_from_before_the_mask_pooling_loads_at_pool_size(route, tmp_path):
    ref, qry = route
    disc = _disc()
    model = make_method("kenyon", 0, {"mask_pooling": False}).fit(_with_border(ref, disc, 0.05))
    path = save_method(model, tmp_path / "k.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    del meta["frontend"]["params"]["mask_pooling"], meta["frontend"]["state"]["pool_"]
    again = load_method(_write_archive(tmp_path / "old.npz", meta, arrays))
    front = again.frontend
    assert front.pool_ == 4 and front.mask_pooling is False and front.n_features_ == 368
    frames = _with_border(qry, disc, 0.3)
    np.testing.assert_array_equal(again.score(frames), model.score(frames))
    # and a file of today keeps its pooling
    auto = load_method(save_method(make_method("kenyon", 0).fit(_with_border(ref, disc, 0.05)),
                                   tmp_path / "new.npz"))  # fmt: skip
    assert auto.frontend.pool_ == 2 and auto.frontend.mask_pooling is True


def test_model_file_with_a_pooling_that_does_not_fit_is_refused(route, tmp_path):
    ref, _ = route
    path = save_method(
        make_method("kenyon", 0).fit(_with_border(ref, _disc(), 0.05)), tmp_path / "k.npz"
    )

    def pool(value):
        def edit(state, arrays):
            state["pool_"] = {"value": value}

        return edit

    with pytest.raises(ModelFileError, match="pool_ must divide pool_size = 4; got 3"):
        load_method(_rewrite(path, tmp_path / "a.npz", pool(3)))
    with pytest.raises(ModelFileError, match="n_features_ must be 368 .* 848 valid pixels"):
        load_method(_rewrite(path, tmp_path / "b.npz", pool(4)))
    with pytest.raises(ModelFileError, match="pool_"):
        load_method(_rewrite(path, tmp_path / "c.npz", pool(0)))


def test_model_file_with_a_mask_that_does_not_fit_is_refused(route, tmp_path):
    ref, _ = route
    model = make_method("kenyon", 0).fit(_with_border(ref, _disc(), 0.05))
    path = save_method(model, tmp_path / "k.npz")
    out = _rewrite(path, tmp_path / "a.npz", _drop_mask)
    # (the file's 2x2 cells: 2048 features of a whole frame)
    with pytest.raises(ModelFileError, match="n_features_ must be 2048 .* 2048 valid pixels"):
        load_method(out)

    def widen(state, arrays):  # 256 more valid pixels, every cell in reach
        arrays["frontend/valid_pixels_"][:, :8] = arrays["frontend/valid_pixels_"][:, -8:] = True

    with pytest.raises(ModelFileError, match="n_features_ must be 2048 .* 1360 valid pixels"):
        load_method(_rewrite(path, tmp_path / "b.npz", widen))

    def crop(state, arrays):
        arrays["frontend/valid_pixels_"] = arrays["frontend/valid_pixels_"][:16]

    with pytest.raises(ModelFileError, match=r"frontend\.state\.valid_pixels_: .*\(32, 64\)"):
        load_method(_rewrite(path, tmp_path / "d.npz", crop))

    def as_bytes(state, arrays):
        arrays["frontend/valid_pixels_"] = arrays["frontend/valid_pixels_"].astype(np.uint8)

    with pytest.raises(ModelFileError, match="valid_pixels_"):
        load_method(_rewrite(path, tmp_path / "c.npz", as_bytes))
