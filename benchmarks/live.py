"""Live localization: ``flyvpr localize --map MAP URL`` on streams served on this machine.

Usage::

    python benchmarks/live.py [--seconds 60] [--json benchmarks/live.json]

Protocol (written into the JSON as ``protocol``):

* the map: the first 400 Nordland summer frames at 64x32
  (``../shared/data/nordland_64x32/summer``, ``images-00010`` .. ``images-04000``), the default
  method (``DEFAULT_METHOD``), seed 0, 32 x 64, built with
  :meth:`flyvpr.localization.maps.Map.build`;
* ``mjpeg_30fps``: the 51 Nordland winter frames at 640x360
  (``../shared/data/nordland_summer_winter_640x360/winter``) letterboxed to 640x480 (60 black
  rows above and below), JPEG quality 85, cycled, served as ``multipart/x-mixed-replace`` over
  HTTP on 127.0.0.1 by a thread of this process at 30 frames/s for ``--seconds`` s;
  ``flyvpr localize --map MAP URL --out records.csv -q`` runs in a fresh process and gets
  SIGINT (Ctrl-C) once the server has sent its last frame and one more second passed;
* ``mjpeg_flood``: the same frames served as fast as the client reads them (TCP paces the
  server), for the same time: a stream faster than the machine can follow;
* for both: frames received, localized and dropped (from the command's summary), the latency
  from a frame's arrival (decoded) to its record written and flushed (the summary's median and
  95th percentile; the records' ``latency_ms``, measured just before the write, agree), the
  latency from the server writing the frame to the socket to its record (the record's wall-clock
  timestamp of arrival plus its ``latency_ms``, minus the server's send time of that frame:
  TCP loses nothing, so record frame ``i`` is sent frame ``i``), and peak memory (``VmHWM`` of
  the localize process just before SIGINT);
* ``udp_vs_file``: the first 400 Nordland winter frames at 64x32 upscaled 4x (nearest) to
  256x128, H.264 (libx264, crf 18, ``tune=zerolatency``: no B-frames, a keyframe every 30
  frames) in MPEG-TS at 30 frames/s, written to ``winter.ts``.  ``flyvpr localize --map MAP
  winter.ts`` gives the file's answers; the same file's packets are then sent as they are
  (remuxed by PyAV, paced by their timestamps) to ``udp://127.0.0.1:PORT``, where
  ``flyvpr localize --map MAP udp://127.0.0.1:PORT`` listens (started first; the sender waits
  until it has bound the port).  Live frames are matched to the file's by their presentation
  timestamps.  Ground truth: winter frame ``i`` shows summer place ``i``; R@1 (the best place
  within ``tolerance`` places of the truth) over the frames each run localized, and the file's
  over the frames the UDP run localized, at the paper's tolerance (20) and at 2.  The UDP run
  uses ``--stream-option probesize=32 --stream-option analyzeduration=0`` (start decoding at
  once); ``udp_vs_file_default_probe`` repeats it with FFmpeg's default probing, whose first
  0.7 s of stream come out in one burst of which only the newest frame is localized.

The machine is shared and has 2 cores; the streams' server runs on it too.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks.stream_servers import (  # noqa: E402
    MjpegServer,
    UdpTsSender,
    free_udp_port,
    jpeg_bytes,
    udp_port_bound,
)

DATA = ROOT.parent / "shared" / "data"
N_PLACES = 400
TOLERANCES = (20, 2)


def _cli(*argv) -> list[str]:
    return [sys.executable, "-m", "flyvpr", *[str(a) for a in argv]]


def _vm_hwm_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def build_map(folder: Path) -> Path:
    """The 400-place map of the first 400 summer frames (a folder of links to them)."""
    from flyvpr.localization.maps import Map

    src = DATA / "nordland_64x32" / "summer"
    links = folder / "summer400"
    links.mkdir()
    for f in sorted(src.glob("*.png"))[:N_PLACES]:
        (links / f.name).symlink_to(f)
    path = folder / "summer400.map"
    Map.build(links, random_state=0).save(path)
    return path


def mjpeg_frames() -> list[bytes]:
    """The 640x360 winter frames letterboxed to 640x480, as JPEG."""
    from PIL import Image

    out = []
    for f in sorted((DATA / "nordland_summer_winter_640x360" / "winter").glob("*.png")):
        rgb = np.asarray(Image.open(f).convert("RGB"))
        canvas = np.zeros((480, 640, 3), np.uint8)
        top = (480 - rgb.shape[0]) // 2
        canvas[top : top + rgb.shape[0], : rgb.shape[1]] = rgb[:, :640]
        out.append(jpeg_bytes(canvas, quality=85))
    return out


def _summary(text: str) -> dict:
    m = re.search(
        r"(\d+) frames received, (\d+) localized, (\d+) dropped.*?median ([\d.]+) ms, 95% "
        r"([\d.]+) ms, max ([\d.]+) ms",
        text,
        re.S,
    )
    if m is None:
        raise RuntimeError(f"no summary in the output of flyvpr localize:\n{text}")
    keys = ("received", "localized", "dropped", "latency_median_ms", "latency_p95_ms",
            "latency_max_ms")  # fmt: skip
    pairs = enumerate(zip(keys, m.groups(), strict=True))
    return {k: (int(v) if i < 3 else float(v)) for i, (k, v) in pairs}


def _records(path: Path) -> dict:
    import csv

    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {
        "frame": np.array([int(r["frame"]) for r in rows], np.int64),
        "timestamp": np.array([float(r["timestamp"]) for r in rows]),
        "place": np.array([int(r["place"]) for r in rows], np.int64),
        "latency_ms": np.array([float(r.get("latency_ms") or "nan") for r in rows]),
    }


def run_mjpeg(map_path: Path, jpegs, fps, seconds: float, folder: Path, log) -> dict:
    """Serve the MJPEG stream for ``seconds`` s and localize it live in a fresh process."""
    out = folder / f"mjpeg_{fps or 'flood'}.csv"
    with MjpegServer(jpegs, fps=fps, duration=seconds, stall_after=30) as srv:
        proc = subprocess.Popen(
            _cli("localize", "--map", map_path, srv.url, "--out", out, "-q",
                 "--stall-timeout", 20),  # fmt: skip
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        # the server starts its clock when the client connects; wait for the last frame
        deadline = time.monotonic() + seconds + 60
        while not srv.hung and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(1.0)
        peak = _vm_hwm_mb(proc.pid) if proc.poll() is None else float("nan")
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
        sent = np.array(srv.sent)
    if proc.returncode != 130:
        raise RuntimeError(f"flyvpr localize ended with {proc.returncode}:\n{stdout}\n{stderr}")
    s = _summary(stdout)
    r = _records(out)
    end_to_end = (r["timestamp"] + r["latency_ms"] / 1000.0 - sent[r["frame"]]) * 1000.0
    res = {
        "frames_sent": int(sent.size),
        "frames_received": s["received"],
        "frames_localized": s["localized"],
        "frames_dropped": s["dropped"],
        "seconds": round(float(sent[-1] - sent[0]), 2),
        "sent_fps": round((sent.size - 1) / float(sent[-1] - sent[0]), 1),
        "localized_fps": round(s["localized"] / float(sent[-1] - sent[0]), 1),
        "latency_arrival_to_record_median_ms": s["latency_median_ms"],
        "latency_arrival_to_record_p95_ms": s["latency_p95_ms"],
        "latency_arrival_to_record_max_ms": s["latency_max_ms"],
        "records_latency_ms_median": round(float(np.median(r["latency_ms"])), 3),
        "latency_sent_to_record_median_ms": round(float(np.median(end_to_end)), 3),
        "latency_sent_to_record_p95_ms": round(float(np.percentile(end_to_end, 95)), 3),
        "peak_rss_mb": round(peak, 1),
        "summary": stdout.strip().splitlines(),
    }
    log(f"  {json.dumps({k: v for k, v in res.items() if k != 'summary'})}")
    return res


def write_winter_ts(path: Path, fps: int = 30) -> int:
    """The first 400 winter frames, 4x nearest to 256x128, H.264 in MPEG-TS."""
    import av
    from PIL import Image

    files = sorted((DATA / "nordland_64x32" / "winter").glob("*.png"))[:N_PLACES]
    with av.open(str(path), "w", format="mpegts") as c:
        st = c.add_stream("libx264", rate=fps)
        st.width, st.height, st.pix_fmt = 256, 128, "yuv420p"
        st.options = {"crf": "18", "tune": "zerolatency", "preset": "veryfast", "g": "30"}
        for i, f in enumerate(files):
            rgb = np.asarray(Image.open(f).convert("RGB"))
            big = np.repeat(np.repeat(rgb, 4, axis=0), 4, axis=1)
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(big), format="rgb24")
            frame.pts = i
            for packet in st.encode(frame):
                c.mux(packet)
        for packet in st.encode():
            c.mux(packet)
    return len(files)


def _recall_at_1(places, truth, tolerance: int) -> float:
    return float(np.mean(np.abs(places - truth) <= tolerance))


#: FFmpeg options of the UDP run: probe only what is needed to start (the live guide's
#: low-latency options); with FFmpeg's defaults the first 0.7 s of the stream go to the probe
#: and come out in one burst, of which the localizer keeps only the newest frame
UDP_OPTIONS = ("probesize=32", "analyzeduration=0")


def run_udp_vs_file(map_path: Path, folder: Path, log, options=UDP_OPTIONS) -> dict:
    video = folder / "winter.ts"
    n = write_winter_ts(video)
    file_out = folder / "file.csv"
    done = subprocess.run(
        _cli("localize", "--map", map_path, video, "--out", file_out, "-q"),
        capture_output=True, text=True,
    )  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"flyvpr localize {video} failed:\n{done.stdout}\n{done.stderr}")
    f = _records(file_out)
    by_time = {round(t, 4): i for i, t in zip(f["frame"], f["timestamp"], strict=True)}

    port = free_udp_port()
    live_out = folder / "udp.csv"
    proc = subprocess.Popen(
        _cli("localize", "--map", map_path, f"udp://127.0.0.1:{port}", "--out", live_out, "-q",
             "--open-timeout", 60, "--stall-timeout", 20,
             *[a for o in options for a in ("--stream-option", o)]),  # fmt: skip
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 60
    while not udp_port_bound(port):
        if time.monotonic() > deadline or proc.poll() is not None:
            raise RuntimeError("flyvpr localize did not start listening on the UDP port")
        time.sleep(0.05)
    with UdpTsSender(port, video=video) as sender:
        sender.done.wait(120)
    if sender.error is not None:
        raise sender.error
    time.sleep(2.0)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    if proc.returncode != 130:
        raise RuntimeError(f"flyvpr localize (UDP) ended with {proc.returncode}:\n{stdout}{stderr}")
    live = _records(live_out)
    frames = np.array([by_time.get(round(t, 4), -1) for t in live["timestamp"]])
    matched = frames >= 0
    res = {
        "frames_in_file": n,
        "file_frames_localized": int(f["frame"].size),
        "udp_packets_sent": sender.n_sent,
        "udp_frames_localized": int(live["frame"].size),
        "udp_frames_matched_to_file_by_timestamp": int(matched.sum()),
        "udp_summary": stdout.strip().splitlines(),
    }
    for tol in TOLERANCES:
        r_file = _recall_at_1(f["place"], f["frame"], tol)
        r_udp = _recall_at_1(live["place"][matched], frames[matched], tol)
        same = frames[matched]
        r_file_same = _recall_at_1(f["place"][same], same, tol)
        res[f"recall_at_1_tol{tol}_file"] = round(r_file, 4)
        res[f"recall_at_1_tol{tol}_udp"] = round(r_udp, 4)
        res[f"recall_at_1_tol{tol}_file_on_udp_frames"] = round(r_file_same, 4)
        res[f"recall_at_1_tol{tol}_abs_diff"] = round(abs(r_udp - r_file), 4)
    agree = live["place"][matched] == f["place"][frames[matched]]
    res["same_answer_as_file"] = round(float(agree.mean()), 4)
    log(f"  {json.dumps({k: v for k, v in res.items() if k != 'udp_summary'})}")
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=60.0, help="length of each MJPEG stream")
    p.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "live.json")
    args = p.parse_args(argv)
    from flyvpr import __version__
    from flyvpr.methods import DEFAULT_METHOD

    def log(text):
        print(text, flush=True)

    result = {
        "protocol": __doc__.split("Protocol (written into the JSON as ``protocol``):")[1].strip(),
        "method": DEFAULT_METHOD,
        "places": N_PLACES,
        "seconds": args.seconds,
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "flyvpr": __version__,
        },
    }
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        log("building the 400-place map")
        map_path = build_map(folder)
        jpegs = mjpeg_frames()
        log(f"MJPEG 640x480 at 30 frames/s for {args.seconds:g} s")
        result["mjpeg_30fps"] = run_mjpeg(map_path, jpegs, 30.0, args.seconds, folder, log)
        log(f"MJPEG 640x480 as fast as the client reads, for {args.seconds:g} s")
        result["mjpeg_flood"] = run_mjpeg(map_path, jpegs, None, args.seconds, folder, log)
        log(f"UDP MPEG-TS against the same file (--stream-option {' '.join(UDP_OPTIONS)})")
        result["udp_vs_file"] = run_udp_vs_file(map_path, folder, log)
        log("UDP MPEG-TS against the same file (FFmpeg's default probing)")
        result["udp_vs_file_default_probe"] = run_udp_vs_file(map_path, folder, log, options=())
    from flyvpr._io import write_text_atomic

    write_text_atomic(args.json, json.dumps(result, indent=2) + "\n")
    log(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
