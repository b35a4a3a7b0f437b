"""The scale benchmark's kidnap share interval."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks.scale import wilson_interval  # noqa: E402


@pytest.mark.parametrize(
    ("successes", "trials", "low", "high"),
    [
        # textbook values of the 95% Wilson score interval
        (44, 50, 0.7620, 0.9438),
        (176, 200, 0.8277, 0.9180),
        (5, 10, 0.2366, 0.7634),
        (0, 10, 0.0, 0.2775),
        (10, 10, 0.7225, 1.0),
    ],
)
def test_wilson_interval(successes, trials, low, high):
    lo, hi = wilson_interval(successes, trials)
    assert lo == pytest.approx(low, abs=5e-4)
    assert hi == pytest.approx(high, abs=5e-4)
    assert 0.0 <= lo <= successes / trials <= hi <= 1.0


def test_wilson_interval_narrows_with_more_trials_and_widens_with_z():
    narrow = wilson_interval(180, 200)
    wide = wilson_interval(45, 50)
    assert narrow[1] - narrow[0] < wide[1] - wide[0]
    z99 = wilson_interval(45, 50, z=2.5758)
    assert z99[0] < wide[0] and z99[1] > wide[1]


def test_wilson_interval_refuses_impossible_counts():
    assert wilson_interval(0, 0) is None
    for bad in (-1, 11):
        with pytest.raises(ValueError, match="successes"):
            wilson_interval(bad, 10)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--kidnaps", "-1"], "--kidnaps must be >= 0; got -1"),
        (["--seed", "-3"], "--seed must be >= 0; got -3"),
        (["--bits", "100"], "--bits must be a multiple of 64"),
        (["--seed", "x"], "invalid int value: 'x'"),
    ],
)
def test_bad_arguments_are_refused_before_any_work(args, message, tmp_path, capsys):
    from benchmarks.scale import main

    out = tmp_path / "scale.json"
    with pytest.raises(SystemExit) as exc:
        main(["--places", "1000", "--json", str(out), *args])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()
