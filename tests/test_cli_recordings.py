"""``flyvpr map`` and ``flyvpr localize --map`` on recordings made from the synthetic route."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

av = pytest.importorskip("av")
pytest.importorskip("rosbags")

from fake_filters import Scripted  # noqa: E402
from flyvpr.cli import main  # noqa: E402
from flyvpr.sources.writers import write_bag, write_video  # noqa: E402
from flyvpr.synthetic import make_route, save_route  # noqa: E402
from videos import write_av  # noqa: E402

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
    assert re.search(
        rf"{N} frames .* frames/s, median confidence .*, localized \d+\.\d% of frames, "
        r"\d+ relocations?\n",
        out,
    )
    assert "odometry" not in out  # the query has no positions
    rows = list(csv.DictReader((tmp_path / "q.csv").open()))
    assert len(rows) == N and list(rows[0]) == [
        "frame", "timestamp", "place", "confidence", "state", "relocated"
    ]  # fmt: skip
    assert {r["state"] for r in rows} <= {"localized", "lost"}
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
    assert list(records[0])[3:5] == ["confidence", "state"]


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


def test_map_summary_counts_places_without_a_position(recordings, tmp_path, capsys):
    rec = recordings["png"]
    short = tmp_path / "short.csv"
    short.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(10)))
    code, out, err = _run(
        capsys, "map", rec["summer"], "--positions", short, "--out", tmp_path / "s.map"
    )
    assert code == 0, err
    assert f"with positions (none for {N - 10} of {N} places: not in {short})" in out
    full = tmp_path / "full.csv"
    full.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(N)))
    code, out, err = _run(
        capsys, "map", rec["summer"], "--positions", full, "--out", tmp_path / "f.map"
    )
    assert code == 0, err
    assert "with positions, 3 m per place" in out and "none for" not in out
    code, out, err = _run(capsys, "map", rec["summer"], "--out", tmp_path / "n.map")
    assert code == 0 and "without positions" in out


def _timed_positions(path, t):
    """A timestamp,x,y CSV of the route's positions at the times ``t`` (the bags' frames are
    3 m apart at 10 Hz from t = 1000 s: 30 m/s)."""
    rows = "".join(f"{s!r},{30.0 * (s - 1000)!r},0\n" for s in np.asarray(t).tolist())
    path.write_text("timestamp,x,y\n" + rows)
    return path


def test_map_positions_slower_than_the_camera_are_interpolated(
    recordings, scripted, tmp_path, capsys
):
    # a 1 Hz GPS under a 10 Hz camera: the places used to take the nearest fix (steps of 0
    # and 30 m), so the map had no spacing, odometry went off and every=6m kept one frame a fix
    bag = recordings["ros1"]["summer"]
    gps = _timed_positions(tmp_path / "gps.csv", 1000.0 + np.arange(7))
    code, out, err = _run(capsys, "map", bag, "--positions", gps, "--out", tmp_path / "g.map")
    assert code == 0, err
    assert f"map of {N} places" in out and "(every 1, with positions, 3 m per place," in out
    code, out, err = _run(
        capsys, "map", bag, "--positions", gps, "--every", "6m", "--out", tmp_path / "e.map"
    )
    assert code == 0, err
    assert f"map of {N // 2} places" in out and "with positions, 6 m per place" in out
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "g.map", recordings["ros1"][QUERY],
        "--positions", gps,
    )  # fmt: skip
    assert code == 0, err
    assert f"odometry: path integration from --positions {gps} (map spacing 3 m per place)\n" in out
    velocities = scripted[-1].velocities  # a place a frame: the map's spacing, the query's
    assert velocities[0] is None and velocities[1:] == pytest.approx([1.0] * (N - 1))


def test_map_places_in_a_gap_of_the_positions_have_none(recordings, tmp_path, capsys, caplog):
    # 20 Hz positions silent for 2 s (1002-1004): frames 20-39 used to take the last fix
    # before the gap or the first after it (up to 30 m off); now they have none, and say so
    bag = recordings["ros1"]["summer"]
    t = 1000 + np.r_[0:40, 80:120] / 20
    gps = _timed_positions(tmp_path / "gap.csv", t)
    code, out, err = _run(capsys, "map", bag, "--positions", gps, "--out", tmp_path / "g.map")
    assert code == 0, err
    assert f"with positions (none for 20 of {N} places: not in {gps}), 3 m per place" in out
    with caplog.at_level("WARNING", logger="flyvpr"):
        code, out, err = _run(
            capsys, "map", bag, "--positions", gps, "--every", "6m", "--out", tmp_path / "e.map"
        )
    assert code == 0, err
    assert f"map of {N // 2 - 10} places" in out  # frames 0, 2, ..., 18, 40, 42, ..., 58
    (warning,) = [r.getMessage() for r in caplog.records if "no position" in r.getMessage()]
    assert warning.endswith(
        f"every=6m skipped 20 of {N} frames that have no position in {gps} (its rows: "
        "timestamps 1000-1005.95 s; 1 gap: timestamps 1001.95-1004 s)"
    )


def test_counted_says_one_thing_or_several():
    from flyvpr.cli._common import counted

    assert [counted(n, "frame") for n in (0, 1, 2)] == ["0 frames", "1 frame", "2 frames"]


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
          "--positions", elsewhere, "--out", tmp_path / "o.csv"],
         f"--every 5m keeps frames by distance, and no frame has a position in {elsewhere} "
         f"(its rows: frames 1000-1000; its frames 0-{N - 1}): a frame,x,y row names a frame's "
         "index in the recording"),
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
    assert re.search(
        r" correct \(best place within tolerance\), localized \d+\.\d% of frames, ", out
    )
    rows = list(csv.DictReader((tmp_path / "l.csv").open()))
    assert list(rows[0]) == ["frame", "source_frame", "place", "confidence", "state", "correct"]
    assert {r["state"] for r in rows} <= {"localized", "lost"}


@pytest.mark.parametrize("odometry", [True, False])
def test_localize_benchmark_mode_states_and_odometry(
    recordings, tmp_path, capsys, monkeypatch, odometry
):
    import flyvpr.methods

    velocities = []

    class Alternating(Scripted):
        def __init__(self, states=("lost", "localized")):
            super().__init__(states)

        def step(self, scores_row, velocity=None):
            velocities.append(velocity)
            return super().step(scores_row, velocity)

    monkeypatch.setitem(flyvpr.methods.FILTERS, "cann", Alternating)
    code, out, err = _run(
        capsys, "localize", "--dataset", "generic", "--root", recordings["png"]["summer"].parent,
        "--reference", "summer", "--query", QUERY, "--tolerance", TOL, "--no-cache",
        "--method", "pixels+cann", "--speed", "2", "--out", tmp_path / "l.csv",
        *(["--odometry"] if odometry else []),
    )  # fmt: skip
    assert code == 0, err
    assert f"{N // 2} frames streamed" in out and ", localized 50.0% of frames, " in out
    rows = list(csv.DictReader((tmp_path / "l.csv").open()))
    assert [r["state"] for r in rows] == ["lost", "localized"] * (N // 4)
    assert [int(r["source_frame"]) for r in rows] == list(range(0, N, 2))
    assert velocities == [None] + [2.0 if odometry else None] * (N // 2 - 1)


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
    assert "left out" not in by_pos
    # a ground truth that starts at frame 10: the frames before it are not scored (their
    # true place is unknown, not off the map), and their records' correct is empty
    late = tmp_path / "late_xy.csv"
    late.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(10, N)))
    records = tmp_path / "late.csv"
    code, out, err = _run(
        capsys, "localize", "--map", m, rec[QUERY], "--ground-truth", late,
        "--radius", 3.0 * TOL, "--out", records,
    )  # fmt: skip
    assert code == 0, err
    assert f"over {N - 10} frames (10 frames without a ground-truth position left out)" in out
    rows = list(csv.DictReader(records.open()))
    assert [r["correct"] for r in rows[:10]] == [""] * 10
    assert {r["correct"] for r in rows[10:]} <= {"0", "1"}
    # a ground truth with a row every other frame: the frames between get the straight line
    # between their neighbours' rows (they were left out as frames without a row)
    sparse = tmp_path / "sparse_xy.csv"
    kept = [*range(0, N, 2), N - 1]
    sparse.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in kept))
    code, out, err = _run(
        capsys, "localize", "--map", m, rec[QUERY], "--ground-truth", sparse, "--radius", 3.0 * TOL
    )
    assert code == 0, err
    assert "left out" not in out and _auc(out) == _auc(by_frames)


def test_realtime_paces_to_the_timestamps(tmp_path, capsys):
    import time

    frames = np.zeros((6, 16, 32), np.uint8) + np.arange(6, dtype=np.uint8)[:, None, None] * 40
    bag = write_bag(tmp_path / "r.bag", frames, version=1, fps=10)
    assert main(["map", str(bag), "--out", str(tmp_path / "r.map"), "--size", "8x16"]) == 0
    t0 = time.perf_counter()
    code, out, err = _run(capsys, "localize", "--map", tmp_path / "r.map", bag, "--realtime")
    assert code == 0, err
    assert time.perf_counter() - t0 >= 0.5  # 6 frames at 10 fps: the last is due after 0.5 s
    assert "were not paced" not in out


def test_an_interrupted_realtime_replay_keeps_its_records(tmp_path, capsys, monkeypatch):
    # a replay as if live: SIGTERM after the third frame keeps the three records, whole;
    # without --realtime the same run leaves no file (written atomically)
    import flyvpr.cli as cli
    import flyvpr.localization.tracking as tracking

    frames = np.zeros((6, 16, 32), np.uint8) + np.arange(6, dtype=np.uint8)[:, None, None] * 40
    bag = write_bag(tmp_path / "r.bag", frames, version=1, fps=50)
    assert main(["map", str(bag), "--out", str(tmp_path / "r.map"), "--size", "8x16"]) == 0
    real = tracking.track

    def cut(*args, **kwargs):  # SIGTERM once 3 frames are done (or when the steps end)
        done = 0
        for step in real(*args, **kwargs):
            if done >= 3:
                raise cli.Terminated
            done += len(step.batch)
            yield step
        raise cli.Terminated

    monkeypatch.setattr(tracking, "track", cut)
    out = tmp_path / "rt.csv"
    code, _, err = _run(capsys, "localize", "--map", tmp_path / "r.map", bag, "--realtime",
                        "--out", out)  # fmt: skip
    assert code == 143
    assert err == (
        f"flyvpr: terminated by SIGTERM; the records written until then are kept in {out}\n"
    )
    assert [r["frame"] for r in csv.DictReader(out.open())] == ["0", "1", "2"]
    out.unlink()
    code, _, err = _run(capsys, "localize", "--map", tmp_path / "r.map", bag, "--out", out)
    assert code == 143 and err == "flyvpr: terminated by SIGTERM; no half-written file left\n"
    assert not out.exists() and not list(tmp_path.glob(".*tmp*"))


def test_a_render_into_the_recordings_image_folder_is_refused(recordings, maps, tmp_path, capsys):
    rec = recordings["png"][QUERY]
    for render in (rec / "trace.html", rec / "sub" / "trace.mp4"):
        code, _, err = _run(capsys, "localize", "--map", maps["bare"], rec, "--render", render)
        assert code == 2 and f"--render {render} would go into {rec}, a folder of images" in err
        assert not render.exists() and not (rec / "sub").exists()


def test_realtime_says_when_a_folder_has_no_timestamps(recordings, tmp_path, capsys):
    rec = recordings["png"]
    m = tmp_path / "f.map"
    assert main(["map", str(rec["summer"]), "--out", str(m)]) == 0
    code, out, err = _run(capsys, "localize", "--map", m, rec[QUERY], "--realtime")
    assert code == 0, err
    assert f"--realtime: image folder {rec[QUERY]}" in out
    assert "has no timestamps" in out and "were not paced" in out
    # without --realtime there is nothing to say
    code, out, err = _run(capsys, "localize", "--map", m, rec[QUERY])
    assert code == 0 and "--realtime" not in out


def test_seed_speed_method_and_param_are_refused_with_a_map(recordings, tmp_path, capsys):
    rec = recordings["png"]
    m = tmp_path / "f.map"
    assert main(["map", str(rec["summer"]), "--out", str(m)]) == 0
    out_csv = tmp_path / "never.csv"
    for extra, says in [
        (["--seed", "0"], "--seed: the map fixes the method and its seed"),
        (["--seed", "3"], "--seed: the map fixes the method and its seed"),
        (["--method", "pixels+cann"], "--method: the map fixes the method"),
        (["--param", "tolerance=3"], "--param: the map fixes the method"),
        (["--speed", "2"], "--speed simulates a robot speed on a --dataset benchmark"),
        # options of the --dataset benchmark: refused, not ignored
        (["--first", "10"], "--first: a --dataset option, not for --map MAP SOURCE; --every"),
        (["--count", "20"], "--count: a --dataset option, not for --map MAP SOURCE"),
        (["--spacing", "2"], "--spacing: a --dataset option"),
        (["--root", "x"], "--root: a --dataset option"),
        (["--reference", "summer"], "--reference: a --dataset option"),
        (["--query", "winter"], "--query: a --dataset option"),
        (["--tolerance-m", "5"], "--tolerance-m: a --dataset option"),
        (["--trust-pickle"], "--trust-pickle: a --dataset option"),
        (["--no-cache"], "--no-cache: a --dataset option"),
        (["--cache-dir", "c"], "--cache-dir: a --dataset option"),
        (["--positions-csv", "p.csv"], "own positions are --positions CSV"),
        # the ground truth's options go with their kind of ground truth
        (["--tolerance", "2"], "--tolerance: only with --ground-truth"),
        (["--radius", "3"], "--radius: only with --ground-truth"),
        (["--ground-truth", "frames", "--tolerance", "2", "--radius", "3"],
         "--radius: for a --ground-truth CSV"),
        (["--ground-truth", "gt.csv", "--radius", "3", "--tolerance", "2"],
         "--tolerance: for --ground-truth frames"),
    ]:  # fmt: skip
        code, _, err = _run(capsys, "localize", "--map", m, rec[QUERY], *extra, "--out", out_csv)
        assert code == 2 and says in err, (extra, err)
        assert not out_csv.exists()
    # "Frames" is the word in any case
    code, out, err = _run(
        capsys, "localize", "--map", m, rec[QUERY], "--ground-truth", "FRAMES", "--tolerance", TOL
    )
    assert code == 0 and f"ground truth (frames within {TOL})" in out, err
    # with --dataset, --seed still seeds the method (0 when not given)
    code, out, err = _run(
        capsys, "localize", "--dataset", "generic", "--root", rec["summer"].parent,
        "--reference", "summer", "--query", QUERY, "--tolerance", TOL, "--no-cache",
        "--method", "pixels+cann",
    )  # fmt: skip
    assert code == 0 and "seed=0" in out, err


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


# -- state and odometry, with a scripted filter in place of the map's CANN ----------------------
@pytest.fixture
def scripted(monkeypatch):
    """Every map loaded gets a :class:`Scripted` filter (alternately lost and localized, the
    lost first); the list holds each such filter as it is reset (the localizer's own copy
    last), to read the velocities they were given."""
    from flyvpr.localization.maps import Map

    load = Map.load.__func__
    made = []

    class Recorded(Scripted):
        def reset(self):
            super().reset()
            made.append(self)

    def load_scripted(cls, path, *, size=None):
        m = load(cls, path, size=size)
        m.method.filter = Recorded(("lost", "localized"))
        m.method.filter.reset()
        return m

    monkeypatch.setattr(Map, "load", classmethod(load_scripted))
    return made


@pytest.fixture(scope="module")
def maps(recordings, tmp_path_factory):
    """The summer bag as a map with positions (3 m per place) and as one without."""
    root = tmp_path_factory.mktemp("maps")
    bag = str(recordings["ros1"]["summer"])
    assert main(["map", bag, "--position-topic", "/odom", "--out", str(root / "xy.map")]) == 0
    assert main(["map", bag, "--out", str(root / "bare.map")]) == 0
    return {"xy": root / "xy.map", "bare": root / "bare.map"}


def test_records_carry_the_filters_state(recordings, maps, scripted, tmp_path, capsys):
    night = recordings["ros1"][QUERY]
    for name in ("s.csv", "s.jsonl"):
        code, out, err = _run(
            capsys, "localize", "--map", maps["xy"], night, "--every", "3", "--out", tmp_path / name
        )
        assert code == 0, err
        assert ", localized 50.0% of frames, 0 relocations\n" in out
    rows = list(csv.DictReader((tmp_path / "s.csv").open()))
    assert list(rows[0]) == [
        "frame", "timestamp", "place", "confidence", "state", "relocated", "x", "y"
    ]  # fmt: skip
    assert [r["state"] for r in rows] == ["lost", "localized"] * (N // 6)
    records = [json.loads(line) for line in (tmp_path / "s.jsonl").read_text().splitlines()]
    assert [r["state"] for r in records] == ["lost", "localized"] * (N // 6)
    assert list(records[0])[:6] == [
        "frame", "timestamp", "place", "confidence", "state", "relocated"
    ]  # fmt: skip
    code, out, err = _run(capsys, "localize", "--map", maps["xy"], night, "--every", "20")
    assert code == 0, err
    assert f"{N // 20} frames" in out and ", localized 33.3% of frames," in out  # 1 of 3


def test_odometry_from_a_positions_csv(recordings, maps, scripted, tmp_path, capsys):
    xy = tmp_path / "night_xy.csv"  # 1.5 m per frame, from frame 5 on
    xy.write_text("frame,x,y\n" + "".join(f"{i},{1.5 * i},7\n" for i in range(5, N)))
    code, out, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY], "--positions", xy,
        "--out", tmp_path / "o.csv",
    )  # fmt: skip
    assert code == 0, err
    assert (
        f"\nodometry: path integration from --positions {xy} (map spacing 3 m per place); "
        f"{N - 5} of {N} frames have a position in it\n" in out
    )
    # frames 0-4 have no position and frame 5 none before it: no odometry for them
    assert scripted[-1].velocities == [None] * 6 + [0.5] * (N - 6)
    # and the records say what the filter was given, frame by frame
    rows = list(csv.DictReader((tmp_path / "o.csv").open()))
    assert list(rows[0])[-1] == "odometry"
    assert [r["odometry"] for r in rows] == [""] * 6 + ["0.5"] * (N - 6)
    code, _, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY], "--positions", xy,
        "--every", "2", "--out", tmp_path / "o.jsonl",
    )  # fmt: skip
    assert code == 0, err
    records = [json.loads(line) for line in (tmp_path / "o.jsonl").read_text().splitlines()]
    # kept frames 0, 2, 4 have no position and 6 none before it
    assert [r["odometry"] for r in records] == [None] * 4 + [1.0] * (N // 2 - 4)


def test_positions_that_cover_no_frame_are_said_to_give_none(
    recordings, maps, scripted, tmp_path, capsys
):
    # rows for frames the recording does not have (another recording's file)
    off = tmp_path / "off.csv"
    off.write_text("frame,x,y\n" + "".join(f"{i},{1.5 * i},7\n" for i in range(1000, 1010)))
    code, out, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY], "--positions", off
    )
    assert code == 0, err
    note = [line for line in out.splitlines() if line.startswith("odometry")]
    assert note == [
        f"odometry: none: no frame of bag {recordings['ros1'][QUERY]} topic /camera/image has a "
        f"position in {off} (its rows: frames 1000-1009), so nothing was integrated"
    ]
    assert scripted[-1].velocities == [None] * N
    # a map built with them is refused: not one place would have a position
    code, out, err = _run(
        capsys, "map", recordings["ros1"][QUERY], "--positions", off, "--out", tmp_path / "m.map"
    )
    assert code == 1 and not (tmp_path / "m.map").exists()
    assert f"no frame has a position in {off} (its rows: frames 1000-1009; its frames 0-" in err


def test_odometry_from_the_bags_topic_and_every(recordings, maps, scripted, capsys):
    code, out, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
        "--position-topic", "/odom", "--every", "2",
    )  # fmt: skip
    assert code == 0, err
    assert (
        "odometry: path integration from --position-topic /odom (map spacing 3 m per place)" in out
    )
    assert scripted[-1].velocities == [None] + [2.0] * (N // 2 - 1)


def test_no_odometry_turns_it_off(recordings, maps, scripted, capsys):
    code, out, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
        "--position-topic", "/odom", "--no-odometry",
    )  # fmt: skip
    assert code == 0, err
    assert "\nodometry: off (--no-odometry)\n" in out and "path integration" not in out
    assert scripted[-1].velocities == [None] * N


def test_the_cann_is_not_carried_across_a_jump_of_the_maps_positions(
    recordings, maps, tmp_path, capsys
):
    from flyvpr.localization.maps import Map

    m = Map.load(maps["xy"])
    xy = m.positions + np.where(np.arange(m.n_places) >= 5, 1000.0, 0.0)[:, None]
    jumped = Map(m.method, m.size, m.timestamps, m.source_index, xy, m.thumbnails, m.info)
    jumped.save(tmp_path / "gap.map")
    night = recordings["ros1"][QUERY]
    code, out, err = _run(capsys, "localize", "--map", tmp_path / "gap.map", night)
    assert code == 0, err
    assert (
        "\nbreaks: the map's route is broken at 1 place (between places 4-5), where its "
        "positions jump: the filter does not carry the robot across (--no-breaks: one route)\n"
        in out
    )
    code, out, err = _run(capsys, "localize", "--map", tmp_path / "gap.map", night, "--no-breaks")
    assert code == 0, err
    assert "\nbreaks: off (--no-breaks): 1 break of the map ignored\n" in out
    code, out, err = _run(capsys, "localize", "--map", maps["xy"], night)
    assert code == 0, err
    assert "breaks" not in out  # (a map without a jump: nothing to say)
    # breaks the map's filter was built with are its own, said as such
    built = Map(
        jumped.method, m.size, m.timestamps, m.source_index, m.positions, m.thumbnails, m.info
    )
    built.method.filter.set_params(breaks=(3,))
    built.save(tmp_path / "own.map")
    code, out, err = _run(capsys, "localize", "--map", tmp_path / "own.map", night)
    assert code == 0, err
    assert "(between places 2-3), as the map's filter was built:" in out
    code, out, err = _run(capsys, "localize", "--map", tmp_path / "own.map", night, "--no-breaks")
    assert "\nbreaks: off (--no-breaks): 1 break of the map ignored\n" in out
    code, _, err = _run(capsys, "localize", "--dataset", "generic", "--no-breaks")
    assert code == 2 and "--no-breaks needs --map MAP SOURCE" in err


def test_odometry_off_when_the_map_has_no_positions(recordings, maps, scripted, capsys):
    code, out, err = _run(
        capsys, "localize", "--map", maps["bare"], recordings["ros1"][QUERY],
        "--position-topic", "/odom",
    )  # fmt: skip
    assert code == 0, err
    note = [line for line in out.splitlines() if line.startswith("odometry")]
    assert note == [
        "odometry: off, the map has no positions to turn the metres of --position-topic /odom "
        "into places (build it with --positions or --position-topic)"
    ]
    assert scripted[-1].velocities == [None] * N


def test_a_glitch_of_the_positions_is_refused_and_said(recordings, maps, tmp_path, capsys):
    # 1.5 m per frame (half a place), one fix 600 m off: that frame's distance, and the next's
    # back, are glitches to the real CANN (more than 8 times the recent distance)
    xy = tmp_path / "glitch.csv"
    rows = [f"{i},{600.0 if i == 30 else 1.5 * i},7" for i in range(N)]
    xy.write_text("frame,x,y\n" + "\n".join(rows) + "\n")
    code, out, err = _run(capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
                          "--positions", xy, "--out", tmp_path / "g.csv")  # fmt: skip
    assert code == 0, err
    assert (
        "\nodometry: 2 frames refused the distance moved as a glitch (more than 8 times the "
        "recent distance per frame) and were localized without it\n" in out
    )
    records = list(csv.DictReader((tmp_path / "g.csv").open()))
    assert float(records[30]["odometry"]) > 150  # the records keep what the filter was given
    clean = tmp_path / "clean.csv"
    clean.write_text("frame,x,y\n" + "".join(f"{i},{1.5 * i},7\n" for i in range(N)))
    code, out, err = _run(capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
                          "--positions", clean)  # fmt: skip
    assert code == 0 and "refused the distance" not in out


def test_odometry_off_for_a_filter_without_it(recordings, maps, capsys):
    code, out, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
        "--position-topic", "/odom", "--every", "10",
    )  # fmt: skip
    assert code == 0, err  # the real CANN takes odometry
    assert "odometry: path integration from --position-topic /odom" in out
    bag = str(recordings["ros1"]["summer"])
    plain = maps["xy"].parent / "pixels.map"
    argv = ["map", bag, "--method", "pixels", "--position-topic", "/odom", "--out", str(plain)]
    assert main(argv) == 0
    code, out, err = _run(
        capsys, "localize", "--map", plain, recordings["ros1"][QUERY], "--position-topic", "/odom"
    )
    assert code == 0, err
    assert "\nodometry: off, pixels has no filter that takes it\n" in out


def test_map_summary_gives_the_spacing(recordings, tmp_path, capsys):
    code, out, err = _run(
        capsys, "map", recordings["ros1"]["summer"], "--position-topic", "/odom", "--every", "2",
        "--out", tmp_path / "m.map",
    )  # fmt: skip
    assert code == 0, err
    assert "(every 2, with positions, 6 m per place, size 32x64" in out


def test_odometry_options_belong_to_their_mode(recordings, maps, tmp_path, capsys):
    code, _, err = _run(capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY],
                        "--odometry")  # fmt: skip
    assert code == 2 and "--odometry: with --map, odometry comes from the recording's" in err
    code, _, err = _run(capsys, "localize", "--dataset", "generic", "--no-odometry")
    assert code == 2 and "--no-odometry needs --map MAP SOURCE" in err


def test_odometry_off_when_the_maps_positions_give_no_spacing(
    recordings, scripted, tmp_path, capsys
):
    still = tmp_path / "still.csv"  # every place at the same spot
    still.write_text("frame,x,y\n" + "".join(f"{i},4,2\n" for i in range(N)))
    bag = recordings["ros1"]["summer"]
    code, out, err = _run(capsys, "map", bag, "--positions", still, "--out", tmp_path / "s.map")
    assert code == 0, err
    assert "(every 1, with positions, size 32x64" in out
    code, out, err = _run(
        capsys, "localize", "--map", tmp_path / "s.map", recordings["ros1"][QUERY],
        "--position-topic", "/odom",
    )  # fmt: skip
    assert code == 0, err
    assert "\nodometry: off, the map's positions give no spacing between places\n" in out
    assert scripted[-1].velocities == [None] * N


def test_html_trace_carries_the_state(recordings, maps, scripted, tmp_path, capsys):
    code, _, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY], "--every", "10",
        "--render", tmp_path / "t.html",
    )  # fmt: skip
    assert code == 0, err
    page = (tmp_path / "t.html").read_text()
    data = json.loads(re.search(r"const D = (\{.*\});", page).group(1))
    assert [row[5] for row in data["rows"]] == ["lost", "localized"] * 3
    assert 'r[5] === "lost" ? "  LOST"' in page


def test_video_caption_says_lost(recordings, maps, scripted, tmp_path, capsys, monkeypatch):
    from PIL import ImageDraw

    captions = []
    draw = ImageDraw.Draw

    class Spy:
        def __init__(self, img):
            self.draw = draw(img)

        def text(self, xy, text, **kwargs):
            captions.append(text)
            self.draw.text(xy, text, **kwargs)

    monkeypatch.setattr(ImageDraw, "Draw", Spy)
    code, _, err = _run(
        capsys, "localize", "--map", maps["xy"], recordings["ros1"][QUERY], "--every", "10",
        "--render", tmp_path / "t.mp4",
    )  # fmt: skip
    assert code == 0, err
    # "frame 0  t=1000.00s  place 0  conf 0.224  LOST": what follows the confidence
    assert [c.split("  ")[4:] for c in captions] == [["LOST"], []] * 3
    assert [c.split("  ")[0] for c in captions] == [f"frame {i}" for i in range(0, N, 10)]


# -- videos of the kinds cameras and editors make; GPS before its first fix ----------------------
def _mkv(path, frames, pts_ms, *, audio_s=0):
    """Lossless Matroska of gray frames at the given times (ms), and optionally a silent audio
    track of ``audio_s`` seconds."""
    from fractions import Fraction

    rgb = np.repeat(np.rint(frames * 255).astype(np.uint8)[..., None], 3, axis=-1)
    stream = {"frames": rgb, "pts": pts_ms, "time_base": Fraction(1, 1000)}
    return write_av(path, [stream], audio_s=audio_s)


def test_unusual_intact_videos_map_and_cut_ones_are_one_line(tmp_path, capsys):
    route = make_route(20, size=(64, 128), conditions=("summer",), random_state=3)
    frames = route.images["summer"]
    vfr = _mkv(tmp_path / "vfr.mkv", frames, [100 * i for i in range(10)] + [
        1000 + 1000 * i for i in range(10)
    ])  # fmt: skip
    audio = _mkv(tmp_path / "audio.mkv", frames, [100 * i for i in range(20)], audio_s=4)
    for video in (vfr, audio):
        code, out, err = _run(capsys, "map", video, "--out", tmp_path / "m.map")
        assert code == 0, err
        assert "map of 20 places" in out
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(audio.read_bytes()[: audio.stat().st_size // 2])
    code, out, err = _run(capsys, "map", cut, "--out", tmp_path / "o.map")
    assert code == 1 and len(err.strip().splitlines()) == 1, err
    assert f"video {cut}: truncated: its header implies at least" in err
    assert not (tmp_path / "o.map").exists()


def test_map_from_a_gps_that_had_no_fix_at_first(tmp_path, capsys, caplog):
    # a receiver sends STATUS_NO_FIX at latitude 0, longitude 0 before its first fix: those
    # used to become the origin, so every place was thousands of km off and the east-west
    # scale that of the equator (4 m per place instead of 2 at latitude 60)
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    from flyvpr.sources.rosbag import EARTH_RADIUS_M

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    route = make_route(20, size=(32, 64), conditions=("summer",), random_state=3)
    east = np.degrees(2.0 / (EARTH_RADIUS_M * np.cos(np.radians(60.0))))
    bag = tmp_path / "gps.bag"
    with Writer(bag) as w:
        cam = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        fix = w.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ts)
        for i, frame in enumerate(route.images["summer"]):
            ns = (1000 * 10 + i) * 10**8  # 1000 s + i / 10 s
            stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
            hdr = T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="cam")
            pixels = np.rint(frame * 255).astype(np.uint8)
            image = T["sensor_msgs/msg/Image"](
                header=hdr, height=32, width=64, encoding="mono8", is_bigendian=0, step=64,
                data=pixels.reshape(-1),
            )  # fmt: skip
            w.write(cam, ns, ts.serialize_ros1(image, "sensor_msgs/msg/Image"))
            no_fix = i < 4
            gps = T["sensor_msgs/msg/NavSatFix"](
                header=hdr, status=T["sensor_msgs/msg/NavSatStatus"](
                    status=-1 if no_fix else 0, service=1
                ),
                latitude=0.0 if no_fix else 60.0, longitude=0.0 if no_fix else 10.0 + i * east,
                altitude=0.0, position_covariance=np.zeros(9), position_covariance_type=0,
            )  # fmt: skip
            w.write(fix, ns, ts.serialize_ros1(gps, "sensor_msgs/msg/NavSatFix"))
    with caplog.at_level("WARNING", logger="flyvpr"):
        code, out, err = _run(
            capsys, "map", bag, "--topic", "/cam", "--position-topic", "/fix",
            "--out", tmp_path / "g.map",
        )  # fmt: skip
    assert code == 0, err
    assert "with positions" in out and "2 m per place" in out, out
    assert "skipped 4 without a fix (status < 0) of 20 position messages" in caplog.text
