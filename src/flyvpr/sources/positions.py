"""Positions of a recording's frames: a CSV file or a position topic of the same bag.

A CSV has a header naming ``timestamp,x,y`` (seconds, metres) or ``frame,x,y`` (the frame's
index in the recording, before thinning); extra columns are ignored.  A frame gets the position
of its own index, or of the nearest timestamp within the rows' time span (widened at either end
by half the median interval between rows); a frame outside it has none, as a frame index
without a row has none.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from ..datasets.base import _read_csv_text
from .base import RecordingError

__all__ = ["Positions", "read_positions"]


class Positions:
    """Positions (metres) looked up by frame index or by nearest timestamp.

    Parameters
    ----------
    keys : ndarray, shape (n,)
        Frame indices (``by='frame'``) or timestamps in seconds (``by='timestamp'``).
    xy : ndarray, shape (n, 2)
    by : {'frame', 'timestamp'}
    origin : str
        Where they came from (for messages and the map file).
    """

    def __init__(self, keys, xy, by: str, origin: str):
        order = np.argsort(keys, kind="stable")
        self.keys = np.asarray(keys, np.float64)[order]
        self.xy = np.asarray(xy, np.float64).reshape(-1, 2)[order]
        self.by = by
        self.origin = origin

    def span(self) -> tuple[float, float]:
        """The keys a frame's own may take to get a position: from the first row's to the
        last's; for timestamps, widened at either end by half the median interval between
        rows (a frame a little before the first fix or after the last one still gets it)."""
        first, last = float(self.keys[0]), float(self.keys[-1])
        if self.by == "timestamp" and len(self.keys) > 1:
            margin = 0.5 * float(np.median(np.diff(self.keys)))
            return first - margin, last + margin
        return first, last

    def at(self, indices, timestamps, *, interpolate: bool = False) -> np.ndarray:
        """Positions (n, 2) of frames; NaN where a frame index has no row, or a timestamp lies
        outside :meth:`span` (a recording that goes on before or after its positions).

        With ``interpolate``, a frame between two rows gets the straight-line blend of their
        positions instead of the nearer one (or, keyed by frame, NaN), so that distances
        between consecutive frames follow the motion when positions are sparser than frames
        (odometry); outside the rows' range it is as without.
        """
        if self.by == "frame":
            q = np.asarray(indices, np.float64)
            pos = np.clip(np.searchsorted(self.keys, q), 0, len(self.keys) - 1)
            out = self.xy[pos].copy()
            out[self.keys[pos] != q] = np.nan
            if interpolate:
                inside = (q >= self.keys[0]) & (q <= self.keys[-1])
                out[inside] = self._interp(q[inside])
            return out
        t = np.asarray(timestamps, np.float64)
        if not np.isfinite(t).all():
            raise RecordingError(
                f"positions {self.origin} are keyed by timestamp, but the recording's frames "
                "have no timestamps: use a frame,x,y CSV"
            )
        lo, hi = self.span()
        if interpolate:
            out = self._interp(t)
        elif len(self.keys) == 1:
            out = np.repeat(self.xy[:1], len(t), axis=0)
        else:
            right = np.clip(np.searchsorted(self.keys, t), 1, len(self.keys) - 1)
            left = right - 1
            nearer_left = np.abs(t - self.keys[left]) <= np.abs(self.keys[right] - t)
            out = self.xy[np.where(nearer_left, left, right)]
        out[(t < lo) | (t > hi)] = np.nan
        return out

    def describe_span(self) -> str:
        """The rows' keys in words, for messages: ``timestamps 10-42.5 s`` or ``frames 0-99``."""
        if self.by == "timestamp":
            return f"timestamps {self.keys[0]:.10g}-{self.keys[-1]:.10g} s"
        return f"frames {int(self.keys[0])}-{int(self.keys[-1])}"

    def check_covers(self, xy, indices, timestamps, where: str) -> None:
        """Raise :class:`RecordingError` when none of a recording's frames (``indices``,
        ``timestamps``; their positions ``xy``, NaN rows for none) got a position: a file of
        another recording, or timestamps on another clock.  ``where``: the recording."""
        xy = np.asarray(xy, np.float64)
        if not len(xy) or np.isfinite(xy).all(axis=1).any():
            return
        if self.by == "timestamp":
            t = np.asarray(timestamps, np.float64)
            frames = f"its frames' timestamps {np.nanmin(t):.10g}-{np.nanmax(t):.10g} s"
            hint = "the positions and the recording must share a clock"
        else:
            i = np.asarray(indices)
            frames = f"its frames {int(i.min())}-{int(i.max())}"
            hint = "a frame,x,y row names a frame's index in the recording"
        raise RecordingError(
            f"{where}: no frame has a position in {self.origin} (its rows: "
            f"{self.describe_span()}; {frames}): {hint}"
        )

    def _interp(self, q: np.ndarray) -> np.ndarray:
        """Linear interpolation between rows (the first/last row's position beyond them)."""
        return np.c_[np.interp(q, self.keys, self.xy[:, 0]), np.interp(q, self.keys, self.xy[:, 1])]


def _read_csv(path: Path) -> Positions:
    text = _read_csv_text(path, "positions CSV")
    rows = csv.DictReader(io.StringIO(text))
    header = [h.strip().lower() for h in (rows.fieldnames or [])]
    rows.fieldnames = header
    key = "frame" if "frame" in header else "timestamp" if "timestamp" in header else None
    if key is None or "x" not in header or "y" not in header:
        raise ValueError(
            f"positions CSV {path}: the header must name timestamp,x,y or frame,x,y; got "
            f"{','.join(header) or 'nothing'}"
        )
    keys, xy = [], []
    first_line: dict[float, int] = {}
    for line, row in enumerate(rows, start=2):
        try:
            k, x, y = float(row[key]), float(row["x"]), float(row["y"])
        except (TypeError, ValueError):
            raise ValueError(
                f"positions CSV {path}, line {line}: {key}, x and y must be numbers; got "
                f"{row.get(key)!r}, {row.get('x')!r}, {row.get('y')!r}"
            ) from None
        if not all(math.isfinite(v) for v in (k, x, y)):
            raise ValueError(f"positions CSV {path}, line {line}: not a finite {key},x,y")
        if key == "frame" and (k != int(k) or k < 0):
            raise ValueError(
                f"positions CSV {path}, line {line}: frame must be a whole number >= 0 (the "
                f"frame's index in the recording); got {row[key].strip()}"
            )
        if k in first_line:
            raise ValueError(
                f"positions CSV {path}, line {line}: {key} {row[key].strip()} is on line "
                f"{first_line[k]} too (one row per {key})"
            )
        first_line[k] = line
        keys.append(k)
        xy.append((x, y))
    if not keys:
        raise ValueError(f"positions CSV {path}: no rows")
    return Positions(np.array(keys), np.array(xy), key, str(path))


def read_positions(csv_path=None, *, bag=None, topic: str | None = None) -> Positions | None:
    """Positions from a CSV file, or from ``topic`` of ``bag``; None when neither is given."""
    if csv_path is not None and topic is not None:
        raise ValueError("give positions as a CSV or as a bag topic, not both")
    if csv_path is not None:
        return _read_csv(Path(csv_path))
    if topic is None:
        return None
    if bag is None:
        raise ValueError(f"position_topic={topic}: the recording is not a ROS bag")
    from .rosbag import read_bag_positions

    t, xy = read_bag_positions(bag, topic)
    return Positions(t, xy, "timestamp", f"bag {bag} topic {topic}")
