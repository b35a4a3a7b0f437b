"""Tests of the Oxford RobotCar loader on synthetic runs in the dataset's own layout."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flyvpr.datasets import load_benchmark, load_robotcar
from flyvpr.datasets.robotcar import GPS_COLUMNS, INS_COLUMNS, read_poses, select_by_distance

T0_US = 1418132416000000  # 2014-12-09, UNIX microseconds (16 digits)
NORTH0, EAST0 = 5735000.0, 620000.0  # Oxford-sized UTM coordinates


def straight(speed=10.0, lateral=0.0):
    """Route along northing at constant speed; ``lateral`` shifts it east (metres)."""
    return lambda t: (NORTH0 + speed * t, EAST0 + lateral + 0 * t)


def curve(speed=10.0, radius=200.0):
    return lambda t: (
        NORTH0 + radius * np.sin(speed * t / radius),
        EAST0 + radius * (1 - np.cos(speed * t / radius)),
    )


def with_stop(speed=10.0, stop_at=10.0, stop_for=5.0):
    """Drive, stand still for ``stop_for`` seconds, drive on."""

    def route(t):
        moving = np.minimum(t, stop_at) + np.maximum(t - stop_at - stop_for, 0)
        return NORTH0 + speed * moving, EAST0 + 0 * t

    return route


def make_run(
    root: Path,
    name: str,
    route,
    duration=20.0,
    fps=16.0,
    pose="ins",
    pose_hz=50.0,
    image_start=0.0,
    pose_margin=0.5,
    image_shape=(6, 8),
) -> Path:
    """Write ``root/name`` in the RobotCar layout: stereo/centre PNGs and gps/<pose>.csv."""
    run = root / name
    centre = run / "stereo" / "centre"
    centre.mkdir(parents=True)
    # A GBRG mosaic of a uniform gray scene: every sample 100.
    mosaic = np.full(image_shape, 100, np.uint8)
    for t in np.arange(image_start, duration, 1 / fps):
        Image.fromarray(mosaic).save(centre / f"{T0_US + round(t * 1e6)}.png")
    (run / "gps").mkdir()
    times = np.arange(-pose_margin, duration + pose_margin, 1 / pose_hz)
    north, east = route(times)
    with open(run / "gps" / f"{pose}.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        if pose == "ins":
            w.writerow(INS_COLUMNS)
            for t, n, e in zip(times, north, east, strict=True):
                w.writerow(
                    [
                        T0_US + round(t * 1e6),
                        "INS_SOLUTION_GOOD",
                        51.76,
                        -1.26,
                        110.0,
                        f"{n:.6f}",
                        f"{e:.6f}",
                        -110.0,
                        "30U",
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                        0.0,
                    ]
                )
        else:
            w.writerow(GPS_COLUMNS)
            for t, n, e in zip(times, north, east, strict=True):
                w.writerow(
                    [
                        T0_US + round(t * 1e6),
                        9,
                        51.76,
                        -1.26,
                        110.0,
                        1.0,
                        1.0,
                        2.0,
                        f"{n:.6f}",
                        f"{e:.6f}",
                        -110.0,
                        "30U",
                    ]
                )
    return run


def brute_gt(q, r, radius):
    d = np.sqrt(((q[:, None, :] - r[None, :, :]) ** 2).sum(-1))
    return d <= radius


@pytest.fixture
def two_runs(tmp_path):
    make_run(tmp_path, "2014-12-09-13-21-02", straight())
    make_run(tmp_path, "2014-12-16-18-44-24", straight(speed=8.0, lateral=3.0), duration=25.0)
    return tmp_path


def test_robotcar_spacing_and_ground_truth(two_runs):
    b = load_robotcar(two_runs, "2014-12-09-13-21-02", "2014-12-16-18-44-24")
    for t in (b.reference, b.query):
        assert t.bayer == "gbrg"
        steps = np.hypot(*np.diff(t.positions, axis=0).T)
        # first frame at or past every 5 m mark: steps within one frame's travel of 5 m
        assert np.all(np.abs(steps - 5.0) < 0.625 + 1e-6)
        assert abs(steps.mean() - 5.0) < 0.05
        assert np.all(np.diff(t.frame_ids) > 0) and np.all(np.diff(t.timestamps) > 0)
        assert t.timestamps[0] == pytest.approx(T0_US / 1e6)
        assert [p.parent.name for p in t.paths[:1]] == ["centre"]
    # the last images lie 199.4 m and 199.5 m along: marks 0, 5, ..., 195 m
    assert b.n_reference == 40 and b.n_query == 40
    np.testing.assert_array_equal(
        b.ground_truth, brute_gt(b.query.positions, b.reference.positions, 50.0)
    )
    assert b.ground_truth.sum(axis=1)[20] in (19, 20, 21)  # about 10 frames each side of 50 m
    p = b.protocol()
    assert p["tolerance"] == {"metres": 50.0} and p["spacing_m"] == 5.0
    assert p["pose_source"] == {"reference": "ins.csv", "query": "ins.csv"}


def test_robotcar_interpolates_positions_at_image_times(tmp_path):
    make_run(tmp_path, "run", straight(speed=10.0), duration=4.0, fps=10.0)
    b = load_robotcar(tmp_path, "run", "run", spacing=1.0)
    expected_north = NORTH0 + 10.0 * (b.reference.timestamps - T0_US / 1e6)
    np.testing.assert_allclose(b.reference.positions[:, 0], expected_north, atol=1e-4)
    np.testing.assert_allclose(b.reference.positions[:, 1], EAST0, atol=1e-6)
    np.testing.assert_array_equal(b.reference.frame_ids, np.arange(40))  # 1 m per frame


def test_robotcar_curved_route_spacing(tmp_path):
    make_run(tmp_path, "curve", curve(), duration=30.0)
    b = load_robotcar(tmp_path, "curve", "curve", spacing=5.0, tolerance_m=12.0)
    steps = np.hypot(*np.diff(b.reference.positions, axis=0).T)
    assert np.all(np.abs(steps - 5.0) < 0.7)
    np.testing.assert_array_equal(
        b.ground_truth, brute_gt(b.query.positions, b.reference.positions, 12.0)
    )
    np.testing.assert_array_equal(b.ground_truth.sum(axis=1)[5:-5], 5)


def test_robotcar_standing_still_adds_no_frames(tmp_path):
    make_run(tmp_path, "stop", with_stop(stop_at=10.0, stop_for=5.0), duration=20.0)
    b = load_robotcar(tmp_path, "stop", "stop", spacing=5.0)
    assert b.n_reference == 30  # 149.4 m driven: marks 0, 5, ..., 145 m
    gaps = np.diff(b.reference.timestamps)
    assert gaps.max() > 5.0  # the stop is skipped in one step


def test_robotcar_gps_csv_fallback(tmp_path):
    make_run(tmp_path, "a", straight(), pose="ins")
    make_run(tmp_path, "b", straight(lateral=1.0), pose="gps")
    b = load_robotcar(tmp_path, "a", "b")
    assert b.protocol()["pose_source"] == {"reference": "ins.csv", "query": "gps.csv"}
    np.testing.assert_allclose(b.query.positions[:, 1], EAST0 + 1.0, atol=1e-6)


def test_robotcar_drops_images_outside_pose_span(tmp_path):
    # images from t = 0, poses only from t = 2 s: the first 32 images cannot be placed
    run = make_run(tmp_path, "late", straight(), duration=10.0, pose_margin=0.0)
    ins = run / "gps" / "ins.csv"
    lines = ins.read_text().splitlines()
    ins.write_text("\n".join(lines[:1] + lines[1 + 100 :]) + "\n")
    b = load_robotcar(tmp_path, "late", "late", spacing=5.0)
    assert b.reference.frame_ids[0] == 32
    assert b.reference.timestamps[0] >= T0_US / 1e6 + 2.0


def test_robotcar_window(two_runs):
    full = load_robotcar(two_runs, "2014-12-09-13-21-02", "2014-12-16-18-44-24")
    b = load_robotcar(two_runs, "2014-12-09-13-21-02", "2014-12-16-18-44-24", first=5, count=10)
    assert b.n_reference == b.n_query == 10
    np.testing.assert_array_equal(b.reference.positions, full.reference.positions[5:15])
    assert (b.protocol()["first"], b.protocol()["count"]) == (5, 10)
    beyond = "first=35, count=10, ending at position 44, lies beyond the data: run .* 40 frames"
    with pytest.raises(ValueError, match=beyond):
        load_robotcar(two_runs, "2014-12-09-13-21-02", "2014-12-16-18-44-24", first=35, count=10)


def test_robotcar_load_images_demosaics(tmp_path):
    make_run(tmp_path, "run", straight(), duration=2.0)
    b = load_benchmark("robotcar", root=tmp_path, reference="run", query="run", spacing=5.0)
    images = b.reference.load_images(size=(3, 4), cache=False, progress=False)
    assert images.shape == (len(b.reference), 3, 4) and images.dtype == np.float32
    np.testing.assert_allclose(images, 100 / 255, atol=1e-5)


# -- errors --------------------------------------------------------------------------------------
def test_robotcar_missing_run_lists_runs(two_runs):
    with pytest.raises(
        FileNotFoundError,
        match=r"query run folder not found: .*2015-01-01.*"
        r"runs found in .*: 2014-12-09-13-21-02, 2014-12-16-18-44-24",
    ):
        load_robotcar(two_runs, "2014-12-09-13-21-02", "2015-01-01-00-00-00")


def test_robotcar_missing_stereo_centre(tmp_path):
    run = make_run(tmp_path, "run", straight(), duration=1.0)
    (run / "stereo" / "centre").rename(run / "stereo" / "left")
    with pytest.raises(FileNotFoundError, match=r"image folder not found: .*stereo.centre"):
        load_robotcar(tmp_path, "run", "run")


def test_robotcar_missing_pose_files(tmp_path):
    run = make_run(tmp_path, "run", straight(), duration=1.0)
    (run / "gps" / "ins.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"neither .*ins.csv nor .*gps.csv exists"):
        load_robotcar(tmp_path, "run", "run")


def test_robotcar_empty_image_folder(tmp_path):
    run = make_run(tmp_path, "run", straight(), duration=1.0)
    for p in (run / "stereo" / "centre").iterdir():
        p.unlink()
    with pytest.raises(ValueError, match="no image files.*centre"):
        load_robotcar(tmp_path, "run", "run")


def test_robotcar_non_numeric_image_name(tmp_path):
    run = make_run(tmp_path, "run", straight(), duration=1.0)
    Image.fromarray(np.zeros((2, 2), np.uint8)).save(run / "stereo" / "centre" / "frame_a.png")
    with pytest.raises(ValueError, match="numeric timestamp in microseconds: .*frame_a.png"):
        load_robotcar(tmp_path, "run", "run")


def test_robotcar_no_image_within_pose_span(tmp_path):
    run = make_run(tmp_path, "run", straight(), duration=2.0)
    ins = run / "gps" / "ins.csv"
    lines = ins.read_text().splitlines()
    shifted = [lines[0]] + [
        ",".join([str(int(r.split(",")[0]) + 10**9)] + r.split(",")[1:]) for r in lines[1:]
    ]
    ins.write_text("\n".join(shifted) + "\n")
    with pytest.raises(ValueError, match="no image of .* lies within the time span of .*ins.csv"):
        load_robotcar(tmp_path, "run", "run")


def _rewrite(path: Path, edit):
    lines = path.read_text().splitlines()
    path.write_text("\n".join(edit(lines)) + "\n")


@pytest.mark.parametrize(
    "edit, match",
    [
        (
            lambda ls: [ls[0].replace("northing", "north").replace("easting", "east")] + ls[1:],
            r"ins.csv: missing column\(s\) northing, easting",
        ),
        (
            lambda ls: [ls[0]] + ["x" + ls[1]] + ls[2:],
            r"ins.csv, line 2: timestamp must be an integer .* got 'x1418",
        ),
        (
            lambda ls: ls[:3] + [ls[3].replace("INS_SOLUTION_GOOD,", "")] + ls[4:],
            r"ins.csv, line 4: expected 15 fields",
        ),
        (
            lambda ls: ls[:5] + [ls[4]] + ls[6:],
            r"ins.csv, line 6: timestamps must be strictly increasing",
        ),
        (lambda ls: [ls[0]], r"ins.csv: no pose rows"),
        (lambda ls: [], r"ins.csv: empty file"),
        (
            lambda ls: [ls[0], ls[1].replace(ls[1].split(",")[5], "abc")] + ls[2:],
            r"ins.csv, line 2: northing must be a number; got 'abc",
        ),
    ],
)
def test_robotcar_malformed_ins_csv(tmp_path, edit, match):
    run = make_run(tmp_path, "run", straight(), duration=1.0)
    _rewrite(run / "gps" / "ins.csv", edit)
    with pytest.raises(ValueError, match=match):
        load_robotcar(tmp_path, "run", "run")


def test_read_poses_reads_only_needed_columns(tmp_path):
    path = tmp_path / "poses.csv"
    path.write_text("easting,timestamp,extra,northing\n2.5,1000,foo,1.5\n3.5,2000,bar,4.5\n")
    t, ne = read_poses(path)
    np.testing.assert_array_equal(t, [1000, 2000])
    np.testing.assert_array_equal(ne, [[1.5, 2.5], [4.5, 3.5]])
    with pytest.raises(FileNotFoundError, match="pose file not found"):
        read_poses(tmp_path / "none.csv")


def test_read_poses_refuses_a_needed_column_named_twice(tmp_path):
    path = tmp_path / "poses.csv"
    path.write_text("timestamp,northing,easting,northing\n1000,1.5,2.5,9\n2000,4.5,3.5,9\n")
    with pytest.raises(ValueError, match=r"poses.csv: column 'northing' appears 2 times"):
        read_poses(path)
    path.write_text("timestamp,northing,easting,extra,extra\n1000,1.5,2.5,a,b\n")
    assert read_poses(path)[1].tolist() == [[1.5, 2.5]]  # (a column not read may repeat)


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"spacing": 0}, ValueError, "spacing must be > 0"),
        ({"spacing": -1.0}, ValueError, "spacing must be >= 0.0; got -1.0"),
        ({"tolerance_m": float("nan")}, ValueError, "tolerance_m must be finite; got nan"),
        ({"tolerance_m": "50"}, TypeError, "tolerance_m must be a number"),
        ({"count": 0}, ValueError, "count must be >= 1"),
    ],
)
def test_robotcar_bad_arguments(two_runs, kwargs, err, match):
    with pytest.raises(err, match=match):
        load_robotcar(two_runs, "2014-12-09-13-21-02", "2014-12-16-18-44-24", **kwargs)


def test_select_by_distance():
    np.testing.assert_array_equal(select_by_distance([[0, 0], [0, 1], [0, 2], [0, 3]], 2.0), [0, 2])
    # frames farther apart than the spacing are each kept once
    np.testing.assert_array_equal(select_by_distance([[0, 0], [0, 10], [0, 20]], 2.0), [0, 1, 2])
    np.testing.assert_array_equal(select_by_distance([[5, 5]], 1.0), [0])
    # standing still: repeated positions are skipped
    np.testing.assert_array_equal(
        select_by_distance([[0, 0], [0, 0], [0, 0], [0, 3], [0, 3], [0, 6]], 3.0), [0, 3, 5]
    )


# 320 images at 16 Hz over 20 s; poses from -margin to 20 + margin s at 50 Hz: with margin
# -0.2 the images at 0-0.19 s and 19.8-19.94 s (4 + 3) lie outside, with -2.0 those at
# 0-1.94 s and 18-19.94 s (32 + 32)
@pytest.mark.parametrize(
    "margin, dropped, first, level", [(-0.2, 7, 4, "INFO"), (-2.0, 64, 32, "WARNING")]
)
def test_images_outside_the_pose_log_are_dropped_and_said(
    tmp_path, caplog, margin, dropped, first, level
):
    # those images cannot be placed (no extrapolation); a twentieth of the run or more is a
    # warning, not an info line
    make_run(tmp_path, "run", straight(), duration=20.0, pose_margin=margin)
    with caplog.at_level("INFO", logger="flyvpr"):
        b = load_robotcar(tmp_path, "run", "run")
    # (reference and query are the same run here: read, and said, once each)
    record, again = [r for r in caplog.records if "outside the time span" in r.getMessage()]
    assert record.getMessage() == again.getMessage()
    assert record.levelname == level
    msg = record.getMessage()
    assert msg.startswith(f"run: dropped {dropped} of 320 images ({100 * dropped / 320:.1f}%)")
    assert ("(images " in msg) == (level == "WARNING")
    assert b.reference.frame_ids.min() == first
