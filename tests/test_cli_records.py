"""The records writer of ``flyvpr localize --out`` (flyvpr.cli._records)."""

from __future__ import annotations

import csv
import json

import pytest

from flyvpr.cli._records import CsvRecords, JsonlRecords, open_records, record_format

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
