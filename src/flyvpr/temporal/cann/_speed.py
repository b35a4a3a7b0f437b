"""The CANN's online speed estimate: a bank of evidence traces, one per candidate speed.

Row ``j`` of the bank holds the evidence along constant-velocity lines of slope
``velocities[j]`` (each row is shifted by its own velocity).  Each frame, the candidate whose
best line stands out most from its own spread, ``(max - mean) / std`` over places, gets a
vote if that contrast reaches ``velocity_contrast``; votes decay over ``velocity_memory``
frames, and the candidate with most votes is the estimate.  See "Shift and copy" in the user
guide's page on the paper's CANN (``docs/guide/cann-paper.md``).
"""

from __future__ import annotations

import numpy as np

from ._kernels import evidence_stats as plain_evidence_stats

#: bank rows whose contrasts tie within this (relative) tolerance give the vote to the
#: candidate nearest 1 place per frame
TIE_TOLERANCE = 1e-5


def tie_winner(values: list, preference: list) -> int:
    """The first index in ``preference`` whose value is within rounding of the highest.

    Within rounding: at least the highest minus ``TIE_TOLERANCE`` times the largest magnitude
    among the values (and at least ``TIE_TOLERANCE`` itself).
    """
    highest = max(values)
    level = highest - TIE_TOLERANCE * max(1.0, highest, -min(values))
    return next(j for j in preference if values[j] >= level)


class SpeedBank:
    """Evidence traces per candidate velocity and the votes between them.

    Parameters
    ----------
    velocities : ndarray of float64, shape (n_v,)
    n_currents, n : int
        Synaptic currents and places.
    keeps, coefs : ndarray of float32, shape (n_currents,)
        Per frame, current ``c`` decays by ``keeps[c]`` and adds ``coefs[c]`` times the input.
    memory, min_contrast : float
        ``velocity_memory`` and ``velocity_contrast``.
    stride : int
        The spread of each row is estimated on every ``stride``-th place.
    noise : float
        Rows whose spread is at most this (rounding residue) do not vote.
    """

    def __init__(
        self, velocities, n_currents, n, keeps, coefs, memory, min_contrast, stride, noise
    ):
        self.velocities = velocities
        self.traces = np.zeros((n_currents, velocities.size, n), np.float32)
        self._spare = np.empty_like(self.traces)
        self._sum = np.empty(self.traces.shape[1:], np.float32) if n_currents > 1 else None
        self._stats = np.zeros((2, velocities.size))  # each row's sampled mean and spread
        self._rows = np.arange(velocities.size)
        self.offsets = np.zeros(velocities.size)  # fractional movement not yet applied
        self.votes = np.zeros(velocities.size)
        self.keeps, self.coefs = keeps, coefs
        self.decay = -np.expm1(-1.0 / memory)
        self.min_contrast = min_contrast
        self.stride = stride
        self.noise = noise
        # Candidates nearest 1 place per frame first (then by index): the order in which ties
        # in the vote are broken; before any vote, the nearest to 1 leads.
        self.preference = sorted(
            range(velocities.size), key=lambda j: (abs(velocities[j] - 1.0), j)
        )
        self.votes[self.preference[0]] = 1e-6
        self.index = self.preference[0]
        self.contrast = np.zeros(velocities.size)

    @property
    def estimate(self) -> float:
        """The estimated movement, places per frame."""
        return float(self.velocities[self.index])

    def shifts(self, first: bool) -> np.ndarray:
        """Whole places each row moves this frame (fractions accumulate, halves round up)."""
        if first:  # the first frame has nothing to move
            return np.zeros(self.velocities.size, np.int64)
        total = self.offsets + self.velocities
        rounded = np.floor(total + 0.5)
        self.offsets = total - rounded
        return rounded.astype(np.int64)

    def update(self, x, first: bool, update_traces, evidence_stats=None) -> None:
        """Move, decay and feed every row with the input ``x``; then vote.

        ``update_traces`` and ``evidence_stats`` are the kernels of that name (the latter, by
        default, the plain one).
        """
        update_traces(self.traces, self._spare, self.shifts(first), self.keeps, self.coefs, x)
        self.traces, self._spare = self._spare, self.traces
        # With one current the evidence is that current's traces.
        self.evidence = self.traces[0] if self._sum is None else self._sum
        # Each row's mean and spread over the sampled places, its peak and its maximum.
        centre, spread = self._stats
        (evidence_stats or plain_evidence_stats)(
            self.traces, self.evidence, self.stride, centre, spread
        )
        self.peaks = self.evidence.argmax(axis=1)
        top = self.evidence[self._rows, self.peaks]
        # Comparing raw maxima would favour slow lines, which count the similar-looking
        # consecutive frames of one place more than once: each row against its own spread.
        self.contrast = (top - centre) / np.maximum(spread, 1e-12)
        self.votes *= 1.0 - self.decay
        # Rows holding the same values in other places (early on, or along a blank stretch)
        # tie up to rounding; such ties go to the candidate nearest 1 place per frame, so the
        # vote does not depend on the order of a floating-point sum.
        best = tie_winner(self.contrast.tolist(), self.preference)
        # Rows whose spread is at rounding level (identical frames, which adaptation turns
        # into rounding residue) carry no evidence and do not vote.
        if spread[best] > self.noise and self.contrast[best] >= self.min_contrast:
            self.votes[best] += self.decay
        self.index = int(np.argmax(self.votes))
