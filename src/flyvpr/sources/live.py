"""Live sources: a network stream or a camera device, read as the frames come.

A :class:`LiveSource` opens an ``rtsp://``, ``http(s)://`` (MJPEG ``multipart/x-mixed-replace``
or any stream FFmpeg reads), ``udp://``, ``tcp://`` ... URL, or a V4L2 camera (``/dev/video0``),
with PyAV, and decodes it on a reader thread that keeps only the newest frame.  The consumer
(the localizer) takes that frame whenever it is ready, so it never falls behind the camera:
when it is slower than the stream, the frames it had no time for are dropped and counted
(``LiveSource.n_dropped``), and the answer it gives is always about the latest frame.

Timestamps come from the stream (a frame's presentation time in seconds, the stream's own
clock: RTSP/RTP, MPEG-TS, a camera driver's capture time) except for formats that carry none,
such as MJPEG over HTTP or a raw H.264 elementary stream, whose frames FFmpeg numbers at an
assumed rate: those get the wall clock (Unix seconds) of their arrival.  ``LiveSource.clock``
says which.

A stream that stalls (no frame for ``stall_timeout`` seconds, or a broken connection) is
reopened up to ``retries`` times in a row, each time with a message to ``notify``; then
:meth:`LiveSource.frames` raises :class:`~flyvpr.sources.RecordingError`.  The end of a stream
(the server closed it cleanly) ends :meth:`LiveSource.frames`.

Needs the ``recordings`` extra (PyAV); it is imported only when a live source is opened.
"""

from __future__ import annotations

import errno
import functools
import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Literal, NamedTuple

import numpy as np

from .._validation import check_real, is_integer
from ..images import DEFAULT_SIZE, _check_size
from .base import RecordingError, _reason, require_extra

__all__ = ["LiveFrame", "LiveSource", "LIVE_SCHEMES", "is_live"]

logger = logging.getLogger(__name__)

#: URL schemes read as live streams (FFmpeg's network protocols)
LIVE_SCHEMES = ("rtsp", "rtsps", "rtmp", "rtmps", "http", "https", "udp", "tcp", "rtp", "srt")

#: container formats whose timestamps FFmpeg makes up from an assumed frame rate (MJPEG over
#: HTTP, raw elementary streams): their frames are stamped with the wall clock instead
_NO_CLOCK_FORMATS = frozenset({"mpjpeg", "mjpeg", "jpeg_pipe", "image2pipe", "h264", "hevc"})

_SCHEME_RE = re.compile(r"^([a-zA-Z][a-zA-Z0-9+.-]*)://")

#: av_opt_find's AV_OPT_SEARCH_CHILDREN | AV_OPT_SEARCH_FAKE_OBJ (libavutil/opt.h): search a
#: class and every class below it, without an object of it
_SEARCH_ALL_CLASSES = 1 | 2


def is_live(source) -> bool:
    """Whether ``source`` names a live source: a URL of :data:`LIVE_SCHEMES` or a device
    under ``/dev/`` (a V4L2 camera such as ``/dev/video0``).

    >>> is_live("rtsp://10.0.0.2:8554/cam"), is_live("/dev/video0"), is_live("drive.mp4")
    (True, True, False)
    """
    text = str(source)
    m = _SCHEME_RE.match(text)
    if m is not None:
        return m.group(1).lower() in LIVE_SCHEMES
    return text.startswith("/dev/")


#: content types of an HTTP answer that is a document, not a video stream
_PAGE_TYPES = ("text/", "application/json", "application/xml", "application/xhtml")


def _web_page_type(url: str, timeout: float) -> str | None:
    """For an ``http(s)`` URL that FFmpeg got no frame from in time: the content type of the
    server's answer when it is a document (an HTML page that keeps its connection open reads
    to FFmpeg as a stream that never sends a frame), else None.  One request, its headers
    only, within ``timeout`` seconds but at most ``_PAGE_PROBE_S`` (a server that answers
    nothing adds no more than that to the wait); the certificate of an ``https`` URL is not
    checked, as FFmpeg does not check it by default (only the answer's type is read); any
    failure gives None."""
    import ssl
    import urllib.parse
    import urllib.request

    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or parts.username or parts.password:
        return None  # (credentials: urllib would send them differently from FFmpeg)
    unchecked = ssl.create_default_context()
    unchecked.check_hostname = False
    unchecked.verify_mode = ssl.CERT_NONE
    try:
        with urllib.request.urlopen(
            url, timeout=min(max(timeout, 0.5), _PAGE_PROBE_S), context=unchecked
        ) as answer:
            kind = answer.headers.get_content_type()
    except Exception:  # (the open already failed: this only words its message)
        return None
    return kind if kind.startswith(_PAGE_TYPES) else None


#: seconds the web-page question of :func:`_web_page_type` may take at most
_PAGE_PROBE_S = 2.0


def _redacted(url: str) -> str:
    """``url`` without a password (``rtsp://user:secret@host`` -> ``rtsp://user:***@host``)."""
    return re.sub(r"^([a-zA-Z][a-zA-Z0-9+.-]*://[^/@:]*):[^/@]*@", r"\1:***@", url)


#: PyAV's compiled modules, any of which links PyAV's own FFmpeg libraries
_PYAV_BINARIES = ("av._core", "av.format", "av.container.core")


def _pyav_binary() -> str | None:
    """The file of a compiled PyAV module (its FFmpeg is reached through it), or None."""
    import importlib

    for name in _PYAV_BINARIES:
        try:
            path = getattr(importlib.import_module(name), "__file__", None)
        except ImportError:
            continue
        if path and not path.endswith(".py"):
            return path
    return None


@functools.cache
def _ffmpeg_option_lookup() -> Callable[[str], bool] | None:
    """A function telling whether FFmpeg has an option of a given name for some format,
    device, protocol or codec; None where PyAV's FFmpeg libraries cannot be found.

    PyAV cannot say which options FFmpeg did not use: ``avformat_open_input`` hands them back,
    but ``av.open`` frees them, and PyAV 18 exposes no option descriptors.  So the names are
    looked up as the ``ffmpeg`` program does before it opens anything (``opt_default`` in
    fftools/cmdutils.c): ``av_opt_find`` on the classes of AVFormatContext and AVCodecContext
    and every class below them (demuxers, devices, protocols, codecs), in PyAV's libraries.
    """
    import ctypes

    require_extra("av")
    # The symbols are looked up through a PyAV binary: the loader resolves them in the
    # libraries it links, so another FFmpeg in the process (another package's) is never used.
    path = _pyav_binary()
    try:
        if path is None:
            raise OSError("no compiled PyAV module found")
        lib = ctypes.CDLL(path)
        find, getters = lib.av_opt_find, (lib.avformat_get_class, lib.avcodec_get_class)
    except (OSError, AttributeError) as exc:
        logger.debug("stream options not checked: FFmpeg's libraries not found (%s)", exc)
        return None
    find.restype = ctypes.c_void_p
    find.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_int, ctypes.c_int]
    for getter in getters:
        getter.restype = ctypes.c_void_p
    # a "fake object": a pointer to the class, as the first field of every object points to it
    classes = [ctypes.c_void_p(getter()) for getter in getters]

    def has_option(name: str) -> bool:
        key = name.encode()
        return any(find(ctypes.byref(c), key, None, 0, _SEARCH_ALL_CLASSES) for c in classes)

    return has_option


class _OpenFailed(Exception):
    """Why a live source could not be opened (the caller adds the source's name)."""


class LiveFrame(NamedTuple):
    """One frame of a live source, as :meth:`LiveSource.frames` hands it over.

    Attributes
    ----------
    index : int
        Count of frames the stream delivered before this one (dropped ones included), so
        gaps between consecutive indices are the frames dropped in between.
    timestamp : float
        Seconds: the stream's presentation time, or the wall clock (Unix time) at arrival
        where the stream has no clock (``LiveSource.clock``); NaN if a frame of a
        stream with a clock has none.
    arrival : float
        ``time.monotonic()`` when the frame was decoded, to measure latency.
    image : ndarray, shape (H, W), float32 in [0, 1]
        The frame in gray at the size asked for.
    frame : av.VideoFrame
        The decoded frame at full size (for a viewer).
    """

    index: int  # type: ignore[assignment]  # a public field name: it hides tuple.index
    timestamp: float
    arrival: float
    image: np.ndarray
    frame: object


#: a JPEG's end-of-image marker, and how far from a packet's end it is looked for first (a
#: camera may pad its JPEGs after it); its start-of-scan marker
_EOI = b"\xff\xd9"
_EOI_REACH = 16
_SOS = b"\xff\xda"


def _whole_jpeg(packet) -> bool:
    """Whether an MJPEG packet (bytes or a buffer) holds a whole JPEG: an end-of-image marker
    after its last start-of-scan.  A torn one (cut in its scan data) has none: the scan data
    cannot hold the marker (a 0xff byte there is followed by 0), and an EXIF thumbnail's own
    markers come before the picture's scan.  FFmpeg decodes a torn JPEG without an error,
    the missing rows gray, so it must be told apart here."""
    view = memoryview(packet)
    if _EOI in bytes(view[-_EOI_REACH:]):
        return True
    data = bytes(view)
    sos = data.rfind(_SOS)
    return sos >= 0 and data.find(_EOI, sos) >= 0


class LiveSource:
    """A network stream or a camera, decoded on a thread that keeps only the newest frame.

    The source is opened (and the stream's first bytes read) when it is created, so a bad
    address fails here with one message; :meth:`frames` then starts the reader thread.

    Parameters
    ----------
    url : str
        A URL (:data:`LIVE_SCHEMES`) or a V4L2 device path (``/dev/video0``).
    options : dict of str to str, optional
        FFmpeg options for the format or protocol, such as ``{"rtsp_transport": "tcp"}`` or,
        for a camera, ``{"video_size": "640x480", "framerate": "30",
        "input_format": "mjpeg"}``.  FFmpeg ignores a name it does not know; each name that
        no FFmpeg format, device, protocol or codec has (a misspelling) is named to
        ``notify``.  An option of another format or protocol than this source's is not.
    stall_timeout : float
        Seconds without a frame after which the stream counts as stalled and is reopened.
    open_timeout : float
        Seconds to wait for the stream to answer when it is opened.
    retries : int
        Reopenings in a row (without a frame in between) before giving up.
    notify : callable, optional
        Called with a one-line message when the stream stalls and is reopened, and for each
        option FFmpeg did not use (above); default a warning on this module's logger.

    Attributes
    ----------
    kind : str
        ``"stream"`` or ``"camera"``.
    clock : str or None
        ``"stream"`` (timestamps from the stream) or ``"wall"`` (arrival time), known from the
        first frame on.
    n_received : int
        Frames the stream delivered so far.
    n_dropped : int
        Frames replaced by a newer one before the consumer took them.
    n_corrupt : int
        Packets that failed to decode (skipped).
    n_reconnects : int
        Times the stream was reopened after a stall.
    ended : bool
        Whether the stream ended (the server closed it).

    Raises
    ------
    FileNotFoundError
        For a device path that does not exist.
    RecordingError
        If the source cannot be opened (unreachable, refused, busy, not a video stream): the
        message names it and says why.
    ValueError
        For a ``url`` that is not live, or timeouts / retries out of range.
    TypeError
        For timeouts / retries that are not numbers.
    ImportError
        Naming the ``recordings`` extra, without PyAV.

    Examples
    --------
    >>> src = LiveSource("udp://127.0.0.1:5000", stall_timeout=2)  # doctest: +SKIP
    >>> for f in src.frames((32, 64)):  # doctest: +SKIP
    ...     fix = localizer.update(f.image)
    """

    def __init__(
        self,
        url,
        *,
        options=None,
        stall_timeout: float = 5.0,
        open_timeout: float = 10.0,
        retries: int = 3,
        notify: Callable[[str], None] | None = None,
    ):
        self.url = str(url)
        if not is_live(self.url):
            raise ValueError(
                f"url must be a stream URL ({', '.join(s + '://' for s in LIVE_SCHEMES)}) or a "
                f"camera device (/dev/video0); got {self.url!r}"
            )
        scheme = _SCHEME_RE.match(self.url)
        if scheme is not None:  # a scheme is case-insensitive; FFmpeg knows lower case only
            self.url = scheme.group(1).lower() + self.url[len(scheme.group(1)) :]
        self.kind = "stream" if scheme is not None else "camera"
        self.options = {str(k): str(v) for k, v in (options or {}).items()}
        self.stall_timeout = check_real(stall_timeout, "stall_timeout", unit="seconds")
        self.open_timeout = check_real(open_timeout, "open_timeout", unit="seconds")
        if not is_integer(retries) or retries < 0:
            raise ValueError(f"retries must be an integer >= 0; got {retries!r}")
        self.retries = int(retries)
        self.notify = notify or logger.warning
        self.clock: str | None = None
        self.n_received = self.n_dropped = self.n_corrupt = self.n_reconnects = 0
        # received MJPEG frames that did not decode (counted in n_corrupt too; other
        # streams' damaged packets never become frames)
        self.n_undecodable = 0
        self.ended = False
        self._av = require_extra("av")
        self._cond = threading.Condition()
        # the newest frame not yet taken: (index, timestamp, arrival, frame)
        self._slot: tuple[int, float, float, Any] | None = None
        self._done = False
        self._error: BaseException | None = None
        self._stopping = False  # a plain flag: stop() may run in a signal handler
        # None before frames(), False if closed before it
        self._thread: threading.Thread | Literal[False] | None = None
        if self.kind == "camera" and not os.path.exists(self.url):
            raise FileNotFoundError(
                f"camera {self.url}: no such device (expected a V4L2 camera such as /dev/video0)"
            )
        self._check_options()
        self._container = self._open()

    def describe(self) -> str:
        """``stream URL`` (password hidden) or ``camera /dev/videoN``."""
        return f"{self.kind} {_redacted(self.url)}"

    # -- opening ----------------------------------------------------------------------------
    def _check_options(self) -> None:
        """Name to ``notify`` each option of a name FFmpeg does not have (it would ignore it
        without a word): before the open, which may wait ``open_timeout``."""
        has_option = _ffmpeg_option_lookup() if self.options else None
        if has_option is None:
            return
        for key in self.options:
            if not has_option(key):
                self.notify(
                    f"{self.describe()}: FFmpeg did not use the option {key!r}: no FFmpeg "
                    "format, device, protocol or codec has an option of that name"
                )

    def _open(self):
        """Open the source, or raise RecordingError naming it and saying why.

        FFmpeg's open blocks (up to ``open_timeout``) in C, where Python cannot deliver
        Ctrl-C or SIGTERM; it runs in a helper thread while this one waits in short steps, so
        an interrupt ends the wait at once (the helper, a daemon, ends with FFmpeg's
        timeout; a container it opens after the interrupt is closed)."""
        outcome: dict = {}

        def attempt() -> None:
            try:
                outcome["container"] = self._try_open()
            except BaseException as exc:  # handed to the waiting thread
                outcome["error"] = exc
            if outcome.get("abandoned") and "container" in outcome:
                outcome["container"].close()

        helper = threading.Thread(target=attempt, name="flyvpr-live-open", daemon=True)
        helper.start()
        try:
            while helper.is_alive():
                helper.join(0.05)
        except BaseException:  # Ctrl-C, SIGTERM: leave FFmpeg to its timeout
            outcome["abandoned"] = True
            if "container" in outcome:
                outcome["container"].close()
            raise
        error = outcome.get("error")
        if isinstance(error, _OpenFailed):
            raise RecordingError(f"{self.describe()}: {error}") from None
        if error is not None:
            raise error
        return outcome["container"]

    def _try_open(self):
        """Open the source; every failure becomes an _OpenFailed with the reason."""
        av = self._av
        kwargs = {"format": "v4l2"} if self.kind == "camera" else {}
        try:
            container = av.open(
                self.url,
                options=self.options,
                timeout=(self.open_timeout, self.stall_timeout),
                **kwargs,
            )
        except av.ExitError:
            page = _web_page_type(self.url, self.open_timeout)
            if page is not None:
                raise _OpenFailed(
                    f"answers with a web page ({page}), not a video stream: give the address "
                    "of the stream itself (a camera's page shows it; it often ends in .mjpg, "
                    "/video or /stream)"
                ) from None
            raise _OpenFailed(
                f"no answer within {self.open_timeout:g} s (no data, or no frame after the "
                f"headers; expected a {self._expected()})"
            ) from None
        except av.InvalidDataError:
            raise _OpenFailed(
                f"sends nothing FFmpeg can read as video (expected a {self._expected()})"
            ) from None
        except (av.FFmpegError, OSError, UnicodeDecodeError, ValueError) as exc:
            raise _OpenFailed(f"cannot open: {self._why(exc)}") from None
        if not container.streams.video:
            container.close()
            raise _OpenFailed(f"has no video stream (expected a {self._expected()})")
        return container

    def _expected(self) -> str:
        if self.kind == "camera":
            return "V4L2 video capture device"
        return "video stream such as MJPEG over HTTP, RTSP or MPEG-TS over UDP"

    def _why(self, exc) -> str:
        code = getattr(exc, "errno", None)
        if code == errno.EBUSY:
            return "the device is busy (another program is using it)"
        if code in (errno.EACCES, errno.EPERM):
            return "permission denied (is the user in the 'video' group?)"
        reason = getattr(exc, "strerror", None) or _reason(exc)
        return f"{reason} (expected a {self._expected()})"

    # -- the reader thread ------------------------------------------------------------------
    def _publish(self, item, stream_time, arrival: float) -> None:
        """Hand ``item`` (a decoded frame, or an MJPEG packet to decode) to the consumer."""
        if self.clock is None:
            stamped = stream_time is not None
            self.clock = (
                "stream"
                if stamped and self._container.format.name not in _NO_CLOCK_FORMATS
                else "wall"
            )
        if self.clock == "wall":
            t = time.time()
        else:
            t = math.nan if stream_time is None else float(stream_time)
        with self._cond:
            if self._slot is not None:
                self.n_dropped += 1
            self._slot = (self.n_received, t, arrival, item)
            self.n_received += 1
            self._cond.notify()

    def _read(self, container) -> str:
        """Decode ``container`` until it ends, stalls or the consumer stops.

        Returns ``"stop"``, ``"end"`` or the reason of a stall.
        """
        av = self._av
        # no frame threading: it holds frames back (one per thread), which a live stream
        # pays for in latency
        stream = container.streams.video[0]
        # every MJPEG packet is a whole picture: hand packets over and let the consumer decode
        # the one it takes, so the frames it drops cost no decoding and the socket is drained
        # at once (a stream faster than the decoder would otherwise queue up in TCP buffers)
        lazy = stream.codec_context.name == "mjpeg"
        last = time.monotonic()
        newest = None  # the last MJPEG packet (whether it was whole is asked when a read fails)
        try:
            for packet in container.demux(stream):
                if self._stopping:
                    return "stop"
                if lazy:
                    if packet.size:
                        newest = packet
                        last = time.monotonic()
                        t = None if packet.pts is None else float(packet.pts * stream.time_base)
                        self._publish(packet, t, last)
                    continue
                try:
                    frames = packet.decode()
                except av.FFmpegError:
                    # a damaged packet (a lost UDP datagram, a torn JPEG): skip it; a stream
                    # that sends nothing but damage stalls below
                    self.n_corrupt += 1
                    frames = ()
                for frame in frames:
                    last = time.monotonic()
                    self._publish(frame, frame.time, last)
                if time.monotonic() - last > self.stall_timeout:
                    return (
                        f"stalled: no decodable frame for {self.stall_timeout:g} s "
                        f"({self.n_corrupt} damaged packets so far)"
                    )
        except av.ExitError:
            return f"stalled: no data for {self.stall_timeout:g} s"
        except (av.FFmpegError, OSError) as exc:
            if newest is not None and self._closed_by_server(exc) and _whole_jpeg(newest):
                return "stop" if self._stopping else "end"
            reason = getattr(exc, "strerror", None) or _reason(exc)
            return f"the connection broke ({reason})"
        return "stop" if self._stopping else "end"

    def _closed_by_server(self, exc) -> bool:
        """Whether a read error is an HTTP server closing the stream: FFmpeg's multipart
        (MJPEG) reader reports the connection's orderly close as EIO, where a reset raises
        ECONNRESET and a silent link stalls (a timeout).  The caller counts it as the end
        only after a whole JPEG: a close in the middle of one is a broken stream."""
        return self.url.lower().startswith(("http://", "https://")) and (
            getattr(exc, "errno", None) == errno.EIO
        )

    def _run(self) -> None:
        container = self._container
        failures = 0
        try:
            while True:
                before = self.n_received
                outcome = self._read(container)
                container.close()
                if outcome == "stop":
                    return
                if outcome == "end":
                    self.ended = True
                    return
                if self.n_received > before:
                    failures = 0
                while True:  # reopen until a stream answers or the retries are spent
                    failures += 1
                    if failures > self.retries:
                        n = self.retries
                        given_up = (
                            f"gave up after {n} reconnection attempt{'s' * (n != 1)}"
                            if n
                            else "not retried (retries=0)"
                        )
                        self._error = RecordingError(f"{self.describe()}: {outcome}; {given_up}")
                        return
                    self.notify(
                        f"{self.describe()}: {outcome}; reconnecting ({failures}/{self.retries})"
                    )
                    pause = time.monotonic() + min(1.0, self.stall_timeout)
                    while time.monotonic() < pause:
                        if self._stopping:
                            return
                        time.sleep(0.05)
                    try:
                        container = self._container = self._try_open()
                    except _OpenFailed as exc:
                        outcome = f"reconnecting failed: {exc}"
                        continue
                    self.n_reconnects += 1
                    break
        except BaseException as exc:  # pragma: no cover - a bug: hand it to the consumer
            self._error = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify()

    # -- the consumer's side ----------------------------------------------------------------
    def _take(self):
        """The newest frame (waits for one); None after the end of the stream."""
        with self._cond:
            while self._slot is None and not self._done and not self._stopping:
                self._cond.wait(0.1)  # short waits: stop() and Ctrl-C are seen promptly
            if self._stopping:
                return None
            if self._slot is not None:
                item, self._slot = self._slot, None
                return item
        if self._error is not None:
            raise self._error
        return None

    def frames(self, size=DEFAULT_SIZE) -> Iterator[LiveFrame]:
        """Yield the newest frame each time the caller asks for the next one.

        Parameters
        ----------
        size : (int, int)
            (H, W) of :attr:`LiveFrame.image` (gray, area-averaged, as for video files).

        Raises
        ------
        RecordingError
            When the stream stalled and every reconnection failed (the message names the
            source and the reason).
        """
        from ..images import area_resize
        from .video import _decoder, _DisplayOps

        h, w = _check_size(size)
        if self._thread is not None:
            raise RuntimeError(f"{self.describe()}: frames() can be iterated only once")
        # compile (or load) the resize kernels now, for contiguous and row-padded planes, so
        # the first frames do not wait for them and pile up behind
        plane = np.zeros((2 * h, 2 * w + 8), np.uint8)
        area_resize(plane, h, w)
        area_resize(plane[:, : 2 * w], h, w)
        jpeg = self._av.CodecContext.create("mjpeg", "r")
        self._thread = threading.Thread(target=self._run, name="flyvpr-live-reader", daemon=True)
        self._thread.start()
        # since when every JPEG taken has been damaged (None after a good one): a stream that
        # sends only damage for stall_timeout ends; one torn JPEG after a silence (a camera
        # that hung mid-picture, which the reader reconnects to) does not
        damaged_since: float | None = None
        display = _DisplayOps()
        try:
            while True:
                item = self._take()
                if item is None:
                    return
                index, t, arrival, frame = item
                if isinstance(frame, self._av.Packet):
                    frame = self._decode_jpeg(jpeg, frame)
                    if frame is None:
                        now = time.monotonic()
                        damaged_since = now if damaged_since is None else damaged_since
                        if now - damaged_since > self.stall_timeout:
                            raise RecordingError(
                                f"{self.describe()}: no decodable frame for "
                                f"{self.stall_timeout:g} s ({self.n_corrupt} damaged JPEG frames)"
                            )
                        continue
                damaged_since = None
                yield LiveFrame(index, t, arrival, _decoder(frame, display)((h, w)), frame)
        finally:
            self.close()

    def _decode_jpeg(self, codec, packet):
        """The picture of one MJPEG packet (None, counted as damaged, if it has none or is
        torn: see :func:`_whole_jpeg`)."""
        frames = []
        if _whole_jpeg(packet):
            try:
                frames = codec.decode(packet)
            except self._av.FFmpegError:
                frames = []
        if not frames:
            self.n_corrupt += 1
            self.n_undecodable += 1
            return None
        return frames[-1]

    def stop(self) -> None:
        """Ask :meth:`frames` to end (within 0.1 s); safe to call from a signal handler."""
        self._stopping = True

    def close(self) -> None:
        """Stop the reader thread (it closes the stream when its current read returns)."""
        self._stopping = True
        if self._thread is None:
            self._container.close()
            self._thread = False  # closed before any frame was read: frames() refuses
        elif self._thread:
            self._thread.join(timeout=0.5)

    def __enter__(self) -> LiveSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
