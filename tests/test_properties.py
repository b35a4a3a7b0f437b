"""Property tests (hypothesis): metrics' range, invariance and agreement with a direct
computation; online filters' causality."""

import importlib.util

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from flyvpr import metrics
from flyvpr.temporal import FILTERS
from flyvpr.temporal.base import OnlineFilter

SETTINGS = settings(max_examples=60, deadline=None)


@st.composite
def problems(draw, max_q=9, max_r=9):
    """An integer-valued score matrix (ties are common) and a ground truth with a True."""
    n_q = draw(st.integers(1, max_q))
    n_r = draw(st.integers(1, max_r))
    S = draw(hnp.arrays(np.float64, (n_q, n_r), elements=st.integers(-4, 4).map(float)))
    gt = draw(hnp.arrays(np.bool_, (n_q, n_r)))
    assume(gt.any())
    return S, gt


def _direct(S, gt):
    """Precision-recall by the definitions, one threshold and one query at a time."""
    n_q = S.shape[0]
    pred = [int(np.argmax(S[q])) for q in range(n_q)]  # first maximum: lowest index
    conf = [S[q, pred[q]] for q in range(n_q)]
    correct = [bool(gt[q, pred[q]]) for q in range(n_q)]
    n_pos = sum(bool(gt[q].any()) for q in range(n_q))
    precision, recall = [], []
    for t in sorted(set(conf), reverse=True):
        above = [q for q in range(n_q) if conf[q] >= t]
        tp = sum(correct[q] for q in above)
        precision.append(tp / len(above))
        recall.append(tp / n_pos)
    auc, r0, p0 = 0.0, 0.0, precision[0]
    for p, r in zip(precision, recall, strict=True):
        auc += (r - r0) * (p + p0) / 2
        r0, p0 = r, p
    perfect = [r for p, r in zip(precision, recall, strict=True) if p == 1.0]
    return auc, max(perfect) if perfect else 0.0


def _direct_recall_at_k(S, gt, k):
    hits = n_pos = 0
    for q in range(S.shape[0]):
        if not gt[q].any():
            continue
        n_pos += 1
        order = sorted(range(S.shape[1]), key=lambda j: (-S[q, j], j))
        hits += any(gt[q, j] for j in order[:k])
    return hits / n_pos


@SETTINGS
@given(problems())
def test_metrics_range_and_order(problem):
    S, gt = problem
    out = metrics.evaluate(S, gt, ks=(1, 2, 3, 5))
    assert 0.0 <= out["auc"] <= 1.0
    ks = [out[f"recall_at_{k}"] for k in (1, 2, 3, 5)]
    assert all(0.0 <= r <= 1.0 for r in ks) and ks == sorted(ks)
    assert 0.0 <= out["recall_at_100_precision"] <= out["recall_at_1"]


@SETTINGS
@given(problems(), st.sampled_from(["affine", "exp", "cube"]))
def test_metrics_invariant_under_increasing_maps(problem, name):
    S, gt = problem
    f = {"affine": lambda x: 3 * x + 2, "exp": lambda x: np.exp(x / 7), "cube": lambda x: x**3}
    a = metrics.evaluate(S, gt)
    b = metrics.evaluate(f[name](S), gt)
    for key in ("auc", "recall_at_1", "recall_at_5", "recall_at_10", "recall_at_100_precision"):
        assert a[key] == b[key], key


@SETTINGS
@given(problems(), st.integers(1, 10))
def test_metrics_agree_with_direct_computation(problem, k):
    S, gt = problem
    auc, r100 = _direct(S, gt)
    assert metrics.pr_auc(S, gt) == pytest.approx(auc, abs=1e-12)
    assert metrics.recall_at_100_precision(S, gt) == pytest.approx(r100, abs=1e-12)
    assert metrics.recall_at_k(S, gt, k) == pytest.approx(_direct_recall_at_k(S, gt, k))


# -- causality of the online filters --------------------------------------------------------
CAUSAL = [
    name
    for name, cls in FILTERS.items()
    if issubclass(cls, OnlineFilter) and not getattr(cls, "needs_reference_scores", False)
]


@pytest.mark.parametrize("name", CAUSAL)
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_online_filter_output_never_depends_on_later_frames(name, data):
    n_q = data.draw(st.integers(2, 25), label="n_query")
    n_r = data.draw(st.integers(2, 15), label="n_reference")
    seed = data.draw(st.integers(0, 2**32 - 1), label="seed")
    t = data.draw(st.integers(0, n_q - 2), label="t")
    rng = np.random.default_rng(seed)
    S = rng.random((n_q, n_r))
    later = S.copy()
    later[t + 1 :] = rng.random((n_q - t - 1, n_r)) * rng.choice([1e-3, 1.0, 1e3])
    filt = FILTERS[name]()
    np.testing.assert_array_equal(filt.filter(S)[: t + 1], filt.filter(later)[: t + 1])


@pytest.mark.skipif(importlib.util.find_spec("torch") is None, reason="needs torch")
def test_trained_online_filters_are_causal_too():
    trained = [
        n
        for n, cls in FILTERS.items()
        if issubclass(cls, OnlineFilter) and getattr(cls, "needs_reference_scores", False)
    ]
    rng = np.random.default_rng(0)
    ref_scores = rng.random((12, 12)) + 3 * np.eye(12)
    for name in trained:
        filt = FILTERS[name]()
        params = filt.get_params()
        small = {k: v for k, v in {"epochs": 1, "hidden_size": 8}.items() if k in params}
        filt.set_params(random_state=0, **small).fit(ref_scores)
        S = rng.random((10, 12))
        later = S.copy()
        later[5:] = rng.random((5, 12))
        np.testing.assert_allclose(filt.filter(S)[:5], filt.filter(later)[:5], rtol=0, atol=0)
