"""Positions of a recording's frames: a CSV file or a position topic of the same bag.

A CSV has a header naming ``timestamp,x,y`` (seconds, metres) or ``frame,x,y`` (the frame's
index in the recording, before thinning); extra columns are ignored.  A frame gets the position
of its own index, or of the nearest timestamp.
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

    def at(self, indices, timestamps, *, interpolate: bool = False) -> np.ndarray:
        """Positions (n, 2) of frames; NaN where a frame index has no row.

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
        if interpolate:
            return self._interp(t)
        right = np.clip(np.searchsorted(self.keys, t), 1, max(1, len(self.keys) - 1))
        left = right - 1
        if len(self.keys) == 1:
            return np.repeat(self.xy[:1], len(t), axis=0)
        nearer_left = np.abs(t - self.keys[left]) <= np.abs(self.keys[right] - t)
        return self.xy[np.where(nearer_left, left, right)]

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
        keys.append(k)
        xy.append((x, y))
    if not keys:
        raise ValueError(f"positions CSV {path}: no rows")
    if len(set(keys)) != len(keys):
        raise ValueError(f"positions CSV {path}: a {key} appears on more than one row")
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
