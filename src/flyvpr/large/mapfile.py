"""Memory-mapped map files of compact codes: open a 10-million-place map in well under a second.

Layout of a file (little-endian; a container of named raw arrays, no pickle anywhere)::

    bytes 0-15       b"FLYVPRLM" and 8 reserved bytes
    arrays           each raw, C-ordered, at an offset aligned to 4096 bytes
    header           UTF-8 JSON: format, version, kind, map_id, arrays {name: {dtype,
                     shape, offset}}, metadata
    trailer          header offset (uint64), header length (uint64), b"FLYVPRLM"

The header sits at the end so that a writer can stream the arrays first.  Opening reads the
trailer and the header and maps each array read-only (``numpy.memmap``): nothing is read until
used, so resident memory grows only with the pages a run touches.  Every field is checked
(dtypes from a short list, shapes, offsets within the file): a corrupt, truncated or foreign
file is refused with an error naming it.

A map file (``kind="map"``) holds ``codes`` (uint8, (n_places, n_bytes)), optionally
``positions`` (float64, (n_places, n_dims)), free JSON ``metadata`` and more named arrays
(:meth:`LargeMapWriter.add_array`: a map built from a recording keeps its encoder and each
place's timestamp and frame there, :mod:`flyvpr.large.recording`).  An index file
(``kind="mih"``) holds the tables of a :class:`~flyvpr.large.index.MultiIndexHash` and the
``map_id`` of the map it indexes.  Both are written atomically (a temporary file renamed at
the end).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from .._io import atomic_open
from .._validation import check_positive_int

__all__ = [
    "LargeMap",
    "LargeMapWriter",
    "MapFileError",
    "load_index",
    "open_large_map",
    "save_index",
    "write_large_map",
]

MAGIC = b"FLYVPRLM"
FORMAT = "flyvpr-large-map"
VERSION = 1
_ALIGN = 4096
_TRAILER = struct.Struct("<QQ8s")
#: dtypes a file may hold (never objects)
_DTYPES = {"|u1", "<u4", "<i4", "<i8", "<f4", "<f8", "<u2"}
#: largest header accepted
_MAX_HEADER = 1 << 24


class MapFileError(ValueError):
    """A map or index file that is malformed, truncated or of another kind."""


class ForeignIndexError(MapFileError):
    """An index file written for another map than the one it is opened with."""


def _aligned(n: int) -> int:
    return -(-n // _ALIGN) * _ALIGN


class _ArrayFile:
    """Writes named arrays into a container file; ``reserve`` lays out an array to be
    filled in slices, ``add`` writes a whole one."""

    def __init__(self, path, kind: str, metadata: dict | None, extra: dict | None = None):
        self.path = Path(path)
        self._stack = ExitStack()
        self._fh = self._stack.enter_context(atomic_open(self.path, "w+b"))
        self._fh.write(MAGIC + bytes(8))
        self._end = len(MAGIC) + 8
        self._arrays: dict = {}
        self._header = {"format": FORMAT, "version": VERSION, "kind": kind, **(extra or {})}
        self._header["metadata"] = metadata or {}

    def reserve(self, name: str, dtype, shape) -> int:
        dtype = np.dtype(dtype)
        offset = _aligned(self._end)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        self._arrays[name] = {"dtype": dtype.str, "shape": list(shape), "offset": offset}
        self._end = offset + nbytes
        return offset

    def write_at(self, offset: int, array: np.ndarray) -> None:
        self._fh.seek(offset)
        self._fh.write(np.ascontiguousarray(array).data)

    def add(self, name: str, array) -> None:
        array = np.asarray(array)
        self.write_at(self.reserve(name, array.dtype, array.shape), array)

    def close(self) -> None:
        self._header["arrays"] = self._arrays
        text = json.dumps(self._header, allow_nan=False).encode("utf-8")
        self._fh.truncate(self._end)  # reserved space never written reads as zeros
        self._fh.seek(self._end)
        self._fh.write(text)
        self._fh.write(_TRAILER.pack(self._end, len(text), MAGIC))
        self._stack.close()

    def abort(self, exc: BaseException) -> None:
        self._stack.__exit__(type(exc), exc, exc.__traceback__)


def _read_container(path, kind: str) -> tuple[dict, dict]:
    """(header, arrays as read-only memmaps) of a container file, every field checked."""
    path = Path(path)
    size = os.stat(path).st_size  # FileNotFoundError names the path
    what = f"{path}"
    if size < 16 + _TRAILER.size:
        raise MapFileError(f"{what}: too short ({size} bytes) to be a flyvpr {kind} file")
    with open(path, "rb") as fh:
        if fh.read(8) != MAGIC:
            raise MapFileError(f"{what}: not a flyvpr {kind} file (no {MAGIC!r} at the start)")
        fh.seek(size - _TRAILER.size)
        offset, length, magic = _TRAILER.unpack(fh.read(_TRAILER.size))
        if magic != MAGIC:
            raise MapFileError(f"{what}: truncated or corrupt (no trailer at the end)")
        if length > _MAX_HEADER or offset + length != size - _TRAILER.size:
            raise MapFileError(f"{what}: corrupt trailer (header at {offset}, {length} bytes)")
        fh.seek(offset)
        try:
            header = json.loads(fh.read(length).decode("utf-8"))
        except ValueError:  # not UTF-8, not JSON, or an integer past Python's digit limit
            raise MapFileError(f"{what}: corrupt header (not JSON)") from None
        except RecursionError:  # json recurses once per level of nesting
            raise MapFileError(f"{what}: corrupt header (JSON nested too deeply)") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise MapFileError(f"{what}: not a {FORMAT} file")
    if header.get("version") != VERSION:
        raise MapFileError(f"{what}: format version {header.get('version')!r}; expected {VERSION}")
    if header.get("kind") != kind:
        raise MapFileError(f"{what}: a {header.get('kind')!r} file; expected a {kind!r} file")
    specs = header.get("arrays")
    if not isinstance(specs, dict):
        raise MapFileError(f"{what}: header lists no arrays")
    arrays = {}
    for name, spec in specs.items():
        try:
            dtype = np.dtype(spec["dtype"]) if spec["dtype"] in _DTYPES else None
            shape = tuple(spec["shape"])
            start = spec["offset"]
            if not all(type(v) is int for v in (*shape, start)):  # (not 60.7 read as 60)
                raise TypeError
        except (KeyError, TypeError, ValueError):
            raise MapFileError(f"{what}: malformed entry for array {name!r}") from None
        if dtype is None:
            raise MapFileError(f"{what}: array {name!r} has unsupported dtype {spec['dtype']!r}")
        if any(v < 0 for v in shape) or start < 16:
            raise MapFileError(f"{what}: array {name!r} has a bad shape or offset")
        nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no wrap-around
        if start + nbytes > offset:
            raise MapFileError(
                f"{what}: truncated: array {name!r} needs bytes {start}..{start + nbytes}, "
                f"the data ends at {offset}"
            )
        if nbytes == 0:
            arrays[name] = np.empty(shape, dtype)
        else:
            arrays[name] = np.memmap(path, dtype=dtype, mode="r", offset=start, shape=shape)
    return header, arrays


class LargeMap:
    """An opened map file: memory-mapped codes and positions, and the metadata.

    Use :func:`open_large_map`; attributes are read-only views of the file.

    Attributes
    ----------
    path : Path
    codes : numpy.memmap of uint8, shape (n_places, n_bytes)
    positions : numpy.memmap of float64, shape (n_places, n_dims), or None
    arrays : dict of str to numpy.memmap
        Every array of the file, ``codes`` and ``positions`` included.
    metadata : dict
    map_id : str
        Identifier of the map's content (the first 32 hex digits of a SHA-256 of its
        metadata and arrays as written): index files name it, and the same map written twice
        has the same.
    n_places, n_bits : int
    """

    def __init__(self, path, header: dict, arrays: dict):
        self.path = Path(path)
        self.codes = arrays["codes"]
        self.positions = arrays.get("positions")
        self.arrays = dict(arrays)
        self.metadata = header.get("metadata", {})
        self.map_id = str(header.get("map_id", ""))
        self.n_places = int(self.codes.shape[0])
        self.n_bits = int(self.codes.shape[1] * 8)

    def __len__(self) -> int:
        return self.n_places

    def __repr__(self) -> str:
        return f"LargeMap({str(self.path)!r}, n_places={self.n_places}, n_bits={self.n_bits})"

    def verify(self) -> float:
        """Read the whole file and check its content against its ``map_id``; return the
        seconds it took.

        Opening checks the file's structure only (nothing else is read), so a byte changed
        inside the codes, the positions or another array would go unseen: this reads every
        array once (SHA-256, about a second per GB) and recomputes the digest the writer
        took.  ``flyvpr localize --map`` does it for every compact map it opens.

        Raises
        ------
        MapFileError
            If the content does not match (the file was changed after it was written).
        """
        t0 = time.perf_counter()
        names = list(self.arrays)
        parts = [hashlib.sha256() for _ in range(3)]
        for name in names:
            array = self.arrays[name]
            digest = parts[0] if name == "codes" else parts[1] if name == "positions" else None
            if digest is None:
                digest = parts[2]
                digest.update(f"{name} {array.dtype.str} {array.shape}".encode())
            _hash_rows(digest, array)
        whole = hashlib.sha256(json.dumps(self.metadata or {}, sort_keys=True).encode())
        for d in parts:
            whole.update(d.digest())
        if whole.hexdigest()[:32] != self.map_id:
            raise MapFileError(
                f"{self.path}: the content does not match the file's map_id: the file was "
                "changed after it was written (corrupt); build the map again"
            )
        return time.perf_counter() - t0


def _hash_rows(digest, array, chunk_bytes: int = 1 << 24) -> None:
    """Feed ``array``'s bytes (C order) to ``digest``, a block of rows at a time."""
    if array.ndim == 0 or array.size == 0:
        digest.update(np.ascontiguousarray(array).data)
        return
    row = max(1, array.nbytes // max(len(array), 1))
    step = max(1, chunk_bytes // row)
    for lo in range(0, len(array), step):
        digest.update(np.ascontiguousarray(array[lo : lo + step]).data)


def open_large_map(path) -> LargeMap:
    """Open a map file written by :class:`LargeMapWriter` or :func:`write_large_map`.

    Nothing but the header is read: the codes are memory-mapped, so opening takes
    milliseconds whatever the size, and resident memory grows only with the pages used.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    MapFileError
        If it is not a map file, or is truncated or corrupt (the message names it).
    """
    header, arrays = _read_container(path, "map")
    codes = arrays.get("codes")
    if codes is None or codes.dtype != np.uint8 or codes.ndim != 2 or codes.shape[1] % 8:
        raise MapFileError(f"{path}: codes must be uint8 (n_places, n_bytes), n_bytes % 8 == 0")
    pos = arrays.get("positions")
    if pos is not None and (pos.ndim != 2 or pos.shape[0] != codes.shape[0]):
        raise MapFileError(f"{path}: positions must have one row per place ({codes.shape[0]})")
    return LargeMap(path, header, arrays)


class LargeMapWriter:
    """Write a map file in chunks: the places' codes (and positions) in route order.

    Parameters
    ----------
    path : str or Path
        The map file; written to a temporary file beside it and renamed on ``close``.
    n_places : int
    n_bytes : int
        Bytes per code, a multiple of 8 (32 for 256 bits).
    n_dims : int, optional
        Coordinates per place position (None: no positions).
    metadata : dict, optional
        JSON-serialisable (the front end's settings, the source, ...).

    Examples
    --------
    >>> import tempfile, os
    >>> path = os.path.join(tempfile.mkdtemp(), "line.fvmap")
    >>> with LargeMapWriter(path, n_places=3, n_bytes=8) as w:
    ...     w.append(np.zeros((2, 8), np.uint8))
    ...     w.append(np.ones((1, 8), np.uint8))
    >>> m = open_large_map(path)
    >>> m.n_places, m.n_bits, int(m.codes[2, 0])
    (3, 64, 1)
    """

    def __init__(self, path, n_places: int, n_bytes: int, n_dims=None, metadata=None):
        self.n_places = check_positive_int(n_places, "n_places")
        self.n_bytes = check_positive_int(n_bytes, "n_bytes", minimum=8)
        if self.n_bytes % 8:
            raise ValueError(f"n_bytes must be a multiple of 8; got {n_bytes}")
        self.n_dims = None if n_dims is None else check_positive_int(n_dims, "n_dims")
        if metadata is not None and not isinstance(metadata, dict):
            raise TypeError(f"metadata must be a dict; got {type(metadata).__name__}")
        json.dumps(metadata or {}, allow_nan=False)  # refuse what cannot be written, now
        self.path = Path(path)
        # the map's identity: a digest of everything written, so that the same map written
        # twice (by one process or by a cluster) is the same file, byte for byte
        # (codes, positions, the other arrays, hashed apart: the chunking changes nothing)
        self._digests = [hashlib.sha256() for _ in range(3)]
        self._metadata_json = json.dumps(metadata or {}, sort_keys=True)
        self.map_id: str | None = None  # set by close
        self._file = _ArrayFile(path, "map", metadata, {"map_id": ""})
        self._codes_at = self._file.reserve("codes", np.uint8, (self.n_places, self.n_bytes))
        self._pos_at = None
        if self.n_dims is not None:
            self._pos_at = self._file.reserve("positions", np.float64, (self.n_places, self.n_dims))
        self.n_written = 0

    def append(self, codes, positions=None) -> None:
        """Write the next places' codes (uint8 (m, n_bytes)) and, with ``n_dims``, positions."""
        codes = np.asarray(codes)
        if codes.dtype != np.uint8 or codes.ndim != 2 or codes.shape[1] != self.n_bytes:
            raise ValueError(
                f"codes must be uint8 of shape (m, {self.n_bytes}); got {codes.dtype} {codes.shape}"
            )
        m = len(codes)
        if self.n_written + m > self.n_places:
            raise ValueError(
                f"{self.path}: {self.n_written + m} places appended; the map has {self.n_places}"
            )
        if (positions is None) != (self.n_dims is None):
            raise ValueError(
                "positions must be given with every chunk when n_dims is set, and never otherwise"
            )
        if positions is not None:
            assert self.n_dims is not None and self._pos_at is not None  # checked just above
            positions = np.asarray(positions, dtype=np.float64)
            if positions.shape != (m, self.n_dims):
                raise ValueError(
                    f"positions must have shape ({m}, {self.n_dims}); got {positions.shape}"
                )
            self._file.write_at(self._pos_at + self.n_written * self.n_dims * 8, positions)
            self._digests[1].update(np.ascontiguousarray(positions).data)
        self._file.write_at(self._codes_at + self.n_written * self.n_bytes, codes)
        self._digests[0].update(np.ascontiguousarray(codes).data)
        self.n_written += m

    def add_array(self, name: str, array) -> None:
        """Write one more named array (read back as ``LargeMap.arrays[name]``).

        Raises
        ------
        ValueError
            If ``name`` is empty or taken (``codes``, ``positions`` or an array added before),
            or the array's dtype is not one a map file holds (uint8, uint16, uint32, int32,
            int64, float32, float64).
        """
        array = np.asarray(array)
        if not isinstance(name, str) or not name or name in self._file._arrays:
            raise ValueError(f"name must be a new, non-empty array name; got {name!r}")
        if array.dtype.str not in _DTYPES:
            raise ValueError(
                f"array {name!r}: dtype {array.dtype} cannot be written (uint8, uint16, uint32, "
                "int32, int64, float32 or float64)"
            )
        self._file.add(name, array)
        self._digests[2].update(f"{name} {array.dtype.str} {array.shape}".encode())
        self._digests[2].update(np.ascontiguousarray(array).data)

    def close(self) -> Path:
        """Finish the file and rename it into place.

        Raises
        ------
        ValueError
            If fewer places were appended than announced (the temporary file is removed).
        """
        if self.n_written != self.n_places:
            exc = ValueError(
                f"{self.path}: {self.n_written} places appended; the map has {self.n_places}"
            )
            self._file.abort(exc)
            raise exc
        whole = hashlib.sha256(self._metadata_json.encode())
        for d in self._digests:
            whole.update(d.digest())
        self.map_id = whole.hexdigest()[:32]
        self._file._header["map_id"] = self.map_id
        self._file.close()
        return self.path

    def __enter__(self) -> LargeMapWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close()
        else:
            self._file.abort(exc)


def write_large_map(path, codes, positions=None, metadata=None, chunk: int = 1 << 20) -> Path:
    """Write a whole code array (and positions) as a map file, atomically.

    Returns
    -------
    Path
    """
    codes = np.asarray(codes)
    if codes.dtype != np.uint8 or codes.ndim != 2:
        raise ValueError(
            f"codes must be uint8 (n_places, n_bytes); got {codes.dtype} {codes.shape}"
        )
    pos = None if positions is None else np.asarray(positions, dtype=np.float64)
    if pos is not None and pos.ndim == 1:
        pos = pos[:, None]
    n_dims = None if pos is None else pos.shape[1]
    with LargeMapWriter(path, len(codes), codes.shape[1], n_dims, metadata) as w:
        for lo in range(0, len(codes), chunk):
            w.append(codes[lo : lo + chunk], None if pos is None else pos[lo : lo + chunk])
    return Path(path)


def save_index(path, index, large_map: LargeMap) -> Path:
    """Write a built :class:`~flyvpr.large.index.MultiIndexHash` of ``large_map`` to ``path``.

    Returns
    -------
    Path
    """
    from .index import MultiIndexHash

    if not isinstance(index, MultiIndexHash) or not hasattr(index, "starts_"):
        raise TypeError(f"index must be a built MultiIndexHash; got {type(index).__name__}")
    if index.n_places_ != large_map.n_places:
        raise ValueError(
            f"index covers {index.n_places_} places; the map {large_map.path} has "
            f"{large_map.n_places}"
        )
    codes = index._codes
    if codes is not large_map.codes and not np.array_equal(codes, large_map.codes):
        raise ValueError(
            f"index was built over other codes than those of the map {large_map.path} (build "
            "it over the map's own: MultiIndexHash().build(large_map.codes))"
        )
    params = {"radius": index.radius, "max_candidates": index.max_candidates}
    f = _ArrayFile(path, "mih", {}, {"map_id": large_map.map_id, "params": params})
    try:
        f.add("starts", index.starts_)
        f.add("places", index.places_)
    except BaseException as exc:
        f.abort(exc)
        raise
    f.close()
    return Path(path)


def load_index(path, large_map: LargeMap, **params):
    """Open an index file written by :func:`save_index` for ``large_map`` (memory-mapped).

    Parameters
    ----------
    **params
        Override the stored search settings (``radius``, ``max_candidates``).

    Raises
    ------
    MapFileError
        If the file is not an index file, is corrupt, or was written for another map
        (:class:`ForeignIndexError`, a MapFileError).
    """
    from .index import MultiIndexHash

    header, arrays = _read_container(path, "mih")
    if header.get("map_id") != large_map.map_id:
        raise ForeignIndexError(f"{path}: indexes another map than {large_map.path}")
    stored = header.get("params") or {}
    settings = {k: stored[k] for k in ("radius", "max_candidates") if k in stored}
    settings.update(params)
    try:
        return MultiIndexHash.from_arrays(
            large_map.codes, arrays.get("starts"), arrays.get("places"), **settings
        )
    except ValueError as exc:
        raise MapFileError(f"{path}: {exc}") from None
