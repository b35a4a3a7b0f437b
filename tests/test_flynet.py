import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends.flynet import FlyNet, softmax


def _places(rng, n=40):
    """n distinct random places plus a slightly noisy second view of each."""
    ref = rng.random((n, 32, 64), dtype=np.float32)
    qry = np.clip(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32), 0, 1)
    return ref, qry


def test_learns_reference_places(rng):
    ref, qry = _places(rng)
    fn = FlyNet(random_state=0, epochs=300, learning_rate=0.01).fit(ref)
    assert fn.train_accuracy_ == 1.0
    S = fn.score(qry)
    assert S.shape == (40, 40)
    np.testing.assert_allclose(S.sum(axis=1), 1.0, rtol=1e-5)
    assert np.mean(S.argmax(axis=1) == np.arange(40)) > 0.8


def test_training_reduces_loss(rng):
    ref, _ = _places(rng)
    fn = FlyNet(random_state=0, epochs=50).fit(ref)
    assert fn.loss_history_.shape == (50,)
    assert fn.loss_history_[-1] < fn.loss_history_[0]
    assert np.all(np.diff(fn.loss_history_) < 1e-6)  # full-batch Adam at lr 1e-3: monotone here


def test_defaults_follow_the_paper():
    p = FlyNet().get_params()
    assert p["epochs"] == 200 and p["learning_rate"] == 0.001 and p["batch_size"] is None
    assert (p["n_hidden"], p["sampling_ratio"], p["wta_ratio"]) == (64, 0.1, 0.5)


def test_seeded(rng):
    ref, qry = _places(rng, 20)
    a = FlyNet(random_state=3, epochs=20).fit(ref).score(qry)
    b = FlyNet(random_state=3, epochs=20).fit(ref).score(qry)
    c = FlyNet(random_state=4, epochs=20).fit(ref).score(qry)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_minibatch_training(rng):
    ref, _ = _places(rng, 30)
    fn = FlyNet(random_state=0, epochs=100, batch_size=8, learning_rate=0.01).fit(ref)
    assert fn.train_accuracy_ > 0.9


def test_gradient_matches_finite_differences(rng):
    # One Adam step from zero state moves each weight by -lr * sign(grad) (up to eps),
    # so compare the sign of the update with a finite-difference gradient.
    from flyvpr.frontends.flynet import _train_linear

    codes = (rng.random((6, 8)) < 0.5).astype(np.float32)
    w0, _, _ = _train_linear(codes, 1, 1e-3, 6, np.random.default_rng(0))
    init = np.random.default_rng(0).uniform(-1 / np.sqrt(8), 1 / np.sqrt(8), size=(8, 6))

    def loss(w):
        p = softmax(codes @ w)
        return -np.log(p[np.arange(6), np.arange(6)]).mean()

    grad = np.zeros_like(init)
    h = 1e-5
    for idx in np.ndindex(*init.shape):
        d = np.zeros_like(init)
        d[idx] = h
        grad[idx] = (loss(init + d) - loss(init - d)) / (2 * h)
    step = w0 - init.astype(np.float32)
    big = np.abs(grad) > 1e-4
    np.testing.assert_array_equal(np.sign(step[big]), -np.sign(grad[big]))


def test_footprint_matches_paper_for_1000_places(rng):
    ref = rng.random((1000, 32, 64), dtype=np.float32)
    fn = FlyNet(random_state=0, epochs=1).fit(ref)
    fp = fn.footprint()
    assert (fp["layers"], fp["params"], fp["neurons"]) == (2, 64000, 1064)


def test_not_fitted():
    with pytest.raises(NotFittedError):
        FlyNet().score(np.zeros((1, 32, 64), np.float32))


@pytest.mark.parametrize(
    "params, match",
    [
        ({"epochs": 0}, "epochs"),
        ({"learning_rate": -1.0}, "learning_rate"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_bad_params(rng, params, match):
    ref, _ = _places(rng, 5)
    with pytest.raises(ValueError, match=match):
        FlyNet(**params).fit(ref)


def test_real_nordland_summer_winter_window(nordland_64x32):
    from flyvpr.images import list_images, load_images

    ref = load_images(list_images(nordland_64x32 / "summer")[:200], cache=False, progress=False)
    qry = load_images(list_images(nordland_64x32 / "winter")[:200], cache=False, progress=False)
    fn = FlyNet(random_state=0).fit(ref)
    assert fn.train_accuracy_ > 0.6
    S = fn.score(qry)
    # single frames summer -> winter are weak but better than chance (1/200 * 41 within 20)
    hit = np.abs(S.argmax(axis=1) - np.arange(200)) <= 20
    assert hit.mean() > 41 / 200
