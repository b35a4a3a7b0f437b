"""Streaming localization: one camera frame in, a :class:`Fix` (place, confidence, state) out.

The :class:`Localizer` wraps a fitted :class:`~flyvpr.methods.Method` whose
temporal filter (if any) is online.  Each :meth:`Localizer.update` encodes one
frame, scores it against the reference places and advances the filter by one
step, so time and memory per frame do not grow with the number of frames seen.
It gives the same answers as the batch path (``Method.score`` then the row
argmax) where the front end scores one row as it scores many (``kenyon``, ``pixels``,
``flyhash``: bit for bit); FlyNet's float32 products differ in the last bits, and a filter
can carry that across a near-tie into another answer on a few frames (see the streaming
guide).

Odometry, when the robot has it, goes to the filter as the number of places moved since the
previous frame (``velocity``), or as metres (``distance``), which the localizer divides by
the map's spacing between places (``place_spacing``).  The CANN does not take it as exact: it
learns the ratio of places moved to the odometry (its ``odometry`` parameter), so a spacing
that is a little off costs little.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from inspect import signature
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from .._validation import NotFittedError, check_images, check_real
from ..methods import DEFAULT_METHOD, Method, make_method
from ..temporal.base import OnlineFilter

if TYPE_CHECKING:
    from .maps import Map

__all__ = ["Localizer", "Fix", "Fixes", "LOCALIZED", "LOST"]

#: the filter is sure enough of its place (see :class:`Fix`)
LOCALIZED = "localized"
#: the filter's place is only a hint
LOST = "lost"


class Fix(NamedTuple):
    """The localizer's answer for one frame (see :meth:`Localizer.update`).

    Attributes
    ----------
    place : int
        Index of the best reference place.
    confidence : float
        With a filter that reports a state (the CANN): the filter's probability, in [0, 1],
        that ``place`` is right.  Otherwise (no filter, or a filter without a state) the raw
        score of the place (similarity or filtered activity; higher = surer), not a
        probability.
    state : str
        ``"localized"`` or ``"lost"``, as the filter decides (the CANN: ``"localized"`` when
        the answer comes from the image sequence and its raw confidence, the support times
        the probability that the place is right (the window's, or where the answer snapped
        to the front end's place nearby, the front end's share of agreement), is at least
        0.5: with the default calibration, a
        confidence of 0.9045 or more); always ``"localized"`` without a filter or with a
        filter that has no state.
    """

    place: int
    confidence: float
    state: str


class Fixes(NamedTuple):
    """The localizer's answers for consecutive frames (see :meth:`Localizer.update_batch`).

    Attributes
    ----------
    places : ndarray of int64, shape (n,)
    confidences : ndarray, shape (n,)
    scores : ndarray, shape (n, n_places)
        The filtered score rows.
    relocated : ndarray of bool, shape (n,)
        Whether the filter relocated its packet at that frame (filters that count
        relocations, such as the CANN; False otherwise).
    states : ndarray of str, shape (n,)
        ``"localized"`` or ``"lost"`` per frame, as in :class:`Fix`.
    """

    places: np.ndarray
    confidences: np.ndarray
    scores: np.ndarray
    relocated: np.ndarray
    states: np.ndarray


def online_method(method, random_state=None, frontend_params=None, filter_params=None) -> Method:
    """``method`` (a :class:`~flyvpr.methods.Method`, or a name made with the other arguments),
    checked to run one frame at a time: its filter, if any, is an online one.

    Raises
    ------
    ValueError
        For a filter that needs the whole query traverse (SeqSLAM, say).
    """
    if isinstance(method, Method):
        m = method
    else:
        m = make_method(method, random_state, frontend_params, filter_params)
    if m.filter is not None and not isinstance(m.filter, OnlineFilter):
        raise ValueError(
            f"method {m.name!r} uses filter {type(m.filter).__name__}, which cannot run one "
            "frame at a time; choose an online filter (e.g. cann) or none"
        )
    return m


def _check_place_spacing(value) -> float | None:
    return None if value is None else check_real(value, "place_spacing", unit="metres")


def odometry_places(velocity, distance, place_spacing, owner: str) -> float | None:
    """One frame's odometry in places (None: the filter estimates the movement itself):
    ``velocity`` in places, or ``distance`` in metres over ``place_spacing``; a 0-d array (an
    element a robot's code took from an array) is its number.  ``owner`` names the class
    whose ``place_spacing`` a missing spacing asks for."""
    velocity, distance = (
        v.item() if isinstance(v, np.ndarray) and v.ndim == 0 else v for v in (velocity, distance)
    )
    if distance is None:
        return None if velocity is None else check_real(velocity, "velocity", low=None)
    if velocity is not None:
        raise ValueError("give the movement as velocity (places) or distance (metres), not both")
    distance = check_real(distance, "distance", low=0, inclusive=True)
    if place_spacing is None:
        raise ValueError(
            f"distance (metres) needs place_spacing, the metres between places: give "
            f"{owner}(place_spacing=...) or a map with positions, or pass velocity in places"
        )
    places = distance / place_spacing
    if not math.isfinite(places):
        raise ValueError(
            f"distance {distance:g} m over place_spacing {place_spacing:g} m is not a "
            "finite number of places"
        )
    return places


def odometry_places_batch(velocities, distances, n: int, place_spacing, owner: str) -> list:
    """Per-frame odometry in places for ``n`` frames (None where NaN or None): as
    :func:`odometry_places`, for arrays of ``velocities`` or ``distances``."""
    if velocities is not None and distances is not None:
        raise ValueError("give the movement as velocities (places) or distances (metres), not both")
    if velocities is None and distances is None:
        return [None] * n
    name = "velocities" if distances is None else "distances"
    raw = np.asarray(velocities if distances is None else distances)
    if raw.dtype == object:  # None marks a frame without odometry
        raw = np.array([np.nan if v is None else v for v in raw.ravel()]).reshape(raw.shape)
    if raw.dtype.kind not in "iuf":
        raise TypeError(f"{name} must be numbers (NaN or None for none); got dtype {raw.dtype}")
    arr = raw.astype(np.float64)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), one entry per image; got {arr.shape}")
    if np.isinf(arr).any():
        raise ValueError(f"{name} must be finite (NaN or None: no odometry for that frame)")
    if distances is not None:
        if (arr < 0).any():
            raise ValueError(f"distances must be >= 0; got {arr[arr < 0][0]:g}")
        if place_spacing is None:
            raise ValueError(
                "distances (metres) need place_spacing, the metres between places: give "
                f"{owner}(place_spacing=...) or a map with positions, or pass velocities "
                "in places"
            )
        with np.errstate(over="ignore"):
            arr = arr / place_spacing
        if np.isinf(arr).any():
            raise ValueError(
                f"distances over place_spacing {place_spacing:g} m must be a finite "
                f"number of places; got {raw.ravel()[np.isinf(arr)][0]:g} m"
            )
    return [None if math.isnan(v) else float(v) for v in arr]


class Localizer:
    """Online place recognition over a reference map.

    Parameters
    ----------
    method : str or Method
        A method name (built with ``make_method``) or a ready :class:`Method`; default
        :data:`flyvpr.methods.DEFAULT_METHOD`.
        Its filter, if any, must be online (offer ``reset``/``step``).  A ready method's
        front end is shared (``fit`` refits it); its filter is copied and reset, so the
        localizer starts a drive afresh and keeps its own state: scoring with the method,
        or a second localizer over it, leaves this one's frames alone.
    random_state : None, int or Generator
        Used when ``method`` is a name.
    frontend_params, filter_params : dict, optional
        Used when ``method`` is a name.
    place_spacing : float, optional
        Metres between consecutive reference places, to turn the ``distance`` given to
        :meth:`update` into places.  :meth:`from_map` takes it from the map's positions
        (:attr:`flyvpr.localization.maps.Map.place_spacing`).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((50, 32, 64), dtype=np.float32)
    >>> loc = Localizer("flyhash", random_state=0).fit(ref)
    >>> loc.update(ref[7]).place
    7
    """

    #: the map of :meth:`from_map` (set there only)
    map_: Map

    def __init__(
        self,
        method=DEFAULT_METHOD,
        random_state=None,
        frontend_params=None,
        filter_params=None,
        place_spacing=None,
    ):
        self.method = online_method(method, random_state, frontend_params, filter_params)
        if self.method is method and method.filter is not None:
            # The caller's method may have filtered frames already (its ``score``), and may
            # serve other localizers: this one gets a filter of its own, from a fresh state.
            own = copy.deepcopy(method.filter)
            if isinstance(own, OnlineFilter):  # (online_method checked that it is)
                own.reset()
            self.method = dataclasses.replace(method, filter=own, timing_={})
        filt = self.method.filter
        self.place_spacing = _check_place_spacing(place_spacing)
        self._takes_velocity = isinstance(filt, OnlineFilter) and (
            "velocity" in signature(filt.step).parameters
        )
        self.n_frames_ = 0

    @classmethod
    def from_map(cls, path, *, size=None, place_spacing=None, breaks=None) -> Localizer:
        """A localizer over the places of a map (see :class:`flyvpr.localization.maps.Map`).

        Parameters
        ----------
        path : str, Path or Map
            A map file written by ``flyvpr map`` / :meth:`Map.save`, or a loaded map.
        size : (int, int), optional
            The image size the caller will feed; a map built for another size is refused.
        place_spacing : float, optional
            Metres between consecutive places; default the map's
            :attr:`~flyvpr.localization.maps.Map.place_spacing` (None for a map without positions).
        breaks : sequence of int, optional
            Places where the map's route is broken, for a method whose filter takes them (the
            CANN's ``breaks``: it does not carry the robot across them); ``()`` for none.
            Default: the breaks the map's filter was built with, if any, else the map's
            :attr:`~flyvpr.localization.maps.Map.breaks` (where its positions jump).  Breaks
            given to a method whose filter takes none are refused (ValueError).

        Notes
        -----
        The map is kept as ``map_`` (timestamps, positions and thumbnails of the places).
        """
        from .maps import Map

        m = path if isinstance(path, Map) else Map.load(path, size=size)
        if place_spacing is None:
            place_spacing = m.place_spacing
        loc = cls(m.method, place_spacing=place_spacing)  # (a filter of its own)
        filt = loc.method.filter
        takes = filt is not None and "breaks" in filt.get_params()
        chosen = None  # (None: the filter keeps what it was built with)
        if breaks is not None:
            from ..temporal.cann._params import _check_breaks

            chosen = tuple(int(b) for b in _check_breaks(breaks))
            if chosen and not takes:
                name = "none" if filt is None else type(filt).__name__
                raise ValueError(
                    f"breaks: the map's method {m.method.name} has no filter that takes them "
                    f"(its filter: {name}); give breaks=None or ()"
                )
        elif takes and filt is not None and np.size(filt.get_params()["breaks"]) == 0:
            chosen = m.breaks
        if takes and filt is not None:
            if chosen is not None:
                filt.set_params(breaks=chosen)
                loc.reset()
            final = np.asarray(filt.get_params()["breaks"]).ravel()
            if final.size and final.max() >= m.n_places:
                whose = "got" if breaks is not None else "the map's filter has"
                raise ValueError(
                    f"breaks must be places 1 .. {m.n_places - 1} of this map of "
                    f"{m.n_places} places; {whose} {final.tolist()}"
                )
        loc.map_ = m
        return loc

    def fit(self, reference_images) -> Localizer:
        """Build the reference map (fits the method on the reference traverse)."""
        self.method.fit(reference_images)
        self.reset()
        return self

    def reset(self) -> None:
        """Forget the frames seen so far (e.g. at the start of a new drive)."""
        if self.method.filter is not None:
            self._online_filter().reset()
        self.n_frames_ = 0

    def _online_filter(self) -> OnlineFilter:
        """The method's filter, online as ``__init__`` checked (callers check there is one)."""
        filt = self.method.filter
        assert isinstance(filt, OnlineFilter)
        return filt

    def _check_fitted(self, call: str) -> None:
        if not hasattr(self.method.frontend, "n_reference_"):
            raise NotFittedError(
                f"Localizer.{call} needs a reference map: call fit(reference_images) first"
            )

    @property
    def n_places(self) -> int:
        """Number of reference places (raises NotFittedError before :meth:`fit`)."""
        self._check_fitted("n_places")
        return self.method.frontend.n_reference_

    @property
    def uses_odometry(self) -> bool:
        """Whether the filter takes odometry (path integration: the CANN); others ignore it."""
        return self._takes_velocity

    def _step(self, row, velocity):
        filt = self._online_filter()
        if velocity is None or not self._takes_velocity:
            return filt.step(row)
        step: Callable[..., np.ndarray] = filt.step  # takes velocity: __init__ checked
        return step(row, velocity=velocity)

    def _velocity(self, velocity, distance) -> float | None:
        return odometry_places(velocity, distance, self.place_spacing, "Localizer")

    def _velocities(self, velocities, distances, n: int) -> list:
        return odometry_places_batch(velocities, distances, n, self.place_spacing, "Localizer")

    def scores(self, image, *, velocity=None, distance=None) -> np.ndarray:
        """Advance by one frame and return the filtered score row (n_reference,).

        ``velocity`` and ``distance`` are as in :meth:`update`.

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.
        """
        self._check_fitted("scores")
        return self._scores(image, self._velocity(velocity, distance))

    def _scores(self, image, velocity) -> np.ndarray:
        frontend = self.method.frontend
        given = type(image).__name__
        try:
            image = np.asarray(image)
        except Exception as exc:  # ragged lists and such
            raise TypeError(f"image must be an array of shape (H, W); {exc}") from exc
        if image.dtype.kind not in "biuf":  # None, a path, a complex or object array
            raise TypeError(
                f"image must be an array of numbers of shape (H, W) = "
                f"{tuple(frontend.image_shape_)}; got {given} of dtype {image.dtype}"
            )
        if image.ndim != 2:
            hint = (
                f"(a colour frame, dtype {image.dtype}: convert camera frames with "
                "flyvpr.images.resize_area(flyvpr.images.to_gray(frame), "
                f"{tuple(frontend.image_shape_)}))"
                if image.ndim == 3 and image.shape[-1] in (3, 4)
                else "(update_batch takes a stack of frames)"
                if image.ndim == 3
                else ""
            )
            raise ValueError(
                f"image must be one gray frame of shape (H, W) = {tuple(frontend.image_shape_)}; "
                f"got shape {image.shape}" + (f" {hint}" if hint else "")
            )
        frame = check_images(image[None], "image", frontend.image_shape_)
        row = frontend.score_codes(frontend._encode(frame))[0]
        if self.method.filter is not None:
            row = self._step(row, velocity)
        self.n_frames_ += 1
        return row

    def _state(self) -> str:
        state = getattr(self.method.filter, "state_", None)
        return LOCALIZED if state is None else str(state)

    def update_batch(self, images, *, velocities=None, distances=None) -> Fixes:
        """Process consecutive frames: the front end scores them in one vectorised call, then
        the filter steps through the rows in order (as :meth:`update` frame by frame).

        Parameters
        ----------
        images : array-like, shape (n, H, W)
        velocities : array-like, shape (n,), optional
            Places moved since the previous frame, per frame (NaN or None: no odometry for
            that frame).
        distances : array-like, shape (n,), optional
            Metres moved since the previous frame, per frame (NaN or None: none), divided by
            ``place_spacing``.  Not with ``velocities``.

        Returns
        -------
        Fixes
            ``places``, ``confidences``, ``scores`` (the filtered rows, (n, n_places)),
            ``relocated`` and ``states``.

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.
        ValueError
            As :meth:`update`, or for odometry of another length than ``images``.
        """
        self._check_fitted("update_batch")
        frontend = self.method.frontend
        frames = check_images(images, "images", frontend.image_shape_)
        moves = self._velocities(velocities, distances, len(frames))
        S = frontend.score_codes(frontend._encode(frames))
        relocated = np.zeros(len(S), dtype=bool)
        states = [LOCALIZED] * len(S)
        filt = self.method.filter
        if filt is not None:
            out = np.empty(S.shape, dtype=np.float32)
            for i in range(len(S)):
                before = getattr(filt, "n_relocations_", 0)
                out[i] = self._step(S[i], moves[i])
                relocated[i] = getattr(filt, "n_relocations_", 0) != before
                states[i] = self._state()
            S = out
        self.n_frames_ += len(S)
        places = np.argmax(S, axis=1)
        return Fixes(
            places, S[np.arange(len(S)), places], S, relocated, np.array(states, dtype=np.str_)
        )

    def update(self, image, *, velocity=None, distance=None) -> Fix:
        """Process one frame.

        Parameters
        ----------
        image : array-like, shape (H, W)
            Gray image in [0, 1] at the reference images' size.
        velocity : float, optional
            Places moved since the previous frame (odometry), for filters that use it
            (:attr:`uses_odometry`: path integration in the CANN; other filters ignore it);
            without it the CANN estimates the movement from the images.  Negative: backwards
            along the map (odometry that knows its direction; a distance has none).
        distance : float, optional
            Metres moved since the previous frame (odometry, GPS), instead of ``velocity``:
            the filter gets ``distance / place_spacing`` places.  Both are keyword-only: a
            number given by position could be either unit.

        Returns
        -------
        Fix
            ``place`` (index of the best reference place), ``confidence`` and ``state``.
            With a filter that reports a state (the CANN), ``confidence`` is its probability
            that the place is right and ``state`` is ``"localized"`` or ``"lost"``; without a
            filter, or with one that has no state, ``confidence`` is the raw score of the place
            (similarity or filtered activity; higher = surer, not a probability) and ``state``
            is always ``"localized"``.

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.
        ValueError
            For both ``velocity`` and ``distance``; a non-finite one or a negative
            ``distance``; ``distance`` without a ``place_spacing``.
        TypeError
            For a ``velocity`` or ``distance`` that is not a number.
        """
        self._check_fitted("update")
        row = self._scores(image, self._velocity(velocity, distance))
        place = int(np.argmax(row))
        return Fix(place, float(row[place]), self._state())
