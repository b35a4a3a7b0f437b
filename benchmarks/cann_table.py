"""The CANN's default calibration table (``flyvpr.temporal.cann.CALIBRATION``), fitted anew.

Usage::

    python benchmarks/cann_table.py [--data DIR] [--json FILE]

Protocol: ``kenyon+cann`` with ``calibration=None`` (the raw confidence: the support times the
window's probability) on the robot views of the dev window (Nordland 64x32 summer -> winter,
frames 0-999: every view of ``benchmarks/accuracy.py`` on ``n64-0``, with and without
odometry, with and without camera noise; the detour's map given its break), seeds 0-2,
tolerance 2.  Every frame whose answer
comes from the sequence gives the fourth root of its raw confidence (the table is given there:
finest where the lost answers lie) and whether the answer was right;
:func:`flyvpr.temporal.cann.fit_calibration` (prior weight 1) turns them into the 11 values of
the table, which the script prints as the
Python tuple to paste into ``temporal/cann/_filter.py``.  It tunes on the dev window only; the
held-out window's reliability is ``benchmarks/calibration.py``'s.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import DEFAULT_DATA, machine  # noqa: E402
from benchmarks.calibration import _runs, _stream  # noqa: E402
from flyvpr.temporal.cann import CANN, fit_calibration  # noqa: E402
from flyvpr.temporal.cann._filter import CALIBRATION_ROOT  # noqa: E402

DEV = "n64-0"
SEEDS = (0, 1, 2)


def run(data: Path, progress: bool = True) -> dict:
    raw, right = [], []
    for _key, _seed, S, moved, gt, breaks in _runs(data, SEEDS, progress, DEV):
        for conf, ok, from_sequence in _stream(CANN(calibration=None, breaks=breaks), S, moved, gt):
            if from_sequence:
                raw.append(conf ** (1.0 / CALIBRATION_ROOT))  # (where the table is given)
                right.append(ok)
    table = fit_calibration(raw, right)
    return {
        "benchmark": "cann-table",
        "protocol": __doc__.split("Protocol: ")[1].split("\n\n")[0].replace("\n", " "),
        "machine": machine(),
        "answers": len(raw),
        "table": [round(v, 3) for v in table],
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--json", type=Path, help="also write the table and its protocol as JSON")
    args = p.parse_args(argv)
    if not (args.data / "nordland_64x32").is_dir():
        print(f"data folder not found: {args.data / 'nordland_64x32'}", file=sys.stderr)
        return 1
    out = run(args.data, progress=True)
    print(f"fitted on {out['answers']} sequence answers:")
    print("CALIBRATION = (" + ", ".join(f"{v:.3f}" for v in out["table"]) + ")")
    if args.json is not None:
        from flyvpr._io import write_text_atomic

        write_text_atomic(args.json, json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
