"""The records writer of ``flyvpr localize --out`` (flyvpr.cli._records)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from flyvpr.cli._records import CsvRecords, JsonlRecords, csv_cell, open_records, record_format

COLUMNS = ["frame", "timestamp", "place", "confidence", "state"]


def _rows(n):
    return [
        {"frame": i, "timestamp": 0.5 * i, "place": 3 * i, "confidence": 0.25, "state": "lost"}
        for i in range(n)
    ]


def _read(path):
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.parametrize(
    ("name", "kind"),
    [
        ("a.csv", CsvRecords),
        ("a.CSV", CsvRecords),
        ("a.jsonl", JsonlRecords),
        ("a.txt", CsvRecords),
    ],
)
def test_format_follows_the_suffix(name, kind):
    assert record_format(name) is kind


@pytest.mark.parametrize("name", ["where.csv", "where.jsonl"])
def test_records_land_when_the_run_ends_well(tmp_path, name):
    path = tmp_path / name
    with open_records(path, COLUMNS) as out:
        for row in _rows(3):
            out.write(row)
        assert not path.exists()  # written to a temporary file until the end
    assert [int(r["frame"]) for r in _read(path)] == [0, 1, 2]
    assert [p.name for p in tmp_path.iterdir()] == [name]


@pytest.mark.parametrize("name", ["where.csv", "where.jsonl"])
def test_an_interrupted_run_leaves_nothing_by_default(tmp_path, name):
    path = tmp_path / name
    with pytest.raises(KeyboardInterrupt), open_records(path, COLUMNS) as out:
        out.write(_rows(1)[0])
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["where.csv", "where.jsonl"])
@pytest.mark.parametrize("error", [KeyboardInterrupt, ValueError])
def test_keep_partial_keeps_the_records_so_far(tmp_path, name, error):
    path = tmp_path / name
    with pytest.raises(error), open_records(path, COLUMNS, keep_partial=True) as out:
        for row in _rows(2):
            out.write(row)
        raise error
    assert [int(r["frame"]) for r in _read(path)] == [0, 1]
    assert [p.name for p in tmp_path.iterdir()] == [name]


@pytest.mark.parametrize("name", ["where.csv", "where.jsonl"])
def test_flush_writes_each_record_to_the_target_as_it_goes(tmp_path, name):
    path = tmp_path / name
    with pytest.raises(KeyboardInterrupt), open_records(path, COLUMNS, flush=True) as out:
        for n, row in enumerate(_rows(3), start=1):
            out.write(row)
            # another process (tail -f) sees every record written so far, whole
            assert len(_read(path)) == n
        raise KeyboardInterrupt
    assert [int(r["frame"]) for r in _read(path)] == [0, 1, 2]
    assert [p.name for p in tmp_path.iterdir()] == [name]


# -- exact numbers ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "value",
    [1_700_000_000.123456, 1_700_000_000 + 1 / 3, 1e6 + 0.1, -1234567.890123, 0.1, 5e-324, 1e300],
)
def test_floats_read_back_exactly(tmp_path, value):
    path = tmp_path / "where.csv"
    with open_records(path, ["frame", "timestamp"]) as out:
        out.write({"frame": np.int64(3), "timestamp": np.float64(value)})
    (row,) = _read(path)
    assert row == {"frame": "3", "timestamp": repr(value)}
    assert float(row["timestamp"]) == value


@pytest.mark.parametrize(
    ("value", "cell"),
    [(float("nan"), ""), (None, ""), (float("inf"), "inf"), (7, 7), (np.int32(-2), -2)],
)
def test_csv_cells(value, cell):
    got = csv_cell(value)
    assert got == cell and type(got) is type(cell)


def test_jsonl_floats_are_exact_and_nan_is_null(tmp_path):
    path = tmp_path / "where.jsonl"
    with open_records(path, ["timestamp", "x", "frame"]) as out:
        out.write({"timestamp": 1_700_000_000 + 1 / 3, "x": float("nan"), "frame": np.int64(2)})
    assert _read(path) == [{"timestamp": 1_700_000_000 + 1 / 3, "x": None, "frame": 2}]


# -- flyvpr localize --out: epoch stamps and positions 10^6 m from the origin ----------------
#: a drive stamped in Unix time, with sub-microsecond parts, 30 frames per second
EPOCH = 1_700_000_000.123456789
FAR = np.array([1_234_567.891234, 2_345_678.912345])  # metres, e.g. UTM eastings/northings


@pytest.fixture(scope="module")
def epoch_bags(tmp_path_factory):
    pytest.importorskip("rosbags")
    from flyvpr.sources.writers import write_bag
    from flyvpr.synthetic import make_route

    root = tmp_path_factory.mktemp("epoch")
    route = make_route(24, size=(32, 64), conditions=("summer", "winter"), random_state=1)
    xy = FAR + np.c_[np.arange(24) * 2.5 + 0.001, np.arange(24) * 0.3]
    bags = {}
    for version in (1, 2):
        for season in ("summer", "winter"):
            bags[version, season] = write_bag(
                root / f"{season}{'.bag' if version == 1 else ''}",
                route.images[season],
                version=version,
                fps=30.0,
                start=EPOCH,
                positions=xy,
            )
    return bags


def _header_stamps(path) -> list[tuple[int, int]]:
    """(sec, nanosec) of every image message, read with rosbags directly."""
    from rosbags.highlevel import AnyReader

    stamps = []
    with AnyReader([path]) as reader:
        conns = [c for c in reader.connections if c.topic == "/camera/image"]
        for conn, _, raw in reader.messages(connections=conns):
            stamp = reader.deserialize(raw, conn.msgtype).header.stamp
            stamps.append((stamp.sec, stamp.nanosec))
    return stamps


@pytest.mark.parametrize("version", [1, 2])
def test_localize_records_epoch_stamps_and_far_positions_exactly(epoch_bags, tmp_path, version):
    from flyvpr.cli import main
    from flyvpr.maps import Map
    from flyvpr.sources import open_source

    ref, qry = epoch_bags[version, "summer"], epoch_bags[version, "winter"]
    route_map = tmp_path / "route.map"
    assert main(["map", str(ref), "--method", "pixels+cann", "--position-topic", "/odom",
                 "--out", str(route_map), "-q"]) == 0  # fmt: skip
    got = {}
    for suffix in (".csv", ".jsonl"):
        out = tmp_path / f"where{suffix}"
        assert main(["localize", "--map", str(route_map), str(qry), "--out", str(out), "-q"]) == 0
        got[suffix] = _read(out)
    rows = got[".csv"]
    stamps = _header_stamps(qry)
    assert len(rows) == len(stamps) == 24
    # every frame its own time, equal to the header stamp to 1 us ...
    t = np.array([float(r["timestamp"]) for r in rows])
    assert len(set(t)) == 24
    exact = np.array([sec + ns / 1e9 for sec, ns in stamps])
    np.testing.assert_allclose(t, exact, rtol=0, atol=1e-6)
    # ... and the very float the source read, as JSON Lines has it
    source_t = np.concatenate([b.timestamps for b in open_source(qry).batches()])
    assert t.tolist() == source_t.tolist()
    assert t.tolist() == [r["timestamp"] for r in got[".jsonl"]]
    # positions: the matched place's map position, every digit
    m = Map.load(route_map)
    for row, js in zip(rows, got[".jsonl"], strict=True):
        place = int(row["place"])
        assert [float(row["x"]), float(row["y"])] == m.positions[place].tolist()
        assert [js["x"], js["y"]] == m.positions[place].tolist()
        assert float(row["confidence"]) == js["confidence"]
    assert np.abs(m.positions - FAR).max() < 100  # the map kept the far origin


# -- -q/--quiet --------------------------------------------------------------------------------
def _subparsers():
    import argparse

    from flyvpr.cli import build_parser

    (action,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return action.choices


#: the commands that show no progress bar: they only print a listing, a table or a page
NO_PROGRESS = {"datasets", "methods", "demo", "report"}


def test_every_command_with_a_progress_bar_takes_quiet():
    commands = _subparsers()
    quiet = {n for n, p in commands.items() if any("-q" in a.option_strings for a in p._actions)}
    assert quiet == set(commands) - NO_PROGRESS
    assert {"map", "localize", "evaluate", "fit", "experiment"} <= quiet


def test_map_progress_bar_only_when_asked(epoch_bags, capsys):
    from flyvpr.maps import Map

    quiet = Map.build(epoch_bags[1, "summer"], "pixels")
    assert capsys.readouterr().err == ""  # library code never prints unless asked
    shown = Map.build(epoch_bags[1, "summer"], "pixels", progress=True)
    assert "reading frames" in capsys.readouterr().err
    assert shown.timestamps.tolist() == quiet.timestamps.tolist()
    np.testing.assert_array_equal(shown.thumbnails, quiet.thumbnails)


def test_localize_dataset_confidence_is_exact(tmp_path):
    from flyvpr.cli import main
    from flyvpr.synthetic import make_route, save_route

    route = make_route(12, size=(32, 64), random_state=0)
    save_route(route, tmp_path / "png")
    out = tmp_path / "stream.csv"
    assert main(["localize", "--dataset", "generic", "--root", str(tmp_path / "png"),
                 "--reference", route.conditions[0], "--query", route.conditions[1],
                 "--tolerance", "1", "--method", "pixels+cann", "--no-cache", "-q",
                 "--out", str(out)]) == 0  # fmt: skip
    rows = _read(out)
    conf = [r["confidence"] for r in rows]
    assert all(repr(float(c)) == c for c in conf)
    # a six-digit rounding would show no cell with more than six significant digits
    assert any(len(c.lstrip("0.").replace(".", "")) > 6 for c in conf)
