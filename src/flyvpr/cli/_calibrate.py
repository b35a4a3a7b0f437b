"""``flyvpr localize --map``'s confidence tables: ``--fit-calibration`` writes one fitted on a
run scored with ``--ground-truth``; ``--calibration`` maps every frame's confidence through one.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._io import write_json_atomic
from ..temporal.cann._calibration import KNOTS as _TABLE_KNOTS
from ._common import UsageError

#: what a table file says it is
FORMAT = "flyvpr-confidence-table"
#: confidences at which a table is given
KNOTS = [round(float(k), 6) for k in _TABLE_KNOTS]
#: the largest table file read (one written by --fit-calibration is about 1.5 kB)
_MAX_BYTES = 1 << 20


def _recalibration_param(loc, option: str):
    """The map's filter, which must take ``recalibration`` (the CANN)."""
    filt = loc.method.filter
    if filt is None or "recalibration" not in filt.get_params():
        raise UsageError(
            f"{option}: the map's method ({loc.map_.method.name}) has no CANN filter, whose "
            "confidence a table maps"
        )
    return filt


def check_calibration_args(args) -> None:
    """Before any work: the two options' combinations."""
    if args.fit_calibration is not None and args.ground_truth is None:
        raise UsageError("--fit-calibration needs --ground-truth (whether each answer was right)")
    if args.fit_calibration is not None and args.calibration is not None:
        raise UsageError(
            "--fit-calibration with --calibration: fit on the run as the map's filter answers "
            "(drop --calibration); the fitted table replaces, not adds to, a given one"
        )


def read_table(path: Path) -> list[float]:
    """The table of a file written by ``--fit-calibration``."""
    try:
        size = Path(path).stat().st_size
        if size > _MAX_BYTES:
            raise ValueError(
                f"--calibration {path}: {size} bytes; a confidence table file is a few "
                f"kilobytes (at most {_MAX_BYTES} read)"
            )
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"--calibration {path}: no such file") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--calibration {path}: not a JSON file ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or "table" not in data:
        raise ValueError(
            f"--calibration {path}: not a confidence table (expected the JSON that "
            f'--fit-calibration writes, with "format": "{FORMAT}" and a "table")'
        )
    table = data["table"]
    if not (
        isinstance(table, list)
        and len(table) == len(KNOTS)
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in table)
    ):
        raise ValueError(
            f'--calibration {path}: "table" must hold {len(KNOTS)} numbers (at confidence '
            f"0, 0.1, ..., 1); got {table!r}"
        )
    return [float(v) for v in table]


def apply_table(loc, path: Path) -> None:
    """Give the map's filter the table of ``path`` as its ``recalibration``."""
    filt = _recalibration_param(loc, "--calibration")
    table = read_table(path)
    before = filt.get_params()["recalibration"]
    filt.set_params(recalibration=table)
    try:
        loc.reset()  # the filter checks its parameters here
    except (ValueError, TypeError) as exc:
        filt.set_params(recalibration=before)
        raise ValueError(f"--calibration {path}: {exc}") from None


def _largest_gap(rows: list[dict]) -> float:
    return max(abs(r["right"] - r["confidence"]) for r in rows)


def fit_and_write(path: Path, confidence: np.ndarray, right: np.ndarray, fitted_on: dict) -> str:
    """Fit a table on the run's confidences and rightness, write it to ``path`` (atomically)
    and return the summary's line."""
    from ..metrics import reliability
    from ..temporal.cann import fit_calibration

    conf = np.asarray(confidence, dtype=np.float64)
    ok = np.asarray(right, dtype=bool)
    if conf.size == 0:
        raise ValueError("--fit-calibration: the run has no frame to fit on")
    table = fit_calibration(conf, ok)
    after = np.interp(conf, KNOTS, table)
    rows_before, rows_after = reliability(conf, ok), reliability(after, ok)
    write_json_atomic(
        path,
        {
            "format": FORMAT,
            "knots": KNOTS,
            "table": list(table),
            "fitted_on": {**fitted_on, "frames": int(conf.size), "right": int(ok.sum())},
            "reliability": {"before": rows_before, "after": rows_after},
        },
    )
    return (
        f"confidence table fitted on {conf.size} frames ({int(ok.sum())} right): largest gap of "
        f"a decile between confidence and share right {_largest_gap(rows_before):.3f} as the "
        f"filter answered, {_largest_gap(rows_after):.3f} through the table (on this run; give "
        f"--calibration {path} to later runs of this route)"
    )
