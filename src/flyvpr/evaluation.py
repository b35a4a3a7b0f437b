"""Run one method on one benchmark and collect metrics, timings and footprint.

Used by ``flyvpr evaluate``, ``flyvpr demo`` and the benchmark scripts so that
every number is produced by the same code path.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from . import metrics
from ._validation import check_positive_int
from .methods import Method, make_method

logger = logging.getLogger(__name__)

__all__ = ["evaluate_method", "RESULT_FIELDS", "self_match_share", "check_true_matches"]

#: fields every result dict carries (the JSON written by ``flyvpr evaluate``)
RESULT_FIELDS = (
    "method",
    "auc",
    "recall_at_1",
    "recall_at_5",
    "recall_at_10",
    "recall_at_100_precision",
    "extended_precision",
    "precision",
    "recall",
    "train_accuracy",
    "timing",
    "footprint",
    "seed",
    "n_reference",
    "n_query",
    "n_query_with_match",
)


def evaluate_method(
    method: str | Method,
    reference_images,
    query_images,
    ground_truth,
    *,
    seed=0,
    frontend_params=None,
    filter_params=None,
    load_s: float | None = None,
    return_scores: bool = False,
    measure_model_bytes: bool = False,
):
    """Fit ``method`` on the reference images, score the queries and measure it.

    Parameters
    ----------
    method : str or Method
        A name of :data:`flyvpr.methods.METHODS`, or a fitted :class:`Method` (then nothing
        is trained and ``fit_s`` is 0).
    reference_images, query_images : ndarray, shape (n, H, W)
        Gray float32 images in [0, 1].
    ground_truth : ndarray of bool, shape (n_query, n_reference)
    seed : int
        ``random_state`` of every random part, when ``method`` is a name (a ready
        ``Method`` keeps its own; ``seed`` is then only recorded in the result).
    frontend_params, filter_params : dict, optional
        Constructor arguments of the parts, when ``method`` is a name (ignored otherwise).
    load_s : float, optional
        Seconds spent loading the images, copied into ``timing``.
    return_scores : bool
        Also return the score matrix.
    measure_model_bytes : bool
        Save the fitted model with :func:`flyvpr.modelio.save_method` to a temporary file and
        record its size as ``model_bytes``.

    Returns
    -------
    dict
        See :data:`RESULT_FIELDS`; ``timing`` holds ``load_s``, ``fit_s``,
        ``encode_s`` (query encoding), ``match_s`` (scoring and filtering) and
        ``per_query_ms`` = (encode_s + match_s) / n_query in milliseconds.
    """
    gt = np.asarray(ground_truth)
    n_query, n_ref = len(query_images), len(reference_images)
    if gt.shape != (n_query, n_ref):
        raise ValueError(
            f"ground_truth must have shape (n_query, n_reference) = {(n_query, n_ref)}; "
            f"got {gt.shape}"
        )
    if isinstance(method, Method):  # already fitted, e.g. loaded from a model file
        model = method
        if model.frontend.n_reference_ != n_ref:
            raise ValueError(
                f"the model knows {model.frontend.n_reference_} reference places; the "
                f"reference traverse has {n_ref}"
            )
        model.timing_ = {"fit_s": 0.0}
        method = model.name
    else:
        model = make_method(method, seed, frontend_params, filter_params)
        model.fit(reference_images)
    S = model.score(query_images)
    scores = metrics.evaluate(S, gt)
    timing = {"load_s": load_s, **model.timing_}
    timing["per_query_ms"] = 1000.0 * (timing["encode_s"] + timing["match_s"]) / n_query
    result = {
        "method": method,
        "seed": seed,
        "n_reference": n_ref,
        "n_query": n_query,
        # recall's denominator: with it and each query's confidence and correctness, the
        # curve, AUC, R@1 and R@100%P can be recomputed from a result file
        "n_query_with_match": scores["n_query_with_match"],
        "auc": scores["auc"],
        "recall_at_1": scores["recall_at_1"],
        "recall_at_5": scores["recall_at_5"],
        "recall_at_10": scores["recall_at_10"],
        "recall_at_100_precision": scores["recall_at_100_precision"],
        "extended_precision": scores["extended_precision"],
        "precision": scores["precision"],
        "recall": scores["recall"],
        "train_accuracy": model.train_accuracy,
        "timing": timing,
        "footprint": model.footprint(),
        "frontend_params": _plain(model.frontend.get_params(), seed),
        "filter_params": _plain(model.filter.get_params(), seed) if model.filter else None,
    }
    if measure_model_bytes:
        import tempfile
        from pathlib import Path

        from .modelio import save_method

        with tempfile.TemporaryDirectory() as tmp:
            path = save_method(
                model, Path(tmp) / "model.npz", size=tuple(np.shape(query_images)[1:])
            )
            result["model_bytes"] = path.stat().st_size
    if return_scores:
        return result, S
    return result


def check_true_matches(benchmark) -> None:
    """Refuse, before any work, a benchmark whose ground truth gives no query a true match.

    Recall, and with it every metric of :func:`evaluate_method`, is undefined then
    (:mod:`flyvpr.metrics`), so fitting and scoring would be wasted.

    Parameters
    ----------
    benchmark : flyvpr.datasets.Benchmark

    Raises
    ------
    ValueError
        If ``benchmark.ground_truth`` holds no True; the message gives the tolerance and the
        numbers of frames.

    A ground truth in which every query matches every reference is let through with a
    warning: every method then scores 1, whatever it does (a tolerance as long as the
    traverses, or positions in degrees read as metres).
    """
    gt = benchmark.ground_truth
    tolerance = ", ".join(f"{v} {unit}" for unit, v in benchmark.tolerance.items()) or "none"
    if gt.size and np.all(gt):
        logger.warning(
            "the ground truth matches every one of the %d queries with every one of the %d "
            "references (tolerance %s): every method scores 1 whatever it answers; check the "
            "tolerance (or radius: positions in degrees are not metres)",
            benchmark.n_query, benchmark.n_reference, tolerance,
        )  # fmt: skip
    if np.any(gt):
        return
    raise ValueError(
        f"the ground truth gives no query a true match: none of the {benchmark.n_query} "
        f"queries lies within the tolerance ({tolerance}) of any of the "
        f"{benchmark.n_reference} references, so recall is undefined; widen the tolerance (or "
        "radius), or check the frames (or positions) of the two traverses"
    )


def self_match_share(model: Method, reference_images, *, radius: int = 2, sample: int = 200):
    """Share of reference images that find their own place through ``model``'s front end.

    A check that a loaded model belongs to a reference window: near 1 for the images it was
    fitted on (a classifier's training accuracy, within the tolerance), near 0 for another
    stretch of the route.

    Parameters
    ----------
    model : Method
        Fitted on as many places as there are ``reference_images``.
    reference_images : ndarray, shape (n, H, W)
    radius : int, default 2
        An image finds its place when a place within ``radius`` of its own index scores as
        high as any (a tie with its own counts: a run of identical frames is not a miss).
    sample : int, default 200
        At most this many images, evenly spaced (the first and, for a sample of 2 or more,
        the last included), are scored.

    Returns
    -------
    float
        In [0, 1].

    Raises
    ------
    ValueError
        For no image, a number of images other than the model's places, ``sample`` < 1 or
        ``radius`` < 0.
    """
    n = len(reference_images)
    if n == 0:
        raise ValueError("reference_images is empty")
    if model.frontend.n_reference_ != n:
        raise ValueError(
            f"the model knows {model.frontend.n_reference_} reference places; got {n} images"
        )
    sample = check_positive_int(sample, "sample")
    radius = check_positive_int(radius, "radius", minimum=0)
    idx = np.unique(np.linspace(0, n - 1, min(sample, n)).round().astype(np.int64))
    scores = np.asarray(model.frontend.score(reference_images[idx]), np.float64)
    near = np.abs(np.arange(n)[None, :] - idx[:, None]) <= radius
    own = np.where(near, scores, -np.inf).max(axis=1)
    return float(np.mean(own >= scores.max(axis=1)))


def _plain(params: dict, seed) -> dict:
    """JSON-friendly copy of estimator parameters; a Generator drawn from ``seed`` shows as it."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, np.random.Generator):
            out[key] = f"from seed {seed}"
        elif isinstance(value, (bool, int, float, str, type(None))):
            out[key] = value
        elif isinstance(value, (np.integer, np.floating)):
            out[key] = value.item()
        elif isinstance(value, (list, tuple)):
            out[key] = list(value)
        else:
            out[key] = repr(value)
    return out


def speed_profile(n_frames: int, speed, random_state=None) -> np.ndarray:
    """Indices of the query frames kept to simulate a robot moving at another speed.

    Parameters
    ----------
    n_frames : int
        Frames in the original (1 place per frame) query traverse.
    speed : float or (float, float)
        A constant speed in places per frame (2.0 keeps every 2nd frame), or a
        range ``(low, high)``: each frame's step is drawn uniformly from it.
    random_state : None, int or Generator
        Seed of the random profile.

    Returns
    -------
    ndarray of int64
        Non-decreasing frame indices (a speed below 1 repeats frames: a slower query),
        starting at 0, all ``< n_frames``.  The
        ground truth of the kept frames is ``gt[indices]``.

    Examples
    --------
    >>> speed_profile(7, 2.0)
    array([0, 2, 4, 6])
    """
    from ._validation import check_positive_int, check_random_state

    n_frames = check_positive_int(n_frames, "n_frames")
    try:
        if np.ndim(speed) == 0:
            low = high = float(speed)
        else:
            low, high = (float(v) for v in speed)
    except (TypeError, ValueError):
        raise ValueError(f"speed must be a number or a (low, high) pair; got {speed!r}") from None
    if not (0 < low <= high) or not np.isfinite(high):
        raise ValueError(f"speed must be positive with low <= high; got {speed!r}")
    # Enough steps to cover the traverse even at the lowest speed.
    n_steps = int(np.ceil(n_frames / low)) + 1
    if low == high:
        steps = np.full(n_steps, low)
    else:
        steps = check_random_state(random_state).uniform(low, high, size=n_steps)
    pos = np.concatenate([[0.0], np.cumsum(steps)])
    idx = np.floor(pos + 1e-9).astype(np.int64)
    return idx[idx < n_frames]
