"""Kenyon: a fixed optic lobe and a Kenyon-cell expansion with winner-take-all (``kenyon``).

A fly-inspired front end that carries more of the place signal than the paper's FlyNet, built
from fixed parts only (nothing is trained):

0. **Static pixels**: ``fit`` marks the pixels that do not vary along the reference traverse
   (``flyvpr.frontends.optic_lobe.varying_pixels``: the black surround of a fisheye lens, the
   robot's chassis, a burnt-in overlay).  They carry no information about the place, but
   their edges with the scene would weigh in every code.  The optic lobe then normalises over
   the varying pixels only (the static ones' values never enter) and drops the features that
   are 0 in every image under the mask.  On frames without static pixels (every pixel varies)
   nothing changes: the codes are bit-identical to those without the mask.  Where fewer than
   half of the pixels vary, the pooling cells shrink so that the varying part of the frame
   gives about as many cells as a whole frame (``mask_pooling``,
   :func:`~flyvpr.frontends.optic_lobe.pool_for_mask`: 2x2 behind a fisheye's disc).
1. **Optic lobe** (``flyvpr.frontends.optic_lobe.optic_lobe``): local contrast
   normalisation, Gabor energy at 4 orientations, 4x4 max pooling, per-image z-score: 512
   features at 32x64 (under a mask of static pixels, those that can vary: fewer, or more where
   the cells shrink, 1376 behind a fisheye's disc).
2. **Centring**: the mean feature vector of the reference traverse is subtracted (``fit``
   takes that and, for the mask of static pixels, each pixel's standard deviation).  Features
   that are high in every frame (a logo burnt into the video, the horizon) would otherwise win
   the competition below in every frame and carry no information about the place.
3. **Kenyon-cell expansion** as in the fly's mushroom body (Dasgupta, Stevens & Navlakha,
   Science 2017): ``n_kenyon`` Kenyon cells (KCs), each summing ``n_inputs`` distinct features
   through fixed binary weights, the connections balanced so that every feature feeds about the
   same number of KCs (see :func:`balanced_connections`: 77-83 with the defaults, most 80);
   then winner-take-all: the ``k = round(active_ratio * n_kenyon)`` most active KCs fire
   (ties: lower index).  With ``n_projections > 1`` the KCs are split into that many
   independent populations, each with its own winner-take-all.
4. **Matching**: the similarity of a query and a place is the number of KCs active in both
   codes, divided by ``k`` (1 for identical codes), computed through an inverted index (for
   each KC, the places where it fires, as 16-bit numbers) by numba kernels -- parallel over
   the queries of a batch, or for a streamed frame one query counting in small integers
   that stay in cache: the work per query is the total length of the query's ``k`` lists,
   about ``n_reference * k * active_ratio``.

Codes are bit-packed: ``n_kenyon / 8`` bytes per place (512 with the defaults, 1/16 of the
8192 bytes of ``pixels``).

Defaults and the data that chose them (``nordland_64x32`` summer -> winter, frames 0-999 and
1000-1999, and ``nordland_64x32_viewpoint`` frames 0-999, all +cann, tolerance 20; never
frames 2000-2399): the Gaussian contrast normalisation (``lcn_sigma=4``) beat SeqSLAM's
8x8 patch normalisation on the viewpoint set (AUC 0.977 vs 0.934 with cosine matching of the
features, with the CANN of the time); the wavelength 6 beat 4 and 8; max beat mean pooling on
frames 0-999; 4096 KCs at 5% active kept the Nordland windows' accuracy, where 1-3% active
scored 0.90-0.94 on the viewpoint set; 10 inputs per KC beat 3, 6 and 16 on the mean of the
three sets (seeds 0-2); balanced connections narrowed the spread over seeds.  See
``docs/guide/fly-frontend.md`` and ``benchmarks/fly_ablation.py``.
"""

from __future__ import annotations

import numpy as np
from scipy import sparse

from .._chunks import in_process
from .._validation import (
    ArraySpec,
    ScalarSpec,
    check_fraction,
    check_images,
    check_memory,
    check_positive_int,
    check_random_state,
)
from .base import Encoder
from .optic_lobe import OpticLobe, _kernels, pool_for_mask, varying_pixels

__all__ = ["KenyonEncoder", "balanced_connections", "code_overlap"]

#: batches with fewer queries run the serial kernel: for one streamed frame, waking threads
#: costs more than it saves (and much more on a loaded machine)
_PARALLEL_MIN_QUERIES = 8

#: places per block when indexing: 4096 x 4096 unpacked bits are 16 MiB
_BLOCK = 4096

#: places per chunk of the inverted index: place numbers are stored as uint16 offsets within
#: their chunk, half the memory traffic of int32 (scoring one query reads its lists from main
#: memory, so that about halves its time)
_CHUNK = 1 << 16


def balanced_connections(n_kenyon: int, n_features: int, n_inputs: int, random_state=None):
    """Draw the inputs of every Kenyon cell: ``n_inputs`` distinct features per cell.

    The ``n_kenyon * n_inputs`` connections are consecutive random permutations of the
    features cut into rows, so every feature feeds ``floor`` or ``ceil`` of
    ``n_kenyon * n_inputs / n_features`` cells but for the rows redrawn: a row that would
    repeat a feature (where two permutations meet) is redrawn as a uniform random subset.
    With the defaults (4096 cells, 10 inputs, 512 features) up to a few rows are, and a
    feature feeds 77-83 cells (seeds 0-9; most 80, all 80 for seed 6).

    Returns
    -------
    ndarray of int32, shape (n_kenyon, n_inputs)
        Sorted indices per row.

    Raises
    ------
    ValueError, TypeError
        For counts that are not positive ints, or ``n_inputs > n_features``.
    flyvpr._validation.InsufficientMemoryError
        If the connections would not fit in memory; raised before drawing them.
    """
    rng = check_random_state(random_state)
    n_kenyon = check_positive_int(n_kenyon, "n_kenyon")
    n_inputs = check_positive_int(n_inputs, "n_inputs")
    if n_inputs > n_features:
        raise ValueError(
            f"n_inputs must be <= the number of optic-lobe features ({n_features}); got {n_inputs}"
        )
    # the permutations (int64, drawn one by one, then joined), the sorted rows and the result
    check_memory(
        32 * n_kenyon * n_inputs + 16 * n_features, f"n_kenyon={n_kenyon} with n_inputs={n_inputs}"
    )
    n_perm = -(-n_kenyon * n_inputs // n_features)
    flat = np.concatenate([rng.permutation(n_features) for _ in range(n_perm)])
    rows = np.sort(flat[: n_kenyon * n_inputs].reshape(n_kenyon, n_inputs), axis=1)
    repeated = np.flatnonzero((np.diff(rows, axis=1) == 0).any(axis=1))
    for i in repeated:  # rare: at most one row per pair of permutations
        rows[i] = np.sort(rng.choice(n_features, n_inputs, replace=False))
    return rows.astype(np.int32)


def _inverted_index(packed: np.ndarray, n_bits: int, chunk: int = _CHUNK) -> tuple:
    """For each KC, the places where it fires, in chunks of ``chunk`` (<= 65,536) places.

    ``packed``: bit-packed codes (n_places, ceil(n_bits / 8)), unpacked a block at a time.

    Returns
    -------
    indptr : ndarray of int64, shape (n_chunks, n_bits + 1)
        The places of KC ``b`` in chunk ``c`` are ``places[indptr[c, b] : indptr[c, b + 1]]``.
    places : ndarray of uint16
        Offsets within the chunk, ascending per list.
    """
    indptr, places, base = [], [], 0
    for start in range(0, len(packed), chunk):
        stop = min(start + chunk, len(packed))
        parts = [
            sparse.csr_matrix(
                np.unpackbits(packed[i : min(i + _BLOCK, stop)], axis=1, count=n_bits)
            )
            for i in range(start, stop, _BLOCK)
        ]
        csc = sparse.vstack(parts, format="csc")
        indptr.append(csc.indptr.astype(np.int64) + base)
        places.append(csc.indices.astype(np.uint16))
        base += csc.nnz
    return np.stack(indptr), np.concatenate(places)


def code_overlap(query_codes, reference_codes) -> np.ndarray:
    """Number of active bits two binary codes share, for every query and reference.

    Parameters
    ----------
    query_codes : array-like of bool, shape (n_query, n_bits)
    reference_codes : array-like of bool, shape (n_reference, n_bits)

    Returns
    -------
    ndarray of int32, shape (n_query, n_reference)

    Examples
    --------
    >>> code_overlap([[1, 1, 0, 0]], [[1, 0, 1, 0], [1, 1, 0, 0]])
    array([[1, 2]], dtype=int32)
    """
    q = np.asarray(query_codes).astype(bool)
    r = np.asarray(reference_codes).astype(bool)
    if q.ndim != 2 or r.ndim != 2 or q.shape[1] != r.shape[1]:
        raise ValueError(
            "query_codes and reference_codes must be 2-d with the same number of bits; "
            f"got shapes {q.shape} and {r.shape}"
        )
    indptr, places = _inverted_index(np.packbits(r, axis=1), r.shape[1])
    overlap = _overlap_packed(np.packbits(q, axis=1), indptr, places, len(r), 1.0)
    return overlap.astype(np.int32)


def _overlap_packed(packed, indptr, places, n_reference: int, scale: float, chunk: int = _CHUNK):
    """``scale`` x the overlap of bit-packed queries with the codes indexed in chunks of
    ``chunk`` places (:func:`_inverted_index`), float32."""
    packed = np.ascontiguousarray(packed)
    out = np.empty((len(packed), n_reference), dtype=np.float32)
    scale32 = np.float32(scale)
    if len(packed) >= _PARALLEL_MIN_QUERIES:
        return _kernels().overlap_parallel(packed, indptr, places, chunk, scale32, out)
    # A few queries (a streamed frame): one at a time, without waking threads
    kernel = _kernels().overlap_counts
    for i, query in enumerate(packed):
        kernel(query, indptr, places, chunk, scale32, out[i])
    return out


class KenyonEncoder(Encoder):
    """Fixed optic lobe + Kenyon-cell expansion with winner-take-all, scored by code overlap.

    Parameters
    ----------
    n_kenyon : int, default 4096
        Number of Kenyon cells (bits per code); a multiple of 8 and of ``n_projections``.
    n_inputs : int, default 10
        Optic-lobe features summed by each Kenyon cell.
    active_ratio : float, default 0.05
        Share of Kenyon cells that fire per image (the fly's 5%).
    n_projections : int, default 1
        Independent Kenyon-cell populations, each with its own winner-take-all.
    lcn_sigma, lcn_eps, n_orientations, wavelength, kernel_size, pool_size
        The optic lobe's settings, see ``flyvpr.frontends.optic_lobe.optic_lobe``: ``lcn_sigma``
        in [0.25, 1e6] pixels, ``lcn_eps`` in [1e-8, 1], ``wavelength`` in [2, 1e6] pixels,
        ``kernel_size`` odd and at least 3.
    mask_pooling : bool, default True
        Where fewer than half of the pixels vary along the reference traverse, pool over
        smaller cells, so that the varying pixels give about as many cells as a whole frame
        (:func:`~flyvpr.frontends.optic_lobe.pool_for_mask`; ``pool_`` is the side used).
        Behind a fisheye's disc (41% of a 32x64 frame) the cells are 2x2: 1376 features
        instead of 368.  A frame whose pixels all vary pools over ``pool_size`` either way.
        Model files saved before it load without it.
    intensity : bool, default False
        Also feed the Kenyon cells the intensity channel: the contrast-normalised image summed
        over each pooling cell (static pixels count 0, so a cell at the mask's edge weighs by
        the share of it that varies; one feature per cell with a valid pixel, 128 at 32x64),
        z-scored per image like the Gabor features.  It keeps the layout of light and dark
        that the phase-blind, max-pooled Gabor energies lose.  Opt-in: measured by
        ``benchmarks/kenyon_intensity.py`` (see the fly front-end guide), it costs a second
        contrast normalisation per image; ``CompactEncoder.from_kenyon`` does not take it.
    random_state : None, int or numpy.random.Generator
        Seed of the connections.

    Attributes
    ----------
    valid_pixels_ : ndarray of bool, shape image_shape_
        Pixels that vary along the reference traverse (all True for ordinary frames); the
        optic lobe looks at these only.
    pool_ : int
        Side of the pooling cells used: ``pool_size``, or with ``mask_pooling`` a divisor of
        it chosen from ``valid_pixels_``.
    connections_ : ndarray of int32, shape (n_kenyon, n_inputs)
        Features summed by each Kenyon cell.
    feature_mean_ : ndarray of float32, shape (n_features_,)
        Mean optic-lobe features of the reference traverse.
    n_features_, n_active_ : int
        Optic-lobe features per image that the Kenyon cells read (those that can vary under
        ``valid_pixels_``, see ``OpticLobe.kept_features``); active Kenyon cells per code.
    reference_codes_ : ndarray of uint8, shape (n_reference, n_kenyon // 8)
        Bit-packed codes of the reference places (the map).

    Raises
    ------
    ValueError
        From ``fit``, for a parameter out of range, or where the varying pixels leave fewer
        than ``n_inputs`` optic-lobe features; ``flyvpr._validation.InsufficientMemoryError``
        (a ValueError) where the Kenyon cells (``n_kenyon``, ``n_inputs``) or the optic lobe
        (``n_orientations``, ``kernel_size``, ``lcn_sigma``) would not fit in memory, before
        anything of that size is allocated.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.random((5, 32, 64), dtype=np.float32)
    >>> enc = KenyonEncoder(random_state=0).fit(ref)
    >>> enc.encode(ref).shape, enc.bytes_per_place()
    ((5, 512), 512.0)
    >>> [int(i) for i in enc.score(ref).argmax(axis=1)]
    [0, 1, 2, 3, 4]

    A static border of 12 black columns on each side: the outermost column of cells on each
    side has no varying pixel within reach of the Gabor kernels (5 pixels), so its features
    (2 x 8 cells x 4 orientations) are dropped; the border's value no longer matters.

    >>> ref[:, :, :12] = ref[:, :, -12:] = 0.0
    >>> enc = KenyonEncoder(random_state=0).fit(ref)
    >>> int(enc.valid_pixels_.sum()), enc.n_features_
    (1280, 448)
    >>> grey = ref.copy()
    >>> grey[:, :, :12] = grey[:, :, -12:] = 0.5
    >>> bool((enc.encode(grey) == enc.encode(ref)).all())
    True
    """

    name = "kenyon"
    #: model files written before the intensity channel or the mask's pooling load without it
    _added_params = ("intensity", "mask_pooling")
    #: (and with ``pool_`` = ``pool_size``)
    _added_state = ("pool_",)

    def __init__(
        self,
        n_kenyon=4096,
        n_inputs=10,
        active_ratio=0.05,
        n_projections=1,
        lcn_sigma=4.0,
        lcn_eps=0.05,
        n_orientations=4,
        wavelength=6.0,
        kernel_size=11,
        pool_size=4,
        intensity=False,
        random_state=None,
        mask_pooling=True,
    ):
        self.n_kenyon = n_kenyon
        self.n_inputs = n_inputs
        self.active_ratio = active_ratio
        self.n_projections = n_projections
        self.lcn_sigma = lcn_sigma
        self.lcn_eps = lcn_eps
        self.n_orientations = n_orientations
        self.wavelength = wavelength
        self.kernel_size = kernel_size
        self.pool_size = pool_size
        self.intensity = intensity
        self.random_state = random_state
        self.mask_pooling = mask_pooling

    # -- set-up ---------------------------------------------------------------
    def _check_layout(self) -> tuple[int, int]:
        """(n_kenyon, n_projections), checked against each other."""
        n_kenyon = check_positive_int(self.n_kenyon, "n_kenyon", minimum=8)
        n_proj = check_positive_int(self.n_projections, "n_projections")
        if n_kenyon % 8 or n_kenyon % n_proj:
            raise ValueError(
                f"n_kenyon must be a multiple of 8 and of n_projections ({n_proj}); got {n_kenyon}"
            )
        return n_kenyon, n_proj

    def _make_lobe(self, pool=None) -> OpticLobe:
        """The optic lobe with the fitted pooling ``pool_`` (``pool``, or ``pool_size``,
        before it is known)."""
        if pool is None:
            pool = getattr(self, "pool_", self.pool_size)
        return OpticLobe(
            self.lcn_sigma,
            self.lcn_eps,
            self.n_orientations,
            self.wavelength,
            self.kernel_size,
            pool,
        )

    def _check_mask_pooling(self) -> bool:
        if not isinstance(self.mask_pooling, (bool, np.bool_)):
            raise TypeError(
                f"mask_pooling must be True or False; got {type(self.mask_pooling).__name__}"
            )
        return bool(self.mask_pooling)

    def _check_intensity(self) -> bool:
        if not isinstance(self.intensity, (bool, np.bool_)):
            raise TypeError(f"intensity must be True or False; got {type(self.intensity).__name__}")
        return bool(self.intensity)

    def _lobe(self, images: np.ndarray) -> np.ndarray:
        if getattr(self, "_optic_lobe", None) is None:
            self._optic_lobe = self._make_lobe()
            self._set_valid()
        features = self._optic_lobe(images, self._valid)
        if not self.intensity:
            return features
        return np.concatenate([features, self._intensity(images)], axis=1)

    def _intensity_cells(self) -> np.ndarray:
        """The pooling cells with a valid pixel: bool, row-major over the (H / pool, W / pool)
        grid (all of them where every pixel is valid)."""
        h, w = self.image_shape_
        self._optic_lobe.n_features(h, w)  # pool_size divides the image size
        p = self._optic_lobe.pool
        valid = np.ones((h, w), bool) if self._valid is None else self._valid
        return valid.reshape(h // p, p, w // p, p).any(axis=(1, 3)).ravel()

    def _intensity(self, images: np.ndarray) -> np.ndarray:
        """The intensity channel: the contrast-normalised image summed over each pooling cell
        (0 at static pixels: a cell at the mask's edge weighs by the share it sees), z-scored
        per image over the cells with a valid pixel (all 0 for a blank image)."""
        lobe = self._optic_lobe
        n, h, w = images.shape
        p = lobe.pool
        x = lobe.normalise(images, self._valid)
        cells = x.reshape(n, h // p, p, w // p, p).sum(axis=(2, 4), dtype=np.float64)
        cells = cells.reshape(n, -1)[:, self._cells]
        cells -= cells.mean(axis=1, keepdims=True)
        spread = cells.std(axis=1, keepdims=True)
        np.divide(cells, spread, out=cells, where=spread > 0)
        return cells.astype(np.float32)

    _fits_in_chunks = True

    def _fit(self, images: np.ndarray) -> None:
        self._fit_chunks(images, in_process)

    def _fit_chunks(self, images: np.ndarray, map_chunks) -> None:
        # the mask and the feature mean need the whole traverse; the optic lobe and the codes
        # are computed image by image (each image's bytes do not depend on its chunk)
        n_kenyon, n_proj = self._check_layout()
        ratio = check_fraction(self.active_ratio, "active_ratio")
        n_in = check_positive_int(self.n_inputs, "n_inputs")
        # connections (int32, drawn as int64 permutations) and, while indexing, one block of
        # places' unpacked bits (a byte each) with its sparse copies (a few bytes per active
        # bit): 9 bytes per bit bounds both
        check_memory(
            n_kenyon * n_in * 16 + min(len(images), _BLOCK) * n_kenyon * 9,
            f"n_kenyon={n_kenyon} with n_inputs={n_in}",
        )
        self._optic_lobe = self._make_lobe(self.pool_size)  # (checks the settings)
        self.valid_pixels_ = varying_pixels(images)
        self.pool_ = self._optic_lobe.pool
        if self._check_mask_pooling():
            self.pool_ = pool_for_mask(self.valid_pixels_, self.pool_)
            if self.pool_ != self._optic_lobe.pool:
                self._optic_lobe = self._make_lobe(self.pool_)
        self._set_valid()
        n_kept = self._n_kept()
        if n_in > n_kept:
            n_cells = n_kept - self._n_gabor()
            plus = f", plus {n_cells} intensity cells" if n_cells else ""
            raise ValueError(
                f"n_inputs must be <= the number of optic-lobe features ({self._n_gabor()} of "
                f"{self._optic_lobe.n_features(*self.image_shape_)} see pixels that vary along "
                f"the reference traverse{plus}); got {n_in}"
            )
        features = map_chunks(self._lobe, images, "optic lobe")
        self.n_features_ = int(features.shape[1])
        self.n_active_ = max(n_proj, int(round(ratio * n_kenyon / n_proj)) * n_proj)
        self.connections_ = balanced_connections(
            n_kenyon, self.n_features_, self.n_inputs, check_random_state(self.random_state)
        )
        self.feature_mean_ = features.mean(axis=0).astype(np.float32)
        self._prepare()
        self.reference_codes_ = map_chunks(self._codes, features, "kenyon codes")
        self._index()

    def _set_valid(self) -> None:
        """The mask as the optic lobe takes it: None where every pixel is valid (the unmasked
        computation, bit for bit), else C-ordered."""
        valid = self.valid_pixels_
        self._valid = None if valid.all() else np.ascontiguousarray(valid)
        self._cells = self._intensity_cells()

    def _n_gabor(self) -> int:
        """Gabor features of the optic lobe that see a valid pixel."""
        if self._valid is None:
            return self._optic_lobe.n_features(*self.image_shape_)
        return len(self._optic_lobe.kept_features(self._valid))

    def _n_kept(self) -> int:
        """Features the Kenyon cells read: the Gabor features under the mask and the
        intensity channel's cells."""
        n = self._n_gabor()
        if self._check_intensity():
            n += int(self._cells.sum())
        return n

    def _prepare(self) -> None:
        """The connections as the compiled kernels read them: C-ordered uint32 (unsigned
        indices spare the kernel numba's negative-index check: about twice as fast)."""
        self._connections = np.ascontiguousarray(self.connections_, dtype=np.uint32)

    def _index(self) -> None:
        n_bits = self.connections_.shape[0]
        self._indptr, self._places = _inverted_index(self.reference_codes_, n_bits)

    # -- encoding and matching -------------------------------------------------
    def kenyon_activity(self, images) -> np.ndarray:
        """Summed input of every Kenyon cell, shape (N, n_kenyon), float32 (before the WTA)."""
        self._check_fitted()
        features = self._lobe(check_images(images, "images", self.image_shape_))
        return self._activity(features)

    def _check_width(self, features: np.ndarray) -> None:
        # the compiled kernels index the features by the connections without a bounds check
        if features.shape[1] != self.feature_mean_.shape[0]:
            raise ValueError(
                f"the optic lobe now gives {features.shape[1]} features and the Kenyon cells "
                f"were fitted on {self.feature_mean_.shape[0]}: a setting changed since fit "
                "(e.g. intensity); fit again"
            )

    def _activity(self, features: np.ndarray) -> np.ndarray:
        self._check_width(features)
        # float32 sums in the order of the sorted connections (as a CSR matrix product would)
        out = np.empty((len(features), self._connections.shape[0]), dtype=np.float32)
        return _kernels().kenyon_activity(features, self.feature_mean_, self._connections, out)

    def _codes(self, features: np.ndarray) -> np.ndarray:
        # activity, winner-take-all per population and bit packing in one compiled pass per
        # image: nothing of size (N, n_kenyon) is materialised
        self._check_width(features)
        n_kenyon = self._connections.shape[0]
        n_proj = self.n_projections
        out = np.empty((len(features), n_kenyon // 8), dtype=np.uint8)
        return _kernels().kenyon_codes(
            features, self.feature_mean_, self._connections, n_proj, self.n_active_ // n_proj, out
        )

    def _encode(self, images: np.ndarray) -> np.ndarray:
        return self._codes(self._lobe(images))

    def _unpack(self, codes: np.ndarray) -> np.ndarray:
        return np.unpackbits(codes, axis=1, count=self.connections_.shape[0]).astype(bool)

    def _score(self, codes: np.ndarray) -> np.ndarray:
        n_bytes = self.reference_codes_.shape[1]
        if codes.ndim != 2 or codes.shape[1] != n_bytes or codes.dtype != np.uint8:
            raise ValueError(
                f"codes must be bit-packed uint8 of shape (N, {n_bytes}) as returned by "
                f"encode; got {codes.dtype} of shape {codes.shape}"
            )
        return _overlap_packed(
            codes, self._indptr, self._places, self.n_reference_, 1.0 / self.n_active_
        )

    # -- saved state -------------------------------------------------------------
    _state_names = (
        "pool_",
        "n_features_",
        "n_active_",
        "valid_pixels_",
        "connections_",
        "feature_mean_",
        "reference_codes_",
    )
    _state_scalars = {
        **Encoder._state_scalars,
        "pool_": ScalarSpec("int", low=1),
        "n_features_": ScalarSpec("int", low=1),
        "n_active_": ScalarSpec("int", low=1),
    }

    def _state_arrays(self, scalars: dict) -> dict:
        n_kenyon, _ = self._check_layout()
        n_in = check_positive_int(self.n_inputs, "n_inputs")
        if scalars["n_active_"] > n_kenyon:
            raise ValueError(f"n_active_ must be <= n_kenyon = {n_kenyon}")
        return {
            # optional (a name ending in * need not be in the file): model files written
            # before the mask existed have none, and load as fitted, with every pixel valid
            "valid_pixels_*": ArraySpec("bool", tuple(scalars["image_shape_"])),
            "connections_": ArraySpec("int32", (n_kenyon, n_in)),
            "feature_mean_": ArraySpec("float32", (scalars["n_features_"],)),
            "reference_codes_": ArraySpec("uint8", (scalars["n_reference_"], n_kenyon // 8)),
        }

    def _set_state(self, state: dict) -> None:
        state = dict(state)
        shape = tuple(state["image_shape_"])
        state.setdefault("valid_pixels_", np.ones(shape, dtype=bool))
        pool = check_positive_int(self.pool_size, "pool_size")
        state.setdefault("pool_", pool)
        if pool % state["pool_"]:
            raise ValueError(f"pool_ must divide pool_size = {pool}; got {state['pool_']}")
        super()._set_state(state)
        c = self.connections_
        if c.min() < 0 or c.max() >= self.n_features_:
            raise ValueError(f"connections_ must index the {self.n_features_} features")
        if (np.diff(np.sort(c, axis=1), axis=1) == 0).any():
            raise ValueError("connections_ repeats a feature within a Kenyon cell")
        self._optic_lobe = self._make_lobe()
        self._optic_lobe.n_features(*shape)  # pool_size divides the image size
        self._set_valid()
        expected = self._n_kept()
        if self.n_features_ != expected:
            raise ValueError(
                f"n_features_ must be {expected} for images of {shape} with "
                f"{int(self.valid_pixels_.sum())} valid pixels"
            )
        active = self._unpack(self.reference_codes_).sum(axis=1)
        if not np.all(active == self.n_active_):
            raise ValueError("every reference code must have n_active_ active bits")
        self._prepare()
        self._index()

    # -- size -----------------------------------------------------------------
    def _map_nbytes(self) -> int:
        # One bit-packed code per place: n_kenyon / 8 bytes (512 with the defaults).  The
        # inverted index built from them at fit/load time (2 bytes per active bit) is a derived
        # search structure, not stored in model files; the connections are shared by all places.
        return int(self.reference_codes_.nbytes)

    def _footprint(self) -> dict:
        return {
            "layers": 2,  # optic lobe, Kenyon cells
            "params": 0,  # nothing is trained
            "neurons": int(self.n_features_ + self.connections_.shape[0]),
            "fixed_connections": int(self.connections_.size),
        }
