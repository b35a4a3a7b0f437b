"""Video files (mp4, mkv, avi, ...) decoded with PyAV straight to small gray frames.

Each decoded frame is converted by FFmpeg's swscale in one call to 8-bit gray at the target
size with area averaging (``frame.reformat(width, height, format="gray",
interpolation="AREA")``), so decoding plus resizing costs little more than decoding, and no
full-size float copy is ever made.  The gray plane is the video's luma expanded to full range
(0-255), then divided by 255.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from .base import RecordingError, Source, require_extra

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

    def _frames(self) -> Iterator[tuple[int, float, object]]:
        av = self._av
        with self._open() as container:
            stream = container.streams.video[0]
            if self.threads:
                stream.thread_type = "AUTO"
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


def _decoder(frame):
    def decode(size):
        h, w = size
        small = frame.reformat(width=w, height=h, format="gray", interpolation="AREA")
        return small.to_ndarray() * np.float32(1.0 / 255.0)

    return decode


def _reason(exc) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def video_frame_count(path) -> int | None:
    """The frame count the container declares (None if it does not say)."""
    av = require_extra("av")
    with av.open(str(path)) as container:
        n = container.streams.video[0].frames
    return int(n) if n and not math.isnan(n) else None
