import numpy as np
import pytest

from flyvpr.localizer import Localizer
from flyvpr.methods import make_method
from flyvpr.synthetic import make_route


@pytest.fixture(scope="module")
def route():
    r = make_route(n_places=120, random_state=1)
    return r.reference_images, r.query_images


@pytest.mark.parametrize("method", ["flyhash", "flynet+cann", "pixels+seqslam", "flyhash+cann"])
def test_stream_matches_batch(route, method):
    ref, qry = route
    params = {"epochs": 20} if method.startswith("flynet") else None
    batch = make_method(method, 0, frontend_params=params).fit(ref)
    S = batch.score(qry)
    loc = Localizer(method, random_state=0, frontend_params=params).fit(ref)
    places, confs = zip(*(loc.update(img) for img in qry), strict=True)
    np.testing.assert_array_equal(places, S.argmax(axis=1))
    np.testing.assert_allclose(confs, S.max(axis=1), rtol=1e-4, atol=1e-5)
    assert loc.n_frames_ == len(qry)


def test_reset_restarts_the_drive(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)
    first = [loc.update(img) for img in qry[:30]]
    loc.reset()
    again = [loc.update(img) for img in qry[:30]]
    assert first == again


def test_velocity_input_is_passed_to_the_filter(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)
    keep = np.arange(0, len(qry), 2)
    for i, k in enumerate(keep):
        loc.update(qry[k], velocity=None if i == 0 else 2.0)
    assert loc.method.filter.velocity_ == 2.0


def test_state_does_not_grow(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)

    def state_size():
        filt = loc.method.filter
        return sum(v.nbytes for v in vars(filt).values() if isinstance(v, np.ndarray))

    loc.update(qry[0])
    size = state_size()
    for img in qry[1:]:
        loc.update(img)
    assert state_size() == size


def test_offline_filter_refused():
    method = make_method("pixels+seqslam", 0, filter_params={"mode": "centered"})
    loc = Localizer(method)
    with pytest.raises(ValueError, match="future|centred|centered"):
        loc.fit(np.random.default_rng(0).random((10, 32, 64), dtype=np.float32))
        loc.update(np.zeros((32, 64), np.float32))


def test_bad_frame(route):
    ref, _ = route
    loc = Localizer("flyhash", random_state=0).fit(ref)
    with pytest.raises(ValueError, match="image size"):
        loc.update(np.zeros((16, 32), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        loc.update(np.full((32, 64), np.nan, np.float32))


@pytest.mark.parametrize("call", ["update", "scores", "n_places"])
def test_calls_before_fit_raise_not_fitted_naming_the_call(call):
    from flyvpr import NotFittedError

    loc = Localizer("flyhash", random_state=0)
    with pytest.raises(NotFittedError, match=f"Localizer.{call}"):
        getattr(loc, call) if call == "n_places" else getattr(loc, call)(np.zeros((32, 64)))
