"""Encoder.bytes_per_place: the map each front end stores per reference place."""

import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends import FRONTENDS, Encoder

#: small, fast settings for parts whose defaults train for long
FAST = {
    "flynet": {"epochs": 2},
    "fc": {"epochs": 2},
    "fc-dropout": {"epochs": 2},
    "cnn": {"epochs": 1},
}


def _make(name):
    cls = FRONTENDS[name]
    for module in getattr(cls, "requires", ()):
        pytest.importorskip(module)
    enc = cls()
    params = {k: v for k, v in FAST.get(name, {}).items() if k in enc.get_params()}
    if "random_state" in enc.get_params():
        params["random_state"] = 0
    return enc.set_params(**params)


@pytest.fixture(scope="module")
def images():
    return np.random.default_rng(3).random((16, 32, 64), dtype=np.float32)


@pytest.mark.parametrize("name", sorted(n for n in FRONTENDS if n != "netvlad"))
def test_every_encoder_reports_its_map(name, images):
    enc = _make(name)
    with pytest.raises(NotFittedError):
        enc.bytes_per_place()
    enc.fit(images)
    small = enc.bytes_per_place()
    assert isinstance(small, float) and small > 0
    # Per place: the same for a longer route (shared weights are not counted).
    longer = _make(name).fit(np.concatenate([images, images[::-1]])).bytes_per_place()
    assert longer == small


@pytest.mark.parametrize(
    ("name", "params", "expected"),
    [
        ("pixels", {}, 32 * 64 * 4),  # 2048 float32
        ("flyhash", {}, 8),  # 64 bits, packed
        ("flyhash", {"n_hidden": 100}, 13),  # 100 bits pad to 13 bytes
        ("flynet", {"epochs": 1}, 64 * 4),  # one classifier column: 64 float32
        ("flynet", {"epochs": 1, "n_hidden": 32}, 32 * 4),
    ],
)
def test_values(name, params, expected, images):
    enc = FRONTENDS[name]().set_params(**params)
    assert enc.fit(images).bytes_per_place() == expected


def test_torch_classifier_counts_only_its_classifier(images):
    pytest.importorskip("torch")
    enc = FRONTENDS["fc"](epochs=1, random_state=0).fit(images)
    n_features = enc.weights_.shape[0]
    assert enc.bytes_per_place() == 4 * n_features
    # The feature layers are far larger and are not counted.
    assert sum(v.nbytes for v in enc.layers_.values()) > 16 * enc.bytes_per_place()


def test_pixels_size_follows_the_image(images):
    enc = FRONTENDS["pixels"]().fit(images[:, :16, :32])
    assert enc.bytes_per_place() == 16 * 32 * 4


def test_after_a_model_file_round_trip(images, tmp_path):
    from flyvpr import make_method
    from flyvpr.modelio import load_method, save_method

    model = make_method("flyhash", random_state=0).fit(images)
    path = save_method(model, tmp_path / "m.npz", size=(32, 64))
    assert load_method(path).frontend.bytes_per_place() == model.frontend.bytes_per_place() == 8


def test_encoder_without_the_hook_says_so(images):
    class Bare(Encoder):
        name = "bare"

        def _fit(self, images):
            pass

    with pytest.raises(NotImplementedError, match="Bare does not report the bytes"):
        Bare().fit(images).bytes_per_place()
