"""Place-recognition metrics: precision-recall curve, its area, recall@k, extended precision;
and the reliability table of a probability-like confidence.

Pure functions of a score matrix ``S`` and a ground-truth matrix ``gt``; no state, no I/O, and no
import of any other flyvpr module (metrics sit at the bottom of the import graph).

Conventions (the paper's Sec. "Evaluation Metrics": PR curves and their AUC):

- ``S`` has shape ``(n_query, n_reference)``, one row per query frame, **higher = more similar**.
  ``n_query`` and ``n_reference`` may differ.
- ``gt`` is a boolean matrix of ``S``'s shape, True where the reference is an acceptable match for
  the query (e.g. within the dataset's frame tolerance).

Definition used by every function here:

- Each query's best-scoring reference (the row argmax of ``S``; ties go to the lowest reference
  index) is its *prediction*, and that score is the prediction's *confidence*.
- A prediction is *correct* when ``gt[q, pred]`` is True.
- For a threshold ``t``, the predictions "above the threshold" are those with confidence
  ``>= t``.
- ``precision(t)`` = correct predictions above ``t`` / predictions above ``t``.
- ``recall(t)`` = correct predictions above ``t`` / number of queries that have at least one True
  in their ``gt`` row.
- Queries with no true match still make predictions: they are always wrong and count in
  precision's denominator, but they are not in recall's denominator.

Recall is therefore counted **per query**, never per reference (database) entry: a query whose
tolerance window covers many references still counts once. Recall is undefined when no query has
a true match, so every function that reports recall raises ``ValueError`` for such a ``gt``.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

__all__ = [
    "best_match",
    "precision_recall_curve",
    "pr_auc",
    "recall_at_k",
    "recall_at_100_precision",
    "extended_precision",
    "evaluate",
    "evaluate_answers",
    "reliability",
    "reliability_counts",
]

# Row-block size (in matrix elements) for the recall@k pass: bounds the temporaries to a few
# tens of MB however large S is, while each block is still one vectorised numpy call.
_BLOCK_ELEMENTS = 1 << 22


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------
def _check_S(S) -> np.ndarray:
    arr = np.asarray(S)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise TypeError(f"S must be a numeric array; got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise TypeError(f"S must hold real scores; got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise ValueError(f"S must have shape (n_query, n_reference); got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"S is empty: got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    # Fast path: a finite sum proves every entry finite (NaN/inf propagate through a sum) without
    # an elementwise temporary of S's size; only when the sum is not finite (a bad entry, or
    # overflow) pay for the full elementwise check.
    with np.errstate(over="ignore", invalid="ignore"):
        total = arr.sum()
    if not np.isfinite(total) and not np.isfinite(arr).all():
        raise ValueError("S contains NaN or infinite values; scores must be finite")
    return arr


def _as_flags(values, name: str) -> np.ndarray:
    """``values`` as a bool array: booleans, or integers 0/1 (masks loaded from text files are
    common); other integers are a bug (ValueError), other dtypes a TypeError."""
    arr = np.asarray(values)
    if arr.dtype == np.bool_ or (arr.size == 0 and arr.dtype.kind in "biuf"):  # ([] is float)
        return arr.astype(np.bool_)
    if np.issubdtype(arr.dtype, np.integer):
        if arr.size and not np.isin(arr, (0, 1)).all():
            raise ValueError(
                f"{name} must be boolean (or integers 0/1); got integer values other than 0 and 1"
            )
        return arr.astype(np.bool_)
    raise TypeError(f"{name} must be a boolean array (or integers 0/1); got dtype {arr.dtype}")


def _check_gt(gt, shape: tuple[int, int]) -> np.ndarray:
    arr = _as_flags(gt, "gt")
    if arr.shape != tuple(shape):
        raise ValueError(f"gt must have shape {tuple(shape)}; got {arr.shape}")
    return arr


def _check_inputs(S, gt) -> tuple[np.ndarray, np.ndarray]:
    S = _check_S(S)
    gt = _check_gt(gt, S.shape)
    return S, gt


def as_floats(values, name: str) -> np.ndarray:
    """``values`` (array-like of numbers or booleans) as a float64 array; a TypeError naming
    ``name`` for strings, objects and the like."""
    try:
        arr = np.asarray(values)
    except Exception as exc:  # ragged lists and such
        raise TypeError(f"{name} must be an array of numbers; {exc}") from exc
    if arr.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be numbers; got dtype {arr.dtype}")
    return arr.astype(np.float64)


def _check_k(k, name: str = "k") -> int:
    if isinstance(k, bool) or not isinstance(k, (numbers.Integral, np.integer)):
        raise TypeError(f"{name} must be an int; got {type(k).__name__}")
    if k < 1:
        raise ValueError(f"{name} must be >= 1; got {k}")
    return int(k)


def _match_rows(gt: np.ndarray) -> tuple[np.ndarray, int]:
    """Which queries have a true match, and how many (recall's denominator)."""
    has_match = np.any(gt, axis=1)
    n = int(np.count_nonzero(has_match))
    if n == 0:
        raise ValueError(
            "gt has no true match for any query: recall is undefined "
            f"(gt has shape {gt.shape} and no True entry)"
        )
    return has_match, n


# --------------------------------------------------------------------------------------------
# core computations on validated arrays
# --------------------------------------------------------------------------------------------
def _best_match(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # np.argmax returns the first maximal index, i.e. the lowest reference index on ties.
    idx = np.argmax(S, axis=1)
    conf = np.take_along_axis(S, idx[:, None], axis=1)[:, 0]
    return idx.astype(np.int64, copy=False), conf


def _curve(S: np.ndarray, gt: np.ndarray, n_pos: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    idx, conf = _best_match(S)
    return _answer_curve(conf, gt[np.arange(S.shape[0]), idx], n_pos)


def _answer_curve(
    conf: np.ndarray, correct: np.ndarray, n_pos: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    # Descending confidence; the order inside a tie does not matter because only the last
    # position of each run of equal confidences becomes a curve point.
    order = np.argsort(conf, kind="stable")[::-1]
    conf_sorted = conf[order]
    tp = np.cumsum(correct[order], dtype=np.int64)
    last_of_run = np.flatnonzero(np.r_[conf_sorted[1:] != conf_sorted[:-1], True])
    n_above = last_of_run + 1
    tp_above = tp[last_of_run]
    precision = tp_above / n_above
    recall = tp_above / n_pos
    thresholds = conf_sorted[last_of_run]
    return precision, recall, thresholds


def _auc(precision: np.ndarray, recall: np.ndarray) -> float:
    # Anchor at recall 0 with the precision of the highest threshold (see pr_auc's Notes).
    r = np.r_[0.0, recall]
    p = np.r_[precision[0], precision]
    return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) * 0.5))


def _recall_at_100_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    # tp / n == 1.0 exactly iff tp == n for integer counts far below 2**53.
    perfect = precision == 1.0
    return float(recall[perfect].max()) if perfect.any() else 0.0


def _extended_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    # Point 0 (the highest threshold) has the lowest recall; among points that share that
    # recall it has the highest precision, since later ones only add wrong predictions.
    return 0.5 * (float(precision[0]) + _recall_at_100_precision(precision, recall))


def _best_true_rank(S: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Rank (0 = top) of each query's best-ranked true reference; meaningless for rows of
    ``gt`` without any True (callers mask those out)."""
    n_query, n_ref = S.shape
    # The rank of reference j in its row (score descending, then index ascending) is
    #   #{i : S[i] > S[j]} + #{i < j : S[i] == S[j]},
    # and the best-ranked true reference is the first argmax of S restricted to gt. So one
    # argmax and a few comparison counts per row give exact, deterministic tie handling (an
    # argpartition would leave the order inside ties unspecified), and the same ranks serve
    # every k. Row blocks keep the temporaries small for large S; each block is one vectorised
    # pass, there is no loop over queries.
    ranks = np.empty(n_query, dtype=np.int64)
    block = max(1, _BLOCK_ELEMENTS // n_ref)
    cols = np.arange(n_ref)
    for start in range(0, n_query, block):
        rows = slice(start, start + block)
        s, g = S[rows], gt[rows]
        j_best = np.argmax(np.where(g, s, -np.inf), axis=1)
        s_best = np.take_along_axis(s, j_best[:, None], axis=1)
        n_greater = np.count_nonzero(s > s_best, axis=1)
        n_ties = np.count_nonzero(s >= s_best, axis=1) - n_greater  # includes j_best itself
        rank = n_greater
        # Ties are rare with real-valued scores: resolve them only on the rows that have any.
        tied = np.flatnonzero(n_ties > 1)
        if tied.size:
            before = (s[tied] == s_best[tied]) & (cols < j_best[tied, None])
            rank[tied] += np.count_nonzero(before, axis=1)
        ranks[rows] = rank
    return ranks


def _recall_at_ks(
    S: np.ndarray, gt: np.ndarray, has_match: np.ndarray, n_pos: int, ks
) -> list[float]:
    ranks = _best_true_rank(S, gt)[has_match]
    # k > n_reference needs no explicit clamp: every rank is < n_reference.
    return [int(np.count_nonzero(ranks < k)) / n_pos for k in ks]


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------
def best_match(S) -> tuple[np.ndarray, np.ndarray]:
    """Each query's prediction: its best-scoring reference and that score.

    The prediction of query ``q`` is ``argmax_j S[q, j]``; ties go to the lowest reference index.
    The score at the prediction is its confidence.

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.

    Returns
    -------
    indices : ndarray of int64, shape (n_query,)
        Predicted reference index for each query.
    confidences : ndarray of float, shape (n_query,)
        ``S[q, indices[q]]``.

    Raises
    ------
    TypeError
        If ``S`` is not numeric.
    ValueError
        If ``S`` is not 2-d, is empty or holds NaN/inf.

    Examples
    --------
    >>> idx, conf = best_match([[0.1, 0.9, 0.9], [0.5, 0.2, 0.0]])
    >>> idx.tolist(), conf.tolist()
    ([1, 0], [0.9, 0.5])
    """
    return _best_match(_check_S(S))


def precision_recall_curve(S, gt) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision-recall curve of the best-match predictions (paper, Sec. Evaluation Metrics).

    Each query's best-scoring reference (row argmax of ``S``; ties -> lowest reference index) is
    its prediction, with that score as confidence. A prediction is correct when
    ``gt[q, pred]`` is True. For a threshold ``t`` the predictions above the threshold are those
    with confidence ``>= t``; ``precision(t)`` = correct predictions above ``t`` / predictions
    above ``t``; ``recall(t)`` = correct predictions above ``t`` / number of queries with at
    least one True in their ``gt`` row. Queries with no true match still predict (always wrong,
    counted in precision's denominator) but are not in recall's denominator.

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match. Integer arrays holding only 0 and 1 are
        accepted and cast.

    Returns
    -------
    precision : ndarray of float64, shape (n_points,)
    recall : ndarray of float64, shape (n_points,)
        Non-decreasing.
    thresholds : ndarray, shape (n_points,)
        The distinct confidence values, in decreasing order; point ``i`` uses
        ``confidence >= thresholds[i]``. ``n_points`` is the number of distinct confidences, and
        the last point (lowest threshold) keeps every prediction.

    Raises
    ------
    TypeError
        If ``S`` is not numeric or ``gt`` is neither boolean nor integer.
    ValueError
        If ``S`` is not 2-d, empty or non-finite; if ``gt`` has another shape or integer values
        other than 0/1; if ``gt`` has no True entry (recall undefined).

    Examples
    --------
    >>> S = [[0.9, 0.1], [0.2, 0.8], [0.7, 0.3]]
    >>> gt = [[True, False], [True, False], [False, True]]
    >>> p, r, t = precision_recall_curve(S, gt)
    >>> p.tolist(), r.tolist(), t.tolist()
    ([1.0, 0.5, 0.3333333333333333], [0.3333333333333333, 0.3333333333333333, 0.3333333333333333], [0.9, 0.8, 0.7])
    """  # noqa: E501
    S, gt = _check_inputs(S, gt)
    return _curve(S, gt, _match_rows(gt)[1])


def pr_auc(S, gt) -> float:
    """Area under the precision-recall curve (the paper's AUC).

    The curve is :func:`precision_recall_curve`; the area is the trapezoidal integral of
    precision over recall.

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match.

    Returns
    -------
    float
        In [0, 1]. Equals 1 when every query has a true match and every prediction is
        correct (to the last bit: the trapezoids' float sum may give 0.9999999999999999).

    Raises
    ------
    TypeError, ValueError
        As :func:`precision_recall_curve`; in particular ``ValueError`` when ``gt`` has no True
        entry, since recall (the integration variable) is then undefined.

    Notes
    -----
    The curve is anchored at recall 0 with the precision of the highest threshold, i.e. the
    point ``(0, precision[0])`` is prepended, so the first segment is flat. The common
    alternative anchor ``(0, 1)`` is optimistic: it credits perfect precision that no threshold
    achieves, and inflates the area most for weak systems. Trapezoids between points (rather
    than scikit-learn's step-wise average precision) follow the usual VPR practice of
    integrating the plotted curve.

    Examples
    --------
    >>> S = [[0.9, 0.1], [0.2, 0.8], [0.7, 0.3]]
    >>> gt = [[True, False], [False, True], [False, True]]
    >>> round(pr_auc(S, gt), 6)  # points (0, 1), (1/3, 1), (2/3, 1), (2/3, 2/3)
    0.666667
    """
    S, gt = _check_inputs(S, gt)
    return _auc(*_curve(S, gt, _match_rows(gt)[1])[:2])


def recall_at_k(S, gt, k: int) -> float:
    """Fraction of matchable queries with a true match among their top-``k`` references.

    The top-``k`` references of a query are its ``k`` highest scores, ties broken by the lower
    reference index (deterministic). The denominator is the number of queries with at least one
    True in their ``gt`` row (recall is per query, not per reference entry).

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match.
    k : int
        At least 1; values above ``n_reference`` are clamped to ``n_reference``.

    Returns
    -------
    float
        In [0, 1]. ``recall_at_k(S, gt, 1)`` equals the last recall of
        :func:`precision_recall_curve`.

    Raises
    ------
    TypeError
        If ``k`` is not an int, or as :func:`precision_recall_curve`.
    ValueError
        If ``k < 1``, or as :func:`precision_recall_curve` (including ``gt`` without any True).

    Examples
    --------
    >>> S = [[0.9, 0.5, 0.1], [0.1, 0.2, 0.3]]
    >>> gt = [[False, True, False], [True, False, False]]
    >>> recall_at_k(S, gt, 1), recall_at_k(S, gt, 2), recall_at_k(S, gt, 3)
    (0.0, 0.5, 1.0)
    """
    k = _check_k(k)
    S, gt = _check_inputs(S, gt)
    return _recall_at_ks(S, gt, *_match_rows(gt), [k])[0]


def recall_at_100_precision(S, gt) -> float:
    """Largest recall among the thresholds whose precision is exactly 1.

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match.

    Returns
    -------
    float
        0.0 when no threshold reaches precision 1 (e.g. the most confident prediction is wrong).

    Raises
    ------
    TypeError, ValueError
        As :func:`precision_recall_curve`.

    Examples
    --------
    >>> S = [[0.9, 0.1], [0.2, 0.8], [0.7, 0.3]]
    >>> gt = [[True, False], [False, True], [False, True]]
    >>> recall_at_100_precision(S, gt)
    0.6666666666666666
    """
    S, gt = _check_inputs(S, gt)
    return _recall_at_100_precision(*_curve(S, gt, _match_rows(gt)[1])[:2])


def extended_precision(S, gt) -> float:
    """Extended Precision: ``EP = (P_R0 + R_P100) / 2``.

    Ferrarini et al., "Exploring Performance Bounds of Visual Place Recognition Using Extended
    Precision", IEEE RA-L 5(2), 2020, as VPR-Bench uses it (Zaffar et al., IJCV 129, 2021):
    ``P_R0`` is the precision at the
    lowest recall of the precision-recall curve and ``R_P100`` the largest recall at 100%
    precision (:func:`recall_at_100_precision`).  Here ``P_R0`` is the precision of the
    curve's first point (:func:`precision_recall_curve`): the share of correct predictions
    among those with the highest confidence (one prediction unless several tie), which is the
    highest precision among the points that share the lowest recall.  EP rewards a system
    whose most confident predictions are right and that keeps precision 1 for long; unlike the
    AUC it ignores the low-precision tail.  The recall is this module's, the share of the
    queries that have an acceptable reference: VPR-Bench's own code divides by the number of
    right predictions instead, so its EP differs wherever a prediction is wrong (see the
    metrics guide).

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match.

    Returns
    -------
    float
        In [0, 1]: at most 0.5 when the most confident prediction is wrong (then ``R_P100`` is
        0), at least 0.5 when the most confident prediction is right (``P_R0`` is 1 then,
        unless several predictions tie at the top), and 1 exactly when every query has a true
        match and every prediction is correct.

    Raises
    ------
    TypeError, ValueError
        As :func:`precision_recall_curve`.

    Examples
    --------
    >>> S = [[0.9, 0.1], [0.2, 0.8], [0.7, 0.3]]
    >>> gt = [[True, False], [False, True], [False, True]]
    >>> extended_precision(S, gt)  # P_R0 = 1 (q0 right), R_P100 = 2/3 (q0, q1 right; q2 wrong)
    0.8333333333333333
    >>> gt = [[False, True], [False, True], [True, False]]
    >>> extended_precision(S, gt)  # the most confident prediction (q0) is wrong: P_R0 = 0
    0.0
    """
    S, gt = _check_inputs(S, gt)
    return _extended_precision(*_curve(S, gt, _match_rows(gt)[1])[:2])


def evaluate(S, gt, ks=(1, 5, 10)) -> dict:
    """All metrics at once, as plain Python types (JSON-serialisable).

    Parameters
    ----------
    S : array_like, shape (n_query, n_reference)
        Finite scores, higher = more similar.
    gt : array_like of bool, shape (n_query, n_reference)
        True where the reference is an acceptable match.
    ks : iterable of int, default (1, 5, 10)
        The ``k`` of each reported ``recall_at_{k}``.

    Returns
    -------
    dict
        ``auc`` (:func:`pr_auc`), ``recall_at_{k}`` for each ``k`` in ``ks``
        (:func:`recall_at_k`), ``recall_at_100_precision``, ``extended_precision``
        (:func:`extended_precision`), ``precision``, ``recall`` and
        ``thresholds`` (lists of float, the curve of :func:`precision_recall_curve`),
        ``n_query``, ``n_reference`` and ``n_query_with_match`` (int).

    Raises
    ------
    TypeError, ValueError
        As the individual functions; ``ks`` must be an iterable of ints >= 1.
    """
    if isinstance(ks, (numbers.Integral, np.integer)):
        raise TypeError(f"ks must be an iterable of ints; got a single int {ks}")
    try:
        ks = [_check_k(k) for k in ks]
    except TypeError as exc:
        raise TypeError(f"ks must be an iterable of ints >= 1; {exc}") from exc
    except ValueError as exc:
        raise ValueError(f"ks must be an iterable of ints >= 1; {exc}") from exc
    S, gt = _check_inputs(S, gt)
    has_match, n_pos = _match_rows(gt)
    precision, recall, thresholds = _curve(S, gt, n_pos)
    result: dict[str, Any] = {"auc": _auc(precision, recall)}
    for k, value in zip(ks, _recall_at_ks(S, gt, has_match, n_pos, ks), strict=True):
        result[f"recall_at_{k}"] = value
    result.update(
        recall_at_100_precision=_recall_at_100_precision(precision, recall),
        extended_precision=_extended_precision(precision, recall),
        precision=precision.tolist(),
        recall=recall.tolist(),
        thresholds=[float(t) for t in thresholds.tolist()],
        n_query=int(S.shape[0]),
        n_reference=int(S.shape[1]),
        n_query_with_match=n_pos,
    )
    return result


def evaluate_answers(confidence, correct, has_match) -> dict:
    """:func:`evaluate`'s curve metrics from each query's answer alone, without a score matrix.

    For a localizer on a map too large for score rows over every place (a
    :class:`flyvpr.large.LargeLocalizer`): each query's answer, its confidence and whether it
    is right give the same precision-recall curve as :func:`evaluate` on a score matrix whose
    row maximum is that answer at that confidence.

    Parameters
    ----------
    confidence : array_like of float, shape (n_query,)
        Finite; higher = surer.
    correct : array_like of bool (or integers 0/1), shape (n_query,)
        Whether the answer is an acceptable match.
    has_match : array_like of bool (or integers 0/1), shape (n_query,)
        Whether the query has any acceptable match (recall's denominator counts these).

    Returns
    -------
    dict
        ``auc``, ``recall_at_1``, ``recall_at_100_precision``, ``extended_precision``,
        ``n_query`` and ``n_query_with_match``.

    Raises
    ------
    ValueError
        For shapes that differ, a non-finite confidence, integer flags other than 0 and 1, no
        query with a match, or a correct answer for a query without one.
    TypeError
        For confidences that are not numbers, or flags that are neither booleans nor integers.

    Examples
    --------
    >>> r = evaluate_answers([0.9, 0.8, 0.3], [True, False, True], [True, True, True])
    >>> round(r["auc"], 4), round(r["recall_at_1"], 4)
    (0.5278, 0.6667)
    """
    conf = as_floats(confidence, "confidence")
    right = _as_flags(correct, "correct")
    match = _as_flags(has_match, "has_match")
    if conf.ndim != 1 or right.shape != conf.shape or match.shape != conf.shape:
        raise ValueError(
            "confidence, correct and has_match must be 1-d of one length; got shapes "
            f"{conf.shape}, {right.shape} and {match.shape}"
        )
    if not np.isfinite(conf).all():
        raise ValueError("confidence must be finite")
    if (right & ~match).any():
        raise ValueError("correct is True for a query whose has_match is False")
    n_pos = int(np.count_nonzero(match))
    if n_pos == 0:
        raise ValueError("has_match is False for every query: recall is undefined")
    precision, recall, _ = _answer_curve(conf, right, n_pos)
    return {
        "auc": _auc(precision, recall),
        "recall_at_1": int(np.count_nonzero(right)) / n_pos,
        "recall_at_100_precision": _recall_at_100_precision(precision, recall),
        "extended_precision": _extended_precision(precision, recall),
        "n_query": int(conf.size),
        "n_query_with_match": n_pos,
    }


# --------------------------------------------------------------------------------------------
# calibration of a probability-like confidence
# --------------------------------------------------------------------------------------------
def reliability_counts(confidence, right, bins: int = 10) -> tuple:
    """Per confidence bin: answers, their summed confidence and how many were right.

    The bins split [0, 1] into ``bins`` equal parts (a confidence of 1 falls in the last).
    Counts, not means, so that the tables of several runs add up.

    Parameters
    ----------
    confidence : array-like of float in [0, 1]
        One answer's confidence each (a probability that the answer is right: the CANN's).
    right : array-like of bool, same length
        Whether each answer was right.
    bins : int, default 10

    Returns
    -------
    n, confidence_sum, right_count : ndarray, shape (bins,)

    Raises
    ------
    TypeError, ValueError
        For ``bins`` not an int >= 1, confidences not finite or outside [0, 1], or labels of
        another length or not booleans (or integers 0/1, as every metric takes them).

    Examples
    --------
    >>> n, c, r = reliability_counts([0.05, 0.15, 0.95, 1.0], [False, True, True, True], bins=2)
    >>> n.tolist(), c.round(2).tolist(), r.tolist()
    ([2, 2], [0.2, 1.95], [1, 2])
    """
    bins = _check_k(bins, "bins")
    c = as_floats(confidence, "confidence").ravel()
    r = _as_flags(right, "right").ravel()
    if r.shape != c.shape:
        raise ValueError(f"right must hold one label per confidence: {c.size}; got {r.size}")
    if c.size and not (np.isfinite(c).all() and c.min() >= 0.0 and c.max() <= 1.0):
        raise ValueError("confidence must be finite and lie in [0, 1]")
    # The bin: how many of the inner edges 1/bins, 2/bins, ... lie at or below (compared with
    # the edges themselves: c * bins misplaces some, 0.29 * 100 = 28.999...).
    b = np.searchsorted(np.arange(1, bins) / bins, c, side="right")
    return (
        np.bincount(b, minlength=bins),
        np.bincount(b, c, minlength=bins),
        np.bincount(b, r, minlength=bins).astype(np.int64),
    )


def reliability(confidence, right, bins: int = 10) -> list[dict]:
    """The reliability table: per confidence bin with answers, its range (``bin``, e.g.
    ``"0.9-1.0"``), answers (``n``), mean ``confidence`` and share ``right``.  A calibrated
    confidence is right as often as it says; see :func:`reliability_counts` for the bins and
    the checks.

    Examples
    --------
    >>> [(r["bin"], r["n"], r["right"]) for r in reliability([0.05, 0.95, 1.0], [0, 1, 0])]
    [('0.0-0.1', 1, 0.0), ('0.9-1.0', 2, 0.5)]
    """
    n, total, hits = reliability_counts(confidence, right, bins)
    # The fewest decimals that write every edge exactly (0.1 for ten bins, 0.05 for twenty,
    # 0.0625 for sixteen), up to six; three where none does (thirds: 0.333-0.667).
    edges = np.arange(bins + 1) / bins
    digits = next((d for d in range(1, 7) if np.allclose(edges.round(d), edges, 0, 1e-12)), 3)
    return [
        {
            "bin": f"{k / bins:.{digits}f}-{(k + 1) / bins:.{digits}f}",
            "n": int(n[k]),
            "confidence": float(total[k] / n[k]),
            "right": float(hits[k] / n[k]),
        }
        for k in np.flatnonzero(n)
    ]
