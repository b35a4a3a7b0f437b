import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flyvpr import images as im


def _save(path, array, mode=None):
    Image.fromarray(array, mode=mode).save(path) if mode else Image.fromarray(array).save(path)
    return path


@pytest.mark.parametrize(
    "array",
    [
        np.full((40, 80, 3), 200, np.uint8),  # RGB
        np.full((40, 80), 200, np.uint8),  # gray
        np.dstack([np.full((40, 80, 3), 200, np.uint8), np.full((40, 80), 7, np.uint8)]),  # RGBA
    ],
    ids=["rgb", "gray", "rgba"],
)
def test_load_image_modes(tmp_path, array):
    p = _save(tmp_path / "a.png", array)
    out = im.load_image(p)
    assert out.shape == (32, 64) and out.dtype == np.float32
    np.testing.assert_allclose(out, 200 / 255, atol=1e-5)


def test_load_16bit_png_keeps_full_range(tmp_path):
    arr = np.full((32, 64), 65535, np.uint16)
    arr[:, :32] = 0
    p = tmp_path / "deep.png"
    Image.fromarray(arr).save(p)
    out = im.load_image(p)
    np.testing.assert_allclose(out[:, :32], 0.0)
    np.testing.assert_allclose(out[:, 32:], 1.0)


def test_load_jpeg(tmp_path):
    p = tmp_path / "a.jpg"
    Image.fromarray(np.full((64, 128, 3), 128, np.uint8)).save(p, quality=95)
    out = im.load_image(p, size=(16, 32))
    assert out.shape == (16, 32)
    np.testing.assert_allclose(out, 128 / 255, atol=2 / 255)


def test_gray_uses_bt601_weights():
    rgb = np.zeros((1, 3, 3), np.uint8)
    rgb[0, 0, 0] = rgb[0, 1, 1] = rgb[0, 2, 2] = 255
    np.testing.assert_allclose(im.to_gray(rgb)[0], [0.299, 0.587, 0.114], atol=1e-6)


def test_resize_is_exact_area_average():
    rng = np.random.default_rng(0)
    src = rng.random((64, 128), dtype=np.float32)
    out = im.resize_area(src, (32, 64))
    expected = src.reshape(32, 2, 64, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_resize_is_the_exact_area_product_at_any_factor():
    # image files, video frames and bags share this one resize: exact area weights
    rng = np.random.default_rng(2)
    src = rng.random((270, 480), dtype=np.float32)
    dense = im.area_matrix(32, 270) @ src @ im.area_matrix(64, 480).T
    np.testing.assert_allclose(im.resize_area(src, (32, 64)), dense, rtol=1e-5, atol=1e-6)
    # output pixel 0 of 270 -> 32 rows covers rows 0-7 and 0.4375 of row 8
    w = im.area_matrix(32, 270)[0]
    np.testing.assert_allclose(w[:9] * 8.4375, [1] * 8 + [0.4375], rtol=1e-6)
    assert w[9:].sum() == 0
    # uint8 frames too (the video path), in their own units
    u8 = rng.integers(0, 256, (360, 640), dtype=np.uint8)
    np.testing.assert_allclose(
        im.area_resize(u8, 32, 64) / 255.0,
        im.resize_area(u8.astype(np.float32) / 255.0, (32, 64)),
        atol=1e-6,
    )


def test_resize_non_integer_factor_preserves_mean():
    rng = np.random.default_rng(1)
    src = rng.random((270, 480), dtype=np.float32)
    out = im.resize_area(src, (32, 64))
    assert out.shape == (32, 64)
    assert abs(out.mean() - src.mean()) < 1e-3


def test_demosaic_gbrg_recovers_flat_colour():
    # A flat colour (r, g, b) sampled in the GBRG pattern must demosaic back to it.
    r, g, b = 0.8, 0.5, 0.2
    raw = np.empty((8, 8), np.float32)
    raw[0::2, 0::2] = g
    raw[0::2, 1::2] = b
    raw[1::2, 0::2] = r
    raw[1::2, 1::2] = g
    rgb = im.demosaic_bilinear(raw, "gbrg")
    np.testing.assert_allclose(rgb[..., 0], r, atol=1e-6)
    np.testing.assert_allclose(rgb[..., 1], g, atol=1e-6)
    np.testing.assert_allclose(rgb[..., 2], b, atol=1e-6)


def test_demosaic_rejects_unknown_pattern():
    with pytest.raises(ValueError, match="bayer pattern"):
        im.demosaic_bilinear(np.zeros((4, 4)), "xyzw")


def test_list_images_natural_order(tmp_path):
    for i in (10, 2, 1):
        _save(tmp_path / f"{i}.png", np.zeros((4, 4), np.uint8))
    (tmp_path / ".DS_Store").write_text("x")  # hidden entries are skipped
    assert [p.name for p in im.list_images(tmp_path)] == ["1.png", "2.png", "10.png"]


def test_list_images_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing"):
        im.list_images(tmp_path / "missing")
    with pytest.raises(ValueError, match="no image files"):
        im.list_images(tmp_path)
    f = tmp_path / "file.png"
    f.write_bytes(b"x")
    with pytest.raises(NotADirectoryError, match="file.png"):
        im.list_images(f)


def _folder(tmp_path, n=5):
    rng = np.random.default_rng(0)
    tmp_path.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        paths.append(
            _save(tmp_path / f"{i}.png", rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
        )
    return paths


def test_cache_roundtrip_and_invalidation(tmp_path):
    paths = _folder(tmp_path / "imgs")
    cache = tmp_path / "cache"
    a = im.load_images(paths, cache=cache, progress=False)
    files = list(cache.glob("*.npz"))
    assert len(files) == 1
    # A second load reads the cache: prove it by corrupting nothing but the source decoder.
    b = im.load_images(paths, cache=cache, progress=False)
    np.testing.assert_array_equal(a, b)
    # Changing a file (size/mtime) changes the key: a new cache entry appears.
    _save(paths[0], np.zeros((32, 64, 3), np.uint8))
    os.utime(paths[0], ns=(1, 1))
    c = im.load_images(paths, cache=cache, progress=False)
    assert len(list(cache.glob("*.npz"))) == 2
    assert not np.array_equal(a[0], c[0])


def test_cache_is_used_without_decoding(tmp_path, monkeypatch):
    paths = _folder(tmp_path / "imgs")
    cache = tmp_path / "cache"
    im.load_images(paths, cache=cache, progress=False)

    def boom(*a, **k):
        raise AssertionError("decoded although cached")

    monkeypatch.setattr(im, "_decode", boom)
    out = im.load_images(paths, cache=cache, progress=False)
    assert out.shape == (5, 32, 64)


def test_size_is_part_of_cache_key(tmp_path):
    paths = _folder(tmp_path / "imgs")
    cache = tmp_path / "cache"
    a = im.load_images(paths, cache=cache, progress=False)
    b = im.load_images(paths, size=(16, 32), cache=cache, progress=False)
    assert a.shape == (5, 32, 64) and b.shape == (5, 16, 32)


@pytest.mark.parametrize("content", [b"", b"not an image at all", "truncated"])
def test_corrupt_image_names_file_and_leaves_no_cache(tmp_path, content):
    paths = _folder(tmp_path / "imgs")
    bad = paths[3]
    if content == "truncated":
        data = bad.read_bytes()
        bad.write_bytes(data[: len(data) // 2])
    else:
        bad.write_bytes(content)
    cache = tmp_path / "cache"
    with pytest.raises(im.ImageReadError, match="3.png"):
        im.load_images(paths, cache=cache, progress=False)
    assert not cache.exists() or not any(cache.iterdir())


def test_missing_file_and_empty_list(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        im.load_images([tmp_path / "nope.png"], cache=False)
    with pytest.raises(ValueError, match="paths is empty"):
        im.load_images([], cache=False)


@pytest.mark.parametrize("size", [(0, 5), (3,), "ab"])
def test_bad_size(size):
    with pytest.raises((ValueError, TypeError), match="size"):
        im.resize_area(np.zeros((4, 4), np.float32), size)


def test_corrupt_cache_file_is_ignored(tmp_path):
    paths = _folder(tmp_path / "imgs")
    cache = tmp_path / "cache"
    a = im.load_images(paths, cache=cache, progress=False)
    (f,) = cache.glob("*.npz")
    f.write_bytes(b"garbage")
    b = im.load_images(paths, cache=cache, progress=False)
    np.testing.assert_array_equal(a, b)


def test_real_nordland_frame(nordland_64x32):
    p = nordland_64x32 / "summer" / "images-00010.png"
    out = im.load_image(p)
    assert out.shape == (32, 64)
    assert 0.0 <= out.min() <= out.max() <= 1.0


class _Interrupt(BaseException):
    """Stands for Ctrl-C or the CLI's SIGTERM exit."""


# (the interrupted archive, never closed, says so when it is garbage collected)
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_an_interruption_while_the_cache_is_written_is_not_swallowed(tmp_path, monkeypatch):
    # The interruption arrives while the cache's zip member is being closed: the archive's
    # own close then raises ValueError ("open writing handle"), which a cache that may fail
    # tolerates -- but the interruption must still stop the work, and leave no file behind.
    import gc
    import zipfile

    paths = _folder(tmp_path / "imgs")
    cache = tmp_path / "cache"
    real_close = zipfile._ZipWriteFile.close

    def interrupted_close(self):
        monkeypatch.setattr(zipfile._ZipWriteFile, "close", real_close)
        raise _Interrupt

    monkeypatch.setattr(zipfile._ZipWriteFile, "close", interrupted_close)
    with pytest.raises(_Interrupt):
        im.load_images(paths, cache=cache, progress=False)
    gc.collect()  # here, under this test's warning filter
    assert not cache.exists() or list(cache.iterdir()) == []
    # without an interruption a failing cache write only warns, and the images come back
    monkeypatch.setattr(im, "_write_cache", _raise_value_error)
    assert im.load_images(paths, cache=cache, progress=False).shape == (5, 32, 64)


def _raise_value_error(*args):
    raise ValueError("cannot write here")


def test_raise_interruption_walks_the_chain():
    from flyvpr._io import raise_interruption

    try:
        try:
            raise _Interrupt
        except _Interrupt:
            raise ValueError("clean-up failed") from None
    except ValueError as exc:
        caught = exc
    # "from None" hides it from the traceback, but it is still the context being handled
    with pytest.raises(_Interrupt):
        raise_interruption(caught)
    plain = ValueError("nothing behind it")
    raise_interruption(plain)  # returns
    try:
        try:
            raise KeyError("an ordinary error")
        except KeyError:
            raise ValueError("while handling it") from None
    except ValueError as exc:
        raise_interruption(exc)  # an Exception in the chain is no interruption: returns

    def frames():
        try:
            yield 1
        finally:
            raise OSError(5, "Input/output error")  # a reader whose close fails

    g = frames()
    next(g)
    with pytest.raises(OSError) as info:
        g.close()
    raise_interruption(info.value)  # a generator closed ends nothing: returns


def test_area_resize_refuses_what_it_cannot_average_by_name():
    y = np.ones((8, 8), np.float32)
    assert im.area_resize(y, 4, 2).shape == (4, 2)
    for bad in (np.ones((2, 8, 8)), np.ones(8), np.ones((0, 8)), [[1.0]]):
        with pytest.raises(ValueError, match="y must be a non-empty 2-d array"):
            im.area_resize(bad, 4, 4)
    for h in (0, 2.5, True):
        with pytest.raises((ValueError, TypeError), match="size must be"):
            im.area_resize(y, h, 4)


def test_list_images_wants_suffixes_with_their_dot(tmp_path):
    (tmp_path / "a.png").write_bytes(b"")
    with pytest.raises(TypeError, match=r"extensions must be a sequence of suffixes"):
        im.list_images(tmp_path, extensions=".png")
    with pytest.raises(ValueError, match=r"extensions must start with a dot"):
        im.list_images(tmp_path, extensions=["png"])
    assert im.list_images(tmp_path, extensions=[".PNG"]) == [tmp_path / "a.png"]


@pytest.mark.parametrize("bayer", ["xyzw", 1, ""])
def test_a_bad_bayer_pattern_is_the_argument_not_the_file(tmp_path, bayer):
    path = tmp_path / "raw.png"
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(path)
    with pytest.raises(ValueError, match=r"^bayer must be None or one of"):
        im.load_image(path, (4, 4), bayer=bayer)


# -- EXIF orientation ------------------------------------------------------------------------
# How the picture U (as a viewer shows it) is stored under each EXIF Orientation, from the
# tag's definition (which stored row and column are the visual top and left side), written
# independently of the decoder's table.
_STORED = {
    1: lambda u: u,
    2: lambda u: u[:, ::-1],  # column 0 is the visual right-hand side
    3: lambda u: u[::-1, ::-1],  # row 0 is the visual bottom, column 0 the right-hand side
    4: lambda u: u[::-1],  # row 0 is the visual bottom
    5: lambda u: u.swapaxes(0, 1),  # row 0 is the visual left-hand side, column 0 the top
    6: lambda u: np.rot90(u, 1),  # row 0 is the visual right-hand side, column 0 the top
    7: lambda u: u[::-1, ::-1].swapaxes(0, 1),  # row 0 right-hand side, column 0 the bottom
    8: lambda u: np.rot90(u, -1),  # row 0 is the visual left-hand side, column 0 the bottom
}


def _save_oriented(path, upright, orientation, **kwargs):
    exif = Image.Exif()
    exif[0x0112] = orientation
    stored = np.ascontiguousarray(_STORED[orientation](upright))
    Image.fromarray(stored).save(path, exif=exif, **kwargs)
    return path


@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_turns_the_frame_upright(tmp_path, orientation):
    # a phone's or a rotated camera's frame is stored sideways with a tag saying how to show it
    rng = np.random.default_rng(orientation)
    upright = rng.integers(0, 256, (24, 40, 3), dtype=np.uint8)
    want = im.load_image(_save(tmp_path / "upright.png", upright), size=(24, 40))
    got = im.load_image(_save_oriented(tmp_path / "a.png", upright, orientation), size=(24, 40))
    np.testing.assert_array_equal(got, want)
    # the same through load_images, and as Pillow's own exif_transpose shows the file
    np.testing.assert_array_equal(
        im.load_images([tmp_path / "a.png"], (24, 40), cache=False, progress=False)[0], want
    )
    from PIL import ImageOps

    shown = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "a.png")))
    np.testing.assert_array_equal(shown, upright)


def test_exif_orientation_of_a_jpeg(tmp_path):
    # the reader's case: a JPEG stored rotated with Orientation 6 read sideways
    x = np.linspace(0, 255, 64)
    upright = np.dstack([np.add.outer(np.linspace(0, 120, 32), x / 2)] * 3).astype(np.uint8)
    want = im.load_image(_save(tmp_path / "b.jpg", upright), size=(16, 32))
    stored = _save_oriented(tmp_path / "a.jpg", upright, 6, quality=95)
    assert Image.open(stored).size == (32, 64)  # (W, H): stored sideways
    np.testing.assert_allclose(im.load_image(stored, size=(16, 32)), want, atol=3 / 255)


@pytest.mark.parametrize("compression", [None, "tiff_deflate"])
@pytest.mark.parametrize("orientation", [3, 6, 8])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_a_tiff_turned_by_its_orientation_tag_is_read_upright(
    tmp_path, orientation, compression, channels
):
    # Pillow turns TIFFs itself while loading them; read from a path it memory-maps an
    # uncompressed one and, for orientations 5-8, garbles its pixels
    rng = np.random.default_rng(orientation)
    upright = rng.integers(0, 256, (24, 40, channels), dtype=np.uint8).squeeze()
    want = im.load_image(_save(tmp_path / "upright.png", upright), size=(24, 40))
    stored = np.ascontiguousarray(_STORED[orientation](upright))
    extra = {"compression": compression} if compression else {}
    Image.fromarray(stored).save(tmp_path / "a.tif", tiffinfo={274: orientation}, **extra)
    np.testing.assert_array_equal(im.load_image(tmp_path / "a.tif", size=(24, 40)), want)


def test_an_exif_block_that_cannot_be_read_is_read_as_stored_with_a_warning(tmp_path, caplog):
    # as Pillow reads such a JPEG (it drops the block at open): the frame loads, and a warning
    # names the file, since its orientation is unknown
    frame = np.arange(16, dtype=np.uint8).reshape(4, 4) * 10
    Image.fromarray(frame).save(tmp_path / "bad.png", exif=b"garbage!")
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        got = im.load_image(tmp_path / "bad.png", size=(4, 4))
    np.testing.assert_allclose(got, frame / 255, atol=1e-6)
    assert "bad.png: its EXIF metadata cannot be read" in caplog.text


def test_a_bayer_tiff_with_an_orientation_tag_is_refused(tmp_path):
    # Pillow turns a TIFF while loading it, before the mosaic could be demosaiced
    exif = Image.Exif()
    exif[0x0112] = 6
    mosaic = np.random.default_rng(1).integers(0, 256, (12, 20), dtype=np.uint8)
    Image.fromarray(mosaic).save(tmp_path / "raw.tif", exif=exif)
    with pytest.raises(im.ImageReadError, match=r"raw\.tif: a raw Bayer TIFF with an orientation"):
        im.load_image(tmp_path / "raw.tif", size=(20, 12), bayer="gbrg")
    # without the tag, or not a mosaic, it loads
    Image.fromarray(mosaic).save(tmp_path / "plain.tif")
    assert im.load_image(tmp_path / "plain.tif", size=(12, 20), bayer="gbrg").shape == (12, 20)
    assert im.load_image(tmp_path / "raw.tif", size=(20, 12)).shape == (20, 12)


def test_exif_orientation_of_a_bayer_mosaic_turns_it_after_demosaicing(tmp_path):
    # turning the mosaic itself would change its pattern (GBRG turned is no longer GBRG)
    rng = np.random.default_rng(3)
    mosaic = rng.integers(0, 256, (12, 20), dtype=np.uint8)
    flat = im.load_image(_save(tmp_path / "raw.png", mosaic), size=(12, 20), bayer="gbrg")
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(mosaic).save(tmp_path / "tagged.png", exif=exif)
    got = im.load_image(tmp_path / "tagged.png", size=(20, 12), bayer="gbrg")
    np.testing.assert_array_equal(got, np.rot90(flat, -1))  # 6: shown turned 90 degrees clockwise


def test_the_decode_version_is_in_the_cache_key_so_old_stacks_are_decoded_again(
    tmp_path, monkeypatch
):
    # a stack cached before orientation was applied must not be served: the cache key holds
    # a decode version of its own (the pre-processing version, written in model files, stays)
    paths = _folder(tmp_path / "imgs", n=2)
    cache = tmp_path / "cache"
    key = im._cache_key(paths, (32, 64), None)
    monkeypatch.setattr(im, "_DECODE_VERSION", im._DECODE_VERSION - 1)
    assert im._cache_key(paths, (32, 64), None) != key
    im.load_images(paths, cache=cache, progress=False)  # a cache written by the older decoder
    monkeypatch.undo()
    decoded = []
    real = im._decode
    monkeypatch.setattr(im, "_decode", lambda *a: decoded.append(a[0]) or real(*a))
    im.load_images(paths, cache=cache, progress=False)
    assert decoded == paths
    assert len(list(cache.glob("*.npz"))) == 2


# -- natural order -----------------------------------------------------------------------------
def test_natural_order_reads_decimal_fractions_as_decimals(tmp_path):
    # timestamps written with str(float): .05 comes before .1, not after .2
    stamps = [1600000000.0, 1600000000.05, 1600000000.1, 1600000000.15, 1600000000.2]
    for t in reversed(stamps):
        (tmp_path / f"{t}.png").write_bytes(b"")
    assert [p.name for p in im.list_images(tmp_path)] == [f"{t}.png" for t in stamps]
    names = ["frame1.png", "frame1.5.png", "frame2.png", "frame2.25.png", "frame10.png"]
    assert sorted(names[::-1], key=lambda n: im._natural_key(Path(n))) == names


def test_natural_order_reads_a_dotted_run_as_whole_numbers():
    # versions and addresses are not decimals: 1.10.0 comes after 1.2.3
    names = ["v1.2.3.png", "v1.10.0.png", "10.0.0.2.png", "10.0.0.10.png", "a.1.png", "a.10.png"]
    got = sorted(names[::-1], key=lambda n: im._natural_key(Path(n)))
    assert got == ["10.0.0.2.png", "10.0.0.10.png", "a.1.png", "a.10.png", "v1.2.3.png",
                   "v1.10.0.png"]  # fmt: skip


def test_an_order_that_a_fraction_decides_is_warned_about(tmp_path, caplog):
    # cam1.10: version 1.10 (after 1.2) or the decimal 1.1 (before)? Read as decimals, said
    for name in ("cam1.10.png", "cam1.2.png", "cam2.png"):
        (tmp_path / name).write_bytes(b"")
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        got = [p.name for p in im.list_images(tmp_path)]
    assert got == ["cam1.10.png", "cam1.2.png", "cam2.png"]
    assert "cam1.10.png before cam1.2.png as decimals, after as whole numbers" in caplog.text
    caplog.clear()
    for stamp in ("1600000000.100", "1600000000.200"):  # zero-padded: either reading agrees
        (tmp_path / "padded").mkdir(exist_ok=True)
        (tmp_path / "padded" / f"{stamp}.png").write_bytes(b"")
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        im.list_images(tmp_path / "padded")
    assert caplog.text == ""


def test_natural_order_breaks_ties_by_name_not_by_listing(tmp_path):
    import itertools

    names = ["001.png", "01.png", "1.0.png", "1.png", "A2.png", "a2.png", "b.png"]
    for name in names:
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in im.list_images(tmp_path)] == names
    for order in itertools.islice(itertools.permutations(names), 0, 5040, 97):
        assert sorted(order, key=lambda n: im._natural_key(Path(n))) == names


# -- 16-bit colour ------------------------------------------------------------------------------
def _png16(path, array, color_type):
    """A 16-bit PNG written by hand (Pillow writes no 16-bit colour): array uint16, (H, W) for
    gray (colour type 0) or (H, W, C) for gray+alpha (4), RGB (2) and RGBA (6)."""
    import struct
    import zlib

    h, w = array.shape[:2]
    raw = b"".join(b"\x00" + array[y].astype(">u2").tobytes() for y in range(h))

    def chunk(kind, data):
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", w, h, 16, color_type, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )
    return path


def _high_byte_warnings(caplog):
    return [
        r
        for r in caplog.records
        if r.name == "flyvpr.images" and r.levelname == "WARNING" and "high byte" in r.message
    ]


@pytest.mark.parametrize(
    "color_type, channels", [(2, 3), (6, 4), (4, 2)], ids=["rgb", "rgba", "la"]
)
def test_16bit_colour_is_named_in_one_warning_per_folder(tmp_path, caplog, color_type, channels):
    # Pillow reads 16-bit colour into 8 bits (its high byte): 12-bit data keeps 16 levels
    ramp = np.tile(np.arange(0, 4096, 4, dtype=np.uint16), (4, 1))  # 12-bit data
    colour = np.dstack([ramp] * channels)
    folder = tmp_path / "frames"
    folder.mkdir()
    paths = [_png16(folder / f"{i}.png", colour, color_type) for i in range(3)]
    _png16(folder / "3.png", ramp, 0)  # 16-bit gray: full precision, no warning
    paths.append(folder / "3.png")
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        out = im.load_images(paths, size=(4, 1024), cache=False, progress=False)
    assert len(np.unique(out[0])) == 16 and len(np.unique(out[3])) == 1024
    (record,) = _high_byte_warnings(caplog)  # one for the folder, not one per frame
    message = record.getMessage()
    assert message.startswith(f"{paths[0]} (and 2 more of the 4 frames): colour of more than 8")
    assert "16-bit gray, which keeps full precision, or as 8-bit colour" in message
    # frame by frame (a folder source): once per folder too
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        for p in paths:
            im.load_image(p, size=(4, 64))
    (record,) = _high_byte_warnings(caplog)
    assert record.getMessage().startswith(f"{paths[0]}: colour of more than 8 bits per sample")


def test_8bit_colour_and_16bit_gray_are_not_warned_about(tmp_path, caplog):
    paths = _folder(tmp_path / "imgs", n=2)
    paths.append(_png16(tmp_path / "imgs" / "gray16.png", np.full((8, 8), 4095, np.uint16), 0))
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        im.load_images(paths, cache=False, progress=False)
        im.load_image(paths[-1])
    assert not _high_byte_warnings(caplog)


# -- colour modes ------------------------------------------------------------------------------
def test_a_colour_mode_read_as_if_rgb_is_refused_by_name(tmp_path):
    rgb = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    Image.fromarray(rgb).convert("LAB").save(tmp_path / "lab.tif")
    assert Image.open(tmp_path / "lab.tif").mode == "LAB"
    expected = "lab.tif: colour mode LAB is not supported; convert the image to RGB or gray"
    with pytest.raises(im.ImageReadError, match=expected):
        im.load_image(tmp_path / "lab.tif")
    with pytest.raises(im.ImageReadError, match="colour mode HSV is not supported"):
        im._check_mode(tmp_path / "hsv.png", Image.new("HSV", (2, 2)))


def test_premultiplied_gray_alpha_is_read_as_its_gray(tmp_path):
    # a TIFF with associated alpha opens as "La": its gray divided by the alpha, alpha ignored
    la = Image.merge("LA", [Image.new("L", (4, 4), 100), Image.new("L", (4, 4), 128)])
    la.save(tmp_path / "la.tif")
    data = (tmp_path / "la.tif").read_bytes()
    unassociated = bytes.fromhex("52010300010000000200")  # ExtraSamples = 2
    assert data.count(unassociated) == 1
    (tmp_path / "la.tif").write_bytes(data.replace(unassociated, unassociated[:-2] + b"\x01\x00"))
    assert Image.open(tmp_path / "la.tif").mode == "La"
    np.testing.assert_allclose(im.load_image(tmp_path / "la.tif", (4, 4)), 199 / 255, atol=1e-6)


def test_every_mode_decoded_is_one_pillow_has():
    assert im._DECODED_MODES <= set(Image.MODES)
    assert {"LAB", "HSV"}.isdisjoint(im._DECODED_MODES)


# -- area_resize of any real dtype ---------------------------------------------------------------
@pytest.mark.parametrize(
    "dtype", [">f4", ">f8", "f2", ">u2", "<u2", "i2", ">i4", "u4", "i8", "int8", "bool", "f8"]
)
def test_area_resize_takes_every_real_dtype(dtype):
    rng = np.random.default_rng(0)
    top = 2 if dtype == "bool" else (100 if dtype == "int8" else 2000)  # exact in each dtype
    y = rng.integers(0, top, (37, 53))
    want = im.area_resize(y.astype(np.float32), 8, 16)
    got = im.area_resize(y.astype(dtype), 8, 16)
    assert got.dtype == np.float32 and got.shape == (8, 16)
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_area_resize_refuses_what_is_not_real_numbers():
    for bad in (np.ones((4, 4), complex), np.full((4, 4), "a"), np.empty((4, 4), object)):
        with pytest.raises(TypeError, match=f"y must hold real numbers; got dtype {bad.dtype}"):
            im.area_resize(bad, 2, 2)


# -- aspect ratios -------------------------------------------------------------------------------
@pytest.mark.parametrize("orientation", range(1, 9))
def test_upright_shape_reads_the_header_and_turns_by_the_tag(tmp_path, orientation):
    upright = np.zeros((24, 40), np.uint8)
    path = _save_oriented(tmp_path / "a.png", upright, orientation)
    assert im.upright_shape(path) == (24, 40)
    assert im.upright_shape(tmp_path / "missing.png") is None
    (tmp_path / "bad.png").write_bytes(b"not an image")
    assert im.upright_shape(tmp_path / "bad.png") is None


def test_same_aspect_within_one_percent():
    assert im.same_aspect((360, 640), (180, 320)) and im.same_aspect((100, 200), (100, 201))
    assert im.same_aspect((100, 200), (100, 202)) and not im.same_aspect((100, 200), (100, 203))
    assert not im.same_aspect((480, 640), (360, 640))
    assert im.same_aspect((200, 100), (201, 100)) and not im.same_aspect((203, 100), (200, 100))


def test_load_images_warns_once_of_frames_of_another_aspect_ratio(tmp_path, caplog):
    paths = []
    for i, shape in enumerate([(36, 64), (36, 64), (48, 64), (18, 32), (48, 64)]):
        paths.append(tmp_path / f"f{i}.png")
        Image.fromarray(np.full(shape, 50 * i, np.uint8)).save(paths[-1])
    with caplog.at_level("WARNING", logger="flyvpr"):
        out = im.load_images(paths, (32, 64), cache=False, progress=False)
    assert out.shape == (5, 32, 64)  # (squeezed all the same: a warning, not an error)
    (record,) = [r for r in caplog.records if "aspect ratio" in r.getMessage()]
    msg = record.getMessage()
    assert msg.startswith("2 of 5 images have another aspect ratio than the first, ")
    assert f"{paths[0]} (64x36)" in msg and f"the first of them being {paths[2]} (64x48)" in msg
    assert "resized to 64x32" in msg
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):
        im.load_images([paths[0], paths[1], paths[3]], (32, 64), cache=False, progress=False)
    assert not [r for r in caplog.records if "aspect ratio" in r.getMessage()]


def _low_range_warnings(caplog):
    return [r for r in caplog.records if "pixels whose values are all at most 255" in r.message]


def test_8bit_values_saved_as_16_or_32_bit_are_named_in_one_warning(tmp_path, caplog):
    # 8-bit data in a 16-bit PNG (Pillow's I;16) or a 32-bit TIFF (mode I) is read on the
    # 16-bit scale: nearly black.  Read as it is (nothing is guessed), with one warning.
    folder = tmp_path / "frames"
    folder.mkdir()
    ramp = np.tile(np.arange(0, 256, dtype=np.uint16), (4, 1))
    paths = [_png16(folder / f"{i}.png", ramp, 0) for i in range(2)]
    Image.fromarray(ramp.astype(np.int32)).save(folder / "2.tif")  # mode I
    paths.append(folder / "2.tif")
    assert Image.open(paths[2]).mode == "I"
    _png16(folder / "3.png", ramp * 200, 0)  # 16-bit data: no warning
    Image.fromarray(np.zeros((4, 256), np.uint16)).save(folder / "4.png")  # blank: none
    Image.fromarray(ramp.astype(np.uint8)).save(folder / "5.png")  # 8-bit: none
    paths += [folder / "3.png", folder / "4.png", folder / "5.png"]
    with caplog.at_level("WARNING", logger="flyvpr.images"):
        out = im.load_images(paths, size=(4, 256), cache=False, progress=False)
    assert out[0].max() == np.float32(255 / 65535) and out[5].max() == 1.0  # (as read)
    (record,) = _low_range_warnings(caplog)
    message = record.getMessage()
    assert message.startswith(f"{paths[0]} (and 2 more of the 6 frames): 16-bit integer pixels")
    assert "save the frames as 8-bit" in message
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr.images"):  # frame by frame: per folder
        for p in [paths[2], *paths]:
            im.load_image(p, size=(4, 64))
    (record,) = _low_range_warnings(caplog)
    assert record.getMessage().startswith(f"{paths[2]}: 32-bit integer pixels")
    assert not _high_byte_warnings(caplog)
