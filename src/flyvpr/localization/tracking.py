"""Localizing a recording against a map, frame by frame, with or without a ground truth.

:func:`track` streams a source (:mod:`flyvpr.sources`) through a map's localizer a batch at a
time and yields one :class:`Step` per batch; memory does not grow with the recording.  With
``odometry`` it also passes the distance the robot moved between kept frames, from the
recording's own positions, to the localizer (path integration).
:func:`ground_truth_frames` and :func:`ground_truth_positions` build the ground truth of a
recording from frame alignment or from positions.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .._validation import check_positive_int
from ..datasets import ground_truth_from_frames, ground_truth_from_positions
from ..sources import Batch, Source

__all__ = [
    "Step",
    "track",
    "distances_moved",
    "ground_truth_frames",
    "ground_truth_positions",
]


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
    states : ndarray of str, shape (n,)
        ``"localized"`` or ``"lost"`` (see :class:`flyvpr.localization.Fix`).
    positions : ndarray, shape (n, 2), or None
        The map positions of the matched places, when the map has positions.
    odometry : ndarray, shape (n,), or None
        With ``odometry``: the places each frame moved since the previous kept frame, as the
        filter was given them (metres over the localizer's ``place_spacing``); NaN on a frame
        that got none.  None without ``odometry``.
    """

    batch: Batch
    places: np.ndarray
    confidences: np.ndarray
    scores: np.ndarray
    relocated: np.ndarray
    states: np.ndarray
    positions: np.ndarray | None
    odometry: np.ndarray | None = None


def track(
    localizer,
    source: Source,
    *,
    every=None,
    positions=None,
    odometry: bool = False,
    realtime=False,
    batch: int = 32,
) -> Iterator[Step]:
    """Localize every kept frame of ``source`` with ``localizer``.

    Parameters
    ----------
    localizer : Localizer
        Fitted, e.g. :meth:`flyvpr.localization.Localizer.from_map` (its ``map_``, when it has
        one, gives the map's positions to the steps).
    source : Source
        The recording (:mod:`flyvpr.sources`).
    every : str or Every, optional
        Which frames to keep (:func:`flyvpr.sources.parse_every`).
    positions : Positions, optional
        The recording's own positions (metres): needed by a metres ``every`` and by
        ``odometry``.
    odometry : bool
        Pass each kept frame's distance from the previous kept frame, from ``positions``
        (interpolated between their rows), to :meth:`Localizer.update_batch`, which turns it
        into places with its ``place_spacing``.  The first frame, and a frame where either
        position is unknown, get no odometry (the filter estimates that step itself).
    realtime : bool
        Pace the frames to the recording's timestamps (wall clock), one frame at a time.
    batch : int, default 32
        Frames read and localized at a time (at least 1).

    Raises
    ------
    ValueError
        For ``odometry`` without ``positions``, or a ``batch`` below 1.
    TypeError
        For a ``batch`` that is not an int.
    """
    batch = check_positive_int(batch, "batch")
    if odometry and positions is None:
        raise ValueError("odometry needs positions: the recording's own (positions=CSV)")
    m = getattr(localizer, "map_", None)
    size = localizer.method.frontend.image_shape_
    start_wall: float | None = None  # the wall clock at the first frame with a timestamp
    start_t = 0.0  # and its timestamp
    last_xy = np.full((1, 2), np.nan)  # the previous kept frame's position
    for b in source.batches(size, every=every, positions=positions, batch=1 if realtime else batch):
        if realtime and np.isfinite(b.timestamps[0]):
            if start_wall is None:
                start_wall, start_t = time.monotonic(), float(b.timestamps[0])
            delay = (float(b.timestamps[0]) - start_t) - (time.monotonic() - start_wall)
            if delay > 0:
                time.sleep(delay)
        distances = moved = None
        if odometry:
            distances, last_xy = distances_moved(positions, b, last_xy)
        fixes = localizer.update_batch(b.images, distances=distances)
        if distances is not None:  # update_batch checked that the localizer has a spacing
            moved = distances / localizer.place_spacing
        xy = None
        if m is not None and m.positions is not None:
            xy = m.positions[fixes.places]
        yield Step(
            b, fixes.places, fixes.confidences, fixes.scores, fixes.relocated, fixes.states, xy,
            moved,
        )  # fmt: skip


def distances_moved(positions, batch: Batch, last_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Metres each frame of ``batch`` moved since the previous kept frame, from the
    recording's ``positions`` (interpolated between their rows; NaN where either position is
    unknown, or would be a row's own copied beyond it: past the first or last fix, or into a
    gap, where two frames with one copied position would read as a stand), and the batch's
    last position (the next call's ``last_xy``, shape (1, 2); all NaN before the first
    frame)."""
    xy = positions.at(batch.indices, batch.timestamps, interpolate=True, copies=False)
    moved = xy - np.concatenate([last_xy, xy[:-1]])
    return np.hypot(moved[:, 0], moved[:, 1]), xy[-1:]


def ground_truth_frames(query_index, reference_index, tolerance: int) -> np.ndarray:
    """Frame-aligned recordings: query frame ``i`` shows the place of reference frame ``i``.

    Returns the boolean matrix (n_query, n_places): ``|query_index - reference_index| <=
    tolerance`` (indices in the recordings, before thinning); see
    :func:`flyvpr.datasets.ground_truth_from_frames`, which it is.
    """
    return ground_truth_from_frames(query_index, reference_index, tolerance)


def ground_truth_positions(query_xy, reference_xy, radius: float) -> np.ndarray:
    """A query frame matches every place within ``radius`` metres; a frame or a place without
    a position (a NaN row: the positions do not cover it) matches nothing.

    The distances are :func:`flyvpr.datasets.ground_truth_from_positions`' over the rows that
    have positions.
    """
    q = np.asarray(query_xy, np.float64)
    r = np.asarray(reference_xy, np.float64)
    if q.ndim != 2 or r.ndim != 2:
        raise ValueError(
            f"query_xy and reference_xy must be 2-d (n, D); got shapes {q.shape} and {r.shape}"
        )
    out = np.zeros((q.shape[0], r.shape[0]), dtype=bool)
    known_q = np.isfinite(q).all(axis=1)
    known_r = np.isfinite(r).all(axis=1)
    if known_q.any() and known_r.any():
        out[np.ix_(known_q, known_r)] = ground_truth_from_positions(q[known_q], r[known_r], radius)
    return out
