"""Tests of the generic two-folder loader."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flyvpr.datasets import load_benchmark, load_generic


def make_folder(path: Path, n: int, suffix=".png") -> list[Path]:
    path.mkdir(parents=True)
    out = []
    for i in range(n):
        out.append(path / f"frame{i}{suffix}")
        Image.fromarray(np.full((4, 4), 10 * i, np.uint8)).save(out[-1])
    return out


def write_csv(path: Path, rows, header="traverse,filename,x,y"):
    path.write_text(header + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows))
    return path


@pytest.fixture
def folders(tmp_path):
    make_folder(tmp_path / "day", 12)  # natural sort: frame2 before frame10
    make_folder(tmp_path / "night", 7)
    return tmp_path


def test_generic_index_matching_non_square(folders):
    b = load_generic(folders, "day", "night", tolerance=2)
    assert b.ground_truth.shape == (7, 12)
    i, j = np.indices((7, 12))
    np.testing.assert_array_equal(b.ground_truth, np.abs(i - j) <= 2)
    assert [p.name for p in b.reference.paths[:3]] == ["frame0.png", "frame1.png", "frame2.png"]
    assert b.reference.paths[-1].name == "frame11.png"
    assert (b.reference.name, b.query.name) == ("day", "night")
    assert b.protocol()["tolerance"] == {"frames": 2}


def test_generic_default_tolerance_and_absolute_paths(folders):
    b = load_benchmark("generic", reference=folders / "day", query=folders / "night")
    np.testing.assert_array_equal(b.ground_truth, np.eye(7, 12, dtype=bool))
    assert b.tolerance == {"frames": 0} and b.root is None


def test_generic_window(folders):
    b = load_generic(folders, "day", "night", tolerance=1, first=2, count=4)
    assert b.n_reference == b.n_query == 4
    np.testing.assert_array_equal(b.reference.frame_ids, [2, 3, 4, 5])
    i, j = np.indices((4, 4))
    np.testing.assert_array_equal(b.ground_truth, np.abs(i - j) <= 1)
    with pytest.raises(
        ValueError, match="first=5, count=4, ending at position 8, lies beyond the data: .*night: 7"
    ):
        load_generic(folders, "day", "night", first=5, count=4)


def test_generic_positions_csv(folders):
    rows = [("reference", f"frame{i}.png", 10.0 * i, 0.0) for i in range(12)]
    rows += [("query", f"frame{i}.png", 10.0 * i + 3.0, 4.0) for i in range(7)]  # 5 m off
    write_csv(folders / "poses.csv", rows[::-1])  # row order does not matter
    b = load_generic(folders, "day", "night", positions_csv="poses.csv", radius=5.0)
    assert b.tolerance == {"metres": 5.0}
    np.testing.assert_allclose(b.reference.positions[:, 0], 10.0 * np.arange(12))
    np.testing.assert_array_equal(b.ground_truth, np.eye(7, 12, dtype=bool))
    wide = load_generic(folders, "day", "night", positions_csv="poses.csv", radius=10.0)
    assert wide.ground_truth.sum() == 14  # (3, 4) -> 5 m and (7, 4) -> 8.06 m away


@pytest.mark.parametrize(
    "header, rows, match",
    [
        ("traverse,filename,x", [], r"missing column\(s\) y"),
        (
            "traverse,filename,x,y,x",
            [("query", "frame0.png", 0, 0, 1)],
            r"p.csv: column 'x' appears 2 times in the header \(columns 3, 5\)",
        ),
        (None, [("ref", "frame0.png", 0, 0)], "line 2: traverse must be 'reference' or 'query'"),
        (None, [("reference", "nope.png", 0, 0)], "line 2: reference folder holds no image named"),
        (None, [("query", "frame0.png", "a", 0)], "line 2: x and y must be numbers"),
        (None, [("query", "frame0.png", "nan", 0)], "line 2: x and y must be finite"),
        (
            None,
            [("query", "frame0.png", 0, 0), ("query", "frame0.png", 1, 1)],
            "line 3: query image 'frame0.png' has a second row",
        ),
        (None, [("query", "frame0.png", 0)], "line 2: expected 4 fields"),
        (
            None,
            [("reference", "frame0.png", 0, 0)],
            r"11 reference image\(s\) have no row, the first being .*frame1.png",
        ),
    ],
)
def test_generic_csv_errors(tmp_path, header, rows, match):
    make_folder(tmp_path / "ref", 12)
    make_folder(tmp_path / "qry", 2)
    write_csv(tmp_path / "p.csv", rows, header or "traverse,filename,x,y")
    with pytest.raises(ValueError, match=match):
        load_generic(tmp_path, "ref", "qry", positions_csv="p.csv", radius=5.0)


@pytest.mark.parametrize(
    "kwargs, err, match",
    [
        ({"radius": 5.0}, ValueError, "radius needs positions_csv"),
        ({"positions_csv": "p.csv"}, ValueError, "radius .* is required with positions_csv"),
        ({"positions_csv": "p.csv", "radius": 5, "tolerance": 2}, ValueError, "not both"),
        (
            {"positions_csv": "missing.csv", "radius": 5},
            FileNotFoundError,
            "positions CSV not found",
        ),
        ({"tolerance": -1}, ValueError, "tolerance must be >= 0"),
        ({"reference": 3}, TypeError, "reference must be a folder path"),
    ],
)
def test_generic_argument_errors(folders, kwargs, err, match):
    args = {"root": folders, "reference": "day", "query": "night", **kwargs}
    with pytest.raises(err, match=match):
        load_generic(**args)


def test_generic_folder_errors(tmp_path):
    make_folder(tmp_path / "ref", 3)
    with pytest.raises(FileNotFoundError, match=r"image folder not found: .*qry.*expected layout"):
        load_generic(tmp_path, "ref", "qry")
    (tmp_path / "qry").mkdir()
    (tmp_path / "qry" / ".readme.md").write_text("hidden: skipped")
    with pytest.raises(ValueError, match="no image files .*qry"):
        load_generic(tmp_path, "ref", "qry")
    with pytest.raises(NotADirectoryError, match="expected a folder of images"):
        load_generic(tmp_path, "ref", "qry/.readme.md")


def test_traverses_of_another_aspect_ratio_are_named_in_a_warning(tmp_path, caplog):
    for name, shape in (("wide", (36, 64)), ("square", (48, 48)), ("small", (18, 32))):
        (tmp_path / name).mkdir()
        for i in range(3):
            Image.fromarray(np.full(shape, 40 * i, np.uint8)).save(tmp_path / name / f"f{i}.png")
    with caplog.at_level("WARNING", logger="flyvpr"):
        ref, qry = load_generic(tmp_path, "wide", "square").load_images((32, 64), cache=False)
    assert ref.shape == qry.shape == (3, 32, 64)
    (record,) = [r for r in caplog.records if "aspect ratio" in r.getMessage()]
    msg = record.getMessage()
    assert f"reference's frames ({tmp_path / 'wide' / 'f0.png'}: 64x36)" in msg
    assert f"the query's ({tmp_path / 'square' / 'f0.png'}: 48x48)" in msg
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):  # another size, the same shape: fine
        load_generic(tmp_path, "wide", "small").load_images((32, 64), cache=False)
    assert not [r for r in caplog.records if "aspect ratio" in r.getMessage()]
