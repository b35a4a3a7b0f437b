"""Localizing a recording against a map, frame by frame, with or without a ground truth.

:func:`track` streams a source (:mod:`flyvpr.sources`) through a map's localizer a batch at a
time and yields one :class:`Step` per batch; memory does not grow with the recording, unless
``keep_scores`` asks for the score rows (needed to score the run against a ground truth).
:func:`ground_truth_frames` and :func:`ground_truth_positions` build the ground truth of a
recording from frame alignment or from positions.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .sources import Batch, Source

__all__ = ["Step", "track", "ground_truth_frames", "ground_truth_positions"]


@dataclass
class Step:
    """The localizer's answers for one batch of frames.

    Attributes
    ----------
    batch : Batch
        The frames (images, timestamps, source indices).
    places, confidences : ndarray, shape (n,)
    scores : ndarray, shape (n, n_places)
        The filter's score rows (the CANN's activity over places).
    relocated : ndarray of bool, shape (n,)
    positions : ndarray, shape (n, 2), or None
        The map positions of the matched places, when the map has positions.
    """

    batch: Batch
    places: np.ndarray
    confidences: np.ndarray
    scores: np.ndarray
    relocated: np.ndarray
    positions: np.ndarray | None


def track(
    localizer, source: Source, *, every=None, positions=None, realtime=False, batch: int = 32
) -> Iterator[Step]:
    """Localize every kept frame of ``source`` with ``localizer`` (from :meth:`Map.localizer`).

    Parameters
    ----------
    realtime : bool
        Pace the frames to the recording's timestamps (wall clock), one frame at a time.
    """
    m = getattr(localizer, "map_", None)
    size = localizer.method.frontend.image_shape_
    start_wall = start_t = None
    for b in source.batches(size, every=every, positions=positions, batch=1 if realtime else batch):
        if realtime and np.isfinite(b.timestamps[0]):
            if start_wall is None:
                start_wall, start_t = time.monotonic(), float(b.timestamps[0])
            delay = (float(b.timestamps[0]) - start_t) - (time.monotonic() - start_wall)
            if delay > 0:
                time.sleep(delay)
        places, conf, scores, relocated = localizer.update_batch(b.images)
        xy = None
        if m is not None and m.positions is not None:
            xy = m.positions[places]
        yield Step(b, places, conf, scores, relocated, xy)


def ground_truth_frames(query_index, reference_index, tolerance: int) -> np.ndarray:
    """Frame-aligned recordings: query frame ``i`` shows the place of reference frame ``i``.

    Returns the boolean matrix (n_query, n_places): ``|query_index - reference_index| <=
    tolerance`` (indices in the recordings, before thinning).
    """
    q = np.asarray(query_index, np.int64)[:, None]
    r = np.asarray(reference_index, np.int64)[None, :]
    return np.abs(q - r) <= int(tolerance)


def ground_truth_positions(query_xy, reference_xy, radius: float) -> np.ndarray:
    """A query frame matches every place within ``radius`` metres (NaN positions never match)."""
    q = np.asarray(query_xy, np.float64)[:, None, :]
    r = np.asarray(reference_xy, np.float64)[None, :, :]
    d = np.hypot(q[..., 0] - r[..., 0], q[..., 1] - r[..., 1])
    return np.nan_to_num(d, nan=np.inf) <= float(radius)
