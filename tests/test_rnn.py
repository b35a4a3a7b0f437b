"""Tests of the FlyNet+RNN temporal filter (flyvpr.temporal.rnn and its _rnn_net helpers)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from flyvpr._validation import NotFittedError  # noqa: E402
from flyvpr.metrics import recall_at_k  # noqa: E402
from flyvpr.temporal import _rnn_net as net  # noqa: E402
from flyvpr.temporal.rnn import FROM_SCRATCH, RNNFilter  # noqa: E402

CELLS = ["rnn", "gru", "lstm"]
INITS = ["route", "random"]


def _reference_scores(n, rng, width=1.5, noise=0.05):
    """Scores of a route's reference frames against its places: a bump on the diagonal."""
    i = np.arange(n)
    R = np.exp(-((i[:, None] - i[None, :]) ** 2) / (2 * width**2))
    return R + noise * rng.standard_normal((n, n))


def _small(**params):
    defaults = dict(hidden_size=16, sequence_length=8, epochs=2, batch_size=8, random_state=0)
    defaults.update(params)
    return RNNFilter(**defaults)


def _queries_along_route(n, rng, signal=0.4):
    """Query rows that revisit the route frame by frame, each a weak, noisy view of its place."""
    S = rng.standard_normal((n, n))
    S[np.arange(n), np.arange(n)] += signal * np.sqrt(n) / 4
    gt = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= 1
    return S, gt


@pytest.fixture
def fitted(rng):
    return _small().fit(_reference_scores(12, rng))


def _params(filt):
    return {k: v.detach().clone() for k, v in filt.module_.state_dict().items()}


def _same_params(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


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
    filt = RNNFilter(hidden_size=7, cell="nonsense", noise=5.0, init="nope")
    assert filt.get_params()["hidden_size"] == 7
    assert filt.get_params()["cell"] == "nonsense"  # checked at fit, as scikit-learn does
    assert filt.get_params()["init"] == "nope"
    assert not hasattr(filt, "module_")
    assert "RNNFilter(hidden_size=7" in repr(filt)


def test_from_scratch_preset_names_parameters():
    filt = RNNFilter(**FROM_SCRATCH)
    assert filt.get_params()["init"] == "random"
    assert set(FROM_SCRATCH) <= set(filt.get_params())


# ---------------------------------------------------------------------------------------------
# smoke, shapes, online equivalence, causality
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("init", INITS)
@pytest.mark.parametrize("cell", CELLS)
def test_smoke_shapes(cell, init, rng):
    n = 12
    filt = _small(cell=cell, init=init).fit(_reference_scores(n, rng))
    assert filt.n_reference_ == n
    assert filt.loss_history_.shape == (2,)
    assert np.all(np.isfinite(filt.loss_history_))
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


@pytest.mark.parametrize("init", INITS)
@pytest.mark.parametrize("cell", CELLS)
def test_causal(cell, init, rng):
    """A frame's output never changes when later frames change."""
    n = 11
    filt = _small(cell=cell, init=init).fit(_reference_scores(n, rng))
    S = rng.random((20, n))
    out = filt.filter(S)
    for t in (0, 7, 18):
        changed = S.copy()
        changed[t + 1 :] = rng.random((20 - t - 1, n)) * 5
        again = filt.filter(changed)
        np.testing.assert_array_equal(again[: t + 1], out[: t + 1])
        assert not np.allclose(again[t + 1 :], out[t + 1 :])


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
# the training data generator
# ---------------------------------------------------------------------------------------------
def _standardise(x):
    x = x - x.mean(axis=-1, keepdims=True)
    return x / x.std(axis=-1, keepdims=True)


def _batch(n=50, batch=400, length=30, speeds=(0.9, 1.1), noise=(0.5, 1.0), seed=0, rng=None):
    Z = net.normalise(_reference_scores(n, rng or np.random.default_rng(1)), False)
    return Z, net.sample_batch(Z, np.random.default_rng(seed), batch, length, speeds, noise)


def test_sampler_shapes_and_standardised_rows():
    Z, b = _batch()
    assert b.x.shape == (400, 30, 50) and b.x.dtype == np.float32
    assert b.places.shape == b.distractors.shape == b.eta.shape == (400, 30)
    np.testing.assert_allclose(b.x.mean(axis=-1), 0.0, atol=1e-5)
    np.testing.assert_allclose(b.x.std(axis=-1), 1.0, atol=1e-4)


def test_sampler_trajectories_follow_their_speed():
    _, b = _batch(speeds=(0.7, 1.3))
    assert np.all((b.speed >= 0.7) & (b.speed <= 1.3))
    assert b.speed.min() < 0.8 and b.speed.max() > 1.2  # the range is used, not one value
    assert b.places.min() >= 0 and b.places.max() <= 49
    steps = np.diff(b.places, axis=1)
    # rounding of start + v t: consecutive places differ by v up to one place, never backwards
    assert np.all(steps >= 0)
    assert np.all(np.abs(steps - b.speed[:, None]) < 1.0 + 1e-9)
    mean_step = (b.places[:, -1] - b.places[:, 0]) / 29
    np.testing.assert_allclose(mean_step, b.speed, atol=1.0 / 29 + 1e-9)


def test_sampler_noise_share_and_distractor_persistence():
    n = 50
    _, b = _batch(n=n, noise=(0.2, 0.6))
    assert np.all((b.eta >= 0.2) & (b.eta <= 0.6))
    assert abs(b.eta.mean() - 0.4) < 0.01  # U(0.2, 0.6): sd of the mean of 12000 draws 0.001
    same = b.distractors[:, 1:] == b.distractors[:, :-1]
    # kept with probability 0.5, or redrawn and equal by chance (1/n)
    p = net.DISTRACTOR_PERSISTENCE + (1 - net.DISTRACTOR_PERSISTENCE) / n
    sd = np.sqrt(p * (1 - p) / same.size)
    assert abs(same.mean() - p) < 5 * sd
    assert 0 <= b.distractors.min() and b.distractors.max() < n
    assert len(np.unique(b.distractors)) == n  # uniform over the whole traverse


def test_sampler_mixes_the_true_row_by_its_noise_share():
    Z, clean = _batch(noise=(0.0, 0.0))
    np.testing.assert_allclose(clean.x, _standardise(Z[clean.places]), atol=1e-5)
    Z, pure = _batch(noise=(1.0, 1.0))
    n = Z.shape[1]
    # no true-place row left: the input correlates with the distractor's row, not the place's
    corr_place = np.mean(np.sum(pure.x * Z[pure.places], axis=-1) / n)
    corr_distractor = np.mean(np.sum(pure.x * Z[pure.distractors], axis=-1) / n)
    same = pure.places == pure.distractors
    assert abs(corr_place) < 0.05 + same.mean()
    assert 0.6 < corr_distractor < 0.8  # 1/sqrt(2): half the variance is the Gaussian part


def test_sampler_is_determined_by_its_generator():
    _, a = _batch(seed=3)
    _, b = _batch(seed=3)
    _, c = _batch(seed=4)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.x, c.x)


# ---------------------------------------------------------------------------------------------
# the route prior
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("n", "hidden"), [(10, 16), (11, 16), (40, 12), (7, 2), (2, 4)])
def test_route_basis_is_orthonormal(n, hidden):
    B, k = net.route_basis(n, hidden)
    m = B.shape[0]
    assert m <= hidden and m <= n - 1 and len(k) == m
    np.testing.assert_allclose(B @ B.T, np.eye(m), atol=1e-12)
    np.testing.assert_allclose(B.sum(axis=1), 0.0, atol=1e-12)  # no constant row
    if hidden >= n - 1:
        assert m == n - 1  # spans every zero-mean row


@pytest.mark.parametrize("n", [9, 10])
@pytest.mark.parametrize("shift", [1, 3, -2])
def test_route_shift_moves_profiles_along_the_route(n, shift, rng):
    B, k = net.route_basis(n, 2 * n)
    f = rng.standard_normal(n)
    f -= f.mean()
    np.testing.assert_allclose(
        net.route_shift(k, n, shift) @ (B @ f), B @ np.roll(f, shift), atol=1e-12
    )
    # fractional shifts rotate every (cos, sin) pair; the alternating row (even n) can only
    # shrink, by cos(pi v)
    T = net.route_shift(k, n, 0.37)
    pairs = 2 * ((n - 1) // 2)
    np.testing.assert_allclose(T[:pairs, :pairs] @ T[:pairs, :pairs].T, np.eye(pairs), atol=1e-12)
    if n % 2 == 0:
        assert T[-1, -1] == pytest.approx(np.cos(np.pi * 0.37))


def test_route_prior_carries_its_belief_through_a_tunnel(rng):
    """Evidence for places 10..19 on frames 0..9, then ten frames without any: the belief
    keeps moving one place per frame."""
    n = 60
    filt = RNNFilter(hidden_size=64, epochs=0, speed_range=1.0).fit(_reference_scores(n, rng))
    S = np.zeros((20, n))
    S[np.arange(10), 10 + np.arange(10)] = 1.0
    out = filt.filter(S)
    np.testing.assert_array_equal(out[:10].argmax(axis=1), 10 + np.arange(10))
    assert np.all(np.abs(out[10:].argmax(axis=1) - (20 + np.arange(10))) <= 1)
    # ... and fades: the confidence falls while no evidence comes
    assert np.all(np.diff(out[10:].max(axis=1)) < 0)


def test_route_prior_speed_is_the_midpoint_of_speed_range(rng):
    n = 80
    filt = RNNFilter(hidden_size=96, epochs=0, speed_range=(1.5, 2.5)).fit(
        _reference_scores(n, rng)
    )
    S = np.zeros((12, n))
    S[np.arange(6), 10 + 2 * np.arange(6)] = 1.0  # evidence at speed 2, then none
    out = filt.filter(S)
    assert np.all(np.abs(out[6:].argmax(axis=1) - (22 + 2 * np.arange(6))) <= 1)


@pytest.mark.parametrize("cell", ["gru", "lstm"])
def test_route_prior_is_the_same_filter_in_gated_cells(cell, rng):
    n = 40
    R = _reference_scores(n, rng)
    S, gt = _queries_along_route(n, rng)
    plain = RNNFilter(hidden_size=48, epochs=0, random_state=0).fit(R).filter(S)
    gated = RNNFilter(hidden_size=48, epochs=0, random_state=0, cell=cell).fit(R).filter(S)
    # the gates are held open or shut, not exactly at 0 or 1, and an LSTM applies tanh twice:
    # close, not equal (a random network's rows differ by far more than 5%)
    np.testing.assert_allclose(gated, plain, rtol=0.05)
    assert abs(recall_at_k(gated, gt, 1) - recall_at_k(plain, gt, 1)) <= 0.05


def test_route_prior_integrates_noisy_queries(rng):
    """Untrained, the prior turns single frames that are mostly wrong into mostly right ones."""
    n = 80
    filt = RNNFilter(hidden_size=96, epochs=0).fit(_reference_scores(n, rng))
    S, gt = _queries_along_route(n, rng)
    raw = recall_at_k(S, gt, 1)
    filtered = recall_at_k(filt.filter(S), gt, 1)
    assert raw < 0.5 and filtered >= raw + 0.3, (raw, filtered)


def test_epochs_zero_keeps_the_prior_and_trained_weights_move(rng):
    R = _reference_scores(30, rng)
    prior = _params(RNNFilter(hidden_size=32, epochs=0, random_state=0).fit(R))
    B, k = net.route_basis(30, 32)
    m = len(k)
    w = prior["recurrent.weight_ih_l0"].numpy()
    np.testing.assert_allclose(w[:m], 0.03 * B, rtol=1e-6, atol=1e-9)
    hh = prior["recurrent.weight_hh_l0"].numpy()[:m, :m]
    np.testing.assert_allclose(hh, 0.98 * net.route_shift(k, 30, 1.0), atol=1e-7)
    trained = _params(_small(hidden_size=32, epochs=1, learning_rate=1e-3).fit(R))
    assert not _same_params(prior, trained)


def test_training_lowers_the_loss_from_scratch(rng):
    R = _reference_scores(30, rng, noise=0.02)
    filt = _small(
        init="random", hidden_size=32, epochs=30, learning_rate=0.01, noise=(0.0, 0.3)
    ).fit(R)
    assert filt.loss_history_[-1] < 0.5 * filt.loss_history_[0]


def test_training_reads_reference_scores_only(rng):
    """The no-query-data rule: fit sees only reference scores; running never trains."""
    R = _reference_scores(12, rng)
    filt = _small().fit(R)
    before = _params(filt)
    queries = rng.random((20, 12))
    filt.filter(queries)
    for row in queries:
        filt.step(row)
    assert _same_params(before, _params(filt))
    assert all(not p.requires_grad for p in filt.module_.parameters())
    # The trained model is a function of the reference scores and the seed alone: refitting
    # after the queries were filtered gives the same parameters.
    assert _same_params(before, _params(_small().fit(R)))


# ---------------------------------------------------------------------------------------------
# determinism and seeding
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("init", INITS)
def test_deterministic_per_seed(init, rng):
    R = _reference_scores(12, rng)
    S = rng.random((9, 12))
    state = torch.get_rng_state()
    threads = torch.get_num_threads()
    a = _small(init=init, random_state=3).fit(R)
    assert torch.equal(torch.get_rng_state(), state)  # torch's global generator untouched
    assert torch.get_num_threads() == threads  # thread setting restored
    b = _small(init=init, random_state=3).fit(R)
    c = _small(init=init, random_state=4).fit(R)
    assert _same_params(_params(a), _params(b))
    np.testing.assert_array_equal(a.filter(S), b.filter(S))
    np.testing.assert_array_equal(a.loss_history_, b.loss_history_)
    assert not _same_params(_params(a), _params(c))


def test_accepts_a_generator(rng):
    R = _reference_scores(8, rng)
    a = _params(_small(random_state=np.random.default_rng(5)).fit(R))
    b = _params(_small(random_state=np.random.default_rng(5)).fit(R))
    assert _same_params(a, b)


# ---------------------------------------------------------------------------------------------
# model files
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "filter_params",
    [
        {"epochs": 1, "hidden_size": 16, "batch_size": 8, "sequence_length": 6},
        {"epochs": 0, "hidden_size": 16, "cell": "gru"},
        {**FROM_SCRATCH, "epochs": 1, "hidden_size": 8, "cell": "lstm", "batch_size": 8},
    ],
)
def test_model_file_round_trip_is_bit_identical(tmp_path, random_images, filter_params):
    from flyvpr.methods import make_method
    from flyvpr.modelio import load_method, save_method

    ref, query = random_images(14), random_images(9)
    model = make_method(
        "flynet+rnn", 0, frontend_params={"epochs": 5}, filter_params=filter_params
    ).fit(ref)
    S = model.score(query)
    again = load_method(save_method(model, tmp_path / "m.npz"))
    saved = {k: v for k, v in again.filter.get_params().items() if k != "random_state"}
    for key, value in saved.items():
        original = model.filter.get_params()[key]
        assert value == (list(original) if isinstance(original, tuple) else original), key
    assert _same_params(_params(model.filter), _params(again.filter))
    np.testing.assert_array_equal(again.filter.loss_history_, model.filter.loss_history_)
    np.testing.assert_array_equal(again.score(query), S)


# ---------------------------------------------------------------------------------------------
# footprint
# ---------------------------------------------------------------------------------------------
def test_footprint_paper_size():
    fp = RNNFilter().footprint(1000)
    h, n = 512, 1000
    assert fp == {"layers": 2, "params": (h * n + h * h + 2 * h) + (h * n + n), "neurons": 1512}
    module = net.build_module(torch, "rnn", n, h, torch.Generator().manual_seed(0))
    assert fp["params"] == sum(p.numel() for p in module.parameters()) == 1_288_168
    # with FlyNet (2 layers, 64 + 1000 neurons): the paper's 4 layers, 1.3m params, 2576 neurons
    assert fp["layers"] + 2 == 4 and fp["neurons"] + 64 + n == 2576
    assert round(fp["params"] / 1e6, 1) == 1.3


@pytest.mark.parametrize("init", INITS)
@pytest.mark.parametrize("cell", CELLS)
def test_footprint_counts_the_fitted_module(cell, init, rng):
    filt = _small(cell=cell, init=init).fit(_reference_scores(9, rng))
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
        (dict(init="zeros"), ValueError, "init"),
        (dict(init=None), ValueError, "init"),
        (dict(decay=0.0), ValueError, "decay"),
        (dict(decay=1.5), ValueError, "decay"),
        (dict(decay="slow"), TypeError, "decay"),
        (dict(input_gain=0.0), ValueError, "input_gain"),
        (dict(input_gain=float("inf")), ValueError, "input_gain"),
        (dict(input_gain=[0.1]), TypeError, "input_gain"),
        (dict(hidden_size=0), ValueError, "hidden_size"),
        (dict(hidden_size=2.5), TypeError, "hidden_size"),
        (dict(sequence_length=0), ValueError, "sequence_length"),
        (dict(epochs=-1), ValueError, "epochs"),
        (dict(epochs=1.0), TypeError, "epochs"),
        (dict(epochs=0, init="random"), ValueError, "untrained"),
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
