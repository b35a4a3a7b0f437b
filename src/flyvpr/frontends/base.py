"""Base class of single-frame encoders (front ends).

The base class owns the public calls and their validation; a subclass fills
``_fit``, ``_encode`` and ``_score``.  Conventions follow scikit-learn:
``__init__`` only stores its keyword arguments, ``fit`` sets attributes ending
in ``_`` and returns ``self``, and calling ``encode``/``score`` before ``fit``
raises :class:`~flyvpr.NotFittedError`.
"""

from __future__ import annotations

import numpy as np

from .._params import ParamsMixin
from .._validation import NotFittedError, ScalarSpec, check_images

__all__ = ["Encoder"]


class Encoder(ParamsMixin):
    """A single-frame encoder: reference images in, a (n_query, n_reference) score matrix out.

    Attributes set by ``fit``
    -------------------------
    image_shape_ : (int, int)
        (H, W) of the reference images; queries must match it.
    n_reference_ : int
        Number of reference places (columns of the score matrix).
    train_accuracy_ : float or None
        Accuracy on the reference images after training, ``None`` where
        nothing is trained.
    """

    #: registry name, set by subclasses
    name = "encoder"
    #: whether two camera frames that differ by sensor noise only can get exactly the same
    #: scores (a binary hash of a small image: FlyHash, FlyNet).  A filter then cannot read a
    #: repeated score row as a repeated frame (see ``CANN``'s ``hold_repeats``).
    repeats_on_noise = False

    # -- public calls ---------------------------------------------------------
    def fit(self, reference_images) -> Encoder:
        """Learn from the reference traverse, one place per image.

        Parameters
        ----------
        reference_images : array-like, shape (n_reference, H, W)
            Gray images in [0, 1].

        Returns
        -------
        self
        """
        return self._fit_checked(reference_images, None)

    def _fit_checked(self, reference_images, map_chunks) -> Encoder:
        """:meth:`fit`, with the per-image work of encoders that can split it run through
        ``map_chunks`` (see :class:`flyvpr._chunks.ChunkRunner`) when it is not None."""
        images = check_images(reference_images, "reference_images")
        self.image_shape_ = tuple(images.shape[1:])
        self.n_reference_ = int(images.shape[0])
        self.train_accuracy_: float | None = None
        if map_chunks is None:
            self._fit(images)
        else:
            self._fit_chunks(images, map_chunks)
        return self

    def encode(self, images) -> np.ndarray:
        """Encode images into the representation the scores are computed from.

        Returns
        -------
        ndarray, shape (N, ...)
        """
        self._check_fitted()
        return self._encode(check_images(images, "images", self.image_shape_))

    def score(self, query_images) -> np.ndarray:
        """Score every query image against every reference place.

        Returns
        -------
        S : ndarray, shape (n_query, n_reference)
            Higher means more similar.
        """
        self._check_fitted()
        images = check_images(query_images, "query_images", self.image_shape_)
        return self.score_codes(self._encode(images))

    def score_codes(self, codes) -> np.ndarray:
        """Score already-encoded queries (output of :meth:`encode`)."""
        self._check_fitted()
        return self._score(np.asarray(codes))

    def footprint(self) -> dict:
        """Model size as in the paper's footprint table: layers, params, neurons."""
        self._check_fitted()
        return self._footprint()

    def bytes_per_place(self) -> float:
        """Bytes per reference place the fitted encoder stores for matching (the map).

        Only storage that grows with the number of reference places counts: what the encoder
        keeps for each place to score queries against (a code, a descriptor, a column of a
        per-place classifier), divided by the number of places.  Weights shared by all places
        (a fixed projection, feature layers, a pretrained backbone) are excluded: they do not
        grow with the route.  Each encoder documents what it counts.

        Returns
        -------
        float
            Bytes per reference place, in the representation the encoder stores.

        Raises
        ------
        NotFittedError
            Before :meth:`fit`.

        Examples
        --------
        >>> import numpy as np
        >>> from flyvpr.frontends import PixelsEncoder
        >>> ref = np.random.default_rng(0).random((5, 32, 64), dtype=np.float32)
        >>> PixelsEncoder().fit(ref).bytes_per_place()  # 2048 float32 values per place
        8192.0
        """
        self._check_fitted()
        return float(self._map_nbytes()) / self.n_reference_

    # -- saved state (see flyvpr.modelio) --------------------------------------
    #: fitted attributes written to model files, besides the ones every encoder has
    _state_names: tuple[str, ...] = ()

    def _get_state(self) -> dict:
        """Fitted attributes to save: arrays, scalars or nested encoders."""
        self._check_fitted()
        state = {
            "image_shape_": tuple(self.image_shape_),
            "n_reference_": self.n_reference_,
            "train_accuracy_": self.train_accuracy_,
        }
        state.update({name: getattr(self, name) for name in self._state_names})
        return state

    #: saved scalar attributes and their checks (model files are validated against them)
    _state_scalars: dict = {
        "image_shape_": ScalarSpec("shape"),
        "n_reference_": ScalarSpec("int", low=1),
        "train_accuracy_": ScalarSpec("float", low=0.0, high=1.0, optional=True),
    }

    def _state_arrays(self, scalars: dict) -> dict | None:
        """Expected arrays and nested parts of the saved state, given its checked scalars.

        Returns ``name -> ArraySpec or PartSpec`` (a name ending in ``*`` matches every
        name with that prefix), or None when the class declares nothing: its model files then
        get only the generic checks.  Called on an instance built with the saved parameters;
        raises ValueError when the scalars and parameters contradict each other.
        """
        return None

    def _set_state(self, state: dict) -> None:
        """Restore what :meth:`_get_state` returned."""
        for name, value in state.items():
            setattr(self, name, value)
        self.image_shape_ = tuple(self.image_shape_)

    # -- hooks ----------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "n_reference_"):
            raise NotFittedError(
                f"this {type(self).__name__} is not fitted yet; call fit(reference_images) first"
            )

    def _fit(self, images: np.ndarray) -> None:
        raise NotImplementedError

    #: True where :meth:`_fit_chunks` spreads its per-image work over ``map_chunks``
    _fits_in_chunks = False

    def _fit_chunks(self, images: np.ndarray, map_chunks) -> None:
        """:meth:`_fit` with its per-image work done by ``map_chunks(func, rows, what)``.

        An encoder that sets ``_fits_in_chunks`` learns what needs the whole traverse here,
        then hands functions of a block of images, each image computed on its own, to
        ``map_chunks``: the result must be the bytes :meth:`_fit` gives.  The default fits in
        this process.
        """
        self._fit(images)

    def _encode(self, images: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _score(self, codes: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _footprint(self) -> dict:
        raise NotImplementedError

    def _map_nbytes(self) -> int:
        """Total bytes of the per-place storage of :meth:`bytes_per_place` (all places)."""
        raise NotImplementedError(
            f"{type(self).__name__} does not report the bytes it stores per place"
        )
