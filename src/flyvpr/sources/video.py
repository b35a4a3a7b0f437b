"""Video files (mp4, mkv, avi, ...) decoded with PyAV straight to small gray frames.

Gray is the video's luma plane (Y), which 8-bit YUV frames (``yuv420p``, ``yuvj420p``,
``nv12``, ``yuv422p``, ``yuv444p`` ...) hand over without any conversion: the plane is viewed
in place and area-averaged to the target size (:func:`flyvpr.images.area_resize`, the one
area resize of the package, also that of image files and ROS bags: exact area weights, as
OpenCV's ``INTER_AREA``).  Limited-range ("TV", 16-235) luma is then expanded to
full range, and the result divided by 255.  That costs a fraction of what FFmpeg's swscale
takes for the same area resize (``frame.reformat(..., interpolation="AREA")``), which remains
the path for every other pixel format (RGB, 10-bit, palette ...): converted to full-size gray
first, then averaged the same way.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..images import area_resize
from .base import Decoder, RecordingError, Source, _reason, require_extra

__all__ = ["VideoSource", "VIDEO_EXTENSIONS"]

#: file suffixes read as video
VIDEO_EXTENSIONS = (".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".ts")


class VideoSource(Source):
    """A video file; timestamps are the frames' presentation times in seconds.

    Parameters
    ----------
    path : str or Path
    threads : bool
        Let FFmpeg decode on several threads (``stream.thread_type = "AUTO"``).
    """

    kind = "video"

    def __init__(self, path, *, threads: bool = True):
        super().__init__(path)
        self.threads = threads
        self._av = require_extra("av")
        if not self.path.is_file():
            raise FileNotFoundError(f"video file not found: {self.path}")
        with self._open() as container:
            if not container.streams.video:
                raise RecordingError(f"video {self.path}: has no video stream")

    def _open(self):
        try:
            return self._av.open(str(self.path))
        except (self._av.FFmpegError, UnicodeDecodeError, ValueError) as exc:
            raise RecordingError(
                f"video {self.path}: not a readable video file ({_reason(exc)})"
            ) from None

    def _frames(self) -> Iterator[tuple[int, float, Decoder]]:
        av = self._av
        with self._open() as container:
            stream = container.streams.video[0]
            if self.threads:
                stream.thread_type = "AUTO"
            expected, says = _expected_frames(container, stream)
            index = 0
            try:
                for frame in container.decode(stream):
                    t = frame.time
                    t = float("nan") if t is None else float(t)
                    yield index, t, _decoder(frame)
                    index += 1
            except av.FFmpegError as exc:
                raise RecordingError(
                    f"video {self.path}: damaged or truncated after frame {index} ({_reason(exc)})"
                ) from None
            if expected is not None and index < expected:
                raise RecordingError(
                    f"video {self.path}: truncated: its header {says} {expected} frames, "
                    f"{index} could be decoded"
                )


def _expected_frames(container, stream) -> tuple[int | None, str]:
    """The frame count the header announces, or the one its duration implies less one frame of
    slack for rounding (None when the header says neither), and how to say it."""
    if stream.frames:
        return int(stream.frames), "announces"
    rate = stream.average_rate or stream.guessed_rate
    if container.duration and rate:
        # container.duration is in microseconds (AV_TIME_BASE)
        return int(container.duration * float(rate) / 1_000_000) - 1, "implies at least"
    return None, ""


#: 8-bit YUV formats whose first plane is the luma, one byte per pixel
_LUMA_FORMATS = frozenset(
    "yuv420p yuvj420p yuv422p yuvj422p yuv444p yuvj444p yuv440p yuvj440p yuv411p yuv410p "
    "nv12 nv21 nv16 gray".split()
)
_FULL_RANGE_FORMATS = frozenset({"yuvj420p", "yuvj422p", "yuvj444p", "yuvj440p", "gray"})


def _luma(frame) -> tuple[np.ndarray, bool]:
    """The frame's 8-bit luma (H, W) without a copy where possible, and whether full range."""
    name = frame.format.name
    if name in _LUMA_FORMATS:
        plane = frame.planes[0]
        y = np.frombuffer(plane, np.uint8).reshape(frame.height, plane.line_size)
        full = name in _FULL_RANGE_FORMATS or getattr(frame, "color_range", 0) == 2
        return y[:, : frame.width], full
    return frame.reformat(format="gray").to_ndarray(), True


def _decoder(frame):
    def decode(size):
        h, w = size
        y, full = _luma(frame)
        small = area_resize(y, h, w)
        if full:
            small *= np.float32(1.0 / 255.0)
        else:  # limited range: 16 -> 0, 235 -> 1
            small = (small - np.float32(16.0)) * np.float32(1.0 / 219.0)
        return np.clip(small, 0.0, 1.0, out=small)

    return decode
