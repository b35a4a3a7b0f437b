"""FlyNet+RNN: a recurrent network that filters a front end's scores over time.

Paper, Sec. "FlyNet+RNN" and Fig. "FlyNet baselines" (c): a vanilla RNN with 512 recurrent
units sits on top of FlyNet's per-frame outputs and a fully connected layer reads one unit per
reference place out of its hidden state; GRU and LSTM cells "showed no significant performance
improvements despite having far more parameters".  The paper gives neither the training data
nor the initialisation of the RNN, so both are this module's choices, documented below and in
``docs/guide/rnn.md`` with the experiments behind them.  Torch is an optional dependency
(``pip install 'flyvpr[torch]'``) imported only when a filter is fitted or run.

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
way: a probability row (all entries > 0 and summing to one, as FlyNet's softmax) is replaced by
its logarithm, i.e. by the logits up to a constant, because FlyNet's rows are far from one-hot
(the best place holds about 2% of the mass among 1000) and their information is in the logits'
relative sizes; then the row is standardised to zero mean and unit standard deviation.  Whether
the log is taken is decided once, from the reference scores, and stored in ``log_input_``.

Initial weights: the route prior (``init="route"``, default)
------------------------------------------------------------
To filter a traverse the network has to carry its belief about where it is from frame to frame
and move it along the route as the vehicle moves.  Learnt from scratch by a 1000-way classifier
on synthetic reference sequences this did not emerge within any affordable training budget (see
the guide), so by default the network *starts* as that structure, which its architecture can
represent exactly.  Let ``B`` (m x n) hold the ``m <= hidden_size`` lowest-frequency rows of the
real Fourier basis over the ``n`` places (cos/sin pairs; the constant row is left out because
normalised rows have zero mean): a profile over the places moved ``v`` places along the route
(circularly) has its coefficients rotated pair by pair, a map ``T_v``.  The first ``m`` units get

* input weights ``input_gain * B``,
* recurrent weights ``decay * T_v`` with ``v`` the midpoint of ``speed_range``,
* readout weights ``(1 - decay) / input_gain * B^T``, readout bias 0,

and every other weight is drawn as in ``init="random"`` and scaled by 0.01 (quiet but
trainable).  GRU and LSTM cells get the same weights in their candidate (``tanh``) block and
gate biases of +-6 that hold the cell at the plain recurrence.  While ``tanh`` stays in its
linear range (``input_gain`` keeps it there), the readout of frame ``t`` is
``sum_j (1 - decay) decay^j P x_{t-j}`` moved ``j v`` places on: an exponentially weighted
average of past rows along the trajectory of speed ``v``, low-passed to the ``m / 2`` lowest
frequencies (``P = B^T B``; exact when ``hidden_size >= n - 1``).  With 512 units and 1000
places the hidden state resolves the route to about 2 places; for much longer routes the
resolution is ``n / hidden_size`` places.  ``decay`` 0.98 (a memory of about 50 frames) and
``input_gain`` 0.03 were chosen on Nordland frames 2000-2399 (summer reference, winter
queries), a window no reported figure uses.

Training sequences: reference traverse only
-------------------------------------------
With ``epochs >= 1``, ``fit`` trains the network on ``reference_scores`` alone: the front
end's scores of the reference images against the reference places,
``Z = normalise(reference_scores)``.  No query
frame is ever used.  Each batch holds ``batch_size`` sequences of ``sequence_length`` frames,
every random draw coming from ``random_state``:

1. *Trajectory.*  A speed ``v ~ U(speed_range)`` (reference places per frame) and a start
   ``s ~ U(0, n_reference - 1 - v (sequence_length - 1))`` per sequence; frame ``t`` shows
   place ``p_t = round(s + v t)`` (clipped to the traverse).  The target of frame ``t`` is
   ``p_t``.
2. *Corruption.*  ``x_t = standardise((1 - eta_t) Z[p_t] + eta_t (Z[d_t] + e_t) / sqrt(2))``
   with a noise share ``eta_t ~ U(noise)`` per frame, a Gaussian row ``e_t ~ N(0, I)`` and a
   *distractor* place ``d_t``: uniform at the first frame and, at each later frame, the previous
   one again with probability 0.5 or a fresh uniform place.  Reference rows are far cleaner than
   query rows under changed appearance (FlyNet classifies its own training images), so the
   corruption stands in for the appearance change without looking at any query.
3. *Loss.*  Cross-entropy of the output at every frame against ``p_t``, Adam with
   ``learning_rate``, gradients clipped to norm 1, every sequence from a zero hidden state.
   One epoch is ``n_reference`` sequences rounded up to whole batches.

Measured on the development window, no reference-only training improved the route prior:
one epoch at step size 1e-5 changed the mean AUC by -0.002, one at 1e-4 by -0.08, and one at
1e-3 brought it down from 0.95 to 0.23, the level of networks trained from scratch (0.18 with
:data:`FROM_SCRATCH`, at most 0.23 with ten times its training).  The
same held for sequences built from FlyNet's scores of augmented reference images and for
training the recurrent weights alone (the guide has the numbers).  Whatever the reference
traverse teaches beyond the prior is how to recognise a place from the whole pattern of its
reference row, and that pattern does not survive a change of season.  So the default is
``epochs=0``: the filter is the route prior, sized and normalised from the reference scores,
and training is there to be measured (``epochs >= 1``).  :data:`FROM_SCRATCH` restores the
earlier baseline: random initial weights, 64-frame sequences, 4 epochs at 0.003.

Running
-------
:meth:`filter` feeds a whole traverse through the network in one call from a zero hidden state;
:meth:`step` feeds one row and keeps the hidden state between calls (:meth:`reset` zeroes it).
Both give the same rows, and a frame's output depends on that frame and earlier ones only.
Running never changes the network.
"""

from __future__ import annotations

import logging
import numbers

import numpy as np

from .._torch import check_threads, torch_threads
from .._validation import (
    NotFittedError,
    check_positive_int,
    check_random_state,
    check_real,
    check_scores,
)
from . import _rnn_net as net
from .base import OnlineFilter

__all__ = ["RNNFilter", "FROM_SCRATCH"]

logger = logging.getLogger(__name__)

_CELLS = ("rnn", "gru", "lstm")
_INITS = ("route", "random")

#: parameters of the earlier baseline: random initial weights trained from scratch
FROM_SCRATCH = {
    "init": "random",
    "sequence_length": 64,
    "epochs": 4,
    "learning_rate": 0.003,
    "batch_size": 64,
}


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


class RNNFilter(OnlineFilter):
    """Recurrent network (RNN, GRU or LSTM) holding a route prior over a front end's scores.

    Parameters
    ----------
    hidden_size : int, default 512
        Recurrent units (512 in the paper).
    cell : {'rnn', 'gru', 'lstm'}, default 'rnn'
        The paper's vanilla ``tanh`` RNN, or the gated cells it also tried.
    init : {'route', 'random'}, default 'route'
        Initial weights: the route prior (module docstring), or torch's default
        distribution U(-1/sqrt(hidden_size), 1/sqrt(hidden_size)) for every weight.
    decay : float in (0, 1], default 0.98
        Route prior: the share of its belief the network keeps from one frame to the next.
    input_gain : float > 0, default 0.03
        Route prior: scale of the input weights; small keeps ``tanh`` in its linear range.
    sequence_length : int, default 32
        Frames per training sequence (gradients flow through this many steps).
    epochs : int >= 0, default 0
        Training epochs on reference sequences; one epoch is ``n_reference`` sequences.  0
        (only with ``init='route'``) keeps the route prior untouched: no training measured on
        the development window improved it (module docstring).
    learning_rate : float, default 1e-5
        Adam's step size (small: larger steps pull the prior towards the synthetic sequences).
    batch_size : int, default 32
        Sequences per gradient step.
    speed_range : float or (float, float), default (0.9, 1.1)
        Speeds (reference places per query frame) of the training sequences; the route prior
        moves its belief by the midpoint per frame.
    noise : float or (float, float), default (0.5, 1.0)
        Range of the per-frame noise share ``eta_t`` in [0, 1] of the training inputs
        (module docstring); 0 trains on clean reference rows.
    random_state : None, int or numpy.random.Generator
        Seeds the initial weights (through a ``torch.Generator`` seeded from it) and every
        draw of the training sequences.  Torch's global generator is never used.
    n_threads : int, optional
        Torch threads while fitting and filtering, capped at the machine's cores; the previous
        setting is restored afterwards.  ``None`` uses one: the recurrent steps are small
        matrix products whose thread synchronisation costs more than it saves when other
        processes share the cores.

    Attributes
    ----------
    module_ : torch.nn.ModuleDict
        ``{"recurrent": RNN/GRU/LSTM, "readout": Linear}``, the network.
    n_reference_ : int
        Places (inputs and outputs).
    log_input_ : bool
        Whether rows are log-transformed before standardisation (probability front ends).
    loss_history_ : ndarray, shape (epochs,)
        Mean training cross-entropy of each epoch.

    See Also
    --------
    FROM_SCRATCH : the parameters of the earlier, randomly initialised baseline.

    Notes
    -----
    ``fit`` needs the front end's scores of the reference images against the reference
    places; :class:`flyvpr.methods.Method` passes them because ``needs_reference_scores`` is
    True.  Query scores are only ever filtered, never learned from.

    Examples
    --------
    >>> import numpy as np
    >>> from flyvpr.temporal import RNNFilter
    >>> rng = np.random.default_rng(0)
    >>> R = np.eye(40) + 0.1 * rng.random((40, 40))  # reference scores: a clear diagonal
    >>> filt = RNNFilter(hidden_size=64).fit(R)
    >>> Q = rng.random((30, 40))
    >>> Q[np.arange(30), 5 + np.arange(30)] += 1.0  # weak evidence for places 5, 6, ...
    >>> S = filt.filter(Q)
    >>> S.shape, int(S[-1].argmax())
    ((30, 40), 34)
    """

    name = "rnn"
    requires = ("torch",)
    needs_reference_scores = True

    def __init__(
        self,
        hidden_size=512,
        cell="rnn",
        init="route",
        decay=0.98,
        input_gain=0.03,
        sequence_length=32,
        epochs=0,
        learning_rate=1e-5,
        batch_size=32,
        speed_range=(0.9, 1.1),
        noise=(0.5, 1.0),
        random_state=None,
        n_threads=None,
    ):
        self.hidden_size = hidden_size
        self.cell = cell
        self.init = init
        self.decay = decay
        self.input_gain = input_gain
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

    def _check_init(self) -> str:
        if self.init not in _INITS:
            raise ValueError(f"init must be one of {_INITS}; got {self.init!r}")
        return self.init

    def _prior(self) -> dict | None:
        """The route prior's parameters, or None for ``init='random'``."""
        if self._check_init() != "route":
            return None
        speeds = self._check_speeds()
        return {
            "decay": check_real(self.decay, "decay", high=1.0),
            "input_gain": check_real(self.input_gain, "input_gain"),
            "speed": 0.5 * (speeds[0] + speeds[1]),
        }

    def _check_speeds(self) -> tuple[float, float]:
        speeds = _check_range(self.speed_range, "speed_range", 0.0, None)
        if speeds[0] <= 0:
            raise ValueError(f"speed_range must be positive; got {self.speed_range!r}")
        return speeds

    def _threads(self) -> int:
        return check_threads(self.n_threads)

    # ----------------------------------------------------------------------------------------
    # training
    # ----------------------------------------------------------------------------------------
    def fit(self, reference_scores=None) -> RNNFilter:
        """Build the network for the reference places and train it on reference sequences.

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
            parameter has a bad value (``cell`` not one of 'rnn', 'gru', 'lstm', ``epochs=0``
            with ``init='random'``, ...).
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
        prior = self._prior()
        length = check_positive_int(self.sequence_length, "sequence_length")
        epochs = check_positive_int(self.epochs, "epochs", minimum=0)
        if epochs == 0 and prior is None:
            raise ValueError(
                "epochs=0 would leave a randomly initialised network untrained; use "
                "init='route' or epochs >= 1"
            )
        batch = check_positive_int(self.batch_size, "batch_size")
        lr = check_real(self.learning_rate, "learning_rate")
        speeds = self._check_speeds()
        noise = _check_range(self.noise, "noise", 0.0, 1.0)
        rng = check_random_state(self.random_state)
        torch = net.import_torch()
        n_threads = self._threads()

        log_input = _is_probability_matrix(R)
        Z = net.normalise(R, log_input)
        generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
        with torch_threads(torch, n_threads):
            module = net.build_module(torch, cell, n, hidden, generator, prior)
            losses = net.train(
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
            "RNNFilter (%s, %d units, init %s) trained %d epochs on %d places; losses %s",
            cell,
            hidden,
            self.init,
            epochs,
            n,
            np.round(losses, 3),
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
        torch = net.import_torch()
        x = torch.from_numpy(net.normalise(S, self.log_input_))[None]
        with torch_threads(torch, self._threads()), torch.no_grad():
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
        torch = net.import_torch()
        weights = {
            key.split(":", 1)[1]: torch.from_numpy(np.array(value))
            for key, value in state.items()
            if key.startswith("weights:")
        }
        n = int(state["n_reference_"])
        hidden = check_positive_int(self.hidden_size, "hidden_size")
        # The saved weights replace every parameter, so the prior is not rebuilt.
        module = net.build_module(torch, self._check_cell(), n, hidden, torch.Generator())
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
        two bias vectors per block included); ``neurons = h + n``.  The route prior sets
        values, not the count: every parameter stays trainable.  With FlyNet in front
        (2 layers, 64 + n neurons) and the defaults this is the paper's 4 layers, 1.3m
        parameters and 2576 neurons for n = 1000.
        """
        n = check_positive_int(n_reference, "n_reference")
        h = check_positive_int(self.hidden_size, "hidden_size")
        g = net.GATES[self._check_cell()]
        return {
            "layers": 2,
            "params": g * (h * n + h * h + 2 * h) + h * n + n,
            "neurons": h + n,
        }
