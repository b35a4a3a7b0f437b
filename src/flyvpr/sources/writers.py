"""Writing frames as recordings: a video file (PyAV) or a ROS 1 / ROS 2 bag (rosbags).

Used to turn the built-in synthetic route into the kinds of recording a robot makes (the
tests and the speed benchmark do), and to convert image folders for other tools.  Both
writers go through :func:`flyvpr._io.atomic_open`-style temporary names, so a failed write
leaves nothing behind.
"""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from .._io import _temporary_name
from .base import require_extra

__all__ = ["write_video", "write_bag"]

_CONTAINERS = {".mp4": "mp4", ".m4v": "mp4", ".mkv": "matroska", ".avi": "avi", ".mov": "mov"}


def _uint8(frames) -> np.ndarray:
    a = np.asarray(frames)
    if a.dtype != np.uint8:
        a = np.clip(np.rint(np.asarray(a, np.float64) * 255.0), 0, 255).astype(np.uint8)
    if a.ndim not in (3, 4) or (a.ndim == 4 and a.shape[3] != 3):
        raise ValueError(f"frames must have shape (n, H, W) or (n, H, W, 3); got {a.shape}")
    return a


def _temporary(path: Path) -> Path:
    """The temporary file beside ``path``: the short name ``flyvpr._io``'s atomic writes use
    (fits for any target name up to the file system's limit), with the target's suffix, from
    which the writers pick the container."""
    return path.with_name(_temporary_name(path.name) + path.suffix[:16])


def _discard(tmp: Path) -> None:
    if tmp.is_dir():
        shutil.rmtree(tmp, ignore_errors=True)
    elif tmp.exists():
        tmp.unlink()


def write_video(path, frames, *, fps: float = 10.0, codec: str = "libx264", crf: int = 18):
    """Encode frames (gray or RGB, uint8 or float in [0, 1]) as a video file.

    Parameters
    ----------
    path : str or Path
        ``.mp4``, ``.mkv``, ``.avi`` ...; the container follows the suffix.
    frames : array-like of shape (n, H, W) or (n, H, W, 3), or an iterable of frames
        H and W must be even (4:2:0 chroma).  An iterable (e.g. a generator) is encoded as it
        comes, so a long video never needs all its frames in memory.
    codec : str
        ``libx264`` (H.264, full-range 4:2:0) or ``mpeg4``.
    crf : int
        x264's constant rate factor (0 = lossless, 18 = visually lossless).
    """
    from fractions import Fraction

    av = require_extra("av")
    path = Path(path)
    tmp = _temporary(path)
    stream = None
    try:
        with av.open(str(tmp), "w", format=_CONTAINERS.get(path.suffix.lower())) as c:
            for frame in frames:
                a = _uint8(np.asarray(frame)[None])[0]
                if stream is None:
                    h, w = a.shape[:2]
                    if h % 2 or w % 2:
                        raise ValueError(f"video frames need an even height and width; got {h}x{w}")
                    stream = c.add_stream(codec, rate=Fraction(fps).limit_denominator(1000))
                    # full-range 4:2:0 with x264, so 8-bit gray survives without a range squeeze
                    pix_fmt = "yuvj420p" if codec == "libx264" else "yuv420p"
                    stream.width, stream.height, stream.pix_fmt = w, h, pix_fmt
                    if codec == "libx264":
                        stream.options = {"crf": str(crf), "preset": "veryfast"}
                    else:  # no crf: a generous bit rate (4 bits per pixel per second)
                        stream.bit_rate = int(4 * w * h * fps)
                fmt = "gray" if a.ndim == 2 else "rgb24"
                c.mux(stream.encode(av.VideoFrame.from_ndarray(a, format=fmt)))
            if stream is None:
                raise ValueError(f"{path}: no frames to write")
            c.mux(stream.encode(None))
        os.replace(tmp, path)
    except BaseException:
        _discard(tmp)
        raise
    return path


def _header(ts, ros1: bool, t: float, frame_id: str = "camera"):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    sec = int(np.floor(t))
    stamp = Time(sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)
    if ros1:
        return Header(seq=0, stamp=stamp, frame_id=frame_id)
    return Header(stamp=stamp, frame_id=frame_id)


#: BT.601 full-range (JPEG) RGB -> Y, U, V, as 8-bit cameras and ``yuvj`` formats use it
_YUV = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])


def _bayer_mosaic(rgb: np.ndarray, cell: str) -> np.ndarray:
    """What a Bayer sensor records of ``rgb`` (H, W, 3): each photosite keeps one colour."""
    mosaic = np.empty(rgb.shape[:2], rgb.dtype)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        mosaic[dy::2, dx::2] = rgb[dy::2, dx::2, "rgb".index(cell[k])]
    return mosaic


def _yuv422(frame: np.ndarray, layout: str) -> np.ndarray:
    """Pixel pairs of ``frame`` (even width) as UYVY or YUYV bytes, shape (H, W, 2).

    A gray frame is its own Y with neutral chroma (128); an RGB frame gets BT.601 full-range
    Y, and U, V averaged over each pixel pair.
    """
    h, w = frame.shape[:2]
    if w % 2:
        raise ValueError(f"{layout} frames need an even width (pixel pairs); got {h}x{w}")
    if frame.ndim == 2:
        y = frame
        u = v = np.full((h, w // 2), 128, np.uint8)
    else:
        yuv = frame.astype(np.float64) @ _YUV.T + [0.0, 128.0, 128.0]
        y = np.clip(np.rint(yuv[:, :, 0]), 0, 255).astype(np.uint8)
        pairs = yuv[:, :, 1:].reshape(h, w // 2, 2, 2).mean(axis=2)
        u, v = np.clip(np.rint(pairs), 0, 255).astype(np.uint8).transpose(2, 0, 1)
    out = np.empty((h, w, 2), np.uint8)
    luma, chroma = (1, 0) if layout == "uyvy" else (0, 1)
    out[:, :, luma] = y
    out[:, 0::2, chroma] = u
    out[:, 1::2, chroma] = v
    return out


def _raw_pixels(frame: np.ndarray, encoding: str, bigendian: bool) -> np.ndarray:
    """The pixel array of one raw ``sensor_msgs/Image`` (any shape; rows first)."""
    from .rosbag import IMAGE_ENCODINGS

    u2 = ">u2" if bigendian else "<u2"
    enc = encoding.lower()
    layout = IMAGE_ENCODINGS.get(enc, (None, None, None))[2]
    if enc.startswith("bayer_") and layout is not None:
        rgb = frame if frame.ndim == 3 else np.repeat(frame[:, :, None], 3, axis=2)
        mosaic = _bayer_mosaic(rgb, layout)
        return mosaic.astype(u2) * np.uint16(257) if enc.endswith("16") else mosaic
    if layout in ("uyvy", "yuyv"):
        return _yuv422(frame, layout)
    if enc in ("mono16", "16uc1"):
        return frame.astype(u2) * np.uint16(257)
    if enc in ("rgb16", "bgr16"):
        rgb = frame if enc == "rgb16" else frame[:, :, ::-1]
        return rgb.astype(u2) * np.uint16(257)
    if enc == "bgr8":
        return frame[:, :, ::-1]
    if enc in ("rgba8", "bgra8"):
        rgb = frame if enc == "rgba8" else frame[:, :, ::-1]
        return np.concatenate([rgb, np.full(frame.shape[:2] + (1,), 255, np.uint8)], axis=2)
    return frame


def _image_message(
    ts, header, frame: np.ndarray, encoding: str, compressed: str | None,
    bigendian: bool = False, padding: int = 0,
):  # fmt: skip
    if compressed is not None:
        buf = io.BytesIO()
        Image.fromarray(frame).save(buf, format={"jpeg": "JPEG", "png": "PNG"}[compressed])
        data = np.frombuffer(buf.getvalue(), np.uint8)
        return "sensor_msgs/msg/CompressedImage", ts.types["sensor_msgs/msg/CompressedImage"](
            header=header, format=compressed, data=data
        )
    pix = np.ascontiguousarray(_raw_pixels(frame, encoding, bigendian))
    h, w = frame.shape[:2]
    rows = pix.view(np.uint8).reshape(h, -1)
    if padding:  # bytes past each row's pixels, as drivers add for alignment: never pixels
        rows = np.concatenate([rows, np.full((h, padding), 0xA5, np.uint8)], axis=1)
    data = rows.reshape(-1)
    return "sensor_msgs/msg/Image", ts.types["sensor_msgs/msg/Image"](
        header=header, height=h, width=w, encoding=encoding, is_bigendian=int(bigendian),
        step=rows.shape[1], data=data,
    )  # fmt: skip


def _odometry(ts, header, xy):
    T = ts.types
    P, Q = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    pose = T["geometry_msgs/msg/PoseWithCovariance"](
        pose=T["geometry_msgs/msg/Pose"](
            position=P(x=float(xy[0]), y=float(xy[1]), z=0.0), orientation=Q(x=0, y=0, z=0, w=1)
        ),
        covariance=np.zeros(36),
    )
    V = T["geometry_msgs/msg/Vector3"]
    twist = T["geometry_msgs/msg/TwistWithCovariance"](
        twist=T["geometry_msgs/msg/Twist"](linear=V(x=0, y=0, z=0), angular=V(x=0, y=0, z=0)),
        covariance=np.zeros(36),
    )
    return T["nav_msgs/msg/Odometry"](header=header, child_frame_id="base", pose=pose, twist=twist)


def write_bag(
    path,
    frames,
    *,
    version: int = 2,
    storage: str = "sqlite3",
    topic: str = "/camera/image",
    encoding: str = "mono8",
    compressed: str | None = None,
    fps: float = 10.0,
    start: float = 1000.0,
    positions=None,
    position_topic: str = "/odom",
    bigendian: bool = False,
    padding: int = 0,
):
    """Write frames as image messages of a ROS 1 ``.bag`` or a ROS 2 bag folder.

    Parameters
    ----------
    path : str or Path
        ROS 1: the ``.bag`` file; ROS 2: the bag folder (``metadata.yaml`` + ``.db3``).
    frames : array-like, shape (n, H, W) or (n, H, W, 3)
    version : {1, 2}
    storage : {'sqlite3', 'mcap'}
        ROS 2 storage: a ``.db3`` or an ``.mcap`` file in the bag folder.
    encoding : str
        Raw encoding unless ``compressed`` is ``'jpeg'`` or ``'png'``: ``mono8``, ``mono16``,
        ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``rgb16``, ``bgr16``; ``16UC1`` writes a
        depth-like image; a camera's raw forms ``bayer_rggb8``, ``bayer_bggr8``,
        ``bayer_gbrg8``, ``bayer_grbg8`` (and ``bayer_*16``) write the mosaic a Bayer sensor
        records of the frame (each pixel keeps the one colour of its photosite), ``yuv422``
        (UYVY) and ``yuv422_yuy2`` (YUYV) its BT.601 full-range Y (a gray frame is its own Y)
        with U, V shared by each pixel pair.  16-bit samples are the 8-bit ones times 257.
    fps, start : float
        Frame ``i`` is stamped ``start + i / fps`` seconds.
    positions : array-like, shape (n, 2), optional
        Also write ``nav_msgs/Odometry`` on ``position_topic`` with these x, y (metres).
    bigendian : bool
        Write 16-bit samples big-endian (``is_bigendian`` 1).
    padding : int
        Bytes added after each row of a raw image (``step`` is then larger than the pixels).
    """
    typesys = require_extra("rosbags.typesys")
    a = _uint8(frames)
    path = Path(path)
    ros1 = version == 1
    # ROS 2 names its storage file after the folder, so that one is written in place (the
    # writer refuses an existing path) and removed on failure.
    tmp = _temporary(path) if ros1 else path
    ts = typesys.get_typestore(typesys.Stores.ROS1_NOETIC if ros1 else typesys.Stores.ROS2_HUMBLE)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(tmp)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(tmp, version=9, storage_plugin=StoragePlugin[storage.upper()])
    try:
        with writer:
            conns = {}
            for i in range(a.shape[0]):
                t = start + i / fps
                stamp_ns = int(round(t * 1e9))
                msgtype, msg = _image_message(
                    ts, _header(ts, ros1, t), a[i], encoding, compressed, bigendian, padding
                )
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
                writer.write(conns[topic], stamp_ns, serialize(msg, msgtype))
                if positions is not None:
                    if position_topic not in conns:
                        conns[position_topic] = writer.add_connection(
                            position_topic, "nav_msgs/msg/Odometry", typestore=ts
                        )
                    odo = _odometry(ts, _header(ts, ros1, t, "odom"), positions[i])
                    writer.write(
                        conns[position_topic], stamp_ns, serialize(odo, "nav_msgs/msg/Odometry")
                    )
        if ros1:
            os.replace(tmp, path)
    except BaseException:
        _discard(tmp)
        raise
    return path
