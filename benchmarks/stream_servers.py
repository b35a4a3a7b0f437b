"""Live streams served on localhost, for the live benchmark and the tests of live sources.

* :class:`MjpegServer`: JPEG frames as ``multipart/x-mixed-replace`` over HTTP (what IP cameras
  and ``mjpg-streamer`` send), from a thread, at a set rate or as fast as the client reads;
  it can also stall, close, or send garbage instead of JPEG.
* :class:`UdpTsSender`: an MPEG-TS stream over UDP muxed with PyAV, from frames (encoded
  with H.264 or MPEG-2 as it goes) or from a video file's packets, paced at their timestamps.

Nothing here is part of the package.
"""

from __future__ import annotations

import http.server
import io
import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np

__all__ = ["MjpegServer", "UdpTsSender", "free_udp_port", "jpeg_bytes", "udp_port_bound"]


def jpeg_bytes(image: np.ndarray, quality: int = 85) -> bytes:
    """``image`` (H, W) or (H, W, 3) uint8 as JPEG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(image, np.uint8)).save(buf, "JPEG", quality=quality)
    return buf.getvalue()


def _part_head(n: int) -> bytes:
    """The multipart header of a JPEG of ``n`` bytes in the MJPEG stream."""
    return b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % n


class _Handler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *args):  # quiet
        pass

    def _half_jpeg(self, data: bytes) -> bool:
        """Send a part head and the first half of ``data``; False if the client left."""
        try:
            self.wfile.write(_part_head(len(data)) + data[: len(data) // 2])
            self.wfile.flush()
        except OSError:
            return False
        return True

    def do_GET(self):  # noqa: N802 - http.server's name
        srv = self.server.owner
        if srv.garbage:
            self.send_response(200)
            self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
            self.end_headers()
            rng = np.random.default_rng(0)
            end = time.monotonic() + srv.duration
            while time.monotonic() < end and not srv.closing:
                try:
                    self.wfile.write(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
                except OSError:
                    return
                time.sleep(0.01)
            return
        self.send_response(200)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
        self.end_headers()
        start = time.monotonic()
        i = 0
        hangs = srv.hang_first is not None and not srv.was_hung
        srv.was_hung = srv.was_hung or hangs
        while not srv.closing and not srv.hung:
            if srv.n_frames is not None and i >= srv.n_frames:
                break
            if hangs and i >= srv.hang_first[0]:
                break
            if srv.duration is not None and time.monotonic() - start >= srv.duration:
                break
            if srv.fps is not None:
                delay = start + i / srv.fps - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            data = srv.jpegs[i % len(srv.jpegs)]
            head = _part_head(len(data))
            sent = time.time()  # before the write: the client may have the frame before it returns
            try:
                self.wfile.write(head + data + b"\r\n")
                self.wfile.flush()
            except OSError:  # the client left
                break
            srv.sent.append(sent)
            i += 1
        if hangs:
            # half of the next JPEG, then silence: a camera that hangs in the middle of a picture
            if self._half_jpeg(srv.jpegs[i % len(srv.jpegs)]):
                end = time.monotonic() + srv.hang_first[1]
                while time.monotonic() < end and not srv.closing:
                    time.sleep(0.05)
            return
        if srv.cut_first and not srv.was_cut:
            # the first connection closes (orderly) in the middle of a JPEG: a broken stream
            srv.was_cut = True
            self._half_jpeg(srv.jpegs[i % len(srv.jpegs)])
            srv.finished.set()
            return
        if srv.reset_first and not srv.was_reset:
            # the first connection ends in a reset (RST), as when the camera's server or the
            # network drops it; later ones end as the others
            srv.was_reset = True
            self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            self.connection.close()
            srv.finished.set()
            return
        if srv.stall_after:
            # keep the connection open and silent: a camera that hangs (and stays hung for
            # every later connection)
            srv.hung = True
            end = time.monotonic() + srv.stall_after
            while time.monotonic() < end and not srv.closing:
                time.sleep(0.05)
        srv.finished.set()


class MjpegServer:
    """Serve JPEG frames as an MJPEG stream (``multipart/x-mixed-replace``) on localhost.

    Parameters
    ----------
    jpegs : list of bytes
        The frames, cycled.
    fps : float or None
        Frames per second; None sends as fast as the client reads (TCP paces it).
    n_frames, duration : int or float, optional
        Stop after so many frames or seconds (then close the connection, or stall first).
    stall_after : float, optional
        After the last frame, keep the connection open without sending for so many seconds.
    garbage : bool
        Send random bytes under the MJPEG content type instead of frames (for ``duration`` s).
    reset_first : bool
        End the first connection with a reset (RST) instead of an orderly close (later
        connections: as without).
    cut_first : bool
        End the first connection after half of one more JPEG (an orderly close in the middle
        of a frame; later connections: as without).
    hang_first : (int, float), optional
        The first connection sends so many frames, then half of one more JPEG, then hangs
        silent for so many seconds (a camera that hangs in the middle of a picture; later
        connections: as without).

    Attributes
    ----------
    url : str
    sent : list of float
        ``time.time()`` just before each frame was written to the socket.
    """

    def __init__(
        self,
        jpegs,
        fps=30.0,
        *,
        n_frames=None,
        duration=None,
        stall_after=None,
        garbage=False,
        reset_first=False,
        cut_first=False,
        hang_first=None,
    ):
        self.jpegs, self.fps = list(jpegs), fps
        self.hang_first, self.was_hung = hang_first, False
        self.reset_first, self.was_reset = reset_first, False
        self.cut_first, self.was_cut = cut_first, False
        self.n_frames, self.duration = n_frames, duration
        self.stall_after, self.garbage = stall_after, garbage
        if garbage and duration is None:
            self.duration = 5.0
        self.sent: list[float] = []
        self.finished = threading.Event()
        self.closing = self.hung = False
        self._httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        self._httpd.daemon_threads = True
        self._httpd.owner = self
        self.url = f"http://127.0.0.1:{self._httpd.server_address[1]}/stream.mjpg"
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)

    def __enter__(self) -> MjpegServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.closing = True
        self._httpd.shutdown()
        self._httpd.server_close()


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def udp_port_bound(port: int) -> bool:
    """Whether a process on this machine has bound UDP ``port`` (Linux: /proc/net/udp)."""
    suffix = f":{port:04X}"
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        # each line: "sl local_address rem_address ..." with the address as HEXIP:HEXPORT
        if any(line.split()[1].endswith(suffix) for line in lines if line.strip()):
            return True
    return False


class UdpTsSender:
    """Send an MPEG-TS stream to ``udp://127.0.0.1:port`` from a thread, muxed with PyAV.

    Parameters
    ----------
    port : int
    frames : ndarray, shape (n, H, W) or (n, H, W, 3), uint8, optional
        Encoded as it goes (``codec``, a keyframe every ``gop`` frames, no B-frames).
    video : str or Path, optional
        Instead of ``frames``: a video file whose packets are sent as they are (remuxed).
    fps : float
        Pace of ``frames``; a file is paced by its packets' timestamps.
    loop : bool
        Send ``frames`` again and again until closed.
    """

    def __init__(self, port, *, frames=None, video=None, fps=30.0, codec="libx264", gop=10,
                 loop=False):  # fmt: skip
        self.port, self.frames, self.video = port, frames, video
        self.fps, self.codec, self.gop, self.loop = fps, codec, gop, loop
        self.n_sent = 0
        self.closing = False
        self.done = threading.Event()
        self.error = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _output(self):
        import av

        return av.open(f"udp://127.0.0.1:{self.port}?pkt_size=1316", "w", format="mpegts")

    def _run(self):
        try:
            if self.video is not None:
                self._send_file()
            else:
                self._send_frames()
        except Exception as exc:  # surfaced by the test or benchmark that reads .error
            self.error = exc
        finally:
            self.done.set()

    def _send_frames(self):
        import av

        out = self._output()
        h, w = self.frames.shape[1:3]
        st = out.add_stream(self.codec, rate=int(round(self.fps)))
        st.width, st.height, st.pix_fmt = w, h, "yuv420p"
        if self.codec == "libx264":
            st.options = {"tune": "zerolatency", "preset": "ultrafast", "g": str(self.gop)}
        else:
            st.codec_context.gop_size = self.gop
        fmt = "gray" if self.frames.ndim == 3 else "rgb24"
        start = time.monotonic()
        i = 0
        try:
            while not self.closing:
                if i >= len(self.frames) and not self.loop:
                    break
                frame = av.VideoFrame.from_ndarray(self.frames[i % len(self.frames)], format=fmt)
                frame.pts = i
                for packet in st.encode(frame):
                    out.mux(packet)
                self.n_sent += 1
                i += 1
                delay = start + i / self.fps - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            for packet in st.encode():
                out.mux(packet)
        finally:
            out.close()

    def _send_file(self):
        import av

        src = av.open(str(self.video))
        out = self._output()
        try:
            ist = src.streams.video[0]
            ost = out.add_stream_from_template(ist)
            start = time.monotonic()
            t0 = None
            for packet in src.demux(ist):
                if self.closing:
                    break
                if packet.dts is None:  # the demuxer's flush packet
                    continue
                t = float(packet.dts * ist.time_base)
                t0 = t if t0 is None else t0
                delay = start + (t - t0) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                packet.stream = ost
                out.mux(packet)
                self.n_sent += 1
        finally:
            out.close()
            src.close()

    def __enter__(self) -> UdpTsSender:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.closing = True
        self._thread.join(timeout=5)
