"""What an image folder yields, which pixels are read, and when a cache entry is trusted."""

import logging
import os
import struct
import zipfile
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from flyvpr import images as im


def _frames(folder, n=4, suffix=".png"):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = folder / f"{i}{suffix}"
        Image.fromarray(rng.integers(0, 256, (32, 64), dtype=np.uint8)).save(p)
        paths.append(p)
    return paths


def _gif(p):
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(p)


@pytest.mark.parametrize(
    "name, make, reason",
    [
        ("x.png", lambda p: p.symlink_to(p.parent / "gone.png"), "dangling symbolic link"),
        ("loop.png", lambda p: p.symlink_to(p), "symbolic link loop"),
        ("pipe.png", lambda p: os.mkfifo(p), "FIFO"),
        ("null.png", lambda p: p.symlink_to("/dev/null"), "device"),
        ("sub", lambda p: p.mkdir(), "sub-folder"),
        ("a.gif", _gif, r"\.gif image"),
        ("a.webp", _gif, r"\.webp image"),
        ("notes.txt", lambda p: p.write_text("x"), "not an image file"),
        ("README", lambda p: p.write_text("x"), "no extension"),
    ],
)
def test_every_other_entry_is_refused_by_name(tmp_path, name, make, reason):
    _frames(tmp_path)
    make(tmp_path / name)
    with pytest.raises(im.ImageFolderError, match=rf"{name}: .*{reason}"):
        im.list_images(tmp_path)


def test_hidden_entries_are_skipped_and_counted(tmp_path, caplog):
    _frames(tmp_path, 3)
    (tmp_path / ".DS_Store").write_bytes(b"x")
    (tmp_path / "._0.png").write_bytes(b"x")
    (tmp_path / ".thumbs").mkdir()
    with caplog.at_level(logging.INFO, logger="flyvpr.images"):
        assert [p.name for p in im.list_images(tmp_path)] == ["0.png", "1.png", "2.png"]
    assert "skipped 3 hidden" in caplog.text


def test_refusal_counts_the_others(tmp_path):
    _frames(tmp_path, 2)
    for name in ("a.txt", "b.txt", "c.gif"):
        (tmp_path / name).write_text("x")
    with pytest.raises(im.ImageFolderError, match=r"a\.txt.*and 2 more"):
        im.list_images(tmp_path)


def test_uppercase_extensions_and_links_to_frames_are_read(tmp_path):
    (p,) = _frames(tmp_path / "src", 1)
    (tmp_path / "dst").mkdir()
    (tmp_path / "dst" / "0.PNG").symlink_to(p)
    assert [q.name for q in im.list_images(tmp_path / "dst")] == ["0.PNG"]


# -- pixels ---------------------------------------------------------------------------------
def test_float_images(tmp_path):
    ok = tmp_path / "ok.tif"
    Image.fromarray(np.full((32, 64), 0.25, np.float32)).save(ok)
    np.testing.assert_allclose(im.load_image(ok), 0.25)
    wide = tmp_path / "wide.tif"
    Image.fromarray(np.full((32, 64), 200.0, np.float32)).save(wide)
    with pytest.raises(im.ImageReadError, match=r"wide\.tif: float pixels must lie in \[0, 1\]"):
        im.load_image(wide)
    nan = tmp_path / "nan.tif"
    arr = np.full((32, 64), 0.5, np.float32)
    arr[3, 3] = np.nan
    Image.fromarray(arr).save(nan)
    with pytest.raises(im.ImageReadError, match=r"nan\.tif: .*NaN"):
        im.load_image(nan)


def test_32bit_integer_images(tmp_path):
    ok = tmp_path / "ok.tif"
    Image.fromarray(np.full((32, 64), 65535, np.int32)).save(ok)
    np.testing.assert_allclose(im.load_image(ok), 1.0)
    big = tmp_path / "big.tif"
    Image.fromarray(np.full((32, 64), 70000, np.int32)).save(big)
    with pytest.raises(im.ImageReadError, match=r"big\.tif: integer pixels must lie in"):
        im.load_image(big)


def test_to_gray_never_clips():
    with pytest.raises(ValueError, match=r"range \[-0.5, 0.5\]"):
        im.to_gray(np.array([[-0.5, 0.5]]))
    np.testing.assert_array_equal(im.to_gray(np.array([[True, False]])), [[1.0, 0.0]])


def _png_declaring(path, w, h):
    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 9))
        + chunk(b"IEND", b"")
    )  # fmt: skip
    return path


@pytest.mark.parametrize("side", [10000, 14000])
def test_huge_declared_png_refused_before_decoding(tmp_path, side):
    path = _png_declaring(tmp_path / "huge.png", side, side)
    with pytest.raises(im.ImageReadError, match=r"huge\.png: declares .*before decoding"):
        im.load_image(path)


# -- cache ------------------------------------------------------------------------------------
def _cached(tmp_path, n=4):
    paths = _frames(tmp_path / "imgs", n)
    cache = tmp_path / "cache"
    clean = im.load_images(paths, cache=cache, progress=False)
    (entry,) = cache.glob("*.npz")
    return paths, cache, entry, clean


def _flip(path, at):
    data = bytearray(path.read_bytes())
    data[at] ^= 0x10
    path.write_bytes(bytes(data))


def _rewrite(entry, edit):
    with zipfile.ZipFile(entry) as zf:
        import json

        key = json.loads(zf.read("meta.json"))["key"]
        with zf.open("images.npy") as fh:
            arr = np.lib.format.read_array(fh)
    im._write_cache(entry, edit(arr), key)


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda e: e.write_bytes(b""), "empty file"),
        (lambda e: e.write_bytes(os.urandom(3000)), "is unusable"),
        (lambda e: e.write_bytes(e.read_bytes()[:-100]), "is unusable"),
        (lambda e: _flip(e, e.stat().st_size // 2), "CRC"),
        (lambda e: _rewrite(e, lambda a: np.where(a > 0.5, np.nan, a)), "NaN or outside"),
        (lambda e: _rewrite(e, lambda a: a * 3), "NaN or outside"),
        (lambda e: _rewrite(e, lambda a: a[:, ::-1].copy()), None),  # valid but other pixels
    ],
)
def test_damaged_cache_entries_are_named_and_rebuilt(tmp_path, caplog, damage, reason):
    paths, cache, entry, clean = _cached(tmp_path)
    damage(entry)
    with caplog.at_level(logging.WARNING, logger="flyvpr.images"):
        again = im.load_images(paths, cache=cache, progress=False)
    if reason is None:  # a well-formed entry written for these files: trusted (our own writer)
        assert not caplog.records
        return
    np.testing.assert_array_equal(again, clean)
    assert entry.name in caplog.text and reason in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="flyvpr.images"):
        np.testing.assert_array_equal(im.load_images(paths, cache=cache, progress=False), clean)
    assert not caplog.records  # rebuilt: the next run trusts it


def test_swapped_entries_are_detected(tmp_path, caplog):
    paths = _frames(tmp_path / "imgs", 4)
    cache = tmp_path / "cache"
    a = im.load_images(paths[:2], cache=cache, progress=False)
    im.load_images(paths[2:], cache=cache, progress=False)
    entries = sorted(cache.glob("*.npz"), key=lambda p: p.stat().st_mtime_ns)
    entries[0].write_bytes(entries[1].read_bytes())
    with caplog.at_level(logging.WARNING, logger="flyvpr.images"):
        np.testing.assert_array_equal(im.load_images(paths[:2], cache=cache, progress=False), a)
    assert "swapped" in caplog.text


def test_picture_replaced_with_same_size_and_mtime(tmp_path):
    paths = _frames(tmp_path / "imgs", 4, suffix=".bmp")  # BMP size depends on shape only
    cache = tmp_path / "cache"
    im.load_images(paths, cache=cache, progress=False)
    st = paths[1].stat()
    paths[1].write_bytes(paths[2].read_bytes())
    os.utime(paths[1], ns=(st.st_atime_ns, st.st_mtime_ns))
    assert paths[1].stat().st_size == st.st_size
    again = im.load_images(paths, cache=cache, progress=False)
    np.testing.assert_array_equal(again[1], again[2])


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=2000))
def test_cache_on_random_bytes(tmp_path_factory, data):
    tmp = tmp_path_factory.mktemp("c")
    paths, cache, entry, clean = _cached(tmp, 2)
    entry.write_bytes(data)
    np.testing.assert_array_equal(im.load_images(paths, cache=cache, progress=False), clean)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=400), suffix=st.sampled_from([".png", ".jpg", ".tif", ".bmp"]))
def test_decoder_on_random_bytes(tmp_path, data, suffix):
    path = tmp_path / f"r{suffix}"
    path.write_bytes(data)
    try:
        out = im.load_image(path)
    except im.ImageReadError as exc:
        assert path.name in str(exc)
    else:
        assert out.shape == (32, 64) and 0 <= out.min() <= out.max() <= 1
