"""fit_calibration: the CANN's confidence table fitted on a labelled run."""

from __future__ import annotations

import numpy as np
import pytest

from flyvpr.temporal.cann import CANN, fit_calibration
from flyvpr.temporal.cann._calibration import KNOTS, MIN_STEP, _pool_adjacent_violators


def _check_table(table):
    t = np.asarray(table)
    assert t.shape == (11,)
    assert t.min() >= 0.0 and t.max() <= 1.0
    assert (np.diff(t) >= MIN_STEP - 1e-12).all()
    CANN(calibration=table).reset()  # the filter takes it


def test_answers_on_the_knots_give_their_share_right():
    # 1,000 answers at each knot, right at the share s(k): the table is s (a tiny prior pull)
    share = np.array([0.1, 0.15, 0.3, 0.32, 0.5, 0.55, 0.6, 0.8, 0.85, 0.9, 0.97])
    raw = np.repeat(KNOTS, 1000)
    right = np.concatenate([np.arange(1000) < round(1000 * s) for s in share])
    table = fit_calibration(raw, right)
    _check_table(table)
    # the prior (weight 1 of 1,001 at each knot) pulls each value towards the knot
    expected = (1000 * share + KNOTS) / 1001
    np.testing.assert_allclose(table, expected, atol=1e-9)
    np.testing.assert_allclose(fit_calibration(raw, right, prior_weight=0.0), share, atol=1e-9)


def test_answers_between_knots_weigh_on_both_linearly():
    # every answer at 0.25 (a quarter of the way from 0.2 to 0.3), right 40% of the time: the
    # interpolated table at 0.25 is 0.4 (no prior)
    raw = np.full(1000, 0.25)
    right = np.arange(1000) < 400
    rng = np.random.default_rng(1)
    other = rng.uniform(size=4000)  # and answers elsewhere, right at 0.2 + 0.6 r
    raw = np.concatenate([raw, other])
    right = np.concatenate([right, rng.uniform(size=other.size) < 0.2 + 0.6 * other])
    table = fit_calibration(raw, right, prior_weight=0.0)
    _check_table(table)
    assert np.interp(0.25, KNOTS, table) == pytest.approx(0.4, abs=0.03)
    assert table[0] == pytest.approx(0.2, abs=0.06)
    assert table[-1] == pytest.approx(0.8, abs=0.06)
    assert table[5] == pytest.approx(0.5, abs=0.05)


def test_smooth_truth_recovered_and_the_docstring_example():
    rng = np.random.default_rng(0)
    raw = rng.uniform(size=20000)
    right = rng.uniform(size=raw.size) < 0.2 + 0.7 * raw
    table = fit_calibration(raw, right)
    _check_table(table)
    np.testing.assert_allclose(table, 0.2 + 0.7 * KNOTS, atol=0.03)


def test_knots_without_answers_stay_at_the_raw_confidence():
    # answers only near 0.5, all right: the knots far away keep the identity
    raw = np.full(50, 0.5)
    table = fit_calibration(raw, np.ones(50, bool))
    _check_table(table)
    np.testing.assert_allclose(table[:4], KNOTS[:4], atol=1e-9)
    # 0.5 itself: (50 * 1 + 1 * 0.5) / 51 (weight 51), then pooled with the knots 0.6-0.9
    # (weight 1 each) that fall below it; 1.0 stays
    pooled = (50 + 0.5 + 0.6 + 0.7 + 0.8 + 0.9) / 55
    np.testing.assert_allclose(table[5:10], pooled + MIN_STEP * np.arange(5), atol=1e-9)
    assert table[10] == 1.0
    # a larger prior weight pulls it further towards 0.5
    assert fit_calibration(raw, np.ones(50, bool), prior_weight=50.0)[5] < 0.8


def test_out_of_order_shares_are_pooled():
    # right more often at 0.3 than at 0.4: pooled into their weighted mean
    raw = np.repeat([0.3, 0.4], [100, 300])
    right = np.concatenate([np.arange(100) < 80, np.arange(300) < 120])
    table = fit_calibration(raw, right, prior_weight=0.0)
    _check_table(table)
    pooled = (80 + 120) / 400
    assert table[3] == pytest.approx(pooled, abs=1e-9)
    assert table[4] == pytest.approx(pooled + MIN_STEP, abs=1e-9)


def test_a_table_at_the_bounds_stays_strict_within_0_1():
    raw = np.concatenate([np.zeros(100), np.ones(100)])
    never = fit_calibration(raw, np.zeros(200, bool), prior_weight=0.0)
    _check_table(never)
    assert never[0] == 0.0
    always = fit_calibration(raw, np.ones(200, bool), prior_weight=0.0)
    _check_table(always)
    assert always[-1] == 1.0
    # The documented least step, 0.001 (the table's values step down from 1 by it).
    assert always[-2] == pytest.approx(0.999, abs=1e-12)
    assert always[0] == pytest.approx(0.99, abs=1e-12)


def _isotonic_reference(values, weights):
    """Pooling from scratch until no neighbours are out of order (slow and plain)."""
    blocks = [[v, w, 1] for v, w in zip(values, weights, strict=True)]
    while True:
        for i in range(len(blocks) - 1):
            if blocks[i][0] > blocks[i + 1][0]:
                (v1, w1, c1), (v2, w2, c2) = blocks[i], blocks[i + 1]
                blocks[i : i + 2] = [[(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, c1 + c2]]
                break
        else:
            return np.repeat([b[0] for b in blocks], [b[2] for b in blocks])


def test_pool_adjacent_violators_against_a_plain_reference():
    rng = np.random.default_rng(7)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        values = rng.normal(size=n).round(1)
        weights = rng.uniform(0.1, 5.0, size=n)
        np.testing.assert_allclose(
            _pool_adjacent_violators(values, weights), _isotonic_reference(values, weights)
        )


def test_negative_least_squares_values_are_raised_to_0():
    # answers at 0.1 all right, at 0.05 all wrong: the fit at 0 is -1 (0.5 c0 + 0.5 c1 = 0
    # with c1 = 1), in order, so only the floor at 0 holds it
    raw = np.repeat([0.05, 0.1], 100)
    right = np.repeat([False, True], 100)
    table = fit_calibration(raw, right, prior_weight=0.0)
    _check_table(table)
    assert table[0] == 0.0
    assert table[1] == pytest.approx(1.0 - 9 * MIN_STEP)


def test_pool_adjacent_violators_by_hand():
    out = _pool_adjacent_violators(np.array([1.0, 3.0, 2.0, 0.0, 5.0]), np.array([1, 1, 1, 2, 1.0]))
    # 3 and 2 pool to 2.5; then 2.5 (weight 2) and 0 (weight 2) pool to 1.25; then 1 and 1.25
    # are in order
    np.testing.assert_allclose(out, [1.0, 1.25, 1.25, 1.25, 5.0])
    np.testing.assert_allclose(_pool_adjacent_violators(np.array([0.0, 1.0]), np.ones(2)), [0, 1])
    # a later violation reaching back over an earlier pool
    out = _pool_adjacent_violators(np.array([2.0, 1.0, 0.0]), np.array([1.0, 1.0, 4.0]))
    np.testing.assert_allclose(out, [0.5, 0.5, 0.5])


def test_a_fitted_table_calibrates_the_filter_on_its_run():
    # raw confidences of a filter on a synthetic route where the front end is weak: the fitted
    # table makes each answer's confidence the share right at its raw confidence
    rng = np.random.default_rng(3)
    n, frames = 300, 400
    truth = (20 + np.arange(frames)) % n
    S = rng.normal(size=(frames, n))
    S[np.arange(frames), truth] += 1.2
    filt = CANN(calibration=None)
    raw, right = [], []
    for t in range(frames):
        row = filt.step(S[t])
        if filt.source_ == "sequence":
            raw.append(filt.confidence_)
            right.append(abs(int(row.argmax()) - truth[t]) <= filt.tolerance)
    table = fit_calibration(raw, right)
    _check_table(table)
    calibrated = np.interp(raw, KNOTS, table)
    assert abs(calibrated.mean() - np.mean(right)) < 0.05


@pytest.mark.parametrize(
    "raw, right, kw, match",
    [
        ([], [], {}, "non-empty 1-d"),
        ([[0.5]], [[True]], {}, "non-empty 1-d"),
        ([0.5, 0.6], [True], {}, "one label per raw confidence"),
        ([0.5, np.nan], [True, False], {}, r"^raw confidences must be finite and lie in \[0, 1\]$"),
        ([0.5, 1.5], [True, False], {}, r"^raw confidences must be finite and lie in \[0, 1\]$"),
        ([-0.1, 0.5], [True, False], {}, r"^raw confidences must be finite and lie in \[0, 1\]$"),
        (
            [0.5, 0.6],
            [1, 2],
            {},
            r"^right must hold booleans \(or 0 and 1\): whether each answer was right$",
        ),
        ([0.5, 0.6], ["yes", "no"], {}, "^right must hold booleans"),
        ([0.5, 0.6], [0.5, 1.0], {}, "^right must hold booleans"),
        ([0.5, 0.6], [True, False], {"prior_weight": -1.0}, "prior_weight"),
        ([0.5, 0.6], [True, False], {"prior_weight": float("nan")}, "prior_weight"),
    ],
)
def test_bad_input_is_refused(raw, right, kw, match):
    with pytest.raises(ValueError, match=match):
        fit_calibration(raw, right, **kw)


def test_labels_as_0_and_1_equal_booleans():
    raw = [0.1, 0.5, 0.9, 0.95]
    assert fit_calibration(raw, [0, 1, 1, 0]) == fit_calibration(raw, [False, True, True, False])
    assert fit_calibration([0.0, 1.0], [0, 1], prior_weight=0.0)[0] == 0.0


@pytest.mark.parametrize(
    "raw, kw, match",
    [
        ([0.5, 0.6], {"prior_weight": "1"}, "^prior_weight must be a number; got str$"),
        ([0.5, 0.6], {"prior_weight": None}, "^prior_weight must be a number; got NoneType$"),
        ([0.5, 0.6], {"prior_weight": True}, "^prior_weight must be a number; got bool$"),
        (["a", "b"], {}, "^raw must be numbers; got dtype <U1$"),
        ([object(), 0.5], {}, "^raw must be numbers; got dtype object$"),
    ],
)
def test_input_of_the_wrong_type_is_refused_by_name(raw, kw, match):
    with pytest.raises(TypeError, match=match):
        fit_calibration(raw, [True, False], **kw)
