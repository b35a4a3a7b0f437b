"""Compact binary codes of places (<= 64 bytes) and their Hamming similarity.

A map of 10 million places cannot hold the ``kenyon`` front end's 512-byte codes in memory
(5 GB), nor score all of them per frame.  :class:`CompactEncoder` keeps the front end's fixed
optic lobe and centring (stages 0-2 of :mod:`flyvpr.frontends.kenyon`) and replaces the
4096 Kenyon cells with ``n_bits`` (256 by default: 32 bytes per place) signs of linear
projections of the centred features:

* ``projection="pca"`` (the default): the ``n_bits`` principal directions of the reference
  traverse's centred features, turned by a random rotation so that every bit carries a
  similar share of the variance (the initialisation of iterative quantisation; Gong &
  Lazebnik, CVPR 2011);
* ``projection="simhash"``: Gaussian random directions (sign random projection; Charikar,
  STOC 2002): the Hamming distance estimates the angle between the feature vectors.

Similarity is ``1 - hamming / n_bits`` (higher = more similar, 1 for identical codes), the
score matrix contract of the rest of the library.  On the dev windows (Nordland 64x32
summer -> winter, frames 0-999 and 1000-1999, seeds 0-2; ``benchmarks/compact_codes.py``)
256 PCA bits lose 0.06 of single-frame recall@1 against the 4096-cell code and 0.002-0.005
of AUC after the CANN; 512 bits lose 0.02 and nothing after the CANN.  See
``docs/guide/large-maps.md`` for the table.

The functions :func:`hamming_similarity` and :func:`hamming_similarity_at` score one or a few
queries against a range or a list of places of a (possibly memory-mapped) code array, without
touching the rest: the cost of a windowed filter's frame does not grow with the map.
"""

from __future__ import annotations

import numpy as np

from .._validation import check_images, check_positive_int, check_random_state
from ..frontends.base import Encoder
from ..frontends.optic_lobe import OpticLobe, varying_pixels

__all__ = [
    "PROJECTIONS",
    "CompactEncoder",
    "as_words",
    "hamming_distance",
    "hamming_similarity",
    "hamming_similarity_at",
]

#: ways to turn the optic-lobe features into bits
PROJECTIONS = ("pca", "simhash")


def _kernels():
    """The compiled Hamming kernels (imports numba on first use)."""
    from . import _kernels

    return _kernels


def as_words(codes, name: str = "codes") -> np.ndarray:
    """Bit-packed codes as 64-bit words, without a copy where possible.

    Parameters
    ----------
    codes : ndarray of uint8, shape (n, n_bytes) or (n_bytes,)
        ``n_bytes`` a multiple of 8; a memory-mapped array stays memory-mapped.
    name : str
        How error messages name the array.

    Returns
    -------
    ndarray of uint64, shape (n, n_bytes // 8) (2-d also for one code)

    Raises
    ------
    TypeError
        If ``codes`` is not uint8.
    ValueError
        If it is not 1-d or 2-d, or its rows are not a multiple of 8 bytes.
    """
    codes = np.asarray(codes)
    if codes.dtype != np.uint8:
        raise TypeError(f"{name} must be bit-packed uint8 codes; got dtype {codes.dtype}")
    if codes.ndim == 1:
        codes = codes[None, :]
    if codes.ndim != 2 or codes.shape[1] == 0 or codes.shape[1] % 8:
        raise ValueError(
            f"{name} must have shape (n, n_bytes) with n_bytes a positive multiple of 8; "
            f"got {codes.shape}"
        )
    if not codes.flags.c_contiguous:
        codes = np.ascontiguousarray(codes)
    return codes.view(np.uint64)


def _pair(query_codes, codes) -> tuple[np.ndarray, np.ndarray]:
    q = as_words(query_codes, "query_codes")
    c = as_words(codes, "codes")
    if q.shape[1] != c.shape[1]:
        raise ValueError(
            f"query_codes must have {c.shape[1] * 8} bytes per code as codes; got {q.shape[1] * 8}"
        )
    return q, c


def _check_range(lo, hi, n: int) -> tuple[int, int]:
    lo = 0 if lo is None else int(lo)
    hi = n if hi is None else int(hi)
    if not 0 <= lo <= hi <= n:
        raise ValueError(f"lo and hi must satisfy 0 <= lo <= hi <= {n} (places); got {lo}, {hi}")
    return lo, hi


def hamming_distance(query_codes, codes, lo=None, hi=None) -> np.ndarray:
    """Hamming distances of queries to the places ``lo`` .. ``hi - 1`` of ``codes``.

    Parameters
    ----------
    query_codes : ndarray of uint8, shape (n_query, n_bytes) or (n_bytes,)
    codes : ndarray of uint8, shape (n_places, n_bytes)
        May be memory-mapped: only rows ``lo`` .. ``hi - 1`` are read.
    lo, hi : int, optional
        The range of places (default: all).

    Returns
    -------
    ndarray of int32, shape (n_query, hi - lo)

    Examples
    --------
    >>> codes = np.zeros((3, 8), np.uint8)
    >>> codes[1, 0], codes[2, :] = 0b111, 255
    >>> hamming_distance(codes[0], codes)
    array([[ 0,  3, 64]], dtype=int32)
    """
    q, c = _pair(query_codes, codes)
    lo, hi = _check_range(lo, hi, len(c))
    k = _kernels()
    out = np.empty((len(q), hi - lo), dtype=np.int32)
    if len(q) >= 8 and hi - lo >= 8192:
        return k.distances_batch(q, c, lo, hi, out)
    for i in range(len(q)):
        k.distances_range(q[i], c, lo, hi, out[i])
    return out


def _similarity(d: np.ndarray, n_bits: int) -> np.ndarray:
    out = d.astype(np.float32)
    out *= np.float32(-1.0 / n_bits)
    out += np.float32(1.0)
    return out


def hamming_similarity(query_codes, codes, lo=None, hi=None) -> np.ndarray:
    """``1 - hamming / n_bits`` of queries and the places ``lo`` .. ``hi - 1`` (higher = more
    similar).

    The scores a windowed filter asks for: one query against a window of places costs
    ``(hi - lo) * n_bytes / 8`` popcounts, whatever the size of the map.

    Parameters
    ----------
    query_codes : ndarray of uint8, shape (n_query, n_bytes) or (n_bytes,)
    codes : ndarray of uint8, shape (n_places, n_bytes)
    lo, hi : int, optional
        The range of places (default: all).

    Returns
    -------
    ndarray of float32, shape (n_query, hi - lo)

    Raises
    ------
    TypeError, ValueError
        For codes that are not uint8 rows of a multiple of 8 bytes, of different widths, or a
        range outside the places.

    Examples
    --------
    >>> codes = np.zeros((4, 8), np.uint8)
    >>> codes[2, :2] = 255
    >>> hamming_similarity(codes[2], codes, lo=1, hi=4)
    array([[0.75, 1.  , 0.75]], dtype=float32)
    """
    n_bits = np.asarray(codes).shape[-1] * 8
    return _similarity(hamming_distance(query_codes, codes, lo, hi), n_bits)


def hamming_similarity_at(query_codes, codes, places) -> np.ndarray:
    """``1 - hamming / n_bits`` of queries and the listed places of ``codes``.

    Parameters
    ----------
    query_codes : ndarray of uint8, shape (n_query, n_bytes) or (n_bytes,)
    codes : ndarray of uint8, shape (n_places, n_bytes)
    places : array-like of int, shape (m,)
        Place numbers in ``0 .. n_places - 1``, any order, repeats allowed.

    Returns
    -------
    ndarray of float32, shape (n_query, m)

    Raises
    ------
    ValueError
        For a place outside the map (besides the checks of :func:`hamming_similarity`).
    """
    q, c = _pair(query_codes, codes)
    idx = np.asarray(places)
    if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
        raise ValueError(f"places must be a 1-d array of integers; got {idx.dtype} {idx.shape}")
    idx = idx.astype(np.int64, copy=False)
    if idx.size and (idx.min() < 0 or idx.max() >= len(c)):
        raise ValueError(
            f"places must lie in 0 .. {len(c) - 1}; got {int(idx.min())} .. {int(idx.max())}"
        )
    k = _kernels()
    out = np.empty((len(q), len(idx)), dtype=np.int32)
    for i in range(len(q)):
        k.distances_at(q[i], c, idx, out[i])
    return _similarity(out, c.shape[1] * 64)


class CompactEncoder(Encoder):
    """The ``kenyon`` front end's optic lobe, with ``n_bits`` sign projections for codes.

    Parameters
    ----------
    n_bits : int, default 256
        Bits per code, a multiple of 64 up to 512 (64 bytes); with ``projection="pca"`` at
        most the number of optic-lobe features.
    projection : {"pca", "simhash"}, default "pca"
        How the centred features become bits (see the module's docstring).
    lcn_sigma, lcn_eps, n_orientations, wavelength, kernel_size, pool_size
        The optic lobe's settings, as :class:`~flyvpr.frontends.KenyonEncoder`'s.
    random_state : None, int or numpy.random.Generator
        Seed of the rotation (``pca``) or of the directions (``simhash``).

    Attributes
    ----------
    valid_pixels_ : ndarray of bool, shape image_shape_
        Pixels that vary along the reference traverse.
    feature_mean_ : ndarray of float32, shape (n_features_,)
        Mean optic-lobe features of the reference traverse.
    projection_ : ndarray of float32, shape (n_features_, n_bits)
        Bit ``b`` of a code is ``(features - feature_mean_) @ projection_[:, b] > 0``.
    reference_codes_ : ndarray of uint8, shape (n_reference, n_bits // 8)
        Bit-packed codes of the reference places.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((6, 32, 64), dtype=np.float32)
    >>> enc = CompactEncoder(random_state=0).fit(ref)
    >>> enc.encode(ref).shape, enc.bytes_per_place()
    ((6, 32), 32.0)
    >>> [int(i) for i in enc.score(ref).argmax(axis=1)]
    [0, 1, 2, 3, 4, 5]
    """

    name = "compact"
    #: 256 bits of signs repeat over frames that differ by sensor noise (see
    #: ``Encoder.repeats_on_noise``; the LargeLocalizer does not hold repeated rows)
    repeats_on_noise = True

    def __init__(
        self,
        n_bits=256,
        projection="pca",
        lcn_sigma=4.0,
        lcn_eps=0.05,
        n_orientations=4,
        wavelength=6.0,
        kernel_size=11,
        pool_size=4,
        random_state=None,
    ):
        self.n_bits = n_bits
        self.projection = projection
        self.lcn_sigma = lcn_sigma
        self.lcn_eps = lcn_eps
        self.n_orientations = n_orientations
        self.wavelength = wavelength
        self.kernel_size = kernel_size
        self.pool_size = pool_size
        self.random_state = random_state

    _LOBE = ("lcn_sigma", "lcn_eps", "n_orientations", "wavelength", "kernel_size", "pool_size")

    @classmethod
    def from_kenyon(cls, kenyon, reference_images, **params) -> CompactEncoder:
        """A compact encoder that shares a fitted ``kenyon`` encoder's optic lobe.

        The optic-lobe settings (with the pooling it used, ``pool_``, as ``pool_size``), the
        mask of varying pixels and the mean features are the Kenyon encoder's; the projection
        is learnt from ``reference_images`` (the Kenyon encoder's reference traverse, or a
        sample of it for a long map).

        Parameters
        ----------
        kenyon : KenyonEncoder
            Fitted.
        reference_images : array-like, shape (n, H, W)
        **params
            ``n_bits``, ``projection``, ``random_state``.

        Returns
        -------
        CompactEncoder
            Fitted, with ``reference_codes_`` the codes of ``reference_images``.

        Raises
        ------
        TypeError
            If ``kenyon`` is not a KenyonEncoder, or ``params`` names an optic-lobe setting.
        ValueError
            If ``kenyon`` has the intensity channel (``intensity=True``).
        """
        from ..frontends.kenyon import KenyonEncoder

        if not isinstance(kenyon, KenyonEncoder):
            raise TypeError(f"kenyon must be a fitted KenyonEncoder; got {type(kenyon).__name__}")
        kenyon._check_fitted()
        if kenyon.intensity:
            raise ValueError(
                "from_kenyon takes the optic lobe's Gabor features only; got a kenyon encoder "
                "with intensity=True (fit one with intensity=False for compact codes)"
            )
        fixed = sorted(set(params) & set(cls._LOBE))
        if fixed:
            raise TypeError(f"from_kenyon takes the optic lobe from kenyon; got {fixed}")
        lobe = {name: getattr(kenyon, name) for name in cls._LOBE}
        lobe["pool_size"] = kenyon.pool_  # (smaller than its pool_size under a large mask)
        enc = cls(**params, **lobe)
        images = check_images(reference_images, "reference_images", kenyon.image_shape_)
        enc._check_params()
        enc.image_shape_ = tuple(images.shape[1:])
        enc.n_reference_ = int(images.shape[0])
        enc.train_accuracy_ = None
        enc.valid_pixels_ = np.array(kenyon.valid_pixels_, dtype=bool)
        enc._setup_lobe()
        features = enc._features(images, centred=False)
        if features.shape[1] != len(kenyon.feature_mean_):
            raise ValueError("kenyon's feature_mean_ does not match its optic lobe's features")
        enc.feature_mean_ = np.array(kenyon.feature_mean_, dtype=np.float32)
        enc._fit_projection(features - enc.feature_mean_)
        return enc

    # -- saved state ------------------------------------------------------------
    #: settings a map file keeps (``random_state`` is not needed to encode)
    _SETTINGS = ("n_bits", "projection", *_LOBE)

    def state(self) -> tuple[dict, dict]:
        """The fitted encoder as JSON settings and arrays, for a map file: with
        :meth:`from_state` they encode later frames exactly as the places were encoded.

        Returns
        -------
        settings : dict
            ``params`` (the constructor's, ``random_state`` left out) and ``image_shape``.
        arrays : dict
            ``valid_pixels`` (uint8 0/1), ``feature_mean`` and ``projection`` (float32).
        """
        self._check_fitted()
        params = {name: getattr(self, name) for name in self._SETTINGS}
        for name in self._LOBE:  # plain numbers for JSON
            params[name] = (
                float(params[name])
                if name in ("lcn_sigma", "lcn_eps", "wavelength")
                else int(params[name])
            )
        params["n_bits"] = int(params["n_bits"])
        settings = {"params": params, "image_shape": [int(v) for v in self.image_shape_]}
        arrays = {
            "valid_pixels": np.asarray(self.valid_pixels_, dtype=np.uint8),
            "feature_mean": np.asarray(self.feature_mean_, dtype=np.float32),
            "projection": np.asarray(self.projection_, dtype=np.float32),
        }
        return settings, arrays

    @classmethod
    def from_state(cls, settings, arrays, reference_codes) -> CompactEncoder:
        """A fitted encoder from :meth:`state`'s settings and arrays and the places' codes.

        Raises
        ------
        ValueError
            If anything is missing or does not fit (the message names the field).
        """
        if not isinstance(settings, dict) or set(settings) != {"params", "image_shape"}:
            raise ValueError("encoder settings must hold exactly params and image_shape")
        params, shape = settings["params"], settings["image_shape"]
        if not isinstance(params, dict) or set(params) != set(cls._SETTINGS):
            raise ValueError(f"encoder params must be exactly {', '.join(cls._SETTINGS)}")
        if (
            not isinstance(shape, list)
            or len(shape) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in shape)
        ):
            raise ValueError(f"encoder image_shape must be two positive integers; got {shape!r}")
        enc = cls(**params)
        n_bits = enc._check_params()
        for name in cls._LOBE:  # the optic lobe checks its own values
            value = params[name]
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"encoder params.{name} must be a number; got {value!r}")
        try:
            enc._optic_lobe = OpticLobe(*(params[name] for name in cls._LOBE))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"encoder params: {exc}") from None
        h, w = shape
        valid = np.asarray(arrays.get("valid_pixels"))
        if valid.dtype != np.uint8 or valid.shape != (h, w) or not np.isin(valid, (0, 1)).all():
            raise ValueError(f"encoder valid_pixels must be uint8 0/1 of shape ({h}, {w})")
        enc.valid_pixels_ = valid.astype(bool)
        if not enc.valid_pixels_.any():
            raise ValueError("encoder valid_pixels has no valid pixel")
        enc._setup_lobe()
        n_features = enc._optic_lobe(np.zeros((1, h, w), np.float32), enc._valid).shape[1]
        for name, want in (("feature_mean", (n_features,)), ("projection", (n_features, n_bits))):
            a = np.asarray(arrays.get(name))
            if a.dtype != np.float32 or a.shape != want or not np.isfinite(a).all():
                raise ValueError(f"encoder {name} must be finite float32 of shape {want}")
        codes = np.asarray(reference_codes)  # (a memory map's view: nothing read)
        if (
            codes.dtype != np.uint8
            or codes.ndim != 2
            or codes.shape[1] * 8 != n_bits
            or not len(codes)
        ):
            raise ValueError(f"reference codes must be uint8 of shape (n, {n_bits // 8}), n >= 1")
        enc.feature_mean_ = np.asarray(arrays["feature_mean"])
        enc.projection_ = np.ascontiguousarray(arrays["projection"])
        enc.n_features_ = int(n_features)
        enc.reference_codes_ = codes
        enc.image_shape_ = (h, w)
        enc.n_reference_ = int(len(codes))
        enc.train_accuracy_ = None
        return enc

    def max_bits(self, size) -> int | None:
        """The most bits a ``projection='pca'`` encoder can have on images of ``size`` (H, W):
        the optic lobe's features there (fewer under a mask of static pixels); None for
        ``simhash``, which takes any number."""
        if self.projection == "simhash":
            return None
        lobe = OpticLobe(*(getattr(self, name) for name in self._LOBE))
        return lobe.n_features(*size)

    # -- fitting ----------------------------------------------------------------
    def _check_params(self) -> int:
        n_bits = check_positive_int(self.n_bits, "n_bits", minimum=64)
        if n_bits % 64 or n_bits > 512:
            raise ValueError(f"n_bits must be a multiple of 64 up to 512; got {n_bits}")
        if self.projection not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}; got {self.projection!r}")
        return n_bits

    def _setup_lobe(self) -> None:
        self._optic_lobe = OpticLobe(*(getattr(self, name) for name in self._LOBE))
        valid = self.valid_pixels_
        self._valid = None if valid.all() else np.ascontiguousarray(valid)

    def _features(self, images: np.ndarray, centred: bool = True) -> np.ndarray:
        features = self._optic_lobe(images, self._valid)
        return features - self.feature_mean_ if centred else features

    def _fit(self, images: np.ndarray) -> None:
        self._check_params()
        self.valid_pixels_ = varying_pixels(images)
        self._setup_lobe()
        features = self._features(images, centred=False)
        self.feature_mean_ = features.mean(axis=0).astype(np.float32)
        self._fit_projection(features - self.feature_mean_)

    def _fit_projection(self, centred: np.ndarray) -> None:
        n_bits = self._check_params()
        n_features = centred.shape[1]
        rng = check_random_state(self.random_state)
        if self.projection == "simhash":
            proj = rng.standard_normal((n_features, n_bits))
        else:
            if n_bits > n_features:
                raise ValueError(
                    f"n_bits must be <= the number of optic-lobe features ({n_features}) with "
                    f"projection='pca'; got {n_bits}"
                )
            x = centred.astype(np.float64)
            _, vectors = np.linalg.eigh(x.T @ x)  # ascending eigenvalues
            top = vectors[:, ::-1][:, :n_bits]
            # a random rotation spreads the variance over the bits (ITQ's initialisation)
            rotation, _ = np.linalg.qr(rng.standard_normal((n_bits, n_bits)))
            proj = top @ rotation
        self.n_features_ = int(n_features)
        self.projection_ = np.ascontiguousarray(proj, dtype=np.float32)
        self.reference_codes_ = self._pack(centred)

    def _pack(self, centred: np.ndarray) -> np.ndarray:
        return np.packbits(centred @ self.projection_ > 0, axis=1)

    # -- encoding and scoring ------------------------------------------------------
    def _encode(self, images: np.ndarray) -> np.ndarray:
        return self._pack(self._features(images))

    def _check_codes(self, codes, name: str = "codes") -> np.ndarray:
        codes = np.asarray(codes)
        n_bytes = self.reference_codes_.shape[1]
        if codes.dtype != np.uint8 or codes.ndim != 2 or codes.shape[1] != n_bytes:
            raise ValueError(
                f"{name} must be bit-packed uint8 of shape (N, {n_bytes}) as returned by "
                f"encode; got {codes.dtype} of shape {codes.shape}"
            )
        return codes

    def _score(self, codes: np.ndarray) -> np.ndarray:
        return hamming_similarity(self._check_codes(codes), self.reference_codes_)

    def score_range(self, codes, lo: int, hi: int) -> np.ndarray:
        """Scores of encoded queries against the reference places ``lo`` .. ``hi - 1`` only.

        Returns
        -------
        ndarray of float32, shape (n_query, hi - lo)
            Equal to ``score_codes(codes)[:, lo:hi]``.
        """
        self._check_fitted()
        return hamming_similarity(self._check_codes(codes), self.reference_codes_, lo, hi)

    def _map_nbytes(self) -> int:
        # one code per place; the projection is shared by all places
        return int(self.reference_codes_.nbytes)

    def _footprint(self) -> dict:
        return {
            "layers": 2,  # optic lobe, sign projections
            "params": 0,  # PCA directions are statistics of the traverse, nothing is trained
            "neurons": int(self.n_features_ + self.projection_.shape[1]),
        }
