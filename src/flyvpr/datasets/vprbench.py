"""VPR-Bench dataset folders: ``ref/``, ``query/`` and a ground-truth file.

VPR-Bench (Zaffar et al., IJCV 2021) ships each dataset as two image folders
and ``ground_truth_new.npy``: a *pickled* numpy object array whose rows are
``[query_index, [reference indices]]``.  Unpickling can execute arbitrary
code, so this loader refuses the pickled file unless the caller says it is
trusted (``trust_pickle=True``, CLI ``--trust-pickle``).  A safe alternative
is ``ground_truth.npy`` holding a plain boolean matrix (n_query, n_reference),
which is read with ``allow_pickle=False``.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .._npy import load_npy, npy_header
from .base import Benchmark, Traverse, _check_root, _list_images_or_explain

__all__ = ["load_vprbench", "parse_vprbench_rows", "LAYOUT"]

logger = logging.getLogger(__name__)

#: Folder layout shown in errors and by ``flyvpr datasets``.
LAYOUT = (
    "<root>/ref/<images>    reference images (sorted by name: index 0, 1, ...)\n"
    "<root>/query/<images>  query images\n"
    "<root>/ground_truth.npy      plain bool matrix (n_query, n_reference), no pickle; or\n"
    "<root>/ground_truth_new.npy  VPR-Bench's pickled rows [query_index, [reference indices]]"
    " (read only with trust_pickle=True / --trust-pickle)"
)

_PLAIN, _PICKLED = "ground_truth.npy", "ground_truth_new.npy"


def _pickle_refusal(path: Path) -> ValueError:
    return ValueError(
        f"{path} is a pickled object array; unpickling a file can execute arbitrary code. "
        "Pass trust_pickle=True (CLI: --trust-pickle) only if you trust where this file came "
        f"from, or convert it to {_PLAIN}: a plain bool matrix (n_query, n_reference)"
    )


def _load_plain(path: Path, n_query: int, n_reference: int):
    """The matrix in ``path`` if it is a plain .npy array, else None (it is pickled).

    The header is checked (dtype, shape, data size, memory) before any allocation, so a
    small file that claims a huge matrix is refused at no cost.
    """
    with open(path, "rb") as fh:
        head = fh.read(6)
    if head != b"\x93NUMPY":
        if head[:1] == b"\x80":  # a bare pickle stream (protocol 2 or later)
            return None
        raise ValueError(f"{path}: not a readable .npy file (no .npy header)")
    shape, _, dtype = npy_header(path)
    if dtype.hasobject:
        return None
    if not (dtype == np.bool_ or np.issubdtype(dtype, np.integer)):
        raise _dtype_error(path, n_query, n_reference, dtype, shape)
    _check_shape(path, n_query, n_reference, shape)
    return load_npy(path, shape=(n_query, n_reference))


def _dtype_error(path, n_query, n_reference, dtype, shape) -> ValueError:
    return ValueError(
        f"{path}: expected a boolean ground-truth matrix (n_query, n_reference) = "
        f"({n_query}, {n_reference}); got dtype {dtype}, shape {shape}"
    )


def _check_shape(path, n_query, n_reference, shape) -> None:
    if tuple(shape) != (n_query, n_reference):
        raise ValueError(
            f"{path}: ground-truth matrix must have shape (n_query, n_reference) = "
            f"({n_query}, {n_reference}) to match the query/ and ref/ folders; got {shape}"
        )


def _check_matrix(gt, path: Path, n_query: int, n_reference: int) -> np.ndarray:
    gt = np.asarray(gt)
    if gt.dtype != np.bool_:
        if np.issubdtype(gt.dtype, np.integer) and np.isin(gt, (0, 1)).all():
            gt = gt.astype(bool)
        else:
            raise _dtype_error(path, n_query, n_reference, gt.dtype, gt.shape)
    _check_shape(path, n_query, n_reference, gt.shape)
    return gt


def _describe(obj) -> str:
    """A short description of ``obj`` for an error message: its type, and a dict's keys."""
    if isinstance(obj, Mapping):
        keys = list(obj)
        shown = ", ".join(repr(k) for k in keys[:5]) + (", ..." if len(keys) > 5 else "")
        return f"a {type(obj).__name__} with {len(keys)} keys ({shown})"
    return f"a {type(obj).__name__}"


def parse_vprbench_rows(rows, n_query: int, n_reference: int, source="ground truth"):
    """Turn VPR-Bench rows ``[query_index, [reference indices]]`` into a bool matrix.

    Queries that no row names get an all-False row (no acceptable match).

    Parameters
    ----------
    rows : sequence of pairs, or object array of shape (n, 2)
    n_query, n_reference : int
        Number of images in ``query/`` and ``ref/``.
    source : str
        Named in error messages (the file).

    Returns
    -------
    ndarray of bool, shape (n_query, n_reference)

    Raises
    ------
    ValueError
        For rows that are not a sequence (a pickled dict, say), a row that is
        not a pair, a non-integer index, an index out of range or a query
        listed twice.
    """
    gt = np.zeros((n_query, n_reference), dtype=bool)
    seen = np.zeros(n_query, dtype=bool)
    if isinstance(rows, np.ndarray) and rows.ndim == 0:
        rows = rows.item()
    is_sequence = isinstance(rows, Sequence) and not isinstance(rows, (str, bytes))
    if not (isinstance(rows, np.ndarray) or is_sequence):
        # A dict (some conversions pickle {query: refs}) would fail on rows[0] with a bare
        # KeyError, or worse, parse its values as rows; name what the file must hold instead.
        raise ValueError(
            f"{source}: expected rows [query_index, [reference indices]] (VPR-Bench's "
            f"ground_truth_new.npy: an object array of shape (n, 2)); got {_describe(rows)}"
        )
    n_rows = len(rows)
    for k in range(n_rows):
        row = rows[k]
        try:
            q_raw, refs_raw = row
            q_arr = np.asarray(q_raw)
            refs = np.atleast_1d(np.asarray(refs_raw))
        except (TypeError, ValueError):
            raise ValueError(
                f"{source}, row {k}: expected [query_index, [reference indices]]; got {row!r}"
            ) from None
        if refs.size == 0:
            refs = refs.astype(np.int64)
        if q_arr.ndim != 0 or not np.issubdtype(q_arr.dtype, np.integer):
            raise ValueError(f"{source}, row {k}: query index must be an int; got {q_raw!r}")
        if refs.ndim != 1 or not np.issubdtype(refs.dtype, np.integer):
            raise ValueError(f"{source}, row {k}: reference indices must be ints; got {refs_raw!r}")
        q = int(q_arr)
        if not 0 <= q < n_query:
            raise ValueError(
                f"{source}, row {k}: query index {q} out of range [0, {n_query}) "
                "(the number of images in query/)"
            )
        if seen[q]:
            raise ValueError(f"{source}, row {k}: query index {q} is listed twice")
        bad = (refs < 0) | (refs >= n_reference)
        if bad.any():
            raise ValueError(
                f"{source}, row {k}: reference index {int(refs[np.argmax(bad)])} out of range "
                f"[0, {n_reference}) (the number of images in ref/)"
            )
        seen[q] = True
        gt[q, refs] = True
    if not seen.all():
        logger.info("%s: %d of %d queries have no row", source, int((~seen).sum()), n_query)
    return gt


def load_vprbench(root, trust_pickle=False) -> Benchmark:
    """Load a VPR-Bench dataset folder.

    Images are indexed in name order (natural sort, so ``2.jpg`` before
    ``10.jpg``; VPR-Bench's zero-padded names sort the same either way).
    The ground truth comes from ``ground_truth.npy`` when it holds a plain
    boolean matrix, else from ``ground_truth_new.npy`` (VPR-Bench's pickled
    rows), which is read only when ``trust_pickle`` is True.  Query frames
    that no row names have no acceptable match.

    Parameters
    ----------
    root : str or Path
        The dataset folder (see ``LAYOUT``).
    trust_pickle : bool
        Allow unpickling the ground-truth file.  Never set it for files from
        an unknown source: a pickle can execute code when loaded.

    Returns
    -------
    Benchmark
        ``tolerance={"ground_truth_file": <file name>}``; traverses ``ref``
        and ``query`` carry ``frame_ids`` (their index) only.

    Raises
    ------
    FileNotFoundError
        If ``root``, ``ref/``, ``query/`` or both ground-truth files are missing.
    ValueError
        If the ground truth is pickled and ``trust_pickle`` is False, or it
        does not match the folders (shape, indices out of range).
    """
    if not isinstance(trust_pickle, bool):
        raise TypeError(f"trust_pickle must be a bool; got {type(trust_pickle).__name__}")
    root = _check_root(root, LAYOUT)
    ref_paths = _list_images_or_explain(root / "ref", LAYOUT)
    query_paths = _list_images_or_explain(root / "query", LAYOUT)
    n_q, n_r = len(query_paths), len(ref_paths)

    candidates = [root / name for name in (_PLAIN, _PICKLED) if (root / name).is_file()]
    if not candidates:
        raise FileNotFoundError(
            f"no ground-truth file in {root}: expected {_PLAIN} or {_PICKLED}; "
            f"expected layout:\n{LAYOUT}"
        )
    gt = source = None
    pickled = []
    for path in candidates:
        arr = _load_plain(path, n_q, n_r)
        if arr is None:
            pickled.append(path)
        elif arr.dtype != object:
            gt, source = _check_matrix(arr, path, n_q, n_r), path
            break
    if gt is None:
        path = pickled[-1]  # prefer ground_truth_new.npy, VPR-Bench's current file
        if not trust_pickle:
            raise _pickle_refusal(path)
        logger.info("unpickling %s (trust_pickle=True)", path)
        try:
            rows = np.load(path, allow_pickle=True)
        except (OSError, EOFError, ValueError, pickle.UnpicklingError) as exc:
            raise ValueError(f"{path}: cannot read the pickled ground truth ({exc})") from None
        gt, source = parse_vprbench_rows(rows, n_q, n_r, source=str(path)), path
    assert source is not None  # set with gt

    ids_q, ids_r = np.arange(n_q), np.arange(n_r)
    return Benchmark(
        dataset="vprbench",
        reference=Traverse("ref", ref_paths, frame_ids=ids_r),
        query=Traverse("query", query_paths, frame_ids=ids_q),
        ground_truth=gt,
        tolerance={"ground_truth_file": source.name},
        root=root,
        first=0,
        count=None,
        details={"trust_pickle": trust_pickle},
        sources=tuple(candidates),
    )
