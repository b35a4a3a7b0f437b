"""FlyNet: the FNA hash followed by a bias-free linear classifier, one class per place.

Paper, Sec. "FlyNet" and Fig. "FlyNet baselines" (a): the 64 binary FNA units
feed a fully connected output layer with one unit per reference place, trained
on the reference traverse (one image per class) with cross-entropy and Adam at
learning rate 0.001.  The authors' public code trains 200 epochs with the whole
traverse as one batch; those are the defaults here.  Training is plain numpy:
no torch needed.
"""

from __future__ import annotations

import logging

import numpy as np

from .._validation import (
    ArraySpec,
    PartSpec,
    check_memory,
    check_positive_int,
    check_random_state,
    check_real,
)
from .base import Encoder
from .flyhash import FlyHash, _check_codes

__all__ = ["FlyNet", "softmax"]

logger = logging.getLogger(__name__)


def softmax(logits: np.ndarray, axis: int = -1) -> np.ndarray:
    """Numerically stable softmax along ``axis``."""
    z = logits - logits.max(axis=axis, keepdims=True)
    np.exp(z, out=z)
    z /= z.sum(axis=axis, keepdims=True)
    return z


class FlyNet(Encoder):
    """FlyHash + a linear classifier over the reference places (paper's FlyNet).

    Parameters
    ----------
    n_hidden, sampling_ratio, wta_ratio
        The FNA layer, see :class:`~flyvpr.frontends.flyhash.FlyHash`.
    epochs : int, default 200
        Passes over the reference traverse.
    learning_rate : float, default 0.001
        Adam's step size (betas 0.9, 0.999, eps 1e-8 as in the usual Adam).
    batch_size : int, optional
        Mini-batch size; ``None`` trains on the whole traverse at once, as the
        authors' code does.
    random_state : None, int or numpy.random.Generator
        Seeds the connections, the initial weights and the batch order.

    Attributes
    ----------
    hash_ : FlyHash
        The fitted FNA layer.
    weights_ : ndarray of float32, shape (n_hidden, n_reference)
        Output layer (no bias).
    loss_history_, accuracy_history_ : ndarray, shape (epochs,)
        Training cross-entropy and accuracy of each epoch's forward passes.
    train_accuracy_ : float
        Share of reference images classified as their own place after training.

    Notes
    -----
    ``score`` returns softmax probabilities, so each row sums to one and its
    maximum is a confidence in [0, 1].
    """

    name = "flynet"
    #: its 64-bit code of a 32x64 image stays the same over frames that differ by sensor noise
    #: (on Nordland 0-999, 81 winter frames where the train stood repeat the last one's scores)
    repeats_on_noise = True

    def __init__(
        self,
        n_hidden=64,
        sampling_ratio=0.1,
        wta_ratio=0.5,
        epochs=200,
        learning_rate=0.001,
        batch_size=None,
        random_state=None,
    ):
        self.n_hidden = n_hidden
        self.sampling_ratio = sampling_ratio
        self.wta_ratio = wta_ratio
        self.epochs = epochs
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.random_state = random_state

    def _fit(self, images: np.ndarray) -> None:
        epochs = check_positive_int(self.epochs, "epochs")
        lr = check_real(self.learning_rate, "learning_rate")
        n = images.shape[0]
        batch = n if self.batch_size is None else check_positive_int(self.batch_size, "batch_size")
        n_hidden = check_positive_int(self.n_hidden, "n_hidden")
        # weights, Adam's two moments and the gradient, plus a batch of logits and softmax
        check_memory(
            16 * n_hidden * n + 8 * min(batch, n) * n,
            f"n_hidden={n_hidden}, batch_size={self.batch_size} with {n} reference places",
        )
        rng = check_random_state(self.random_state)
        self.hash_ = FlyHash(self.n_hidden, self.sampling_ratio, self.wta_ratio, random_state=rng)
        self.hash_.fit(images)
        codes = self.hash_.reference_codes_.astype(np.float32)
        self.weights_, self.loss_history_, self.accuracy_history_ = _train_linear(
            codes, epochs, lr, min(batch, n), rng
        )
        # In blocks: a whole n x n logit matrix would not fit for a long route.
        correct = 0
        for start in range(0, n, 512):
            pred = np.argmax(codes[start : start + 512] @ self.weights_, axis=1)
            correct += int(np.sum(pred == np.arange(start, start + len(pred))))
        self.train_accuracy_ = correct / n
        logger.info("FlyNet trained on %d places: train accuracy %.3f", n, self.train_accuracy_)

    _state_names = ("hash_", "weights_", "loss_history_", "accuracy_history_")

    def _state_arrays(self, scalars: dict) -> dict:
        n_hidden = check_positive_int(self.n_hidden, "n_hidden")
        epochs = check_positive_int(self.epochs, "epochs")
        return {
            "hash_": PartSpec(("flyhash",)),
            "weights_": ArraySpec("float32", (n_hidden, scalars["n_reference_"])),
            "loss_history_": ArraySpec("float64", (epochs,)),
            "accuracy_history_": ArraySpec("float64", (epochs,)),
        }

    def _encode(self, images: np.ndarray) -> np.ndarray:
        return self.hash_._encode(images)

    def logits(self, codes) -> np.ndarray:
        """Output-layer activations before the softmax, shape (N, n_reference)."""
        self._check_fitted()
        codes = _check_codes(np.asarray(codes), self.weights_.shape[0])
        return codes.astype(np.float32) @ self.weights_

    def _score(self, codes: np.ndarray) -> np.ndarray:
        return softmax(self.logits(codes))

    def _map_nbytes(self) -> int:
        # Matching reads one column of the classifier per place: n_hidden float32 weights (256
        # bytes for 64 units).  The FNA layer is shared by all places; its reference codes
        # (hash_.reference_codes_, 8 bytes per place packed) are kept in the model file but not
        # used to score queries, so they are not counted.
        return int(self.weights_.nbytes)

    def _footprint(self) -> dict:
        n_hidden, n_ref = self.weights_.shape
        return {
            "layers": 2,  # FNA + FC, as the paper's table
            "params": int(self.weights_.size),  # trained weights; the FNA's are fixed
            "neurons": int(n_hidden + n_ref),
            "fixed_connections": int(self.hash_.connections_.size),
            "bytes_packed": int(self.hash_.packed_connections().nbytes + self.weights_.nbytes),
        }


def _train_linear(codes, epochs, lr, batch, rng, beta1=0.9, beta2=0.999, eps=1e-8):
    """Adam on softmax cross-entropy of a bias-free linear layer; labels are row indices."""
    n, d = codes.shape
    # Same initialisation family as torch.nn.Linear: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
    bound = 1.0 / np.sqrt(d)
    w = rng.uniform(-bound, bound, size=(d, n)).astype(np.float32)
    m = np.zeros_like(w)
    v = np.zeros_like(w)
    labels = np.arange(n)
    losses = np.empty(epochs)
    accs = np.empty(epochs)
    t = 0
    for epoch in range(epochs):
        order = labels if batch >= n else rng.permutation(n)
        loss_sum = 0.0
        correct = 0
        for start in range(0, n, batch):
            idx = order[start : start + batch]
            x = codes[idx]
            p = softmax(x @ w)
            rows = np.arange(len(idx))
            loss_sum += float(-np.log(np.maximum(p[rows, idx], 1e-30)).sum())
            correct += int(np.sum(np.argmax(p, axis=1) == idx))
            p[rows, idx] -= 1.0  # d(loss)/d(logits), summed over the batch
            grad = x.T @ p
            grad /= np.float32(len(idx))
            t += 1
            m *= beta1
            m += (1 - beta1) * grad
            v *= beta2
            v += (1 - beta2) * grad * grad
            m_hat = m / np.float32(1 - beta1**t)
            v_hat = v / np.float32(1 - beta2**t)
            w -= np.float32(lr) * m_hat / (np.sqrt(v_hat) + np.float32(eps))
        losses[epoch] = loss_sum / n
        accs[epoch] = correct / n
    return w, losses, accs
