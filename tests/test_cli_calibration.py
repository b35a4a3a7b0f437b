"""``flyvpr localize --map``: ``--fit-calibration`` and ``--calibration`` (a route's own
confidence table)."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from flyvpr.cli import main
from flyvpr.cli._calibrate import FORMAT, KNOTS, read_table
from flyvpr.metrics import reliability
from flyvpr.synthetic import make_route, save_route
from flyvpr.temporal.cann import fit_calibration

N = 60
TOL = 1


@pytest.fixture(scope="module")
def route(tmp_path_factory):
    """A map of a synthetic route (summer, kenyon+cann) and its night traverse as PNGs."""
    root = tmp_path_factory.mktemp("calroute")
    r = make_route(N, size=(32, 64), conditions=("summer", "night"), random_state=3)
    save_route(r, root / "png")
    code = main(["map", str(root / "png" / "summer"), "--out", str(root / "r.map"), "--quiet"])
    assert code == 0
    return root / "r.map", root / "png" / "night"


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _records(path):
    return list(csv.DictReader(path.open()))


def test_fit_then_apply(route, tmp_path, capsys):
    m, query = route
    table_path = tmp_path / "table.json"
    code, out, err = _run(
        capsys, "localize", "--map", m, query, "--ground-truth", "frames", "--tolerance", TOL,
        "--out", tmp_path / "a.csv", "--fit-calibration", table_path,
    )  # fmt: skip
    assert code == 0, err
    data = json.loads(table_path.read_text())
    assert data["format"] == FORMAT and data["knots"] == KNOTS
    rows = _records(tmp_path / "a.csv")
    conf = np.array([float(r["confidence"]) for r in rows])
    right = np.array([r["correct"] == "1" for r in rows])
    # the table is the library's fit on the run's own confidences and rightness
    assert data["table"] == pytest.approx(list(fit_calibration(conf, right)), abs=1e-12)
    assert data["fitted_on"]["frames"] == N and data["fitted_on"]["right"] == int(right.sum())
    assert data["fitted_on"]["ground_truth"] == f"frames within {TOL}"
    assert data["reliability"]["before"] == reliability(conf, right)
    match = re.search(r"confidence table fitted on 60 frames \((\d+) right\)", out)
    assert match and int(match.group(1)) == int(right.sum())
    assert f"wrote {table_path}" in out

    # applied: every confidence through the table; places, states and correctness unchanged
    code, out, err = _run(
        capsys, "localize", "--map", m, query, "--ground-truth", "frames", "--tolerance", TOL,
        "--out", tmp_path / "b.csv", "--calibration", table_path,
    )  # fmt: skip
    assert code == 0, err
    assert f"confidence through the table of --calibration {table_path}" in out
    again = _records(tmp_path / "b.csv")
    for a, b in zip(rows, again, strict=True):
        assert (a["place"], a["state"], a["correct"]) == (b["place"], b["state"], b["correct"])
        expected = np.interp(float(a["confidence"]), KNOTS, data["table"])
        assert float(b["confidence"]) == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_a_table_that_moves_confidences(route, tmp_path, capsys):
    # a hand-made table halves every confidence: the records say so
    m, query = route
    table = [0.5 * k + 0.001 * i for i, k in enumerate(KNOTS)]
    path = tmp_path / "half.json"
    path.write_text(json.dumps({"format": FORMAT, "table": table}))
    assert read_table(path) == table
    code, _, err = _run(capsys, "localize", "--map", m, query, "--out", tmp_path / "p.csv")
    assert code == 0, err
    code, _, err = _run(
        capsys, "localize", "--map", m, query, "--out", tmp_path / "h.csv", "--calibration", path
    )
    assert code == 0, err
    plain = [float(r["confidence"]) for r in _records(tmp_path / "p.csv")]
    halved = [float(r["confidence"]) for r in _records(tmp_path / "h.csv")]
    np.testing.assert_allclose(halved, np.interp(plain, KNOTS, table), rtol=1e-5, atol=1e-6)
    assert max(halved) < 0.52


def _table_file(tmp_path, content, name="t.json"):
    path = tmp_path / name
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "not a JSON file"),
        ({"table": [0.0] * 11}, "not a confidence table"),
        ([0.1] * 11, "not a confidence table"),
        ({"format": FORMAT, "table": [0.1, 0.2]}, '"table" must hold 11 numbers'),
        ({"format": FORMAT, "table": ["a"] * 11}, '"table" must hold 11 numbers'),
        ({"format": FORMAT, "table": [True] * 11}, '"table" must hold 11 numbers'),
        ({"format": FORMAT, "table": [0.5] * 11}, "recalibration must increase strictly"),
        ({"format": FORMAT, "table": [0.1 * i + 0.2 for i in range(11)]}, r"lie in \[0, 1\]"),
    ],
)
def test_bad_tables_are_refused_naming_the_file(route, tmp_path, capsys, content, message):
    m, query = route
    path = _table_file(tmp_path, content)
    out_path = tmp_path / "x.csv"
    code, _, err = _run(
        capsys, "localize", "--map", m, query, "--out", out_path, "--calibration", path
    )
    assert code == 1
    assert f"--calibration {path}" in err and re.search(message, err), err
    assert not out_path.exists()


def test_a_huge_table_file_is_not_read(route, tmp_path, capsys):
    m, query = route
    path = tmp_path / "huge.json"
    path.write_text('{"format": "' + FORMAT + '", "table": [' + "0.5, " * 300000 + "1]}")
    code, _, err = _run(capsys, "localize", "--map", m, query, "--calibration", path)
    assert code == 1 and f"--calibration {path}: " in err and "bytes; a confidence table" in err


def test_a_missing_table_file(route, tmp_path, capsys):
    m, query = route
    code, _, err = _run(
        capsys, "localize", "--map", m, query, "--calibration", tmp_path / "none.json"
    )
    assert code == 1 and "no such file" in err and "none.json" in err


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--fit-calibration", "T"], "--fit-calibration needs --ground-truth"),
        (
            ["--ground-truth", "frames", "--tolerance", "1", "--fit-calibration", "T",
             "--calibration", "C"],
            "--fit-calibration with --calibration",
        ),
        (["--out", "SAME", "--fit-calibration", "SAME", "--ground-truth", "frames",
          "--tolerance", "1"], "already an output of this run"),
    ],
)  # fmt: skip
def test_usage_errors(route, tmp_path, capsys, extra, message):
    m, query = route
    argv = [str(tmp_path / "x.csv") if a == "SAME" else a for a in extra]
    argv = [str(tmp_path / "t.json") if a == "T" else a for a in argv]
    argv = [str(_table_file(tmp_path, {}, "c.json")) if a == "C" else a for a in argv]
    code, _, err = _run(capsys, "localize", "--map", m, query, *argv)
    assert code == 2 and message in err, err
    assert not (tmp_path / "t.json").exists()


def test_options_need_a_map(tmp_path, capsys):
    for option in ("--calibration", "--fit-calibration"):
        code, _, err = _run(
            capsys, "localize", "--dataset", "generic", "--root", tmp_path, "--reference", "a",
            "--query", "b", option, tmp_path / "t.json",
        )  # fmt: skip
        assert code == 2 and f"{option} needs --map MAP SOURCE" in err


def test_a_map_without_the_cann(tmp_path, capsys):
    r = make_route(20, size=(32, 64), conditions=("summer", "night"), random_state=1)
    save_route(r, tmp_path / "png")
    m = tmp_path / "p.map"
    assert main(["map", str(tmp_path / "png" / "summer"), "--method", "pixels", "--out", str(m),
                 "--quiet"]) == 0  # fmt: skip
    path = _table_file(tmp_path, {"format": FORMAT, "table": KNOTS})
    code, _, err = _run(
        capsys, "localize", "--map", m, tmp_path / "png" / "night", "--calibration", path
    )
    assert code == 2 and "has no CANN filter" in err
