"""Reading ``.npy`` files and ``.npz`` members without trusting their headers.

``numpy.load`` allocates whatever shape a header claims before it reads a byte of data, so a
100-byte file that claims a (10**6, 10**6) array, or a 1 MB deflate bomb inside an ``.npz``,
costs gigabytes (or a ``MemoryError``) before it is refused.  The readers here parse the
header first and refuse, naming the file, before allocating:

* object (pickled) dtypes, which could execute code;
* a shape or dtype other than the caller expects;
* a data size that disagrees with the file (a truncated or padded file, a zip member whose
  declared size does not match its header);
* an array larger than the memory available (:func:`flyvpr._validation.check_memory`).

Only then is the data read, in chunks into the final array, so the peak memory is the array
itself.  ``.npz`` members must be stored uncompressed (as flyvpr writes them), so no member can
expand beyond the bytes it occupies on disk.  Kept free of flyvpr imports other than
``_validation`` so every layer can use it.
"""

from __future__ import annotations

import os
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ._validation import check_memory, format_bytes

__all__ = ["ArrayFileError", "npy_header", "load_npy", "npz_member_header", "read_npz_member"]

#: largest header accepted (numpy's own default limit)
_MAX_HEADER = 10_000
#: bytes copied per read from a zip member
_CHUNK = 1 << 20


class ArrayFileError(ValueError):
    """A ``.npy`` file or ``.npz`` member that is malformed, unexpected or too large."""


def _parse_header(fh, what: str):
    try:
        with warnings.catch_warnings():
            # numpy evaluates the header's text as a Python literal: a corrupt header can
            # make Python warn about its escapes before the parse fails (the error says it)
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", SyntaxWarning)
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh, _MAX_HEADER)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh, _MAX_HEADER)
            else:
                raise ArrayFileError(f"{what}: unsupported .npy format version {version}")
    except ArrayFileError:
        raise
    except Exception as exc:  # numpy's header parser raises many kinds on malformed text
        raise ArrayFileError(f"{what}: not a valid .npy array ({type(exc).__name__})") from None
    if not isinstance(shape, tuple) or any(
        not isinstance(d, int) or isinstance(d, bool) or d < 0 for d in shape
    ):
        raise ArrayFileError(f"{what}: invalid array shape {shape!r} in the header")
    return shape, bool(fortran), np.dtype(dtype)


def _check_expected(what, shape, dtype, want_dtype, want_shape):
    if dtype.hasobject:
        raise ArrayFileError(
            f"{what}: holds Python objects (a pickle), which are never loaded: it could run code"
        )
    if want_dtype is not None and dtype != np.dtype(want_dtype):
        raise ArrayFileError(f"{what}: expected dtype {np.dtype(want_dtype)}; got {dtype}")
    if want_shape is not None:
        ok = len(shape) == len(want_shape) and all(
            w is None or w == d for w, d in zip(want_shape, shape, strict=False)
        )
        if not ok:
            shown = ", ".join("*" if w is None else str(w) for w in want_shape)
            shown = f"({shown},)" if len(want_shape) == 1 else f"({shown})"
            raise ArrayFileError(f"{what}: expected shape {shown}; got {shape}")


def _nbytes(shape, dtype) -> int:
    n = dtype.itemsize
    for d in shape:
        n *= d
    return n


def npy_header(path, what: str | None = None):
    """``(shape, fortran_order, dtype)`` of a ``.npy`` file, reading only its header.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ArrayFileError
        If the header is malformed.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        return _parse_header(fh, what or str(path))


def load_npy(path, *, what: str | None = None, dtype=None, shape=None):
    """Read a ``.npy`` file, refusing before allocation anything unexpected or too large.

    Parameters
    ----------
    path : str or Path
    what : str, optional
        How messages name the file (default: its path).
    dtype : dtype-like, optional
        Required dtype.
    shape : tuple of (int or None), optional
        Required shape; ``None`` entries accept any length.

    Returns
    -------
    ndarray

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ArrayFileError
        For a malformed header, a pickled (object) array, another dtype or shape, or a data
        size that disagrees with the file's size.
    flyvpr._validation.InsufficientMemoryError
        If the array is larger than the available memory.
    """
    path = Path(path)
    what = what or str(path)
    with open(path, "rb") as fh:
        a_shape, fortran, a_dtype = _parse_header(fh, what)
        _check_expected(what, a_shape, a_dtype, dtype, shape)
        nbytes = _nbytes(a_shape, a_dtype)
        have = os.fstat(fh.fileno()).st_size - fh.tell()
        if have != nbytes:
            raise ArrayFileError(
                f"{what}: header declares {a_dtype} {a_shape} ({format_bytes(nbytes)}) but the "
                f"file holds {format_bytes(have)} of data (truncated or not a .npy file)"
            )
        check_memory(nbytes, f"{what} (array {a_dtype} {a_shape})")
        count = nbytes // a_dtype.itemsize if a_dtype.itemsize else 0
        data = np.fromfile(fh, dtype=a_dtype, count=count)
    if data.size != count:
        raise ArrayFileError(f"{what}: file ended early (changed while being read?)")
    return data.reshape(a_shape, order="F" if fortran else "C")


def npz_member_header(zf: zipfile.ZipFile, name: str, what: str):
    """``(shape, fortran_order, dtype, info)`` of the member ``name`` (``.npy`` added).

    Only uncompressed (stored) members are read: flyvpr never writes compressed ones, and
    refusing them rules out deflate bombs whatever their headers claim.

    Raises
    ------
    ArrayFileError
        If the member is missing or compressed, its header is malformed, or its declared size
        disagrees with the header.
    """
    member = name if name.endswith(".npy") else name + ".npy"
    try:
        info = zf.getinfo(member)
    except KeyError:
        raise ArrayFileError(f"{what}: missing entry {name!r}") from None
    if info.compress_type != zipfile.ZIP_STORED:
        # flyvpr writes uncompressed entries; refusing the others rules out deflate bombs
        raise ArrayFileError(
            f"{what}, entry {name!r}: is compressed; flyvpr reads uncompressed entries only"
        )
    try:
        with zf.open(info) as fh:
            shape, fortran, dtype = _parse_header(fh, f"{what}, entry {name!r}")
            header_len = fh.tell()
    except ArrayFileError:
        raise
    except Exception as exc:  # zipfile raises many kinds on a damaged member
        raise ArrayFileError(
            f"{what}, entry {name!r}: unreadable ({type(exc).__name__}: {exc})"
        ) from None
    nbytes = _nbytes(shape, dtype)
    if info.file_size - header_len != nbytes:
        raise ArrayFileError(
            f"{what}, entry {name!r}: header declares {dtype} {shape} ({format_bytes(nbytes)}) "
            f"but the entry holds {format_bytes(info.file_size - header_len)}"
        )
    return shape, fortran, dtype, info


def read_npz_member(zf: zipfile.ZipFile, name: str, what: str, *, dtype=None, shape=None):
    """Read one ``.npz`` member after checking its header, dtype, shape and size.

    The data are copied in 1 MB chunks into the final array, so a compressed member costs
    no more memory than its (checked) size.  See :func:`load_npy` for the checks.
    """
    a_shape, fortran, a_dtype, info = npz_member_header(zf, name, what)
    label = f"{what}, entry {name!r}"
    _check_expected(label, a_shape, a_dtype, dtype, shape)
    nbytes = _nbytes(a_shape, a_dtype)
    check_memory(nbytes, f"{label} (array {a_dtype} {a_shape})")
    out = np.empty(a_shape, dtype=a_dtype, order="F" if fortran else "C")
    view = out.reshape(-1, order="A").view(np.uint8).data if nbytes else None
    try:
        with zf.open(info) as fh:
            _parse_header(fh, label)
            done = 0
            while done < nbytes:
                chunk = fh.read(min(_CHUNK, nbytes - done))
                if not chunk:
                    break
                assert view is not None  # nbytes > 0
                view[done : done + len(chunk)] = chunk
                done += len(chunk)
            if fh.read(1):
                raise ArrayFileError(f"{label}: more data than its header declares")
    except ArrayFileError:
        raise
    except Exception as exc:  # a CRC error, a short read, ...
        raise ArrayFileError(f"{label}: damaged ({type(exc).__name__}: {exc})") from None
    if done != nbytes:
        raise ArrayFileError(f"{label}: entry ended early (truncated)")
    return out
