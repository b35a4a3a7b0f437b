"""The fault battery (tests/faults/faults.py) as tests: one test per case, each must be OK.

A case whose verdict is "n/a" (its data is missing, or a signal could not be timed to a
write) is skipped with the battery's own explanation.
"""

import importlib.util
import sys
from pathlib import Path

import pytest

BATTERY = Path(__file__).resolve().parent / "faults"


def _load_battery():
    sys.path.insert(0, str(BATTERY))
    spec = importlib.util.spec_from_file_location("faults", BATTERY / "faults.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["faults"] = module
    spec.loader.exec_module(module)
    return module


faults = _load_battery()
CASES = {case.id: case for case in faults.all_cases()}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    base = tmp_path_factory.mktemp("faults")
    shared = base / "_shared"
    shared.mkdir()
    return base, shared


#: groups that take longest (subprocesses, 500-frame routes, real data): also marked slow
SLOW_GROUPS = ("evidence", "signals")


@pytest.mark.parametrize(
    "case_id",
    [
        pytest.param(i, marks=pytest.mark.slow) if c.group in SLOW_GROUPS else i
        for i, c in CASES.items()
    ],
)
def test_fault_case(workdir, case_id):
    base, shared = workdir
    row = faults.run_case(CASES[case_id], base, shared)
    if row["verdict"] == "n/a":
        pytest.skip(row["observed"])
    assert row["verdict"] == "OK", f"expected {row['expected']}; observed {row['observed']}"


def test_render_markdown_from_observations():
    data = {
        "flyvpr_version": "0",
        "python": "3",
        "platform": "p",
        "counts": {"OK": 1, "FAIL": 1, "n/a": 0},
        "cases": [
            {"case": "a", "class": "c", "expected": "e|x", "observed": "o", "verdict": "OK"},
            {"case": "b", "class": "c", "expected": "e", "observed": "o", "verdict": "FAIL"},
        ],
    }
    text = faults.render_markdown(data)
    assert "2 cases: 1 OK, 1 FAIL" in text
    assert "| a | c | e\\|x | o | OK |" in text
