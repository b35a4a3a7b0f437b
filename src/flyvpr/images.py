"""Load and pre-process images: gray, float32 in [0, 1], area-averaged to 32x64.

The paper (Data Preprocessing) converts each RGB frame to one gray channel in
[0, 1] and resizes it to 32 x 64 (H x W) pixels, m = 2048 inputs; the authors
used OpenCV's area interpolation, which for down-sampling is the exact average
of the source pixels each target pixel covers.  Pillow's ``BOX`` filter computes
the same average, so that is what we use.

Decoded stacks are cached on disk (``.npy``, no pickle) under a key built from
the file list with each file's size and modification time, the target size
and the pre-processing version, so a second run does not decode again.
Cache files are written atomically: a crash never leaves a partial cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

__all__ = [
    "DEFAULT_SIZE",
    "IMAGE_EXTENSIONS",
    "ImageReadError",
    "to_gray",
    "resize_area",
    "demosaic_bilinear",
    "load_image",
    "load_images",
    "list_images",
    "default_cache_dir",
]

logger = logging.getLogger(__name__)

#: Image size (H, W) used by the paper: 32 x 64 = 2048 inputs.
DEFAULT_SIZE = (32, 64)
#: File suffixes treated as images when a folder is listed.
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm")
#: Bumped whenever pre-processing changes, so stale caches are never reused.
_PREPROCESS_VERSION = 1
#: ITU-R BT.601 luma weights, as OpenCV's RGB -> gray conversion.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
_BAYER_PATTERNS = ("gbrg", "grbg", "rggb", "bggr")


class ImageReadError(ValueError):
    """An image file could not be decoded (corrupt, truncated or not an image)."""


def _check_size(size) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in size)
    except (TypeError, ValueError):
        raise TypeError(f"size must be a pair (H, W) of ints; got {size!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive (H, W); got {size!r}")
    return h, w


def to_gray(array: np.ndarray) -> np.ndarray:
    """Convert an image array to float32 gray in [0, 1].

    Accepts (H, W) gray, (H, W, 3) RGB and (H, W, 4) RGBA (alpha ignored), with
    dtype uint8, uint16 (full 16-bit range) or float (taken as already in [0, 1]).

    Examples
    --------
    >>> to_gray(np.full((2, 2, 3), 255, np.uint8)).max()
    1.0
    """
    a = np.asarray(array)
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / np.float32(255.0)
    elif a.dtype == np.uint16:
        a = a.astype(np.float32) / np.float32(65535.0)
    elif np.issubdtype(a.dtype, np.integer):
        # 32-bit integer modes hold 16-bit data in practice (Pillow's "I" for PNG).
        a = a.astype(np.float32) / np.float32(65535.0)
    else:
        a = a.astype(np.float32)
    if a.ndim == 3:
        if a.shape[2] == 1:
            a = a[:, :, 0]
        elif a.shape[2] in (3, 4):
            a = a[:, :, :3] @ _LUMA
        else:
            raise ValueError(f"image must have 1, 3 or 4 channels; got shape {a.shape}")
    elif a.ndim != 2:
        raise ValueError(f"image must have shape (H, W) or (H, W, C); got shape {a.shape}")
    return np.clip(a, 0.0, 1.0, out=a if a.flags.writeable else None).astype(np.float32, copy=False)


def resize_area(gray: np.ndarray, size=DEFAULT_SIZE) -> np.ndarray:
    """Resize a float gray image to ``size`` (H, W) by area averaging."""
    h, w = _check_size(size)
    gray = np.asarray(gray, dtype=np.float32)
    if gray.shape == (h, w):
        return gray.copy()
    img = Image.fromarray(np.ascontiguousarray(gray), mode="F")
    out = np.asarray(img.resize((w, h), Image.Resampling.BOX), dtype=np.float32)
    return np.clip(out, 0.0, 1.0)


def demosaic_bilinear(raw: np.ndarray, pattern: str = "gbrg") -> np.ndarray:
    """Bilinear demosaicing of a single-channel Bayer mosaic into RGB.

    Oxford RobotCar's stereo camera stores raw Bayer images with the GBRG
    pattern (the first row starts G, B; the second R, G).  Each missing colour
    sample is the mean of its nearest same-colour neighbours.

    Parameters
    ----------
    raw : ndarray, shape (H, W)
        Mosaic, any numeric dtype (converted with :func:`to_gray` scaling).
    pattern : {'gbrg', 'grbg', 'rggb', 'bggr'}
        Colour of the 2x2 cell, row by row.

    Returns
    -------
    ndarray, shape (H, W, 3), float32 in [0, 1]
    """
    from scipy.ndimage import convolve

    pattern = pattern.lower()
    if pattern not in _BAYER_PATTERNS:
        raise ValueError(f"bayer pattern must be one of {_BAYER_PATTERNS}; got {pattern!r}")
    mosaic = to_gray(raw)
    if mosaic.ndim != 2:
        raise ValueError(f"a Bayer mosaic must be single-channel; got shape {np.shape(raw)}")
    h, w = mosaic.shape
    rgb = np.empty((h, w, 3), dtype=np.float32)
    cell = {(0, 0): pattern[0], (0, 1): pattern[1], (1, 0): pattern[2], (1, 1): pattern[3]}
    kernel_rb = np.array([[0.25, 0.5, 0.25], [0.5, 1.0, 0.5], [0.25, 0.5, 0.25]], np.float32)
    kernel_g = np.array([[0.0, 0.25, 0.0], [0.25, 1.0, 0.25], [0.0, 0.25, 0.0]], np.float32)
    for channel, colour in enumerate("rgb"):
        mask = np.zeros((h, w), dtype=np.float32)
        for (dy, dx), c in cell.items():
            if c == colour:
                mask[dy::2, dx::2] = 1.0
        kernel = kernel_g if colour == "g" else kernel_rb
        # Normalised convolution: divide by the weight of the samples present, so
        # borders are handled without bias.
        num = convolve(mosaic * mask, kernel, mode="mirror")
        den = convolve(mask, kernel, mode="mirror")
        rgb[:, :, channel] = num / den
    return np.clip(rgb, 0.0, 1.0)


def _decode(path: Path, bayer: str | None) -> np.ndarray:
    """Decode one file to a float32 gray array in [0, 1] at its native size."""
    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            if mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            elif mode in ("LA", "PA"):
                img = img.convert("L")
            elif mode == "CMYK" or mode == "YCbCr":
                img = img.convert("RGB")
            elif mode == "1":
                img = img.convert("L")
            arr = np.array(img)
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {path}") from None
    except UnidentifiedImageError:
        raise ImageReadError(f"{path}: not a readable image file") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise ImageReadError(f"{path}: corrupt or truncated image ({exc})") from None
    if bayer is not None:
        if arr.ndim != 2:
            raise ImageReadError(
                f"{path}: expected a single-channel raw Bayer image; got shape {arr.shape}"
            )
        return demosaic_bilinear(arr, bayer) @ _LUMA
    return to_gray(arr)


def load_image(path, size=DEFAULT_SIZE, *, bayer: str | None = None) -> np.ndarray:
    """Load one image file as float32 gray in [0, 1], area-resized to ``size``.

    Parameters
    ----------
    path : str or Path
        PNG, JPEG or any format Pillow reads; 8 or 16 bit; gray, RGB or RGBA.
    size : (int, int)
        Target (H, W); the paper's is (32, 64).
    bayer : str, optional
        If set (e.g. ``'gbrg'``), the file is a raw Bayer mosaic, demosaiced
        bilinearly before the gray conversion.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ImageReadError
        If it is corrupt, truncated or not an image (message names the file).
    """
    size = _check_size(size)
    with warnings.catch_warnings():
        # Pillow warns on very large images; they are still decoded correctly.
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        gray = _decode(Path(path), bayer)
    return resize_area(gray, size)


def _natural_key(path: Path):
    parts = re.split(r"(\d+)", path.name)
    return [int(p) if p.isdigit() else p.lower() for p in parts]


def list_images(folder, extensions: Sequence[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """List the image files of ``folder`` in natural order (``2.png`` before ``10.png``).

    Raises
    ------
    FileNotFoundError
        If the folder does not exist.
    NotADirectoryError
        If it is a file.
    ValueError
        If it holds no image file.
    """
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"image folder not found: {folder}")
    if not folder.is_dir():
        raise NotADirectoryError(f"expected a folder of images; got a file: {folder}")
    exts = tuple(e.lower() for e in extensions)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in exts]
    if not files:
        raise ValueError(f"no image files ({', '.join(exts)}) in folder {folder}")
    return sorted(files, key=_natural_key)


def default_cache_dir() -> Path:
    """The cache folder.

    ``$FLYVPR_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/flyvpr``, else ``~/.cache/flyvpr``.
    """
    env = os.environ.get("FLYVPR_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "flyvpr"


def _cache_key(paths: Sequence[Path], size, bayer) -> str:
    entries = []
    for p in paths:
        try:
            st = p.stat()
        except FileNotFoundError:
            raise FileNotFoundError(f"image file not found: {p}") from None
        entries.append([str(p.resolve()), st.st_size, st.st_mtime_ns])
    blob = json.dumps(
        {"v": _PREPROCESS_VERSION, "size": list(size), "bayer": bayer, "files": entries}
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def _write_atomic_npy(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.save(fh, array, allow_pickle=False)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def _want_progress(progress) -> bool:
    if progress is None:
        return sys.stderr.isatty()
    return bool(progress)


def load_images(
    paths,
    size=DEFAULT_SIZE,
    *,
    cache=True,
    progress=None,
    bayer: str | None = None,
    desc: str = "loading images",
) -> np.ndarray:
    """Load many image files into a float32 stack (N, H, W) in [0, 1].

    Parameters
    ----------
    paths : sequence of str or Path
        Files in traverse order.
    size : (int, int)
        Target (H, W).
    cache : bool or path
        ``True`` caches under :func:`default_cache_dir`, a path caches there,
        ``False`` never reads or writes a cache.
    progress : bool, optional
        Show a progress bar; ``None`` shows one only when stderr is a terminal.
    bayer : str, optional
        Raw Bayer pattern of the files (see :func:`load_image`).
    desc : str
        Label of the progress bar.

    Raises
    ------
    ValueError
        If ``paths`` is empty.
    FileNotFoundError, ImageReadError
        For a missing or undecodable file; nothing is cached then.
    """
    from tqdm.auto import tqdm

    size = _check_size(size)
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("paths is empty: expected at least one image file")
    cache_file = None
    if cache is not False and cache is not None:
        cache_dir = default_cache_dir() if cache is True else Path(cache)
        cache_file = cache_dir / f"images-{_cache_key(paths, size, bayer)}.npy"
        if cache_file.is_file():
            try:
                arr = np.load(cache_file, allow_pickle=False)
                if arr.shape == (len(paths), *size) and arr.dtype == np.float32:
                    logger.debug("image cache hit: %s", cache_file)
                    return arr
                logger.warning("ignoring cache file with unexpected shape: %s", cache_file)
            except (OSError, ValueError) as exc:
                logger.warning("ignoring unreadable cache file %s (%s)", cache_file, exc)
    out = np.empty((len(paths), *size), dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        for i, p in enumerate(
            tqdm(paths, desc=desc, unit="img", disable=not _want_progress(progress), leave=False)
        ):
            out[i] = resize_area(_decode(p, bayer), size)
    if cache_file is not None:
        try:
            _write_atomic_npy(cache_file, out)
        except OSError as exc:  # a read-only cache must not stop the work
            logger.warning("could not write image cache %s (%s)", cache_file, exc)
    return out
