"""The network, route prior, training sequences and training loop behind ``RNNFilter``.

Private helpers of :mod:`flyvpr.temporal.rnn`.  Torch is never imported at module level: the
functions that need it take the ``torch`` module as their first argument, so ``import flyvpr``
stays free of torch.  The design is documented in :mod:`flyvpr.temporal.rnn`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._torch import import_torch as _import_torch

#: weight blocks per cell type: a GRU has 3 (r, z, n), an LSTM 4 (i, f, g, o) (torch's layout)
GATES = {"rnn": 1, "gru": 3, "lstm": 4}
#: chance that a training frame's distractor place is the previous frame's
DISTRACTOR_PERSISTENCE = 0.5
GRAD_CLIP = 1.0
#: scale of the random weights of the units and gates the route prior does not set: small
#: enough not to disturb the prior, non-zero so that training can still reach them
QUIET = 0.01
#: gate bias that holds a gate open (sigmoid(6) = 0.9975) or shut under the route prior
GATE_BIAS = 6.0


def import_torch():
    """``import torch`` or an ImportError naming the pip extra."""
    return _import_torch("RNNFilter (method 'flynet+rnn')")


def normalise(S: np.ndarray, log_input: bool) -> np.ndarray:
    """Rows -> (log ->) zero mean, unit standard deviation; float32 (n, n_reference)."""
    X = S.astype(np.float64)
    if log_input:
        # Query rows of a probability front end are positive too; the floor only guards
        # against a zero that a caller's rounding produced.
        X = np.log(np.maximum(X, np.finfo(np.float64).tiny))
    X -= X.mean(axis=1, keepdims=True)
    std = X.std(axis=1, keepdims=True)
    X /= np.where(std > 0, std, 1.0)
    return X.astype(np.float32)


# ---------------------------------------------------------------------------------------------
# route prior
# ---------------------------------------------------------------------------------------------
def route_basis(n: int, hidden: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal Fourier rows over ``n`` places that a circular shift only rotates.

    Returns ``(B, k)``: ``B`` (m, n) holds ``sqrt(2/n) cos(2 pi k i / n)`` and
    ``sqrt(2/n) sin(2 pi k i / n)`` for ``k = 1 .. K``, ``K = min(hidden // 2, (n - 1) // 2)``
    (the lowest frequencies), then the alternating row ``(-1)^i / sqrt(n)`` when ``n`` is even,
    every lower frequency is in and a unit is left; ``k`` (m,) is each row's frequency (``n/2``
    for the alternating row).  The constant row is left out: normalised score rows have zero
    mean.  With ``hidden >= n - 1`` the rows span every zero-mean row exactly.
    """
    n_pairs = min(hidden // 2, (n - 1) // 2)
    places = np.arange(n)
    freqs = np.arange(1, n_pairs + 1)
    angle = 2 * np.pi * np.outer(freqs, places) / n
    rows = np.empty((2 * n_pairs, n))
    rows[0::2] = np.cos(angle)
    rows[1::2] = np.sin(angle)
    rows *= np.sqrt(2.0 / n)
    k = np.repeat(freqs, 2).astype(np.float64)
    if n % 2 == 0 and n_pairs == (n - 1) // 2 and 2 * n_pairs < hidden:
        rows = np.vstack([rows, np.where(places % 2 == 0, 1.0, -1.0) / np.sqrt(n)])
        k = np.append(k, n / 2)
    return rows, k


def route_shift(k: np.ndarray, n: int, speed: float) -> np.ndarray:
    """(m, m) map of :func:`route_basis` coefficients for a profile moved ``speed`` places on.

    A profile ``f(i)`` becomes ``f(i - speed)`` (circularly): each (cos, sin) pair rotates by
    ``2 pi k speed / n``; the alternating row is scaled by ``cos(pi speed)``.
    """
    m = len(k)
    out = np.zeros((m, m))
    n_pairs = m // 2
    theta = 2 * np.pi * k[0 : 2 * n_pairs : 2] * speed / n
    c, s = np.cos(theta), np.sin(theta)
    i = 2 * np.arange(n_pairs)
    out[i, i] = c
    out[i, i + 1] = -s
    out[i + 1, i] = s
    out[i + 1, i + 1] = c
    if m % 2:
        out[-1, -1] = np.cos(np.pi * speed)
    return out


def build_module(torch, cell: str, n: int, hidden: int, generator, prior=None):
    """Recurrent layer + readout, initialised from ``generator`` only (and the prior).

    The layers are created on the "meta" device, which skips torch's own initialisation (it
    would draw from the global generator), then given uninitialised CPU memory; every parameter
    is then drawn from U(-1/sqrt(hidden), 1/sqrt(hidden)), the distribution torch's defaults use
    for these layers.  ``prior`` (a dict with ``decay``, ``input_gain``, ``speed``) then
    overwrites them with the route prior (:func:`set_route_prior`).
    """
    recurrent_cls = {"rnn": torch.nn.RNN, "gru": torch.nn.GRU, "lstm": torch.nn.LSTM}[cell]
    recurrent = recurrent_cls(n, hidden, batch_first=True, device="meta")
    readout = torch.nn.Linear(hidden, n, device="meta")
    module = torch.nn.ModuleDict({"recurrent": recurrent, "readout": readout})
    module = module.to_empty(device="cpu")
    bound = 1.0 / np.sqrt(hidden)
    with torch.no_grad():
        for param in module.parameters():
            param.uniform_(-bound, bound, generator=generator)
    if prior is not None:
        set_route_prior(torch, module, cell, n, hidden, **prior)
    return module


def set_route_prior(torch, module, cell, n, hidden, *, decay, input_gain, speed) -> None:
    """Write the route prior into ``module``'s weights (module docstring of ``rnn``)."""
    basis, k = route_basis(n, hidden)
    m = basis.shape[0]
    blocks = GATES[cell]
    candidate = {"rnn": 0, "gru": 2, "lstm": 2}[cell]  # the block holding tanh's argument
    recurrent, readout = module["recurrent"], module["readout"]
    with torch.no_grad():
        for param in module.parameters():
            param.mul_(QUIET)
        w_ih = recurrent.weight_ih_l0.view(blocks, hidden, n)
        w_hh = recurrent.weight_hh_l0.view(blocks, hidden, hidden)
        w_ih[candidate, :m] = torch.from_numpy(input_gain * basis)
        w_hh[candidate, :m, :m] = torch.from_numpy(decay * route_shift(k, n, speed))
        # Gates held at the value that turns the cell into the plain tanh recurrence.
        bias = recurrent.bias_ih_l0.view(blocks, hidden)
        if cell == "gru":  # r open (reset nothing), z shut (take the new candidate)
            bias[0] = GATE_BIAS
            bias[1] = -GATE_BIAS
        elif cell == "lstm":  # input and output gates open, forget gate shut
            bias[0] = GATE_BIAS
            bias[1] = -GATE_BIAS
            bias[3] = GATE_BIAS
        readout.weight[:, :m] = torch.from_numpy((1.0 - decay) / input_gain * basis.T)
        readout.bias.zero_()


# ---------------------------------------------------------------------------------------------
# training sequences and loop
# ---------------------------------------------------------------------------------------------
class Batch(NamedTuple):
    """One batch of training sequences (inputs, targets and how they were drawn)."""

    x: np.ndarray  # (batch, length, n) float32, each row standardised
    places: np.ndarray  # (batch, length) int64, the true place of every frame (the target)
    distractors: np.ndarray  # (batch, length) int64
    eta: np.ndarray  # (batch, length) float32, noise share of every frame
    speed: np.ndarray  # (batch,) places per frame


def sample_batch(Z, rng, batch, length, speeds, noise) -> Batch:
    """Corrupted reference sequences (module docstring of ``rnn``), drawn from ``rng``."""
    n = Z.shape[0]
    steps = np.arange(length)
    speed = rng.uniform(speeds[0], speeds[1], size=batch)
    start = rng.uniform(0.0, np.maximum(n - 1 - speed * (length - 1), 0.0))
    places = np.clip(np.rint(start[:, None] + speed[:, None] * steps), 0, n - 1).astype(np.int64)
    # Distractors: a fresh place where `fresh`, else the previous frame's.  The index of the
    # last fresh frame, carried forward by a running maximum, picks it without a loop.
    candidates = rng.integers(0, n, size=(batch, length))
    fresh = rng.random((batch, length)) >= DISTRACTOR_PERSISTENCE
    fresh[:, 0] = True
    last_fresh = np.maximum.accumulate(np.where(fresh, steps, 0), axis=1)
    distractors = np.take_along_axis(candidates, last_fresh, axis=1)
    eta = rng.uniform(noise[0], noise[1], size=(batch, length, 1)).astype(np.float32)
    x = rng.standard_normal((batch, length, n), dtype=np.float32)
    x += Z[distractors]
    x *= eta / np.float32(np.sqrt(2.0))
    x += (1 - eta) * Z[places]
    x -= x.mean(axis=-1, keepdims=True)
    std = x.std(axis=-1, keepdims=True)
    x /= np.where(std > 0, std, 1.0)
    return Batch(x, places, distractors, eta[..., 0], speed)


def train(torch, module, Z, rng, *, length, epochs, batch, lr, speeds, noise) -> np.ndarray:
    """Adam on the per-frame cross-entropy; returns the mean loss of each epoch."""
    n = Z.shape[0]
    params = list(module.parameters())
    optimiser = torch.optim.Adam(params, lr=lr)
    recurrent, readout = module["recurrent"], module["readout"]
    batches_per_epoch = max(1, int(np.ceil(n / batch)))
    losses = np.empty(epochs)
    module.train()
    for epoch in range(epochs):
        total = 0.0
        for _ in range(batches_per_epoch):
            drawn = sample_batch(Z, rng, batch, length, speeds, noise)
            h, _ = recurrent(torch.from_numpy(drawn.x))
            logits = readout(h)
            loss = torch.nn.functional.cross_entropy(
                logits.reshape(-1, n), torch.from_numpy(drawn.places).reshape(-1)
            )
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, GRAD_CLIP)
            optimiser.step()
            total += loss.item()
        losses[epoch] = total / batches_per_epoch
    return losses
