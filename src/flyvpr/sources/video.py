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

Which stream: the one a player picks (of the default-flagged video streams if any, else of
all, the one with the largest picture, as the ``ffmpeg`` command picks, then the most frames;
a cover picture only where there is nothing else), said at info level when there are several.
A display matrix that turns the picture by a multiple of 90 degrees (what phones write
instead of rotating the pixels), and mirrors it too, is applied as the ``ffmpeg`` command's
autorotate applies it, so frames come upright as a player shows them.

A truncated file is refused: by the demuxer's or decoder's own error where it raises one
(MP4, H.264 ...), and otherwise by time.  The video stream's header says when it ends (its
own duration, never the container's, which spans an audio track too; a Matroska stream's
``DURATION`` tag; an AVI stream's frame count); the last decoded frame must reach that end
within three frame intervals.  Frame counts would not do: a variable-frame-rate video has no
count to expect, and an MP4 cut losslessly keeps samples its edit list leaves out.  A stream
whose header says no end (an MPEG-TS file, a multi-stream Matroska file without
``DURATION`` tags) can only be refused on a decoding error.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Iterator

import numpy as np

from ..images import area_resize
from .base import Decoder, RecordingError, Source, _reason, require_extra

__all__ = ["VideoSource", "VIDEO_EXTENSIONS"]

logger = logging.getLogger(__name__)

#: file suffixes read as video
VIDEO_EXTENSIONS = (".mp4", ".mkv", ".avi", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".ts")
#: Version of the decoding of a video's frames, recorded in the maps built from a video
#: (``video_decode``): a map of an older one warns when loaded.  1 (maps without the field):
#: the frames as stored; 2: the display matrix applied (rotation and mirrors).
_DECODE_VERSION = 2


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
            stream = _video_stream(container)
            n_video = len(container.streams.video)
            if n_video > 1:
                logger.info(
                    "video %s: reading video stream #%d (%s), the one FFmpeg would play, of "
                    "%d video streams",
                    self.path, stream.index, _describe_stream(stream), n_video,
                )  # fmt: skip

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
            stream = _video_stream(container)
            if self.threads:
                stream.thread_type = "AUTO"
            ends = _stream_end(container, stream)
            nominal = _nominal_interval(stream)
            display = _DisplayOps()
            index = 0
            times = [math.nan, math.nan]  # the last two frames' presentation times
            last_duration = math.nan  # the last frame's own duration, where it has one
            try:
                for frame in container.decode(stream):
                    t = frame.time
                    t = float("nan") if t is None else float(t)
                    times = [times[1], t]
                    last_duration = _frame_duration(frame)
                    yield index, t, _decoder(frame, display)
                    index += 1
            except av.FFmpegError as exc:
                raise RecordingError(
                    f"video {self.path}: damaged or truncated after frame {index} ({_reason(exc)})"
                ) from None
            # the longest of the stated, the last seen and the last frame's own interval: a
            # variable rate may have slowed towards the end
            step = max(
                x for x in (nominal, times[1] - times[0], last_duration, 0.0) if math.isfinite(x)
            )
            if ends is None or step == 0.0 or (index and math.isnan(times[1])):
                return  # nothing to compare: no end in the header, no frame rate, no times
            if index:
                reached = times[1] + (last_duration if last_duration > 0 else step)
            else:
                reached = _stream_start(stream)
            missing = ends - reached
            if missing > 0.5 * step + _CLOCK_SLACK_S:  # (a frame missing at the end, or more)
                expected, says = _expected_frames(
                    stream, decoded=index, missing_s=missing, interval=step
                )
                count = f"its header {says} {expected} frames, " if expected else ""
                raise RecordingError(
                    f"video {self.path}: truncated: {count}{index} could be decoded (its video "
                    f"stream lasts until {ends:.2f} s, the decoded frames reach {reached:.2f} s)"
                )


#: seconds of timestamp rounding forgiven beyond the frame intervals (Matroska keeps ms)
_CLOCK_SLACK_S = 0.002


def _video_stream(container):
    """The video stream a player picks: of the default-flagged ones if any, else of all, the
    one with the largest picture (as the ``ffmpeg`` command picks), then the most frames; a
    cover picture (an attached picture) only where there is nothing else; the first on a tie."""
    import av

    streams = list(container.streams.video)
    cover = int(av.stream.Disposition.attached_pic)
    default = int(av.stream.Disposition.default)
    flags = [int(getattr(s, "disposition", 0) or 0) for s in streams]
    moving = [s for s, f in zip(streams, flags, strict=True) if not f & cover] or streams
    chosen = [s for s in moving if int(getattr(s, "disposition", 0) or 0) & default] or moving

    def size(s):
        ctx = s.codec_context
        return (int(ctx.width or 0) * int(ctx.height or 0), int(s.frames or 0))

    return max(chosen, key=size)  # (max keeps the first of equals)


def _describe_stream(stream) -> str:
    flags = []
    disposition = int(getattr(stream, "disposition", 0) or 0)
    if disposition & 1:  # AV_DISPOSITION_DEFAULT
        flags.append("default")
    if disposition & 1024:  # AV_DISPOSITION_ATTACHED_PIC
        flags.append("cover picture")
    name = stream.codec_context.name if stream.codec_context is not None else "unknown codec"
    text = f"{name} {stream.width}x{stream.height}"
    return f"{text}, {', '.join(flags)}" if flags else text


def _stream_start(stream) -> float:
    tb = stream.time_base
    return float(stream.start_time * tb) if stream.start_time is not None and tb else 0.0


def _nominal_interval(stream) -> float:
    """Seconds between frames at the stream's nominal rate (NaN when it states none)."""
    rate = stream.average_rate or stream.guessed_rate
    return 1.0 / float(rate) if rate else math.nan


def _frame_duration(frame) -> float:
    """The frame's own duration in seconds (NaN when the container gives none)."""
    duration, tb = getattr(frame, "duration", None), frame.time_base
    return float(duration * tb) if duration and tb else math.nan


_DURATION_TAG = re.compile(r"^(\d+):([0-5]?\d):(\d+(?:\.\d*)?)$")


def _duration_tag(metadata) -> float | None:
    """A Matroska stream's ``DURATION`` tag (``HH:MM:SS.nnnnnnnnn``) in seconds, or None.

    FFmpeg's muxer writes the stream's last presentation time plus its duration; mkvmerge
    also writes one (language-suffixed keys such as ``DURATION-eng`` included)."""
    for key, value in metadata.items():
        if key.upper().split("-")[0] == "DURATION":
            m = _DURATION_TAG.match(str(value).strip())
            if m:
                return int(m[1]) * 3600 + int(m[2]) * 60 + float(m[3])
    return None


def _stream_end(container, stream) -> float | None:
    """When the video stream ends by its header, in seconds on its frames' clock, or None.

    The stream's own duration from its start; an AVI stream's frame count (one time-base
    tick per frame: a cut AVI's demuxer shortens the duration to what it found, not the
    count); a Matroska stream's ``DURATION`` tag, read as an end time (FFmpeg's meaning;
    as a duration it could only say less).  The container's duration only when the video
    is its one stream: it spans every stream, so an audio track longer than the video would
    count.
    """
    tb, start = stream.time_base, _stream_start(stream)
    ends = []
    if stream.duration and tb:
        ends.append(start + float(stream.duration * tb))
    if container.format.name == "avi" and stream.frames and tb:
        ends.append(start + float(stream.frames * tb))
    tag = _duration_tag(stream.metadata)
    if tag is not None:
        ends.append(tag)
    if not ends and len(container.streams) == 1 and container.duration:
        # container times are in microseconds (AV_TIME_BASE)
        ends.append(((container.start_time or 0) + container.duration) / 1_000_000)
    return max(ends) if ends else None


def _expected_frames(
    stream, *, decoded: int, missing_s: float, interval=None
) -> tuple[int | None, str]:
    """How many frames the header announces, or at least implies, and how to say it: words
    for the message of a video found truncated (None, "" when the header says neither).

    The count it announces; else the ``decoded`` frames and the ``missing_s`` seconds of
    stream after them at the nominal rate, or one frame per ``interval`` where frames came
    further apart (a variable rate), less one frame of slack for rounding.
    """
    if stream.frames and stream.frames > decoded:
        return int(stream.frames), "announces"
    rate = stream.average_rate or stream.guessed_rate
    rate = float(rate) if rate else math.nan
    if interval:
        rate = min(rate, 1.0 / interval) if math.isfinite(rate) else 1.0 / interval
    if not math.isfinite(rate):
        return None, ""
    return decoded + int(missing_s * rate) - 1, "implies at least"


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


#: how each step of :func:`_display_ops` changes a picture (rows top to bottom): the
#: ``transpose`` filter's directions and the flips, as the ``ffmpeg`` command's autorotate
_OPS = {
    "clock": lambda y: np.rot90(y, -1),  # 90 degrees clockwise
    "cclock": lambda y: np.rot90(y, 1),  # 90 degrees counter-clockwise
    "cclock_flip": lambda y: y.T,  # counter-clockwise, then upside down: the transpose
    "clock_flip": lambda y: np.rot90(y, -1)[::-1],  # clockwise, then upside down
    "hflip": lambda y: y[:, ::-1],
    "vflip": lambda y: y[::-1],
}


def _display_ops(frame) -> tuple[str, ...]:
    """The steps of :data:`_OPS` that show the frame as the ``ffmpeg`` command does, from its
    display matrix (FFmpeg's side data: what phones write instead of turning the pixels):
    FFmpeg's clockwise angle, ``-frame.rotation``, in [0, 360), and the matrix's signs, which
    say a mirror (``fftools``' autorotate, to the letter).  An angle that is not a multiple of
    90 degrees is not applied (said once per angle)."""
    rotation = getattr(frame, "rotation", None)
    if rotation is None:  # PyAV before 14.1 has no VideoFrame.rotation
        if None not in _WARNED_ANGLES:
            _WARNED_ANGLES.add(None)
            logger.warning(
                "this PyAV does not expose a video's display rotation (VideoFrame.rotation); "
                "rotated videos are read as stored: pip install 'av>=14.1'"
            )
        return ()
    if not math.isfinite(rotation) or abs(rotation) > 360:
        return ()  # a singular matrix (NaN in some PyAV versions, INT_MIN in PyAV 18)
    m = _display_matrix(frame)
    if m is None:  # the angle alone: the matrix of a pure turn by it
        r = math.radians(rotation)
        m = (math.cos(r), -math.sin(r), math.sin(r), math.cos(r))
    m0, _, m3, m4 = m  # (FFmpeg reads these three)
    theta = -round(rotation)
    theta -= 360 * math.floor(theta / 360 + 0.9 / 360)
    if abs(theta - 90) < 1:
        return ("cclock_flip",) if m3 > 0 else ("clock",)
    if abs(theta - 180) < 1:
        return (("hflip",) if m0 < 0 else ()) + (("vflip",) if m4 < 0 else ())
    if abs(theta - 270) < 1:
        return ("clock_flip",) if m3 < 0 else ("cclock",)
    if abs(theta) < 1 or abs(theta - 360) < 1:
        return ("vflip",) if m4 < 0 else ()
    if rotation not in _WARNED_ANGLES:
        _WARNED_ANGLES.add(rotation)
        logger.warning(
            "a video's display matrix rotates it by %.1f degrees; only multiples of 90 are "
            "applied, so its frames are read unrotated",
            rotation,
        )
    return ()


#: angles (None: no rotation in this PyAV) warned of already
_WARNED_ANGLES: set[float | None] = set()


def _display_matrix(frame) -> tuple[float, float, float, float] | None:
    """Entries 0, 1, 3 and 4 of the frame's display matrix (FFmpeg's 3x3, row by row, 16.16
    fixed point), or None without one."""
    side = getattr(frame, "side_data", None)
    try:
        matrix = side.get("DISPLAYMATRIX") if side is not None else None
        if matrix is None:
            return None
        m = np.frombuffer(bytes(matrix), np.int32)[:5].astype(np.float64) / 65536.0
    except (TypeError, ValueError, AttributeError):  # (no such side data in this PyAV)
        return None
    return float(m[0]), float(m[1]), float(m[3]), float(m[4])


class _DisplayOps:
    """:func:`_display_ops` for the frames of one stream, the display matrix read once per
    angle: again only when ``frame.rotation`` changes (computed in C, without building
    ``frame.side_data``).

    Reading a frame's side data (``frame.side_data``) makes PyAV keep a reference cycle
    between the frame and its side data, so the frame's picture is freed by the cyclic
    garbage collector instead of at once: read for every frame of a 640 x 480 video, it
    raised the peak memory of ``flyvpr localize`` by about 95 MB.  A stream's display matrix
    is usually the container's (MP4's track matrix), the same on every frame; a stream whose
    mirroring changed mid-stream without its angle (H.264's display-orientation messages can
    set one per frame) keeps the first frame's."""

    def __init__(self):
        self._angle: object = ()  # (no frame seen: no angle equals it)
        self._ops: tuple[str, ...] = ()

    def __call__(self, frame) -> tuple[str, ...]:
        angle = getattr(frame, "rotation", None)
        if angle is not None and math.isnan(angle):
            angle = "nan"  # (a singular matrix in some PyAV versions: equal to itself here)
        if angle != self._angle:
            self._angle = angle
            self._ops = _display_ops(frame)
        return self._ops


def _decoder(frame, display):
    """A function of the size (h, w) that decodes ``frame`` to gray at that size, upright
    (``display``: the steps that show it, from the frame; a :class:`_DisplayOps` per stream
    reads its display matrix once per angle)."""

    def decode(size):
        h, w = size
        y, full = _luma(frame)
        ops = display(frame)
        for op in ops:
            y = _OPS[op](y)
        if ops:
            y = np.ascontiguousarray(y)
        small = area_resize(y, h, w)
        if full:
            small *= np.float32(1.0 / 255.0)
        else:  # limited range: 16 -> 0, 235 -> 1
            small = (small - np.float32(16.0)) * np.float32(1.0 / 219.0)
        return np.clip(small, 0.0, 1.0, out=small)

    return decode
