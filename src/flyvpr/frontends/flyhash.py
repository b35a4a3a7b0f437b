"""FlyHash: the FlyNet algorithm's fixed sparse binary projection and winner-take-all (FNA).

Paper, Sec. "FlyNet algorithm" (Algorithm 1): a binary sparse random matrix W
(n_hidden x m) in which every hidden unit sums a random ``sampling_ratio``
share of the m = H*W pixels; y = W x; then winner-take-all keeps the top
``wta_ratio`` share of the hidden units active (1) and silences the rest (0).
The defaults are the paper's: 2048 inputs -> 64 units, 10% sampling, 50% WTA.

Two choices the paper leaves open are fixed here and documented:

* **Exact sums.**  Inputs are quantised to integer levels (at least 8-bit
  resolution; 16-bit for the paper's 10% sampling) before the projection, so
  every unit's sum is an exact integer in float32.  Encoding is then
  bit-identical whatever the batch size or BLAS blocking, which makes the
  streaming and batch paths agree and makes ties well defined.
* **Tie rule.**  Units are ranked by their sum, highest first; equal sums are
  ranked by unit index, lowest first; the first ``k`` win.  Exactly ``k`` units
  are active in every code (the authors' ``>= k-th largest`` rule could switch
  on more).
"""

from __future__ import annotations

import numpy as np

from .._validation import (
    ArraySpec,
    ScalarSpec,
    check_fraction,
    check_memory,
    check_positive_int,
    check_random_state,
)
from .base import Encoder

__all__ = ["FlyHash", "winner_take_all", "sample_connections"]

#: largest integer that float32 represents exactly, bounds the quantisation
_F32_EXACT = 2**24
#: images per block when encoding large batches
_BLOCK = 2048


def sample_connections(n_hidden: int, n_inputs: int, n_samples: int, random_state=None):
    """Draw each hidden unit's input indices: ``n_samples`` distinct inputs per unit.

    Returns
    -------
    ndarray of int32, shape (n_hidden, n_samples)
        Sorted indices per row.
    """
    rng = check_random_state(random_state)
    if not 1 <= n_samples <= n_inputs:
        raise ValueError(f"n_samples must be in [1, {n_inputs}]; got {n_samples}")
    # An independent permutation per row: every unit gets a uniform random subset.
    perm = rng.permuted(
        np.broadcast_to(np.arange(n_inputs, dtype=np.int32), (n_hidden, n_inputs)), axis=1
    )
    return np.sort(perm[:, :n_samples], axis=1)


def winner_take_all(activations, k: int) -> np.ndarray:
    """Binary winner-take-all: exactly ``k`` ones per row.

    The ``k`` largest activations of each row win; among equal activations the
    lower column index wins.

    Parameters
    ----------
    activations : array-like, shape (N, n_hidden)
    k : int
        Number of winners, 1 <= k <= n_hidden.

    Returns
    -------
    ndarray of bool, shape (N, n_hidden)

    Examples
    --------
    >>> winner_take_all(np.array([[3.0, 1.0, 3.0, 2.0]]), 2).astype(int)
    array([[1, 0, 1, 0]])
    >>> winner_take_all(np.zeros((1, 4)), 2).astype(int)
    array([[1, 1, 0, 0]])
    """
    y = np.asarray(activations)
    if y.ndim != 2:
        raise ValueError(f"activations must have shape (N, n_hidden); got {y.shape}")
    n = y.shape[1]
    k = check_positive_int(k, "k")
    if k > n:
        raise ValueError(f"k must be <= n_hidden = {n}; got {k}")
    if k == n:
        return np.ones(y.shape, dtype=bool)
    # k-th largest value per row, then fill the remaining places among the ties
    # from the left so the count is exactly k.
    kth = np.partition(y, n - k, axis=1)[:, n - k : n - k + 1]
    above = y > kth
    tied = y == kth
    out = above | tied
    # Rows where more units tie at the k-th value than there are places left: keep the
    # leftmost ties.  They are rare, so only those rows pay for the cumulative count.
    excess = np.flatnonzero(out.sum(axis=1) > k)
    if excess.size:
        t = tied[excess]
        free = k - above[excess].sum(axis=1, keepdims=True)
        out[excess] = above[excess] | (t & (np.cumsum(t, axis=1) <= free))
    return out


class FlyHash(Encoder):
    """Fixed sparse binary projection + winner-take-all (the paper's FNA layer).

    Parameters
    ----------
    n_hidden : int, default 64
        Number of hidden units (code length).
    sampling_ratio : float, default 0.1
        Share of the inputs each unit sums: exactly ``round(sampling_ratio * m)``.
    wta_ratio : float, default 0.5
        Share of units left active: exactly ``round(wta_ratio * n_hidden)``.
    random_state : None, int or numpy.random.Generator
        Seed of the connections.

    Attributes
    ----------
    connections_ : ndarray of int32, shape (n_hidden, n_samples_)
        Input indices of each hidden unit (the non-zeros of W).
    n_inputs_, n_samples_, n_active_ : int
        m, inputs per unit, active units per code.
    reference_codes_ : ndarray of bool, shape (n_reference, n_hidden)
        Codes of the reference images, for :meth:`score`.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> fh = FlyHash(random_state=0).fit(rng.random((5, 32, 64), dtype=np.float32))
    >>> fh.encode(rng.random((3, 32, 64), dtype=np.float32)).sum(axis=1)
    array([32, 32, 32])
    """

    name = "flyhash"
    #: its 64-bit code of a 32x64 image stays the same over frames that differ by sensor noise
    #: (on Nordland 0-999, 81 winter frames where the train stood repeat the last one's scores)
    repeats_on_noise = True

    def __init__(self, n_hidden=64, sampling_ratio=0.1, wta_ratio=0.5, random_state=None):
        self.n_hidden = n_hidden
        self.sampling_ratio = sampling_ratio
        self.wta_ratio = wta_ratio
        self.random_state = random_state

    # -- set-up ---------------------------------------------------------------
    def _build(self, n_inputs: int, rng) -> None:
        """Draw the connections for ``n_inputs`` inputs (no reference images needed)."""
        n_hidden = check_positive_int(self.n_hidden, "n_hidden")
        sampling = check_fraction(self.sampling_ratio, "sampling_ratio")
        wta = check_fraction(self.wta_ratio, "wta_ratio")
        # dense projection (float32) and the permuted index table drawn per unit (int32, x2)
        check_memory(
            12 * n_hidden * int(n_inputs), f"n_hidden={n_hidden} with {n_inputs} inputs per image"
        )
        self.n_inputs_ = int(n_inputs)
        self.n_samples_ = max(1, int(round(sampling * n_inputs)))
        self.n_active_ = min(n_hidden, max(1, int(round(wta * n_hidden))))
        self.connections_ = sample_connections(n_hidden, n_inputs, self.n_samples_, rng)
        self._prepare()

    def _prepare(self) -> None:
        """Derive the dense projection and quantisation used for fast encoding."""
        n_hidden = self.connections_.shape[0]
        proj = np.zeros((self.n_inputs_, n_hidden), dtype=np.float32)
        proj[self.connections_, np.arange(n_hidden)[:, None]] = 1.0
        self._projection = proj
        self._levels = float(min(65535, _F32_EXACT // self.n_samples_))

    def _fit(self, images: np.ndarray) -> None:
        self._build(images.shape[1] * images.shape[2], check_random_state(self.random_state))
        self.reference_codes_ = self._encode(images)

    # -- encoding -------------------------------------------------------------
    def activations(self, images) -> np.ndarray:
        """Hidden-unit sums y = W x of quantised inputs, shape (N, n_hidden), float32.

        Each value is ``levels`` times the sum of the unit's pixels (an exact integer).
        """
        self._check_fitted()
        x = np.asarray(images, dtype=np.float32).reshape(len(images), -1)
        out = np.empty((len(x), self.connections_.shape[0]), dtype=np.float32)
        buf = np.empty((min(len(x), _BLOCK), x.shape[1]), dtype=np.float32)
        levels = np.float32(self._levels)
        # Blocks of a few thousand images keep the quantised copy in cache and bound memory.
        for start in range(0, len(x), _BLOCK):
            chunk = x[start : start + _BLOCK]
            q = buf[: len(chunk)]
            np.multiply(chunk, levels, out=q)
            np.rint(q, out=q)
            np.matmul(q, self._projection, out=out[start : start + len(chunk)])
        return out

    def _encode(self, images: np.ndarray) -> np.ndarray:
        return winner_take_all(self.activations(images), self.n_active_)

    def _score(self, codes: np.ndarray) -> np.ndarray:
        codes = _check_codes(codes, self.connections_.shape[0])
        # Shared active units / k: 1 for identical codes, and a monotone function
        # of the Hamming distance since every code has exactly k ones.
        overlap = codes.astype(np.float32) @ self.reference_codes_.T.astype(np.float32)
        return overlap / np.float32(self.n_active_)

    # -- saved state: 1 bit per connection weight and per code bit --------------
    _state_names = ("n_inputs_", "n_samples_", "n_active_")
    _state_scalars = {
        **Encoder._state_scalars,
        "n_inputs_": ScalarSpec("int", low=1),
        "n_samples_": ScalarSpec("int", low=1),
        "n_active_": ScalarSpec("int", low=1),
    }

    def _state_arrays(self, scalars: dict) -> dict:
        n_hidden = check_positive_int(self.n_hidden, "n_hidden")
        h, w = scalars["image_shape_"]
        n_inputs = scalars["n_inputs_"]
        if n_inputs != h * w:
            raise ValueError(f"n_inputs_ must be H*W = {h * w}; got {n_inputs}")
        if scalars["n_samples_"] > n_inputs or scalars["n_active_"] > n_hidden:
            raise ValueError(
                f"n_samples_ ({scalars['n_samples_']}) must be <= n_inputs_ ({n_inputs}) and "
                f"n_active_ ({scalars['n_active_']}) <= n_hidden ({n_hidden})"
            )
        n_reference = scalars["n_reference_"]
        return {
            "connections_bits": ArraySpec("uint8", (n_hidden, -(-n_inputs // 8))),
            "reference_codes_bits": ArraySpec("uint8", (n_reference, -(-n_hidden // 8))),
        }

    def _get_state(self) -> dict:
        state = super()._get_state()
        state["connections_bits"] = self.packed_connections()
        state["reference_codes_bits"] = np.packbits(self.reference_codes_, axis=1)
        return state

    def _set_state(self, state: dict) -> None:
        state = dict(state)
        bits = state.pop("connections_bits")
        codes = state.pop("reference_codes_bits")
        super()._set_state(state)
        n_hidden = bits.shape[0]
        dense = np.unpackbits(bits, axis=1, count=self.n_inputs_).astype(bool)
        rows, cols = np.nonzero(dense)
        if not np.all(np.bincount(rows, minlength=n_hidden) == self.n_samples_):
            raise ValueError("saved FlyHash connections do not have n_samples_ inputs per unit")
        self.connections_ = cols.reshape(n_hidden, self.n_samples_).astype(np.int32)
        self.reference_codes_ = np.unpackbits(codes, axis=1, count=n_hidden).astype(bool)
        self._prepare()

    # -- size -----------------------------------------------------------------
    def packed_connections(self) -> np.ndarray:
        """The binary matrix W (n_hidden x m) bit-packed row-wise: 1 bit per weight."""
        self._check_fitted()
        dense = np.zeros((self.connections_.shape[0], self.n_inputs_), dtype=bool)
        dense[np.arange(dense.shape[0])[:, None], self.connections_] = True
        return np.packbits(dense, axis=1)

    def _map_nbytes(self) -> int:
        # One binary code per place, bit-packed as in a model file: ceil(n_hidden / 8) bytes
        # (8 for 64 units).  The codes are kept unpacked (one byte per bit) in memory for the
        # overlap product; the connections are shared by all places and not counted.
        n_reference, n_hidden = self.reference_codes_.shape
        return n_reference * ((n_hidden + 7) // 8)

    def _footprint(self) -> dict:
        return {
            "layers": 1,
            "params": 0,  # nothing is trained
            "neurons": int(self.connections_.shape[0]),
            "fixed_connections": int(self.connections_.size),
            "bytes_packed": int(self.packed_connections().nbytes),
        }


def _check_codes(codes: np.ndarray, n_hidden: int) -> np.ndarray:
    if codes.ndim != 2 or codes.shape[1] != n_hidden:
        raise ValueError(f"codes must have shape (N, {n_hidden}); got {codes.shape}")
    return codes
