"""Streaming localization: one camera frame in, (place index, confidence) out.

The :class:`Localizer` wraps a fitted :class:`~flyvpr.methods.Method` whose
temporal filter (if any) is online.  Each :meth:`Localizer.update` encodes one
frame, scores it against the reference places and advances the filter by one
step, so time and memory per frame do not grow with the number of frames seen.
It gives the same answers as the batch path (``Method.score`` then the row
argmax), up to float rounding of the one-row versus many-row products.
"""

from __future__ import annotations

import numpy as np

from ._validation import NotFittedError, check_images
from .methods import DEFAULT_METHOD, Method, make_method
from .temporal.base import OnlineFilter

__all__ = ["Localizer"]


class Localizer:
    """Online place recognition over a reference map.

    Parameters
    ----------
    method : str or Method
        A method name (built with ``make_method``) or a ready :class:`Method`; default
        :data:`flyvpr.methods.DEFAULT_METHOD`.
        Its filter, if any, must be online (offer ``reset``/``step``).
    random_state : None, int or Generator
        Used when ``method`` is a name.
    frontend_params, filter_params : dict, optional
        Used when ``method`` is a name.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((50, 32, 64), dtype=np.float32)
    >>> loc = Localizer("flyhash", random_state=0).fit(ref)
    >>> loc.update(ref[7])[0]
    7
    """

    def __init__(
        self, method=DEFAULT_METHOD, random_state=None, frontend_params=None, filter_params=None
    ):
        if isinstance(method, Method):
            self.method = method
        else:
            self.method = make_method(method, random_state, frontend_params, filter_params)
        filt = self.method.filter
        if filt is not None and not isinstance(filt, OnlineFilter):
            raise ValueError(
                f"method {self.method.name!r} uses filter {type(filt).__name__}, which cannot run "
                "one frame at a time; choose an online filter (e.g. cann)"
            )
        self.n_frames_ = 0

    @classmethod
    def from_map(cls, path, *, size=None) -> Localizer:
        """A localizer over the places of a map (see :class:`flyvpr.maps.Map`).

        Parameters
        ----------
        path : str, Path or Map
            A map file written by ``flyvpr map`` / :meth:`Map.save`, or a loaded map.
        size : (int, int), optional
            The image size the caller will feed; a map built for another size is refused.

        The map is kept as ``map_`` (timestamps, positions and thumbnails of the places).
        """
        from .maps import Map

        m = path if isinstance(path, Map) else Map.load(path, size=size)
        loc = cls(m.method)
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
            self.method.filter.reset()
        self.n_frames_ = 0

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

    def scores(self, image, velocity=None) -> np.ndarray:
        """Advance by one frame and return the filtered score row (n_reference,).

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.
        """
        self._check_fitted("scores")
        return self._scores(image, velocity)

    def _scores(self, image, velocity) -> np.ndarray:
        frontend = self.method.frontend
        frame = check_images(np.asarray(image)[None], "image", frontend.image_shape_)
        row = frontend.score_codes(frontend._encode(frame))[0]
        filt = self.method.filter
        if filt is not None:
            row = filt.step(row) if velocity is None else filt.step(row, velocity=velocity)
        self.n_frames_ += 1
        return row

    def update_batch(self, images):
        """Process consecutive frames: the front end scores them in one vectorised call, then
        the filter steps through the rows in order (as :meth:`update` frame by frame).

        Parameters
        ----------
        images : array-like, shape (n, H, W)

        Returns
        -------
        places : ndarray of int64, shape (n,)
        confidences : ndarray, shape (n,)
        scores : ndarray, shape (n, n_places)
            The filtered score rows.
        relocated : ndarray of bool, shape (n,)
            Whether the filter relocated its packet at that frame (filters that count
            relocations, such as the CANN; False otherwise).
        """
        self._check_fitted("update_batch")
        frontend = self.method.frontend
        frames = check_images(images, "images", frontend.image_shape_)
        S = frontend.score_codes(frontend._encode(frames))
        relocated = np.zeros(len(S), dtype=bool)
        filt = self.method.filter
        if filt is not None:
            out = np.empty(S.shape, dtype=np.float32)
            for i in range(len(S)):
                before = getattr(filt, "n_relocations_", 0)
                out[i] = filt.step(S[i])
                relocated[i] = getattr(filt, "n_relocations_", 0) != before
            S = out
        self.n_frames_ += len(S)
        places = np.argmax(S, axis=1)
        return places, S[np.arange(len(S)), places], S, relocated

    def update(self, image, velocity=None) -> tuple[int, float]:
        """Process one frame.

        Parameters
        ----------
        image : array-like, shape (H, W)
            Gray image in [0, 1] at the reference images' size.
        velocity : float, optional
            Places moved since the previous frame (odometry), for filters that use it.

        Returns
        -------
        place : int
            Index of the best reference place.
        confidence : float
            Its score (the filtered activity or similarity; higher = surer).

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.
        """
        self._check_fitted("update")
        row = self._scores(image, velocity)
        place = int(np.argmax(row))
        return place, float(row[place])
