"""Positions of a recording's frames: a CSV file or a position topic of the same bag.

A CSV has a header naming ``timestamp,x,y`` (seconds, metres) or ``frame,x,y`` (the frame's
index in the recording, before thinning); extra columns are ignored.  A frame gets the position
of its own index, or of the nearest timestamp within the rows' time span (widened at either end
by half the median interval between rows); a frame outside it has none, as a frame index
without a row has none.  Interpolated (``at(..., interpolate=True)``, what maps, ``every='2m'``
and odometry use), a frame between two rows gets its point on the straight line between
them (by timestamp, or by index for rows keyed by frame).

A frame inside a *gap*, two neighbouring rows further apart than ``GAP_INTERVALS`` (3) times
the median interval between rows and, for timestamps, than ``GAP_MIN_SECONDS`` (1 s), has no
position either way: a position topic that stopped for a while says nothing about where the
robot went meanwhile, and neither the row next to it nor a straight line across is a place
to store or a distance to drive.  As at the ends of the rows, a frame within half the median
interval of the row at either side of a gap gets that row's position.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

import numpy as np

from ..datasets.base import _check_unique_columns, _read_csv_text
from .base import RecordingError

__all__ = ["Positions", "read_positions"]

#: two neighbouring rows further apart than this many median intervals between rows ...
GAP_INTERVALS = 3.0
#: ... and, keyed by timestamp, further apart than this many seconds leave a gap between them
#: (a fix lost now and then, or a topic delayed by a busy recorder, is not one)
GAP_MIN_SECONDS = 1.0


class Positions:
    """Positions (metres) looked up by frame index or by timestamp.

    Parameters
    ----------
    keys : ndarray, shape (n,)
        Frame indices (``by='frame'``) or timestamps in seconds (``by='timestamp'``).
    xy : ndarray, shape (n, 2)
    by : {'frame', 'timestamp'}
    origin : str
        Where they came from (for messages and the map file).

    Attributes
    ----------
    interval : float
        The median interval between neighbouring rows (0 for a single row).
    gaps : ndarray, shape (n_gaps, 2)
        The keys of the two rows on either side of each gap (see the module's docstring).
    """

    def __init__(self, keys, xy, by: str, origin: str):
        order = np.argsort(keys, kind="stable")
        self.keys = np.asarray(keys, np.float64)[order]
        self.xy = np.asarray(xy, np.float64).reshape(-1, 2)[order]
        self.by = by
        self.origin = origin
        # contiguous columns: np.interp copies a strided one on every call (a frame at a
        # time, as --every reads them, that was a copy of the whole table per frame)
        self._x = np.ascontiguousarray(self.xy[:, 0])
        self._y = np.ascontiguousarray(self.xy[:, 1])
        steps = np.diff(self.keys)
        # over the distinct keys: a message read twice (two connections of one topic) must not
        # make the usual interval 0, and every interval a gap
        distinct = steps[steps > 0]
        self.interval = float(np.median(distinct)) if len(distinct) else 0.0
        limit = GAP_INTERVALS * self.interval
        if by == "timestamp":
            limit = max(limit, GAP_MIN_SECONDS)
        #: row i is followed by a gap (length n - 1)
        self._gap_after = steps > limit
        before = np.flatnonzero(self._gap_after)
        self.gaps = np.c_[self.keys[before], self.keys[before + 1]]

    def _margin(self) -> float:
        """How far beyond a row (at the ends, and into a gap) a timestamp still gets it."""
        return 0.5 * self.interval if self.by == "timestamp" else 0.0

    def span(self) -> tuple[float, float]:
        """The keys a frame's own may take to get a position: from the first row's to the
        last's; for timestamps, widened at either end by half the median interval between
        rows (a frame a little before the first fix or after the last one still gets it)."""
        first, last = float(self.keys[0]), float(self.keys[-1])
        margin = self._margin()
        return first - margin, last + margin

    def at(
        self, indices, timestamps, *, interpolate: bool = False, copies: bool = True
    ) -> np.ndarray:
        """Positions (n, 2) of frames; NaN where a frame index has no row, or a timestamp lies
        outside :meth:`span` (a recording that goes on before or after its positions), and
        for a frame inside one of the ``gaps`` (more than half the median interval from
        the rows on either side of it).

        With ``interpolate``, a frame between two rows gets the straight-line blend of their
        positions instead of the nearer one (or, keyed by frame, NaN), so that positions and
        distances between consecutive frames follow the motion when positions are sparser than
        frames (map places, ``every='2m'``, odometry); outside the rows' range and in a gap it
        is as without.

        ``copies=False``: NaN for a frame whose position would be a row's own beyond it (a
        timestamp within half an interval past the first or last row, or into a gap), where
        frames are not between two rows: odometry, for which a copied position would read as
        a stand.
        """
        if self.by == "frame":
            q = np.asarray(indices, np.float64)
        else:
            q = np.asarray(timestamps, np.float64)
            if not np.isfinite(q).all():
                raise RecordingError(
                    f"positions {self.origin} are keyed by timestamp, but the recording's "
                    "frames have no timestamps: use a frame,x,y CSV"
                )
        n = len(self.keys)
        if interpolate:
            out = self._interp(q)
        elif self.by == "frame":
            pos = np.clip(np.searchsorted(self.keys, q), 0, n - 1)
            out = self.xy[pos].copy()
            out[self.keys[pos] != q] = np.nan
        elif n == 1:
            out = np.repeat(self.xy[:1], len(q), axis=0)
        else:
            right = np.clip(np.searchsorted(self.keys, q), 1, n - 1)
            left = right - 1
            nearer_left = np.abs(q - self.keys[left]) <= np.abs(self.keys[right] - q)
            out = self.xy[np.where(nearer_left, left, right)]
        lo, hi = self.span() if copies else (self.keys[0], self.keys[-1])
        out[(q < lo) | (q > hi)] = np.nan
        if len(self.gaps):
            self._blank_gaps(q, out, copies)
        return out

    def _blank_gaps(self, q: np.ndarray, out: np.ndarray, copies: bool = True) -> None:
        """NaN for the keys ``q`` inside a gap; the row's own position within the margin of
        either side (as at the ends), in place of an interpolated one, or NaN there too
        without ``copies``."""
        n = len(self.keys)
        right = np.searchsorted(self.keys, q, side="right")  # the first row after q
        left = np.clip(right - 1, 0, n - 2)
        right = np.clip(right, 1, n - 1)
        inside = (q > self.keys[0]) & (q < self.keys[-1]) & self._gap_after[left]
        margin = self._margin() if copies else 0.0  # (a frame at a row is not a copy)
        near_left = inside & (q - self.keys[left] <= margin)
        near_right = inside & ~near_left & (self.keys[right] - q <= margin)
        out[near_left] = self.xy[left[near_left]]
        out[near_right] = self.xy[right[near_right]]
        out[inside & ~near_left & ~near_right] = np.nan

    def describe_gaps(self, most: int = 3) -> str:
        """The gaps in words, for messages (``''`` for none): ``2 gaps: timestamps
        1005.95-1008 s, 1020-1031 s``."""
        if not len(self.gaps):
            return ""
        unit = " s" if self.by == "timestamp" else ""
        shown = ", ".join(f"{a:.10g}-{b:.10g}{unit}" for a, b in self.gaps[:most])
        more = f" and {len(self.gaps) - most} more" if len(self.gaps) > most else ""
        kind = "timestamps" if self.by == "timestamp" else "frames"
        word = "gap" if len(self.gaps) == 1 else "gaps"
        return f"{len(self.gaps)} {word}: {kind} {shown}{more}"

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
        frames, hint = self.describe_frames(indices, timestamps)
        raise RecordingError(
            f"{where}: no frame has a position in {self.origin} (its rows: "
            f"{self.describe_span()}; {frames}): {hint}"
        )

    def describe_frames(self, indices, timestamps) -> tuple[str, str]:
        """A recording's frames (``indices``, ``timestamps``; not empty) in the words of the
        rows' key, and what a file that gives none of them a position is likely to have got
        wrong: ``("its frames 0-99", "a frame,x,y row names ...")``."""
        if self.by == "timestamp":
            t = np.asarray(timestamps, np.float64)  # a recording without any is refused before
            frames = f"its frames' timestamps {np.nanmin(t):.10g}-{np.nanmax(t):.10g} s"
            return frames, "the positions and the recording must share a clock"
        i = np.asarray(indices)
        frames = f"its frames {int(i.min())}-{int(i.max())}"
        return frames, "a frame,x,y row names a frame's index in the recording"

    def _interp(self, q: np.ndarray) -> np.ndarray:
        """Linear interpolation between rows (the first/last row's position beyond them)."""
        return np.c_[np.interp(q, self.keys, self._x), np.interp(q, self.keys, self._y)]


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
    _check_unique_columns(header, (key, "x", "y"), f"positions CSV {path}")
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
