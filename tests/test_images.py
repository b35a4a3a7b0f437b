import os

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
