"""ROS 1 ``.bag`` and ROS 2 bags (``.db3`` / ``.mcap``) read with the pure-Python ``rosbags``.

Images come from one topic of type ``sensor_msgs/Image`` (encodings :data:`IMAGE_ENCODINGS`)
or ``sensor_msgs/CompressedImage`` (JPEG or PNG, decoded with Pillow).  Raw camera encodings
are read without demosaicing or colour conversion, since a 32x64 gray frame needs neither:

* Bayer mosaics (``bayer_rggb8``, ``bayer_bggr8``, ``bayer_gbrg8``, ``bayer_grbg8`` and their
  16-bit forms ``bayer_*16``): each 2x2 cell becomes one gray value, the BT.601 luma of its
  colours, ``0.299 R + 0.587 (G1 + G2) / 2 + 0.114 B`` (the weights of
  :func:`flyvpr.images.to_gray`), so the frame is gray at half the resolution.  The height and
  width must be even (whole cells).
* YUV 4:2:2 (``yuv422`` = UYVY and ``yuv422_yuy2`` = YUYV; also their newer ROS 2 names
  ``uyvy`` and ``yuyv``): the Y (luma) samples are the gray frame, at full resolution and as
  the camera sent them (no range expansion); the width must be even (pixel pairs share U, V).

The generic ``8UC3`` and ``8UC4`` are read as ``bgr8`` and ``bgra8``, as cv_bridge reads
them.  Every raw image honours ``step`` (bytes per row, padding included) and, for 16 bits,
``is_bigendian``.  A frame's timestamp is
its header stamp, or the time the bag recorded it when the stamp is zero.  Positions come from a
``sensor_msgs/NavSatFix`` topic (latitude/longitude to local metres, equirectangular about the
first fix; messages without a fix, ``status.status < 0``, are skipped) or a
``nav_msgs/Odometry`` topic (pose position x, y); messages with a non-finite position are
skipped too, and how many is logged as a warning.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from ..images import _LUMA, resize_area, to_gray
from .base import Decoder, RecordingError, Source, _reason, require_extra

__all__ = ["BagSource", "IMAGE_ENCODINGS", "BAG_EXTENSIONS", "read_bag_positions"]

logger = logging.getLogger(__name__)

#: file suffixes read as bags (a ROS 2 bag may also be given as its folder)
BAG_EXTENSIONS = (".bag", ".db3", ".mcap")
_IMAGE = ("sensor_msgs/msg/Image", "sensor_msgs/Image")
_COMPRESSED = ("sensor_msgs/msg/CompressedImage", "sensor_msgs/CompressedImage")
_NAVSAT = ("sensor_msgs/msg/NavSatFix", "sensor_msgs/NavSatFix")
_ODOMETRY = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
#: the 2x2 cells of the Bayer encodings, read row by row
_BAYER_CELLS = ("rggb", "bggr", "gbrg", "grbg")
#: raw encodings read: name (lower case) -> (numpy dtype of a sample, samples per pixel,
#: layout): the channel order of colour images, the 2x2 cell of a Bayer mosaic row by row
#: (``"rggb"``: R G over G B), or the byte order of a YUV 4:2:2 pixel pair
IMAGE_ENCODINGS = {
    "mono8": ("u1", 1, None),
    "8uc1": ("u1", 1, None),
    "mono16": ("u2", 1, None),
    "rgb8": ("u1", 3, "rgb"),
    "bgr8": ("u1", 3, "bgr"),
    # generic OpenCV types as drivers publish colour frames; cv_bridge reads them as bgr8 and
    # bgra8 (OpenCV's channel order).  16UC1 is not here: it is the depth-image encoding
    # (REP 118, millimetres), not a camera frame
    "8uc3": ("u1", 3, "bgr"),
    "rgba8": ("u1", 4, "rgb"),
    "bgra8": ("u1", 4, "bgr"),
    "8uc4": ("u1", 4, "bgr"),
    "rgb16": ("u2", 3, "rgb"),
    "bgr16": ("u2", 3, "bgr"),
    **{
        f"bayer_{cell}{bits}": (dtype, 1, cell)
        for bits, dtype in (("8", "u1"), ("16", "u2"))
        for cell in _BAYER_CELLS
    },
    "yuv422": ("u1", 2, "uyvy"),
    "uyvy": ("u1", 2, "uyvy"),
    "yuv422_yuy2": ("u1", 2, "yuyv"),
    "yuyv": ("u1", 2, "yuyv"),
}
#: mean Earth radius (m) for the equirectangular projection of NavSatFix positions
EARTH_RADIUS_M = 6_371_000.0


def _bag_paths(path: Path) -> list[Path]:
    """What ``AnyReader`` opens: a ROS 1 file, or a ROS 2 bag's folder (with metadata.yaml)."""
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            raise RecordingError(f"bag {path}: a ROS 2 bag folder needs its metadata.yaml")
        return [path]
    if not path.is_file():
        raise FileNotFoundError(f"bag not found: {path}")
    if path.suffix.lower() in (".db3", ".mcap"):
        if not (path.parent / "metadata.yaml").is_file():
            raise RecordingError(
                f"bag {path}: a ROS 2 bag file needs the metadata.yaml of its folder"
            )
        return [path.parent]
    return [path]


class _Bag:
    """An open bag with flyvpr's error messages."""

    def __init__(self, path: Path):
        self.path = path
        hl = require_extra("rosbags.highlevel")
        self._errors = _rosbags_errors()
        paths = _bag_paths(path)  # (its own errors name the bag as they are: not re-wrapped)
        try:
            self.reader = hl.AnyReader(paths)
            self.reader.open()
        except self._errors as exc:
            raise RecordingError(f"bag {path}: not a readable ROS bag ({_reason(exc)})") from None

    def topics(self, types) -> dict[str, str]:
        return {c.topic: c.msgtype for c in self.reader.connections if c.msgtype in types}

    def pick(self, topic: str | None, types, what: str, option: str):
        found = self.topics(types)
        if topic is None:
            if len(found) != 1:
                listing = ", ".join(f"{t} ({m})" for t, m in sorted(found.items())) or "none"
                raise RecordingError(
                    f"bag {self.path}: name the {what} topic with {option}; {what} topics in "
                    f"the bag: {listing}"
                )
            topic = next(iter(found))
        if topic not in found:
            all_topics = {c.topic: c.msgtype for c in self.reader.connections}
            extra = f" (it has type {all_topics[topic]})" if topic in all_topics else ""
            listing = ", ".join(sorted(found)) or "none"
            raise RecordingError(
                f"bag {self.path}: no {what} topic {topic!r}{extra}; {what} topics in the bag: "
                f"{listing}"
            )
        return [c for c in self.reader.connections if c.topic == topic]

    def messages(self, connections):
        try:
            for conn, logtime, raw in self.reader.messages(connections=connections):
                try:
                    msg = self.reader.deserialize(raw, conn.msgtype)
                except Exception as exc:  # rosbags raises several kinds on damaged payloads
                    raise RecordingError(
                        f"bag {self.path}: damaged {conn.msgtype} message on {conn.topic} "
                        f"({_reason(exc)})"
                    ) from None
                yield conn, logtime, msg
        except self._errors as exc:
            raise RecordingError(
                f"bag {self.path}: damaged or truncated ({_reason(exc)})"
            ) from None

    def close(self):
        self.reader.close()


def _rosbags_errors() -> tuple:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as Reader1Error
    from rosbags.rosbag2 import ReaderError as Reader2Error

    return (AnyReaderError, Reader1Error, Reader2Error, OSError, EOFError, KeyError, ValueError)


def _stamp(msg, logtime: int) -> float:
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is not None:
        sec = getattr(stamp, "sec", getattr(stamp, "secs", 0))
        nsec = getattr(stamp, "nanosec", getattr(stamp, "nsecs", 0))
        if sec or nsec:
            return float(sec) + 1e-9 * float(nsec)
    return 1e-9 * float(logtime)


class BagSource(Source):
    """Image messages of one topic of a ROS 1 or ROS 2 bag.

    Parameters
    ----------
    path : str or Path
        A ``.bag`` file, a ROS 2 bag folder, or its ``.db3`` / ``.mcap`` file.
    topic : str, optional
        Image topic; when omitted the bag must have exactly one.
    """

    kind = "bag"

    def __init__(self, path, topic: str | None = None):
        super().__init__(path)
        bag = _Bag(self.path)
        try:
            conns = bag.pick(topic, _IMAGE + _COMPRESSED, "image", "topic=TOPIC")
        finally:
            bag.close()
        self.topic = conns[0].topic

    def describe(self) -> str:
        return f"bag {self.path} topic {self.topic}"

    def _frames(self) -> Iterator[tuple[int, float, Decoder]]:
        bag = _Bag(self.path)
        try:
            conns = bag.pick(self.topic, _IMAGE + _COMPRESSED, "image", "topic=TOPIC")
            for index, (conn, logtime, msg) in enumerate(bag.messages(conns)):
                yield index, _stamp(msg, logtime), self._decoder(conn.msgtype, msg, index)
        finally:
            bag.close()

    def _decoder(self, msgtype: str, msg, index: int):
        where = f"bag {self.path} topic {self.topic} message {index}"

        def decode(size):
            gray = _compressed_gray(msg, where) if msgtype in _COMPRESSED else _raw_gray(msg, where)
            return resize_area(gray, size)

        return decode


def _raw_gray(msg, where: str) -> np.ndarray:
    enc = str(msg.encoding).lower()
    if enc not in IMAGE_ENCODINGS:
        raise RecordingError(
            f"{where}: unsupported image encoding {msg.encoding!r} (flyvpr reads "
            f"{', '.join(IMAGE_ENCODINGS)}; depth and float images are not camera frames)"
        )
    kind, channels, layout = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = int(kind[1])
    row_bytes = w * channels * itemsize
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if h < 1 or w < 1:
        raise RecordingError(f"{where}: {enc} image of {h}x{w} pixels holds no pixel")
    if step < row_bytes:
        raise RecordingError(
            f"{where}: {h}x{w} {enc} image with step {step}: a row needs at least "
            f"{row_bytes} bytes ({w} pixels x {channels * itemsize} bytes)"
        )
    if data.size < h * step:
        raise RecordingError(
            f"{where}: {h}x{w} {enc} image with step {step} needs {h * step} bytes of data; "
            f"got {data.size} (truncated)"
        )
    if layout in _BAYER_CELLS and (h % 2 or w % 2):
        raise RecordingError(
            f"{where}: a {enc} image needs an even height and width (whole 2x2 Bayer "
            f"cells); got {h}x{w}"
        )
    if layout in ("uyvy", "yuyv") and w % 2:
        raise RecordingError(
            f"{where}: a {enc} image needs an even width (pixel pairs share U and V); got {h}x{w}"
        )
    rows = data[: h * step].reshape(h, step)[:, :row_bytes]
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    pixels = (
        rows.copy().view(dtype).reshape(h, w, channels)
        if itemsize > 1
        else rows.reshape(h, w, channels)
    )
    pixels = pixels.astype(pixels.dtype.newbyteorder("="), copy=False)
    if layout in _BAYER_CELLS:
        return _bayer_gray(pixels[:, :, 0], layout)
    if layout == "uyvy":  # U Y0 V Y1: each pixel is (chroma, luma)
        return to_gray(pixels[:, :, 1])
    if layout == "yuyv":  # Y0 U Y1 V: each pixel is (luma, chroma)
        return to_gray(pixels[:, :, 0])
    if layout == "bgr":
        pixels = pixels[:, :, 2::-1]
    elif channels == 4:
        pixels = pixels[:, :, :3]
    return to_gray(pixels[:, :, 0] if channels == 1 else pixels)


def _bayer_gray(mosaic: np.ndarray, cell: str) -> np.ndarray:
    """One gray value per 2x2 cell of a Bayer mosaic (even H, W): half-resolution luma.

    Parameters
    ----------
    mosaic : ndarray, shape (H, W), uint8 or uint16
    cell : {'rggb', 'bggr', 'gbrg', 'grbg'}
        The cell's colours row by row (``'rggb'``: R G over G B).

    Returns
    -------
    ndarray, shape (H // 2, W // 2), float32 in [0, 1]
        ``0.299 R + 0.587 (G1 + G2) / 2 + 0.114 B`` of each cell.
    """
    m = to_gray(mosaic)
    quarters = [m[0::2, 0::2], m[0::2, 1::2], m[1::2, 0::2], m[1::2, 1::2]]
    greens = [q for q, colour in zip(quarters, cell, strict=True) if colour == "g"]
    red, blue = quarters[cell.index("r")], quarters[cell.index("b")]
    gray = _LUMA[0] * red + _LUMA[1] * (0.5 * (greens[0] + greens[1])) + _LUMA[2] * blue
    # the weights sum to 1: a weighted mean in [0, 1] but for rounding
    return np.clip(gray, 0.0, 1.0).astype(np.float32, copy=False)


def _compressed_gray(msg, where: str) -> np.ndarray:
    try:
        with Image.open(io.BytesIO(np.asarray(msg.data, dtype=np.uint8).tobytes())) as img:
            img.load()
            arr = np.array(img if img.mode in ("L", "I;16", "RGB", "RGBA") else img.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise RecordingError(
            f"{where}: compressed image (format {msg.format!r}) is not a readable JPEG or PNG "
            f"({_reason(exc)})"
        ) from None
    return to_gray(arr)


def read_bag_positions(path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (n,) and local positions (n, 2) in metres from a NavSatFix or Odometry topic.

    NavSatFix messages without a fix (``status.status < 0``: ``STATUS_NO_FIX``, whose
    latitude and longitude are placeholders such as 0, 0) and messages with a non-finite
    position are skipped; how many is logged as a warning.  NavSatFix positions are metres
    east and north of the first fix (equirectangular, scaled by the cosine of its latitude).

    Raises
    ------
    RecordingError
        If the bag has no such topic (the message lists the position topics it has) or no
        usable position on it.
    """
    bag = _Bag(Path(path))
    try:
        conns = bag.pick(topic, _NAVSAT + _ODOMETRY, "position", "position_topic=TOPIC")
        navsat = conns[0].msgtype in _NAVSAT
        stamps, values, n_messages, n_no_fix = [], [], 0, 0
        for conn, logtime, msg in bag.messages(conns):
            n_messages += 1
            if conn.msgtype in _NAVSAT:
                if int(msg.status.status) < 0:  # STATUS_NO_FIX (-1), STATUS_UNKNOWN (-2)
                    n_no_fix += 1
                    continue
                values.append((msg.latitude, msg.longitude))
            else:
                p = msg.pose.pose.position
                values.append((p.x, p.y))
            stamps.append(_stamp(msg, logtime))
    finally:
        bag.close()
    xy = np.asarray(values, dtype=np.float64).reshape(-1, 2)
    keep = np.isfinite(xy).all(axis=1)
    n_not_finite = int(np.count_nonzero(~keep))
    t, xy = np.asarray(stamps, np.float64)[keep], xy[keep]
    skipped = []
    if n_no_fix:
        skipped.append(f"{n_no_fix} without a fix (status < 0)")
    if n_not_finite:
        skipped.append(f"{n_not_finite} with a non-finite position")
    if len(t) == 0:
        why = f" ({n_messages} messages: {', '.join(skipped)})" if skipped else ""
        raise RecordingError(f"bag {path} topic {topic}: no usable position{why}")
    if skipped:
        logger.warning(
            "bag %s topic %s: skipped %s of %d position messages",
            path, topic, " and ".join(skipped), n_messages,
        )  # fmt: skip
    if navsat:
        lat0, lon0 = np.radians(xy[0])
        lat, lon = np.radians(xy[:, 0]), np.radians(xy[:, 1])
        xy = np.stack(
            [EARTH_RADIUS_M * (lon - lon0) * np.cos(lat0), EARTH_RADIUS_M * (lat - lat0)], axis=1
        )
    return t, xy
