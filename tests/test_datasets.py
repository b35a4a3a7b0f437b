"""Tests of flyvpr.datasets: traverses, benchmarks, ground truth, registry and Nordland."""

from __future__ import annotations

import inspect
import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flyvpr.datasets import (
    DATASETS,
    Benchmark,
    Traverse,
    ground_truth_from_frames,
    ground_truth_from_positions,
    load_benchmark,
    load_nordland,
)
from flyvpr.datasets import base as ds_base
from flyvpr.images import ImageReadError


# -- helpers -------------------------------------------------------------------------------------
def write_png(path: Path, value: int = 128, size=(8, 16)) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full(size, value, np.uint8)).save(path)
    return path


def make_season(root: Path, season: str, numbers, pattern="images-{:05d}.png") -> list[Path]:
    return [write_png(root / season / pattern.format(k), value=k % 256) for k in numbers]


def slow_frames_gt(q, r, tol):
    out = np.zeros((len(q), len(r)), dtype=bool)
    for i, a in enumerate(q):
        for j, b in enumerate(r):
            out[i, j] = abs(int(a) - int(b)) <= tol
    return out


def slow_positions_gt(q, r, radius):
    q, r = np.asarray(q, float), np.asarray(r, float)
    out = np.zeros((len(q), len(r)), dtype=bool)
    for i in range(len(q)):
        for j in range(len(r)):
            out[i, j] = np.sqrt(((q[i] - r[j]) ** 2).sum()) <= radius
    return out


# -- ground truth from frames --------------------------------------------------------------------
def test_ground_truth_from_frames_hand_worked_3x3():
    gt = ground_truth_from_frames([0, 1, 2], [0, 1, 2], 1)
    assert gt.dtype == np.bool_
    np.testing.assert_array_equal(gt, [[1, 1, 0], [1, 1, 1], [0, 1, 1]])
    np.testing.assert_array_equal(ground_truth_from_frames([0, 1, 2], [0, 1, 2], 0), np.eye(3))


@pytest.mark.parametrize("n_q, n_r, tol", [(7, 7, 2), (5, 11, 3), (13, 4, 0), (1, 1, 0)])
def test_ground_truth_from_frames_matches_loop(n_q, n_r, tol):
    rng = np.random.default_rng(n_q * 100 + n_r)
    q = rng.integers(0, 20, n_q)
    r = rng.integers(0, 20, n_r)
    gt = ground_truth_from_frames(q, r, tol)
    assert gt.shape == (n_q, n_r)
    np.testing.assert_array_equal(gt, slow_frames_gt(q, r, tol))


def test_ground_truth_from_frames_blockwise(monkeypatch):
    monkeypatch.setattr(ds_base, "_BLOCK_ELEMENTS", 7)  # forces many row blocks
    q, r = np.arange(23), np.arange(5, 16)
    np.testing.assert_array_equal(ground_truth_from_frames(q, r, 2), slow_frames_gt(q, r, 2))


@pytest.mark.parametrize(
    "q, r, tol, err, match",
    [
        ([0.5, 1.0], [0, 1], 1, TypeError, "query_ids must be integer"),
        ([0, 1], [[0, 1]], 1, ValueError, "reference_ids must be a non-empty 1-d"),
        ([], [0, 1], 1, TypeError, "query_ids"),
        ([0, 1], [0, 1], -1, ValueError, "tolerance must be >= 0"),
        ([0, 1], [0, 1], 1.5, TypeError, "tolerance must be an int"),
    ],
)
def test_ground_truth_from_frames_errors(q, r, tol, err, match):
    with pytest.raises(err, match=match):
        ground_truth_from_frames(q, r, tol)


# -- ground truth from positions -----------------------------------------------------------------
def test_ground_truth_from_positions_boundary_is_inclusive():
    gt = ground_truth_from_positions([[0.0, 0.0]], [[30.0, 40.0], [0.0, 50.0001], [-50, 0]], 50)
    np.testing.assert_array_equal(gt, [[True, False, True]])


@pytest.mark.parametrize("n_q, n_r, radius", [(40, 60, 8.0), (60, 25, 0.5), (10, 10, 100.0)])
def test_ground_truth_from_positions_matches_loop(n_q, n_r, radius):
    rng = np.random.default_rng(n_q + n_r)
    q = rng.uniform(0, 50, (n_q, 2)) + [5.7e6, 6.2e5]  # UTM-sized coordinates
    r = rng.uniform(0, 50, (n_r, 2)) + [5.7e6, 6.2e5]
    gt = ground_truth_from_positions(q, r, radius)
    assert gt.shape == (n_q, n_r) and gt.dtype == np.bool_
    np.testing.assert_array_equal(gt, slow_positions_gt(q, r, radius))


def test_ground_truth_from_positions_radius_zero_keeps_identical_points():
    q = [[1.0, 2.0], [3.0, 4.0]]
    r = [[3.0, 4.0], [1.0, 2.0], [1.0, 2.0]]
    np.testing.assert_array_equal(
        ground_truth_from_positions(q, r, 0), [[False, True, True], [True, False, False]]
    )


def test_ground_truth_from_positions_large_route():
    # 5000 x 5000 along a straight line 5 m apart: 50 m is 10 frames each side.
    line = np.column_stack([np.arange(5000) * 5.0, np.zeros(5000)])
    gt = ground_truth_from_positions(line, line, 50.0)
    sums = gt.sum(axis=1)
    assert sums[2500] == 21 and sums[0] == 11
    assert gt.sum() == 5000 * 21 - 2 * (10 * 11 // 2)


@pytest.mark.parametrize(
    "q, r, radius, err, match",
    [
        ([[0, 0]], [[0, 0, 0]], 1, ValueError, "same number of columns"),
        ([[0, np.nan]], [[0, 0]], 1, ValueError, "query_positions contains NaN"),
        ([], [[0, 0]], 1, ValueError, r"query_positions must have shape \(N, D\)"),
        ([[0, 0]], [[0, 0]], -1, ValueError, "radius must be >= 0.0; got -1.0"),
        ([[0, 0]], [[0, 0]], "50", TypeError, "radius must be a number"),
    ],
)
def test_ground_truth_from_positions_errors(q, r, radius, err, match):
    with pytest.raises(err, match=match):
        ground_truth_from_positions(q, r, radius)


# -- Traverse ------------------------------------------------------------------------------------
def make_traverse(n=6, name="t"):
    return Traverse(
        name,
        [f"/x/{i}.png" for i in range(n)],
        timestamps=np.arange(n) * 0.5,
        positions=np.column_stack([np.arange(n), np.zeros(n)]),
        frame_ids=np.arange(10, 10 + n),
    )


def test_traverse_fields_and_len():
    t = make_traverse()
    assert len(t) == 6
    assert all(isinstance(p, Path) for p in t.paths)
    assert t.positions.dtype == np.float64 and t.positions.shape == (6, 2)
    assert t.frame_ids.dtype == np.int64
    assert "n_frames=6" in repr(t)


@pytest.mark.parametrize(
    "indices, expected",
    [
        (slice(None, None, 2), [0, 2, 4]),
        ([5, 0, 0, 3], [5, 0, 0, 3]),  # order kept, repeats allowed
        (np.array([True, False, True, False, False, True]), [0, 2, 5]),
        (np.array([1, 4], dtype=np.uint8), [1, 4]),
    ],
)
def test_traverse_subset(indices, expected):
    t = make_traverse()
    s = t.subset(indices)
    assert len(s) == len(expected) and s.name == t.name
    assert s.paths == [t.paths[i] for i in expected]
    np.testing.assert_array_equal(s.frame_ids, t.frame_ids[expected])
    np.testing.assert_array_equal(s.positions, t.positions[expected])
    np.testing.assert_array_equal(s.timestamps, t.timestamps[expected])


@pytest.mark.parametrize(
    "indices, err, match",
    [
        ([0, 6], ValueError, r"must lie in \[0, 6\); got 6"),
        ([-1], ValueError, "got -1"),
        ([], ValueError, "selects no frame"),
        (slice(10, None), ValueError, "selects no frame"),
        ([0.0, 1.0], TypeError, "sequence of ints"),
        (np.array([True, False]), ValueError, r"shape \(6,\)"),
        ([[0, 1]], ValueError, "one-dimensional"),
    ],
)
def test_traverse_subset_errors(indices, err, match):
    with pytest.raises(err, match=match):
        make_traverse().subset(indices)


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"paths": []}, ValueError, "paths is empty"),
        ({"paths": "a.png"}, TypeError, "single path"),
        ({"timestamps": [1.0]}, ValueError, r"timestamps must have shape \(2,\)"),
        ({"timestamps": [1.0, np.nan]}, ValueError, "NaN"),
        ({"positions": [1.0, 2.0]}, ValueError, r"positions must have shape \(2, 2\)"),
        ({"frame_ids": [0.0, 1.0]}, TypeError, "frame_ids must be integers"),
        ({"frame_ids": [0]}, ValueError, r"frame_ids must have shape \(2,\)"),
        ({"name": 3}, TypeError, "name must be a str"),
        ({"bayer": 1}, TypeError, "bayer"),
    ],
)
def test_traverse_validation(kwargs, err, match):
    args = {"name": "t", "paths": ["a.png", "b.png"], **kwargs}
    with pytest.raises(err, match=match):
        Traverse(**args)


def test_traverse_load_images_and_cache(tmp_path):
    paths = [write_png(tmp_path / "img" / f"{i}.png", value=40 * i) for i in range(4)]
    t = Traverse("t", paths)
    cache = tmp_path / "cache"
    images = t.load_images(size=(4, 8), cache=cache, progress=False)
    assert images.shape == (4, 4, 8) and images.dtype == np.float32
    np.testing.assert_allclose(images[:, 0, 0], np.arange(4) * 40 / 255, atol=1e-6)
    assert len(list(cache.glob("*.npz"))) == 1
    np.testing.assert_array_equal(t.load_images(size=(4, 8), cache=cache), images)


# -- Benchmark -----------------------------------------------------------------------------------
def make_benchmark(n_q=4, n_r=6):
    ref, qry = make_traverse(n_r, "ref"), make_traverse(n_q, "qry")
    gt = ground_truth_from_frames(qry.frame_ids, ref.frame_ids, 1)
    return Benchmark("synthetic", ref, qry, gt, {"frames": 1}, root="/data", count=n_r)


def test_benchmark_protocol_is_complete_and_json():
    b = make_benchmark()
    p = b.protocol()
    for key in (
        "dataset",
        "root",
        "reference",
        "query",
        "first",
        "count",
        "n_reference",
        "n_query",
        "tolerance",
    ):
        assert key in p
    assert (p["n_query"], p["n_reference"], p["reference"], p["query"]) == (4, 6, "ref", "qry")
    assert p["root"] == "/data" and p["tolerance"] == {"frames": 1}
    json.dumps(p)
    assert "tolerance={'frames': 1}" in repr(b)


def test_benchmark_subset_queries_keeps_rows():
    b = make_benchmark()
    s = b.subset_queries([3, 1, 1])
    assert s.n_query == 3 and s.n_reference == 6 and s.reference is b.reference
    np.testing.assert_array_equal(s.ground_truth, b.ground_truth[[3, 1, 1]])
    np.testing.assert_array_equal(s.query.frame_ids, b.query.frame_ids[[3, 1, 1]])
    assert s.protocol()["query_subset"] == "3 of 4 query frames"
    assert b.n_query == 4  # the original is unchanged
    every_second = b.subset_queries(slice(None, None, 2))
    np.testing.assert_array_equal(every_second.ground_truth, b.ground_truth[::2])


def test_benchmark_validation():
    b = make_benchmark()
    with pytest.raises(ValueError, match=r"ground_truth must have shape .* \(4, 6\); got \(6, 4\)"):
        Benchmark("x", b.reference, b.query, b.ground_truth.T, {"frames": 1})
    with pytest.raises(TypeError, match="ground_truth must be a boolean"):
        Benchmark("x", b.reference, b.query, b.ground_truth.astype(int), {"frames": 1})
    with pytest.raises(TypeError, match="reference must be a Traverse"):
        Benchmark("x", "ref", b.query, b.ground_truth, {"frames": 1})
    with pytest.raises(TypeError, match="tolerance must be a dict"):
        Benchmark("x", b.reference, b.query, b.ground_truth, 20)


def test_benchmark_fingerprint_follows_the_files_and_the_ground_truth(tmp_path):
    import os
    import shutil

    for season in ("summer", "winter"):
        make_season(tmp_path / "a", season, range(1, 7))
    first = load_nordland(tmp_path / "a", tolerance=1).fingerprint()
    json.dumps(first)
    assert first == load_nordland(tmp_path / "a", tolerance=1).fingerprint()
    assert first["reference"]["n_images"] == first["query"]["n_images"] == 6
    assert first["ground_truth"]["shape"] == [6, 6] and first["ground_truth"]["n_true"] == 16
    # a copy that keeps the modification times, elsewhere: the same data
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    assert load_nordland(tmp_path / "b", tolerance=1).fingerprint() == first
    # the same files, another tolerance: another ground truth
    wider = load_nordland(tmp_path / "a", tolerance=2).fingerprint()
    assert wider["reference"] == first["reference"] and wider["query"] == first["query"]
    assert wider["ground_truth"] != first["ground_truth"]
    # a picture written again (a new modification time)
    os.utime(tmp_path / "a" / "winter" / "images-00003.png", (1e9, 1e9))
    touched = load_nordland(tmp_path / "a", tolerance=1).fingerprint()
    assert touched["reference"] == first["reference"]
    assert touched["query"]["files"] != first["query"]["files"]
    assert touched["ground_truth"] == first["ground_truth"]
    # fewer frames
    fewer = load_nordland(tmp_path / "a", tolerance=1, count=5).fingerprint()
    assert fewer["query"]["n_images"] == 5 and fewer["ground_truth"]["shape"] == [5, 5]
    # a file gone since the benchmark was loaded is named
    bench = load_nordland(tmp_path / "b", tolerance=1)
    (tmp_path / "b" / "summer" / "images-00002.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"image file not found: .*images-00002\.png"):
        bench.fingerprint()


# -- registry ------------------------------------------------------------------------------------
def test_registry_names_and_specs():
    assert set(DATASETS) == {"nordland", "robotcar", "vprbench", "generic"}
    for name, spec in DATASETS.items():
        params = inspect.signature(spec.loader).parameters
        assert set(spec.options) <= set(params), name
        assert "root" in spec.options
        assert spec.description and "\n" not in spec.description
        assert "<root>" in spec.layout


def test_load_benchmark_unknown_name_lists_known():
    with pytest.raises(ValueError, match="unknown dataset 'kitti'.*generic, nordland, robotcar"):
        load_benchmark("kitti", root=".")


def test_load_benchmark_unknown_option(tmp_path):
    with pytest.raises(TypeError, match="takes no option.*spacing.*options are: root"):
        load_benchmark("nordland", root=tmp_path, spacing=5)


def test_load_benchmark_dispatches(tmp_path):
    for season in ("summer", "winter"):
        make_season(tmp_path, season, range(1, 6))
    b = load_benchmark("nordland", root=tmp_path, tolerance=1)
    assert b.dataset == "nordland" and b.ground_truth.shape == (5, 5)


# -- Nordland, synthetic -------------------------------------------------------------------------
@pytest.mark.parametrize("pattern", ["images-{:05d}.png", "{}.png"])
def test_nordland_pairs_by_frame_number(tmp_path, pattern):
    numbers = [0, 1, 2, 9, 10, 11, 100]  # natural order differs from text order
    make_season(tmp_path, "summer", numbers, pattern)
    make_season(tmp_path, "winter", numbers[::-1], pattern)
    b = load_nordland(tmp_path, tolerance=1)
    names = [p.name for p in b.reference.paths]
    assert names == [pattern.format(k) for k in numbers]
    assert [p.name for p in b.query.paths] == names
    assert b.reference.bayer is None and b.reference.positions is None
    np.testing.assert_array_equal(b.query.frame_ids, np.arange(7))
    np.testing.assert_array_equal(b.ground_truth, slow_frames_gt(range(7), range(7), 1))
    assert b.protocol()["frame_number_range"] == [0, 100]


def test_nordland_window_uses_positions_not_file_numbers(tmp_path):
    for season in ("summer", "winter"):
        make_season(tmp_path, season, range(10, 110, 10))  # 10 frames numbered 10..100
    b = load_nordland(tmp_path, first=3, count=4, tolerance=0)
    assert [p.name for p in b.reference.paths] == [f"images-{k:05d}.png" for k in (40, 50, 60, 70)]
    np.testing.assert_array_equal(b.reference.frame_ids, [3, 4, 5, 6])
    np.testing.assert_array_equal(b.ground_truth, np.eye(4, dtype=bool))
    assert (b.first, b.count) == (3, 4)


@pytest.mark.parametrize(
    "first, count, match",
    [
        (10, None, r"first=10, count=None \(to the end\) lies beyond the data: .* 10 frames"),
        (8, 3, "first=8, count=3, ending at position 10, lies beyond the data: .* 10 frames"),
        (0, 11, "first=0, count=11, ending at position 10, lies beyond"),
    ],
)
def test_nordland_window_beyond_data(tmp_path, first, count, match):
    for season in ("summer", "winter"):
        make_season(tmp_path, season, range(10))
    with pytest.raises(ValueError, match=match):
        load_nordland(tmp_path, first=first, count=count)


@pytest.mark.parametrize(
    "first, count, err",
    [(-1, None, ValueError), (0, 0, ValueError), (1.5, None, TypeError), (0, "5", TypeError)],
)
def test_nordland_window_types(tmp_path, first, count, err):
    for season in ("summer", "winter"):
        make_season(tmp_path, season, range(3))
    with pytest.raises(err, match="first|count"):
        load_nordland(tmp_path, first=first, count=count)


def test_nordland_mismatched_seasons(tmp_path):
    make_season(tmp_path, "summer", range(10))
    make_season(tmp_path, "winter", [k for k in range(12) if k != 4])
    with pytest.raises(ValueError, match="frame-aligned") as info:
        load_nordland(tmp_path)
    msg = str(info.value)
    assert str(tmp_path / "summer") in msg and str(tmp_path / "winter") in msg
    assert "images-00004.png" in msg and "images-00010.png" in msg


def test_nordland_missing_season_lists_found(tmp_path):
    for season in ("summer", "fall"):
        make_season(tmp_path, season, range(3))
    with pytest.raises(FileNotFoundError, match=r"winter.*seasons found in .*: fall, summer") as e:
        load_nordland(tmp_path)
    assert "images-NNNNN.png" in str(e.value)  # the expected layout


def test_nordland_missing_root(tmp_path):
    with pytest.raises(FileNotFoundError, match="dataset root not found.*expected layout"):
        load_nordland(tmp_path / "nope")


def test_nordland_empty_and_non_image_folders(tmp_path):
    make_season(tmp_path, "summer", range(3))
    (tmp_path / "winter").mkdir()
    with pytest.raises(ValueError, match="no image files.*winter.*expected layout"):
        load_nordland(tmp_path)
    (tmp_path / "winter" / ".notes.txt").write_text("hidden: skipped")
    with pytest.raises(ValueError, match="no image files.*winter"):
        load_nordland(tmp_path)
    (tmp_path / "winter" / "notes.txt").write_text("not an image")
    with pytest.raises(ValueError, match=r"winter/notes.txt: not an image file"):
        load_nordland(tmp_path)


def test_nordland_file_name_without_number(tmp_path):
    make_season(tmp_path, "summer", range(3))
    make_season(tmp_path, "winter", range(3))
    write_png(tmp_path / "winter" / "cover.png")
    with pytest.raises(ValueError, match="cannot read a frame number.*cover.png"):
        load_nordland(tmp_path)


def test_nordland_duplicate_frame_number(tmp_path):
    make_season(tmp_path, "summer", range(3))
    make_season(tmp_path, "winter", range(3))
    write_png(tmp_path / "winter" / "images-2.png")
    with pytest.raises(ValueError, match="frame number 2 appears twice"):
        load_nordland(tmp_path)


def test_nordland_bad_arguments(tmp_path):
    for season in ("summer", "winter"):
        make_season(tmp_path, season, range(3))
    with pytest.raises(ValueError, match="tolerance must be >= 0"):
        load_nordland(tmp_path, tolerance=-1)
    with pytest.raises(TypeError, match="reference must be a season folder name"):
        load_nordland(tmp_path, reference=None)
    with pytest.raises(TypeError, match="root must be a str or Path"):
        load_nordland(None)


def _truncated_png() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (40, 40), np.uint8)).save(buf, "PNG")
    return buf.getvalue()[:200]


@pytest.mark.parametrize("payload", [b"this is not a png", _truncated_png()])
def test_corrupt_image_raises_and_leaves_no_cache(tmp_path, payload):
    data = tmp_path / "data"
    for season in ("summer", "winter"):
        make_season(data, season, range(5))
    bad = data / "winter" / "images-00003.png"
    bad.write_bytes(payload)
    b = load_nordland(data)  # listing does not decode
    cache = tmp_path / "cache"
    b.reference.load_images(size=(4, 8), cache=cache, progress=False)
    n_cached = len(list(cache.iterdir()))
    with pytest.raises(ImageReadError, match="images-00003.png"):
        b.query.load_images(size=(4, 8), cache=cache, progress=False)
    assert len(list(cache.iterdir())) == n_cached == 1  # nothing partial written


# -- Nordland, real data -------------------------------------------------------------------------
def test_nordland_64x32_paper_window(shared_data):
    root = shared_data / "nordland_64x32"
    full = load_nordland(root)
    assert full.n_reference == full.n_query == 2400
    b = load_nordland(root, "summer", "winter", first=0, count=1000, tolerance=20)
    assert b.ground_truth.shape == (1000, 1000)
    i, j = np.indices((1000, 1000))
    np.testing.assert_array_equal(b.ground_truth, np.abs(i - j) <= 20)
    sums = b.ground_truth.sum(axis=1)
    assert (sums[0], sums[500], sums[-1]) == (21, 41, 21)
    assert b.reference.paths[0].name == "images-00010.png"
    assert b.query.paths[-1].name == "images-10000.png"
    assert b.reference.paths[0].parent.name == "summer" and b.query.paths[0].parent.name == "winter"
    p = b.protocol()
    assert (p["first"], p["count"], p["tolerance"]) == (0, 1000, {"frames": 20})
    last = load_nordland(root, first=1400, count=1000)
    assert last.reference.paths[-1].name == "images-24000.png"
    with pytest.raises(ValueError, match="first=1401, count=1000, .* 2400 frames"):
        load_nordland(root, first=1401, count=1000)


@pytest.mark.parametrize("query", ["fall", "winter"])
def test_nordland_flynet_subset100(shared_data, query):
    root = shared_data / "nordland_flynet_subset100"
    b = load_nordland(root, "summer", query, tolerance=2)
    assert b.n_reference == b.n_query == 100
    assert [p.name for p in b.query.paths[:11]] == [f"{k}.png" for k in range(11)]
    assert b.query.paths[0].parent.name == query
    with pytest.raises(FileNotFoundError, match="seasons found in .*: fall, summer, winter"):
        load_nordland(root, "summer", "spring")


def test_nordland_640x360_matches_64x32_copy(shared_data):
    hi = load_nordland(shared_data / "nordland_summer_winter_640x360")
    assert hi.n_reference == hi.n_query == 51
    assert hi.reference.paths[0].name == "images-00900.png"
    assert hi.protocol()["frame_number_range"] == [900, 950]
    lo = load_nordland(shared_data / "nordland_64x32", first=89, count=1)
    assert lo.reference.paths[0].name == "images-00900.png"
    a = hi.reference.subset([0]).load_images(cache=False, progress=False)
    b = lo.reference.load_images(cache=False, progress=False)
    assert a.shape == b.shape == (1, 32, 64)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99
