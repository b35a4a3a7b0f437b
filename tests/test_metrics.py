"""Tests for flyvpr.metrics: hand-worked cases, a slow loop reference, properties, errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from flyvpr.metrics import (
    best_match,
    evaluate,
    extended_precision,
    pr_auc,
    precision_recall_curve,
    recall_at_100_precision,
    recall_at_k,
)

T, F = True, False


# --------------------------------------------------------------------------------------------
# slow, obviously correct reference implementations (plain Python loops)
# --------------------------------------------------------------------------------------------
def loop_best_match(S):
    preds, confs = [], []
    for row in S.tolist():
        best = 0
        for j in range(len(row)):
            if row[j] > row[best]:  # strict: a tie keeps the lower index
                best = j
        preds.append(best)
        confs.append(row[best])
    return preds, confs


def loop_curve(S, gt):
    preds, confs = loop_best_match(S)
    gt_rows = gt.tolist()
    n_pos = sum(1 for row in gt_rows if any(row))
    precision, recall, thresholds = [], [], []
    for t in sorted(set(confs), reverse=True):
        n_above = 0
        n_correct = 0
        for q in range(len(preds)):
            if confs[q] >= t:
                n_above += 1
                if gt_rows[q][preds[q]]:
                    n_correct += 1
        precision.append(n_correct / n_above)
        recall.append(n_correct / n_pos)
        thresholds.append(t)
    return precision, recall, thresholds


def loop_auc(S, gt):
    precision, recall, _ = loop_curve(S, gt)
    xs = [0.0] + recall
    ys = [precision[0]] + precision
    area = 0.0
    for i in range(1, len(xs)):
        area += (xs[i] - xs[i - 1]) * (ys[i] + ys[i - 1]) / 2
    return area


def loop_recall_at_k(S, gt, k):
    n_pos = 0
    hits = 0
    for row, gt_row in zip(S.tolist(), gt.tolist(), strict=True):
        if not any(gt_row):
            continue
        n_pos += 1
        ranked = sorted(range(len(row)), key=lambda j, row=row: (-row[j], j))
        if any(gt_row[j] for j in ranked[:k]):
            hits += 1
    return hits / n_pos


def loop_recall_at_100_precision(S, gt):
    precision, recall, _ = loop_curve(S, gt)
    best = 0.0
    for p, r in zip(precision, recall, strict=True):
        if p == 1.0 and r > best:
            best = r
    return best


def loop_extended_precision(S, gt):
    """(precision at the lowest recall + largest recall at precision 1) / 2, by plain loops."""
    precision, recall, _ = loop_curve(S, gt)
    lowest = min(recall)
    p_r0 = max(p for p, r in zip(precision, recall, strict=True) if r == lowest)
    return (p_r0 + loop_recall_at_100_precision(S, gt)) / 2


def random_case(shape, seed, ties):
    """Random S (with many ties when ``ties``) and gt with a few rows without any match."""
    rng = np.random.default_rng(seed)
    n_query, n_ref = shape
    if ties:
        S = rng.integers(0, 4, size=shape).astype(np.float64)
    else:
        S = rng.standard_normal(shape)
    gt = rng.random(shape) < 0.3
    # Favour the argmax sometimes so that precision is not always tiny.
    hit = rng.random(n_query) < 0.5
    gt[np.arange(n_query)[hit], np.argmax(S, axis=1)[hit]] = True
    # Some queries with no true match at all.
    gt[rng.random(n_query) < 0.2] = False
    if not gt.any():
        gt[0, 0] = True
    return S, gt


SHAPES = [(1, 1), (1, 6), (6, 1), (3, 3), (9, 4), (4, 9), (40, 15), (15, 40), (60, 60)]


# --------------------------------------------------------------------------------------------
# hand-worked 3x3 cases
# --------------------------------------------------------------------------------------------
def test_hand_worked_mixed_with_unmatched_query():
    S = np.array([[0.9, 0.1, 0.0], [0.3, 0.2, 0.6], [0.5, 0.4, 0.1]])
    gt = np.array([[T, F, F], [F, T, F], [F, F, F]])
    # Predictions: q0 -> ref 0 (0.9, correct), q1 -> ref 2 (0.6, wrong), q2 -> ref 0 (0.5, wrong;
    # q2 has no true match at all). Queries with a match: q0, q1 -> recall denominator 2.
    # t=0.9: 1 above, 1 correct -> P=1,   R=1/2
    # t=0.6: 2 above, 1 correct -> P=1/2, R=1/2
    # t=0.5: 3 above, 1 correct -> P=1/3, R=1/2   (q2 counts in precision, not in recall)
    idx, conf = best_match(S)
    assert idx.tolist() == [0, 2, 0]
    np.testing.assert_allclose(conf, [0.9, 0.6, 0.5])
    p, r, t = precision_recall_curve(S, gt)
    np.testing.assert_allclose(p, [1, 1 / 2, 1 / 3])
    np.testing.assert_allclose(r, [1 / 2, 1 / 2, 1 / 2])
    np.testing.assert_allclose(t, [0.9, 0.6, 0.5])
    # AUC: anchor (0, 1) -> (1/2, 1): area 1/2; the remaining segments have zero width.
    assert pr_auc(S, gt) == pytest.approx(0.5)
    assert recall_at_100_precision(S, gt) == pytest.approx(0.5)
    # EP: P_R0 = 1 (the 0.9 prediction is right), R@100P = 1/2 -> (1 + 1/2) / 2.
    assert extended_precision(S, gt) == pytest.approx(3 / 4)
    # recall@k: q0 hit at k=1; q1's true ref 1 (0.2) ranks third behind 0.6 and 0.3.
    assert recall_at_k(S, gt, 1) == pytest.approx(1 / 2)
    assert recall_at_k(S, gt, 2) == pytest.approx(1 / 2)
    assert recall_at_k(S, gt, 3) == pytest.approx(1.0)


def test_hand_worked_ties():
    S = np.array([[0.5, 0.5, 0.1], [0.2, 0.7, 0.7], [0.7, 0.0, 0.0]])
    gt = np.array([[F, T, F], [F, F, T], [T, F, F]])
    # Row ties go to the lowest index: q0 -> ref 0 (0.5, wrong), q1 -> ref 1 (0.7, wrong),
    # q2 -> ref 0 (0.7, correct). All three queries have a match -> recall denominator 3.
    # t=0.7: q1, q2 above, 1 correct -> P=1/2, R=1/3
    # t=0.5: all 3 above, 1 correct  -> P=1/3, R=1/3
    idx, _ = best_match(S)
    assert idx.tolist() == [0, 1, 0]
    p, r, t = precision_recall_curve(S, gt)
    np.testing.assert_allclose(p, [1 / 2, 1 / 3])
    np.testing.assert_allclose(r, [1 / 3, 1 / 3])
    np.testing.assert_allclose(t, [0.7, 0.5])
    # AUC: anchor (0, 1/2) -> (1/3, 1/2): 1/6; then a zero-width segment.
    assert pr_auc(S, gt) == pytest.approx(1 / 6)
    # No threshold reaches precision 1.
    assert recall_at_100_precision(S, gt) == 0.0
    # EP: the top threshold (0.7) keeps two tied predictions, one right: P_R0 = 1/2 -> 1/4.
    assert extended_precision(S, gt) == pytest.approx(1 / 4)
    # k=2: the tie partner (ref 1 for q0, ref 2 for q1) is second in the tie order -> all hit.
    assert recall_at_k(S, gt, 1) == pytest.approx(1 / 3)
    assert recall_at_k(S, gt, 2) == pytest.approx(1.0)


def test_hand_worked_trapezoid():
    S = np.array([[0.9, 0.0, 0.0], [0.8, 0.1, 0.0], [0.0, 0.0, 0.7]])
    gt = np.eye(3, dtype=bool)
    # q0 -> 0 (0.9, correct), q1 -> 0 (0.8, wrong), q2 -> 2 (0.7, correct); denominator 3.
    # Points (R, P): (1/3, 1), (1/3, 1/2), (2/3, 2/3).
    # AUC = anchor (0,1)->(1/3,1): 1/3, + 0, + (1/3) * (1/2 + 2/3) / 2 = 7/36 -> 19/36.
    p, r, _ = precision_recall_curve(S, gt)
    np.testing.assert_allclose(p, [1, 1 / 2, 2 / 3])
    np.testing.assert_allclose(r, [1 / 3, 1 / 3, 2 / 3])
    assert pr_auc(S, gt) == pytest.approx(19 / 36)
    assert recall_at_100_precision(S, gt) == pytest.approx(1 / 3)
    # EP = (1 + 1/3) / 2: the later recovery to P = 2/3 does not count.
    assert extended_precision(S, gt) == pytest.approx(2 / 3)
    # q1's true ref 1 (0.1) ranks second behind 0.8.
    assert recall_at_k(S, gt, 2) == pytest.approx(1.0)


def test_recall_is_per_query_not_per_reference_entry():
    # 2 queries x 5 references with a wide tolerance for q0 (4 acceptable references).
    S = np.array([[0.1, 0.9, 0.2, 0.3, 0.0], [0.8, 0.1, 0.1, 0.1, 0.2]])
    gt = np.array([[T, T, T, T, F], [F, F, F, F, T]])
    # q0 -> ref 1 (correct), q1 -> ref 0 (wrong). Per query: recall = 1/2. The per-database-entry
    # count (1 correct out of 5 True entries = 0.2) or "fraction of True entries retrieved" would
    # be wrong.
    _, r, _ = precision_recall_curve(S, gt)
    assert r[-1] == pytest.approx(0.5)
    assert recall_at_k(S, gt, 1) == pytest.approx(0.5)
    # q1's only true ref (0.2) ranks second; q0 already hit -> 1, not e.g. 2/5 of entries.
    assert recall_at_k(S, gt, 2) == pytest.approx(1.0)
    assert evaluate(S, gt, ks=(1, 2))["n_query_with_match"] == 2


# --------------------------------------------------------------------------------------------
# comparison with the loop reference on random cases
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_curve_matches_loop_reference(shape, ties, seed):
    S, gt = random_case(shape, seed, ties)
    p, r, t = precision_recall_curve(S, gt)
    p_ref, r_ref, t_ref = loop_curve(S, gt)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(t, t_ref)
    assert pr_auc(S, gt) == pytest.approx(loop_auc(S, gt), abs=1e-12)
    assert recall_at_100_precision(S, gt) == pytest.approx(
        loop_recall_at_100_precision(S, gt), abs=1e-12
    )
    assert extended_precision(S, gt) == pytest.approx(loop_extended_precision(S, gt), abs=1e-12)
    idx, conf = best_match(S)
    preds_ref, confs_ref = loop_best_match(S)
    assert idx.dtype == np.int64 and idx.shape == (shape[0],)
    assert idx.tolist() == preds_ref
    assert conf.tolist() == confs_ref


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_recall_at_k_matches_loop_reference(shape, ties, seed):
    S, gt = random_case(shape, seed, ties)
    n_ref = shape[1]
    for k in sorted({1, 2, 3, 5, n_ref, n_ref + 3}):
        expected = loop_recall_at_k(S, gt, min(k, n_ref))
        assert recall_at_k(S, gt, k) == pytest.approx(expected, abs=1e-12), k


def test_recall_at_k_block_boundaries(monkeypatch):
    # Force tiny row blocks so the blocked pass is exercised across several blocks.
    import flyvpr.metrics as metrics

    monkeypatch.setattr(metrics, "_BLOCK_ELEMENTS", 7)
    S, gt = random_case((23, 5), seed=3, ties=True)
    for k in (1, 2, 4):
        assert recall_at_k(S, gt, k) == pytest.approx(loop_recall_at_k(S, gt, k), abs=1e-12)


# --------------------------------------------------------------------------------------------
# properties
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(1, 1), (5, 12), (12, 5), (30, 30)])
def test_perfect_scores(shape):
    rng = np.random.default_rng(7)
    n_query, n_ref = shape
    S = rng.random(shape)
    gt = rng.random(shape) < 0.2
    true_ref = rng.integers(0, n_ref, size=n_query)
    gt[np.arange(n_query), true_ref] = True  # every query has a match
    S[np.arange(n_query), true_ref] = 2.0  # ... and it is the argmax
    assert pr_auc(S, gt) == pytest.approx(1.0)
    assert recall_at_k(S, gt, 1) == 1.0
    assert recall_at_100_precision(S, gt) == 1.0
    assert extended_precision(S, gt) == 1.0


@pytest.mark.parametrize("shape", [(9, 4), (4, 9), (40, 40)])
@pytest.mark.parametrize("ties", [False, True])
def test_curve_properties(shape, ties):
    S, gt = random_case(shape, seed=11, ties=ties)
    p, r, t = precision_recall_curve(S, gt)
    assert p.shape == r.shape == t.shape
    assert np.all(np.diff(t) < 0)  # distinct, decreasing
    assert np.all(np.diff(r) >= 0)  # recall non-decreasing
    assert np.all((p >= 0) & (p <= 1)) and np.all((r >= 0) & (r <= 1))
    assert len(t) == len(np.unique(best_match(S)[1]))
    assert r[-1] == pytest.approx(recall_at_k(S, gt, 1))
    assert 0.0 <= pr_auc(S, gt) <= 1.0
    ep = extended_precision(S, gt)
    assert 0.0 <= ep <= 1.0
    assert (ep >= 0.5) == (p[0] == 1.0)  # EP >= 1/2 exactly when the top threshold is all right
    # A strictly increasing map of the scores keeps every prediction and the order: same EP.
    assert extended_precision(np.tanh(S / 4) * 3 + 1, gt) == ep
    # recall@k is non-decreasing in k and reaches 1 at k = n_reference.
    values = [recall_at_k(S, gt, k) for k in range(1, shape[1] + 1)]
    assert values == sorted(values) and values[-1] == 1.0


def test_inputs_not_modified_and_dtypes():
    S, gt = random_case((10, 6), seed=5, ties=True)
    S_copy, gt_copy = S.copy(), gt.copy()
    evaluate(S, gt)
    np.testing.assert_array_equal(S, S_copy)
    np.testing.assert_array_equal(gt, gt_copy)
    # float32 and integer scores, 0/1 integer ground truth give the same numbers.
    base = evaluate(S, gt)
    assert evaluate(S.astype(np.float32), gt.astype(np.int64)) == base
    assert evaluate(S.astype(np.int32), gt.astype(np.uint8)) == base
    assert evaluate(S.tolist(), gt.tolist()) == base


def test_hand_worked_extended_precision_first_prediction_wrong():
    S = np.array([[0.1, 0.9, 0.0], [0.0, 0.8, 0.1], [0.0, 0.1, 0.7]])
    gt = np.eye(3, dtype=bool)
    # q0 -> 1 (0.9, wrong), q1 -> 1 (0.8, correct), q2 -> 2 (0.7, correct); denominator 3.
    # Points (R, P): (0, 0), (1/3, 1/2), (2/3, 2/3). The lowest recall is 0, with P = 0, and
    # no threshold has P = 1: EP = 0, although two of three predictions are right.
    p, r, _ = precision_recall_curve(S, gt)
    np.testing.assert_allclose(p, [0, 1 / 2, 2 / 3])
    np.testing.assert_allclose(r, [0, 1 / 3, 2 / 3])
    assert extended_precision(S, gt) == 0.0
    # Make the right prediction the most confident one: P_R0 = 1, R@100P = 1/3 -> 2/3.
    S[1, 1] = 0.95
    assert extended_precision(S, gt) == pytest.approx(2 / 3)


def test_hand_worked_extended_precision_perfect_and_all_wrong():
    S = np.array([[0.9, 0.1, 0.0], [0.0, 0.8, 0.1], [0.0, 0.1, 0.7]])
    assert extended_precision(S, np.eye(3, dtype=bool)) == 1.0
    assert extended_precision(S, np.roll(np.eye(3, dtype=bool), 1, axis=1)) == 0.0


def test_huge_finite_scores_are_accepted():
    # Their sum overflows to inf, which must not be mistaken for a non-finite entry.
    S = np.array([[1e308, 1e308], [1e308, -1e308]])
    gt = np.array([[T, F], [F, T]])
    assert recall_at_k(S, gt, 1) == 0.5


# --------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------
def test_evaluate_contents_and_json():
    S, gt = random_case((12, 7), seed=4, ties=True)
    out = evaluate(S, gt)
    text = json.dumps(out)
    assert json.loads(text) == out
    assert set(out) == {
        "auc",
        "recall_at_1",
        "recall_at_5",
        "recall_at_10",
        "recall_at_100_precision",
        "extended_precision",
        "precision",
        "recall",
        "thresholds",
        "n_query",
        "n_reference",
        "n_query_with_match",
    }
    assert out["auc"] == pytest.approx(pr_auc(S, gt))
    assert out["recall_at_5"] == pytest.approx(recall_at_k(S, gt, 5))
    assert out["recall_at_10"] == pytest.approx(recall_at_k(S, gt, 10))  # clamped to 7
    assert out["recall_at_100_precision"] == pytest.approx(recall_at_100_precision(S, gt))
    assert out["extended_precision"] == pytest.approx(extended_precision(S, gt))
    p, r, t = precision_recall_curve(S, gt)
    assert out["precision"] == p.tolist() and out["recall"] == r.tolist()
    assert out["thresholds"] == t.tolist()
    assert (out["n_query"], out["n_reference"]) == (12, 7)
    assert out["n_query_with_match"] == int(gt.any(axis=1).sum())
    for key in ("auc", "recall_at_1", "recall_at_100_precision", "extended_precision"):
        assert type(out[key]) is float
    assert all(type(v) is float for v in out["thresholds"] + out["precision"])
    assert type(out["n_query"]) is int


def test_evaluate_custom_ks_float32_json():
    S, gt = random_case((8, 20), seed=6, ties=False)
    out = evaluate(S.astype(np.float32), gt, ks=(2, 3))
    assert "recall_at_2" in out and "recall_at_3" in out and "recall_at_1" not in out
    json.dumps(out)
    assert all(math.isfinite(v) for v in out["thresholds"])


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------
GOOD_S = np.array([[0.9, 0.1, 0.0], [0.3, 0.2, 0.6], [0.5, 0.4, 0.1]])
GOOD_GT = np.eye(3, dtype=bool)

ALL_WITH_GT = [
    precision_recall_curve,
    pr_auc,
    recall_at_100_precision,
    extended_precision,
    evaluate,
    lambda S, gt: recall_at_k(S, gt, 1),
]


@pytest.mark.parametrize("func", ALL_WITH_GT)
@pytest.mark.parametrize(
    "S, gt, error, match",
    [
        (GOOD_S[0], GOOD_GT[0], ValueError, r"S must have shape \(n_query, n_reference\)"),
        (np.zeros((0, 3)), np.zeros((0, 3), bool), ValueError, "S is empty"),
        (np.where(GOOD_GT, np.nan, GOOD_S), GOOD_GT, ValueError, "S contains NaN"),
        (np.where(GOOD_GT, np.inf, GOOD_S), GOOD_GT, ValueError, "S contains NaN or infinite"),
        (np.array([["a", "b"]]), np.array([[T, F]]), TypeError, "S must be a numeric array"),
        (GOOD_S, GOOD_GT[:, :2], ValueError, r"gt must have shape \(3, 3\); got \(3, 2\)"),
        (GOOD_S, GOOD_GT.T[None], ValueError, r"gt must have shape \(3, 3\); got \(1, 3, 3\)"),
        (GOOD_S, GOOD_GT.astype(float), TypeError, "gt must be a boolean array"),
        (GOOD_S, 2 * GOOD_GT.astype(int), ValueError, "gt must be boolean .*other than 0 and 1"),
        (GOOD_S, np.zeros((3, 3), bool), ValueError, "gt has no true match"),
    ],
)
def test_errors(func, S, gt, error, match):
    with pytest.raises(error, match=match):
        func(S, gt)


@pytest.mark.parametrize(
    "S, error, match",
    [
        (np.ones(3), ValueError, "S must have shape"),
        (np.ones((2, 0)), ValueError, "S is empty"),
        (np.array([[1.0, np.nan]]), ValueError, "S contains NaN"),
        (np.array([[1 + 1j]]), TypeError, "S must hold real scores"),
    ],
)
def test_best_match_errors(S, error, match):
    with pytest.raises(error, match=match):
        best_match(S)


@pytest.mark.parametrize(
    "k, error, match",
    [
        (0, ValueError, "k must be >= 1; got 0"),
        (-2, ValueError, "k must be >= 1"),
        (1.0, TypeError, "k must be an int; got float"),
        (True, TypeError, "k must be an int; got bool"),
        ("1", TypeError, "k must be an int; got str"),
    ],
)
def test_recall_at_k_bad_k(k, error, match):
    with pytest.raises(error, match=match):
        recall_at_k(GOOD_S, GOOD_GT, k)


def test_recall_at_k_accepts_numpy_int():
    assert recall_at_k(GOOD_S, GOOD_GT, np.int64(3)) == 1.0


@pytest.mark.parametrize(
    "ks, error, match",
    [
        (5, TypeError, "ks must be an iterable of ints"),
        ((1, 0), ValueError, "ks must be an iterable of ints >= 1; k must be >= 1"),
        ((1, 2.5), TypeError, "ks must be an iterable of ints >= 1; k must be an int"),
    ],
)
def test_evaluate_bad_ks(ks, error, match):
    with pytest.raises(error, match=match):
        evaluate(GOOD_S, GOOD_GT, ks=ks)


def test_reliability_by_hand():
    from flyvpr.metrics import reliability, reliability_counts

    conf = np.array([0.05, 0.15, 0.15, 0.95, 1.0, 0.0])
    right = np.array([False, True, False, True, True, True])
    rows = reliability(conf, right)
    assert [r["bin"] for r in rows] == ["0.0-0.1", "0.1-0.2", "0.9-1.0"]
    assert [r["n"] for r in rows] == [2, 2, 2]  # 0 and 0.05 share the first; 1.0 the last
    assert rows[0]["confidence"] == pytest.approx(0.025) and rows[0]["right"] == 0.5
    assert rows[1]["confidence"] == pytest.approx(0.15) and rows[1]["right"] == 0.5
    assert rows[2]["confidence"] == pytest.approx(0.975) and rows[2]["right"] == 1.0
    n, total, hits = reliability_counts(conf, right.astype(int), bins=4)
    assert n.tolist() == [4, 0, 0, 2] and hits.tolist() == [2, 0, 0, 2]
    np.testing.assert_allclose(total, [0.35, 0.0, 0.0, 1.95])
    assert [r["bin"] for r in reliability(conf, right, bins=20)][:2] == ["0.00-0.05", "0.05-0.10"]
    assert reliability([], []) == []


def test_reliability_bins_hold_their_lower_edge_and_name_their_edges():
    from flyvpr.metrics import reliability, reliability_counts

    # 0.29 * 100 is 28.999...: each confidence on an edge still opens its own bin
    edges = [0.29, 0.57, 0.58, 0.99, 0.01]
    n, _, _ = reliability_counts(edges, [True] * 5, bins=100)
    assert np.flatnonzero(n).tolist() == [1, 29, 57, 58, 99]
    n, _, _ = reliability_counts([0.3, 0.7, 0.6, 1 / 3], [True] * 4, bins=10)
    assert n.tolist() == [0, 0, 0, 2, 0, 0, 1, 1, 0, 0]
    # edges that one decimal cannot write get three
    bins3 = [r["bin"] for r in reliability([0.1, 0.5, 0.9], [True] * 3, bins=3)]
    assert bins3 == ["0.000-0.333", "0.333-0.667", "0.667-1.000"]
    assert [r["bin"] for r in reliability([0.0, 0.99], [1, 1], bins=8)] == [
        "0.000-0.125",
        "0.875-1.000",
    ]
    assert [r["bin"] for r in reliability([0.5], [1], bins=2)] == ["0.5-1.0"]
    # sixteenths need four decimals, not three (0.062 would not be the edge 0.0625)
    assert [r["bin"] for r in reliability([0.07, 0.99], [1, 1], bins=16)] == [
        "0.0625-0.1250",
        "0.9375-1.0000",
    ]


@pytest.mark.parametrize(
    "confidence, right, bins, error, match",
    [
        (
            [0.5, 1.2],
            [True, False],
            10,
            ValueError,
            r"confidence must be finite and lie in \[0, 1\]",
        ),
        ([-0.1], [True], 10, ValueError, r"confidence must be finite and lie in \[0, 1\]"),
        ([np.nan], [True], 10, ValueError, r"confidence must be finite and lie in \[0, 1\]"),
        ([0.5, 0.6], [True], 10, ValueError, "one label per confidence: 2; got 1"),
        ([0.5], [2], 10, ValueError, r"right must be boolean \(or integers 0/1\)"),
        ([0.5], [1.0], 10, TypeError, r"right must be a boolean array .* got dtype float64$"),
        ([0.5], [True], 0, ValueError, "^bins must be >= 1; got 0$"),
        ([0.5], [True], 2.5, TypeError, "^bins must be an int; got float$"),
        (["x"], [True], 10, TypeError, "^confidence must be numbers; got dtype <U1$"),
    ],
)
def test_reliability_refuses(confidence, right, bins, error, match):
    from flyvpr.metrics import reliability

    with pytest.raises(error, match=match):
        reliability(confidence, right, bins)


def test_evaluate_answers_refuses_confidences_that_are_not_numbers():
    from flyvpr.metrics import evaluate_answers

    with pytest.raises(TypeError, match="^confidence must be numbers; got dtype <U1$"):
        evaluate_answers(["x"], [True], [True])
    with pytest.raises(TypeError, match="^confidence must be an array of numbers"):
        evaluate_answers([[0.5], [0.5, 0.6]], [True, True], [True, True])


def test_evaluate_answers_takes_flags_as_every_metric_does():
    # 0/1 integers as booleans (as gt and the reliability counts take them); other values or
    # dtypes refused, naming the parameter
    from flyvpr.metrics import evaluate_answers

    flags = evaluate_answers([0.9, 0.8, 0.3], [True, False, True], [True, True, True])
    ints = evaluate_answers([0.9, 0.8, 0.3], np.array([1, 0, 1]), [1, 1, 1])
    assert ints == flags
    with pytest.raises(ValueError, match="correct must be boolean .* other than 0 and 1"):
        evaluate_answers([0.9, 0.8], [2, 0], [True, True])
    with pytest.raises(TypeError, match="has_match must be a boolean array .* got dtype float64"):
        evaluate_answers([0.9, 0.8], [True, False], [1.0, 1.0])
