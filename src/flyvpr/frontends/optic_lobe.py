"""A fixed optic lobe: local contrast normalisation, Gabor energy, pooling (no learning).

The first stage of the ``kenyon`` front end (:class:`~flyvpr.frontends.kenyon.KenyonEncoder`),
loosely modelled on the early visual system of insects, in which photoreceptors adapt to the
local light level (lamina) and the medulla responds to oriented edges:

1. :func:`local_contrast_normalize`: every pixel minus the Gaussian-weighted mean of its
   neighbourhood, divided by ``sqrt(variance + eps**2)`` of the Gaussian-weighted variance.  Unlike
   SeqSLAM's patch normalisation on a fixed grid of patches it is shift-equivariant, so a camera
   that moves by a few pixels sees the same normalised image, moved.
2. Gabor energy: the response energy ``sqrt(even^2 + odd^2)`` of a quadrature pair of Gabor
   filters at a few orientations (a complex Gabor kernel, :func:`gabor_bank`):
   phase-invariant edge and bar detectors, by a compiled direct convolution (each kernel is
   the sum of two separable ones; the tests check it against an FFT convolution, to float32
   rounding).
3. Max pooling over ``pool_size x pool_size`` cells, the square root (compresses the heavy tail
   of the energies) and a per-image z-score (divisive normalisation: only the pattern of
   responses counts, not the image's overall contrast).

:func:`optic_lobe` chains the three; at 32x64 with the defaults it gives
``4 orientations x 8 x 16 cells = 512`` features per image.

Static pixels (the black surround of a fisheye lens, the robot's own chassis, an overlay burnt
into the video) carry no information about the place, but their edges with the scene would
weigh in every stage.  :func:`varying_pixels` finds them in a traverse; given that mask
(``valid_pixels``), the contrast normalisation averages over the valid pixels only and is 0
elsewhere, so the static pixels' values never enter; the features that are then 0 in every
image (no valid pixel within reach of their cell's Gabor kernels) are dropped, and the z-score
takes the others only.  With every pixel valid nothing changes.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .._validation import check_images, check_memory, check_positive_int, check_real

__all__ = [
    "varying_pixels",
    "pool_for_mask",
    "local_contrast_normalize",
    "gabor_bank",
    "optic_lobe",
]

#: images per block: bounds the FFT temporaries (about 0.5 MB per image at 32x64)
_BLOCK = 256

#: A pixel varies along a traverse if its standard deviation over the frames exceeds this
#: share of the 90th percentile of the pixels' standard deviations.  Relative, so it does not
#: depend on the camera's gain or the data set: a pixel that sees the scene spreads by 0.1-0.3
#: gray levels over a route (the 90th percentile says how much; a median would fail where more
#: than half the frame is static, as behind a fisheye lens), while sensor noise and compression
#: in a black surround or on a fixed overlay move it by a few levels of 256 (about 0.01), well
#: under 5% of that.
_MIN_RELATIVE_SPREAD = 0.05
_SPREAD_PERCENTILE = 90

#: Accepted ranges of the real-valued settings, inclusive (the docstrings of
#: :func:`local_contrast_normalize` and :func:`gabor_bank` say why): the Gaussian window's
#: ``sigma`` and the Gabor ``wavelength`` in pixels, ``eps`` in gray levels of images in [0, 1]
_SIGMA_RANGE = (0.25, 1e6)
_EPS_RANGE = (1e-8, 1.0)
_WAVELENGTH_RANGE = (2.0, 1e6)


def varying_pixels(images) -> np.ndarray:
    """Pixels whose value varies along a traverse; False marks the static ones.

    A pixel is static if the standard deviation of its value over the frames is at most 5% of
    the 90th percentile of all pixels' standard deviations: the black surround of a fisheye
    lens, a robot's own chassis in view, an overlay burnt into the video.  Where no pixel varies
    (one frame, or identical frames) there is nothing to tell apart and every pixel counts as
    varying.

    Parameters
    ----------
    images : array-like, shape (N, H, W)
        The frames of one traverse, gray in [0, 1].

    Returns
    -------
    ndarray of bool, shape (H, W)

    Examples
    --------
    >>> x = np.random.default_rng(0).random((10, 4, 8))
    >>> x[:, :, 0] = 0.05  # a static first column
    >>> varying_pixels(x).sum(axis=0)
    array([0, 4, 4, 4, 4, 4, 4, 4])
    """
    x = check_images(images, "images")
    spread = _pixel_std(x)
    varying = spread > _MIN_RELATIVE_SPREAD * np.percentile(spread, _SPREAD_PERCENTILE)
    return varying if varying.any() else np.ones_like(varying)


def pool_for_mask(valid_pixels, pool_size: int) -> int:
    """The side of the pooling cells that gives the varying pixels about a whole frame's cells.

    A mask that hides much of the frame (a fisheye's surround hides 59% of a 32x64 frame)
    leaves fewer cells, and so fewer features, for the same place.  The cells then shrink:
    their area goes with the share ``s`` of valid pixels, and the side is the divisor of
    ``pool_size`` nearest to ``pool_size * sqrt(s)`` in ratio, the larger one on a tie
    (compared in exact integer arithmetic).  With a ``pool_size`` of 4: 4 wherever at least
    half of the pixels are valid (every pixel valid included), 2 from an eighth up to half,
    1 below an eighth.  No constant of its own.

    Parameters
    ----------
    valid_pixels : ndarray of bool, shape (H, W)
        As :func:`varying_pixels` returns (at least one True).
    pool_size : int
        The side on a whole frame; a positive int.

    Returns
    -------
    int
        A divisor of ``pool_size``.

    Raises
    ------
    TypeError
        If ``valid_pixels`` is not a bool array or ``pool_size`` not an int.
    ValueError
        If ``valid_pixels`` is not 2-d or marks no valid pixel, or ``pool_size`` < 1.

    Examples
    --------
    >>> y, x = np.mgrid[0:32, 0:64]
    >>> disc = ((y - 15.5) / 16) ** 2 + ((x - 31.5) / 16.8) ** 2 <= 1  # 41% of the pixels
    >>> pool_for_mask(disc, 4), pool_for_mask(np.ones((32, 64), bool), 4)
    (2, 4)
    """
    pool = check_positive_int(pool_size, "pool_size")
    shape = np.shape(valid_pixels)
    if len(shape) != 2:
        raise ValueError(f"valid_pixels must be 2-d (H, W); got shape {shape}")
    valid = _check_valid_pixels(valid_pixels, *shape)  # (None: every pixel valid)
    n = shape[0] * shape[1]
    k = n if valid is None else int(np.count_nonzero(valid))
    if k == 0:
        raise ValueError("valid_pixels must mark at least one valid pixel; got none")
    # the side d against the target t = pool * sqrt(k / n): (d / t)^2 = d^2 n / (pool^2 k); a
    # side's distance in ratio is max(a, b) / min(a, b) of those two integers
    b = pool * pool * k
    best, far = pool, (max(pool * pool * n, b), min(pool * pool * n, b))
    for d in range(pool - 1, 0, -1):
        if pool % d:
            continue
        a = d * d * n
        this = (max(a, b), min(a, b))
        if this[0] * far[1] < far[0] * this[1]:  # strictly nearer: a tie keeps the larger
            best, far = d, this
    return best


def _pixel_std(x: np.ndarray) -> np.ndarray:
    """Per-pixel standard deviation over the frames (float64, two passes, blocks of frames:
    no float64 copy of the whole stack)."""
    n = len(x)
    total = np.zeros(x.shape[1:])
    for start in range(0, n, _BLOCK):
        total += x[start : start + _BLOCK].sum(axis=0, dtype=np.float64)
    mean = total / n
    squares = np.zeros(x.shape[1:])
    for start in range(0, n, _BLOCK):
        squares += np.square(x[start : start + _BLOCK] - mean).sum(axis=0)
    return np.sqrt(squares / n)


def _check_valid_pixels(valid_pixels, h: int, w: int):
    """``valid_pixels`` as a C-ordered bool array of shape (h, w), or None where all are valid."""
    if valid_pixels is None:
        return None
    valid = np.asarray(valid_pixels)
    if valid.dtype != np.bool_:
        raise TypeError(f"valid_pixels must be a bool array; got dtype {valid.dtype}")
    if valid.shape != (h, w):
        raise ValueError(f"valid_pixels must have the image size {(h, w)}; got shape {valid.shape}")
    return None if valid.all() else np.ascontiguousarray(valid)


def local_contrast_normalize(
    images, sigma: float = 4.0, eps: float = 0.05, *, valid_pixels=None
) -> np.ndarray:
    """Subtract the local mean and divide by the local standard deviation (Gaussian windows).

    ``out = (x - G * x) / sqrt(G * (x - G * x)^2 + eps^2)`` with ``G`` a Gaussian of standard
    deviation ``sigma`` pixels (reflecting borders), per image.  ``eps`` keeps flat regions
    (sky, snow) from blowing noise up to full contrast.

    With a mask ``valid_pixels`` (``m``, 1 where valid) the windows cover the valid pixels only
    (normalised convolution): the local mean is ``G * (m x) / G * m`` and the local variance
    ``G * (m (x - mean)^2) / G * m``; invalid pixels give 0, and their values never enter.

    Parameters
    ----------
    images : array-like, shape (N, H, W)
        Gray images in [0, 1].
    sigma : float, default 4.0
        Width of the neighbourhood in pixels, in [0.25, 1e6].  The window is cut off at
        ``4 * sigma``, so from 0.25 on it reaches the neighbouring pixels (below, their weight
        is under ``exp(-8)``, and below 0.125 every normalised image is 0); once wider than the
        image it averages the whole (reflected) image, and 1e6 is past any image.
    eps : float, default 0.05
        Contrast floor, in gray levels, in [1e-8, 1].  A smaller floor is under the float32
        resolution of gray levels (``2**-24``, 6e-8, near 1) and blows rounding noise up to full
        contrast (below about 1e-22 its square is 0 in float32, and a flat patch divides 0 by
        0); one above 1 exceeds the contrast of any image in [0, 1] (a standard deviation of at
        most 0.5) and only shrinks the output.
    valid_pixels : ndarray of bool, shape (H, W), optional
        E.g. from :func:`varying_pixels`; None or all True: every pixel is valid.

    Returns
    -------
    ndarray of float32, shape (N, H, W)

    Raises
    ------
    ValueError, TypeError
        For a parameter out of range or a mask of another shape or dtype.
    flyvpr._validation.InsufficientMemoryError
        If the window (``sigma``) would not fit in memory for images of this size; raised
        before allocating.

    Examples
    --------
    >>> x = np.random.default_rng(0).random((2, 32, 64))
    >>> local_contrast_normalize(x).shape
    (2, 32, 64)
    >>> float(np.abs(local_contrast_normalize(np.full((1, 8, 8), 0.3))).max())
    0.0
    """
    x = check_images(images, "images")
    sigma, eps = _check_lcn(sigma, eps)
    valid = _check_valid_pixels(valid_pixels, *x.shape[1:])
    if valid is None:
        return _lcn(x, sigma, eps)
    n, h, w = x.shape
    taps, index_h, index_w, eps2 = _lcn_plan(sigma, eps, h, w)
    out = np.empty((n, h, w), dtype=np.float32)
    gm = _window_weight(valid, sigma)
    return _kernels().lcn_masked(x, valid, gm, taps, index_h, index_w, eps2, out)


def _check_lcn(sigma, eps, prefix: str = "") -> tuple[float, float]:
    """``sigma`` and ``eps`` of the contrast normalisation in their ranges, as floats; the
    messages name them with ``prefix`` (``"lcn_"`` for the optic lobe's settings)."""
    low, high = _SIGMA_RANGE
    sigma = check_real(sigma, f"{prefix}sigma", low=low, inclusive=True, high=high, unit="pixels")
    low, high = _EPS_RANGE
    eps = check_real(eps, f"{prefix}eps", low=low, inclusive=True, high=high)
    return sigma, eps


def _window_weight(valid: np.ndarray, sigma: float) -> np.ndarray:
    """``G * m``: the weight of the valid pixels in each pixel's Gaussian window, float32."""
    return ndimage.gaussian_filter(valid.astype(np.float32), sigma, mode="reflect")


def _kernels():
    """The compiled kernels of the optic lobe and the Kenyon cells (numba, imported on first
    use: ``import flyvpr`` stays light)."""
    from . import _kenyon_kernels

    return _kenyon_kernels


def _lcn_plan(sigma: float, eps: float, h: int, w: int, name: str = "sigma") -> tuple:
    """What the LCN kernel needs for images of size (h, w): Gaussian taps, border indices.

    ``sigma`` (checked, in range; ``name`` in the messages): a window that would not fit in
    memory with the kernel's buffers is refused here, before anything is allocated.
    """
    radius = int(4.0 * sigma + 0.5)  # as gaussian_taps cuts the window off
    # taps and border indices (a few float64 and int64 lines of up to 2r + h + w values), the
    # compiled filter's lines padded by r (float64) and its float32 images
    check_memory(
        64 * (2 * radius + h + w)
        + 8 * max((h + 2 * radius) * w, (w + 2 * radius) * h)
        + 20 * h * w,
        f"{name}={sigma:g} on images of {h}x{w}",
    )
    k = _kernels()
    taps = k.gaussian_taps(sigma)
    r = len(taps) - 1
    return taps, k.reflect_index(h, r), k.reflect_index(w, r), np.float32(eps * eps)


def _lcn(x: np.ndarray, sigma: float, eps: float, plan=None) -> np.ndarray:
    # Same arithmetic as ``scipy.ndimage.gaussian_filter(x, (0, sigma, sigma),
    # mode="reflect")`` for the local mean and variance (float32 between steps), then
    # ``(x - mean) / sqrt(var + eps**2)``, in one compiled pass per image.
    n, h, w = x.shape
    taps, index_h, index_w, eps2 = plan or _lcn_plan(sigma, eps, h, w)
    out = np.empty((n, h, w), dtype=np.float32)
    return _kernels().lcn(np.ascontiguousarray(x), taps, index_h, index_w, eps2, out)


def _gabor_factors(n_orientations: int, wavelength: float, size: int) -> tuple:
    """The 1-d factors of the Gabor kernels (checked settings): ``g, a, b, dc, z``.

    Kernel ``k`` is ``(a[k](x) b[k](y) - dc[k] g(x) g(y)) / z[k]``: the circular Gaussian
    envelope ``g(x) g(y)`` times the carrier ``exp(2 pi i (x cos + y sin) / wavelength)``,
    which splits into a factor along x and one along y; minus the envelope times the even
    part's mean (``dc``, so that flat regions give no response); over its L1 norm ``z``.
    """
    r = size // 2
    t = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-(t**2) / (2.0 * (0.56 * wavelength) ** 2))
    theta = np.arange(n_orientations)[:, None] * np.pi / n_orientations
    a = g * np.exp(2j * np.pi * np.cos(theta) * t / wavelength)
    b = g * np.exp(2j * np.pi * np.sin(theta) * t / wavelength)
    carrier = b[:, :, None] * a[:, None, :]  # (orientation, y, x)
    envelope = np.outer(g, g)
    dc = carrier.real.sum(axis=(1, 2)) / envelope.sum()
    z = np.abs(carrier - dc[:, None, None] * envelope).sum(axis=(1, 2))
    return g, a, b, dc, z


def _check_gabor(
    n_orientations, wavelength, size, size_name: str = "size"
) -> tuple[int, float, int]:
    """The settings of :func:`gabor_bank`, checked (``size`` named ``size_name`` in the
    messages); kernels that would not fit in memory are refused before anything is allocated."""
    n_orientations = check_positive_int(n_orientations, "n_orientations")
    low, high = _WAVELENGTH_RANGE
    wavelength = check_real(
        wavelength, "wavelength", low=low, inclusive=True, high=high, unit="pixels"
    )
    size = check_positive_int(size, size_name, minimum=3)
    if size % 2 == 0:
        raise ValueError(f"{size_name} must be odd (a kernel centred on a pixel); got {size}")
    # the kernels and the two temporaries of their size that make them (complex128)
    check_memory(
        48 * n_orientations * size * size,
        f"n_orientations={n_orientations} with {size_name}={size}",
    )
    return n_orientations, wavelength, size


def gabor_bank(n_orientations: int = 4, wavelength: float = 6.0, size: int = 11) -> np.ndarray:
    """Complex Gabor kernels: the real part is the even filter, the imaginary part the odd one.

    Kernel ``k`` has orientation ``k * pi / n_orientations``, a circular Gaussian envelope of
    standard deviation ``0.56 * wavelength`` (a bandwidth of about one octave), zero mean (the
    even part's DC is removed, so flat regions give no response) and unit L1 norm.

    Parameters
    ----------
    n_orientations : int, default 4
        Orientations, evenly spaced over 180 degrees.
    wavelength : float, default 6.0
        Period of the carrier in pixels, in [2, 1e6].  2 is the Nyquist limit: a shorter
        period aliases to a longer one (at 1 the carrier is flat and the kernels vanish).  Once
        the period is a few kernels long the kernels hardly change any more (the even part
        fades, the odd part tends to a ramp); 1e6 keeps them well inside float32's range.
    size : int, default 11
        Side of the kernels in pixels, odd, at least 3.

    Returns
    -------
    ndarray of complex128, shape (n_orientations, size, size)
        Axis 1 is y (rows), axis 2 is x (columns).

    Raises
    ------
    ValueError, TypeError
        For a parameter out of range or of the wrong type.
    flyvpr._validation.InsufficientMemoryError
        If the kernels would not fit in memory (``n_orientations * size**2`` complex numbers);
        raised before allocating.
    """
    return _compose(*_gabor_factors(*_check_gabor(n_orientations, wavelength, size)))


def _compose(g, a, b, dc, z) -> np.ndarray:
    """The 2-d kernels (orientation, y, x) of the factors of :func:`_gabor_factors`."""
    kernel = b[:, :, None] * a[:, None, :] - dc[:, None, None] * np.outer(g, g)
    return kernel / z[:, None, None]


def optic_lobe(
    images,
    *,
    lcn_sigma: float = 4.0,
    lcn_eps: float = 0.05,
    n_orientations: int = 4,
    wavelength: float = 6.0,
    kernel_size: int = 11,
    pool_size: int = 4,
    valid_pixels=None,
) -> np.ndarray:
    """Fixed optic-lobe features: contrast normalisation, Gabor energy, max pooling, z-score.

    Parameters
    ----------
    images : array-like, shape (N, H, W)
        Gray images in [0, 1]; ``H`` and ``W`` must be multiples of ``pool_size``.
    lcn_sigma, lcn_eps : float
        See :func:`local_contrast_normalize`.
    n_orientations, wavelength, kernel_size : int, float, int
        See :func:`gabor_bank`.
    pool_size : int, default 4
        Side of the max-pooling cells.
    valid_pixels : ndarray of bool, shape (H, W), optional
        Pixels to look at (e.g. from :func:`varying_pixels`): the contrast normalisation
        averages over them only and is 0 elsewhere, and only the features that can differ from
        0 are kept (in the same order): those of the cells with a valid pixel within
        ``kernel_size // 2`` pixels.  None or all True: every pixel and every feature.

    Returns
    -------
    ndarray of float32, shape (N, n_kept)
        ``n_kept`` is ``n_orientations * (H // pool_size) * (W // pool_size)`` without a mask.
        Each row has mean 0 and standard deviation 1 (all zeros for a blank image).

    Raises
    ------
    ValueError
        If ``pool_size`` does not divide the image size, a parameter is out of range, or
        ``valid_pixels`` has another shape or no valid pixel.
    TypeError
        If ``valid_pixels`` is not a bool array.
    flyvpr._validation.InsufficientMemoryError
        If the kernels (``n_orientations``, ``kernel_size``), the window (``lcn_sigma``) or
        the compiled filter's buffers for this image size would not fit in memory; raised
        before allocating.

    Examples
    --------
    >>> f = optic_lobe(np.random.default_rng(0).random((3, 32, 64)))
    >>> f.shape, round(float(f[0].std()), 3)
    ((3, 512), 1.0)
    """
    x = check_images(images, "images")
    lobe = OpticLobe(lcn_sigma, lcn_eps, n_orientations, wavelength, kernel_size, pool_size)
    return lobe(x, _check_valid_pixels(valid_pixels, *x.shape[1:]))


class OpticLobe:
    """:func:`optic_lobe` with its settings checked once and the kernels' factors cached.

    Calling it on a validated float32 stack (N, H, W), optionally with a checked mask
    ``valid_pixels`` (C-ordered bool (H, W); None: all valid), returns the features; used by
    the ``kenyon`` encoder, which encodes one frame at a time when streaming.
    """

    def __init__(self, lcn_sigma, lcn_eps, n_orientations, wavelength, kernel_size, pool_size):
        self.lcn_sigma, self.lcn_eps = _check_lcn(lcn_sigma, lcn_eps, "lcn_")
        factors = _gabor_factors(
            *_check_gabor(n_orientations, wavelength, kernel_size, "kernel_size")
        )
        self.bank = _compose(*factors)
        # the kernels' 1-d factors as the compiled filter takes them, float32
        g, a, b, dc, z = factors
        f32 = np.float32
        self._factors = tuple(
            np.ascontiguousarray(v, dtype=f32)
            for v in (g, a.real, a.imag, b.real, b.imag, dc, 1.0 / z)
        )
        self.pool = check_positive_int(pool_size, "pool_size")
        self._cache: dict = {}
        self._mask: tuple = (None, None)

    def n_features(self, h: int, w: int) -> int:
        """Features per image of size (h, w); ValueError if ``pool_size`` does not divide it."""
        pool = self.pool
        if h % pool or w % pool:
            raise ValueError(
                f"pool_size must divide the image size (H, W) = ({h}, {w}); got {pool}"
            )
        return self.bank.shape[0] * (h // pool) * (w // pool)

    def kept_features(self, valid_pixels: np.ndarray) -> np.ndarray:
        """Indices (uint32, ascending) of the features :meth:`__call__` returns with this mask.

        The contrast normalisation is 0 at invalid pixels, so a pixel's Gabor energies are 0
        unless a valid pixel lies within the kernels' reach (``kernel_size // 2`` along both
        axes), and a cell's features are 0 in every image unless one of its pixels is in
        reach.  Those are dropped; they would only weigh in the z-score.  No threshold: every
        feature that can vary is kept.
        """
        h, w = valid_pixels.shape
        self.n_features(h, w)
        p, size = self.pool, self.bank.shape[1]
        reached = ndimage.binary_dilation(valid_pixels, np.ones((size, size), bool))
        kept = reached.reshape(h // p, p, w // p, p).any(axis=(1, 3)).ravel()
        return np.flatnonzero(np.tile(kept, self.bank.shape[0])).astype(np.uint32)

    def _plan(self, h: int, w: int) -> tuple:
        """The LCN set-up for images of (h, w), made once; buffers of the compiled filter that
        would not fit in memory for that size are refused first."""
        if (h, w) not in self._cache:
            n, size = self.bank.shape[:2]
            r, p = size // 2, self.pool
            # two float32 lines per orientation and five more, of the image widened by the
            # kernels' radius, and one image's features (twice under a mask)
            check_memory(
                4 * (2 * n + 5) * (h + 2 * r) * (w + 2 * r) + 8 * n * (h // p) * (w // p),
                f"n_orientations={n} with kernel_size={size} on images of {h}x{w}",
            )
            self._cache[(h, w)] = _lcn_plan(self.lcn_sigma, self.lcn_eps, h, w, "lcn_sigma")
        return self._cache[(h, w)]

    def _masked(self, valid: np.ndarray) -> tuple:
        """The set-up of one mask (the last one used is kept): the window weights ``G * m``
        and the kept features."""
        key = (valid.shape, valid.tobytes())
        if self._mask[0] != key:
            if not valid.any():
                raise ValueError("valid_pixels must mark at least one valid pixel; got none")
            self._mask = (key, (_window_weight(valid, self.lcn_sigma), self.kept_features(valid)))
        return self._mask[1]

    def normalise(self, x: np.ndarray, valid_pixels: np.ndarray | None = None) -> np.ndarray:
        """The lobe's contrast normalisation of a validated float32 stack (N, H, W), with its
        set-up cached (:func:`local_contrast_normalize` with the lobe's settings)."""
        n, h, w = x.shape
        x = np.ascontiguousarray(x)
        plan = self._plan(h, w)  # (first: it checks the memory)
        if valid_pixels is None:
            return _lcn(x, self.lcn_sigma, self.lcn_eps, plan)
        out = np.empty((n, h, w), dtype=np.float32)
        gm = self._masked(valid_pixels)[0]
        return _kernels().lcn_masked(x, valid_pixels, gm, *plan, out)

    def __call__(self, x: np.ndarray, valid_pixels: np.ndarray | None = None) -> np.ndarray:
        n, h, w = x.shape
        n_features = self.n_features(h, w)
        plan = self._plan(h, w)  # (first: it checks the memory)
        if valid_pixels is not None:
            gm, kept = self._masked(valid_pixels)
            n_features = len(kept)
        if n > 64:  # small batches (a streamed frame) need no check of /proc/meminfo
            check_memory(n * n_features * 4, f"optic_lobe on {n} images of {h}x{w}")
        features = np.empty((n, n_features), dtype=np.float32)
        x = np.ascontiguousarray(x)
        # LCN, Gabor energy, max pooling, square root and the per-image z-score (a blank
        # image has no edges: every feature is equal and the row stays all zeros), compiled,
        # one image at a time
        if valid_pixels is None:
            return _kernels().optic_lobe(x, *plan, *self._factors, self.pool, features)
        return _kernels().optic_lobe_masked(
            x, valid_pixels, gm, *plan, *self._factors, self.pool, kept, features
        )
