"""FlyNet+RNN: a recurrent network trained to filter a front end's scores over time.

Paper, Sec. "FlyNet+RNN" and Fig. "FlyNet baselines" (c): a vanilla RNN with 512 recurrent
units sits on top of FlyNet's per-frame outputs and a fully connected layer reads one unit per
reference place out of its hidden state; GRU and LSTM cells "showed no significant performance
improvements despite having far more parameters".  The paper gives neither the training data
nor the schedule of the RNN, so both are this module's choices, documented below.  Torch is an
optional dependency (``pip install 'flyvpr[torch]'``) imported only when a filter is fitted or
run.

Architecture
------------
``x_t`` (one row of scores, normalised as below) -> recurrent cell (``hidden_size`` units;
``tanh`` RNN, GRU or LSTM) -> linear layer ``hidden_size -> n_reference`` with bias -> softmax.
The filtered row of frame ``t`` is that softmax, so its maximum is a confidence in [0, 1] as
FlyNet's.  With FlyNet in front, 1000 places and 512 units the whole model has 4 layers,
1.29 million parameters and 2576 neurons: the paper's footprint table (4 / 1.3m / 2576).

Input normalisation
-------------------
Every score row (reference rows at training time, query rows at run time) is mapped the same
way before it enters the network: if the row is a probability vector (all entries > 0, as
FlyNet's softmax outputs) it is first replaced by its logarithm, i.e. by the logits up to a
constant, because FlyNet's rows are far from one-hot (the best place often holds only 2% of the
mass) and their information is in the logits' relative sizes; then the row is standardised to
zero mean and unit standard deviation (a constant row becomes zeros).  Standardisation makes
the filter indifferent to the front end's score scale (SAD similarities, Hamming similarities,
probabilities).  Whether the log is taken is decided once, from the reference scores, and
stored in ``log_input_``.

Training sequences: reference traverse only
-------------------------------------------
The filter is trained on ``reference_scores`` alone: the front end's scores of the reference
images against the reference places, ``Z = normalise(reference_scores)`` with row ``i`` being
what the front end says when it sees place ``i``.  No query frame is ever used.  Each training
batch holds ``batch_size`` sequences of ``sequence_length`` frames built as follows, every
random draw coming from ``random_state``:

1. *Trajectory.*  A speed ``v ~ U(speed_range)`` (reference places per frame) and a start
   ``s ~ U(0, n_reference - 1 - v (sequence_length - 1))`` are drawn per sequence; frame ``t``
   shows place ``p_t = round(s + v t)`` (clipped to the traverse when the traverse is shorter
   than the sequence: the vehicle waits at its end).  Speeds below one repeat places, speeds
   above one skip places, so the network learns to integrate along trajectories of any speed
   in the range rather than memorising one.  The target of frame ``t`` is ``p_t``.
2. *Corruption.*  Reference rows are nearly what the front end was trained on and thus far
   cleaner than query rows under changed appearance; trained on them alone the network would
   trust every frame.  So each frame's input is
   ``x_t = standardise((1 - eta_t) Z[p_t] + eta_t (Z[d_t] + e_t) / sqrt(2))``
   with a noise share ``eta_t ~ U(noise)`` drawn per frame, a Gaussian row
   ``e_t ~ N(0, I)`` and a *distractor* place ``d_t``: uniform over the traverse at the first
   frame and, at each later frame, the previous distractor again with probability 0.5 or a
   fresh uniform place otherwise.  The distractor rows mimic perceptual aliasing (a query
   that looks like another place, often for a few frames in a row); the Gaussian part mimics
   unstructured noise; drawing ``eta_t`` per frame mixes informative frames with useless ones
   (``eta_t = 1``: a tunnel), so the network learns to weigh each frame by how peaked it is
   and to carry its estimate along the route through the useless ones.  At ``eta_t = 0.8``
   the true place's standardised input is about 1 while the largest wrong entry is about 3,
   roughly what FlyNet gives for Nordland winter queries against a summer reference.
3. *Loss.*  Cross-entropy of the output at every frame against ``p_t`` (one class per
   reference place), Adam with ``learning_rate``, gradients clipped to norm 1.  Every sequence
   starts from a zero hidden state, as the filter does after :meth:`reset`.

One epoch is ``n_reference`` sequences rounded up to whole batches, so each place starts
about one sequence per epoch.

Defaults and what they give
---------------------------
The defaults (64-frame sequences, 4 epochs, Adam at 0.003, speeds 0.9-1.1, per-frame noise
share 0.5-1) were chosen on Nordland frames 1000-1999 (summer reference, winter queries,
64x32), kept apart from the frames 0-999 the paper's protocol evaluates.  On them FlyNet+RNN
raised FlyNet's PR AUC from 0.023 / 0.013 to 0.095 / 0.084 (seeds 0 / 1); GRU cells, wider
speed ranges, per-sequence noise, more epochs or smaller batches did not do better.  On
frames 0-999 the gain was smaller (0.033 -> 0.042, 0.022 -> 0.040).  The network learns to
integrate along the route on synthetic sequences but integrates real query rows far less
than a sequence search over the same rows does, in line with the paper ranking FlyNet+RNN
below FlyNet+CANN.

Running
-------
:meth:`filter` feeds a whole traverse through the network in one call from a zero hidden
state; :meth:`step` feeds one row and keeps the hidden state between calls (:meth:`reset`
zeroes it).  Both give the same rows.  Running never changes the network: the parameters
after any number of ``filter``/``step`` calls are those ``fit`` left.
"""

from __future__ import annotations

import contextlib
import logging
import numbers
import os

import numpy as np

from .._validation import (
    NotFittedError,
    check_positive_int,
    check_random_state,
    check_scores,
)
from .base import OnlineFilter

__all__ = ["RNNFilter"]

logger = logging.getLogger(__name__)

_CELLS = ("rnn", "gru", "lstm")
#: weight blocks per cell type: a GRU has 3 gates, an LSTM 4 (torch's layout)
_GATES = {"rnn": 1, "gru": 3, "lstm": 4}
#: chance that a frame's distractor place is the previous frame's (aliasing lasts a while)
_DISTRACTOR_PERSISTENCE = 0.5
_GRAD_CLIP = 1.0


def _import_torch():
    try:
        import torch
    except ImportError as exc:
        raise ImportError(
            "RNNFilter (method 'flynet+rnn') needs torch: pip install 'flyvpr[torch]'"
        ) from exc
    return torch


@contextlib.contextmanager
def _torch_threads(torch, n_threads):
    """Run torch on ``n_threads`` threads inside the block, then restore the setting."""
    previous = torch.get_num_threads()
    torch.set_num_threads(n_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _check_range(value, name: str, low: float, high: float | None) -> tuple[float, float]:
    """A number or a pair (lo, hi) with low <= lo <= hi (<= high), as a float pair."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        pair = (value, value)
    else:
        try:
            pair = tuple(value)
        except TypeError:
            raise TypeError(
                f"{name} must be a number or a pair (low, high); got {type(value).__name__}"
            ) from None
    if len(pair) != 2 or not all(
        isinstance(v, numbers.Real) and not isinstance(v, bool) for v in pair
    ):
        raise TypeError(f"{name} must be a number or a pair (low, high) of numbers; got {value!r}")
    lo, hi = float(pair[0]), float(pair[1])
    upper = np.inf if high is None else high
    if not (np.isfinite(lo) and np.isfinite(hi) and low <= lo <= hi <= upper):
        bound = f"[{low}, {high}]" if high is not None else f"[{low}, inf)"
        raise ValueError(f"{name} must satisfy low <= high within {bound}; got {value!r}")
    return lo, hi


def _is_probability_matrix(S: np.ndarray) -> bool:
    return bool(np.all(S > 0) and np.allclose(S.sum(axis=1), 1.0, rtol=0, atol=1e-3))


def _normalise(S: np.ndarray, log_input: bool) -> np.ndarray:
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


class RNNFilter(OnlineFilter):
    """Recurrent network (RNN, GRU or LSTM) trained on the reference traverse (FlyNet+RNN).

    Parameters
    ----------
    hidden_size : int, default 512
        Recurrent units (512 in the paper).
    cell : {'rnn', 'gru', 'lstm'}, default 'rnn'
        The paper's vanilla ``tanh`` RNN, or the gated cells it also tried.
    sequence_length : int, default 64
        Frames per training sequence (gradients flow through this many steps).
    epochs : int, default 4
        Training epochs; one epoch is ``n_reference`` sequences.
    learning_rate : float, default 0.003
        Adam's step size (0.001 converged too slowly for the few epochs a fit can afford).
    batch_size : int, default 64
        Sequences per gradient step.
    speed_range : float or (float, float), default (0.9, 1.1)
        Range of the constant speed (reference places per frame) of training sequences.
        Wider ranges generalise to other speeds but cost accuracy at speed 1 (the aligned
        Nordland traverses: (0.8, 1.25) lost about a third of the AUC gain on a held-out
        segment).
    noise : float or (float, float), default (0.5, 1.0)
        Range of the per-frame noise share ``eta_t`` in [0, 1] of the corrupted inputs
        (module docstring); 0 trains on clean reference rows.
    random_state : None, int or numpy.random.Generator
        Seeds the initial weights (through a ``torch.Generator`` seeded from it) and every
        draw of the training sequences.  Torch's global generator is never used.
    n_threads : int, optional
        Torch threads while fitting and filtering, capped at the machine's cores; the previous
        setting is restored afterwards.  ``None`` uses one: the recurrent steps are small
        matrix products whose thread synchronisation costs more than it saves when other
        processes share the cores (on a loaded 2-core machine a training step with 1000
        places took 1.1 s with one thread and 6 s with two).

    Attributes
    ----------
    module_ : torch.nn.ModuleDict
        ``{"recurrent": RNN/GRU/LSTM, "readout": Linear}``, the trained network.
    n_reference_ : int
        Places (inputs and outputs).
    log_input_ : bool
        Whether rows are log-transformed before standardisation (probability front ends).
    loss_history_ : ndarray, shape (epochs,)
        Mean training cross-entropy of each epoch.

    Notes
    -----
    ``fit`` needs the front end's scores of the reference images against the reference
    places; :class:`flyvpr.methods.Method` passes them because ``needs_reference_scores`` is
    True.  Query scores are only ever filtered, never learned from.
    """

    name = "rnn"
    requires = ("torch",)
    needs_reference_scores = True

    def __init__(
        self,
        hidden_size=512,
        cell="rnn",
        sequence_length=64,
        epochs=4,
        learning_rate=0.003,
        batch_size=64,
        speed_range=(0.9, 1.1),
        noise=(0.5, 1.0),
        random_state=None,
        n_threads=None,
    ):
        self.hidden_size = hidden_size
        self.cell = cell
        self.sequence_length = sequence_length
        self.epochs = epochs
        self.learning_rate = learning_rate
        self.batch_size = batch_size
        self.speed_range = speed_range
        self.noise = noise
        self.random_state = random_state
        self.n_threads = n_threads
        self._hidden = None

    # ----------------------------------------------------------------------------------------
    # parameters
    # ----------------------------------------------------------------------------------------
    def _check_cell(self) -> str:
        if self.cell not in _CELLS:
            raise ValueError(f"cell must be one of {_CELLS}; got {self.cell!r}")
        return self.cell

    def _threads(self) -> int:
        if self.n_threads is None:
            return 1
        return min(check_positive_int(self.n_threads, "n_threads"), os.cpu_count() or 1)

    # ----------------------------------------------------------------------------------------
    # training
    # ----------------------------------------------------------------------------------------
    def fit(self, reference_scores=None) -> RNNFilter:
        """Train the network on sequences drawn from the reference traverse.

        Parameters
        ----------
        reference_scores : array-like, shape (n_reference, n_reference)
            The front end's scores of the reference images (rows, in traverse order) against
            the reference places (columns).  Query scores must never be passed here.

        Returns
        -------
        self

        Raises
        ------
        ValueError
            If ``reference_scores`` is missing, not square, has fewer than 2 places, or a
            parameter has a bad value (``cell`` not one of 'rnn', 'gru', 'lstm', ...).
        TypeError
            For parameters of the wrong type.
        ImportError
            If torch is not installed.
        """
        if reference_scores is None:
            raise ValueError(
                "RNNFilter is trained on the reference traverse: fit needs reference_scores, "
                "the front end's (n_reference, n_reference) scores of the reference images"
            )
        R = check_scores(reference_scores, "reference_scores")
        n = R.shape[0]
        if R.shape[1] != n:
            raise ValueError(
                "reference_scores must be square (n_reference, n_reference): the reference "
                f"images against their own places; got shape {R.shape}"
            )
        if n < 2:
            raise ValueError(f"reference_scores must cover at least 2 places; got {n}")
        cell = self._check_cell()
        hidden = check_positive_int(self.hidden_size, "hidden_size")
        length = check_positive_int(self.sequence_length, "sequence_length")
        epochs = check_positive_int(self.epochs, "epochs")
        batch = check_positive_int(self.batch_size, "batch_size")
        lr = self.learning_rate
        if isinstance(lr, bool) or not isinstance(lr, numbers.Real):
            raise TypeError(f"learning_rate must be a number; got {type(lr).__name__}")
        if not (np.isfinite(lr) and lr > 0):
            raise ValueError(f"learning_rate must be a positive number; got {lr}")
        speeds = _check_range(self.speed_range, "speed_range", 0.0, None)
        if speeds[0] <= 0:
            raise ValueError(f"speed_range must be positive; got {self.speed_range!r}")
        noise = _check_range(self.noise, "noise", 0.0, 1.0)
        rng = check_random_state(self.random_state)
        torch = _import_torch()
        n_threads = self._threads()

        log_input = _is_probability_matrix(R)
        Z = _normalise(R, log_input)
        generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
        with _torch_threads(torch, n_threads):
            module = _build_module(torch, cell, n, hidden, generator)
            losses = _train(
                torch,
                module,
                Z,
                rng,
                length=length,
                epochs=epochs,
                batch=batch,
                lr=float(lr),
                speeds=speeds,
                noise=noise,
            )
        module.eval()
        module.requires_grad_(False)
        self.module_ = module
        self.n_reference_ = n
        self.log_input_ = log_input
        self.loss_history_ = losses
        self._hidden = None
        logger.info(
            "RNNFilter (%s, %d units) trained on %d places: loss %.3f -> %.3f",
            cell,
            hidden,
            n,
            losses[0],
            losses[-1],
        )
        return self

    # ----------------------------------------------------------------------------------------
    # running
    # ----------------------------------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "module_"):
            raise NotFittedError(
                f"{type(self).__name__} is not fitted; call fit(reference_scores) first"
            )

    def _check_width(self, n: int, name: str) -> None:
        if n != self.n_reference_:
            raise ValueError(
                f"{name} must have {self.n_reference_} columns (reference places at fit time); "
                f"got {n}"
            )

    def reset(self) -> None:
        """Zero the hidden state: the next :meth:`step` starts a new traverse."""
        self._hidden = None

    def _run(self, S: np.ndarray) -> np.ndarray:
        """Rows of S through the network from the current hidden state; keeps the new state."""
        torch = _import_torch()
        x = torch.from_numpy(_normalise(S, self.log_input_))[None]
        with _torch_threads(torch, self._threads()), torch.no_grad():
            h, self._hidden = self.module_["recurrent"](x, self._hidden)
            out = torch.softmax(self.module_["readout"](h[0]), dim=-1)
        return out.numpy().astype(S.dtype, copy=False)

    def _filter(self, S: np.ndarray) -> np.ndarray:
        self._check_fitted()
        self._check_width(S.shape[1], "S")
        self.reset()
        return self._run(S)

    def _step(self, row: np.ndarray) -> np.ndarray:
        self._check_fitted()
        self._check_width(row.shape[0], "scores_row")
        return self._run(row[None])[0]

    # -- saved state (flyvpr.modelio): the weights as plain arrays, never a pickle --------
    def _get_state(self) -> dict:
        self._check_fitted()
        state = {
            "n_reference_": int(self.n_reference_),
            "log_input_": bool(self.log_input_),
            "loss_history_": np.asarray(self.loss_history_, dtype=np.float64),
        }
        for key, tensor in self.module_.state_dict().items():
            state[f"weights:{key}"] = tensor.detach().cpu().numpy()
        return state

    def _set_state(self, state: dict) -> None:
        torch = _import_torch()
        weights = {
            key.split(":", 1)[1]: torch.from_numpy(np.array(value))
            for key, value in state.items()
            if key.startswith("weights:")
        }
        n = int(state["n_reference_"])
        hidden = check_positive_int(self.hidden_size, "hidden_size")
        module = _build_module(torch, self._check_cell(), n, hidden, torch.Generator())
        try:
            module.load_state_dict(weights, strict=True)
        except RuntimeError as exc:
            raise ValueError(f"saved RNN weights do not fit the saved parameters: {exc}") from None
        module.eval()
        module.requires_grad_(False)
        self.module_ = module
        self.n_reference_ = n
        self.log_input_ = bool(state["log_input_"])
        self.loss_history_ = state["loss_history_"]
        self._hidden = None

    def footprint(self, n_reference: int) -> dict:
        """Layers, parameters and neurons of the recurrent and output layers.

        ``params = g (h n + h^2 + 2 h) + (h n + n)`` with ``h = hidden_size``,
        ``n = n_reference`` and ``g`` = 1, 3, 4 weight blocks for RNN, GRU, LSTM (torch's
        two bias vectors per block included); ``neurons = h + n``.  With FlyNet in front
        (2 layers, 64 + n neurons) and the defaults this is the paper's 4 layers, 1.3m
        parameters and 2576 neurons for n = 1000.
        """
        n = check_positive_int(n_reference, "n_reference")
        h = check_positive_int(self.hidden_size, "hidden_size")
        g = _GATES[self._check_cell()]
        return {
            "layers": 2,
            "params": g * (h * n + h * h + 2 * h) + h * n + n,
            "neurons": h + n,
        }


def _build_module(torch, cell: str, n: int, hidden: int, generator):
    """Recurrent layer + readout, initialised from ``generator`` only.

    The layers are created on the "meta" device, which skips torch's own initialisation (it
    would draw from the global generator), then given uninitialised CPU memory; every parameter
    is then drawn from U(-1/sqrt(hidden), 1/sqrt(hidden)), the distribution torch's defaults
    use for these layers.
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
    return module


def _sample_batch(Z, rng, batch, length, speeds, noise):
    """One batch of corrupted reference sequences (module docstring): inputs, targets."""
    n = Z.shape[0]
    steps = np.arange(length)
    speed = rng.uniform(speeds[0], speeds[1], size=batch)
    start = rng.uniform(0.0, np.maximum(n - 1 - speed * (length - 1), 0.0))
    places = np.clip(np.rint(start[:, None] + speed[:, None] * steps), 0, n - 1).astype(np.int64)
    # Distractors: a fresh place where `fresh`, else the previous frame's.  The index of the
    # last fresh frame, carried forward by a running maximum, picks it without a loop.
    candidates = rng.integers(0, n, size=(batch, length))
    fresh = rng.random((batch, length)) >= _DISTRACTOR_PERSISTENCE
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
    return x, places


def _train(torch, module, Z, rng, *, length, epochs, batch, lr, speeds, noise):
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
            x, places = _sample_batch(Z, rng, batch, length, speeds, noise)
            h, _ = recurrent(torch.from_numpy(x))
            logits = readout(h)
            loss = torch.nn.functional.cross_entropy(
                logits.reshape(-1, n), torch.from_numpy(places).reshape(-1)
            )
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, _GRAD_CLIP)
            optimiser.step()
            total += loss.item()
        losses[epoch] = total / batches_per_epoch
    return losses
