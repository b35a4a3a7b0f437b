"""The same checks over every registered encoder and temporal filter."""

import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends import FRONTENDS
from flyvpr.temporal import FILTERS, OnlineFilter

#: small, fast settings for parts whose defaults train for long
FAST = {
    "flynet": {"epochs": 5},
    "fc": {"epochs": 5},
    "fc-dropout": {"epochs": 5},
    "cnn": {"epochs": 3},
    "netvlad": {"epochs": 3},
    "rnn": {"epochs": 2, "hidden_size": 16},
}


def _needs(cls):
    for mod in getattr(cls, "requires", ()):
        pytest.importorskip(mod)


def _make(registry, name, **extra):
    cls = registry[name]
    _needs(cls)
    obj = cls()
    params = {k: v for k, v in FAST.get(name, {}).items() if k in obj.get_params()}
    obj.set_params(**params, **extra)
    if "random_state" in obj.get_params():
        obj.set_params(random_state=0)
    return obj


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(7)
    ref = rng.random((12, 32, 64), dtype=np.float32)
    qry = np.clip(ref[:9] + rng.normal(0, 0.05, (9, 32, 64)).astype(np.float32), 0, 1)
    return ref, qry


@pytest.mark.parametrize("name", sorted(FRONTENDS))
def test_encoder_contract(name, images):
    ref, qry = images
    enc = _make(FRONTENDS, name)
    assert enc.name == name
    with pytest.raises(NotFittedError):
        enc.score(qry)
    params_before = enc.get_params()
    assert enc.fit(ref) is enc
    assert enc.get_params() == params_before  # fit does not change constructor parameters
    S = enc.score(qry)
    assert S.shape == (9, 12) and np.isfinite(S).all()
    codes = enc.encode(qry)
    np.testing.assert_array_equal(enc.score_codes(codes), S)
    with pytest.raises(ValueError, match="image size|shape"):
        enc.score(np.zeros((2, 16, 32), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        enc.score(np.full((2, 32, 64), np.nan, np.float32))
    fp = enc.footprint()
    assert {"layers", "params", "neurons"} <= set(fp)
    if "random_state" in params_before:
        again = _make(FRONTENDS, name).fit(ref).score(qry)
        np.testing.assert_allclose(again, S, rtol=1e-5, atol=1e-6)


def _scores(rng, n_q=30, n_r=25):
    S = rng.random((n_q, n_r)).astype(np.float32)
    idx = np.minimum(np.arange(n_q), n_r - 1)
    S[np.arange(n_q), idx] += 1.0
    return S


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_filter_contract(name):
    rng = np.random.default_rng(3)
    filt = _make(FILTERS, name)
    assert filt.name == name
    S = _scores(rng)
    if getattr(filt, "needs_reference_scores", False):
        filt.fit(_scores(rng, 25, 25))
    original = S.copy()
    out = filt.filter(S)
    assert out.shape == S.shape and np.isfinite(out).all()
    np.testing.assert_array_equal(S, original)  # input untouched
    with pytest.raises(ValueError, match="NaN"):
        filt.filter(np.where(S > 0.5, np.nan, S))
    with pytest.raises(ValueError, match="shape"):
        filt.filter(S[0])
    fp = filt.footprint(25)
    assert {"layers", "params", "neurons"} <= set(fp)
    if isinstance(filt, OnlineFilter) and getattr(filt, "mode", "causal") == "causal":
        filt.reset()
        rows = np.stack([filt.step(row) for row in S])
        np.testing.assert_allclose(rows, out, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", sorted(FILTERS))
def test_filter_is_deterministic(name):
    rng = np.random.default_rng(4)
    S = _scores(rng)
    outs = []
    for _ in range(2):
        filt = _make(FILTERS, name)
        if getattr(filt, "needs_reference_scores", False):
            filt.fit(_scores(np.random.default_rng(5), 25, 25))
        outs.append(filt.filter(S))
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-6)
