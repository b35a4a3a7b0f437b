"""Raw camera encodings of ``sensor_msgs/Image`` in bags: Bayer mosaics and YUV 4:2:2."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("rosbags")

from flyvpr.cli import main  # noqa: E402
from flyvpr.images import to_gray  # noqa: E402
from flyvpr.sources import RecordingError, open_source  # noqa: E402
from flyvpr.sources.rosbag import IMAGE_ENCODINGS, _raw_gray  # noqa: E402
from flyvpr.sources.writers import write_bag  # noqa: E402

#: the bag kinds write_bag makes: ROS 1 .bag, ROS 2 with .db3 and with .mcap storage
BAG_KINDS = {
    "ros1": {"version": 1},
    "ros2-sqlite3": {"version": 2, "storage": "sqlite3"},
    "ros2-mcap": {"version": 2, "storage": "mcap"},
}
CELLS = ("rggb", "bggr", "gbrg", "grbg")
BAYER = [f"bayer_{c}{bits}" for bits in ("8", "16") for c in CELLS]
YUV = {"yuv422": "uyvy", "uyvy": "uyvy", "yuv422_yuy2": "yuyv", "yuyv": "yuyv"}
H, W = 12, 16  # even: whole Bayer cells and YUV pixel pairs


def _bag(tmp_path, kind, frames, encoding, **kwargs):
    name = "rec.bag" if BAG_KINDS[kind]["version"] == 1 else "rec"
    return write_bag(tmp_path / name, frames, encoding=encoding, **BAG_KINDS[kind], **kwargs)


def _gray(frames) -> np.ndarray:
    return np.stack([to_gray(f) for f in frames])


def _decoded(path, size):
    """Every frame of the bag, decoded at ``size`` (the decoder's own size: no resize)."""
    return open_source(path).read_all(size).images


def _bayer_reference(mosaic: np.ndarray, cell: str) -> np.ndarray:
    """A slow, obviously correct binning: one loop over the cells, float64."""
    m = mosaic.astype(np.float64) / (255.0 if mosaic.dtype == np.uint8 else 65535.0)
    out = np.empty((m.shape[0] // 2, m.shape[1] // 2))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            y, x = 2 * i, 2 * j
            block = [m[y, x], m[y, x + 1], m[y + 1, x], m[y + 1, x + 1]]
            colours = dict.fromkeys("rb", 0.0)
            greens = []
            for value, colour in zip(block, cell, strict=True):
                if colour == "g":
                    greens.append(value)
                else:
                    colours[colour] = value
            green = (greens[0] + greens[1]) / 2
            out[i, j] = 0.299 * colours["r"] + 0.587 * green + 0.114 * colours["b"]
    return out


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(0)
    # colour that is constant over each 2x2 cell: binning it gives exactly its luma
    half = rng.integers(0, 256, (3, H // 2, W // 2, 3), dtype=np.uint8)
    cells = np.repeat(np.repeat(half, 2, axis=1), 2, axis=2)
    gray = rng.integers(0, 256, (3, H, W), dtype=np.uint8)
    rgb = rng.integers(0, 256, (3, H, W, 3), dtype=np.uint8)
    return {"half": half, "cells": cells, "gray": gray, "rgb": rgb}


def test_the_encodings_are_listed():
    for name in [*BAYER, *YUV]:
        assert name in IMAGE_ENCODINGS


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("encoding", BAYER)
def test_bayer_cells_bin_to_their_luma(tmp_path, kind, encoding, images):
    got = _decoded(_bag(tmp_path, kind, images["cells"], encoding), (H // 2, W // 2))
    assert got.shape == (3, H // 2, W // 2) and got.dtype == np.float32
    np.testing.assert_allclose(got, _gray(images["half"]), atol=1e-6)


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("encoding", BAYER)
def test_bayer_gray_frame_matches_a_loop(tmp_path, kind, encoding, images):
    from flyvpr.sources.writers import _bayer_mosaic

    cell = encoding[6:10]
    got = _decoded(_bag(tmp_path, kind, images["gray"], encoding), (H // 2, W // 2))
    for frame, decoded in zip(images["gray"], got, strict=True):
        # a gray scene: the sensor sees the same value through every filter
        mosaic = _bayer_mosaic(np.repeat(frame[:, :, None], 3, axis=2), cell)
        np.testing.assert_array_equal(mosaic, frame)
        np.testing.assert_allclose(decoded, _bayer_reference(mosaic, cell), atol=1e-6)


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("encoding", YUV)
def test_yuv422_gray_frame_is_its_y(tmp_path, kind, encoding, images):
    got = _decoded(_bag(tmp_path, kind, images["gray"], encoding), (H, W))
    np.testing.assert_array_equal(got, _gray(images["gray"]))


@pytest.mark.parametrize("kind", BAG_KINDS)
@pytest.mark.parametrize("encoding", YUV)
def test_yuv422_colour_frame_reads_its_luma(tmp_path, kind, encoding, images):
    got = _decoded(_bag(tmp_path, kind, images["rgb"], encoding), (H, W))
    # Y is the BT.601 luma rounded to 8 bits: within half a step of the exact value
    np.testing.assert_allclose(got, _gray(images["rgb"]), atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("encoding", ["bayer_gbrg16", "mono16", "rgb16", "bgr16"])
@pytest.mark.parametrize("bigendian", [False, True])
def test_sixteen_bits_in_either_byte_order(tmp_path, encoding, bigendian, images):
    frames = images["gray"] if encoding == "mono16" else images["cells"]
    path = _bag(tmp_path, "ros1", frames, encoding, bigendian=bigendian)
    if encoding.startswith("bayer"):
        size, expected = (H // 2, W // 2), _gray(images["half"])
    else:
        size, expected = (H, W), _gray(frames)
    np.testing.assert_allclose(_decoded(path, size), expected, atol=1e-6)


@pytest.mark.parametrize(
    "encoding", ["bayer_rggb8", "bayer_bggr16", "yuv422", "yuv422_yuy2", "mono8"]
)
@pytest.mark.parametrize("padding", [1, 7])
def test_row_padding_is_skipped(tmp_path, encoding, padding, images):
    bayer = encoding.startswith("bayer")
    frames = images["cells"] if bayer else images["gray"]
    padded = _decoded(_bag(tmp_path, "ros1", frames, encoding, padding=padding), (H // 2, W // 2))
    (tmp_path / "plain").mkdir()
    plain = _decoded(_bag(tmp_path / "plain", "ros1", frames, encoding), (H // 2, W // 2))
    np.testing.assert_array_equal(padded, plain)


def test_localize_a_bayer_bag_end_to_end(tmp_path, capsys):
    from flyvpr.synthetic import make_route

    route = make_route(16, size=(64, 128), conditions=("summer", "winter"), random_state=2)
    bags = {
        season: write_bag(tmp_path / f"{season}.bag", route.images[season], version=1,
                          encoding="bayer_gbrg8")
        for season in ("summer", "winter")
    }  # fmt: skip
    out = tmp_path / "where.csv"
    assert main(["map", str(bags["summer"]), "--out", str(tmp_path / "r.map"), "-q"]) == 0
    assert main(["localize", "--map", str(tmp_path / "r.map"), str(bags["winter"]),
                 "--out", str(out), "-q"]) == 0  # fmt: skip
    assert len(out.read_text().splitlines()) == 17


# -- bad input -----------------------------------------------------------------------------------
def _message(encoding, h, w, step=None, data=None, bigendian=0):
    per_pixel = {"u1": 1, "u2": 2}[IMAGE_ENCODINGS[encoding][0]] * IMAGE_ENCODINGS[encoding][1]
    step = w * per_pixel if step is None else step
    data = np.zeros(h * step, np.uint8) if data is None else data
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=step, data=data, is_bigendian=bigendian
    )


WHERE = "bag d.bag topic /cam message 4"


@pytest.mark.parametrize("encoding", ["bayer_rggb8", "bayer_grbg16"])
@pytest.mark.parametrize(("h", "w"), [(5, 8), (6, 9), (7, 7)])
def test_bayer_odd_sizes_are_refused(encoding, h, w):
    with pytest.raises(
        RecordingError,
        match=rf"{WHERE}: a {encoding} image needs an even height and width .*; got {h}x{w}",
    ):
        _raw_gray(_message(encoding, h, w), WHERE)


@pytest.mark.parametrize("encoding", list(YUV))
def test_yuv422_odd_width_is_refused(encoding):
    with pytest.raises(RecordingError, match=rf"{WHERE}: a {encoding} image needs an even width"):
        _raw_gray(_message(encoding, 4, 5), WHERE)


@pytest.mark.parametrize("encoding", ["bayer_bggr8", "bayer_bggr16", "yuv422", "yuv422_yuy2"])
def test_truncated_data_is_refused(encoding):
    full = _message(encoding, 4, 6)
    short = _message(encoding, 4, 6, data=full.data[:-1])
    with pytest.raises(
        RecordingError,
        match=rf"{WHERE}: 4x6 {encoding} image with step {full.step} needs {full.data.size} "
        rf"bytes of data; got {full.data.size - 1} \(truncated\)",
    ):
        _raw_gray(short, WHERE)


@pytest.mark.parametrize(("encoding", "row"), [("bayer_rggb16", 12), ("yuv422", 12)])
def test_step_shorter_than_a_row_is_refused(encoding, row):
    with pytest.raises(RecordingError, match=rf"step {row - 1}: a row needs at least {row} bytes"):
        _raw_gray(_message(encoding, 4, 6, step=row - 1), WHERE)


def test_empty_image_is_refused():
    with pytest.raises(RecordingError, match=rf"{WHERE}: bayer_rggb8 image of 0x4 pixels"):
        _raw_gray(_message("bayer_rggb8", 0, 4), WHERE)


def test_odd_bayer_bag_through_the_cli(tmp_path, capsys):
    frames = np.zeros((2, 5, 8), np.uint8)
    bag = write_bag(tmp_path / "odd.bag", frames, version=1, encoding="bayer_rggb8")
    code = main(["map", str(bag), "--out", str(tmp_path / "r.map"), "-q"])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1
    assert f"bag {bag} topic /camera/image message 0: a bayer_rggb8 image needs an even" in err
    assert not (tmp_path / "r.map").exists()


def test_writer_refuses_odd_yuv_width(tmp_path):
    with pytest.raises(ValueError, match="yuyv frames need an even width"):
        write_bag(tmp_path / "o.bag", np.zeros((1, 4, 5), np.uint8), version=1, encoding="yuyv")
    assert list(tmp_path.iterdir()) == []


# -- generic OpenCV types: 8UC3 and 8UC4 are cv_bridge's bgr8 and bgra8 --------------------------
def _colour_message(encoding, rgb, *, step=None):
    """A raw message of ``rgb`` (H, W, 3) in OpenCV's channel order: BGR, plus opaque alpha
    for four channels."""
    h, w = rgb.shape[:2]
    pixels = rgb[:, :, ::-1]
    if encoding.lower() in ("8uc4", "bgra8"):
        pixels = np.concatenate([pixels, np.full((h, w, 1), 255, np.uint8)], axis=2)
    rows = np.ascontiguousarray(pixels).reshape(h, -1)
    if step is not None:
        rows = np.concatenate([rows, np.zeros((h, step - rows.shape[1]), np.uint8)], axis=1)
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=rows.shape[1], data=rows.reshape(-1),
        is_bigendian=0,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("encoding", "alias"),
    [("8UC3", "bgr8"), ("8uc3", "bgr8"), ("8UC4", "bgra8"), ("8uc4", "bgra8")],
)
def test_cv_type_colour_encodings_read_as_bgr(encoding, alias, images):
    rgb = images["rgb"][0]
    assert IMAGE_ENCODINGS[encoding.lower()] == IMAGE_ENCODINGS[alias]
    got = _raw_gray(_colour_message(encoding, rgb), WHERE)
    np.testing.assert_array_equal(got, _raw_gray(_colour_message(alias, rgb), WHERE))
    np.testing.assert_allclose(got, to_gray(rgb), atol=1e-6)
    # the step is honoured as for any raw image
    padded = _colour_message(encoding, rgb, step=rgb.shape[1] * 4 + 5)
    np.testing.assert_array_equal(_raw_gray(padded, WHERE), got)


def test_cv_type_colour_bag_through_the_cli(tmp_path, capsys, images):
    # an 8UC3 bag as a driver writes it (rosbags directly: BGR bytes labelled 8UC3)
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    bag = tmp_path / "c.bag"
    with Writer(bag) as w:
        conn = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        for i, rgb in enumerate(images["rgb"]):
            m = _colour_message("8UC3", rgb)
            stamp = T["builtin_interfaces/msg/Time"](sec=100 + i, nanosec=0)
            msg = T["sensor_msgs/msg/Image"](
                header=T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="cam"),
                height=m.height, width=m.width, encoding="8UC3", is_bigendian=0, step=m.step,
                data=m.data,
            )  # fmt: skip
            w.write(conn, (100 + i) * 10**9, ts.serialize_ros1(msg, "sensor_msgs/msg/Image"))
    np.testing.assert_allclose(_decoded(bag, (H, W)), _gray(images["rgb"]), atol=1e-6)
    assert main(["map", str(bag), "--out", str(tmp_path / "r.map"), "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_depth_encoding_16uc1_stays_refused():
    # 16UC1 is REP 118's depth image (millimetres), not a camera frame: not read as mono16
    assert "16uc1" not in IMAGE_ENCODINGS
    depth = SimpleNamespace(
        encoding="16UC1", height=4, width=6, step=12, data=np.zeros(48, np.uint8), is_bigendian=0
    )
    with pytest.raises(RecordingError, match=rf"{WHERE}: unsupported image encoding '16UC1'"):
        _raw_gray(depth, WHERE)
