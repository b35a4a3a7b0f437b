"""Tests of the FlyNet+RNN temporal filter (flyvpr.temporal.rnn)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from flyvpr._validation import NotFittedError  # noqa: E402
from flyvpr.metrics import recall_at_k  # noqa: E402
from flyvpr.temporal.rnn import RNNFilter, _build_module  # noqa: E402

CELLS = ["rnn", "gru", "lstm"]


def _reference_scores(n, rng, width=1.5, noise=0.05):
    """Scores of a route's reference frames against its places: a bump on the diagonal."""
    i = np.arange(n)
    R = np.exp(-((i[:, None] - i[None, :]) ** 2) / (2 * width**2))
    return R + noise * rng.standard_normal((n, n))


def _small(**params):
    defaults = dict(hidden_size=16, sequence_length=8, epochs=2, batch_size=8, random_state=0)
    defaults.update(params)
    return RNNFilter(**defaults)


@pytest.fixture
def fitted(rng):
    return _small().fit(_reference_scores(12, rng))


def _params(filt):
    return {k: v.detach().clone() for k, v in filt.module_.state_dict().items()}


# ---------------------------------------------------------------------------------------------
# import and registry contract
# ---------------------------------------------------------------------------------------------
def test_import_does_not_load_torch():
    code = (
        "import sys, flyvpr, flyvpr.temporal.rnn\n"
        "assert 'torch' not in sys.modules, 'torch imported at module level'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_class_attributes():
    assert RNNFilter.name == "rnn"
    assert RNNFilter.requires == ("torch",)
    assert RNNFilter.needs_reference_scores is True


def test_missing_torch_names_the_extra(monkeypatch, rng):
    monkeypatch.setitem(sys.modules, "torch", None)  # makes `import torch` raise ImportError
    with pytest.raises(ImportError, match=r"pip install 'flyvpr\[torch\]'"):
        _small().fit(_reference_scores(6, rng))


def test_params_are_only_stored():
    filt = RNNFilter(hidden_size=7, cell="nonsense", noise=5.0)
    assert filt.get_params()["hidden_size"] == 7
    assert filt.get_params()["cell"] == "nonsense"  # checked at fit, as scikit-learn does
    assert not hasattr(filt, "module_")
    assert "RNNFilter(hidden_size=7" in repr(filt)


# ---------------------------------------------------------------------------------------------
# smoke, shapes, online equivalence
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cell", CELLS)
def test_smoke_shapes(cell, rng):
    n = 12
    filt = _small(cell=cell).fit(_reference_scores(n, rng))
    assert filt.n_reference_ == n
    assert filt.loss_history_.shape == (2,)
    S = rng.random((9, n))
    out = filt.filter(S)
    assert out.shape == (9, n)
    assert out.dtype == np.float64
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    np.testing.assert_allclose(out.sum(axis=1), 1.0, rtol=1e-5)
    assert filt.filter(S.astype(np.float32)).dtype == np.float32


@pytest.mark.parametrize("cell", CELLS)
def test_step_equals_filter(cell, rng):
    n = 10
    filt = _small(cell=cell).fit(_reference_scores(n, rng))
    S = rng.random((15, n))
    whole = filt.filter(S)
    filt.reset()
    rows = np.stack([filt.step(row) for row in S])
    np.testing.assert_allclose(rows, whole, rtol=1e-5, atol=1e-6)


def test_step_continues_after_filter(fitted, rng):
    S = rng.random((10, 12))
    whole = fitted.filter(S)
    fitted.filter(S[:6])  # leaves the hidden state after frame 5
    rest = np.stack([fitted.step(row) for row in S[6:]])
    np.testing.assert_allclose(rest, whole[6:], rtol=1e-5, atol=1e-6)


def test_reset_forgets_the_past(fitted, rng):
    S = rng.random((8, 12))
    first = np.stack([fitted.step(row) for row in S])
    more = np.stack([fitted.step(row) for row in S])
    assert not np.allclose(more, first)  # the state carried over
    fitted.reset()
    again = np.stack([fitted.step(row) for row in S])
    np.testing.assert_allclose(again, first, rtol=1e-6, atol=1e-7)
    # filter() always starts from a zero state, whatever was stepped before
    np.testing.assert_allclose(fitted.filter(S), first, rtol=1e-5, atol=1e-6)


def test_filter_does_not_modify_input(fitted, rng):
    S = rng.random((7, 12))
    copy = S.copy()
    fitted.filter(S)
    fitted.step(S[0])
    np.testing.assert_array_equal(S, copy)


def test_probability_rows_are_log_transformed(rng):
    logits = rng.standard_normal((10, 10)) * 3
    P = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    assert _small().fit(P).log_input_ is True
    assert _small().fit(_reference_scores(10, rng)).log_input_ is False


# ---------------------------------------------------------------------------------------------
# learning
# ---------------------------------------------------------------------------------------------
def test_learns_a_diagonal_route(rng):
    """Trained on reference rows only, it integrates noisy query rows along the route."""
    n = 60
    R = _reference_scores(n, rng, noise=0.02)
    filt = RNNFilter(
        hidden_size=64,
        sequence_length=20,
        epochs=60,
        batch_size=32,
        learning_rate=0.003,
        speed_range=1.0,
        noise=(0.5, 0.85),
        random_state=1,
    ).fit(R)
    # Queries revisit the route frame by frame with a weak, noisy view of their place.
    q = np.arange(n)
    S = 0.25 * (R[q] - R[q].mean(axis=1, keepdims=True)) / R[q].std(axis=1, keepdims=True)
    S += rng.standard_normal(S.shape)
    gt = np.abs(q[:, None] - np.arange(n)[None, :]) <= 1
    raw = recall_at_k(S, gt, 1)
    filtered = recall_at_k(filt.filter(S), gt, 1)
    assert filtered >= raw + 0.25, (raw, filtered)
    assert filtered >= 0.6, (raw, filtered)


def test_training_reads_reference_scores_only(rng):
    """The no-query-data rule: fit sees only reference scores; running never trains."""
    R = _reference_scores(12, rng)
    filt = _small().fit(R)
    before = _params(filt)
    queries = rng.random((20, 12))
    filt.filter(queries)
    for row in queries:
        filt.step(row)
    after = _params(filt)
    assert before.keys() == after.keys()
    for key in before:
        assert torch.equal(before[key], after[key]), key
    assert all(not p.requires_grad for p in filt.module_.parameters())
    # The trained model is a function of the reference scores and the seed alone: refitting
    # after the queries were filtered gives the same parameters.
    refit = _params(_small().fit(R))
    for key in before:
        assert torch.equal(before[key], refit[key]), key


def test_seeding_is_local(rng):
    R = _reference_scores(12, rng)
    state = torch.get_rng_state()
    threads = torch.get_num_threads()
    a = _params(_small(random_state=3).fit(R))
    assert torch.equal(torch.get_rng_state(), state)  # torch's global generator untouched
    assert torch.get_num_threads() == threads  # thread setting restored
    b = _params(_small(random_state=3).fit(R))
    c = _params(_small(random_state=4).fit(R))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_accepts_a_generator(rng):
    R = _reference_scores(8, rng)
    a = _params(_small(random_state=np.random.default_rng(5)).fit(R))
    b = _params(_small(random_state=np.random.default_rng(5)).fit(R))
    assert all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------------------------------
# footprint
# ---------------------------------------------------------------------------------------------
def test_footprint_paper_size():
    fp = RNNFilter().footprint(1000)
    h, n = 512, 1000
    assert fp == {"layers": 2, "params": (h * n + h * h + 2 * h) + (h * n + n), "neurons": 1512}
    module = _build_module(torch, "rnn", n, h, torch.Generator().manual_seed(0))
    assert fp["params"] == sum(p.numel() for p in module.parameters()) == 1_288_168
    # with FlyNet (2 layers, 64 + 1000 neurons): the paper's 4 layers, 1.3m params, 2576 neurons
    assert fp["layers"] + 2 == 4 and fp["neurons"] + 64 + n == 2576
    assert round(fp["params"] / 1e6, 1) == 1.3


@pytest.mark.parametrize("cell", CELLS)
def test_footprint_counts_the_fitted_module(cell, rng):
    filt = _small(cell=cell).fit(_reference_scores(9, rng))
    fp = filt.footprint(9)
    assert fp["params"] == sum(p.numel() for p in filt.module_.parameters())
    assert fp["neurons"] == 16 + 9


# ---------------------------------------------------------------------------------------------
# the method pipeline
# ---------------------------------------------------------------------------------------------
def test_method_trains_the_filter_on_reference_scores(random_images):
    from flyvpr.frontends.flynet import FlyNet
    from flyvpr.methods import Method

    ref, query = random_images(12), random_images(7)
    method = Method("flynet+rnn", FlyNet(epochs=5, random_state=0), _small())
    method.fit(ref)
    assert method.filter.n_reference_ == 12
    S = method.score(query)
    assert S.shape == (7, 12)
    np.testing.assert_allclose(S.sum(axis=1), 1.0, rtol=1e-5)
    assert method.footprint()["layers"] == 4


# ---------------------------------------------------------------------------------------------
# errors
# ---------------------------------------------------------------------------------------------
def test_not_fitted(rng):
    filt = _small()
    with pytest.raises(NotFittedError, match="fit"):
        filt.filter(rng.random((3, 4)))
    with pytest.raises(NotFittedError, match="fit"):
        filt.step(rng.random(4))


@pytest.mark.parametrize(
    ("params", "error", "match"),
    [
        (dict(cell="transformer"), ValueError, "cell"),
        (dict(hidden_size=0), ValueError, "hidden_size"),
        (dict(hidden_size=2.5), TypeError, "hidden_size"),
        (dict(sequence_length=0), ValueError, "sequence_length"),
        (dict(epochs=0), ValueError, "epochs"),
        (dict(batch_size=0), ValueError, "batch_size"),
        (dict(learning_rate=0.0), ValueError, "learning_rate"),
        (dict(learning_rate="fast"), TypeError, "learning_rate"),
        (dict(speed_range=(0.0, 1.0)), ValueError, "speed_range"),
        (dict(speed_range=(2.0, 1.0)), ValueError, "speed_range"),
        (dict(speed_range=(1.0, 2.0, 3.0)), TypeError, "speed_range"),
        (dict(noise=1.5), ValueError, "noise"),
        (dict(noise=(0.5, 0.2)), ValueError, "noise"),
        (dict(noise="high"), TypeError, "noise"),
        (dict(n_threads=0), ValueError, "n_threads"),
        (dict(random_state=-1), ValueError, "random_state"),
    ],
)
def test_bad_parameters(params, error, match, rng):
    with pytest.raises(error, match=match):
        _small(**params).fit(_reference_scores(6, rng))


def test_bad_reference_scores(rng):
    with pytest.raises(ValueError, match="reference_scores"):
        _small().fit()
    with pytest.raises(ValueError, match="square"):
        _small().fit(rng.random((5, 6)))
    with pytest.raises(ValueError, match="at least 2"):
        _small().fit(np.ones((1, 1)))
    with pytest.raises(ValueError, match="NaN"):
        _small().fit(np.full((3, 3), np.nan))


def test_wrong_width_at_run_time(fitted, rng):
    with pytest.raises(ValueError, match="12 columns"):
        fitted.filter(rng.random((3, 5)))
    with pytest.raises(ValueError, match="scores_row"):
        fitted.step(rng.random(5))
