"""Single-frame neural networks the paper compares FlyNet with: FC, FC+Dropout and a CNN.

Paper, Sec. "Comparison of FlyNet to other Neural Networks": every network is trained end to
end on the reference traverse, one class per place (reference image ``i`` has label ``i``),
through a *linear* classifier with one output unit per place, with cross-entropy and Adam at
learning rate 0.001.  :class:`~flyvpr.frontends.netvlad.NetVLADNet` (the NetVLAD baseline)
shares the machinery defined here.  PyTorch is an optional dependency
(``pip install 'flyvpr[torch]'``), imported only when a network is fitted or run.

Architectures (for 32 x 64 gray input and N places)
---------------------------------------------------
``fc`` (:class:`FCNet`)
    The flattened image (2048 pixels) -> fully connected 64 -> ReLU -> fully connected 64 ->
    ReLU -> classifier N: the paper's "three-layer MLP with 64-64-1000 units".
``fc-dropout`` (:class:`FCDropoutNet`)
    The same MLP trained with dropout on the *inputs* of its first two layers: 90% of the
    pixels are dropped before the first layer and 50% of the first layer's units before the
    second.  The paper uses these rates "to approximate the FlyNet sparsity": each FNA unit
    reads 10% of the pixels (90% dropped) and winner-take-all silences 50% of the 64 units,
    which is where the two dropout layers sit here.  Dropout is inverted (kept values are
    scaled by 1 / (1 - p) during training) and off at inference.
``cnn`` (:class:`ConvNet`)
    Two convolutional layers on the 1 x 32 x 64 gray image, the "vanilla CNN often used in
    visual navigation research" the paper cites (the encoder of Mnih et al.'s A3C, used by
    Mirowski et al. and IMPALA): convolution 16 filters 8 x 8 stride 4 -> ReLU -> convolution
    32 filters 4 x 4 stride 2 -> ReLU, no padding and no pooling, giving 16 x 7 x 15 and then
    32 x 2 x 6 = 384 features -> classifier N.  For N = 1000 that is 393,216 parameters, 6.1
    times FlyNet's 64,000 (the paper: "6 times more parameters than FlyNet").

Conventions shared by these networks
------------------------------------
* **No biases.**  Every layer is bias-free, like FlyNet's output layer.  This is also how the
  paper counts: the FC network's 2048*64 + 64*64 + 64*1000 = 199,168 weights are its "199k".
* **Initialisation.**  Layers followed by a ReLU draw weights from He's uniform
  distribution ``U(-sqrt(6 / fan_in), sqrt(6 / fan_in))``; the classifier draws from
  ``U(-1 / sqrt(fan_in), 1 / sqrt(fan_in))`` (torch's ``nn.Linear`` bound, as FlyNet).
* **Training.**  ``epochs`` passes over the reference traverse, the whole traverse as one batch
  (``batch_size=None``, as the authors' FlyNet code) or shuffled mini-batches.  The defaults
  are 200 full-batch epochs (the authors' FlyNet schedule) except for :class:`FCDropoutNet`,
  which learns too slowly for that (see there) and NetVLAD (100 epochs).
* **Randomness.**  ``random_state`` becomes a numpy Generator once
  (:func:`~flyvpr._validation.check_random_state`), which seeds one ``torch.Generator`` that
  draws the initial weights, the dropout masks and the batch order.  Torch's global random
  state is never used or changed, so equal seeds give equal networks.
* **Threads.**  Torch runs on ``n_threads`` threads (one by default) while a network is
  fitted or encodes, and the previous setting is restored afterwards.  Torch's matrix
  products and convolution gradients split their sums over the threads, and another split
  rounds differently: over the epochs another thread count trains another network.  With one
  thread a seed gives the same network and scores whatever the machine's or the job's thread
  count.
* **Codes and scores.**  :meth:`encode` returns the classifier's input (the last hidden
  layer: 64 values for ``fc``, 384 for ``cnn``); ``score`` is the softmax of the classifier's
  outputs, shape (n_query, n_reference), each row summing to one.
* **Footprint** (:meth:`footprint`).  ``layers``: layers with weights (fully connected,
  convolutional, the classifier; the input is not a layer).  ``params``: every parameter used
  at inference, ``trainable_params`` the trained ones and ``frozen_params`` the fixed ones
  (a pretrained backbone).  ``neurons``: output units per image summed over the layers: the
  width of a fully connected layer, ``channels x height x width`` of a convolution's output
  map, and N for the classifier; input pixels are not counted.  These are the paper's
  conventions for FlyNet (2 layers, 64k parameters, 64 + 1000 = 1064 neurons).
"""

from __future__ import annotations

import logging
import numbers

import numpy as np

from .._torch import check_threads, import_torch, torch_threads
from .._validation import ArraySpec, check_positive_int, check_random_state, check_real
from .base import Encoder
from .flynet import softmax

__all__ = ["TorchClassifier", "FCNet", "FCDropoutNet", "ConvNet", "import_torch"]

logger = logging.getLogger(__name__)

#: images per forward pass at inference
_ENCODE_CHUNK = 256


def torch_generator(torch, random_state):
    """A ``torch.Generator`` seeded from ``random_state`` (None, int or numpy Generator)."""
    rng = check_random_state(random_state)
    return torch.Generator().manual_seed(int(rng.integers(2**62)))


def _uniform(torch, shape, bound: float, generator):
    return torch.empty(shape, dtype=torch.float32).uniform_(-bound, bound, generator=generator)


def _he_uniform(torch, shape, fan_in: int, generator):
    return _uniform(torch, shape, float(np.sqrt(6.0 / fan_in)), generator)


def _dropout(torch, x, rate: float, generator):
    """Inverted dropout with the masks drawn from ``generator``."""
    keep = torch.rand(x.shape, generator=generator) >= rate
    return x * keep / (1.0 - rate)


def _check_rate_tuple(value, name: str, length: int) -> tuple[float, ...]:
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        value = (value,) * length
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{name} must be a number or a sequence of numbers; got {value!r}")
    try:
        rates = tuple(value)
    except TypeError:
        raise TypeError(
            f"{name} must be a sequence of numbers; got {type(value).__name__}"
        ) from None
    if len(rates) != length:
        raise ValueError(f"{name} must have {length} rates (one per hidden layer); got {rates}")
    for r in rates:
        if isinstance(r, bool) or not isinstance(r, numbers.Real):
            raise TypeError(f"{name} must hold numbers; got {type(r).__name__}")
        if not 0.0 <= float(r) < 1.0:
            raise ValueError(f"{name} rates must be in [0, 1); got {rates}")
    return tuple(float(r) for r in rates)


def _check_int_tuple(value, name: str, length: int | None = None) -> tuple[int, ...]:
    if isinstance(value, (numbers.Integral, np.integer)) and not isinstance(value, bool):
        value = (value,)
    try:
        items = tuple(value)
    except TypeError:
        raise TypeError(f"{name} must be a sequence of ints; got {type(value).__name__}") from None
    if not items:
        raise ValueError(f"{name} must not be empty")
    if length is not None and len(items) != length:
        raise ValueError(f"{name} must have {length} entries; got {items}")
    return tuple(check_positive_int(v, name) for v in items)


class TorchClassifier(Encoder):
    """Base of the torch networks: feature layers + a bias-free linear classifier per place.

    A subclass defines its feature layers through four hooks: ``_check_architecture``,
    ``_network_inputs`` (images -> the tensor the layers read), ``_init_layers`` and
    ``_forward``, plus ``_layer_neurons`` for the footprint.  This class owns the training
    loop, the classifier, encoding and scoring.

    Attributes set by ``fit``
    -------------------------
    layers_ : dict of str -> ndarray of float32
        Trained parameters of the feature layers.
    weights_ : ndarray of float32, shape (n_features, n_reference)
        The classifier (no bias).
    loss_history_, accuracy_history_ : ndarray, shape (epochs,)
        Mean training cross-entropy and training accuracy of each epoch's forward passes
        (with dropout where the network uses it).
    train_accuracy_ : float
        Share of the reference images classified as their own place after training,
        without dropout.
    """

    name = "torch-classifier"
    requires: tuple[str, ...] = ("torch",)
    #: model files written before ``n_threads`` existed load with its default
    _added_params = ("n_threads",)

    # the training parameters every subclass's __init__ stores
    epochs: int
    learning_rate: float
    batch_size: int | None
    random_state: int | np.random.Generator | None
    n_threads: int | None

    # -- validation -----------------------------------------------------------------------
    def _check_training(self) -> tuple[int, float, int | None]:
        epochs = check_positive_int(self.epochs, "epochs")
        lr = check_real(self.learning_rate, "learning_rate")
        batch = (
            None if self.batch_size is None else check_positive_int(self.batch_size, "batch_size")
        )
        return epochs, float(lr), batch

    def _who(self) -> str:
        return f"{type(self).__name__} (method {self.name!r})"

    # -- public calls (through Encoder) -----------------------------------------------------
    def _fit(self, images: np.ndarray) -> None:
        epochs, lr, batch = self._check_training()
        n_threads = check_threads(self.n_threads)
        self._check_architecture(images.shape[1:])
        rng = check_random_state(self.random_state)
        torch = import_torch(self._who(), getattr(self, "extra", "torch"))
        with torch_threads(torch, n_threads):
            self._setup(torch)
            generator = torch_generator(torch, rng)
            n = images.shape[0]
            with torch.no_grad():
                inputs = self._network_inputs(torch, images)
                layers = self._init_layers(torch, inputs, generator)
                n_features = self._forward(torch, layers, inputs[:1], None).shape[1]
            weights = _uniform(torch, (n_features, n), 1.0 / np.sqrt(n_features), generator)
            losses, accs = _train(
                torch, self, layers, weights, inputs, epochs, lr, min(batch or n, n), generator
            )
            self.layers_ = {k: v.detach().numpy() for k, v in layers.items()}
            self.weights_ = weights.detach().numpy()
            self.loss_history_ = losses
            self.accuracy_history_ = accs
            codes = self._codes(torch, inputs)
            pred = np.argmax(codes @ self.weights_, axis=1)
            self.train_accuracy_ = float(np.mean(pred == np.arange(n)))
        logger.info(
            "%s trained on %d places, %d epochs: loss %.3f -> %.3f, train accuracy %.3f",
            type(self).__name__,
            n,
            epochs,
            losses[0],
            losses[-1],
            self.train_accuracy_,
        )

    def _encode(self, images: np.ndarray) -> np.ndarray:
        torch = import_torch(self._who(), getattr(self, "extra", "torch"))
        out = []
        with torch_threads(torch, check_threads(self.n_threads)):
            for start in range(0, images.shape[0], _ENCODE_CHUNK):
                with torch.no_grad():
                    inputs = self._network_inputs(torch, images[start : start + _ENCODE_CHUNK])
                out.append(self._codes(torch, inputs))
        return np.concatenate(out)

    def logits(self, codes) -> np.ndarray:
        """Classifier outputs before the softmax, shape (N, n_reference)."""
        self._check_fitted()
        codes = np.asarray(codes)
        n_features = self.weights_.shape[0]
        if codes.ndim != 2 or codes.shape[1] != n_features:
            raise ValueError(f"codes must have shape (N, {n_features}); got {codes.shape}")
        return codes.astype(np.float32, copy=False) @ self.weights_

    def _score(self, codes: np.ndarray) -> np.ndarray:
        return softmax(self.logits(codes))

    def _map_nbytes(self) -> int:
        # One classifier column per place: n_features float32 weights.  The feature layers
        # (and a pretrained backbone) are shared by all places and not counted.
        return int(self.weights_.nbytes)

    def _footprint(self) -> dict:
        trainable = sum(int(v.size) for v in self.layers_.values()) + int(self.weights_.size)
        frozen = self._frozen_params()
        neurons = self._layer_neurons()
        return {
            "layers": len(neurons) + 1,
            "params": trainable + frozen,
            "trainable_params": trainable,
            "frozen_params": frozen,
            "neurons": int(sum(neurons)) + int(self.n_reference_),
        }

    # -- saved state (flyvpr.modelio) -----------------------------------------------------
    _state_names: tuple[str, ...] = ("weights_", "loss_history_", "accuracy_history_")

    def _state_arrays(self, scalars: dict) -> dict:
        epochs = check_positive_int(self.epochs, "epochs")
        return {
            "weights_": ArraySpec("float32", (None, scalars["n_reference_"])),
            "loss_history_": ArraySpec("float64", (epochs,)),
            "accuracy_history_": ArraySpec("float64", (epochs,)),
            "layer_*": ArraySpec("float32", None),
        }

    def _get_state(self) -> dict:
        state = super()._get_state()
        state.update({f"layer_{k}": v for k, v in self.layers_.items()})
        return state

    def _set_state(self, state: dict) -> None:
        state = dict(state)
        self.layers_ = {
            k[len("layer_") :]: np.asarray(state.pop(k), dtype=np.float32)
            for k in list(state)
            if k.startswith("layer_")
        }
        super()._set_state(state)

    # -- helpers and hooks ----------------------------------------------------------------
    def _codes(self, torch, inputs) -> np.ndarray:
        """Classifier inputs of a batch of network inputs, without dropout."""
        layers = {k: torch.from_numpy(v) for k, v in self.layers_.items()}
        out = []
        with torch.no_grad():
            for start in range(0, inputs.shape[0], _ENCODE_CHUNK):
                chunk = inputs[start : start + _ENCODE_CHUNK]
                out.append(self._forward(torch, layers, chunk, None).numpy())
        return np.concatenate(out).astype(np.float32, copy=False)

    def _setup(self, torch) -> None:
        """Prepare fixed parts (a pretrained backbone) before the inputs are computed."""

    def _frozen_params(self) -> int:
        return 0

    def _check_architecture(self, image_shape: tuple[int, int]) -> None:
        raise NotImplementedError

    def _network_inputs(self, torch, images: np.ndarray):
        raise NotImplementedError

    def _init_layers(self, torch, inputs, generator) -> dict:
        raise NotImplementedError

    def _forward(self, torch, layers: dict, x, generator):
        """Feature layers; ``generator`` is None at inference and draws dropout in training."""
        raise NotImplementedError

    def _layer_neurons(self) -> list[int]:
        """Output units per image of every feature layer (the classifier excluded)."""
        raise NotImplementedError


def _train(torch, net, layers, weights, inputs, epochs, lr, batch, generator):
    """Adam on softmax cross-entropy, label of input ``i`` = ``i``; returns loss/accuracy."""
    params = [*layers.values(), weights]
    for p in params:
        p.requires_grad_(True)
    optimiser = torch.optim.Adam(params, lr=lr)
    n = inputs.shape[0]
    labels = torch.arange(n)
    losses = np.empty(epochs)
    accs = np.empty(epochs)
    for epoch in range(epochs):
        order = torch.randperm(n, generator=generator) if batch < n else None
        loss_sum = 0.0
        correct = 0
        for start in range(0, n, batch):
            if order is None:
                x, y = inputs, labels
            else:
                idx = order[start : start + batch]
                x, y = inputs[idx], labels[idx]
            logits = net._forward(torch, layers, x, generator) @ weights
            loss = torch.nn.functional.cross_entropy(logits, y)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            loss_sum += loss.item() * len(y)
            correct += int((logits.detach().argmax(dim=1) == y).sum())
        losses[epoch] = loss_sum / n
        accs[epoch] = correct / n
    for p in params:
        p.requires_grad_(False)
    return losses, accs


class FCNet(TorchClassifier):
    """Fully connected network on the flattened image (paper's FC baseline).

    Paper, Sec. "Comparison of FlyNet to other Neural Networks": a three-layer MLP with
    64-64-1000 units (for 1000 places), bias-free, ReLU after the hidden layers; see the
    module docstring for the shared conventions.

    Parameters
    ----------
    hidden_sizes : sequence of int, default (64, 64)
        Widths of the hidden layers.
    dropout : None, float or sequence of float
        Dropout rate on the input of each hidden layer during training (one rate per hidden
        layer, in [0, 1)); ``None`` for none.
    epochs : int, default 200
        Passes over the reference traverse (the authors trained FlyNet for 200).
    learning_rate : float, default 0.001
        Adam's step size (the paper's).
    batch_size : int, optional
        Mini-batch size; ``None`` trains on the whole traverse at once.
    random_state : None, int or numpy.random.Generator
        Seeds initial weights, dropout masks and batch order.
    n_threads : int, optional
        Torch threads while fitting and encoding, capped at the machine's cores; the previous
        setting is restored afterwards.  ``None`` uses one, so that a seed gives the same
        network and scores whatever the machine's or the job's thread count (torch splits
        sums over its threads, and another split rounds differently: module docstring).

    Attributes
    ----------
    layers_ : dict
        ``"fc1"``, ``"fc2"``, ...: weights of shape (fan_in, width).
    weights_, loss_history_, accuracy_history_, train_accuracy_
        See :class:`TorchClassifier`.

    Examples
    --------
    >>> import numpy as np
    >>> ref = np.random.default_rng(0).random((20, 32, 64), dtype=np.float32)
    >>> net = FCNet(epochs=50, learning_rate=0.01, random_state=0).fit(ref)  # doctest: +SKIP
    >>> net.score(ref).shape  # doctest: +SKIP
    (20, 20)
    """

    name = "fc"

    def __init__(
        self,
        hidden_sizes=(64, 64),
        dropout=None,
        epochs=200,
        learning_rate=0.001,
        batch_size=None,
        random_state=None,
        n_threads=None,
    ):
        self.hidden_sizes = hidden_sizes
        self.dropout = dropout
        self.epochs = epochs
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.random_state = random_state
        self.n_threads = n_threads

    def _sizes(self) -> tuple[int, ...]:
        return _check_int_tuple(self.hidden_sizes, "hidden_sizes")

    def _rates(self) -> tuple[float, ...]:
        n = len(self._sizes())
        if self.dropout is None:
            return (0.0,) * n
        return _check_rate_tuple(self.dropout, "dropout", n)

    def _check_architecture(self, image_shape) -> None:
        self._sizes()
        self._rates()

    def _network_inputs(self, torch, images):
        return torch.from_numpy(np.ascontiguousarray(images)).reshape(images.shape[0], -1)

    def _init_layers(self, torch, inputs, generator) -> dict:
        layers = {}
        fan_in = inputs.shape[1]
        for i, width in enumerate(self._sizes(), start=1):
            layers[f"fc{i}"] = _he_uniform(torch, (fan_in, width), fan_in, generator)
            fan_in = width
        return layers

    def _forward(self, torch, layers, x, generator):
        h = x
        for i, rate in enumerate(self._rates(), start=1):
            if generator is not None and rate > 0:
                h = _dropout(torch, h, rate, generator)
            h = torch.relu(h @ layers[f"fc{i}"])
        return h

    def _layer_neurons(self) -> list[int]:
        return [int(self.layers_[f"fc{i}"].shape[1]) for i in range(1, len(self.layers_) + 1)]


class FCDropoutNet(FCNet):
    """Fully connected network trained with dropout 90% / 50% (paper's FC+Dropout baseline).

    :class:`FCNet` with ``dropout=(0.9, 0.5)``: 90% of the pixels are dropped at the input of
    the first layer and 50% of the first layer's units at the input of the second, during
    training only.  The paper chose the rates "to approximate the FlyNet sparsity" (10%
    sampling, 50% winner-take-all).  Parameters as :class:`FCNet`, except the training
    defaults.

    With 90% of the pixels dropped, every step sees a different tenth of each image, and one
    image per place: the network learns far more slowly than without dropout.  On Nordland
    (1000 summer places, 32 x 64, seed 0, lr 0.001) 200 full-batch epochs leave it at chance
    (0.1% training accuracy) where :class:`FCNet` reaches 82%; shuffled mini-batches of 100
    learn faster per pass (15% after 600 epochs, 26% after 1000).  The defaults are therefore
    ``epochs=1000, batch_size=100`` (about a minute on one CPU core).
    """

    name = "fc-dropout"

    def __init__(
        self,
        hidden_sizes=(64, 64),
        dropout=(0.9, 0.5),
        epochs=1000,
        learning_rate=0.001,
        batch_size=100,
        random_state=None,
        n_threads=None,
    ):
        super().__init__(
            hidden_sizes=hidden_sizes,
            dropout=dropout,
            epochs=epochs,
            learning_rate=learning_rate,
            batch_size=batch_size,
            random_state=random_state,
            n_threads=n_threads,
        )


class ConvNet(TorchClassifier):
    """Two-layer convolutional network on the gray image (paper's CNN baseline).

    Convolution -> ReLU -> convolution -> ReLU (bias-free, no padding, no pooling) -> flatten ->
    linear classifier.  The defaults are the A3C / IMPALA "vanilla" navigation encoder
    (16 filters 8x8 stride 4, 32 filters 4x4 stride 2): on 32 x 64 images 384 features and,
    for 1000 places, 393,216 parameters (6.1 x FlyNet).

    Parameters
    ----------
    channels : sequence of int, default (16, 32)
        Filters of each convolution.
    kernel_sizes : sequence of int, default (8, 4)
        Square kernel side of each convolution.
    strides : sequence of int, default (4, 2)
        Stride of each convolution.
    epochs, learning_rate, batch_size, random_state, n_threads
        As :class:`FCNet`.

    Attributes
    ----------
    layers_ : dict
        ``"conv1"``, ``"conv2"``, ...: kernels of shape (out, in, k, k).

    Raises
    ------
    ValueError
        From ``fit`` if the images are too small for the kernels and strides.
    """

    name = "cnn"

    def __init__(
        self,
        channels=(16, 32),
        kernel_sizes=(8, 4),
        strides=(4, 2),
        epochs=200,
        learning_rate=0.001,
        batch_size=None,
        random_state=None,
        n_threads=None,
    ):
        self.channels = channels
        self.kernel_sizes = kernel_sizes
        self.strides = strides
        self.epochs = epochs
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.random_state = random_state
        self.n_threads = n_threads

    def _spec(self):
        channels = _check_int_tuple(self.channels, "channels")
        kernels = _check_int_tuple(self.kernel_sizes, "kernel_sizes", len(channels))
        strides = _check_int_tuple(self.strides, "strides", len(channels))
        return channels, kernels, strides

    def _map_shapes(self, image_shape) -> list[tuple[int, int, int]]:
        """(channels, height, width) of every convolution's output."""
        h, w = image_shape
        shapes = []
        for c, k, s in zip(*self._spec(), strict=True):
            if h < k or w < k:
                raise ValueError(
                    f"images of size {tuple(image_shape)} are too small for ConvNet's kernels "
                    f"{self.kernel_sizes} and strides {self.strides}: a {k}x{k} kernel meets a "
                    f"{h}x{w} map"
                )
            h, w = (h - k) // s + 1, (w - k) // s + 1
            shapes.append((c, h, w))
        return shapes

    def _check_architecture(self, image_shape) -> None:
        self._map_shapes(image_shape)

    def _network_inputs(self, torch, images):
        return torch.from_numpy(np.ascontiguousarray(images)).unsqueeze(1)

    def _init_layers(self, torch, inputs, generator) -> dict:
        layers = {}
        c_in = inputs.shape[1]
        for i, (c, k, _) in enumerate(zip(*self._spec(), strict=True), start=1):
            fan_in = c_in * k * k
            layers[f"conv{i}"] = _he_uniform(torch, (c, c_in, k, k), fan_in, generator)
            c_in = c
        return layers

    def _forward(self, torch, layers, x, generator):
        h = x
        for i, s in enumerate(self._spec()[2], start=1):
            h = torch.relu(torch.nn.functional.conv2d(h, layers[f"conv{i}"], stride=s))
        return h.flatten(1)

    def _layer_neurons(self) -> list[int]:
        return [c * h * w for c, h, w in self._map_shapes(self.image_shape_)]
