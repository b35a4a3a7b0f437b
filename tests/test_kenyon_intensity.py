"""The ``kenyon`` front end's intensity channel (``KenyonEncoder(intensity=True)``)."""

import json

import numpy as np
import pytest

from flyvpr.frontends import _kenyon_kernels as kk
from flyvpr.frontends.kenyon import KenyonEncoder, balanced_connections
from flyvpr.frontends.optic_lobe import local_contrast_normalize, optic_lobe
from flyvpr.large import CompactEncoder
from flyvpr.methods import make_method
from flyvpr.modelio import ModelFileError, _write_archive, load_method, save_method


def _disc():
    y, x = np.mgrid[0:32, 0:64]
    return ((y - 15.5) / 16) ** 2 + ((x - 31.5) / 16.8) ** 2 <= 1


def _with_border(images, valid, value):
    return np.where(valid, images, np.float32(value)).astype(np.float32)


def _channel(images, sigma, eps, pool, valid=None):
    """The intensity channel in plain numpy: LCN, sums over the cells, z-score per image."""
    x = local_contrast_normalize(images, sigma, eps, valid_pixels=valid).astype(np.float64)
    n, h, w = x.shape
    cells = x.reshape(n, h // pool, pool, w // pool, pool).sum(axis=(2, 4)).reshape(n, -1)
    if valid is not None:
        cells = cells[:, valid.reshape(h // pool, pool, w // pool, pool).any(axis=(1, 3)).ravel()]
    mean = cells.mean(axis=1, keepdims=True)
    sd = cells.std(axis=1, keepdims=True)
    return (cells - mean) / sd


@pytest.fixture(scope="module")
def route(sliding_world):
    return sliding_world


def test_off_by_default():
    assert KenyonEncoder().intensity is False
    assert make_method("kenyon").frontend.intensity is False


def test_channel_follows_the_gabor_features_and_feeds_the_kenyon_cells(route):
    ref, qry = route
    settings = {"lcn_sigma": 2.0, "lcn_eps": 0.1, "pool_size": 8}
    enc = KenyonEncoder(random_state=0, intensity=True, **settings).fit(ref)
    n_gabor = 4 * 4 * 8
    assert enc.n_features_ == n_gabor + 4 * 8
    assert enc.footprint()["neurons"] == n_gabor + 32 + 4096
    features = enc._lobe(qry)
    np.testing.assert_array_equal(features[:, :n_gabor], optic_lobe(qry, **settings))
    np.testing.assert_allclose(features[:, n_gabor:], _channel(qry, 2.0, 0.1, 8), atol=2e-6)
    assert features.dtype == np.float32
    # the Kenyon cells read both: connections over all features, centred on the map's mean
    ref_features = enc._lobe(ref)
    connections = balanced_connections(4096, n_gabor + 32, 10, random_state=0)
    np.testing.assert_array_equal(enc.connections_, connections)
    mean = ref_features.mean(axis=0)
    np.testing.assert_array_equal(enc.feature_mean_, mean)
    out = np.empty((len(qry), 512), np.uint8)
    codes = kk.kenyon_codes(features, mean, connections.astype(np.uint32), 1, 205, out)
    np.testing.assert_array_equal(enc.encode(qry), codes)
    # and the channel changes the codes
    plain = KenyonEncoder(random_state=0, **settings).fit(ref)
    assert plain.n_features_ == n_gabor
    assert (plain.encode(qry) != codes).any()


def test_channel_under_a_mask_sees_the_valid_pixels_only(route):
    ref, qry = route
    disc = _disc()
    enc = KenyonEncoder(random_state=0, intensity=True).fit(_with_border(ref, disc, 0.05))
    # 41% of the pixels vary: the cells are 2x2 (the pooling under a mask), for both channels
    assert enc.pool_ == 2
    cells = disc.reshape(16, 2, 32, 2).any(axis=(1, 3))
    assert cells.sum() == 228
    assert enc.n_features_ == 1376 + 228
    frames = _with_border(qry, disc, 0.3)
    features = enc._lobe(frames)
    np.testing.assert_allclose(
        features[:, 1376:], _channel(frames, 4.0, 0.05, 2, valid=disc), atol=2e-6
    )
    at4 = KenyonEncoder(random_state=0, intensity=True, mask_pooling=False)
    at4.fit(_with_border(ref, disc, 0.05))
    assert at4.pool_ == 4 and disc.reshape(8, 4, 16, 4).any(axis=(1, 3)).sum() == 64
    assert at4.n_features_ == 368 + 64
    np.testing.assert_allclose(
        at4._lobe(frames)[:, 368:], _channel(frames, 4.0, 0.05, 4, valid=disc), atol=2e-6
    )
    # a cell at the disc's edge weighs by the share of it that the disc covers: its sum, not
    # its mean, is z-scored (the mean over its valid pixels would differ)
    np.testing.assert_array_equal(enc.encode(frames), enc.encode(_with_border(qry, disc, 0.05)))
    np.testing.assert_array_equal(enc.encode(frames), enc.encode(qry))
    # ordinary frames: every cell, no mask
    full = KenyonEncoder(random_state=0, intensity=True).fit(ref)
    assert full.n_features_ == 512 + 128
    np.testing.assert_allclose(full._lobe(qry)[:, 512:], _channel(qry, 4.0, 0.05, 4), atol=2e-6)


def test_blank_image_gives_a_zero_channel(route):
    ref, _ = route
    enc = KenyonEncoder(random_state=0, intensity=True).fit(ref)
    blank = np.full((2, 32, 64), 0.4, np.float32)
    channel = enc._lobe(blank)[:, 512:]
    assert np.isfinite(channel).all() and not channel.any()
    masked = KenyonEncoder(random_state=0, intensity=True).fit(_with_border(ref, _disc(), 0.05))
    # under a mask the normalised convolution leaves float32 rounding (below 1e-6), which the
    # z-score scales up, as it does the Gabor energies': finite, and the same for both frames
    channel = masked._lobe(blank)[:, 1376:]
    assert channel.shape == (2, 228) and np.isfinite(channel).all()
    np.testing.assert_array_equal(channel[0], channel[1])


def test_places_are_recognised_with_the_channel(route):
    ref, qry = route
    for valid in (None, _disc()):
        r = ref if valid is None else _with_border(ref, valid, 0.05)
        q = qry if valid is None else _with_border(qry, valid, 0.05)
        S = KenyonEncoder(random_state=0, intensity=True).fit(r).score(q)
        assert np.mean(S.argmax(axis=1) == np.arange(40)) >= 0.9


def test_low_contrast_frames_are_z_scored_too(route):
    # below the contrast floor (lcn_eps) the normalised image is faint: the cells' spread is
    # well below 1, and the channel is still scaled to unit spread
    ref, _ = route
    enc = KenyonEncoder(random_state=0, intensity=True).fit(ref)
    faint = (0.4 + 0.004 * ref[:3]).astype(np.float32)
    raw = _channel(faint, 4.0, 0.05, 4) * 1.0
    channel = enc._lobe(faint)[:, 512:]
    np.testing.assert_allclose(channel, raw, atol=2e-5)
    np.testing.assert_allclose(channel.std(axis=1), 1.0, rtol=1e-5)
    x = local_contrast_normalize(faint).astype(np.float64)
    assert x.reshape(3, 8, 4, 16, 4).sum(axis=(2, 4)).reshape(3, -1).std(axis=1).max() < 0.5


def test_too_many_inputs_names_both_feature_kinds(route):
    with pytest.raises(
        ValueError,
        match=r"^n_inputs must be <= .* features \(512 of 512 see .* traverse, plus 128 "
        r"intensity cells\); got 700",
    ):
        KenyonEncoder(intensity=True, n_inputs=700).fit(route[0])


def test_turning_the_channel_off_after_fit_is_refused(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0, intensity=True).fit(ref)
    enc.set_params(intensity=False)
    for fn in (enc.encode, enc.kenyon_activity):
        with pytest.raises(ValueError, match="gives 512 features .* fitted on 640.* fit again"):
            fn(qry)
    enc.set_params(intensity=True)
    assert enc.encode(qry).shape == (40, 512)


def test_pool_size_that_does_not_divide_the_frame(route):
    with pytest.raises(ValueError, match="pool_size must divide the image size"):
        KenyonEncoder(intensity=True, pool_size=5).fit(route[0])


@pytest.mark.parametrize("value", [1, 0, None, "yes", 1.0])
def test_intensity_must_be_a_bool(route, value):
    with pytest.raises(TypeError, match="intensity must be True or False; got"):
        KenyonEncoder(intensity=value).fit(route[0])


def test_numpy_bool_is_accepted(route):
    enc = KenyonEncoder(random_state=0, intensity=np.bool_(True)).fit(route[0])
    assert enc.n_features_ == 640


def test_model_file_keeps_the_channel(route, tmp_path):
    ref, qry = route
    model = make_method("kenyon+cann", 0, {"intensity": True}).fit(ref)
    again = load_method(save_method(model, tmp_path / "k.npz"))
    assert again.frontend.intensity is True and again.frontend.n_features_ == 640
    np.testing.assert_array_equal(again.score(qry), model.score(qry))


def _rewrite(path, out, edit):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    edit(meta["frontend"]["params"])
    return _write_archive(out, meta, arrays)


def test_model_file_from_before_the_channel_loads_without_it(route, tmp_path):
    ref, qry = route
    model = make_method("kenyon", 0).fit(ref)
    path = save_method(model, tmp_path / "k.npz")

    def drop(params):
        del params["intensity"]

    again = load_method(_rewrite(path, tmp_path / "old.npz", drop))
    assert again.frontend.intensity is False
    np.testing.assert_array_equal(again.score(qry), model.score(qry))


def test_model_file_whose_features_do_not_match_the_channel_is_refused(route, tmp_path):
    ref, _ = route
    path = save_method(make_method("kenyon", 0, {"intensity": True}).fit(ref), tmp_path / "k.npz")

    def off(params):
        params["intensity"] = False

    with pytest.raises(ModelFileError, match="n_features_ must be 512"):
        load_method(_rewrite(path, tmp_path / "a.npz", off))

    def as_int(params):
        params["intensity"] = 1

    with pytest.raises((ModelFileError, TypeError), match="intensity must be True or False"):
        load_method(_rewrite(path, tmp_path / "b.npz", as_int))


def test_compact_codes_refuse_the_channel(route):
    ref, _ = route
    enc = KenyonEncoder(random_state=0, intensity=True).fit(ref)
    with pytest.raises(ValueError, match="intensity=True"):
        CompactEncoder.from_kenyon(enc, ref, n_bits=64)
