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
    from flyvpr.localization.maps import Map
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
    from flyvpr.localization.maps import Map

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


# -- MCAP ------------------------------------------------------------------------------------
def _mcap(path):
    """(schemas by topic, messages as (topic, log_time, publish_time, decoded JSON)), metadata."""
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        schemas = {}
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            schemas[channel.topic] = (schema.name, json.loads(schema.data))
        messages = [
            (channel.topic, message.log_time, message.publish_time, json.loads(message.data))
            for _, channel, message in reader.iter_messages(log_time_order=False)
        ]
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return schemas, messages, metadata


def test_mcap_records_read_back_exactly(tmp_path):
    pytest.importorskip("mcap")
    path = tmp_path / "where.mcap"
    columns = [*COLUMNS, "x"]
    rows = [
        {"frame": 0, "timestamp": EPOCH, "place": 2, "confidence": 1 / 3, "state": "lost",
         "x": 1e6 + 0.1},
        {"frame": 1, "timestamp": EPOCH + 1 / 30, "place": 3, "confidence": float("nan"),
         "state": "localized", "x": float("nan")},
    ]  # fmt: skip
    with open_records(path, columns, metadata={"map": "route.map"}) as out:
        for row in rows:
            out.write(row, {"query": np.zeros((2, 3), np.uint8)})  # no thumbnails: ignored
    schemas, messages, metadata = _mcap(path)
    name, schema = schemas["/flyvpr/localization"]
    assert list(schemas) == ["/flyvpr/localization"]
    assert name == "flyvpr.Localization"
    assert schema["required"] == ["frame", "place", "state"]  # the others may be unknown
    assert {k: v["type"] for k, v in schema["properties"].items()} == {
        "frame": "integer", "timestamp": "number", "place": "integer", "confidence": "number",
        "state": "string", "x": "number",
    }  # fmt: skip
    # NaN (null in JSON Lines) is left out, as the schema allows
    assert [m[3] for m in messages] == [rows[0], {k: rows[1][k] for k in COLUMNS[:3] + ["state"]}]
    for (_, log_time, publish_time, record), row in zip(messages, rows, strict=True):
        assert log_time == publish_time == round(row["timestamp"] * 1e9)
        assert record["timestamp"] == row["timestamp"]  # the float itself, every digit
    assert metadata == {"flyvpr": {"map": "route.map"}}


def test_mcap_without_timestamps_uses_the_wall_clock(tmp_path):
    pytest.importorskip("mcap")
    import time

    path = tmp_path / "where.mcap"
    before = time.time_ns()
    with open_records(path, ["frame", "timestamp"]) as out:
        out.write({"frame": 0, "timestamp": float("nan")})
    (message,) = _mcap(path)[1]
    assert before <= message[1] <= time.time_ns()
    assert message[3] == {"frame": 0}


def test_mcap_schema_types_other_columns_by_their_first_value(tmp_path):
    pytest.importorskip("mcap")
    path = tmp_path / "where.mcap"
    with open_records(path, ["frame", "latency_ms", "source", "dropped"]) as out:
        out.write({"frame": 0, "latency_ms": 1.5, "source": "cam", "dropped": np.int64(2)})
    schema = _mcap(path)[0]["/flyvpr/localization"][1]
    assert {k: v["type"] for k, v in schema["properties"].items()} == {
        "frame": "integer", "latency_ms": "number", "source": "string", "dropped": "integer"
    }  # fmt: skip


def test_mcap_thumbnails_are_foxglove_compressed_images(tmp_path):
    pytest.importorskip("mcap")
    import base64
    import io

    from PIL import Image

    rng = np.random.default_rng(0)
    query, match = (rng.integers(0, 256, (4, 8), dtype=np.uint8) for _ in range(2))
    path = tmp_path / "where.mcap"
    with open_records(path, ["frame", "timestamp"], thumbnails=True) as out:
        out.write({"frame": 0, "timestamp": 12.5}, {"query": query, "match": match})
    schemas, messages, _ = _mcap(path)
    assert schemas["/flyvpr/query"][0] == schemas["/flyvpr/match"][0] == "foxglove.CompressedImage"
    images = {topic: msg for topic, _, _, msg in messages if topic != "/flyvpr/localization"}
    for topic, expected in (("/flyvpr/query", query), ("/flyvpr/match", match)):
        msg = images[topic]
        assert msg["timestamp"] == {"sec": 12, "nsec": 500_000_000}
        assert msg["format"] == "png" and msg["frame_id"] == topic.rsplit("/", 1)[1]
        png = Image.open(io.BytesIO(base64.b64decode(msg["data"])))
        np.testing.assert_array_equal(np.asarray(png), expected)
    assert {m[1] for m in messages} == {12_500_000_000}


@pytest.mark.parametrize("name", ["where.csv", "where.jsonl"])
def test_thumbnails_need_mcap(tmp_path, name):
    with pytest.raises(ValueError, match=rf"{name}: a \.\w+ records file holds no thumbnails"):
        with open_records(tmp_path / name, COLUMNS, thumbnails=True):
            pass
    assert list(tmp_path.iterdir()) == []


def test_mcap_interrupted_leaves_nothing_or_keeps_a_valid_file(tmp_path):
    pytest.importorskip("mcap")
    path = tmp_path / "where.mcap"
    with pytest.raises(KeyboardInterrupt), open_records(path, COLUMNS) as out:
        out.write(_rows(1)[0])
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []
    for mode in ({"keep_partial": True}, {"flush": True}):
        with pytest.raises(RuntimeError), open_records(path, COLUMNS, **mode) as out:
            for row in _rows(3):
                out.write(row)
            raise RuntimeError("the stream went away")
        assert [m[3]["frame"] for m in _mcap(path)[1]] == [0, 1, 2]
        assert [p.name for p in tmp_path.iterdir()] == ["where.mcap"]


def test_mcap_flush_puts_each_message_on_disk(tmp_path):
    pytest.importorskip("mcap")
    path = tmp_path / "where.mcap"
    sizes = []
    with open_records(path, COLUMNS, flush=True) as out:
        for row in _rows(3):
            out.write(row)
            sizes.append(path.stat().st_size)
    assert sizes[0] < sizes[1] < sizes[2] < path.stat().st_size
    assert len(_mcap(path)[1]) == 3


@pytest.mark.parametrize("version", [1, 2])
def test_localize_mcap_matches_jsonl_record_for_record(epoch_bags, tmp_path, version):
    pytest.importorskip("mcap")
    import base64
    import io

    from PIL import Image

    from flyvpr.cli import main
    from flyvpr.localization.maps import Map

    ref, qry = epoch_bags[version, "summer"], epoch_bags[version, "winter"]
    route_map = tmp_path / "route.map"
    assert main(["map", str(ref), "--position-topic", "/odom", "--out", str(route_map),
                 "-q"]) == 0  # fmt: skip
    for name, extra in (("where.jsonl", []), ("where.mcap", ["--mcap-thumbnails"])):
        assert main(["localize", "--map", str(route_map), str(qry), "--out",
                     str(tmp_path / name), "-q", *extra]) == 0  # fmt: skip
    expected = _read(tmp_path / "where.jsonl")
    schemas, messages, metadata = _mcap(tmp_path / "where.mcap")
    records = [m for m in messages if m[0] == "/flyvpr/localization"]
    assert [m[3] for m in records] == expected  # place, confidence, state, stamps: exact
    assert [m[1] for m in records] == [round(r["timestamp"] * 1e9) for r in expected]
    assert list(schemas["/flyvpr/localization"][1]["properties"]) == list(expected[0])
    assert metadata["flyvpr"]["map"] == str(route_map)
    assert metadata["flyvpr"]["method"] == Map.load(route_map).method.name
    m = Map.load(route_map)
    matches = [msg for topic, _, _, msg in messages if topic == "/flyvpr/match"]
    queries = [msg for topic, _, _, msg in messages if topic == "/flyvpr/query"]
    assert len(matches) == len(queries) == len(expected)
    for record, match, query in zip(expected, matches, queries, strict=True):
        png = np.asarray(Image.open(io.BytesIO(base64.b64decode(match["data"]))))
        np.testing.assert_array_equal(png, m.thumbnails[record["place"]])
        assert (
            np.asarray(Image.open(io.BytesIO(base64.b64decode(query["data"])))).shape
            == (m.thumbnails.shape[1:])
        )


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--out", "{tmp}/w.csv", "--mcap-thumbnails"], "--mcap-thumbnails needs --out FILE.mcap"),
        (["--mcap-thumbnails"], "--mcap-thumbnails needs --out FILE.mcap"),
    ],
)
def test_localize_mcap_usage_errors(epoch_bags, tmp_path, capsys, argv, message):
    from flyvpr.cli import main

    route_map = tmp_path / "route.map"
    assert main(["map", str(epoch_bags[1, "summer"]), "--out", str(route_map), "-q"]) == 0
    argv = [a.format(tmp=tmp_path) for a in argv]
    assert main(["localize", "--map", str(route_map), str(epoch_bags[1, "winter"]), *argv]) == 2
    assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["route.map"]


@pytest.mark.parametrize("name", ["s.mcap", "s.jsonl"])
def test_localize_dataset_refuses_mcap_and_jsonl(tmp_path, capsys, name):
    from flyvpr.cli import main

    code = main(["localize", "--dataset", "generic", "--root", str(tmp_path), "--reference", "a",
                 "--query", "b", "--out", str(tmp_path / name)])  # fmt: skip
    assert code == 2
    assert f"--out {tmp_path / name}: with --dataset the records are CSV" in capsys.readouterr().err


def test_mcap_without_its_package_names_the_extra(tmp_path, monkeypatch):
    import sys

    for name in ("mcap", "mcap.writer"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(ImportError, match=r"pip install 'flyvpr\[recordings\]'"):
        with open_records(tmp_path / "where.mcap", COLUMNS, flush=True):
            pass
    assert list(tmp_path.iterdir()) == []
