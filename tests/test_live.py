"""Live sources: streams served on localhost from inside the tests (MJPEG over HTTP from a
server thread, MPEG-TS over UDP muxed with PyAV), the newest-frame rule, stalls and bad input."""

from __future__ import annotations

import errno
import os
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

av = pytest.importorskip("av")

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.stream_servers import (  # noqa: E402
    MjpegServer,
    UdpTsSender,
    free_udp_port,
    jpeg_bytes,
)
from flyvpr.sources import LiveSource, RecordingError, is_live  # noqa: E402

#: gray level of served frame i (distinct for 40 frames, away from the ends of the range)
LEVELS = 40 + 4 * np.arange(40)


def _gray_jpegs(n=40, shape=(48, 64)):
    return [jpeg_bytes(np.full(shape, LEVELS[i], np.uint8), quality=95) for i in range(n)]


@pytest.mark.parametrize(
    "text, live",
    [
        ("rtsp://10.0.0.2:8554/cam", True),
        ("RTSP://cam/x", True),
        ("http://127.0.0.1:8080/stream.mjpg", True),
        ("https://cam.local/video", True),
        ("udp://0.0.0.0:5000", True),
        ("tcp://127.0.0.1:9000?listen", True),
        ("srt://host:9000", True),
        ("/dev/video0", True),
        ("/dev/v4l/by-id/usb-cam-video-index0", True),
        ("drive.mp4", False),
        ("route/summer", False),
        ("file:///tmp/x.mp4", False),
        ("ftp://host/x.mp4", False),
    ],
)
def test_is_live(text, live):
    assert is_live(text) is live


def test_mjpeg_over_http_wall_clock_and_pixels():
    """The frames of an MJPEG stream arrive in order, stamped with the wall clock, with the
    pixels that were sent."""
    with MjpegServer(_gray_jpegs(), fps=50, n_frames=80, stall_after=5) as srv:
        before = time.time()
        src = LiveSource(srv.url, stall_timeout=2, retries=0)
        assert src.describe() == f"stream {srv.url}" and src.kind == "stream"
        got = []
        for f in src.frames((8, 16)):
            got.append(f)
            if f.index == 79:
                break
    # the frames read while FFmpeg probed the stream come in a burst and only the newest is
    # kept; on a loaded machine the probing takes longer (seen: the first frame was 63)
    assert len(got) >= 5 and got[-1].index == 79
    assert src.clock == "wall"
    idx = np.array([f.index for f in got])
    assert (np.diff(idx) > 0).all()
    t = np.array([f.timestamp for f in got])
    assert (np.diff(t) >= 0).all() and before - 1 < t[0] < time.time()
    for f in got:
        assert f.image.shape == (8, 16) and f.image.dtype == np.float32
        assert abs(float(f.image.mean()) * 255 - LEVELS[f.index % 40]) < 2
        assert f.frame.width == 64 and f.frame.height == 48


def test_a_slow_consumer_gets_the_newest_frame_and_the_drops_are_counted():
    with MjpegServer(_gray_jpegs(), fps=100, n_frames=60, stall_after=5) as srv:
        src = LiveSource(srv.url, stall_timeout=2, retries=0)
        got = []
        for f in src.frames((8, 16)):
            got.append(f.index)
            if f.index >= 59:
                break
            time.sleep(0.05)  # five frames' time per frame: the localizer is slower
    assert src.n_dropped > 20
    assert src.n_received - len(got) >= src.n_dropped
    assert len(got) < 40 and got[-1] == 59
    assert max(np.diff(got)) > 1


def test_udp_mpegts_timestamps_from_the_stream():
    port = free_udp_port()
    frames = np.stack([np.full((64, 128), LEVELS[i], np.uint8) for i in range(40)])
    src = None
    with UdpTsSender(port, frames=frames, fps=50, loop=True) as sender:
        src = LiveSource(f"udp://127.0.0.1:{port}", stall_timeout=2, retries=0)
        got = []
        for f in src.frames((16, 32)):
            got.append(f)
            if len(got) == 30:
                break
    assert sender.error is None
    assert src.clock == "stream"
    for f in got:
        k = round(f.timestamp * 50)  # the sender's pts: frame k at k / 50 s
        assert f.timestamp == pytest.approx(k / 50, abs=1e-6)
        # H.264 over limited-range YUV: a gray level comes back within a couple of steps
        assert abs(float(f.image.mean()) * 255 - LEVELS[k % 40]) < 3


def test_an_upper_case_scheme_is_read_as_its_lower_case():
    # RFC 3986: a scheme is case-insensitive; FFmpeg refused HTTP:// ("protocol not found")
    with MjpegServer(_gray_jpegs(), fps=None, n_frames=5) as srv:
        url = "HTTP" + srv.url[len("http") :]
        src = LiveSource(url, stall_timeout=2, retries=0)
        got = list(src.frames((8, 16)))
    assert src.url == srv.url and src.describe() == f"stream {srv.url}"
    assert len(got) + src.n_dropped == 5 and src.n_received == 5


#: the line naming an option FFmpeg does not have
UNUSED = (
    "{source}: FFmpeg did not use the option '{key}': no FFmpeg format, device, protocol or "
    "codec has an option of that name"
)


@pytest.mark.parametrize("typo", ["rtsp_transprt", "timout", "stimeout"])
def test_an_option_ffmpeg_does_not_have_is_named(typo):
    # FFmpeg ignores an option it does not know without a word (stimeout: the RTSP socket
    # timeout's name before FFmpeg 5, now timeout); the stream is read all the same
    messages = []
    with MjpegServer(_gray_jpegs(), fps=None, n_frames=5) as srv:
        src = LiveSource(srv.url, options={typo: "5000000", "user_agent": "flyvpr"},
                         stall_timeout=2, retries=0, notify=messages.append)  # fmt: skip
        got = list(src.frames((8, 16)))
    assert messages == [UNUSED.format(source=f"stream {srv.url}", key=typo)]
    assert got and src.n_received == 5


def test_options_ffmpeg_has_are_not_named():
    # the format's, the protocols' (HTTP, TCP, UDP, RTSP) and the generic ones: whether this
    # stream uses them or not, FFmpeg has them
    valid = {
        "timeout": "5000000", "rw_timeout": "5000000", "user_agent": "flyvpr",
        "headers": "X-Flyvpr: 1\r\n", "reconnect": "0", "rtsp_transport": "tcp",
        "buffer_size": "65536", "fflags": "nobuffer", "probesize": "32",
        "analyzeduration": "0", "threads": "1",
    }  # fmt: skip
    messages = []
    with MjpegServer(_gray_jpegs(), fps=None, n_frames=5) as srv:
        src = LiveSource(srv.url, options=valid, stall_timeout=2, retries=0,
                         notify=messages.append)  # fmt: skip
        got = list(src.frames((8, 16)))
    assert messages == [] and got  # (probesize=32: the probe may take the first frame)


def test_camera_options_are_checked_before_the_device_is_opened(monkeypatch):
    def busy(*args, **kwargs):
        raise av.error.OSError(errno.EBUSY, "Device or resource busy", args[0])

    monkeypatch.setattr(av, "open", busy)
    options = {"video_size": "640x480", "framerate": "30", "input_format": "mjpeg",
               "pixel_format": "yuyv422", "vidoe_size": "640x480"}  # fmt: skip
    messages = []
    with pytest.raises(RecordingError, match="the device is busy"):
        LiveSource("/dev/null", options=options, notify=messages.append)
    assert messages == [UNUSED.format(source="camera /dev/null", key="vidoe_size")]


def test_options_are_not_checked_without_ffmpegs_libraries(monkeypatch):
    from flyvpr.sources import live

    monkeypatch.setattr(live, "_pyav_binary", lambda: None)
    live._ffmpeg_option_lookup.cache_clear()
    try:
        assert live._ffmpeg_option_lookup() is None
        messages = []
        with MjpegServer(_gray_jpegs(), fps=None, n_frames=5) as srv:
            src = LiveSource(srv.url, options={"timout": "1"}, notify=messages.append)
            src.close()
        assert messages == []
    finally:
        live._ffmpeg_option_lookup.cache_clear()


def test_a_stall_is_retried_then_raises():
    messages = []
    with MjpegServer(_gray_jpegs(), fps=100, n_frames=10, stall_after=30) as srv:
        src = LiveSource(srv.url, stall_timeout=0.5, open_timeout=1, retries=2,
                         notify=messages.append)  # fmt: skip
        n = 0
        t0 = time.monotonic()
        with pytest.raises(RecordingError, match=r"stream http://127\.0\.0\.1:\d+/stream\.mjpg: "
                           r".*gave up after 2 reconnection attempts"):  # fmt: skip
            for _ in src.frames((8, 16)):
                n += 1
    assert n >= 1 and src.n_received == 10
    assert len(messages) == 2 and all("reconnecting" in m and srv.url in m for m in messages)
    assert "stalled: no data for 0.5 s" in messages[0]
    assert time.monotonic() - t0 < 15


def test_an_http_server_closing_the_stream_ends_it():
    # FFmpeg reports an orderly close of an MJPEG-over-HTTP stream as EIO: the end, as the
    # end of a file, not a broken connection to reopen
    messages = []
    with MjpegServer(_gray_jpegs(), fps=None, n_frames=12) as srv:
        src = LiveSource(srv.url, stall_timeout=2, retries=3, notify=messages.append)
        got = []
        for f in src.frames((8, 16)):
            got.append(f)
            if len(got) > 30:  # the server serves the stream again at each reconnection
                break
    assert src.ended and src.n_received == 12 and src.n_reconnects == 0
    assert len(got) + src.n_dropped == 12 and messages == []


@pytest.mark.parametrize("how", ["reset_first", "cut_first"])
def test_a_reset_or_cut_connection_is_reopened(how):
    # a reset (RST), or an orderly close in the middle of a JPEG, is a broken connection:
    # reopened, and the stream read on to its end
    messages = []
    with MjpegServer(_gray_jpegs(), fps=None, n_frames=12, **{how: True}) as srv:
        src = LiveSource(srv.url, stall_timeout=2, retries=1, notify=messages.append)
        for n, _ in enumerate(src.frames((8, 16))):
            if n > 40:
                break
    assert src.ended and src.n_reconnects == 1
    assert 12 < src.n_received <= 25  # the first connection's frames may be cut by the reset
    assert len(messages) == 1 and "the connection broke" in messages[0]


def test_stop_ends_the_frames_promptly():
    with MjpegServer(_gray_jpegs(), fps=30, duration=20) as srv:
        src = LiveSource(srv.url, stall_timeout=5, retries=0)
        n = 0
        t0 = time.monotonic()
        for _ in src.frames((8, 16)):
            n += 1
            if n == 3:
                src.stop()
        assert n == 3 and time.monotonic() - t0 < 3


def test_unreachable_url():
    port = free_udp_port()  # nothing listens on it over TCP either
    with pytest.raises(RecordingError, match=rf"^stream http://127\.0\.0\.1:{port}/x: cannot "
                       r"open: Connection refused \(expected a video stream"):  # fmt: skip
        LiveSource(f"http://127.0.0.1:{port}/x", open_timeout=2)


def test_silent_udp_port_times_out():
    port = free_udp_port()
    t0 = time.monotonic()
    with pytest.raises(RecordingError, match=rf":{port}: no answer within 0\.5 s"):
        LiveSource(f"udp://127.0.0.1:{port}", open_timeout=0.5)
    assert time.monotonic() - t0 < 5


def test_garbage_is_named():
    with MjpegServer([], garbage=True, duration=3) as srv:
        with pytest.raises(RecordingError, match=r"sends nothing FFmpeg can read as video"):
            LiveSource(srv.url, open_timeout=2)


def test_missing_camera():
    with pytest.raises(FileNotFoundError, match=r"^camera /dev/video97: no such device"):
        LiveSource("/dev/video97")


def test_busy_camera(monkeypatch, tmp_path):
    """A device another program holds: FFmpeg's EBUSY becomes one line saying so."""

    def busy(*args, **kwargs):
        raise av.error.OSError(errno.EBUSY, "Device or resource busy", args[0])

    device = "/dev/null"  # exists, so the open is tried
    monkeypatch.setattr(av, "open", busy)
    with pytest.raises(RecordingError, match=r"^camera /dev/null: cannot open: the device is busy"):
        LiveSource(device)


def test_password_is_not_shown():
    port = free_udp_port()
    with pytest.raises(RecordingError) as info:
        LiveSource(f"rtsp://admin:hunter2@127.0.0.1:{port}/cam", open_timeout=1)
    assert "hunter2" not in str(info.value) and "admin:***@" in str(info.value)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"stall_timeout": 0}, "stall_timeout must be > 0.0 seconds; got 0.0"),
        ({"open_timeout": float("inf")}, "open_timeout must be finite; got inf"),
        ({"retries": -1}, r"retries must be an integer >= 0; got -1"),
        ({"retries": 1.5}, r"retries must be an integer >= 0; got 1.5"),
    ],
)
def test_parameters_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LiveSource("udp://127.0.0.1:9", **kwargs)


def test_not_a_live_source():
    with pytest.raises(ValueError, match=r"url must be a stream URL .* got 'drive\.mp4'"):
        LiveSource("drive.mp4")


def test_a_stream_of_damaged_jpegs_raises():
    """An MJPEG stream whose parts are torn JPEGs: named, after stall_timeout."""
    good = jpeg_bytes(np.zeros((48, 64), np.uint8))
    rng = np.random.default_rng(0)
    torn = [good[:200] + rng.integers(0, 256, 2000, dtype=np.uint8).tobytes() for _ in range(5)]
    with MjpegServer([good] * 3 + torn * 100, fps=50, duration=10) as srv:
        src = LiveSource(srv.url, stall_timeout=1, retries=0)
        with pytest.raises(RecordingError, match=r"no decodable frame for 1 s \(\d+ damaged JPEG"):
            for _ in src.frames((8, 16)):
                pass
    assert src.n_corrupt > 10


def test_a_torn_jpeg_is_told_from_a_whole_one():
    from flyvpr.sources.live import _whole_jpeg

    good = jpeg_bytes(np.full((48, 64), 120, np.uint8))
    assert _whole_jpeg(good) and _whole_jpeg(good + b"\0" * 600)  # padded after its end
    sos = good.rfind(b"\xff\xda")
    for cut in (len(good) - 2, (sos + len(good)) // 2, sos + 4, sos, 100):
        assert not _whole_jpeg(good[:cut]), cut
    # an EXIF-like thumbnail (a whole JPEG inside) before the picture: its end marker does not
    # make a torn picture whole
    inner = jpeg_bytes(np.zeros((8, 8), np.uint8))
    framed = good[:2] + b"\xff\xe1" + (len(inner) + 2).to_bytes(2, "big") + inner + good[2:]
    assert _whole_jpeg(framed) and not _whole_jpeg(framed[: len(framed) - 40])


def test_a_torn_jpeg_is_skipped_not_localized():
    """FFmpeg decodes half a JPEG without an error (the rest gray): it must not become a frame."""
    rng = np.random.default_rng(0)
    noise = rng.integers(-8, 9, (6, 120, 160))
    frames = [jpeg_bytes((LEVELS[i] + noise[i]).astype(np.uint8), quality=90) for i in range(6)]
    torn = frames[3][: len(frames[3]) * 7 // 10]
    assert av.CodecContext.create("mjpeg", "r").decode(av.Packet(torn))  # what FFmpeg does
    # slow enough that the consumer takes every frame after the first ones
    with MjpegServer(frames[:3] + [torn] + frames[4:], fps=5, n_frames=6) as srv:
        src = LiveSource(srv.url, stall_timeout=2, retries=0)
        got = list(src.frames((8, 16)))
    seen = {f.index: float(f.frame.to_ndarray(format="gray").mean()) for f in got}
    assert 3 not in seen and {4, 5} <= set(seen)
    assert all(abs(level - LEVELS[i]) <= 1 for i, level in seen.items()), seen
    assert len(got) + src.n_dropped + src.n_undecodable == src.n_received == 6
    assert src.n_undecodable == src.n_corrupt == 1


def test_a_camera_that_hangs_in_the_middle_of_a_jpeg_is_reconnected():
    """The first connection sends 20 frames and half a JPEG, then hangs: after the stall the
    reader reconnects; the torn JPEG it hands over after the silence is not a stream of
    damage, and the frames go on."""
    with MjpegServer(_gray_jpegs(), fps=50, n_frames=60, hang_first=(20, 30)) as srv:
        src = LiveSource(srv.url, stall_timeout=1, retries=3)
        got = [f.index for f in src.frames((8, 16))]
    assert src.n_reconnects >= 1 and len(got) > 40
    assert src.ended


def test_the_end_of_a_stream_ends_the_frames(tmp_path):
    """A server that sends a short MPEG-TS over TCP and closes: the frames end, no error."""
    import socket
    import threading

    path = tmp_path / "short.ts"
    with av.open(str(path), "w", format="mpegts") as c:
        st = c.add_stream("mpeg2video", rate=25)
        st.width, st.height, st.pix_fmt = 64, 48, "yuv420p"
        for i in range(20):
            frame = av.VideoFrame.from_ndarray(np.full((48, 64), LEVELS[i], np.uint8), "gray")
            frame.pts = i
            for packet in st.encode(frame):
                c.mux(packet)
        for packet in st.encode():
            c.mux(packet)
    data = path.read_bytes()
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)

    def serve():
        conn, _ = server.accept()
        conn.sendall(data)
        conn.close()

    threading.Thread(target=serve, daemon=True).start()
    src = LiveSource(f"tcp://127.0.0.1:{server.getsockname()[1]}", stall_timeout=2, retries=0)
    got = [f.index for f in src.frames((8, 16))]
    server.close()
    assert src.ended and src.n_received == 20 and src.clock == "stream"
    assert got and got[-1] == 19  # the last frame is always taken


def test_an_interrupt_while_the_stream_opens_is_taken_at_once():
    """FFmpeg's open blocks in C; a signal (Ctrl-C, the CLI's SIGTERM) must not wait for its
    open_timeout: a server that accepts and never answers, a signal after 0.5 s."""
    import signal
    import socket
    import threading

    class Interrupted(Exception):
        pass

    def handler(signum, frame):
        raise Interrupted

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        url = f"http://127.0.0.1:{server.getsockname()[1]}/stream.mjpg"
        previous = signal.signal(signal.SIGUSR1, handler)
        timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGUSR1))
        try:
            timer.start()
            t0 = time.monotonic()
            with pytest.raises(Interrupted):
                LiveSource(url, open_timeout=20)
            assert time.monotonic() - t0 < 3.0
        finally:
            timer.cancel()
            signal.signal(signal.SIGUSR1, previous)


def test_a_web_page_that_keeps_its_connection_open_is_named_as_one():
    # A camera's HTML page instead of its stream: FFmpeg waits for a frame that never comes
    # and times out; the message says what the address answers with and what to give.
    import http.server

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.end_headers()
            self.wfile.write(b"<html><body><img src='/video.mjpg'></body></html>")
            self.wfile.flush()
            time.sleep(4)  # (the connection stays open)

        def log_message(self, *args):
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{httpd.server_address[1]}/"
    try:
        with pytest.raises(
            RecordingError,
            match=rf"^stream {re.escape(url)}: answers with a web page \(text/html\), not a "
            r"video stream: give the address of the stream itself",
        ):
            LiveSource(url, open_timeout=1.0)
    finally:
        httpd.shutdown()
        httpd.server_close()
    # a stream that is slow to start is not a page: the usual message
    from flyvpr.sources.live import _web_page_type

    with MjpegServer([], garbage=True, duration=2) as srv:
        assert _web_page_type(srv.url, 1.0) is None
    assert _web_page_type("udp://127.0.0.1:9", 1.0) is None
    assert _web_page_type("http://user:pw@127.0.0.1:9/", 1.0) is None  # (never asked)
    # a server that takes the connection and answers nothing: the question gives up within
    # its own limit (2 s), whatever the open's timeout
    import socket

    silent = socket.create_server(("127.0.0.1", 0))
    try:
        t0 = time.monotonic()
        assert _web_page_type(f"http://127.0.0.1:{silent.getsockname()[1]}/", 10.0) is None
        assert time.monotonic() - t0 < 4.0
    finally:
        silent.close()
