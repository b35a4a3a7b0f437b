"""``flyvpr map`` and ``flyvpr localize --map`` on recordings made from the synthetic route."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

av = pytest.importorskip("av")
pytest.importorskip("rosbags")

from flyvpr.cli import main  # noqa: E402
from flyvpr.sources.writers import write_bag, write_video  # noqa: E402
from flyvpr.synthetic import make_route, save_route  # noqa: E402

N = 60
TOL = 1
#: the query traverse: at night pixels alone reach an AUC near 0.3 and pixels+cann near 0.98
#: on this route (seed 3), so neither score is a trivial 1.0
QUERY = "night"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """One synthetic route (summer reference, night query) as PNG folders, mp4 and bags."""
    root = tmp_path_factory.mktemp("route")
    route = make_route(N, size=(64, 128), conditions=("summer", QUERY), random_state=3)
    save_route(route, root / "png")
    out = {"png": {c: root / "png" / c for c in ("summer", QUERY)}}
    xy = np.c_[np.arange(N) * 3.0, np.zeros(N)]
    for season in ("summer", QUERY):
        frames = route.images[season]
        # crf 0: x264's lossless mode (full range), so the comparison tests the decoding and
        # streaming, not the codec's loss (at crf 10 one of the 60 night frames flips: 1/60 AUC)
        out.setdefault("mp4", {})[season] = write_video(root / f"{season}.mp4", frames, crf=0)
        out.setdefault("ros2", {})[season] = write_bag(root / f"{season}_ros2", frames, version=2)
        out.setdefault("ros1", {})[season] = write_bag(
            root / f"{season}.bag", frames, version=1, positions=xy
        )
    return out


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _auc(text: str) -> float:
    return float(re.search(r"AUC (\d+\.\d+)", text).group(1))


@pytest.fixture(scope="module")
def evaluate_auc(recordings, tmp_path_factory):
    """AUC of ``flyvpr evaluate`` on the route's PNG folders, per method."""
    aucs = {}
    for method in ("pixels+cann", "pixels"):
        out = tmp_path_factory.mktemp("eval") / "e.json"
        code = main(
            ["evaluate", "--dataset", "generic", "--root", str(recordings["png"]["summer"].parent),
             "--reference", "summer", "--query", QUERY, "--tolerance", str(TOL),
             "--method", method, "--no-cache", "--quiet", "--out", str(out)]
        )  # fmt: skip
        assert code == 0
        aucs[method] = json.loads(out.read_text())["auc"]
    return aucs


@pytest.mark.parametrize("method", ["pixels+cann", "pixels"])
@pytest.mark.parametrize("kind", ["mp4", "ros2", "ros1", "png"])
def test_map_then_localize_scores_like_evaluate(
    kind, method, recordings, evaluate_auc, tmp_path, capsys
):
    rec = recordings[kind]
    expected = evaluate_auc[method]
    assert 0.1 < expected < 0.999  # neither trivial nor hopeless
    code, out, err = _run(
        capsys, "map", rec["summer"], "--method", method, "--out", tmp_path / "r.map"
    )
    assert code == 0, err
    assert f"map of {N} places" in out
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "r.map", rec[QUERY], "--out", tmp_path / "q.csv"
    )
    assert code == 0, err
    assert re.search(rf"{N} frames .* frames/s, median confidence .*, \d+ relocations", out)
    rows = list(csv.DictReader((tmp_path / "q.csv").open()))
    assert len(rows) == N and list(rows[0]) == [
        "frame", "timestamp", "place", "confidence", "relocated"
    ]  # fmt: skip
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "r.map", rec[QUERY],
        "--ground-truth", "frames", "--tolerance", TOL, "--out", tmp_path / "q.jsonl",
    )  # fmt: skip
    assert code == 0, err
    assert abs(_auc(out) - expected) <= 0.005, (kind, _auc(out), expected)
    if kind in ("ros2", "ros1", "png"):  # lossless frames: the very same scores
        assert abs(_auc(out) - expected) < 1e-4
    records = [json.loads(line) for line in (tmp_path / "q.jsonl").read_text().splitlines()]
    assert len(records) == N and set(records[0]) >= {"frame", "place", "confidence", "correct"}


def test_positions_from_the_bag_and_every(recordings, tmp_path, capsys):
    rec = recordings["ros1"]
    code, out, err = _run(
        capsys, "map", rec["summer"], "--position-topic", "/odom", "--every", "6m",
        "--out", tmp_path / "p.map",
    )  # fmt: skip
    assert code == 0, err
    assert f"map of {N // 2} places" in out and "with positions" in out
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "p.map", rec[QUERY], "--every", "0.2s",
        "--out", tmp_path / "p.csv",
    )  # fmt: skip
    assert code == 0, err
    rows = list(csv.DictReader((tmp_path / "p.csv").open()))
    assert [int(r["frame"]) for r in rows] == list(range(0, N, 2))
    assert float(rows[3]["x"]) == 3.0 * 2 * int(rows[3]["place"])


def test_render_video_and_page(recordings, tmp_path, capsys):
    rec = recordings["ros2"]
    assert main(["map", str(rec["summer"]), "--out", str(tmp_path / "r.map")]) == 0
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "r.map", rec[QUERY],
        "--render", tmp_path / "t.mp4", "--render", tmp_path / "t.html",
    )  # fmt: skip
    assert code == 0, err
    with av.open(str(tmp_path / "t.mp4")) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == N
    assert frames[0].shape == (272, 512, 3)
    page = (tmp_path / "t.html").read_text()
    data = json.loads(re.search(r"const D = (\{.*\});", page).group(1))
    assert len(data["rows"]) == N and data["n_places"] == N


def test_bad_inputs_one_line_exit_1_nothing_written(recordings, tmp_path, capsys):
    video = recordings["mp4"]["summer"]
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(video.read_bytes()[:4000])
    depth = write_bag(tmp_path / "depth.bag", np.zeros((3, 8, 8), np.uint8), encoding="16UC1",
                      version=1)  # fmt: skip
    assert main(["map", str(recordings["ros2"]["summer"]), "--out", str(tmp_path / "r.map")]) == 0
    empty = tmp_path / "empty"
    empty.mkdir()
    elsewhere = tmp_path / "elsewhere.csv"  # positions of no frame of the recording
    elsewhere.write_text("frame,x,y\n1000,0,0\n")
    cases = [
        (["map", cut, "--out", tmp_path / "o.map"], "cut.mp4"),
        (["map", recordings["ros1"]["summer"], "--topic", "/nope", "--out", tmp_path / "o.map"],
         "image topics in the bag: /camera/image"),
        (["map", depth, "--out", tmp_path / "o.map"], "unsupported image encoding '16UC1'"),
        (["map", empty, "--out", tmp_path / "o.map"], "no image files"),
        (["localize", "--map", tmp_path / "r.map", "--size", "16x32", recordings["ros2"][QUERY],
          "--out", tmp_path / "o.csv"], "fitted on 32x64 images"),
        (["localize", "--map", tmp_path / "r.map", cut, "--out", tmp_path / "o.csv"], "cut.mp4"),
        (["localize", "--map", tmp_path / "r.map", recordings["ros2"][QUERY], "--every", "5m",
          "--positions", elsewhere, "--out", tmp_path / "o.csv"], "--every 5m keeps no frame"),
    ]  # fmt: skip
    for argv, needle in cases:
        code, out, err = _run(capsys, *argv)
        assert code == 1, (argv, err)
        assert needle in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "o.map").exists() and not (tmp_path / "o.csv").exists()
        assert not list(tmp_path.glob(".*tmp*")), list(tmp_path.iterdir())


def test_usage_errors(recordings, tmp_path, capsys):
    rec = recordings["ros2"][QUERY]
    for argv in (
        ["localize", rec],
        ["localize", "--map", tmp_path / "x.map"],
        ["localize", "--dataset", "generic", "--render", tmp_path / "t.mp4"],
        ["map", rec, "--out", tmp_path / "m.map", "--every", "2km"],
        ["localize", "--map", tmp_path / "x.map", rec, "--render", tmp_path / "t.gif"],
        [
            "localize",
            "--map",
            tmp_path / "x.map",
            rec,
            "--out",
            tmp_path / "a.html",
            "--render",
            tmp_path / "a.html",
        ],
    ):
        code, _, err = _run(capsys, *argv)
        assert code == 2, (argv, err)


def test_localize_benchmark_mode_still_works(recordings, tmp_path, capsys):
    code, out, err = _run(
        capsys, "localize", "--dataset", "generic", "--root", recordings["png"]["summer"].parent,
        "--reference", "summer", "--query", QUERY, "--tolerance", TOL, "--no-cache",
        "--method", "pixels+cann", "--out", tmp_path / "l.csv",
    )  # fmt: skip
    assert code == 0, err
    assert f"{N} frames streamed" in out


def test_ground_truth_by_positions_scores_like_frames(recordings, tmp_path, capsys):
    rec = recordings["ros1"]
    m = tmp_path / "p.map"
    assert main(["map", str(rec["summer"]), "--position-topic", "/odom", "--out", str(m)]) == 0
    gt = tmp_path / "night_xy.csv"
    gt.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(N)))
    code, by_pos, err = _run(
        capsys, "localize", "--map", m, rec[QUERY], "--ground-truth", gt, "--radius", 3.0 * TOL
    )
    assert code == 0, err
    code, by_frames, err = _run(
        capsys, "localize", "--map", m, rec[QUERY], "--ground-truth", "frames", "--tolerance", TOL
    )
    assert code == 0, err
    assert _auc(by_pos) == _auc(by_frames)
    assert f"{gt} within {3.0 * TOL:g} m" in by_pos


def test_realtime_paces_to_the_timestamps(tmp_path, capsys):
    import time

    frames = np.zeros((6, 16, 32), np.uint8) + np.arange(6, dtype=np.uint8)[:, None, None] * 40
    bag = write_bag(tmp_path / "r.bag", frames, version=1, fps=10)
    assert main(["map", str(bag), "--out", str(tmp_path / "r.map"), "--size", "8x16"]) == 0
    t0 = time.perf_counter()
    code, _, err = _run(capsys, "localize", "--map", tmp_path / "r.map", bag, "--realtime")
    assert code == 0, err
    assert time.perf_counter() - t0 >= 0.5  # 6 frames at 10 fps: the last is due after 0.5 s


def test_video_speed_benchmark_runs_small():
    """The speed benchmark's video row, at a toy size: every figure is there and sane."""
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from benchmarks import video_speed

    res = video_speed.run(n_places=8, lengths=(12, 24), repeat=1, log=lambda _: None)
    assert res["video_frames"] == 12
    assert res["video_decode_fps"] > 0 and res["video_localize_fps"] > 0
    assert res["video_localize_over_decode"] == pytest.approx(
        res["video_localize_fps"] / res["video_decode_fps"]
    )
    assert res["video_peak_rss_mb_12"] > 10 and res["video_peak_rss_mb_24"] > 10
