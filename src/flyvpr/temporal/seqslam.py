"""SeqSLAM sequence matching as a temporal filter over a score matrix.

SeqSLAM (Milford & Wyeth, ICRA 2012; defaults of their OpenSeqSLAM release) turns single-frame
scores into sequence scores in two steps:

1. *Local contrast enhancement.*  Each difference ``D = -S`` is normalised by the mean and
   standard deviation of the differences of the same query to the nearby reference places
   (a window of ``enhance_window // 2`` places on each side, cut at the ends of the traverse),
   so a place is judged against its neighbourhood rather than the whole route.
2. *Constant-velocity sequence search.*  For every reference place ``r`` and every velocity
   ``v`` (reference places per query frame) on the grid ``v_min, v_min + v_step, ..., v_max``,
   the enhanced differences are summed along the straight line through the query frames of
   the window that passes place ``r`` at the current query frame; the place's score is the
   best (lowest) line.

The paper compares FlyNet+CANN with SeqSLAM run with the OpenSeqSLAM defaults and a sequence
length of 20 (Sec. "Compared systems" in PAPER-NOTES); the paper's FlyNet+SeqSLAM baseline runs
the same filter on FlyNet's scores.

Conventions and where they differ from OpenSeqSLAM
--------------------------------------------------
- Window.  ``mode="causal"`` (default) uses the current query frame and the
  ``sequence_length - 1`` frames before it, so the filter can run online (:meth:`SeqSLAM.step`).
  ``mode="centered"`` uses ``sequence_length // 2`` frames before and
  ``sequence_length - 1 - sequence_length // 2`` after the current one, as OpenSeqSLAM (which
  looks ``ds/2`` frames back and forward); it needs future frames and cannot run online.
- Trajectories.  At query offset ``j`` from the current frame (``j < 0`` in the past) a line
  with velocity ``v`` through place ``r`` reads place ``r + round(v * j)``, rounded to the
  nearest integer with halves away from zero.  Velocities whose lines coincide are searched
  once.  The velocity grid is ``v_min:v_step:v_max`` (5 velocities by default).  OpenSeqSLAM
  instead spans ``ds + 1`` frames, rounds the offsets down from the line's first frame, and
  checks the velocities ``(vmin * ds : vmax * ds) / ds`` (9 for ``ds = 20``), ignoring its
  ``vskip``.
- Missing frames count as no evidence.  A line's frame can be missing in two ways: the
  place it reads lies outside the reference traverse (the line runs off either end of the
  map), or the query frame itself does not exist (the first ``sequence_length - 1`` queries in
  causal mode; both ends of the query traverse in centred mode).  Either way the term adds 0,
  the expected contrast-enhanced difference where nothing matches, and every line's sum is
  divided by the same ``sqrt(n_frames)`` (``n_frames = sequence_length``).  So every line in
  every row is judged on the same scale: a line clipped at an end of the route, or a row with
  little history, can only win on the evidence it has, never by having fewer terms.  Where
  nothing matches, each term is roughly a zero-mean, unit-variance z-score, so a full line's
  ``sum / sqrt(n_frames)`` has unit spread and a clipped line's less: its best line is less
  extreme by chance, and a true match's confidence grows with the frames that support it.
  The rows at the start of a traverse therefore get lower confidences, as they hold less
  evidence.  Earlier versions read the first (or last) place instead of a place outside the
  traverse ("the vehicle waited at the end of the map") and divided each row by the square
  root of its own number of frames.  Waiting at the end is a line of velocity 0, outside the
  searched range: a place at the start of the route that scores well against every query (a
  "hub") then won every row whose lines reached back past the start; FlyNet + SeqSLAM on
  Nordland summer -> winter, frames 300-499, seed 1, predicted the window's first place for
  84% of the frames (AUC 0.007).  With missing terms as no evidence: AUC 0.81, at most 4% of
  the frames on one place (seeds 0-9: AUC 0.68-0.83, at most 5%); pixels + SeqSLAM on frames
  0-999 / 1000-1999 (tolerance 20): 0.878 / 0.955, was 0.878 / 0.948.  OpenSeqSLAM gives
  lines that run past the last place infinite cost and reports a line's first place plus
  ``ds/2``, so places near either end of the traverse can never be matched.
- Output.  ``S' = -(best sum / sqrt(n_frames))``, so higher = better, as every score matrix in
  flyvpr.  OpenSeqSLAM reports a ratio of the best to the second-best score outside a window
  instead; that ratio is a confidence, not a per-place score.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.ndimage import uniform_filter1d

from .._validation import check_memory, check_positive_int, check_real
from .base import OnlineFilter

__all__ = ["SeqSLAM", "enhance_contrast"]

_MODES = ("causal", "centered")
#: A window whose standard deviation is below this fraction of the row's spread is flat: its
#: "contrast" is rounding noise of the running window sums, so it becomes 0, not amplified.
_FLAT_RELATIVE_STD = 1e-6


def enhance_contrast(D, window: int = 10) -> np.ndarray:
    """OpenSeqSLAM's local contrast enhancement along the reference axis.

    ``D'[q, i] = (D[q, i] - mean(D[q, lo:hi])) / std(D[q, lo:hi])`` with
    ``lo = max(0, i - window // 2)`` and ``hi = min(n_reference, i + window // 2 + 1)``; the
    standard deviation uses ``ddof=1`` (MATLAB's ``std``, as OpenSeqSLAM).  Windows whose
    values are all equal (up to rounding) give 0.

    Parameters
    ----------
    D : array-like, shape (n_query, n_reference)
        Differences (lower = more similar) or any matrix to enhance row by row.
    window : int, default 10
        Window width; ``window // 2`` places on each side of the centre (11 places for 10).

    Returns
    -------
    ndarray of float64, shape (n_query, n_reference)

    Raises
    ------
    ValueError
        If ``window`` is below 2 or ``D`` is not a 2-d array.

    Examples
    --------
    >>> enhance_contrast([[0.0, 1.0, 2.0, 3.0]], window=2).round(3)
    array([[-0.707,  0.   ,  0.   ,  0.707]])
    """
    window = check_positive_int(window, "window", minimum=2)
    D = np.asarray(D, dtype=np.float64)
    if D.ndim != 2:
        raise ValueError(f"D must have shape (n_query, n_reference); got shape {D.shape}")
    n_reference = D.shape[1]
    half = window // 2
    size = 2 * half + 1
    # Centring each row first keeps the window sums small, so the variance computed from them
    # does not lose its digits to cancellation.
    x = D - D.mean(axis=1, keepdims=True)
    # Zero padding plus the true count of each (cut) window gives the cut windows' sums.
    total = uniform_filter1d(x, size, axis=1, mode="constant", cval=0.0) * size
    total_sq = uniform_filter1d(x * x, size, axis=1, mode="constant", cval=0.0) * size
    centre = np.arange(n_reference)
    count = (np.minimum(centre + half + 1, n_reference) - np.maximum(centre - half, 0)).astype(
        np.float64
    )
    mean = total / count
    denom = np.maximum(count - 1.0, 1.0)  # a 1-place window only occurs for n_reference == 1
    std = np.sqrt(np.maximum(total_sq - total * mean, 0.0) / denom)
    spread = np.abs(x).max(axis=1, keepdims=True)
    flat = std <= _FLAT_RELATIVE_STD * spread
    return np.where(flat, 0.0, (x - mean) / np.where(flat, 1.0, std))


#: place shifts are capped at this size: a line that far off the route reads nothing, as any
#: farther one (and huge velocities, such as 1e308 x 19, fit int64 and stay finite)
_MAX_SHIFT = 2.0**62


def _round_half_away(x: np.ndarray) -> np.ndarray:
    # The small nudge makes products such as 0.9 * 5 = 4.5000000000000004 or 1.5 * 3 = 4.5
    # round the same way whatever their last bit.
    rounded = np.sign(x) * np.floor(np.abs(x) + 0.5 + 1e-9)
    return np.clip(rounded, -_MAX_SHIFT, _MAX_SHIFT).astype(np.int64)


def _add_shifted(acc: np.ndarray, src: np.ndarray, shift: int) -> None:
    """``acc[:, r] += src[:, r + shift]`` where ``0 <= r + shift < n``; other columns unchanged.

    A line's frame whose place lies outside the reference traverse adds nothing (see "Places
    outside the reference traverse" in the module docstring).  Slices, no gather.
    """
    n = acc.shape[1]
    if shift >= n or shift <= -n:
        return
    if shift >= 0:
        acc[:, : n - shift] += src[:, shift:]
    else:
        acc[:, -shift:] += src[:, : n + shift]


class SeqSLAM(OnlineFilter):
    """SeqSLAM sequence matching (Milford & Wyeth 2012, OpenSeqSLAM defaults) over a score matrix.

    See the module docstring for the algorithm and how it differs from OpenSeqSLAM.

    Parameters
    ----------
    sequence_length : int, default 20
        Number of query frames a line spans (OpenSeqSLAM's ``ds``; the paper uses 20).
    v_min, v_max : float, default 0.8, 1.2
        Range of velocities searched, in reference places per query frame (OpenSeqSLAM's
        range).  ``v_min=0.75, v_max=2.0, v_step=0.125`` searches the same speeds as the
        paper's CANN's default velocity bank (:class:`~flyvpr.temporal.cann.AttractorCANN`),
        for comparisons where the query moves faster than the reference; the place-velocity
        CANN (:class:`~flyvpr.temporal.cann.CANN`) follows 0 to 3.5 places per frame.
    v_step : float, default 0.1
        Spacing of the velocity grid; ``v_max`` is included when it lies on the grid.
    enhance_window : int, default 10
        Width of the contrast-enhancement window along the reference axis (``window // 2``
        places on each side).
    mode : {"causal", "centered"}, default "causal"
        ``"causal"``: the line ends at the current query frame (online, :meth:`step` works).
        ``"centered"``: the line is centred on it, as OpenSeqSLAM (needs future frames).

    Notes
    -----
    ``filter(S)`` returns ``S'[q, r]`` = minus the lowest sum of contrast-enhanced differences
    along any searched line through place ``r`` at query ``q``, divided by
    ``sqrt(sequence_length)``; frames of the line that lie before the first query, after the
    last one or off either end of the reference traverse add 0 (no evidence).  Higher =
    better, same shape as ``S``.  The enhancement works
    on each query row alone, so the causal filter only ever reads the current and past rows,
    and ``step`` (one row at a time, with a buffer of the last ``sequence_length`` enhanced
    rows) returns exactly the rows of ``filter``.  Cost: about
    ``n_velocities * sequence_length`` passes over the matrix; nothing loops over places.
    Nothing is learned: the footprint is zero.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> S = rng.normal(size=(60, 80))
    >>> S[np.arange(60), np.arange(60) + 10] += 1.0  # a weak diagonal of true matches
    >>> out = SeqSLAM().filter(S)
    >>> out.shape
    (60, 80)
    >>> float(np.mean(out.argmax(axis=1) == np.arange(60) + 10)) > 0.9
    True
    """

    name = "seqslam"

    def __init__(
        self,
        sequence_length: int = 20,
        v_min: float = 0.8,
        v_max: float = 1.2,
        v_step: float = 0.1,
        enhance_window: int = 10,
        mode: str = "causal",
    ):
        self.sequence_length = sequence_length
        self.v_min = v_min
        self.v_max = v_max
        self.v_step = v_step
        self.enhance_window = enhance_window
        self.mode = mode

    # -- parameters -----------------------------------------------------------
    def _check_params(self) -> None:
        check_positive_int(self.sequence_length, "sequence_length")
        check_positive_int(self.enhance_window, "enhance_window", minimum=2)
        for name in ("v_min", "v_max", "v_step"):
            check_real(getattr(self, name), name, low=None)
        if self.v_step <= 0:
            raise ValueError(f"v_step must be > 0; got {self.v_step}")
        if self.v_min > self.v_max:
            raise ValueError(f"v_min must be <= v_max; got v_min={self.v_min}, v_max={self.v_max}")
        if self.mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}; got {self.mode!r}")

    def velocities(self) -> np.ndarray:
        """The velocity grid searched: ``v_min, v_min + v_step, ..., <= v_max``.

        Raises
        ------
        ValueError, TypeError
            For invalid parameters (each message names the parameter).
        """
        self._check_params()
        with np.errstate(over="ignore"):
            span = np.floor((float(self.v_max) - float(self.v_min)) / float(self.v_step) + 1e-9)
        if not np.isfinite(span):
            raise ValueError(
                f"v_min={self.v_min:g} to v_max={self.v_max:g} in steps of v_step="
                f"{self.v_step:g} are more velocities than can be counted; expected a grid "
                "of a few velocities (by default 5: 0.8 to 1.2 in steps of 0.1)"
            )
        n_steps = int(span)
        # The grid and the table of line shifts (velocities x sequence_length int64), refused
        # before they are allocated.
        check_memory(
            8 * (n_steps + 1) * (2 + 2 * self.sequence_length),
            f"v_step={self.v_step:g} ({n_steps + 1} velocities from v_min={self.v_min:g} to "
            f"v_max={self.v_max:g}) with sequence_length={self.sequence_length}",
        )
        return self.v_min + self.v_step * np.arange(n_steps + 1)

    def _offsets(self) -> np.ndarray:
        """Query offsets of a line's frames relative to the current frame, current first."""
        length = self.sequence_length
        if self.mode == "causal":
            return -np.arange(length)
        back = length // 2
        forward = length - 1 - back
        # Current frame first, then outwards: the summation order is the same in every row.
        order = np.argsort(np.abs(np.arange(-back, forward + 1)), kind="stable")
        return np.arange(-back, forward + 1)[order]

    def _shift_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets (n_offsets,), place shifts (n_lines, n_offsets)) with duplicate lines removed.

        Cached per parameter set, because :meth:`step` needs it at every frame.
        """
        key = tuple(self.get_params().values())
        cached = getattr(self, "_table_cache", None)
        if cached is None or cached[0] != key:
            velocities = self.velocities()  # first: it refuses grids too large for memory
            offsets = self._offsets()
            with np.errstate(over="ignore"):  # inf: off the route, capped at _MAX_SHIFT
                shifts = _round_half_away(np.outer(velocities, offsets))
            cached = (key, (offsets, np.unique(shifts, axis=0)))
            self._table_cache = cached
        return cached[1]

    # -- whole matrix ---------------------------------------------------------
    def _filter(self, S: np.ndarray) -> np.ndarray:
        self._check_params()
        offsets, shifts = self._shift_table()
        n_query = S.shape[0]
        enhanced = enhance_contrast(-S, self.enhance_window).astype(S.dtype)
        best = None
        acc = np.empty_like(enhanced)
        for line in shifts:
            acc.fill(0)
            for j, shift in zip(offsets, line, strict=True):
                # Rows t whose frame t + j exists read row t + j of the enhanced matrix.
                t0, t1 = max(0, -j), n_query - max(0, j)
                if t0 < t1:
                    _add_shifted(acc[t0:t1], enhanced[t0 + j : t1 + j], int(shift))
            best = acc.copy() if best is None else np.minimum(best, acc, out=best)
        assert best is not None  # the table has at least one line
        best *= -self._scale(S.dtype)
        return best

    def _scale(self, dtype) -> np.floating:
        """``1 / sqrt(frames per line)``: the same for every line, row and place."""
        return np.dtype(dtype).type(1.0 / np.sqrt(len(self._offsets())))

    # -- online ---------------------------------------------------------------
    def reset(self) -> None:
        """Forget all past frames (call before a new query traverse)."""
        # The table of lines first: it refuses grids and lengths too large for memory, so the
        # buffer's length fits (deque takes a Python int, not numpy's, and at most 2**63 - 1).
        self._shift_table()
        self._buffer: deque[np.ndarray] = deque(maxlen=int(self.sequence_length))

    def _step(self, row: np.ndarray) -> np.ndarray:
        self._check_params()
        if self.mode != "causal":
            raise ValueError(
                f"step needs mode='causal': mode={self.mode!r} looks at future frames; "
                "use filter(S) on the whole traverse instead"
            )
        buffer = getattr(self, "_buffer", None)
        if buffer is None or buffer.maxlen != self.sequence_length:
            self.reset()  # first step, or sequence_length changed through set_params
            buffer = self._buffer
        if buffer and buffer[-1].shape[1] != row.shape[0]:
            raise ValueError(
                f"scores_row must have shape ({buffer[-1].shape[1]},) as the previous rows; "
                f"got {row.shape} (call reset() before a new reference traverse)"
            )
        dtype = np.float32 if row.dtype == np.float32 else np.float64
        if not buffer:
            # The buffer will hold sequence_length enhanced rows.
            check_memory(
                self.sequence_length * row.shape[0] * np.dtype(dtype).itemsize,
                f"sequence_length={self.sequence_length} buffered rows of {row.shape[0]} places",
            )
        buffer.append(enhance_contrast(-row[None, :], self.enhance_window).astype(dtype))
        offsets, shifts = self._shift_table()
        n_frames = len(buffer)
        acc = np.empty_like(buffer[-1])
        best = None
        for line in shifts:
            acc.fill(0)
            for j, shift in zip(offsets[:n_frames], line[:n_frames], strict=True):
                _add_shifted(acc, buffer[n_frames - 1 + j], int(shift))
            best = acc.copy() if best is None else np.minimum(best, acc, out=best)
        assert best is not None  # the table has at least one line
        best *= -self._scale(dtype)
        return best[0]
