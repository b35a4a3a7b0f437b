"""Traverses, benchmarks and ground-truth builders shared by every dataset loader.

A *traverse* is one drive along the route: its image files in time order plus
whatever is known about each frame (time stamp, metric position, index in the
source sequence).  A *benchmark* pairs a reference traverse with a query
traverse and the boolean ground truth of shape (n_query, n_reference): True
where the reference frame is an acceptable match for the query frame (the
paper's protocol, Sec. Experiments: within 20 frames on Nordland, within 50 m
on Oxford RobotCar).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .._validation import check_positive_int, check_real
from ..images import DEFAULT_SIZE, ImageFolderError, list_images, load_images, stat_image

__all__ = [
    "Traverse",
    "Benchmark",
    "ground_truth_from_frames",
    "ground_truth_from_positions",
]

logger = logging.getLogger(__name__)

#: Upper bound on the elements of one temporary block when building ground truth,
#: so a 30k x 30k matrix never needs a 30k x 30k int64 intermediate.
_BLOCK_ELEMENTS = 1 << 22


# -- index handling ------------------------------------------------------------------------------
def _check_indices(indices, n: int, name: str = "indices") -> np.ndarray:
    """Turn a slice, boolean mask or integer sequence into int positions in [0, n)."""
    if isinstance(indices, slice):
        idx = np.arange(n)[indices]
    else:
        arr = np.asarray(indices)
        if arr.dtype == np.bool_:
            if arr.shape != (n,):
                raise ValueError(
                    f"{name} as a boolean mask must have shape ({n},); got shape {arr.shape}"
                )
            idx = np.flatnonzero(arr)
        elif arr.size == 0 and arr.ndim == 1:
            idx = arr.astype(np.intp)
        elif np.issubdtype(arr.dtype, np.integer):
            if arr.ndim != 1:
                raise ValueError(f"{name} must be one-dimensional; got shape {arr.shape}")
            idx = arr.astype(np.intp)
            bad = (idx < 0) | (idx >= n)
            if bad.any():
                raise ValueError(f"{name} must lie in [0, {n}); got {int(idx[np.argmax(bad)])}")
        else:
            raise TypeError(
                f"{name} must be a slice, a boolean mask or a sequence of ints; "
                f"got dtype {arr.dtype}"
            )
    if idx.size == 0:
        raise ValueError(f"{name} selects no frame: expected at least one of the {n} frames")
    return idx


def _check_window(first, count, n_available: int, what: str) -> tuple[int, int]:
    """Validate a ``first``/``count`` window over ``n_available`` frames; return (first, count)."""
    first = check_positive_int(first, "first", minimum=0)
    if count is not None:
        count = check_positive_int(count, "count", minimum=1)
    stop = n_available if count is None else first + count
    if first >= n_available or stop > n_available:
        shown = "None (to the end)" if count is None else count
        ends = "" if count is None else f", ending at position {stop - 1},"
        raise ValueError(
            f"window first={first}, count={shown}{ends} lies beyond the data: {what}: "
            f"{n_available} frames (valid positions 0..{n_available - 1})"
        )
    return first, stop - first


def _check_root(root, layout: str) -> Path:
    """A dataset root folder that exists; the error shows the layout a loader expects."""
    if not isinstance(root, (str, Path)):
        raise TypeError(f"root must be a str or Path; got {type(root).__name__}")
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"dataset root not found: {root}; expected layout:\n{layout}")
    if not root.is_dir():
        raise NotADirectoryError(f"dataset root must be a folder; got a file: {root}")
    return root


def _list_images_or_explain(folder: Path, layout: str, **kwargs) -> list[Path]:
    """:func:`flyvpr.images.list_images` with the loader's expected layout in the message."""
    try:
        return list_images(folder, **kwargs)
    except FileNotFoundError as exc:
        raise FileNotFoundError(f"{exc}; expected layout:\n{layout}") from None
    except NotADirectoryError as exc:
        raise NotADirectoryError(f"{exc}; expected layout:\n{layout}") from None
    except ImageFolderError:
        raise  # names the entry and why; the layout would not help
    except ValueError as exc:
        raise ValueError(f"{exc}; expected layout:\n{layout}") from None


def _read_csv_text(path: Path, what: str) -> str:
    """The text of a CSV file: UTF-8, a leading byte-order mark dropped.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a regular file or not UTF-8 (the message names the file, the line and
        the byte).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    if not path.is_file():
        raise ValueError(f"{what} {path} is not a regular file")
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ValueError(
            f"{path}, line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
            f"{exc.start}); save the file as UTF-8"
        ) from None


def _check_unique_columns(header, used, where: str) -> None:
    """Refuse a CSV header that names one of the columns read (``used``) more than once:
    which of the two holds the values would be a guess (``where`` starts the message)."""
    for name in used:
        at = [i + 1 for i, h in enumerate(header) if h == name]
        if len(at) > 1:
            raise ValueError(
                f"{where}: column {name!r} appears {len(at)} times in the header (columns "
                f"{', '.join(map(str, at))}); expected each column once"
            )


def _subfolders(root: Path) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))


# -- traverse ------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Traverse:
    """One drive along the route: image files in time order and per-frame metadata.

    Parameters
    ----------
    name : str
        Label shown in reports (season, run folder name, ...).
    paths : sequence of str or Path, length N
        Image files in traverse (time) order.
    timestamps : array-like, shape (N,), optional
        Capture times in seconds (float64), e.g. UNIX time for Oxford RobotCar.
    positions : array-like, shape (N, 2), optional
        Metric positions (float64), e.g. (northing, easting) in metres.
    frame_ids : array-like of int, shape (N,), optional
        Index of each frame in its source sequence; frame-aligned ground truth
        compares these (:func:`ground_truth_from_frames`).
    bayer : str, optional
        Raw Bayer pattern of the files (``'gbrg'`` for RobotCar's stereo
        camera); ``None`` for ordinary gray/RGB images.

    Raises
    ------
    TypeError, ValueError
        If ``paths`` is empty or a metadata array has the wrong type, length
        or shape, or holds NaN/inf.
    """

    name: str
    paths: list[Path]
    timestamps: np.ndarray | None = None
    positions: np.ndarray | None = None
    frame_ids: np.ndarray | None = None
    bayer: str | None = None

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a str; got {type(self.name).__name__}")
        if isinstance(self.paths, (str, Path)):
            raise TypeError("paths must be a sequence of file paths, not a single path")
        paths = [Path(p) for p in self.paths]
        if not paths:
            raise ValueError(f"traverse {self.name!r}: paths is empty; expected at least one image")
        n = len(paths)
        object.__setattr__(self, "paths", paths)
        if self.timestamps is not None:
            ts = np.asarray(self.timestamps, dtype=np.float64)
            if ts.shape != (n,):
                raise ValueError(
                    f"traverse {self.name!r}: timestamps must have shape ({n},); got {ts.shape}"
                )
            if not np.isfinite(ts).all():
                raise ValueError(f"traverse {self.name!r}: timestamps contain NaN or inf")
            object.__setattr__(self, "timestamps", ts)
        if self.positions is not None:
            pos = np.asarray(self.positions, dtype=np.float64)
            if pos.shape != (n, 2):
                raise ValueError(
                    f"traverse {self.name!r}: positions must have shape ({n}, 2); got {pos.shape}"
                )
            if not np.isfinite(pos).all():
                raise ValueError(f"traverse {self.name!r}: positions contain NaN or inf")
            object.__setattr__(self, "positions", pos)
        if self.frame_ids is not None:
            ids = np.asarray(self.frame_ids)
            if not np.issubdtype(ids.dtype, np.integer):
                raise TypeError(
                    f"traverse {self.name!r}: frame_ids must be integers; got dtype {ids.dtype}"
                )
            if ids.shape != (n,):
                raise ValueError(
                    f"traverse {self.name!r}: frame_ids must have shape ({n},); got {ids.shape}"
                )
            object.__setattr__(self, "frame_ids", ids.astype(np.int64))
        if self.bayer is not None and not isinstance(self.bayer, str):
            raise TypeError(f"bayer must be None or a str; got {type(self.bayer).__name__}")

    def __len__(self) -> int:
        return len(self.paths)

    def __repr__(self) -> str:
        extras = [
            k for k in ("timestamps", "positions", "frame_ids") if getattr(self, k) is not None
        ]
        return (
            f"Traverse(name={self.name!r}, n_frames={len(self)}, with={extras}, "
            f"bayer={self.bayer!r})"
        )

    def load_images(self, size=DEFAULT_SIZE, cache=True, progress=None) -> np.ndarray:
        """Decode the traverse's frames into a float32 stack (N, H, W) in [0, 1].

        Parameters
        ----------
        size : (int, int)
            Target (H, W); the paper's is (32, 64).
        cache : bool or path
            As :func:`flyvpr.images.load_images`: the cache file is written only
            after every file decoded, so a corrupt file leaves no partial cache.
        progress : bool, optional
            Show a progress bar (``None``: only when stderr is a terminal).

        Raises
        ------
        FileNotFoundError, flyvpr.images.ImageReadError
            For a missing or undecodable file (the message names it).
        """
        return load_images(
            self.paths, size, cache=cache, progress=progress, bayer=self.bayer, desc=self.name
        )

    def subset(self, indices) -> Traverse:
        """A new traverse holding the frames at ``indices``, in the order given.

        Parameters
        ----------
        indices : slice, boolean mask of shape (N,), or sequence of int
            Positions in this traverse.  ``slice(None, None, 2)`` keeps every
            second frame (the vehicle seems to drive twice as fast); repeated
            indices are allowed (it seems to stop or slow down).

        Raises
        ------
        ValueError
            If an index is out of range or nothing is selected.
        TypeError
            For indices that are not ints, a mask or a slice.
        """
        idx = _check_indices(indices, len(self))

        def take(arr):
            return None if arr is None else arr[idx]

        return Traverse(
            name=self.name,
            paths=[self.paths[i] for i in idx],
            timestamps=take(self.timestamps),
            positions=take(self.positions),
            frame_ids=take(self.frame_ids),
            bayer=self.bayer,
        )


# -- benchmark -----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Benchmark:
    """A reference traverse, a query traverse and their ground truth.

    Parameters
    ----------
    dataset : str
        Registry name of the loader (``'nordland'``, ``'robotcar'``, ...).
    reference, query : Traverse
        The traverse the system learns from and the one it localises.
    ground_truth : ndarray of bool, shape (n_query, n_reference)
        True where the reference frame is an acceptable match of the query.
    tolerance : dict
        How the ground truth was built, e.g. ``{"frames": 20}`` or ``{"metres": 50.0}``.
    root : Path, optional
        Dataset folder, for reports.
    first, count : int
        Window of frames that was kept (``count=None``: every frame from ``first``).
    details : dict
        Further protocol facts for reports (JSON-serialisable values).
    sources : tuple of Path
        The files besides the images that the ground truth was built from (a positions CSV,
        pose logs, a ground-truth matrix): with the images, the run's inputs, which an output
        must never overwrite (see :meth:`input_files`).

    Raises
    ------
    TypeError, ValueError
        If the traverses are not :class:`Traverse` objects or the ground truth
        is not a boolean matrix of shape (len(query), len(reference)).
    """

    dataset: str
    reference: Traverse
    query: Traverse
    ground_truth: np.ndarray
    tolerance: dict
    root: Path | None = None
    first: int = 0
    count: int | None = None
    details: dict = field(default_factory=dict)
    sources: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "sources", tuple(Path(p) for p in self.sources))
        for role in ("reference", "query"):
            if not isinstance(getattr(self, role), Traverse):
                raise TypeError(
                    f"{role} must be a Traverse; got {type(getattr(self, role)).__name__}"
                )
        gt = np.asarray(self.ground_truth)
        if gt.dtype != np.bool_:
            raise TypeError(f"ground_truth must be a boolean array; got dtype {gt.dtype}")
        expected = (len(self.query), len(self.reference))
        if gt.shape != expected:
            raise ValueError(
                f"ground_truth must have shape (n_query, n_reference) = {expected}; got {gt.shape}"
            )
        object.__setattr__(self, "ground_truth", gt)
        if not isinstance(self.tolerance, dict):
            raise TypeError(f"tolerance must be a dict; got {type(self.tolerance).__name__}")
        if self.root is not None:
            object.__setattr__(self, "root", Path(self.root))

    @property
    def n_reference(self) -> int:
        return len(self.reference)

    @property
    def n_query(self) -> int:
        return len(self.query)

    def __repr__(self) -> str:
        return (
            f"Benchmark(dataset={self.dataset!r}, reference={self.reference.name!r} "
            f"[{self.n_reference}], query={self.query.name!r} [{self.n_query}], "
            f"tolerance={self.tolerance})"
        )

    def protocol(self) -> dict:
        """The facts a report must print next to every number (JSON-serialisable).

        Keys: ``dataset``, ``root``, ``reference``, ``query`` (traverse names),
        ``first``, ``count``, ``n_reference``, ``n_query``, ``tolerance``, ``sources`` (the
        files the ground truth was read from, such as a positions CSV), then the loader's
        ``details`` (e.g. RobotCar's ``spacing_m``).
        """
        out = {
            "dataset": self.dataset,
            "root": None if self.root is None else str(self.root),
            "reference": self.reference.name,
            "query": self.query.name,
            "first": self.first,
            "count": self.count,
            "n_reference": self.n_reference,
            "n_query": self.n_query,
            "tolerance": dict(self.tolerance),
            "sources": [str(p) for p in self.sources],
        }
        out.update(self.details)
        return out

    def input_files(self) -> list[Path]:
        """Every file this benchmark reads: the images of both traverses and its ``sources``."""
        return [*self.reference.paths, *self.query.paths, *self.sources]

    def fingerprint(self) -> dict:
        """What a result computed on this benchmark depends on, cheaply: to tell later whether
        the data are still the same.

        Each traverse is summed up by its image files in order: each file's path relative to
        ``root``, its size and its modification time (whole seconds, which copies made with
        ``cp -p``, ``rsync -a`` or ``tar`` keep); the files are not read, only ``stat``-ed.  The
        ground truth is hashed itself (its bits), which covers the files it was built from
        (``sources``) and the tolerance.  Two traverses of 2400 frames take about 50 ms.

        Returns
        -------
        dict
            ``reference`` and ``query``: ``{"n_images": int, "files": str}`` (the SHA-256 of
            the file list, 16 hex digits); ``ground_truth``: ``{"shape": [n_query,
            n_reference], "n_true": int, "sha256": str}`` (16 hex digits).  JSON values: equal
            dicts mean the same data, as far as paths, sizes and times tell.

        Raises
        ------
        FileNotFoundError
            If an image file is gone (the message names it).
        """
        root = None if self.root is None else os.path.abspath(self.root)
        out: dict = {}
        for role in ("reference", "query"):
            paths = getattr(self, role).paths
            entries = []
            for p in paths:
                st = stat_image(p)
                entries.append([_relative(p, root), st.st_size, st.st_mtime_ns // 1_000_000_000])
            out[role] = {"n_images": len(paths), "files": _digest(json.dumps(entries))}
        gt = self.ground_truth
        packed = np.packbits(gt, axis=None).tobytes()
        out["ground_truth"] = {
            "shape": list(gt.shape),
            "n_true": int(np.count_nonzero(gt)),
            "sha256": _digest(f"{gt.shape}".encode() + packed),
        }
        return out

    def load_images(self, size=DEFAULT_SIZE, cache=True, progress=None):
        """Decode both traverses: returns ``(reference_images, query_images)``.

        See :meth:`Traverse.load_images`.
        """
        self._check_aspects()
        return (
            self.reference.load_images(size, cache=cache, progress=progress),
            self.query.load_images(size, cache=cache, progress=progress),
        )

    def _check_aspects(self) -> None:
        """Warn where the traverses' first frames differ in aspect ratio: both are resized to
        one size, so the same scene would be stretched differently in each."""
        from ..images import same_aspect, upright_shape

        if not (self.reference.paths and self.query.paths):
            return
        ref, qry = self.reference.paths[0], self.query.paths[0]
        a, b = upright_shape(ref), upright_shape(qry)
        if a is not None and b is not None and not same_aspect(a, b):
            logger.warning(
                "the reference's frames (%s: %dx%d) and the query's (%s: %dx%d) differ in "
                "aspect ratio: both are resized to one size, so the same scene is stretched "
                "differently in each and matches worse; crop or pad one of them to the other's "
                "aspect ratio",
                ref,
                a[1],
                a[0],
                qry,
                b[1],
                b[0],
            )

    def subset_queries(self, indices) -> Benchmark:
        """A benchmark that keeps the query frames at ``indices`` and their ground-truth rows.

        The reference traverse is unchanged.  ``indices`` follows
        :meth:`Traverse.subset` (slice, boolean mask or ints; repeats allowed).
        """
        idx = _check_indices(indices, self.n_query)
        details = dict(self.details)
        details["query_subset"] = f"{idx.size} of {self.n_query} query frames"
        return replace(
            self,
            query=self.query.subset(idx),
            ground_truth=self.ground_truth[idx],
            details=details,
        )


def _relative(path: Path, root: str | None) -> str:
    """``path`` relative to ``root`` (so that moving the dataset keeps it), else absolute."""
    if root is not None:
        try:
            return os.path.relpath(path, root)
        except ValueError:  # (Windows: another drive)
            pass
    return os.path.abspath(path)


def _digest(data: str | bytes) -> str:
    """16 hex digits of the SHA-256 of ``data``."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    return hashlib.sha256(data).hexdigest()[:16]


# -- ground truth --------------------------------------------------------------------------------
def _check_ids(ids, name: str) -> np.ndarray:
    arr = np.asarray(ids)
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"{name} must be integer frame indices; got dtype {arr.dtype}")
    if arr.ndim != 1 or arr.size == 0:
        raise ValueError(f"{name} must be a non-empty 1-d array; got shape {arr.shape}")
    return arr.astype(np.int64)


def ground_truth_from_frames(query_ids, reference_ids, tolerance) -> np.ndarray:
    """Frame-aligned ground truth: ``|query_ids[i] - reference_ids[j]| <= tolerance``.

    Used for frame-aligned traverses such as Nordland, where frame k of every
    season shows the same place (paper, Sec. Experiments: a match counts when
    it lies within 20 frames).  The two traverses may differ in length.

    Parameters
    ----------
    query_ids : array-like of int, shape (n_query,)
    reference_ids : array-like of int, shape (n_reference,)
    tolerance : int
        Largest accepted frame difference, >= 0.

    Returns
    -------
    ndarray of bool, shape (n_query, n_reference)

    Raises
    ------
    TypeError
        For non-integer ids or tolerance.
    ValueError
        For empty or multi-dimensional ids or a negative tolerance.

    Examples
    --------
    >>> ground_truth_from_frames([0, 1, 2], [0, 1, 2], 1).astype(int)
    array([[1, 1, 0],
           [1, 1, 1],
           [0, 1, 1]])
    """
    q = _check_ids(query_ids, "query_ids")
    r = _check_ids(reference_ids, "reference_ids")
    tolerance = check_positive_int(tolerance, "tolerance", minimum=0)
    out = np.empty((q.size, r.size), dtype=bool)
    # Row blocks bound the int64 temporary (a full n x n one would be 8x the output).
    step = max(1, _BLOCK_ELEMENTS // r.size)
    for start in range(0, q.size, step):
        block = q[start : start + step, None] - r[None, :]
        np.less_equal(np.abs(block, out=block), tolerance, out=out[start : start + step])
    return out


def _check_positions(positions, name: str) -> np.ndarray:
    try:
        arr = np.asarray(positions, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be a numeric array of shape (N, 2); {exc}") from None
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"{name} must have shape (N, D) with N, D >= 1; got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def ground_truth_from_positions(query_positions, reference_positions, radius) -> np.ndarray:
    """Metric ground truth: Euclidean distance between positions ``<= radius``.

    The paper counts an Oxford RobotCar match as correct within 50 m
    (Sec. Experiments).  Neighbours are found with a k-d tree, so the cost
    grows with the number of true pairs, not with n_query x n_reference; the
    candidate pairs are then re-checked with the exact distance
    ``sqrt(sum((q - r) ** 2))`` so the boundary case ``distance == radius``
    is always included.

    Parameters
    ----------
    query_positions : array-like, shape (n_query, D)
    reference_positions : array-like, shape (n_reference, D)
        Same units as ``radius`` (metres for northing/easting).
    radius : float
        Largest accepted distance, >= 0.

    Returns
    -------
    ndarray of bool, shape (n_query, n_reference)

    Raises
    ------
    ValueError
        For empty, non-finite or mismatching positions or a negative radius.

    Examples
    --------
    >>> ground_truth_from_positions([[0.0, 0.0]], [[30.0, 40.0], [0.0, 51.0]], 50).tolist()
    [[True, False]]
    """
    from scipy.spatial import cKDTree

    q = _check_positions(query_positions, "query_positions")
    r = _check_positions(reference_positions, "reference_positions")
    if q.shape[1] != r.shape[1]:
        raise ValueError(
            "query_positions and reference_positions must have the same number of columns; "
            f"got {q.shape[1]} and {r.shape[1]}"
        )
    radius = check_real(radius, "radius", low=0.0, inclusive=True)
    tree = cKDTree(r)
    # Search a hair wider than radius; the exact test below decides the boundary.
    neighbours = tree.query_ball_point(q, radius * (1 + 1e-9) + 1e-12, return_sorted=False)
    lengths = np.fromiter((len(n) for n in neighbours), dtype=np.intp, count=len(neighbours))
    cols = np.fromiter(
        itertools.chain.from_iterable(neighbours), dtype=np.intp, count=int(lengths.sum())
    )
    rows = np.repeat(np.arange(q.shape[0]), lengths)
    dist = np.sqrt(((q[rows] - r[cols]) ** 2).sum(axis=1))
    keep = dist <= radius
    out = np.zeros((q.shape[0], r.shape[0]), dtype=bool)
    out[rows[keep], cols[keep]] = True
    return out
