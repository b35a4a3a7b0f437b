"""The ``kenyon`` front end: optic lobe, Kenyon-cell expansion, packed codes, overlap scores."""

import json
import re
import tracemalloc
import warnings

import numpy as np
import pytest

from flyvpr._validation import InsufficientMemoryError, NotFittedError
from flyvpr.frontends import FRONTENDS, KenyonEncoder
from flyvpr.frontends.kenyon import balanced_connections, code_overlap
from flyvpr.frontends.optic_lobe import (
    gabor_bank,
    local_contrast_normalize,
    optic_lobe,
)
from flyvpr.localization import Localizer
from flyvpr.methods import METHODS, make_method
from flyvpr.modelio import ModelFileError, _write_archive, load_method, save_method
from oracles import gabor_energy


@pytest.fixture(scope="module")
def route(sliding_world):
    return sliding_world


def test_registered_and_combinable():
    assert FRONTENDS["kenyon"] is KenyonEncoder
    for filt in ("cann", "seqslam", "rnn"):
        assert METHODS[f"kenyon+{filt}"].frontend == "kenyon"


def test_codes_are_packed_with_exactly_k_active_bits(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    codes = enc.encode(qry)
    assert codes.dtype == np.uint8 and codes.shape == (40, 4096 // 8)
    bits = np.unpackbits(codes, axis=1)
    assert enc.n_active_ == round(0.05 * 4096)
    assert np.all(bits.sum(axis=1) == enc.n_active_)
    # the bits are the WTA of the Kenyon-cell activity: every winner beats every loser
    y = enc.kenyon_activity(qry)
    for row, b in zip(y, bits.astype(bool), strict=True):
        assert row[b].min() >= row[~b].max()


@pytest.mark.parametrize(("n_kenyon", "n_proj", "ratio"), [(1024, 1, 0.1), (2048, 4, 0.05)])
def test_each_projection_has_its_own_winners(route, n_kenyon, n_proj, ratio):
    ref, _ = route
    enc = KenyonEncoder(
        n_kenyon=n_kenyon, n_projections=n_proj, active_ratio=ratio, random_state=1
    ).fit(ref)
    bits = np.unpackbits(enc.encode(ref), axis=1).reshape(len(ref), n_proj, -1)
    per = round(ratio * n_kenyon / n_proj)
    assert np.all(bits.sum(axis=2) == per)
    assert enc.n_active_ == per * n_proj


def test_score_is_overlap_over_k_computed_directly(route):
    ref, qry = route
    enc = KenyonEncoder(n_kenyon=2048, random_state=3).fit(ref)
    q = np.unpackbits(enc.encode(qry), axis=1).astype(np.int64)
    r = np.unpackbits(enc.reference_codes_, axis=1).astype(np.int64)
    direct = np.array([[np.sum(a & b) for b in r] for a in q]) / enc.n_active_
    S = enc.score(qry)
    assert S.dtype == np.float32
    np.testing.assert_allclose(S, direct, rtol=1e-6)
    np.testing.assert_allclose(enc.score(ref).diagonal(), 1.0)


@pytest.mark.parametrize("n_query", [1, 3, 8, 50])
def test_code_overlap_matches_a_loop_serial_and_parallel(n_query):
    rng = np.random.default_rng(n_query)
    q = rng.random((n_query, 70)) < 0.2
    r = rng.random((33, 70)) < 0.3
    expected = [[int(np.sum(a & b)) for b in r] for a in q]
    np.testing.assert_array_equal(code_overlap(q, r), expected)


@pytest.mark.parametrize("n_query", [1, 8])
def test_code_overlap_over_more_places_than_one_chunk_of_the_index(n_query):
    # The inverted index stores places as uint16 offsets within chunks of its own size: a map
    # of more than 65,536 places spans two chunks, and each must be scored at its own places.
    rng = np.random.default_rng(7)
    n_places = 70_000
    q = rng.random((n_query, 24)) < 0.3
    r = rng.random((n_places, 24)) < 0.3
    expected = q.astype(np.int32) @ r.T.astype(np.int32)
    got = code_overlap(q, r)
    np.testing.assert_array_equal(got, expected)
    assert (got[:, 65_536:] > 0).any()  # the second chunk is scored, not left at 0


def test_code_overlap_bad_shapes():
    with pytest.raises(ValueError, match="same number of bits"):
        code_overlap(np.zeros((2, 8), bool), np.zeros((2, 9), bool))


def test_bytes_per_place_is_an_eighth_of_pixels_or_less(route):
    ref, _ = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    assert enc.bytes_per_place() == 512.0
    pixels = FRONTENDS["pixels"]().fit(ref).bytes_per_place()
    assert enc.bytes_per_place() <= pixels / 8
    assert KenyonEncoder(n_kenyon=8192, random_state=0).fit(ref).bytes_per_place() == 1024.0


def test_determinism_per_seed(route):
    ref, qry = route
    a = KenyonEncoder(random_state=5).fit(ref)
    b = KenyonEncoder(random_state=5).fit(ref)
    c = KenyonEncoder(random_state=6).fit(ref)
    np.testing.assert_array_equal(a.connections_, b.connections_)
    np.testing.assert_array_equal(a.encode(qry), b.encode(qry))
    assert not np.array_equal(a.connections_, c.connections_)


def test_encoding_is_batch_independent(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    batch = enc.encode(qry)
    one_by_one = np.concatenate([enc.encode(qry[i : i + 1]) for i in range(len(qry))])
    np.testing.assert_array_equal(batch, one_by_one)


def test_streaming_equals_batch_scores(route):
    ref, qry = route
    S = make_method("kenyon", 0).fit(ref).score(qry)
    loc = Localizer(make_method("kenyon", 0)).fit(ref)
    rows = np.stack([loc.scores(img) for img in qry])
    np.testing.assert_array_equal(rows, S)


def test_balanced_connections():
    conn = balanced_connections(1000, 120, 6, random_state=0)
    assert conn.shape == (1000, 6) and conn.dtype == np.int32
    assert np.all(np.diff(conn, axis=1) > 0)  # distinct, sorted
    counts = np.bincount(conn.ravel(), minlength=120)
    assert counts.max() - counts.min() <= 2  # 50 each, give or take a redrawn row
    with pytest.raises(ValueError, match="n_inputs must be <="):
        balanced_connections(10, 5, 6)
    with pytest.raises(ValueError, match="^n_kenyon must be >= 1; got 0$"):
        balanced_connections(0, 5, 2)
    with pytest.raises(ValueError, match="^n_inputs must be >= 1; got 0$"):
        balanced_connections(10, 5, 0)


def test_recognises_places_of_the_route(route):
    ref, qry = route
    S = KenyonEncoder(random_state=0).fit(ref).score(qry)
    assert np.mean(S.argmax(axis=1) == np.arange(len(qry))) >= 0.9


@pytest.mark.parametrize("filt", ["cann", "seqslam"])
def test_combines_with_filters(route, filt):
    ref, qry = route
    m = make_method(f"kenyon+{filt}", 0).fit(ref)
    S = m.score(qry)
    assert S.shape == (40, 40) and np.isfinite(S).all()
    assert np.mean(np.abs(S.argmax(axis=1) - np.arange(40)) <= 2) >= 0.9


def test_model_file_round_trip(route, tmp_path):
    ref, qry = route
    model = make_method("kenyon+cann", 0).fit(ref)
    path = save_method(model, tmp_path / "k.npz")
    again = load_method(path)
    np.testing.assert_array_equal(again.frontend.reference_codes_, model.frontend.reference_codes_)
    np.testing.assert_array_equal(again.score(qry), model.score(qry))


def test_model_file_with_inconsistent_codes_refused(route, tmp_path):
    ref, _ = route
    path = save_method(make_method("kenyon", 0).fit(ref), tmp_path / "k.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    arrays["frontend/reference_codes_"][0, 0] ^= 0xFF  # 8 more or fewer active bits
    out = _write_archive(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(ModelFileError, match=r"\(every reference code must have n_active_ active"):
        load_method(out)


def _tampered(path, out, edit):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    edit(meta["frontend"]["state"], {k[len("frontend/") :]: k for k in arrays}, arrays)
    return _write_archive(out, meta, arrays)


def _set(name, value):
    def edit(state, keys, arrays):
        arrays[keys[name]] = value(arrays[keys[name]])

    return edit


def _set_scalar(name, value):
    def edit(state, keys, arrays):
        state[name]["value"] = value

    return edit


def _repeat_feature(c):
    c = c.copy()
    c[3, 1] = c[3, 0]
    return c


def _index(value):
    def edit(c):
        c = c.copy()
        c[0, 0] = value
        return np.sort(c, axis=1)

    return edit


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (_set("connections_", lambda c: c[:, :9]), "connections_"),
        (_set("connections_", lambda c: c.astype(np.int64)), "connections_"),
        (_set("feature_mean_", lambda m: m[:500]), "feature_mean_"),
        (_set("feature_mean_", lambda m: m.astype(np.float64)), "feature_mean_"),
        (_set("reference_codes_", lambda r: r[:, :500]), "reference_codes_"),
        (_set("reference_codes_", lambda r: r.astype(np.uint16)), "reference_codes_"),
        (_set("connections_", _index(512)), r"\(connections_ must index the 512 features\)"),
        (_set("connections_", _index(-1)), r"\(connections_ must index the 512 features\)"),
        (
            _set("connections_", _repeat_feature),
            r"\(connections_ repeats a feature within a Kenyon cell\)",
        ),
        (_set_scalar("n_active_", 4097), r"\(n_active_ must be <= n_kenyon = 4096\)"),
    ],
)
def test_model_file_with_a_bad_state_is_refused(route, tmp_path, edit, match):
    path = save_method(make_method("kenyon", 0).fit(route[0]), tmp_path / "k.npz")
    with pytest.raises(ModelFileError, match=match):
        load_method(_tampered(path, tmp_path / "bad.npz", edit))


def test_model_file_with_bad_parameters_is_refused(route, tmp_path):
    path = save_method(make_method("kenyon", 0).fit(route[0]), tmp_path / "k.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    meta["frontend"]["params"]["n_inputs"] = 0
    out = _write_archive(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(ModelFileError, match=r"parameters \(n_inputs must be >= 1; got 0\)"):
        load_method(out)


def test_model_file_with_every_kenyon_cell_active_loads(route, tmp_path):
    # n_active_ may equal n_kenyon: every code all ones
    path = save_method(make_method("kenyon", 0).fit(route[0]), tmp_path / "k.npz")

    def edit(state, keys, arrays):
        state["n_active_"]["value"] = 4096
        arrays[keys["reference_codes_"]][:] = 0xFF

    again = load_method(_tampered(path, tmp_path / "all.npz", edit))
    assert again.frontend.n_active_ == 4096
    np.testing.assert_array_equal(again.score(route[1][:2]), 1.0)


def test_an_encoder_rebuilds_a_dropped_optic_lobe(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    codes = enc.encode(qry)
    del enc._optic_lobe, enc._valid  # as a copy of the public state only would have
    np.testing.assert_array_equal(enc.encode(qry), codes)


@pytest.mark.parametrize(
    ("params", "error", "match"),
    [
        ({"n_kenyon": 1004}, ValueError, "multiple of 8"),
        ({"n_kenyon": 0}, ValueError, "^n_kenyon must be >= 8; got 0$"),
        ({"n_kenyon": 4}, ValueError, "^n_kenyon must be >= 8; got 4$"),
        ({"n_projections": 0}, ValueError, "^n_projections must be >= 1; got 0$"),
        ({"n_projections": 1.5}, TypeError, "^n_projections must be an int; got float$"),
        ({"n_kenyon": 4096, "n_projections": 3}, ValueError, "multiple of 8 and of n_proj"),
        ({"active_ratio": 0.0}, ValueError, r"^active_ratio must be in \(0.0, 1.0\]; got 0.0"),
        ({"active_ratio": "5%"}, TypeError, "^active_ratio must be a number; got str"),
        ({"n_inputs": 0}, ValueError, "^n_inputs must be >= 1; got 0"),
        ({"n_inputs": 10_000}, ValueError, r"^n_inputs must be <= .* features \(512 of 512 see"),
        ({"n_kenyon": 8 * 10**12}, ValueError, "n_kenyon=8000000000000 .* would need"),
        ({"pool_size": 5}, ValueError, "pool_size must divide"),
        ({"lcn_sigma": -1.0}, ValueError, "lcn_sigma"),
        ({"kernel_size": 10}, ValueError, "size must be odd"),
        ({"wavelength": float("nan")}, ValueError, "wavelength"),
    ],
)
def test_bad_parameters(route, params, error, match):
    ref, _ = route
    with pytest.raises(error, match=match):
        KenyonEncoder(random_state=0, **params).fit(ref)


def test_bad_input(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0)
    with pytest.raises(NotFittedError):
        enc.encode(qry)
    enc.fit(ref)
    with pytest.raises(ValueError, match="image size"):
        enc.score(np.zeros((2, 16, 32), np.float32))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        enc.score(qry * 3)
    with pytest.raises(ValueError, match="bit-packed uint8"):
        enc.score_codes(np.zeros((2, 511), np.uint8))


def test_blank_frames_are_handled(route):
    ref, _ = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    assert np.all(optic_lobe(np.zeros((2, 32, 64))) == 0)
    S = enc.score(np.full((2, 32, 64), 0.5, np.float32))
    assert np.isfinite(S).all()
    assert np.all(np.unpackbits(enc.encode(np.zeros((1, 32, 64))), axis=1).sum() == enc.n_active_)


def test_optic_lobe_parts():
    rng = np.random.default_rng(0)
    x = rng.random((3, 32, 64)).astype(np.float32)
    lcn = local_contrast_normalize(x)
    # invariant to a gain and an offset of the image (up to the eps floor)
    brighter = local_contrast_normalize(np.clip(0.5 * x + 0.2, 0, 1), eps=1e-6)
    np.testing.assert_allclose(brighter, local_contrast_normalize(x, eps=1e-6), atol=1e-3)
    assert lcn.shape == x.shape and lcn.dtype == np.float32
    bank = gabor_bank(4, 6.0, 11)
    assert bank.shape == (4, 11, 11)
    np.testing.assert_allclose(bank.real.sum(axis=(1, 2)), 0.0, atol=1e-12)  # no DC response
    # a vertical grating excites the 0-degree filter most (it varies along x)
    grating = np.tile(0.5 + 0.5 * np.cos(2 * np.pi * np.arange(64) / 6.0), (1, 32, 1))
    energy = gabor_energy(grating.astype(np.float32), bank)[0, :, 10:22, 20:44].mean(axis=(1, 2))
    assert energy.argmax() == 0 and energy[0] > 5 * energy[2]
    # the FFT convolution equals a direct one
    from scipy.signal import convolve2d

    direct = np.abs(convolve2d(x[0], bank[1], mode="same"))
    np.testing.assert_allclose(gabor_energy(x[:1], bank)[0, 1], direct, atol=1e-5)
    f = optic_lobe(x)
    assert f.shape == (3, 512)
    np.testing.assert_allclose(f.mean(axis=1), 0, atol=1e-5)
    np.testing.assert_allclose(f.std(axis=1), 1, atol=1e-4)


def test_footprint_counts_no_trained_parameters(route):
    enc = KenyonEncoder(random_state=0).fit(route[0])
    fp = enc.footprint()
    assert fp["params"] == 0 and fp["neurons"] == 512 + 4096


def test_kenyon_activity_checks_its_images_and_is_float32(route):
    ref, qry = route
    enc = KenyonEncoder(random_state=0).fit(ref)
    y = enc.kenyon_activity(qry)
    assert y.dtype == np.float32 and y.shape == (len(qry), 4096)
    with pytest.raises(ValueError, match=r"^images must have image size \(H, W\) = \(32, 64\)"):
        enc.kenyon_activity(np.zeros((2, 16, 32), np.float32))
    with pytest.raises(ValueError, match=r"^images must hold gray values in \[0, 1\]"):
        enc.kenyon_activity(qry * 3)


def test_footprint_names_its_layers_and_fixed_connections(route):
    enc = KenyonEncoder(n_kenyon=1024, n_inputs=8, random_state=0).fit(route[0])
    fp = enc.footprint()
    assert fp["layers"] == 2  # optic lobe, Kenyon cells
    assert fp["fixed_connections"] == 1024 * 8 == enc.connections_.size
    assert fp["neurons"] == enc.n_features_ + 1024


def test_the_smallest_layout_fits(route, tmp_path):
    # n_kenyon = 8 (one byte per place) is allowed, and so is one active cell, in a model file
    ref, qry = route
    enc = KenyonEncoder(n_kenyon=8, active_ratio=0.25, n_inputs=4, random_state=0).fit(ref)
    assert enc.encode(qry).shape == (len(qry), 1) and enc.n_active_ == 2
    params = {"n_kenyon": 8, "active_ratio": 0.125, "n_inputs": 1}
    one = make_method("kenyon", 0, frontend_params=params).fit(ref)
    assert one.frontend.n_active_ == 1
    again = load_method(save_method(one, tmp_path / "one.npz"))
    assert again.frontend.n_active_ == 1
    np.testing.assert_array_equal(again.score(qry), one.score(qry))


def test_the_optic_lobe_is_built_once_and_the_fit_names_its_chunked_work(route):
    ref, qry = route
    seen = []

    def recording(func, rows, what=""):
        seen.append((what, len(rows)))
        return func(rows)

    enc = KenyonEncoder(random_state=0)
    enc._fit_checked(ref, recording)
    assert seen == [("optic lobe", len(ref)), ("kenyon codes", len(ref))]
    np.testing.assert_array_equal(
        enc.reference_codes_, KenyonEncoder(random_state=0).fit(ref).reference_codes_
    )
    lobe = enc._optic_lobe
    enc.encode(qry)
    enc.score(qry)
    assert enc._optic_lobe is lobe


@pytest.mark.parametrize(
    ("q", "r"),
    [
        (np.zeros(8, bool), np.zeros((3, 8), bool)),
        (np.zeros((2, 8), bool), np.zeros(8, bool)),
        (np.zeros((2, 8), bool), np.zeros((3, 16), bool)),
    ],
)
def test_code_overlap_refuses_other_shapes(q, r):
    with pytest.raises(ValueError, match=r"^query_codes and reference_codes must be 2-d with th"):
        code_overlap(q, r)


def test_code_overlap_is_int32():
    out = code_overlap([[1, 1, 0, 0]], [[1, 0, 1, 0], [1, 1, 0, 0]])
    assert out.dtype == np.int32
    np.testing.assert_array_equal(out, [[1, 2]])


def test_gabor_bank_defaults_are_the_optic_lobes():
    # 4 orientations, a 6-pixel wavelength, 11x11 kernels: what the optic lobe uses by default
    bank = gabor_bank()
    assert bank.shape == (4, 11, 11)
    np.testing.assert_array_equal(bank, gabor_bank(4, 6.0, 11))
    assert not np.allclose(bank, gabor_bank(4, 7.0, 11))


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"n_orientations": 0}, "n_orientations must be >= 1; got 0"),
        ({"wavelength": -1.0}, r"wavelength must be in \[2\.0, 1000000\.0\] pixels; got -1\.0"),
        ({"size": 1}, "size must be >= 3; got 1"),
    ],
)
def test_gabor_bank_names_a_bad_parameter(params, message):
    with pytest.raises(ValueError, match=f"^{message}$"):
        gabor_bank(**params)


@pytest.mark.parametrize(
    ("params", "error", "message"),
    [
        (
            {"lcn_sigma": 0.0},
            ValueError,
            r"lcn_sigma must be in \[0\.25, 1000000\.0\] pixels; got 0\.0",
        ),
        ({"lcn_eps": -1.0}, ValueError, r"lcn_eps must be in \[1e-08, 1\.0\]; got -1\.0"),
        ({"lcn_eps": "a"}, TypeError, "lcn_eps must be a number; got str"),
        ({"pool_size": 0}, ValueError, "pool_size must be >= 1; got 0"),
        ({"kernel_size": 1}, ValueError, "kernel_size must be >= 3; got 1"),
        (
            {"kernel_size": 10},
            ValueError,
            r"kernel_size must be odd \(a kernel centred on a pixel\); got 10",
        ),
    ],
)
def test_optic_lobe_names_a_bad_parameter(params, error, message):
    from flyvpr.frontends.optic_lobe import OpticLobe

    base = {
        "lcn_sigma": 4.0,
        "lcn_eps": 0.05,
        "n_orientations": 4,
        "wavelength": 6.0,
        "kernel_size": 11,
        "pool_size": 4,
    }
    with pytest.raises(error, match=f"^{message}$"):
        OpticLobe(**{**base, **params})


# -- settings out of range: one-line errors, raised before anything big is allocated ------------
#: the accepted ranges, as the messages give them
_RANGES = {
    "wavelength": r"wavelength must be in \[2\.0, 1000000\.0\] pixels",
    "lcn_sigma": r"lcn_sigma must be in \[0\.25, 1000000\.0\] pixels",
    "lcn_eps": r"lcn_eps must be in \[1e-08, 1\.0\]",
}


@pytest.mark.parametrize(
    ("name", "value"),
    [
        # what each did before it was checked
        ("wavelength", 1e308),  # (0.56 * wavelength) ** 2: OverflowError
        ("wavelength", 1e41),  # 1 / z past float32: inf factors, NaN features
        ("wavelength", 1e-308),  # divide by zero: NaN kernels and features
        ("wavelength", 1.0),  # below Nyquist: a flat carrier, kernels of rounding noise
        ("wavelength", 0.0),
        ("wavelength", -6.0),
        ("lcn_sigma", 1e308),  # OverflowError: cannot convert float infinity to integer
        ("lcn_sigma", 1e20),  # numpy's ValueError: Maximum allowed size exceeded
        ("lcn_sigma", 1e-308),  # ZeroDivisionError
        ("lcn_sigma", 1e-160),  # NaN features
        ("lcn_sigma", 0.1),  # the window holds the pixel alone: every feature 0
        ("lcn_sigma", -4.0),
        ("lcn_eps", 1e308),  # every feature 0
        ("lcn_eps", 1e30),  # overflow in the cast of eps**2 to float32
        ("lcn_eps", 1e-30),  # eps**2 is 0 in float32: ZeroDivisionError on a black frame
        ("lcn_eps", 0.0),
    ],
)
def test_real_settings_out_of_range_are_one_line_value_errors(route, name, value):
    method = make_method("kenyon", 0, frontend_params={name: value})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no numpy warning on the way either)
        with pytest.raises(ValueError, match=rf"^{_RANGES[name]}; got {re.escape(str(value))}$"):
            method.fit(route[0])


@pytest.mark.parametrize("name", ["wavelength", "lcn_sigma", "lcn_eps"])
@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_real_settings_must_be_finite(route, name, value):
    method = make_method("kenyon", 0, frontend_params={name: value})
    with pytest.raises(ValueError, match=rf"^{name} must be finite; got {value}$"):
        method.fit(route[0])


@pytest.mark.parametrize(
    "settings",
    [
        {"wavelength": 2.0},
        {"wavelength": 1e6},
        {"wavelength": 1e6, "kernel_size": 3},
        {"lcn_sigma": 0.25},
        {"lcn_eps": 1e-8},
        {"lcn_eps": 1.0},
    ],
)
def test_the_ends_of_the_ranges_give_finite_features(settings):
    x = np.random.default_rng(0).random((3, 32, 64), dtype=np.float32)
    x[1] = 0.0  # black: flat everywhere
    x[2, :, :20] = 0.5  # a flat patch
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = optic_lobe(x, **settings)
    assert np.isfinite(f).all()
    assert not f[1].any()
    np.testing.assert_allclose(f[[0, 2]].std(axis=1), 1.0, atol=1e-4)


def test_the_functions_name_their_own_real_parameters():
    x = np.zeros((1, 8, 8))
    with pytest.raises(
        ValueError, match=r"^sigma must be in \[0\.25, 1000000\.0\] pixels; got 1e\+308$"
    ):
        local_contrast_normalize(x, sigma=1e308)
    with pytest.raises(ValueError, match=r"^eps must be in \[1e-08, 1\.0\]; got 1e-30$"):
        local_contrast_normalize(x, eps=1e-30)
    with pytest.raises(ValueError, match=rf"^{_RANGES['wavelength']}; got 1e-308$"):
        gabor_bank(wavelength=1e-308)


def _peak_bytes(func):
    """The exception ``func`` raises and the most memory Python and numpy held on the way."""
    tracemalloc.start()
    try:
        func()
    except Exception as exc:
        return exc, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    raise AssertionError("nothing raised")


def test_a_billion_orientations_are_refused_before_allocating(route, monkeypatch):
    # they allocated 7.45 GiB (the orientations' angles, int64) before any check
    monkeypatch.setenv("FLYVPR_MAX_MEMORY", "4G")  # (5.81 TB is refused anywhere, then)
    method = make_method("kenyon", 0, frontend_params={"n_orientations": 10**9})
    exc, peak = _peak_bytes(lambda: method.fit(route[0]))
    assert isinstance(exc, InsufficientMemoryError)
    assert re.match(
        r"n_orientations=1000000000 with kernel_size=11 would need [\d.]+ TB of memory; "
        r"[\d.,]+ [kMGT]?B is available$",
        str(exc),
    )
    assert peak < 1 << 20


@pytest.mark.parametrize(
    ("settings", "mask", "message"),
    [
        # the kernels: 10**5 x 11 x 11 complex128, with the temporaries that make them
        ({"n_orientations": 10**5}, False, "n_orientations=100000 with kernel_size=11"),
        ({"kernel_size": 1001}, False, "n_orientations=4 with kernel_size=1001"),
        # the compiled filter's buffers for 32x64 frames: two float32 lines per orientation
        (
            {"n_orientations": 10**4},
            False,
            "n_orientations=10000 with kernel_size=11 on images of 32x64",
        ),
        # the window: 8 * lcn_sigma taps, and the frame's lines padded by as many pixels
        ({"lcn_sigma": 1e5}, False, "lcn_sigma=100000 on images of 32x64"),
        ({"lcn_sigma": 1e5}, True, "lcn_sigma=100000 on images of 32x64"),
    ],
)
def test_settings_that_would_not_fit_in_memory_are_refused_first(
    monkeypatch, settings, mask, message
):
    monkeypatch.setenv("FLYVPR_MAX_MEMORY", "100M")
    x = np.random.default_rng(0).random((1, 32, 64), dtype=np.float32)
    valid = np.ones((32, 64), bool)
    valid[:, :8] = False  # (the window weights of a mask come after the check too)
    exc, peak = _peak_bytes(lambda: optic_lobe(x, **settings, valid_pixels=valid if mask else None))
    assert isinstance(exc, InsufficientMemoryError)
    assert re.match(rf"{message} would need [\d.]+ MB of memory; 105 MB is available$", str(exc))
    assert peak < 100 << 20  # (the 52 MB kernels of 10**4 orientations fit, their buffers not)


def test_balanced_connections_that_would_not_fit_in_memory_are_refused_first(monkeypatch):
    # (a million cells of 10 inputs took 20,000 permutations of the 512 features, 80 MB)
    monkeypatch.setenv("FLYVPR_MAX_MEMORY", "10M")
    exc, peak = _peak_bytes(lambda: balanced_connections(10**6, 512, 10, 0))
    assert isinstance(exc, InsufficientMemoryError)
    assert str(exc) == (
        "n_kenyon=1000000 with n_inputs=10 would need 320 MB of memory; 10.5 MB is available"
    )
    assert peak < 1 << 20


@pytest.mark.parametrize(
    ("name", "value", "problem"),
    [
        ("wavelength", 1e308, _RANGES["wavelength"] + r"; got 1e\+308"),
        ("lcn_sigma", 1e-308, _RANGES["lcn_sigma"] + "; got 1e-308"),
        ("lcn_eps", 1e308, _RANGES["lcn_eps"] + r"; got 1e\+308"),
        ("kernel_size", 12, r"kernel_size must be odd \(a kernel centred on a pixel\); got 12"),
        (
            "n_orientations",
            10**9,
            r"n_orientations=1000000000 with kernel_size=11 would need [\d.]+ TB of memory; "
            r"[\d.,]+ [kMGT]?B is available",
        ),
    ],
)
def test_model_file_with_settings_out_of_range_is_refused(route, tmp_path, name, value, problem):
    path = save_method(make_method("kenyon", 0).fit(route[0]), tmp_path / "k.npz")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    meta["frontend"]["params"][name] = value
    out = _write_archive(tmp_path / "bad.npz", meta, arrays)
    with pytest.raises(
        ModelFileError,
        match=rf"bad\.npz: frontend\.state: does not restore a kenyon \({problem}\)$",
    ):
        load_method(out)
