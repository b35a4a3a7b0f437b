"""``flyvpr localize --map MAP URL``: live streams served from inside the tests, Ctrl-C, stalls,
bad input, and the live view saved as a Rerun recording and read back."""

from __future__ import annotations

import csv
import os
import signal
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

from benchmarks.stream_servers import MjpegServer, free_udp_port, jpeg_bytes  # noqa: E402
from flyvpr.cli import main  # noqa: E402
from flyvpr.localization.maps import Map  # noqa: E402
from flyvpr.synthetic import make_route, save_route  # noqa: E402

N = 30


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    """A synthetic route: a ``pixels`` map of its summer frames (with positions) and the same
    frames as JPEG at 4x the map's size, so each served frame has one right answer."""
    root = tmp_path_factory.mktemp("live")
    r = make_route(N, size=(32, 64), conditions=("summer",), random_state=5)
    save_route(r, root / "png")
    positions = root / "xy.csv"
    positions.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},1.5\n" for i in range(N)))
    m = Map.build(root / "png" / "summer", "pixels", positions=positions)
    m.save(root / "route.map")
    big = np.repeat(np.repeat(r.images["summer"], 4, axis=1), 4, axis=2)
    jpegs = [jpeg_bytes(np.rint(im * 255).astype(np.uint8), quality=95) for im in big]
    return {"map": root / "route.map", "jpegs": jpegs, "png": root / "png" / "summer"}


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _records(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _check_answers(rows):
    """Each served frame i (cycled) shows place i: pixels answers it exactly."""
    assert rows
    for r in rows:
        assert int(r["place"]) == int(r["frame"]) % N
        assert float(r["x"]) == 3.0 * int(r["place"]) and float(r["y"]) == 1.5


def test_stall_ends_with_exit_1_and_every_record_kept(route, tmp_path, capsys):
    out = tmp_path / "where.csv"
    with MjpegServer(route["jpegs"], fps=60, n_frames=N, stall_after=30) as srv:
        code, stdout, err = _run(
            capsys, "localize", "--map", route["map"], srv.url, "--out", out,
            "--stall-timeout", 0.5, "--retries", 1, "--open-timeout", 1,
        )  # fmt: skip
    assert code == 1
    lines = err.strip().splitlines()
    assert lines[-1].startswith(f"flyvpr localize: error: stream {srv.url}: ")
    assert lines[-1].endswith("gave up after 1 reconnection attempt")
    assert any("reconnecting (1/1)" in line for line in lines[:-1])
    rows = _records(out)
    _check_answers(rows)
    assert [c for c in rows[0]] == [
        "frame", "timestamp", "place", "confidence", "state", "relocated", "x", "y", "latency_ms",
    ]  # fmt: skip
    assert rows[-1]["frame"] == str(N - 1)  # the last frame before the stall was processed
    # wall-clock stamps (MJPEG carries none), in order, and a latency for each
    t = np.array([float(r["timestamp"]) for r in rows])
    assert (np.diff(t) >= 0).all() and abs(t[-1] - time.time()) < 60
    assert all(0 <= float(r["latency_ms"]) < 5000 for r in rows)
    received = int(stdout.split(" frames received")[0].rsplit(" ", 1)[-1])
    assert received == N
    assert f"{len(rows)} localized, {N - len(rows)} dropped" in stdout
    assert "ended: the stream failed (the error line below says how)" in stdout
    assert "wall clock" in stdout


def test_a_stream_the_server_ends_and_a_damaged_frame_add_up(route, tmp_path, capsys):
    # frame 5 is not a JPEG; the server then ends the stream: exit 0, and the frames
    # received are the ones localized, dropped and damaged, each counted once
    jpegs = list(route["jpegs"])
    jpegs[5] = b"not a jpeg" * 50
    out = tmp_path / "where.csv"
    with MjpegServer(jpegs, fps=30, n_frames=N) as srv:
        code, stdout, err = _run(
            capsys, "localize", "--map", route["map"], srv.url, "--out", out, "--retries", 0
        )
    assert code == 0, err
    assert "ended: the stream ended" in stdout and "reconnecting" not in err
    rows = _records(out)
    assert "5" not in [r["frame"] for r in rows]
    dropped = int(stdout.split(" dropped")[0].rsplit(" ", 1)[-1])
    assert f"{N} frames received, {len(rows)} localized, " in stdout
    assert "1 damaged packet skipped" in stdout
    assert len(rows) + dropped + 1 == N


def test_the_same_ctrl_c_delivered_twice_stops_once(monkeypatch):
    # rerun's own handler (with --view and --view-save) passes a Ctrl-C on: two SIGINTs at
    # once are one Ctrl-C (the run finishes its frame and writes its summary); a second one
    # a moment later interrupts at once
    from flyvpr.cli import _live

    class Source:
        stops = 0

        def stop(self):
            self.stops += 1

    src = Source()
    before = signal.getsignal(signal.SIGINT)  # (ignored in a background job: SIG_IGN)
    with _live._first_ctrl_c_stops(src) as state:
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        assert state["interrupted"] and src.stops == 1
        time.sleep(_live._SECOND_CTRL_C + 0.05)
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.5)
    assert signal.getsignal(signal.SIGINT) == before  # restored on the way out


def test_ctrl_c_ends_with_exit_130_and_every_processed_frame_written(route, tmp_path, capsys):
    out = tmp_path / "where.jsonl"
    timer = threading.Timer(2.0, os.kill, (os.getpid(), signal.SIGINT))
    with MjpegServer(route["jpegs"], fps=30, duration=30) as srv:
        timer.start()
        try:
            code, stdout, err = _run(capsys, "localize", "--map", route["map"], srv.url,
                                     "--out", out)  # fmt: skip
        finally:
            timer.cancel()
    assert code == 130
    assert "ended by Ctrl-C" in stdout
    text = out.read_text()
    assert text.endswith("\n")
    import json

    rows = [json.loads(line) for line in text.splitlines()]
    assert len(rows) >= 20  # two seconds at 30 frames/s, less the start
    assert f"{len(rows)} localized" in stdout
    for r in rows:
        assert r["place"] == r["frame"] % N


def test_records_are_flushed_as_they_are_made(route, tmp_path, capsys):
    """While the run goes on, the file already holds the records so far (tail -f works)."""
    out = tmp_path / "where.csv"
    seen = []

    def peek():
        time.sleep(1.5)
        seen.append(out.read_text() if out.exists() else "")
        os.kill(os.getpid(), signal.SIGINT)

    with MjpegServer(route["jpegs"], fps=30, duration=30) as srv:
        t = threading.Thread(target=peek)
        t.start()
        code, _, _ = _run(capsys, "localize", "--map", route["map"], srv.url, "--out", out)
        t.join()
    assert code == 130
    lines = seen[0].splitlines()
    assert len(lines) > 10 and lines[0].startswith("frame,timestamp")
    assert out.read_text().startswith(seen[0])


@pytest.mark.parametrize(
    "source, match",
    [
        ("http://127.0.0.1:{port}/cam.mjpg", "stream http://127.0.0.1:{port}/cam.mjpg: cannot open:"
         " Connection refused"),
        ("/dev/video97", "camera /dev/video97: no such device"),
        ("udp://127.0.0.1:{port}", "stream udp://127.0.0.1:{port}: no answer within 0.5 s"),
    ],
)  # fmt: skip
def test_bad_sources_one_line_exit_1(route, tmp_path, capsys, source, match):
    port = free_udp_port()
    source, match = source.format(port=port), match.format(port=port)
    out = tmp_path / "where.csv"
    code, stdout, err = _run(capsys, "localize", "--map", route["map"], source, "--out", out,
                             "--open-timeout", 0.5)  # fmt: skip
    assert code == 1
    assert err.count("\n") == 1 and err.startswith(f"flyvpr localize: error: {match}")
    assert not out.exists()


def test_a_stream_that_never_sends_a_whole_picture_leaves_no_records(route, tmp_path, capsys):
    # torn JPEGs only: no frame is localized; no file of a header only, no "wrote"
    good = jpeg_bytes(np.zeros((48, 64), np.uint8))
    torn = [good[: len(good) // 2]] * 200
    out = tmp_path / "new" / "deep" / "never.csv"  # folders made for it go too
    with MjpegServer(torn, fps=50, duration=6) as srv:
        code, stdout, err = _run(capsys, "localize", "--map", route["map"], srv.url, "--retries",
                                 0, "--stall-timeout", 1, "--out", out)  # fmt: skip
    assert code == 1 and "no decodable frame" in err
    assert " 0 localized" in stdout and "wrote" not in stdout
    assert not (tmp_path / "new").exists()


def test_garbage_stream_one_line_exit_1(route, tmp_path, capsys):
    with MjpegServer([], garbage=True, duration=3) as srv:
        code, _, err = _run(capsys, "localize", "--map", route["map"], srv.url,
                            "--open-timeout", 2)  # fmt: skip
    assert code == 1 and err.count("\n") == 1
    assert f"stream {srv.url}: sends nothing FFmpeg can read as video" in err


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--every", "2"], "--every: not with a live source"),
        (["--realtime"], "--realtime: not with a live source"),
        (["--ground-truth", "frames", "--tolerance", "1"], "--ground-truth: not with a live"),
        (["--render", "x.mp4"], "--render: not with a live source"),
        (["--fit-calibration", "t.json"], "--fit-calibration: not with a live source"),
        (["--view-save", "x.txt"], "--view-save x.txt: expected a .rrd file"),
        (["--view", "--view-port", "9000", "--view-data-port", "9000"], "two ports are needed"),
        (["--view-port", "9001"], "--view-port: only with --view"),
        (["--view-data-port", "9002"], "--view-data-port: only with --view"),
        (["--view", "--view-port", "70000"], "--view-port 70000: a port is 1-65535"),
        (["--mcap-thumbnails"], "--mcap-thumbnails needs --out FILE.mcap"),
        (["--mcap-thumbnails", "--out", "t.csv"], "--mcap-thumbnails needs --out FILE.mcap"),
    ],
)
def test_live_usage_errors(route, capsys, extra, match):
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9", *extra)
    assert code == 2 and match in err


@pytest.mark.parametrize("text", ["rtsp_transport", "=tcp", " =tcp"])
def test_a_stream_option_without_a_key_is_one_line(route, capsys, text):
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9",
                        "--stream-option", text)  # fmt: skip
    assert code == 2 and err.count("\n") == 1
    assert f"--stream-option: expected KEY=VALUE (an FFmpeg option); got {text!r}" in err


def test_a_stream_option_given_twice_or_empty_is_refused(route, capsys):
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9",
                        "--stream-option", "rtsp_transport=tcp",
                        "--stream-option", "fflags=nobuffer",
                        "--stream-option", "rtsp_transport=udp")  # fmt: skip
    assert code == 2 and err.count("\n") == 1
    assert "--stream-option rtsp_transport: given twice ('tcp' and 'udp'); give it once" in err
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9",
                        "--stream-option", "rtsp_transport=")  # fmt: skip
    assert code == 2 and err.count("\n") == 1
    assert "--stream-option: expected KEY=VALUE with a value; got 'rtsp_transport='" in err


def test_a_stream_option_ffmpeg_does_not_have_is_named(route, capsys):
    # a misspelt option: FFmpeg would ignore it without a word; the run goes on
    with MjpegServer(route["jpegs"], fps=None, n_frames=N) as srv:
        code, stdout, err = _run(
            capsys, "localize", "--map", route["map"], srv.url, "--retries", 0,
            "--stream-option", "rw_timeout=5000000", "--stream-option", "timout=5000000",
        )  # fmt: skip
    assert code == 0, err
    assert err.splitlines() == [
        f"flyvpr localize: stream {srv.url}: FFmpeg did not use the option 'timout': no "
        "FFmpeg format, device, protocol or codec has an option of that name"
    ]
    assert f"{N} frames received" in stdout


def test_live_calibration_is_read_and_needs_the_cann(route, tmp_path, capsys):
    # the live path reads the table too: a missing file, then a map without the CANN
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9",
                        "--calibration", tmp_path / "none.json")  # fmt: skip
    assert code == 2 and "has no CANN filter" in err  # the method is checked first
    table = tmp_path / "t.json"
    table.write_text('{"format": "flyvpr-confidence-table", "table": [0.1]}')
    code, _, err = _run(capsys, "localize", "--map", route["map"], "udp://127.0.0.1:9",
                        "--calibration", table)  # fmt: skip
    assert code == 2 and "pixels" in err and "has no CANN filter" in err


def test_live_options_need_a_live_source(route, capsys):
    code, _, err = _run(capsys, "localize", "--map", route["map"], route["png"],
                        "--stall-timeout", 2)  # fmt: skip
    assert code == 2 and "--stall-timeout: only for a live SOURCE" in err
    code, _, err = _run(capsys, "localize", "--dataset", "nordland", "--retries", 2)
    assert code == 2 and "--retries needs --map MAP SOURCE" in err


# -- the live view ---------------------------------------------------------------------------
rr = pytest.importorskip("rerun")


def _read_rrd(path) -> dict:
    """entity path -> {component column: list of values, timeline: list}, from an .rrd."""
    from rerun.chunk import RrdReader

    out: dict = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        cols = out.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            if name.startswith("rerun.") or name in ("log_time", "time"):
                continue
            cols.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


def _flat(values):
    return [v[0] if isinstance(v, list) else v for v in values]


def test_view_save_of_a_live_run_holds_what_was_logged(route, tmp_path, capsys):
    out, trace = tmp_path / "where.csv", tmp_path / "trace.rrd"
    with MjpegServer(route["jpegs"], fps=30, n_frames=2 * N, stall_after=30) as srv:
        code, stdout, _ = _run(
            capsys, "localize", "--map", route["map"], srv.url, "--out", out,
            "--view-save", trace, "--stall-timeout", 0.5, "--retries", 0,
        )  # fmt: skip
    assert code == 1
    rows = _records(out)
    got = _read_rrd(trace)
    for entity in ("/query", "/input", "/match", "/filter/activity", "/fix/place",
                   "/fix/confidence", "/fix/localized", "/fix/events", "/route/places",
                   "/route/position"):  # fmt: skip
        assert entity in got, entity
    shown = int(stdout.split("live view: ")[1].split(" frames shown")[0])
    assert shown >= 1
    frames = got["/fix/place"]["frame"]
    places = _flat(got["/fix/place"]["Scalars:scalars"])
    assert len(places) == shown
    by_frame = {int(r["frame"]): r for r in rows}
    for f, p in zip(frames, places, strict=True):  # the view shows what the records say
        assert int(p) == int(by_frame[f]["place"])
    bars = got["/filter/activity"]
    assert len(bars["frame"]) == shown
    assert len(got["/route/places"]["Points2D:positions"][0]) == N


def test_view_save_of_a_recording_has_every_frame(route, tmp_path, capsys):
    out, trace = tmp_path / "where.csv", tmp_path / "trace.rrd"
    code, stdout, _ = _run(capsys, "localize", "--map", route["map"], route["png"],
                           "--out", out, "--view-save", trace)  # fmt: skip
    assert code == 0 and f"live view: {N} frames shown, 0 skipped" in stdout
    rows = _records(out)
    got = _read_rrd(trace)
    assert got["/fix/place"]["frame"] == list(range(N))
    assert [int(p) for p in _flat(got["/fix/place"]["Scalars:scalars"])] == [
        int(r["place"]) for r in rows
    ]
    conf = _flat(got["/fix/confidence"]["Scalars:scalars"])
    assert conf == pytest.approx([float(r["confidence"]) for r in rows], rel=1e-6)


def test_outputs_in_missing_folders_are_created(route, tmp_path, capsys):
    # A recording: --out through atomic_open, --view-save through rerun's own file sink.
    out, trace = tmp_path / "a" / "b" / "where.csv", tmp_path / "c" / "d" / "trace.rrd"
    code, _, _ = _run(capsys, "localize", "--map", route["map"], route["png"],
                      "--out", out, "--view-save", trace)  # fmt: skip
    assert code == 0 and len(_records(out)) == N
    assert _read_rrd(trace)["/fix/place"]["frame"] == list(range(N))
    # A live stream: the records file is written straight to its target, flushed.
    live = tmp_path / "e" / "f" / "where.csv"
    with MjpegServer(route["jpegs"], fps=60, n_frames=N, stall_after=10) as srv:
        code, _, _ = _run(
            capsys, "localize", "--map", route["map"], srv.url, "--out", live,
            "--stall-timeout", 0.5, "--retries", 0,
        )  # fmt: skip
    assert code == 1  # the stall ends it; every record so far is kept
    _check_answers(_records(live))


def test_the_viewer_is_served(route, tmp_path):
    """With serve=True the web viewer's page answers on localhost (no internet involved)."""
    import urllib.request

    from flyvpr.view import LiveView

    web, data = free_udp_port(), free_udp_port()
    view = LiveView(Map.load(route["map"]), serve=True, web_port=web, grpc_port=data)
    try:
        assert view.url == f"http://localhost:{web}/?url=rerun+http://localhost:{data}/proxy"
        deadline = time.monotonic() + 10
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=2) as r:
                    page = r.read().decode("utf-8", "replace")
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        assert "<html" in page.lower()
    finally:
        view.close()


def test_view_needs_the_extra(route, monkeypatch):
    import builtins

    from flyvpr.view import LiveView

    real = builtins.__import__

    def no_rerun(name, *args, **kwargs):
        if name == "rerun" or name.startswith("rerun."):
            raise ImportError("No module named 'rerun'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rerun)
    with pytest.raises(ImportError, match=r"pip install 'flyvpr\[view\]'"):
        LiveView(Map.load(route["map"]), serve=False, save="x.rrd")


@pytest.mark.parametrize("option", ["--view-port", "--view-data-port"])
def test_a_busy_view_port_fails_the_run_before_any_work(route, tmp_path, capsys, option):
    import socket

    with socket.socket() as busy:
        busy.bind(("0.0.0.0", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        out = tmp_path / "r.csv"
        code, _, err = _run(capsys, "localize", "--map", route["map"], route["png"], "--view",
                            option, port, "--out", out)  # fmt: skip
    assert code == 2 and f"{option} {port}: already in use by another program" in err
    assert not out.exists()
