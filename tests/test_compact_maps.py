"""Compact maps of a recording: ``flyvpr map --compact`` and ``flyvpr localize`` against one."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import threading

import numpy as np
import pytest

import flyvpr._chunks
from flyvpr.cli import main
from flyvpr.large import CompactEncoder, LargeLocalizer, MapFileError, write_large_map
from flyvpr.large.recording import (
    build_compact_map,
    compact_localizer,
    index_path,
    is_compact_map,
    open_compact_map,
)
from flyvpr.metrics import evaluate, evaluate_answers

N = 120


@pytest.fixture(scope="module")
def route(nordland_64x32, tmp_path_factory):
    """The first N summer (map) and winter (query) frames, each in a folder of its own, and
    positions 2 m apart for both."""
    root = tmp_path_factory.mktemp("route")
    out = {}
    for season in ("summer", "winter"):
        folder = root / season
        folder.mkdir()
        for path in sorted((nordland_64x32 / season).glob("*.png"))[:N]:
            shutil.copy(path, folder / path.name)
        out[season] = folder
    xy = root / "xy.csv"
    xy.write_text("frame,x,y\n" + "".join(f"{i},{2.0 * i},5\n" for i in range(N)))
    out["xy"] = xy
    return out


@pytest.fixture(scope="module")
def frames(route):
    from flyvpr.images import list_images, load_images

    return {s: load_images(list_images(route[s]), progress=False) for s in ("summer", "winter")}


@pytest.fixture(scope="module")
def built(route, tmp_path_factory):
    path = tmp_path_factory.mktemp("maps") / "summer.fvmap"
    build_compact_map(route["summer"], path, positions=route["xy"], index="mih")
    return path


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# -- the library -------------------------------------------------------------------------------
def test_the_map_holds_the_encoders_codes_and_the_recordings_places(built, frames):
    cmap = open_compact_map(built)
    direct = CompactEncoder(random_state=0).fit(frames["summer"])
    np.testing.assert_array_equal(cmap.large_map.codes, direct.encode(frames["summer"]))
    q = frames["winter"][:7]
    np.testing.assert_array_equal(cmap.encoder.encode(q), direct.encode(q))
    np.testing.assert_array_equal(cmap.encoder.score(q), direct.score(q))
    np.testing.assert_array_equal(cmap.frames, np.arange(N))
    assert np.isnan(cmap.timestamps).all() and cmap.timestamps.dtype == np.float64
    np.testing.assert_array_equal(cmap.positions, np.c_[2.0 * np.arange(N), np.full(N, 5.0)])
    assert cmap.place_spacing == 2.0 and cmap.size == (32, 64) and cmap.n_places == N
    assert cmap.info["fit_frames"] == N and cmap.info["seed"] == 0
    assert cmap.info["source_kind"] == "image folder" and cmap.info["every"] == "1"
    assert cmap.info["positions_from"] is not None and is_compact_map(built)
    assert index_path(built).exists()


def test_a_long_recording_fits_the_encoder_on_an_evenly_spaced_sample(route, frames, tmp_path):
    # 120 frames, at most 50: the stride doubles to 4 (120 -> 60 -> 30 frames)
    cmap = build_compact_map(route["summer"], tmp_path / "m.fvmap", fit_frames=50, n_bits=128)
    direct = CompactEncoder(n_bits=128, random_state=0).fit(frames["summer"][::4])
    np.testing.assert_array_equal(cmap.encoder.projection_, direct.projection_)
    np.testing.assert_array_equal(cmap.large_map.codes, direct.encode(frames["summer"]))
    assert cmap.info["fit_frames"] == 30 and cmap.large_map.n_bits == 128
    # at most 60: stride 2
    cmap = build_compact_map(route["summer"], tmp_path / "n.fvmap", fit_frames=60, every=2)
    assert cmap.info["fit_frames"] == 60 and cmap.n_places == 60
    np.testing.assert_array_equal(cmap.frames, np.arange(0, N, 2))


@pytest.fixture
def small_chunks(monkeypatch):
    # 120 frames in chunks of 50 (batches of 16 chunks): three chunks, the last one short
    monkeypatch.setattr(flyvpr._chunks, "CHUNK", 50)


def test_jobs_write_the_one_process_file_byte_for_byte(route, tmp_path, small_chunks):
    one = build_compact_map(route["summer"], tmp_path / "one.fvmap", positions=route["xy"])
    two = build_compact_map(
        route["summer"], tmp_path / "two.fvmap", positions=route["xy"], n_jobs=2
    )
    assert one.path.read_bytes() == two.path.read_bytes()
    assert one.large_map.map_id == two.large_map.map_id


def test_a_dask_cluster_writes_the_one_process_file_byte_for_byte(route, tmp_path, small_chunks):
    distributed = pytest.importorskip("distributed")
    one = build_compact_map(route["summer"], tmp_path / "one.fvmap")
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        two = build_compact_map(route["summer"], tmp_path / "two.fvmap", scheduler=client)
    assert one.path.read_bytes() == two.path.read_bytes()


def test_the_localizer_tracks_the_winter_frames(built, frames):
    loc = compact_localizer(open_compact_map(built), window=64)
    assert isinstance(loc, LargeLocalizer) and loc.n_places == N
    fixes = [loc.update(image) for image in frames["winter"]]
    right = np.array([abs(f.place - i) <= 2 for i, f in enumerate(fixes)])
    assert right[40:].mean() > 0.9
    assert any(f.state == "localized" for f in fixes[40:])


def test_mih_reads_the_maps_index_file_and_builds_one_without_it(built, monkeypatch, tmp_path):
    from flyvpr.large import MultiIndexHash

    cmap = open_compact_map(built)

    def no_build(self, codes):
        raise AssertionError("built")

    monkeypatch.setattr(MultiIndexHash, "build", no_build)
    loc = compact_localizer(cmap, index="mih")
    assert isinstance(loc.index, MultiIndexHash) and isinstance(loc.index.places_, np.memmap)
    monkeypatch.undo()
    copy = tmp_path / "copy.fvmap"
    shutil.copy(built, copy)  # no .mih beside it
    loc = compact_localizer(open_compact_map(copy), index="mih")
    assert isinstance(loc.index, MultiIndexHash) and not isinstance(loc.index.places_, np.memmap)
    with pytest.raises(ValueError, match="index must be 'exhaustive' or 'mih'; got 'faiss'"):
        compact_localizer(cmap, index="faiss")


def test_a_map_without_an_encoder_is_refused(tmp_path):
    path = write_large_map(tmp_path / "bare.fvmap", np.zeros((4, 32), np.uint8))
    with pytest.raises(MapFileError, match="bare.fvmap: a map of compact codes without an encoder"):
        open_compact_map(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda s, a: s.pop("image_shape"), "exactly params and image_shape"),
        (lambda s, a: s["params"].pop("pool_size"), "params must be exactly"),
        (lambda s, a: s.update(image_shape=[32, 0]), "two positive integers"),
        (lambda s, a: s["params"].update(n_bits=100), "multiple of 64"),
        (lambda s, a: s["params"].update(wavelength="6"), "wavelength must be a number"),
        (lambda s, a: a.update(valid_pixels=a["valid_pixels"] * 2), "valid_pixels must be"),
        (lambda s, a: a.update(valid_pixels=a["valid_pixels"] * 0), "no valid pixel"),
        (lambda s, a: a.update(feature_mean=a["feature_mean"][:-1]), "feature_mean must be"),
        (lambda s, a: a["projection"].__setitem__((0, 0), np.nan), "projection must be finite"),
        (lambda s, a: a.update(projection=a["projection"].astype(np.float64)), "projection must"),
    ],
)
def test_a_saved_encoder_that_does_not_fit_is_refused(frames, change, message):
    enc = CompactEncoder(random_state=0).fit(frames["summer"][:20])
    settings, arrays = enc.state()
    settings = json.loads(json.dumps(settings))
    arrays = {k: v.copy() for k, v in arrays.items()}
    change(settings, arrays)
    with pytest.raises(ValueError, match=message):
        CompactEncoder.from_state(settings, arrays, enc.reference_codes_)


def test_reference_codes_of_another_width_are_refused(frames):
    enc = CompactEncoder(random_state=0).fit(frames["summer"][:20])
    settings, arrays = enc.state()
    with pytest.raises(ValueError, match=r"reference codes must be uint8 of shape \(n, 32\)"):
        CompactEncoder.from_state(settings, arrays, enc.reference_codes_[:, :16])
    back = CompactEncoder.from_state(settings, arrays, enc.reference_codes_)
    assert back.n_reference_ == 20 and back.image_shape_ == (32, 64)


@pytest.mark.parametrize("fit_frames", [1, 0])
def test_bad_build_parameters(route, tmp_path, fit_frames):
    with pytest.raises(ValueError, match=f"fit_frames must be >= 2; got {fit_frames}"):
        build_compact_map(route["summer"], tmp_path / "m.fvmap", fit_frames=fit_frames)
    with pytest.raises(ValueError, match="index must be None or 'mih'; got 'hnsw'"):
        build_compact_map(route["summer"], tmp_path / "m.fvmap", index="hnsw")
    with pytest.raises(ValueError, match="n_bits must be a multiple of 64"):
        build_compact_map(route["summer"], tmp_path / "m.fvmap", n_bits=100)
    with pytest.raises(ValueError, match=r"fit_frames=10000000000000 \(a sample of 32x64"):
        build_compact_map(route["summer"], tmp_path / "m.fvmap", fit_frames=10**13)
    assert not list(tmp_path.iterdir())


# -- metrics from answers ----------------------------------------------------------------------
def test_evaluate_answers_equals_evaluate_on_the_answers_matrix():
    rng = np.random.default_rng(0)
    n, places = 200, 50
    answer = rng.integers(0, places, n)
    conf = rng.random(n).round(2)  # ties too
    truth = rng.integers(0, places, n)
    gt = np.abs(np.arange(places)[None, :] - truth[:, None]) <= 2
    gt[:10] = False  # queries without a match
    S = np.full((n, places), -1.0)
    S[np.arange(n), answer] = conf
    a = evaluate(S, gt, ks=(1,))
    b = evaluate_answers(conf, gt[np.arange(n), answer], gt.any(axis=1))
    for key in ("auc", "recall_at_1", "recall_at_100_precision", "extended_precision"):
        assert b[key] == pytest.approx(a[key], abs=1e-12), key
    assert b["n_query"] == n and b["n_query_with_match"] == a["n_query_with_match"] == n - 10


def test_evaluate_answers_refusals():
    with pytest.raises(ValueError, match="1-d of one length"):
        evaluate_answers([0.5, 0.4], [True], [True, True])
    with pytest.raises(ValueError, match="correct must be boolean .* other than 0 and 1"):
        evaluate_answers([0.5], [2], [True])
    with pytest.raises(ValueError, match="confidence must be finite"):
        evaluate_answers([np.nan], [True], [True])
    with pytest.raises(ValueError, match="correct is True for a query whose has_match is False"):
        evaluate_answers([0.5], [True], [False])
    with pytest.raises(ValueError, match="has_match is False for every query"):
        evaluate_answers([0.5], [False], [False])


# -- the command line --------------------------------------------------------------------------
def test_map_then_localize_from_the_command_line(route, tmp_path, capsys):
    path = tmp_path / "s.fvmap"
    code, out, err = _run(capsys, "map", route["summer"], "--out", path, "--compact", "--mih")
    assert code == 0, err
    assert out.startswith(f"compact map of {N} places (256 bits, ")
    assert "encoder fitted on 120 frames, seed 0" in out and "without positions" in out
    assert f"wrote {path}\nwrote {path.with_suffix('.mih')}\n" in out
    records = tmp_path / "r.csv"
    code, out, err = _run(
        capsys, "localize", "--map", path, route["winter"], "--out", records,
        "--ground-truth", "frames", "--tolerance", "2", "--index", "mih",
    )  # fmt: skip
    assert code == 0, err
    assert f"compact map ({N} places, 256 bits, ready in " in out
    assert "relocation by multi-index hashing from s.mih)" in out
    assert f"{N} frames of image folder" in out
    with open(records, newline="") as fh:
        rows = list(csv.DictReader(fh))
    columns = ["frame", "timestamp", "place", "confidence", "state", "relocated", "correct"]
    assert list(rows[0]) == columns
    assert [int(r["frame"]) for r in rows] == list(range(N))
    correct = np.array([r["correct"] == "1" for r in rows])
    np.testing.assert_array_equal(
        correct, [abs(int(r["place"]) - int(r["frame"])) <= 2 for r in rows]
    )
    assert {r["state"] for r in rows} == {"localized", "lost"}
    assert sum(int(r["relocated"]) for r in rows) >= 1
    conf = np.array([float(r["confidence"]) for r in rows])
    expected = evaluate_answers(conf, correct, np.ones(N, bool))
    auc = float(re.search(r"AUC (\d\.\d+)", out).group(1))
    assert auc == round(expected["auc"], 4) and correct[40:].mean() > 0.9
    localized = float(re.search(r"localized (\d+\.\d)% of frames", out).group(1))
    assert localized == round(100 * np.mean([r["state"] == "localized" for r in rows]), 1)


def test_localize_records_the_maps_positions_and_drives_odometry(
    built, route, tmp_path, capsys, monkeypatch
):
    seen = []
    real = LargeLocalizer.update_code

    def spy(self, code, velocity=None):
        seen.append(velocity)
        return real(self, code, velocity)

    monkeypatch.setattr(LargeLocalizer, "update_code", spy)
    query_xy = tmp_path / "q.csv"  # 3 m per frame from frame 4 on: 1.5 places per frame
    query_xy.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(4, N)))
    records = tmp_path / "r.jsonl"
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--positions", query_xy,
        "--out", records,
    )  # fmt: skip
    assert code == 0, err
    assert f"\nodometry: path integration from --positions {query_xy} (map spacing 2 m per " in out
    assert seen == [None] * 5 + [1.5] * (N - 5)
    rows = [json.loads(line) for line in records.read_text().splitlines()]
    assert len(rows) == N and set(rows[0]) >= {"x", "y", "place", "state", "confidence"}
    assert all(r["x"] == 2.0 * r["place"] and r["y"] == 5.0 for r in rows)
    assert [r["odometry"] for r in rows] == seen  # what the filter was given, None for none
    seen.clear()
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--positions", query_xy,
        "--no-odometry", "--every", "2", "--out", records,
    )  # fmt: skip
    assert code == 0, err
    assert "\nodometry: off (--no-odometry)\n" in out and seen == [None] * (N // 2)
    assert "odometry" not in json.loads(records.read_text().splitlines()[0])


def test_ground_truth_by_positions(built, route, capsys):
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--ground-truth", route["xy"],
        "--radius", "4",
    )  # fmt: skip
    assert code == 0, err
    by_position = float(re.search(r"within 4 m\): AUC (\d\.\d+)", out).group(1))
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--ground-truth", "frames",
        "--tolerance", "2",
    )  # fmt: skip
    assert code == 0, err
    assert by_position == float(re.search(r"within 2\): AUC (\d\.\d+)", out).group(1))


def test_ground_truth_rows_sparser_than_frames_are_interpolated(built, route, tmp_path, capsys):
    # a row every third frame: the frames between get the straight line between their
    # neighbours' rows (without it they had no row and were left out of the score)
    full = _run(
        capsys, "localize", "--map", built, route["winter"], "--ground-truth", route["xy"],
        "--radius", "4",
    )[1]  # fmt: skip
    sparse = tmp_path / "sparse.csv"
    rows = np.loadtxt(route["xy"], delimiter=",", skiprows=1)
    kept = rows[np.r_[0 : len(rows) : 3, len(rows) - 1]]
    sparse.write_text(
        "frame,x,y\n" + "".join(f"{int(f)},{float(x)!r},{float(y)!r}\n" for f, x, y in kept)
    )
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--ground-truth", sparse,
        "--radius", "4",
    )  # fmt: skip
    assert code == 0, err
    assert "left out" not in out
    auc = re.compile(r"within 4 m\): AUC (\d\.\d+)")
    assert auc.search(out).group(1) == auc.search(full).group(1)


def test_frames_the_ground_truth_gives_no_position_are_not_scored(built, route, tmp_path, capsys):
    from flyvpr.metrics import evaluate_answers

    gt = tmp_path / "late.csv"  # positions from frame 20 on only
    gt.write_text("frame,x,y\n" + "".join(f"{i},{2.0 * i},5\n" for i in range(20, N)))
    records = tmp_path / "r.csv"
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--ground-truth", gt,
        "--radius", "4", "--out", records,
    )  # fmt: skip
    assert code == 0, err
    assert f"over {N - 20} frames (20 frames without a ground-truth position left out)" in out
    rows = list(csv.DictReader(records.open()))
    assert len(rows) == N and all(r["correct"] == "" for r in rows[:20])
    assert {r["correct"] for r in rows[20:]} <= {"0", "1"}
    conf = np.array([float(r["confidence"]) for r in rows[20:]])
    right = np.array([r["correct"] == "1" for r in rows[20:]])
    expected = evaluate_answers(conf, right, np.ones(N - 20, bool))["auc"]
    assert float(re.search(r"within 4 m\): AUC (\d\.\d+)", out).group(1)) == round(expected, 4)


def test_odometry_off_when_the_map_has_no_positions(route, tmp_path, capsys):
    path = tmp_path / "bare.fvmap"
    assert _run(capsys, "map", route["summer"], "--out", path, "--compact", "-q")[0] == 0
    code, out, err = _run(
        capsys, "localize", "--map", path, route["winter"], "--positions", route["xy"]
    )
    assert code == 0, err
    assert (
        f"odometry: off, the map has no positions to turn the metres of --positions "
        f"{route['xy']} into places (build it with --positions or --position-topic)"
    ) in out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["map", "{summer}", "--out", "{tmp}/m.fvmap", "--bits", "128"], "--bits needs --compact"),
        (["map", "{summer}", "--out", "{tmp}/m.map", "--mih"], "--mih needs --compact"),
        (["map", "{summer}", "--out", "{tmp}/m.fvmap", "--compact", "--method", "pixels"],
         "--method: a compact map has its own encoder"),
        (["map", "{summer}", "--out", "{tmp}/m.fvmap", "--compact", "--fit-frames", "1"],
         "--fit-frames: must be >= 2; got 1"),
        (["map", "{summer}", "--out", "{summer}", "--compact"], "--out"),
        (["localize", "--map", "{map}", "{winter}", "--render", "{tmp}/t.html"],
         "--render: not with a compact map"),
        (["localize", "--map", "{map}", "{winter}", "--size", "16x32"],
         "--size: a compact map fixes the image size"),
        (["localize", "--map", "{map}", "{winter}", "--calibration", "{tmp}/c.json"],
         "--calibration: not with a compact map"),
        (["localize", "--map", "{map}", "rtsp://example.invalid/s", "--view-save", "{tmp}/v.rrd"],
         "--view-save: not with a compact map"),
        (["localize", "--map", "{map}", "rtsp://example.invalid/s", "--mcap-thumbnails"],
         "--mcap-thumbnails: not with a compact map"),
        (["localize", "--map", "{map}", "{winter}", "--out", "{map}"], "--out"),
        (["localize", "--map", "{map}", "{winter}", "--ground-truth", "frames"],
         "needs --tolerance"),
        (["localize", "--dataset", "nordland", "--index", "mih"], "--index needs --map"),
    ],
)  # fmt: skip
def test_usage_errors_exit_2_and_write_nothing(built, route, tmp_path, capsys, argv, message):
    subs = {"summer": route["summer"], "winter": route["winter"], "tmp": tmp_path, "map": built}
    before = sorted(p.name for p in tmp_path.iterdir())
    code, out, err = _run(capsys, *[a.format(**subs) for a in argv])
    assert code == 2 and re.search(message, err), err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_index_with_a_map_that_is_not_compact(route, tmp_path, capsys):
    path = tmp_path / "plain.map"
    assert _run(capsys, "map", route["summer"], "--out", path, "--method", "pixels", "-q")[0] == 0
    code, out, err = _run(capsys, "localize", "--map", path, route["winter"], "--index", "mih")
    assert code == 2 and "--index: only with a compact map" in err


def test_a_corrupt_or_foreign_map_exits_1_and_writes_nothing(built, route, tmp_path, capsys):
    cut = tmp_path / "cut.fvmap"
    cut.write_bytes(built.read_bytes()[:-100])
    bare = write_large_map(tmp_path / "bare.fvmap", np.zeros((4, 32), np.uint8))
    junk = tmp_path / "junk.fvmap"  # not even the start of one: named as a compact map's fault
    junk.write_bytes(b"\x00" * 5000)
    empty_file = tmp_path / "empty.fvmap"
    empty_file.write_bytes(b"")
    for path, message in (
        (cut, "truncated or corrupt"),
        (bare, "without an encoder"),
        (junk, "not a flyvpr map file (no b'FLYVPRLM' at the start)"),
        (empty_file, "too short (0 bytes) to be a flyvpr map file"),
        (tmp_path / "none.fvmap", "map file not found"),
    ):
        out_file = tmp_path / "r.csv"
        code, out, err = _run(capsys, "localize", "--map", path, route["winter"], "--out", out_file)
        assert code == 1 and str(path) in err and message in err, err
        assert not out_file.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    code, out, err = _run(capsys, "map", empty, "--out", tmp_path / "e.fvmap", "--compact")
    assert code == 1 and str(empty) in err, err
    assert not (tmp_path / "e.fvmap").exists()


def test_mih_without_its_file_says_the_tables_were_built(built, route, tmp_path, capsys):
    copy = tmp_path / "copy.fvmap"
    shutil.copy(built, copy)  # no .mih beside it
    code, out, err = _run(capsys, "localize", "--map", copy, route["winter"], "--index", "mih")
    assert code == 0, err
    assert "relocation by multi-index hashing, tables built (no copy.mih))" in out


def test_a_model_map_named_fvmap_is_still_a_model_map(route, tmp_path, capsys):
    # `flyvpr map` without --compact writes a model-file map whatever its name
    path = tmp_path / "plain.fvmap"
    code, _, err = _run(capsys, "map", route["summer"], "--out", path)
    assert code == 0, err
    code, out, err = _run(capsys, "localize", "--map", path, route["winter"])
    assert code == 0, err
    assert f"{N} frames of image folder" in out and "compact map" not in out


def test_a_live_stream_against_a_compact_map(built, frames, tmp_path, capsys):
    av = pytest.importorskip("av")  # noqa: F841
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    from benchmarks.stream_servers import MjpegServer, jpeg_bytes

    # the map's own frames at 4x its size, so each served frame has one right answer
    big = np.repeat(np.repeat(frames["summer"], 4, axis=1), 4, axis=2)
    jpegs = [jpeg_bytes(np.rint(im * 255).astype(np.uint8), quality=95) for im in big]
    out = tmp_path / "live.csv"
    timer = threading.Timer(3.5, os.kill, (os.getpid(), signal.SIGINT))
    with MjpegServer(jpegs, fps=30, duration=30) as srv:  # 3.5 s: about 100 of the 120 frames
        timer.start()
        try:
            code, stdout, err = _run(capsys, "localize", "--map", built, srv.url, "--out", out)
        finally:
            timer.cancel()
    assert code == 130, err
    assert stdout.startswith(f"compact 256-bit codes + windowed CANN: stream {srv.url} against ")
    assert "ended by Ctrl-C" in stdout
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == [
        "frame", "timestamp", "place", "confidence", "state", "relocated", "x", "y", "latency_ms"
    ]  # fmt: skip
    assert len(rows) >= 60 and max(int(r["frame"]) for r in rows) < N  # no wrap to frame 0
    late = [r for r in rows if int(r["frame"]) >= 40]
    right = [abs(int(r["place"]) - int(r["frame"]) % N) <= 2 for r in late]
    assert late and np.mean(right) > 0.9
    assert all(float(r["x"]) == 2.0 * int(r["place"]) for r in rows)


def test_a_map_changed_after_it_was_written_is_refused_unless_unverified(
    built, route, tmp_path, capsys
):
    from flyvpr.large.mapfile import _read_container

    bad = tmp_path / "bad.fvmap"
    shutil.copy(built, bad)
    header, _ = _read_container(bad, "map")
    raw = bytearray(bad.read_bytes())
    raw[header["arrays"]["codes"]["offset"] + 40] ^= 0x10  # one bit of place 1's code
    bad.write_bytes(bytes(raw))
    with pytest.raises(MapFileError, match="bad.fvmap: the content does not match the file's"):
        open_compact_map(bad)
    assert open_compact_map(bad, verify=False).large_map.n_places == N  # structure intact
    out = tmp_path / "where.csv"
    code, _, err = _run(capsys, "localize", "--map", bad, route["winter"], "--out", out)
    assert code == 1 and "the content does not match" in err and not out.exists()


def test_more_bits_than_the_optic_lobe_has_features_is_a_usage_error(route, tmp_path, capsys):
    out = tmp_path / "small.fvmap"
    code, _, err = _run(capsys, "map", route["summer"], "--compact", "--size", "8x8", "--out", out)
    assert code == 2 and not out.exists()
    assert "--bits 256: a compact map at --size 8x8 has at most 16 bits" in err
    assert "a compact map needs at least 64, or a larger --size" in err
    code, _, err = _run(
        capsys, "map", route["summer"], "--compact", "--size", "30x62", "--out", out
    )
    assert code == 2 and not out.exists()
    assert "--size 30x62: a compact map needs both sides multiples of 4" in err
    code, _, err = _run(
        capsys, "map", route["summer"], "--compact", "--size", "16x16", "--bits", "128",
        "--out", out, "-q",
    )  # fmt: skip
    assert code == 2 and "--bits 128: a compact map at --size 16x16 has at most 64 bits" in err
    assert "give --bits 64 or fewer" in err
    assert _run(
        capsys, "map", route["summer"], "--compact", "--size", "16x16", "--bits", "64",
        "--out", out, "-q",
    )[0] == 0  # fmt: skip


def test_max_bits_is_the_lobe_s_features_or_none_for_simhash():
    from flyvpr.large.codes import CompactEncoder

    assert CompactEncoder().max_bits((32, 64)) == 4 * 8 * 16
    assert CompactEncoder(pool_size=2).max_bits((8, 8)) == 4 * 4 * 4
    assert CompactEncoder(projection="simhash").max_bits((8, 8)) is None


def test_the_index_file_of_each_map_is_its_own(route, tmp_path, capsys, caplog):
    assert index_path(tmp_path / "a.fvmap") == tmp_path / "a.mih"
    assert index_path(tmp_path / "route.v1") == tmp_path / "route.v1.mih"
    assert index_path(tmp_path / "x.mih") == tmp_path / "x.mih.mih"  # never the map itself
    # two maps whose names differ only after the last dot: two index files
    for name, seed in (("route.v1", "1"), ("route.v2", "2")):
        argv = ["map", route["summer"], "--out", tmp_path / name, "--compact", "--mih", "-q"]
        assert _run(capsys, *argv, "--seed", seed)[0] == 0
    for name in ("route.v1", "route.v2"):
        code, out, err = _run(
            capsys, "localize", "--map", tmp_path / name, route["winter"], "--index", "mih"
        )
        assert code == 0 and f"relocation by multi-index hashing from {name}.mih)" in out, err
    # a map written over with --out x.mih: map and tables stay apart
    x = tmp_path / "x.mih"
    assert _run(capsys, "map", route["summer"], "--out", x, "--compact", "--mih", "-q")[0] == 0
    assert is_compact_map(x) and (tmp_path / "x.mih.mih").is_file()


def test_a_rebuilt_map_drops_or_ignores_the_tables_of_the_map_it_replaced(
    route, tmp_path, capsys, caplog
):
    path = tmp_path / "st.fvmap"
    sidecar = tmp_path / "st.mih"
    assert _run(capsys, "map", route["summer"], "--out", path, "--compact", "--mih", "-q")[0] == 0
    kept = sidecar.read_bytes()
    # another map in its place (another seed), without --mih: the old tables index nothing
    with caplog.at_level("WARNING", logger="flyvpr"):
        argv = ["map", route["summer"], "--out", path, "--compact", "--seed", "5", "-q"]
        assert _run(capsys, *argv)[0] == 0
    assert not sidecar.exists()
    assert any(f"removed {sidecar}" in r.getMessage() for r in caplog.records)
    # a stale index file (left by a rebuild that stopped before it): built in memory, said so
    sidecar.write_bytes(kept)
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):
        code, out, err = _run(
            capsys, "localize", "--map", path, route["winter"], "--index", "mih",
            "--ground-truth", "frames", "--tolerance", "2",
        )  # fmt: skip
    assert code == 0, err
    assert "relocation by multi-index hashing, tables built (st.mih indexes another map))" in out
    assert any("indexes another map than" in r.getMessage() for r in caplog.records)
    exact = _run(
        capsys, "localize", "--map", path, route["winter"], "--ground-truth", "frames",
        "--tolerance", "2",
    )[1]  # fmt: skip
    assert re.search(r"AUC (\d\.\d+)", out).group(1) == re.search(r"AUC (\d\.\d+)", exact).group(1)
    # the same map again (same seed): its tables still fit and stay
    assert _run(capsys, "map", route["summer"], "--out", path, "--compact", "--mih", "-q",
                "--seed", "5")[0] == 0  # fmt: skip
    tables = sidecar.read_bytes()
    assert _run(capsys, "map", route["summer"], "--out", path, "--compact", "-q",
                "--seed", "5")[0] == 0  # fmt: skip
    assert sidecar.read_bytes() == tables


def test_maps_x_and_x_fvmap_share_x_mih_and_neither_build_harms_the_others(route, tmp_path, caplog):
    # route.fvmap's tables are route.mih, as are those of a map named route (no suffix)
    fvmap, bare, sidecar = tmp_path / "route.fvmap", tmp_path / "route", tmp_path / "route.mih"
    build_compact_map(route["summer"], fvmap, index="mih")
    tables = sidecar.read_bytes()
    with caplog.at_level("WARNING", logger="flyvpr"):
        build_compact_map(route["summer"], bare, random_state=5)  # not removed: not stale
    assert sidecar.read_bytes() == tables
    assert any(f"holds the tables of the map {fvmap}" in r.getMessage() for r in caplog.records)
    with pytest.raises(ValueError, match=f"holds those of the map {fvmap}; name this map"):
        build_compact_map(route["summer"], bare, random_state=5, index="mih")
    assert sidecar.read_bytes() == tables
    # with route.fvmap gone, the file is stale for route: written over
    fvmap.unlink()
    build_compact_map(route["summer"], bare, random_state=5, index="mih")
    assert sidecar.read_bytes() != tables


def test_ground_truth_by_positions_at_the_radius_agrees_with_the_full_maps():
    # a KD-tree's distance and hypot's may differ in the last bit; at a radius of exactly
    # one of them the frame could be judged unmatchable but its answer right (the run then
    # failed in evaluate_answers): both now take the full map's sqrt(sum((q - r) ** 2))
    import types

    from scipy.spatial import cKDTree

    from flyvpr.cli._compact import _truth
    from flyvpr.localization.tracking import ground_truth_positions

    place = np.array([[5_700_000.3, 620_000.7]])  # UTM-sized metres
    rng = np.random.default_rng(0)
    differ = []
    for _ in range(20000):
        q = place + rng.normal(0.0, 30.0, (1, 2))
        exact = float(np.sqrt(((place - q) ** 2).sum()))
        if exact != float(np.hypot(*(place - q)[0])):
            differ.append((q, exact, float(np.hypot(*(place - q)[0]))))
        if len(differ) == 8:
            break
    assert len(differ) == 8

    class Batch(types.SimpleNamespace):
        def __len__(self):
            return len(self.indices)

    batch = Batch(indices=np.array([0]), timestamps=np.array([0.0]))
    for q, exact, other in differ:
        for radius in (exact, other):
            args = types.SimpleNamespace(ground_truth="gt.csv", radius=radius, tolerance=None)
            positions = types.SimpleNamespace(at=lambda i, t, interpolate=True, q=q: q)
            can, judge, known = _truth(
                args, types.SimpleNamespace(positions=place), batch, positions, cKDTree(place)
            )
            full = bool(ground_truth_positions(q, place, radius)[0, 0])
            assert known[0] and bool(can[0]) == bool(judge(np.array([0]))[0]) == full


def test_a_glitch_of_the_positions_is_refused_and_said(built, route, tmp_path, capsys):
    # 3 m per frame (1.5 places), one fix 600 m off: that frame's distance, and the next's
    # back, are glitches to every layer (more than 8 times the recent distance), counted
    # whether or not the layer re-seeds between them
    xy = tmp_path / "glitch.csv"
    xy.write_text("frame,x,y\n" + "".join(
        f"{i},{600.0 if i == 30 else 3.0 * i},0\n" for i in range(N)
    ))  # fmt: skip
    code, out, err = _run(capsys, "localize", "--map", built, route["winter"], "--positions", xy)
    assert code == 0, err
    assert (
        "\nodometry: 2 frames refused the distance moved as a glitch (more than 8 times the "
        "recent distance per frame) and were localized without it\n" in out
    )
    clean = tmp_path / "clean.csv"
    clean.write_text("frame,x,y\n" + "".join(f"{i},{3.0 * i},0\n" for i in range(N)))
    code, out, err = _run(capsys, "localize", "--map", built, route["winter"], "--positions", clean)
    assert code == 0 and "refused the distance" not in out
    code, out, err = _run(
        capsys, "localize", "--map", built, route["winter"], "--positions", xy, "--no-odometry"
    )
    assert code == 0 and "refused the distance" not in out


@pytest.fixture(scope="module")
def broken(route, tmp_path_factory):
    """The summer map with positions that jump 500 m between places 59 and 60: the first
    drive left a stretch of the road out."""
    root = tmp_path_factory.mktemp("broken")
    xy = root / "jump.csv"
    xy.write_text(
        "frame,x,y\n"
        + "".join(f"{i},{2.0 * i + (500.0 if i >= 60 else 0.0)},5\n" for i in range(N))
    )
    path = root / "broken.fvmap"
    build_compact_map(route["summer"], path, positions=xy)
    return path


def test_a_compact_map_reads_its_breaks_from_its_positions(built, broken, route, tmp_path):
    assert open_compact_map(built).breaks == ()
    cmap = open_compact_map(broken)
    assert cmap.breaks == (60,)
    assert compact_localizer(cmap).filter_.breaks_.tolist() == [60]
    assert compact_localizer(cmap, breaks=()).filter_.breaks_.size == 0
    # a map without positions has none
    path = tmp_path / "bare.fvmap"
    build_compact_map(route["summer"], path)
    assert open_compact_map(path).breaks == ()


def test_localize_gives_a_compact_map_its_breaks_and_says_so(broken, route, capsys, monkeypatch):
    seen = []
    real = LargeLocalizer.update_code

    def spy(self, code, velocity=None):
        seen.append(self.filter_.breaks_.tolist())
        return real(self, code, velocity)

    monkeypatch.setattr(LargeLocalizer, "update_code", spy)
    code, out, err = _run(capsys, "localize", "--map", broken, route["winter"])
    assert code == 0, err
    assert (
        "\nbreaks: the map's route is broken at 1 place (between places 59-60), where its "
        "positions jump: the filter does not carry the robot across (--no-breaks: one route)\n"
    ) in out
    assert seen and all(b == [60] for b in seen)
    seen.clear()
    code, out, err = _run(capsys, "localize", "--map", broken, route["winter"], "--no-breaks")
    assert code == 0, err
    assert "\nbreaks: off (--no-breaks): 1 break of the map ignored\n" in out
    assert seen and all(b == [] for b in seen)


def test_a_compact_map_without_breaks_says_nothing_of_them(built, route, capsys):
    for extra in ((), ("--no-breaks",)):
        code, out, err = _run(capsys, "localize", "--map", built, route["winter"], *extra)
        assert code == 0, err
        assert "breaks:" not in out


def test_a_live_run_on_a_compact_map_takes_no_breaks_too(broken):
    import types

    from flyvpr.cli._live import _CompactSteps

    args = types.SimpleNamespace(map=broken, index=None, no_breaks=False)
    assert _CompactSteps(args).loc.filter_.breaks_.tolist() == [60]
    args.no_breaks = True
    assert _CompactSteps(args).loc.filter_.breaks_.size == 0
