"""Load and pre-process images: gray, float32 in [0, 1], area-averaged to 32x64.

The paper (Data Preprocessing) converts each RGB frame to one gray channel in
[0, 1] and resizes it to 32 x 64 (H x W) pixels, m = 2048 inputs; the authors
used OpenCV's area interpolation, which for down-sampling is the exact average
of the source pixels each target pixel covers.  :func:`area_resize` computes that average
(partial pixels weighted by the fraction covered) for image files, video frames and ROS bags
alike.

What is read (see :data:`FOLDER_RULES` and ``docs/guide/reliability.md``): every entry of
an image folder is a frame or is refused by name, except hidden entries; integer pixels are
scaled by their type's white level; float pixels must already lie in [0, 1]; a frame larger
than Pillow's ``MAX_IMAGE_PIXELS`` is refused before it is decoded.  A frame is turned upright
by its EXIF orientation tag (as a viewer shows it); a colour mode that is not RGB in some form
(LAB, HSV) is refused; colour of more than 8 bits per sample, of which Pillow reads the high
byte only, is named in a warning.

Decoded stacks are cached on disk (no pickle) under a key built from the file list with each
file's size, modification time, inode and status-change time, the target size and the
pre-processing and decoding versions, so a second run does not decode again.  Each cache file
carries its key, and the zip's CRC-32 of its pixels is checked on every read; an entry that
fails any check (unreadable, swapped, damaged, NaN or out of range) is named in a warning and
rebuilt.  Cache files are written atomically: a crash never leaves a partial cache.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import logging
import os
import re
import stat
import struct
import sys
import warnings
import zipfile
from collections.abc import Sequence
from decimal import Decimal
from pathlib import Path

import numpy as np
from PIL import ExifTags, Image, ImageOps, UnidentifiedImageError

from ._io import ZipWriter, atomic_open, raise_interruption
from ._npy import read_npz_member
from ._validation import array_nbytes, check_memory

__all__ = [
    "DEFAULT_SIZE",
    "IMAGE_EXTENSIONS",
    "ImageReadError",
    "ImageFolderError",
    "FOLDER_RULES",
    "to_gray",
    "resize_area",
    "same_aspect",
    "upright_shape",
    "area_resize",
    "area_matrix",
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
#: Bumped whenever pre-processing changes, so stale caches are never reused.  It is written
#: into model files too, which refuse to load under another version.
_PREPROCESS_VERSION = 1
#: Version of the decoding of a file into pixels, part of the image cache's key only (not of
#: model files: a file decodes as before unless it is one of the cases a version fixed).
#: 2: EXIF orientation applied; LAB/HSV files refused.
_DECODE_VERSION = 2
#: Pillow modes :func:`_decode` turns into gray correctly (converted first where needed).
_DECODED_MODES = frozenset(
    {"1", "L", "LA", "La", "P", "PA", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr", "F"}
    | {"I", "I;16", "I;16L", "I;16B", "I;16N"}
)
#: Raw modes in which Pillow reads 16-bit colour (or gray with alpha) samples into an 8-bit
#: mode, keeping only each sample's high byte (PNG, TIFF, SGI).
_HIGH_BYTE_RAWMODES = re.compile(r"(L|LA|La|RGB|RGBA|RGBa|RGBX|CMYK|YCbCr);16[BLN]?")
#: EXIF Orientation -> the transposition that shows the picture upright (EXIF 2.32, 4.6.5).
_ORIENTATION = {
    2: Image.Transpose.FLIP_LEFT_RIGHT,
    3: Image.Transpose.ROTATE_180,
    4: Image.Transpose.FLIP_TOP_BOTTOM,
    5: Image.Transpose.TRANSPOSE,
    6: Image.Transpose.ROTATE_270,
    7: Image.Transpose.TRANSVERSE,
    8: Image.Transpose.ROTATE_90,
}
#: ITU-R BT.601 luma weights, as OpenCV's RGB -> gray conversion.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
_BAYER_PATTERNS = ("gbrg", "grbg", "rggb", "bggr")


#: What :func:`list_images` reads, shown by ``flyvpr datasets``.
FOLDER_RULES = (
    "Image folders: every entry but a hidden one is a frame or is refused by name.\n"
    "- frames: regular files (or links to them) ending in "
    + " ".join(IMAGE_EXTENSIONS)
    + " (any case), in natural name order: numbers by value, decimals too (2.png before "
    "10.png, 1.05.png before 1.1.png; a warning where that decides the order), names equal "
    "but for that (1.png, 01.png) by name;\n"
    "- skipped, counted with `flyvpr --verbose COMMAND`: hidden entries, whose name starts "
    "with '.' (.DS_Store, ._* AppleDouble files);\n"
    "- refused: anything else (another extension such as .gif, .webp or .txt, a sub-folder, a "
    "dangling link, a link loop, a FIFO, a device, an unreadable file).\n"
    "Pixels: 8/16-bit integers are scaled by 255/65535; float images must lie in [0, 1] (other "
    "ranges and NaN are refused); 16-bit colour is read by its high byte only (a warning names "
    "the file; 16-bit gray keeps full precision); colour modes other than RGB, CMYK, YCbCr "
    "and palettes (LAB, HSV) are refused; frames are turned upright by their EXIF orientation; "
    "frames over PIL.Image.MAX_IMAGE_PIXELS pixels are refused before decoding."
)


class ImageReadError(ValueError):
    """An image file could not be decoded (corrupt, truncated or not an image)."""


class ImageFolderError(ValueError):
    """An entry of an image folder that is neither a frame nor skipped (named in the message)."""


def _check_size(size) -> tuple[int, int]:
    try:
        h, w = size
        if isinstance(h, (bool, np.bool_)) or isinstance(w, (bool, np.bool_)):
            raise TypeError
        if int(h) != h or int(w) != w:  # (32.0 is 32; 32.9 is no size)
            raise ValueError
        h, w = int(h), int(w)
    except (TypeError, ValueError, OverflowError):
        raise TypeError(f"size must be a pair (H, W) of ints; got {size!r}") from None
    if h < 1 or w < 1:
        raise ValueError(f"size must be positive (H, W); got {size!r}")
    return h, w


def to_gray(array: np.ndarray) -> np.ndarray:
    """Convert an image array to float32 gray in [0, 1].

    Accepts (H, W) gray, (H, W, 3) RGB and (H, W, 4) RGBA (alpha ignored), with dtype
    uint8 and other 1-byte integers (divided by 255), uint16 and other integers holding values
    in [0, 65535] (16-bit data in Pillow's 32-bit mode ``I``, divided by 65535), bool, or
    float already in [0, 1].  No value is clipped: anything else is refused.

    Raises
    ------
    ValueError
        For a wrong shape, NaN or infinite values, float values outside [0, 1] or integers
        outside [0, 65535] (the message gives the range found).

    Examples
    --------
    >>> float(to_gray(np.full((2, 2, 3), 255, np.uint8)).max())
    1.0
    """
    a = np.asarray(array)
    if a.dtype == np.uint8:
        a = a.astype(np.float32) / np.float32(255.0)
    elif a.dtype == np.bool_:
        a = a.astype(np.float32)
    elif np.issubdtype(a.dtype, np.integer):
        if a.dtype.itemsize > 2 or np.issubdtype(a.dtype, np.signedinteger):
            lo, hi = (int(a.min()), int(a.max())) if a.size else (0, 0)
            if lo < 0 or hi > 65535:
                raise ValueError(
                    f"integer pixels must lie in [0, 65535] (8 or 16-bit data); got range "
                    f"[{lo}, {hi}] in a {a.dtype} image: convert it to 8 or 16 bits"
                )
        a = a.astype(np.float32) / np.float32(255.0 if a.dtype.itemsize == 1 else 65535.0)
    elif np.issubdtype(a.dtype, np.floating):
        a = a.astype(np.float32)
        if a.size and not np.isfinite(a).all():
            raise ValueError("float pixels contain NaN or infinite values")
        low, high = (float(a.min()), float(a.max())) if a.size else (0.0, 0.0)
        if low < 0.0 or high > 1.0:
            raise ValueError(
                f"float pixels must lie in [0, 1]; got range [{low:g}, {high:g}]: flyvpr does not "
                "guess the white level of a float image, scale it to [0, 1] (or save 8/16-bit)"
            )
    else:
        raise ValueError(f"image must hold numbers; got dtype {a.dtype}")
    if a.ndim == 3:
        if a.shape[2] == 1:
            a = a[:, :, 0]
        elif a.shape[2] in (3, 4):
            # The weights sum to 1, so this is a weighted mean; the clip only removes rounding.
            a = np.clip(a[:, :, :3] @ _LUMA, 0.0, 1.0)
        else:
            raise ValueError(f"image must have 1, 3 or 4 channels; got shape {a.shape}")
    elif a.ndim != 2:
        raise ValueError(f"image must have shape (H, W) or (H, W, C); got shape {a.shape}")
    return a.astype(np.float32, copy=False)


def resize_area(gray: np.ndarray, size=DEFAULT_SIZE) -> np.ndarray:
    """Resize a float gray image in [0, 1] to ``size`` (H, W) by area averaging
    (:func:`area_resize`, clipped to [0, 1] against rounding)."""
    h, w = _check_size(size)
    gray = np.asarray(gray, dtype=np.float32)
    if gray.shape == (h, w):
        return gray.copy()
    return np.clip(area_resize(gray, h, w), 0.0, 1.0)


@functools.lru_cache(maxsize=16)
def area_matrix(n_out: int, n_in: int) -> np.ndarray:
    """Weights (n_out, n_in) of an area resize along one axis: each output pixel is the mean of
    the input interval it covers, partial pixels weighted by their covered fraction."""
    edges = np.arange(n_out + 1, dtype=np.float64) * (n_in / n_out)
    j = np.arange(n_in, dtype=np.float64)[None, :]
    overlap = np.minimum(edges[1:, None], j + 1) - np.maximum(edges[:-1, None], j)
    weights = np.clip(overlap, 0.0, None)
    return (weights / weights.sum(axis=1, keepdims=True)).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _row_band(n_out: int, n_in: int):
    """:func:`area_matrix` as a band: per output row its first input row, the count of input
    rows it covers and their weights (zero-padded to the widest band)."""
    m = area_matrix(n_out, n_in)
    nz = m > 0
    starts = nz.argmax(axis=1).astype(np.int64)
    counts = nz.sum(axis=1).astype(np.int64)
    weights = np.zeros((n_out, int(counts.max())), np.float32)
    for i in range(n_out):  # n_out rows (32 by default), once per frame size
        weights[i, : counts[i]] = m[i, starts[i] : starts[i] + counts[i]]
    return starts, counts, weights


#: The dtypes the area-resize kernel reads as they are (native byte order).
_KERNEL_DTYPES = (np.dtype(np.uint8), np.dtype(np.float32), np.dtype(np.float64))


def area_resize(y: np.ndarray, h: int, w: int) -> np.ndarray:
    """Area-average the 2-d array ``y`` (any real dtype, any range) to ``(h, w)``, float32.

    The package's one resize (image files, video frames, ROS bags): the weights of
    :func:`area_matrix` along both axes, exact for any factor, as OpenCV's ``INTER_AREA``.
    Along the rows only the band of input rows each output row covers is read (a compiled
    loop: one multiply-add per input pixel, instead of a dense product's ``h`` per pixel),
    then the same along the columns of that small result.  No BLAS call: BLAS threads would
    compete with a video decoder's.

    uint8, float32 and float64 in this machine's byte order are read as they are; any other
    real dtype (other integers, bool, float16, either byte order) is first converted to
    float32, the type of the result.

    Raises
    ------
    ValueError
        If ``y`` is not a non-empty 2-d array.
    TypeError
        If its dtype is not real numbers (complex, object, strings).
    """
    from . import _image_kernels

    if not isinstance(y, np.ndarray) or y.ndim != 2 or y.size == 0:
        raise ValueError(
            f"y must be a non-empty 2-d array; got {getattr(y, 'shape', type(y).__name__)}"
        )
    h, w = _check_size((h, w))
    if y.dtype.kind not in "biuf":
        raise TypeError(f"y must hold real numbers; got dtype {y.dtype}")
    if y.dtype not in _KERNEL_DTYPES:  # (== compares the byte order too)
        # numba compiles neither float16 nor the other byte order; one float32 kernel serves
        # every other integer type rather than one compilation per type
        y = y.astype(np.float32)
    kernel = _image_kernels.band
    rows = np.zeros((h, y.shape[1]), np.float32)
    kernel(y, *_row_band(h, y.shape[0]), rows)
    cols = np.zeros((w, h), np.float32)
    kernel(rows.T, *_row_band(w, y.shape[1]), cols)
    return np.ascontiguousarray(cols.T)


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


def _decode(path: Path, bayer: str | None, notes: dict | None = None) -> np.ndarray:
    """Decode one file to a float32 gray array in [0, 1] at its native size, upright (its
    EXIF orientation applied).

    A 16-bit colour file, of which Pillow reads only the high byte of each sample, and a file
    of integers wider than a byte whose values are all at most 255 (8-bit data saved wide) are
    appended to ``notes["high byte"]`` with the raw mode and ``notes["low range"]`` with the
    pixel type (for the caller's one warning of each kind), or warned about here (once per
    folder) when ``notes`` is None.
    """
    img: Image.Image  # the opened file, then maybe a converted copy
    try:
        # Opened from a file object, not a path, so that Pillow never memory-maps it: its
        # mmap path takes the upright size of an uncompressed TIFF turned by its orientation
        # tag (5-8) for the stored one and garbles the pixels (Pillow 13).
        with open(path, "rb") as fh, Image.open(fh) as img:
            _check_pixels(path, img)
            _check_mode(path, img)
            rawmode = _high_byte_rawmode(img)  # (from the tiles, which load() clears)
            if bayer is not None and img.format == "TIFF" and _orientation(path, img) != 1:
                # Pillow turns a TIFF itself while loading it: a mosaic turned before it is
                # demosaiced changes its pattern, and the tag is gone by then
                raise ImageReadError(
                    f"{path}: a raw Bayer TIFF with an orientation tag (Pillow turns it before "
                    "it can be demosaiced, which changes its pattern); save it without the tag "
                    "or as PNG"
                )
            img.load()
            # (Pillow turns a TIFF itself while loading it, and drops the tag)
            transpose = _ORIENTATION.get(_orientation(path, img))
            if transpose is not None and bayer is None:
                # (a Bayer mosaic is turned after demosaicing: turning it changes its pattern)
                img = ImageOps.exif_transpose(img)
            mode = img.mode
            if mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            elif mode in ("LA", "PA"):
                img = img.convert("L")
            elif mode == "La":  # (premultiplied: LA divides the alpha out, which L ignores)
                img = img.convert("LA").convert("L")
            elif mode in ("CMYK", "YCbCr", "RGBa"):
                img = img.convert("RGB")
            elif mode == "1":
                img = img.convert("L")
            arr = np.array(img)
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {path}") from None
    except UnidentifiedImageError:
        raise ImageReadError(f"{path}: not a readable image file") from None
    except Image.DecompressionBombError as exc:
        raise ImageReadError(
            f"{path}: declares more pixels than PIL.Image.MAX_IMAGE_PIXELS allows; refused "
            f"before decoding ({exc})"
        ) from None
    except IsADirectoryError:
        raise ImageReadError(f"{path}: is a folder, not an image file") from None
    except PermissionError:
        raise ImageReadError(f"{path}: not readable (permission denied)") from None
    except (OSError, SyntaxError, ValueError) as exc:
        if isinstance(exc, ImageReadError):
            raise
        raise ImageReadError(f"{path}: corrupt or truncated image ({exc})") from None
    try:
        if bayer is not None:
            if arr.ndim != 2:
                raise ImageReadError(
                    f"{path}: expected a single-channel raw Bayer image; got shape {arr.shape}"
                )
            gray = demosaic_bilinear(arr, bayer) @ _LUMA
            if transpose is not None:
                gray = np.asarray(Image.fromarray(gray.astype(np.float32)).transpose(transpose))
        else:
            gray = to_gray(arr)
    except ImageReadError:
        raise
    except ValueError as exc:
        raise ImageReadError(f"{path}: {exc}") from None
    found = []
    if rawmode is not None:
        found.append(("high byte", rawmode))
    if bayer is None and arr.dtype.kind in "iu" and arr.dtype.itemsize > 1 and arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo >= 0 and 0 < hi <= 255:
            found.append(("low range", f"{8 * arr.dtype.itemsize}-bit"))
    for kind, detail in found:
        if notes is None:
            _warn_frames(kind, [(path, detail)])
        else:
            notes[kind].append((path, detail))
    return gray


def _check_mode(path: Path, img) -> None:
    """Refuse a colour mode that :func:`_decode` would misread (LAB, HSV: not RGB)."""
    if img.mode not in _DECODED_MODES:
        raise ImageReadError(
            f"{path}: colour mode {img.mode} is not supported; convert the image to RGB or gray"
        )


def _high_byte_rawmode(img) -> str | None:
    """The raw mode of a file whose colour samples of more than 8 bits (16-bit PNG, TIFF, SGI;
    a PPM with a maxval over 255) Pillow reads into 8 bits, or None."""
    if img.mode.startswith(("I", "F")):  # 16-bit gray: full precision
        return None
    for tile in img.tile:
        args = tile[3] if len(tile) > 3 else None
        rawmode = args if isinstance(args, str) else None
        if isinstance(args, tuple) and args and isinstance(args[0], str):
            rawmode = args[0]
            # a PPM of more than 8 bits: Pillow's "ppm" decoder rescales it to 8 bits
            if tile[0].startswith("ppm") and len(args) > 1 and args[1] > 255:
                return f"{rawmode}, maxval {args[1]}"
        if rawmode is not None and _HIGH_BYTE_RAWMODES.fullmatch(rawmode):
            return rawmode
    return None


_HIGH_BYTE_ADVICE = (
    "Pillow reads only the high byte of each sample (8 bits; the rest is lost): save the frames "
    "as 16-bit gray, which keeps full precision, or as 8-bit colour"
)
_LOW_RANGE_ADVICE = (
    "{} integer pixels whose values are all at most 255: read on the 16-bit scale (divided by "
    "65535) the frame is nearly black, at most 0.4% of white; if these are 8-bit values, save "
    "the frames as 8-bit (a dark 16-bit frame is read right: nothing is changed)"
)
#: Folders already warned about by :func:`load_image` (a folder source reads frame by frame),
#: per kind of warning.
_warned_folders: dict[str, set[str]] = {"high byte": set(), "low range": set()}


def _warn_frames(kind: str, found: list, n_frames: int | None = None) -> None:
    """One warning of ``kind`` ("high byte" or "low range") naming the first of ``found``
    ((path, detail) pairs): per call of :func:`load_images` (``n_frames`` loaded), or per
    folder for frames loaded one by one."""
    path, detail = found[0]
    if n_frames is None:
        folder = os.path.abspath(path.parent)
        if folder in _warned_folders[kind]:
            return
        _warned_folders[kind].add(folder)
    more = f" (and {len(found) - 1} more of the {n_frames} frames)" if len(found) > 1 else ""
    if kind == "high byte":
        logger.warning(
            "%s%s: colour of more than 8 bits per sample (raw mode %s); %s",
            path,
            more,
            detail,
            _HIGH_BYTE_ADVICE,
        )
    else:
        logger.warning("%s%s: %s", path, more, _LOW_RANGE_ADVICE.format(detail))


def _orientation(path: Path, img, warn: bool = True) -> int:
    """The EXIF Orientation of an opened file (1, upright, when it has none, or when its EXIF
    block cannot be read: a warning names the file, as Pillow reads such a JPEG as stored;
    none with ``warn`` False)."""
    try:
        value = img.getexif().get(ExifTags.Base.Orientation, 1)
    except (SyntaxError, ValueError, TypeError, KeyError, IndexError, OSError, struct.error) as exc:
        # (the kinds Pillow's EXIF parser raises on a damaged block)
        if warn:
            logger.warning(
                "%s: its EXIF metadata cannot be read (%s): read as stored, not turned by an "
                "orientation tag",
                path,
                exc,
            )
        return 1
    return value if isinstance(value, int) else 1


def _check_pixels(path: Path, img) -> None:
    """Refuse, from the header alone, a frame too large to decode."""
    w, h = img.size
    limit = Image.MAX_IMAGE_PIXELS
    if limit is not None and w * h > limit:
        raise ImageReadError(
            f"{path}: declares {w}x{h} pixels ({w * h / 1e6:.0f} MP), more than the "
            f"{limit / 1e6:.0f} MP that PIL.Image.MAX_IMAGE_PIXELS allows; refused before "
            "decoding (resize it, or raise that limit if the file is trusted)"
        )
    # decoded bands plus the float32 gray copy and its resize
    bands = max(1, len(img.getbands()))
    check_memory(w * h * (bands * 4 + 8), f"{path} ({w}x{h} pixels, {bands} bands)")


def load_image(path, size=DEFAULT_SIZE, *, bayer: str | None = None) -> np.ndarray:
    """Load one image file as float32 gray in [0, 1], area-resized to ``size``.

    Parameters
    ----------
    path : str or Path
        PNG, JPEG or any format Pillow reads; 8 or 16 bit; gray, RGB or RGBA (or CMYK, YCbCr,
        a palette).  It is turned upright by its EXIF orientation tag.  Colour of more than 8
        bits per sample is read by its high byte only (Pillow's decoding): a warning names the
        file (once per folder); 16-bit gray keeps full precision.
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
        If it is corrupt, truncated or not an image, holds float values outside [0, 1] or
        NaN, has a colour mode that is not RGB in some form (LAB, HSV), is a raw Bayer TIFF
        with an orientation tag, or declares more pixels than ``PIL.Image.MAX_IMAGE_PIXELS``
        (the message names the file).  An EXIF block that cannot be read is warned about and
        the frame read as stored.
    ValueError, TypeError
        For a ``bayer`` that is not one of the patterns, or a bad ``size``.
    """
    size = _check_size(size)
    if bayer is not None and (not isinstance(bayer, str) or bayer.lower() not in _BAYER_PATTERNS):
        raise ValueError(f"bayer must be None or one of {_BAYER_PATTERNS}; got {bayer!r}")
    with warnings.catch_warnings():
        # Pillow warns on very large images; _check_pixels refuses those itself.
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        gray = _decode(Path(path), bayer)
    return resize_area(gray, size)


#: a number: a decimal (digits, a dot, digits, not part of a longer dotted run such as
#: ``v1.10.0`` or ``10.0.0.2``, whose parts are whole numbers), else a run of digits
_NUMBER = re.compile(r"((?<!\d\.)(?<!\d)\d+\.\d+(?!\d)(?!\.\d)|\d+)")
_WHOLE = re.compile(r"(\d+)")


def _natural_key(path: Path, number=_NUMBER):
    """Natural order: runs of digits by value, a decimal fraction too (``1600000000.05.png``,
    a timestamp written by ``str(float)``, before ``1600000000.1.png``; a dotted run of more
    than two numbers, ``v1.10.0``, is whole numbers), text without case; names equal but for
    that (``1.png``, ``01.png``; ``a2.png``, ``A2.png``) by the name itself, so the order never
    depends on the folder listing's.  ``number``: :data:`_WHOLE` reads every run of digits as
    a whole number (``1.10`` after ``1.2``)."""
    parts = number.split(path.name)
    # split alternates text and number, so equal positions always hold the same type
    key = [Decimal(p) if i % 2 else p.lower() for i, p in enumerate(parts)]
    return key, path.name


def _sorted_frames(folder: Path, files: list[Path]) -> list[Path]:
    """``files`` in natural order, with a warning where reading a fraction as a decimal or
    as a whole number gives another order (``cam1.10``, ``1600000000.300``: a version, or
    nanoseconds without their zeros?)."""
    ordered = sorted(files, key=_natural_key)
    whole = sorted(files, key=lambda f: _natural_key(f, _WHOLE))
    if ordered != whole:
        first = next(i for i, (a, b) in enumerate(zip(ordered, whole, strict=True)) if a != b)
        logger.warning(
            "%s: the numbers with a fraction in the frames' names sort one way read as decimals "
            "and another read as whole numbers (%s before %s as decimals, after as whole "
            "numbers): read as decimals; zero-pad the fractions to the same length, or rename "
            "the frames, if that is not their order",
            folder,
            ordered[first].name,
            whole[first].name,
        )
    return ordered


def _refusal(entry: os.DirEntry, extensions: tuple[str, ...]) -> str | None:
    """Why a (non-hidden) folder entry is not a frame, or None when it is one."""
    try:
        st = os.stat(entry.path)  # follows links
    except FileNotFoundError:
        try:
            target = os.readlink(entry.path)
        except OSError:
            target = "?"
        return f"dangling symbolic link (its target {target} does not exist)"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "symbolic link loop"
        return f"cannot be examined ({exc.strerror})"
    if stat.S_ISDIR(st.st_mode):
        return "a sub-folder: frames must be files directly in the image folder"
    if not stat.S_ISREG(st.st_mode):
        kind = "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "not a regular file"
        if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
            kind = "a device"
        elif stat.S_ISSOCK(st.st_mode):
            kind = "a socket"
        return kind
    suffix = os.path.splitext(entry.name)[1].lower()
    if suffix not in extensions:
        shown = " ".join(extensions)
        if suffix in Image.registered_extensions():
            return f"a {suffix} image, a format not read here (frames must end in {shown})"
        what = f"extension {suffix!r}" if suffix else "no extension"
        return f"not an image file ({what}; frames must end in {shown}): move it out"
    if not os.access(entry.path, os.R_OK):
        return "not readable (permission denied)"
    return None


def list_images(folder, extensions: Sequence[str] = IMAGE_EXTENSIONS) -> list[Path]:
    """List the frames of an image folder in natural order (``2.png`` before ``10.png``).

    Every entry is a frame or refused by name (see :data:`FOLDER_RULES`): a frame is a
    regular file, or a link to one, whose extension is in ``extensions`` (any case); hidden
    entries (name starting with ``.``) are skipped; anything else (another extension, a
    sub-folder, a dangling link, a link loop, a FIFO, a device, an unreadable file) is refused,
    so a stray file can never shift an index-matched ground truth.

    Raises
    ------
    FileNotFoundError
        If the folder does not exist.
    NotADirectoryError
        If it is a file.
    ImageFolderError
        Naming the first entry that is not a frame and why (and how many more there are).
    ValueError
        If it holds no image file.
    """
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"image folder not found: {folder}")
    if not folder.is_dir():
        raise NotADirectoryError(f"expected a folder of images; got a file: {folder}")
    if isinstance(extensions, str):
        raise TypeError(
            f"extensions must be a sequence of suffixes such as ('.png',); got {extensions!r}"
        )
    exts = tuple(e.lower() for e in extensions)
    if not all(e.startswith(".") for e in exts):
        raise ValueError(f"extensions must start with a dot, such as '.png'; got {extensions!r}")
    files, hidden, refused = [], 0, []
    with os.scandir(folder) as entries:
        for entry in entries:
            if entry.name.startswith("."):
                hidden += 1
                continue
            reason = _refusal(entry, exts)
            if reason is None:
                files.append(Path(entry.path))
            else:
                refused.append((entry.name, reason))
    if refused:
        name, reason = min(refused)
        more = f" (and {len(refused) - 1} more such entries)" if len(refused) > 1 else ""
        raise ImageFolderError(f"{folder / name}: {reason}{more}")
    if hidden:
        logger.info("%s: skipped %d hidden entries (names starting with '.')", folder, hidden)
    if not files:
        raise ValueError(f"no image files ({', '.join(exts)}) in folder {folder}")
    return _sorted_frames(folder, files)


def default_cache_dir() -> Path:
    """The cache folder.

    ``$FLYVPR_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/flyvpr``, else ``~/.cache/flyvpr``.
    """
    env = os.environ.get("FLYVPR_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "flyvpr"


#: Format name and version written into every cache file.
_CACHE_FORMAT = "flyvpr-image-cache"
_CACHE_VERSION = 3  # 3: exact area weights at any factor (Pillow's box filter before)


def stat_image(path: Path) -> os.stat_result:
    """``path.stat()``, or a FileNotFoundError naming the image file (one that went between
    listing and reading)."""
    try:
        return path.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {path}") from None


def _cache_key(paths: Sequence[Path], size, bayer) -> str:
    """Key of a stack: every file's path, size, mtime, device, inode and ctime, and settings.

    The status-change time (ctime) is set by the kernel on every write, rename or ``touch``
    and cannot be set back, so a picture replaced with the same size and mtime still gets a
    new key; a ``chmod`` also changes it (the stack is then decoded again, which is safe).
    """
    entries = []
    for p in paths:
        st = stat_image(p)
        # (device, inode) names the file itself, so the path need not be resolved (slow)
        entries.append(
            [os.path.abspath(p), st.st_size, st.st_mtime_ns, st.st_dev, st.st_ino, st.st_ctime_ns]
        )
    blob = json.dumps(
        {
            "v": _PREPROCESS_VERSION,
            "decode": _DECODE_VERSION,
            "size": list(size),
            "bayer": bayer,
            "files": entries,
        }
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


def _write_cache(path: Path, array: np.ndarray, key: str) -> None:
    meta = {
        "format": _CACHE_FORMAT,
        "version": _CACHE_VERSION,
        "key": key,
        "shape": list(array.shape),
    }
    with atomic_open(path, "wb") as fh:
        zf = ZipWriter(fh, "w", zipfile.ZIP_STORED)
        try:
            zf.writestr("meta.json", json.dumps(meta))
            with zf.open("images.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, array, allow_pickle=False)
        except BaseException:
            # an interruption or a failed write: the archive is dropped unclosed (its close
            # would raise over a member still open, now and again from __del__); the temporary
            # file goes with atomic_open
            zf.fp = None
            raise
        zf.close()


def _read_cache(path: Path, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """The cached stack, or ValueError saying why the entry cannot be trusted."""
    if path.stat().st_size == 0:
        raise ValueError("empty file")
    try:
        with zipfile.ZipFile(path) as zf:
            names = sorted(zf.namelist())
            if names != ["images.npy", "meta.json"]:
                raise ValueError(f"unexpected entries {names}")
            if zf.getinfo("meta.json").file_size > 4096:
                raise ValueError("oversized metadata")
            meta = json.loads(zf.read("meta.json"))
            if not isinstance(meta, dict) or meta.get("format") != _CACHE_FORMAT:
                raise ValueError("not a flyvpr image cache")
            if meta.get("version") != _CACHE_VERSION or meta.get("key") != key:
                raise ValueError("written for other files or settings (swapped or renamed)")
            # read_npz_member reads to the end, so zipfile checks the entry's CRC-32
            arr = read_npz_member(zf, "images", str(path), dtype=np.float32, shape=shape)
    except ValueError:
        raise
    except Exception as exc:  # zipfile raises many kinds on a damaged archive
        raise ValueError(f"{type(exc).__name__}: {exc}") from None
    if not np.isfinite(arr).all() or (arr.size and (arr.min() < 0.0 or arr.max() > 1.0)):
        raise ValueError("pixels are NaN or outside [0, 1]")
    return arr


def _want_progress(progress) -> bool:
    if progress is None:
        return sys.stderr.isatty()
    return bool(progress)


#: aspect ratios (width / height) closer than this, relatively, count as one
ASPECT_TOLERANCE = 0.01


def same_aspect(shape_a, shape_b) -> bool:
    """Whether two image shapes ``(H, W)`` have the same aspect ratio, within
    ``ASPECT_TOLERANCE`` (relative)."""
    (ha, wa), (hb, wb) = shape_a[:2], shape_b[:2]
    return abs((wa * hb) / (ha * wb) - 1.0) <= ASPECT_TOLERANCE


def upright_shape(path) -> tuple[int, int] | None:
    """``(H, W)`` of an image file as it is decoded (turned by its EXIF orientation), read
    from its header only; None where the file cannot be opened (its decoding says why)."""
    try:
        with open(path, "rb") as fh, Image.open(fh) as img:
            w, h = img.size
            # (as the decoding turns it; a damaged EXIF block: as stored, the decoding warns)
            orientation = _orientation(Path(path), img, warn=False)
    except (OSError, ValueError, SyntaxError, Image.DecompressionBombError):
        return None
    return (w, h) if orientation in (5, 6, 7, 8) else (h, w)


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

    Each file is decoded as by :func:`load_image`.  Files of colour with more than 8 bits per
    sample, read by their high byte only, are named in one warning per call; so are files of
    16 or 32-bit integers whose values are all at most 255 (8-bit data saved wide: read on the
    16-bit scale they come out nearly black) and files of another aspect ratio than the
    first (each is squeezed to ``size``).  The warnings come when the files are decoded, not
    on a cache hit.

    Parameters
    ----------
    paths : sequence of str or Path
        Files in traverse order.
    size : (int, int)
        Target (H, W).
    cache : bool or path
        ``True`` caches under :func:`default_cache_dir`, a path caches there,
        ``False`` never reads or writes a cache.  A cache entry is used only if its key,
        shape, dtype, CRC-32 checksum and value range all check out; otherwise a warning
        names it and it is rebuilt.
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
    flyvpr._validation.InsufficientMemoryError
        If the stack would not fit in the available memory (before decoding anything).
    FileNotFoundError, ImageReadError
        For a missing or undecodable file; nothing is cached then.
    """
    from tqdm.auto import tqdm

    size = _check_size(size)
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("paths is empty: expected at least one image file")
    shape = (len(paths), *size)
    check_memory(
        array_nbytes(shape, np.float32),
        f"{len(paths)} images at size {size[0]}x{size[1]} (float32)",
    )
    cache_file = None
    if cache is not False and cache is not None:
        cache_dir = default_cache_dir() if cache is True else Path(cache)
        key = _cache_key(paths, size, bayer)
        cache_file = cache_dir / f"images-{key}.npz"
        if cache_file.is_file():
            try:
                arr = _read_cache(cache_file, key, shape)
                logger.debug("image cache hit: %s", cache_file)
                return arr
            except (OSError, ValueError) as exc:
                raise_interruption(exc)
                logger.warning("image cache %s is unusable (%s); rebuilding it", cache_file, exc)
    out = np.empty(shape, dtype=np.float32)
    notes: dict = {"high byte": [], "low range": []}
    first: tuple | None = None  # the first file and its upright (H, W)
    other: list = []  # files of another aspect ratio than the first's, with theirs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        for i, p in enumerate(
            tqdm(paths, desc=desc, unit="img", disable=not _want_progress(progress), leave=False)
        ):
            img = _decode(p, bayer, notes)
            if first is None:
                first = (p, img.shape)
            elif not same_aspect(img.shape, first[1]):
                other.append((p, img.shape))
            out[i] = resize_area(img, size)
    for kind, found in notes.items():
        if found:
            _warn_frames(kind, found, len(paths))
    if other:
        (path, (h, w)), (path0, (h0, w0)) = other[0], first  # type: ignore[misc]
        logger.warning(
            "%d of %d images have another aspect ratio than the first, %s (%dx%d), the first "
            "of them being %s (%dx%d): each image is resized to %dx%d whatever its own shape, "
            "so these are stretched unlike the others; crop or pad them to one aspect ratio",
            len(other),
            len(paths),
            path0,
            w0,
            h0,
            path,
            w,
            h,
            size[1],
            size[0],
        )
    if cache_file is not None:
        try:
            _write_cache(cache_file, out, key)
        except (OSError, ValueError) as exc:  # a read-only cache must not stop the work
            raise_interruption(exc)  # ... but a Ctrl-C or SIGTERM while writing it must
            logger.warning("could not write image cache %s (%s)", cache_file, exc)
    return out
