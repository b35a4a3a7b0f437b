"""What every recording source shares: batches of frames, ``every`` thinning, errors.

A source yields :class:`Batch` objects: a few dozen frames already converted to gray, in
[0, 1] and resized, with their timestamps (seconds, NaN when the recording has none) and their
index in the recording.  Memory therefore depends on the batch size, never on the length of
the recording.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from .._validation import check_positive_int
from ..images import DEFAULT_SIZE, _check_size

__all__ = ["Batch", "Every", "RecordingError", "Source", "parse_every", "require_extra"]

logger = logging.getLogger(__name__)
#: (recording, rule, positions) whose frames without a position were warned of already
_WARNED_UNPLACED: set[tuple] = set()
#: (recording, rule) whose timestamps stepping back were warned of already
_WARNED_STEP_BACK: set[tuple] = set()

#: a step of ``every`` ('0.5s', '2m') that falls short by no more than this (seconds or
#: metres), plus a few units in the last place of the numbers it is computed from, is taken
#: as the full step: rounding, such as 0.1 m steps adding up to 0.30000000000000004 m or
#: Unix timestamps (float64 holds them to about 0.2 us), does not drop a frame
EVERY_SLACK = 1e-9
#: ... and this share of the step (a millionth: a micrometre in a metre)
EVERY_RELATIVE_SLACK = 1e-6

#: frames per batch unless a caller asks for another number
DEFAULT_BATCH = 32

#: ``decode(size)``: one frame as float32 gray in [0, 1] at ``size`` (H, W)
Decoder = Callable[[tuple[int, int]], np.ndarray]


class RecordingError(ValueError):
    """A recording that cannot be read as asked (the message names the file)."""


def _reason(exc) -> str:
    """An exception's message on one line (its type name when it has none)."""
    return " ".join(str(exc).split()) or type(exc).__name__


def require_extra(module: str) -> ModuleType:
    """Import an optional module of the ``recordings`` extra, or say how to install it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(
            f"reading recordings needs the {module.split('.')[0]!r} package: "
            "pip install 'flyvpr[recordings]'"
        ) from None


@dataclass(frozen=True)
class Every:
    """Which frames to keep: every ``value``-th frame, one per ``value`` s or per ``value`` m."""

    value: float = 1.0
    unit: str = "frames"  # 'frames', 'seconds' or 'metres'

    def __str__(self) -> str:
        suffix = {"frames": "", "seconds": "s", "metres": "m"}[self.unit]
        return f"{self.value:g}{suffix}"


_EVERY_RE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:e[-+]?\d+)?)\s*(s|m)?\s*$", re.IGNORECASE)


def parse_every(text) -> Every:
    """``every``: ``3`` (every 3rd frame), ``0.5s`` (one per half second), ``2m`` (per 2 m).

    Raises
    ------
    ValueError
        For anything else, a count that is not an integer >= 1 or a step that is not > 0.
    """
    if text is None:
        return Every()
    if isinstance(text, Every):
        value, unit = text.value, text.unit
        if unit not in ("frames", "seconds", "metres"):
            raise ValueError(f"every: unit must be 'frames', 'seconds' or 'metres'; got {unit!r}")
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"every: the step must be a number; got {value!r}")
    else:
        m = _EVERY_RE.match(str(text))
        if m is None:
            raise ValueError(
                f"every: expected N (every N-th frame), Ts (seconds) or Dm (metres), such as 3, "
                f"0.5s or 2m; got {text!r}"
            )
        value = float(m.group(1))
        unit = {None: "frames", "s": "seconds", "m": "metres"}[(m.group(2) or "").lower() or None]
    if unit == "frames" and (not math.isfinite(value) or value != int(value) or value < 1):
        raise ValueError(f"every: a frame count must be an integer >= 1; got {text!r}")
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"every: the step must be a finite number > 0; got {text!r}")
    return Every(float(value), unit)


@dataclass
class Batch:
    """Consecutive kept frames of a recording.

    Attributes
    ----------
    images : ndarray, shape (n, H, W), float32 in [0, 1]
    timestamps : ndarray, shape (n,), float64
        Seconds (the recording's clock); NaN where unknown.
    indices : ndarray, shape (n,), int64
        Index of each frame among all frames of the recording (before thinning).
    """

    images: np.ndarray
    timestamps: np.ndarray
    indices: np.ndarray

    def __len__(self) -> int:
        return int(self.images.shape[0])


def _short(step: float, every: float, *values) -> bool:
    """Whether ``step`` falls short of ``every`` by more than rounding: :data:`EVERY_SLACK`
    plus 4 units in the last place of the largest of ``values`` (what ``step`` is computed
    from), so that the test does not depend on where the clock or the coordinates start, plus
    :data:`EVERY_RELATIVE_SLACK` of ``every`` (positions interpolated at Unix timestamps carry
    the timestamps' rounding too, times the speed)."""
    scale = max((abs(float(v)) for v in values), default=0.0)
    slack = EVERY_SLACK + 4 * math.ulp(scale) + EVERY_RELATIVE_SLACK * every
    return step < every - slack


class _Thinner:
    """Decides frame by frame whether ``every`` keeps it (positions for the metres rule)."""

    def __init__(self, every: Every, where: str, positions=None):
        self.every = every
        self.where = where
        self.positions = positions
        self.last_t: float | None = None
        self.prev_t: float | None = None  # the previous frame's timestamp (kept or not)
        self.last_xy: np.ndarray | None = None
        self.unplaced = 0  # frames a metres rule skipped for want of a position
        if every.unit == "metres" and positions is None:
            raise ValueError(
                f"every={every}: keeping frames by distance needs positions "
                "(positions=CSV or position_topic=TOPIC)"
            )

    def keep(self, index: int, timestamp: float) -> bool:
        e = self.every
        if e.unit == "frames":
            return index % int(e.value) == 0
        if e.unit == "seconds":
            if not math.isfinite(timestamp):
                raise RecordingError(
                    f"{self.where}: every={e} needs timestamps, and this recording has none"
                )
            prev, self.prev_t = self.prev_t, timestamp
            if prev is not None and timestamp < prev:
                # a clock set back (or stamps out of order): the step back counts as no time,
                # so the rule goes on from the new time instead of waiting for the old one
                self._stepped_back(index, prev - timestamp)
                if self.last_t is not None:
                    self.last_t -= prev - timestamp
            if self.last_t is not None and _short(
                timestamp - self.last_t, e.value, timestamp, self.last_t
            ):
                return False
            self.last_t = timestamp
            return True
        # between rows by time (or index), as odometry reads them: positions slower than the
        # camera give each frame its own point on the way, not the nearest row's
        xy = self.positions.at(np.array([index]), np.array([timestamp]), interpolate=True)[0]
        if not np.isfinite(xy).all():
            self.unplaced += 1
            return False
        if self.last_xy is not None and _short(
            float(np.hypot(*(xy - self.last_xy))), e.value, *xy, *self.last_xy
        ):
            return False
        self.last_xy = xy
        return True

    def _stepped_back(self, index: int, step: float) -> None:
        said = (self.where, str(self.every))
        if said in _WARNED_STEP_BACK:  # once a recording, though a map reads it twice
            return
        _WARNED_STEP_BACK.add(said)
        logger.warning(
            "%s: the timestamps step back by %.6g s at frame %d; every=%s counts the step as "
            "no time and goes on from the new time (later steps back are not reported)",
            self.where, step, index, self.every,
        )  # fmt: skip


class Source:
    """A recording: an image folder, a video file or a ROS bag (see :func:`open_source`).

    Subclasses implement :meth:`_frames`, a generator of ``(index, timestamp, decode)`` with
    ``decode(size)`` returning the frame as float32 gray in [0, 1] at ``size``; frames that
    ``every`` drops are never decoded further than the container needs.
    """

    kind = "source"

    def __init__(self, path):
        self.path = Path(path)

    def describe(self) -> str:
        return f"{self.kind} {self.path}"

    def _frames(self) -> Iterator[tuple[int, float, Decoder]]:  # pragma: no cover - abstract
        raise NotImplementedError

    def batches(
        self, size=DEFAULT_SIZE, *, every=None, positions=None, batch: int = DEFAULT_BATCH
    ) -> Iterator[Batch]:
        """Stream the kept frames in batches of at most ``batch`` frames.

        Parameters
        ----------
        size : (int, int)
            (H, W) after the gray conversion and area-averaging resize.
        every : str or Every, optional
            Thinning rule (:func:`parse_every`); default every frame.
        positions : Positions, optional
            Needed by a metres rule.
        batch : int, default 32
            Frames per batch (at least 1).

        Raises
        ------
        RecordingError
            If the recording cannot be read, or holds no frame at all (names the file).
        ImageReadError
            For a damaged file in an image folder (names it).
        ValueError
            For a bad ``every`` (a metres rule without ``positions`` too) or ``batch``.
        """
        h, w = _check_size(size)
        batch = check_positive_int(batch, "batch")
        thin = _Thinner(parse_every(every), self.describe(), positions)
        images = np.empty((batch, h, w), np.float32)
        stamps = np.empty(batch, np.float64)
        idx = np.empty(batch, np.int64)
        n = 0
        seen = 0
        ends = [-1, -1]  # the first and last frame's index, and the timestamps' range
        times = [math.inf, -math.inf]
        for index, timestamp, decode in self._frames():
            seen += 1
            if seen == 1:
                ends[0] = index
            ends[1] = index
            if timestamp == timestamp:  # not NaN
                times[:] = min(times[0], timestamp), max(times[1], timestamp)
            if not thin.keep(index, timestamp):
                continue
            images[n] = decode((h, w))
            stamps[n] = timestamp
            idx[n] = index
            n += 1
            if n == batch:
                yield Batch(images.copy(), stamps.copy(), idx.copy())
                n = 0
        if seen == 0:
            raise RecordingError(f"{self.describe()}: the recording holds no frame")
        if positions is not None and thin.unplaced == seen:
            frames, hint = positions.describe_frames(ends, times)
            raise RecordingError(
                f"{self.describe()}: every={thin.every} keeps frames by distance, and no frame "
                f"has a position in {positions.origin} (its rows: {positions.describe_span()}; "
                f"{frames}): {hint}"
            )
        said = (self.describe(), str(thin.every), positions.origin if positions else None)
        if thin.unplaced and said not in _WARNED_UNPLACED:  # once, though a map reads twice
            _WARNED_UNPLACED.add(said)
            gaps = positions.describe_gaps()
            logger.warning(
                "%s: every=%s skipped %d of %d frames that have no position in %s (its rows: "
                "%s%s)",
                self.describe(), thin.every, thin.unplaced, seen, positions.origin,
                positions.describe_span(), f"; {gaps}" if gaps else "",
            )  # fmt: skip
        if n:
            yield Batch(images[:n].copy(), stamps[:n].copy(), idx[:n].copy())

    def read_all(self, size=DEFAULT_SIZE, *, every=None, positions=None) -> Batch:
        """Every kept frame in one :class:`Batch` (for a reference map, which needs them all)."""
        parts = list(self.batches(size, every=every, positions=positions))
        if not parts:
            raise RecordingError(f"{self.describe()}: every={every} keeps no frame")
        return Batch(
            np.concatenate([b.images for b in parts]),
            np.concatenate([b.timestamps for b in parts]),
            np.concatenate([b.indices for b in parts]),
        )
