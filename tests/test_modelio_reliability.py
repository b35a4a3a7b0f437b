"""Model files trust nothing: every dropped key, every flipped byte, every crafted field."""

import gc
import json
import re
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flyvpr.cli import main
from flyvpr.methods import make_method
from flyvpr.modelio import ModelFileError, _write_archive, load_method, save_method
from flyvpr.temporal.cann._filter import table_at_roots


def _read(path):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return json.loads(arrays.pop("__meta__").tobytes()), arrays


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A FlyNet+CANN model of 3 places of 8x16 images: a file of a few kB."""
    rng = np.random.default_rng(0)
    ref = rng.random((3, 8, 16), dtype=np.float32)
    model = make_method("flynet+cann", 0, {"n_hidden": 8, "epochs": 2}).fit(ref)
    path = save_method(model, tmp_path_factory.mktemp("m") / "tiny.npz", size=(8, 16))
    return path, model.score(ref), ref


def _key_paths(obj, prefix=()):
    """Every dict key of the JSON metadata, as a path of keys."""
    if isinstance(obj, dict):
        for key, value in obj.items():
            yield (*prefix, key)
            yield from _key_paths(value, (*prefix, key))


def test_every_dropped_key_is_refused_naming_the_file(tiny, tmp_path):
    path, _, _ = tiny
    meta, arrays = _read(path)
    paths = [p for p in _key_paths(meta) if p != ("checksum",)]
    assert len(paths) > 40
    for key_path in paths:
        edited = json.loads(json.dumps(meta))
        node = edited
        for key in key_path[:-1]:
            node = node[key]
        del node[key_path[-1]]
        out = _write_archive(tmp_path / "x.npz", edited, arrays)  # checksums recomputed
        if key_path[-2:] == ("params", "odometry"):  # added later: a file without it loads
            assert load_method(out).filter.odometry == "scaled"
            continue
        if key_path[-2:] == ("params", "hold_repeats"):  # the same (off behind FlyNet)
            assert load_method(out).filter.hold_repeats is False
            continue
        if key_path[-2:] == ("params", "jitter"):  # the same (its default: none)
            assert load_method(out).filter.jitter == 0.0
            continue
        if key_path[-2:] == ("params", "snap"):  # the same (off: it runs as it ran)
            assert load_method(out).filter.snap is False
            continue
        if key_path[-2:] == ("params", "adapt_front"):  # the same
            assert load_method(out).filter.adapt_front is False
            continue
        if key_path[-2:] == ("params", "breaks"):  # the same (its default: one route)
            assert load_method(out).filter.breaks == ()
            continue
        if key_path == ("seed",):  # added later: a file without it loads, with no seed
            assert load_method(out).seed is None
            continue
        if key_path[-2:] == ("filter", "calibration_root"):  # the same (its table resampled)
            saved = meta["filter"]["params"]["calibration"]
            assert load_method(out).filter.calibration == table_at_roots(saved, 2)
            continue
        with pytest.raises(ModelFileError, match=r"model file .*x\.npz") as info:
            load_method(out)
        assert "\n" not in str(info.value), key_path


def test_every_dropped_array_is_refused(tiny, tmp_path):
    path, _, _ = tiny
    meta, arrays = _read(path)
    for key in arrays:
        kept = {k: v for k, v in arrays.items() if k != key}
        out = _write_archive(tmp_path / "x.npz", meta, kept)
        with pytest.raises(ModelFileError, match=key.rsplit("/", 1)[-1]):
            load_method(out)


def test_every_single_byte_corruption_is_refused(tiny, tmp_path):
    path, _, _ = tiny
    data = path.read_bytes()
    out = tmp_path / "x.npz"
    for i in range(len(data)):
        flipped = bytearray(data)
        flipped[i] ^= 0xFF
        out.write_bytes(bytes(flipped))
        with pytest.raises((ModelFileError, FileNotFoundError)):
            load_method(out)


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda m, a: a.update({"frontend/weights_": a["frontend/weights_"].astype(np.float64)}),
         "weights_"),
        (lambda m, a: a.update({"frontend/weights_": a["frontend/weights_"][:, :2]}), "weights_"),
        (lambda m, a: a.update({"frontend/weights_": a["frontend/weights_"] * np.nan}), "NaN"),
        (lambda m, a: m.update(method="flyhash+cann"), "method"),
        (lambda m, a: m.update(method="flynet"), "method"),
        (lambda m, a: m["frontend"]["params"].update(n_hidden=16), "frontend"),
        (lambda m, a: m["frontend"]["params"].update(bogus=1), "frontend.params.bogus"),
        (lambda m, a: m["frontend"]["state"]["n_reference_"].update(value=-3), "n_reference_"),
        (lambda m, a: m["frontend"]["state"].update(extra={"value": 1}), "extra"),
        (lambda m, a: m["frontend"].update(state={}), "frontend.state"),
        (lambda m, a: m["filter"].update(name="seqslam"), "method"),
        (lambda m, a: m["preprocessing"].update(gray="green channel"), "preprocessing.gray"),
        (lambda m, a: m["frontend"]["state"]["hash_"]["state"]["n_inputs_"].update(value=100),
         "n_inputs_"),
        (lambda m, a: m.update(flyvpr_version=3), "flyvpr_version: has the wrong type: int"),
        (lambda m, a: m.update(aaa=1, zzz=2), "aaa: not a field of a flyvpr model"),
        (lambda m, a: m.update(format="other"), "format: not a flyvpr model"),
        (lambda m, a: m["frontend"]["state"]["weights_"].update(array="frontend/other"),
         "weights_: must name entry 'frontend/weights_'; got 'frontend/other'"),
        (lambda m, a: m["frontend"]["state"]["hash_"].update(object="pixels"),
         "hash_: unexpected nested part 'pixels'"),
        (lambda m, a: m["frontend"]["state"].update(weights_={"value": 1}),
         "weights_: malformed entry"),
        # an image size of one row passes as a size, and is then refused as the front end's
        (lambda m, a: m["preprocessing"].update(image_size=[1, 16]),
         r"image_shape_: \(8, 16\) differs from preprocessing.image_size \(1, 16\)"),
        (lambda m, a: m["preprocessing"].update(image_size=[0, 16]),
         r"image_size: must be \[H, W\]; got \[0, 16\]"),
    ],
)  # fmt: skip
def test_crafted_fields_are_refused_even_with_recomputed_checksums(tiny, tmp_path, edit, field):
    path, _, _ = tiny
    meta, arrays = _read(path)
    edit(meta, arrays)
    out = _write_archive(tmp_path / "x.npz", meta, arrays)
    with pytest.raises(ModelFileError, match=rf"x\.npz.*{field}"):
        load_method(out)


def test_compressed_entries_are_refused(tiny, tmp_path):
    import zipfile

    path, _, _ = tiny
    out = tmp_path / "z.npz"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info), zipfile.ZIP_DEFLATED)
        dst.comment = src.comment
    with pytest.raises(ModelFileError):
        load_method(out)


def _archive_with_meta(path, blob: bytes):
    """An archive holding only a ``__meta__`` entry of the bytes ``blob``, as they are."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        with zf.open("__meta__.npy", "w") as member:
            np.lib.format.write_array(member, np.frombuffer(blob, np.uint8), allow_pickle=False)
    return path


@pytest.mark.parametrize("depth", [100_000, 500_000])
def test_deeply_nested_metadata_is_refused_naming_the_file(tmp_path, capsys, depth):
    # Within the 1 MB metadata limit, but json.loads recurses once per "[".
    path = _archive_with_meta(tmp_path / "deep.npz", b"[" * depth + b"]" * depth)
    expected = rf"^model file {re.escape(str(path))}: __meta__: metadata is malformed"
    with pytest.raises(ModelFileError, match=expected):
        load_method(path)
    frames = tmp_path / "frames"
    frames.mkdir()
    assert main(["localize", "--map", str(path), str(frames)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "metadata is malformed" in err


def test_loaded_model_matches_and_filter_starts_clean(tiny):
    path, S, ref = tiny
    again = load_method(path)
    np.testing.assert_array_equal(again.score(ref), S)


@settings(
    max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    method=st.sampled_from(["pixels", "flyhash", "flynet", "flyhash+cann", "pixels+seqslam"]),
    n=st.integers(2, 6),
    seed=st.integers(0, 2**31),
)
def test_roundtrip_property(tmp_path, method, n, seed):
    rng = np.random.default_rng(seed)
    ref = rng.random((n, 8, 16), dtype=np.float32)
    qry = rng.random((3, 8, 16), dtype=np.float32)
    params = {"epochs": 2} if method.startswith("flynet") else None
    model = make_method(method, seed, params).fit(ref)
    again = load_method(save_method(model, tmp_path / "m.npz", size=(8, 16)), size=(8, 16))
    np.testing.assert_array_equal(again.score(qry), model.score(qry))
    assert again.name == method


class _Stop(BaseException):
    """Stands for the CLI's SIGTERM exit (an interruption, not an Exception)."""


# the abandoned archive's __del__ tries to close it again and says so (ignored, as it would be
# in a process that is ending)
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize("interruption", [KeyboardInterrupt, _Stop])
def test_an_interruption_inside_a_members_close_ends_the_write(tmp_path, monkeypatch, interruption):
    # The signal lands inside a zip member's close: the archive's close then raises
    # ValueError ("open writing handle") over it.  The write must end by the interruption,
    # with the old file kept and no temporary file left.
    rng = np.random.default_rng(0)
    model = make_method("pixels+cann", 0).fit(rng.random((6, 32, 64), dtype=np.float32))
    target = save_method(model, tmp_path / "m.npz")
    before = target.read_bytes()
    real_close = zipfile._ZipWriteFile.close
    calls = []

    def close(self):
        calls.append(1)
        if len(calls) == 2:
            raise interruption()
        return real_close(self)

    monkeypatch.setattr(zipfile._ZipWriteFile, "close", close)
    with pytest.raises(interruption):
        save_method(model, target)
    monkeypatch.setattr(zipfile._ZipWriteFile, "close", real_close)
    gc.collect()  # the abandoned archive's complaint, here rather than in a later test
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz"]


def test_the_format_version_and_the_file_checksum(tiny):
    # Version 2 is what every saved model and map holds: a new number refuses them all, so
    # it changes only with an incompatible layout (and this test with it).
    import hashlib

    from flyvpr.modelio import FORMAT_VERSION

    assert FORMAT_VERSION == 2
    path, _, _ = tiny
    assert _read(path)[0]["format_version"] == 2
    # the file ends with the hex SHA-256 of every byte before it
    body = path.read_bytes()
    assert body[-64:] == hashlib.sha256(body[:-64]).hexdigest().encode("ascii")


@pytest.mark.parametrize(
    "blob, problem",
    [
        (b"[1]", "format: not a flyvpr model"),
        (b'{"format": "other"}', "format: not a flyvpr model"),
        # over 1 MB (the limit), under 2
        (b'{"format": "flyvpr-model", "pad": "' + b"x" * (1 << 20) + b'"}',
         "__meta__: must be a JSON document of at most 1 MB"),
    ],
)  # fmt: skip
def test_metadata_that_is_no_model_is_refused(tmp_path, blob, problem):
    path = _archive_with_meta(tmp_path / "m.npz", blob)
    with pytest.raises(ModelFileError, match=rf"m\.npz: {problem}"):
        load_method(path)


def test_metadata_not_stored_as_bytes_is_refused(tmp_path):
    path = tmp_path / "m.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        with zf.open("__meta__.npy", "w") as member:
            np.lib.format.write_array(member, np.frombuffer(b"{}  ", np.int32))
    with pytest.raises(ModelFileError, match=r"m\.npz: __meta__: must be a JSON document"):
        load_method(path)


def test_entries_not_part_of_the_model_are_refused_naming_the_first(tiny, tmp_path):
    path, _, _ = tiny
    meta, arrays = _read(path)
    arrays.update({"zzz": np.zeros(2), "aaa": np.zeros(2)})
    out = _write_archive(tmp_path / "x.npz", meta, arrays)
    with pytest.raises(ModelFileError, match=r"x\.npz: entry 'aaa\.npy' is not part of"):
        load_method(out)


def test_sections_are_named_and_their_arrays_prefixed(tiny, tmp_path):
    model = load_method(tiny[0])
    with pytest.raises(ValueError, match="unknown model file section 'atlas'"):
        save_method(model, tmp_path / "a.npz", size=(8, 16), sections={"atlas": ({}, {})})
    bad = {"map": ({}, {"mapx/ids": np.arange(3)})}
    with pytest.raises(ValueError, match="unknown model file section 'map' or misnamed arrays"):
        save_method(model, tmp_path / "b.npz", size=(8, 16), sections=bad)
    good = {"map": ({"n": 3}, {"map/ids": np.arange(3)})}
    path = save_method(model, tmp_path / "c.npz", size=(8, 16), sections=good)
    assert _read(path)[0]["map"] == {"n": 3}
    with pytest.raises(ModelFileError, match=r"c\.npz: map: the file is a flyvpr map"):
        load_method(path)


@pytest.mark.parametrize(
    "scores, problem",
    [
        (
            lambda n: np.full((2, n), np.nan, np.float32),
            r"scores of shape \(2, 3\) \(finite: False\)",
        ),
        (lambda n: np.zeros((3, n), np.float32), r"scores of shape \(3, 3\) \(finite: True\)"),
    ],
)
def test_a_model_that_fails_on_a_test_frame_is_refused(
    tiny, tmp_path, monkeypatch, scores, problem
):
    # (a front end whose restored state scores nothing sensible: here its score replaced)
    path, _, _ = tiny
    cls = type(load_method(path).frontend)
    monkeypatch.setattr(cls, "score", lambda self, frames: scores(self.n_reference_))
    with pytest.raises(ModelFileError, match=rf"fails on a test frame \({problem}\)"):
        load_method(path)


@pytest.mark.parametrize("root", [1, 2, 4])
def test_the_recorded_root_decides_how_the_table_is_read(tiny, tmp_path, root):
    # (not the presence of hold_repeats, which only guesses it for files without a root)
    path, _, _ = tiny
    meta, arrays = _read(path)
    assert "hold_repeats" in meta["filter"]["params"]
    meta["filter"]["calibration_root"] = root
    saved = meta["filter"]["params"]["calibration"]
    loaded = load_method(_write_archive(tmp_path / "x.npz", meta, arrays)).filter.calibration
    assert tuple(loaded) == table_at_roots(saved, root)
    assert (tuple(loaded) == tuple(saved)) is (root == 4)


def test_a_bad_root_is_refused_with_no_table_too(tiny, tmp_path):
    path, _, _ = tiny
    meta, arrays = _read(path)
    meta["filter"]["params"]["calibration"] = None
    meta["filter"]["calibration_root"] = 3
    with pytest.raises(ModelFileError, match=r"x\.npz: filter\.calibration_root: 3: 1, 2 or 4"):
        load_method(_write_archive(tmp_path / "x.npz", meta, arrays))
    meta["filter"]["calibration_root"] = 2  # (a good one: nothing to resample)
    assert load_method(_write_archive(tmp_path / "y.npz", meta, arrays)).filter.calibration is None


@pytest.mark.parametrize("shape, fill", [((2, 3), np.nan), ((3, 3), 0.0)])
def test_a_filter_that_fails_on_the_test_frames_is_refused(
    tiny, tmp_path, monkeypatch, shape, fill
):
    path, _, _ = tiny
    cls = type(load_method(path).filter)
    monkeypatch.setattr(cls, "filter", lambda self, S: np.full(shape, fill, np.float32))
    expected = rf"fails on a test frame \(filtered scores of shape \({shape[0]}, 3\)\)"
    with pytest.raises(ModelFileError, match=expected):
        load_method(path)
