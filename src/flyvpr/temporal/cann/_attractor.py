"""The paper's CANN: an attractor network over the places (the ``cann-paper`` filter).

The paper's architecture for reproducing it (``flynet+cann-paper``), with flyvpr's own
parameters where the paper gives none (see ``docs/guide/cann-paper.md``); the default ``cann``
filter is :class:`~flyvpr.temporal.cann.CANN`, the place-velocity layer.
"""

from __future__ import annotations

import math

import numpy as np

from ..._validation import check_memory, check_positive_int
from . import _kernels, _readout
from ._input import TINY as _TINY
from ._input import OdometryFilter, begin_frame, normalised_input
from ._kernels import excitation_kernel
from ._params import DEFAULT_VELOCITIES, check_params
from ._speed import SpeedBank

#: about this many places estimate the evidence's mean and spread
_STATS_SAMPLES = 4096


class AttractorCANN(OdometryFilter):
    """The paper's 1-d continuous attractor network (FlyNet+CANN's architecture).

    The equations, the readout and how the defaults were chosen are on the user guide's CANN
    page (``docs/guide/cann-paper.md``).  All times are in frame periods, all distances in
    reference places.  A row of :meth:`step` or :meth:`filter` is the readout: higher = more
    likely place, and its maximum the confidence (see "Output" on the guide page): 0 without
    an answer, below 1 a tentative one, 1 to 2 the front end's while the sequence is lost,
    2 + the packet's evidence contrast otherwise.  Odometry (``velocity``) overrides
    ``movement`` for its frame.

    Parameters
    ----------
    excitation_strength : float, default 15.0
        ``A``: total weight of a place unit's recurrent excitation onto itself and its
        neighbours (the Gaussian kernel's weights sum to about ``A``).
    excitation_width : float, default 1.0
        Standard deviation of the Gaussian excitation, in places (the demo's width).
    inhibition : float, default 3.2
        Weight of the global inhibitor onto every place unit (the inhibitor reads the place
        units with weight 1).  Between the values where a packet dies on its own and where two
        unsupported packets coexist.
    tonic_inhibition : float, default 1.0
        The inhibitor's minimum (tonic) rate, in units of one fully active place unit.
    threshold : float, default 1.0
        Potential above which a place unit fires (its rate is ``u - threshold``, at most 1).
    time_constant : float, default 1.0
        Time constant of the place units' potentials, in frames.
    synaptic_time_constant : float, default 25.0
        Time constant of the input synapses, in frames: how long evidence for a place is
        remembered (the CANN's counterpart of SeqSLAM's sequence length).  With
        ``slow_time_constant`` set, the fast current's.
    slow_time_constant : float or None, default None
        Time constant, in frames, of a second, slow synaptic current driven by the same input;
        ``None``: a single current.
    slow_fraction : float, default 0.5
        Weight of the slow current in the evidence (the fast one gets ``1 - slow_fraction``);
        only used with ``slow_time_constant``.
    input_gain : float, default 10.0
        Gain from the normalised input (z-scores) to the synaptic current.
    n_steps : int, default 3
        Euler integration steps per frame; ``n_steps * time_constant`` must be >= 1.
    movement : float or "estimate", default "estimate"
        Places moved per frame when :meth:`step` gets no ``velocity``: a number (for
        frame-aligned traverses, 1.0) or ``"estimate"`` to estimate it online from the data.
    velocities : sequence of float, default 0.75, 0.875, ..., 2.0 (steps of 1/8)
        Candidate movements per frame for ``movement="estimate"``; the estimate is always one
        of them.  Before any vote the candidate nearest 1 is used.
    bidirectional : bool, default False
        With ``movement="estimate"``, also try each velocity's negative, so that a query
        traverse driven the other way along the route (places in decreasing order) is
        followed too; doubles the bank.  Off by default: the CANN assumes forward motion.
    velocity_memory : float, default 100.0
        Time constant, in frames, of the votes that choose the estimated velocity.
    velocity_contrast : float, default 4.0
        A frame votes only if its best line's ``(max - mean) / std`` reaches this.
    adaptation : float or None, default 50.0
        Time constant, in frames, of each place's input adaptation (subtraction of its running
        mean input); ``None`` switches adaptation off.
    adapt_variance : bool, default True
        Also divide each place's input by the square root of its running variance (see
        "Input" on the guide page); needs ``adaptation``.
    input_transform : {"auto", "log", "linear"}, default "auto"
        How a score row becomes the input before its z-score; ``"log"`` needs non-negative
        scores.
    input_clip : float or None, default 4.0
        Bound on the normalised input, in standard deviations; ``None``: no bound.
    relocation_floor : float, default 5.5
        Evidence (in units of ``s``) that a place must exceed before the packet can be
        relocated there (see "Relocation" on the guide page).
    relocation_margin : float or None, default 0.5
        Lead of that place's evidence over the packet's own evidence (in units of ``s``) at
        which the packet is relocated there; ``None`` switches relocation off.
    fallback_contrast : float or None, default 2.5
        Support (the packet's evidence contrast averaged over recent frames, in standard
        deviations) below which the sequence counts as lost and the front end answers (see
        "Output" on the guide page); ``None``: the packet always answers.
    fallback_memory : float, default 200.0
        Frames over which the support is averaged; the first half as many frames give
        tentative answers.

    Attributes
    ----------
    velocity_ : float
        Movement applied at the last step (places per frame; NaN before the first step).
    n_frames_ : int
        Frames seen since the last :meth:`reset`.
    n_relocations_ : int
        Relocations since the last :meth:`reset`.
    confidence_ : float
        Confidence of the last step's answer, the maximum of the row it returned (see
        "Output" on the guide page); exactly 0 without a packet.
    contrast_ : float
        The packet's evidence contrast at the last step; 0 without a packet.
    support_ : float
        The packet's evidence contrast averaged over recent frames.
    potentials_ : ndarray of float32, shape (n_reference,)
        The place units' potentials after the last step (a copy).
    compiled_ : bool
        Whether the per-frame updates run compiled by numba (the default) or uncompiled
        (``_kernels.USE_NUMBA = False``, for tests: much slower); the results agree up to
        float rounding.

    Notes
    -----
    Defaults.  Tuned on FlyNet scores (``FlyNet(random_state=seed)``, seeds 0-4) of Nordland
    summer (reference) -> winter (query) at 64 x 32, frame-aligned, windows of frames 0-999 and
    1000-1999, ground truth within 20 frames, at 1x, 2x and a random 1-1.5x speed, and on a
    query stream that jumps 200 places; the attractor properties above were required of every
    candidate; the 100-place summer -> winter subset (tolerance 2) served as a check.  A wide
    range of nearby values does as well.  Measured there (PR AUC, mean over seeds, windows
    0-999 / 1000-1999): 0.89 / 0.98 at 1x (FlyNet alone 0.02, FlyNet + SeqSLAM 0.57 and
    0.62), 0.82 / 0.95 at the random 1-1.5x speed, 0.91 / 0.97 at 2x; the same defaults on
    pixel (SAD) scores give 0.98 / 0.995 (pixels + SeqSLAM 0.88 / 0.95).  After a jump of 200
    places (the kidnap of ``benchmarks/accuracy.py``, 35 jumps per window) the argmax is first
    back within 20 places after a median of 20 / 14 frames (at most 59 / 27); without
    relocation 32 / 24 (at most 74 / 60), with 1x AUC 0.91 / 0.97.  The slowest jumps land
    where FlyNet's scores hold almost no evidence for the true place for 40-60 frames.

    The readout's fallback (``fallback_*``) was chosen on the same scores with the queries of
    window 0-999 shuffled (``numpy.random.default_rng(0).permutation(1000)``), tolerance 20:
    PR AUC of pixels + CANN 0.091 against 0.003 without the fallback (pixels alone 0.108),
    FlyNet + CANN 0.021 against 0.002 (FlyNet alone 0.022, means over seeds 0-4), while the
    in-order numbers at 1x, 1.5x, 2x and 1-1.5x stay within 0.001 or improve.  The first
    ``fallback_memory / 2`` frames of a shuffled stream are tentative answers, which is most of
    what is left of the gap.

    Differences from the authors' demo: the route is a line, not a ring; rates saturate at 1
    (the demo clips at 100); the input drives a slow synaptic current instead of the potential
    directly for 0.4 of each frame, and the place units are fast (``tau = 1`` frame, the demo's
    is 4), so a packet forms or switches within a frame or two once the evidence is there,
    while the evidence itself is remembered for ``synaptic_time_constant`` frames; a few Euler
    steps per frame (the demo takes 1000); the inhibitor has a tonic rate; inputs are
    normalised, adapted and clipped.

    Examples
    --------
    >>> import numpy as np
    >>> from flyvpr.temporal.cann import AttractorCANN
    >>> rng = np.random.default_rng(0)
    >>> S = rng.normal(size=(60, 200))
    >>> S[np.arange(60), 20 + np.arange(60)] += 3.0    # the true place advances 1 per frame
    >>> out = AttractorCANN(movement=1.0).filter(S)
    >>> int(out[-1].argmax())
    79
    """

    name = "cann-paper"

    def __init__(
        self,
        excitation_strength=15.0,
        excitation_width=1.0,
        inhibition=3.2,
        tonic_inhibition=1.0,
        threshold=1.0,
        time_constant=1.0,
        synaptic_time_constant=25.0,
        slow_time_constant=None,
        slow_fraction=0.5,
        input_gain=10.0,
        n_steps=3,
        movement="estimate",
        velocities=DEFAULT_VELOCITIES,
        bidirectional=False,
        velocity_memory=100.0,
        velocity_contrast=4.0,
        adaptation=50.0,
        adapt_variance=True,
        input_transform="auto",
        input_clip=4.0,
        relocation_floor=5.5,
        relocation_margin=0.5,
        fallback_contrast=2.5,
        fallback_memory=200.0,
    ):
        self.excitation_strength = excitation_strength
        self.excitation_width = excitation_width
        self.inhibition = inhibition
        self.tonic_inhibition = tonic_inhibition
        self.threshold = threshold
        self.time_constant = time_constant
        self.synaptic_time_constant = synaptic_time_constant
        self.slow_time_constant = slow_time_constant
        self.slow_fraction = slow_fraction
        self.input_gain = input_gain
        self.n_steps = n_steps
        self.movement = movement
        self.velocities = velocities
        self.bidirectional = bidirectional
        self.velocity_memory = velocity_memory
        self.velocity_contrast = velocity_contrast
        self.adaptation = adaptation
        self.adapt_variance = adapt_variance
        self.input_transform = input_transform
        self.input_clip = input_clip
        self.relocation_floor = relocation_floor
        self.relocation_margin = relocation_margin
        self.fallback_contrast = fallback_contrast
        self.fallback_memory = fallback_memory

    def _check_params(self) -> dict:
        """Validate the constructor parameters; return them as plain numbers."""
        return check_params(self)

    @staticmethod
    def _kernel_of(p: dict) -> np.ndarray:
        """The excitation kernel, refused before allocation if it would not fit in memory."""
        radius = np.ceil(3.0 * p["excitation_width"])
        check_memory(
            (2 * radius + 1) * 8 * 4,
            f"excitation_width={p['excitation_width']:g} (a kernel of {2 * radius + 1:.0f} taps)",
        )
        return excitation_kernel(p["excitation_strength"], p["excitation_width"])

    # -- footprint ------------------------------------------------------------
    def footprint(self, n_reference: int) -> dict:
        """Layers, parameters and neurons the CANN adds on top of a front end.

        ``params`` counts connections: the recurrent excitation's synapses (each place unit
        onto itself and its neighbours within the kernel radius, fewer at the route's ends)
        plus the ``n_reference`` synapses onto the inhibitor and the ``n_reference`` from it.
        ``distinct_weights`` counts the different non-zero weight values instead: the kernel's
        symmetric taps plus the two inhibitor weights.  ``neurons`` = place units + the
        inhibitor.  The paper's table reports 72k parameters and 2066 neurons for FlyNet+CANN
        with 1000 places (FlyNet: 64k, 1064), i.e. about 8k parameters and 1002 units for its
        CANN.  The synaptic currents (and with ``movement="estimate"`` the velocity bank's
        ``len(velocities) * n_reference`` evidence traces) are state, not parameters; they are
        reported as ``state_variables``.
        """
        n = check_positive_int(n_reference, "n_reference")
        p = self._check_params()
        k = self._kernel_of(p)
        radius = (k.size - 1) // 2
        offsets = np.arange(-radius, radius + 1)
        # Synapses of offset d exist for the n - |d| units whose neighbour lies on the route.
        recurrent = int(np.sum(np.maximum(n - np.abs(offsets), 0)[k != 0]))
        n_bank = 0 if p["movement"] is not None else p["velocities"].size
        n_cur = len(p["currents"])
        return {
            "layers": 1,
            "params": recurrent + 2 * n,
            "neurons": n + 1,
            "distinct_weights": int(np.unique(k[k != 0]).size) + 2,
            "state_variables": (1 + n_cur + n_cur * n_bank) * n + 1,
        }

    # -- online ---------------------------------------------------------------
    def reset(self) -> None:
        """Forget all past frames: no packet, no evidence, no adaptation, no velocity votes.

        Parameters changed with ``set_params`` take effect here (``filter`` always resets;
        the first ``step`` after construction resets by itself).
        """
        self._params = self._check_params()
        self._kernel = self._kernel_of(self._params)
        # the state is allocated by the first row, which fixes n_reference
        self._n: int | None = None
        self.compiled_ = False  # chosen with the route's length (see _kernels)
        self.n_frames_ = 0
        self.n_relocations_ = 0
        self.velocity_ = float("nan")
        self.confidence_ = self.contrast_ = self.support_ = 0.0

    def _allocate(self, n: int) -> None:
        p = self._params
        n_cur = len(p["currents"])
        n_vel = 0 if p["movement"] is not None else p["velocities"].size
        # Potentials, evidence, adaptation, scratch, the currents (twice) and the bank (twice).
        check_memory(
            4 * n * (8 + 2 * n_cur + 2 * n_cur * n_vel + (n_vel if n_cur > 1 else 0)),
            f"n_reference={n} places with {n_vel} velocities x {n_cur} synaptic currents "
            "(velocities, bidirectional, slow_time_constant)",
        )
        self._n = n
        self._kernels, self.compiled_ = _kernels.get_kernels(n)
        self._u = np.zeros(n, np.float32)  # potentials
        # The synaptic currents, each already weighted (fast first), and a spare buffer (the
        # update is out of place); s is their sum.
        self._cur = np.zeros((n_cur, 1, n), np.float32)
        self._cur_spare = np.empty_like(self._cur)
        self._s = np.zeros(n, np.float32)
        self._mean = np.zeros(n, np.float32)  # adaptation: running mean input per place
        self._var = np.ones(n, np.float32)  # and running variance (prior: the row's, 1)
        self._x = np.empty(n, np.float32)  # the input row
        self._stats_stride = max(1, n // _STATS_SAMPLES)
        self._g = 0.0  # inhibitor rate
        # The Euler steps' constants (see _kernels.integrate).
        h = 1.0 / (p["n_steps"] * p["time_constant"])
        self._euler = (
            np.float32(h),
            np.float32(1.0 - h),
            np.float32(p["threshold"]),
            float(p["tonic_inhibition"]),
            h * p["inhibition"],
            self._kernel * np.float32(h),
            p["n_steps"],
        )
        self._offset = 0.0  # fractional movement not yet applied to the packet
        # Per frame, current c decays by keeps[c] and adds coefs[c] * (input_gain * x).
        taus = np.array([tau for tau, _ in p["currents"]])
        weights = np.array([w for _, w in p["currents"]])
        alphas = -np.expm1(-1.0 / taus)
        self._keeps = (1.0 - alphas).astype(np.float32)
        self._coefs = (alphas * weights).astype(np.float32)
        # Evidence differences below this are rounding residue (1e-4 of what one frame of a
        # one-standard-deviation input adds to s), never evidence.
        self._noise = 1e-4 * float(self._coefs.sum()) * p["input_gain"]
        if p["relocation_margin"] is not None:
            # Compiled now rather than at the first packet: a call that moves nothing (q = p).
            radius = (self._kernel.size - 1) // 2
            self._kernels["relocate"](
                self._u, self._s, 0, 0, radius, p["relocation_floor"], p["relocation_margin"], _TINY
            )
        self._bank = None
        if n_vel:
            self._bank = SpeedBank(
                p["velocities"],
                n_cur,
                n,
                self._keeps,
                self._coefs,
                p["velocity_memory"],
                p["velocity_contrast"],
                self._stats_stride,
                self._noise,
            )

    @property
    def potentials_(self) -> np.ndarray:
        """The place units' potentials ``u`` after the last step (a copy)."""
        return self._u.copy()

    def _input(self, row: np.ndarray) -> np.ndarray:
        """This frame's input: the row normalised, adapted, clipped and scaled (see "Input")."""
        return normalised_input(self, row, self._params["input_gain"], prior_var=False)

    def _step(self, row: np.ndarray, velocity: float | None = None) -> np.ndarray:
        begin_frame(self, row)
        p = self._params
        kernels = self._kernels
        t = self.n_frames_
        x = self._input(row)
        bank = self._bank
        if bank is not None:
            bank.update(x, t == 0, kernels["update_traces"], kernels["evidence_stats"])
        v = velocity if velocity is not None else p["movement"]
        if v is None:
            assert bank is not None  # movement="estimate" made one
            v = bank.estimate
        k = 0
        if t > 0:  # the first frame has nothing to move
            total = self._offset + v
            k = math.floor(total + 0.5)
            self._offset = total - k
            # A move of the route's length or more empties the line (everything enters at
            # rest), as any longer one does: bounded so that it fits the kernels' int64
            # (velocity=1e19 overflowed there).
            n = self._u.shape[0]
            k = max(-n, min(n, k))
        # What enters is at rest (its potential: the inhibition alone).  On the first frame a
        # shift by 0, which moves nothing, compiles the kernel.
        kernels["shift"](self._u, k, np.float32(-p["inhibition"] * self._g))
        if bank is not None and velocity is None:
            # The evidence follows the estimated speed: the bank's row of that velocity.
            self._cur[:, 0] = bank.traces[:, bank.index]
            self._s[:] = bank.evidence[bank.index]
            q = int(bank.peaks[bank.index])
        else:
            kernels["update_traces"](
                self._cur, self._cur_spare, np.array([k]), self._keeps, self._coefs, x
            )
            self._cur, self._cur_spare = self._cur_spare, self._cur
            np.sum(self._cur[:, 0], axis=0, out=self._s)
            q = int(np.argmax(self._s))
        self._g = kernels["integrate"](self._u, self._s, *self._euler)
        radius = (self._kernel.size - 1) // 2
        if p["relocation_margin"] is not None:
            peak = int(np.argmax(self._u))
            if self._u[peak] > p["threshold"] and kernels["relocate"](
                self._u,
                self._s,
                peak,
                q,
                radius,
                p["relocation_floor"],
                p["relocation_margin"],
                np.float32(-p["inhibition"] * self._g),
            ):
                self.n_relocations_ += 1
        self.n_frames_ = t + 1
        self.velocity_ = float(v)
        return self._read(row, radius, t)

    def _read(self, row: np.ndarray, radius: int, t: int) -> np.ndarray:
        """The readout of this frame (see "Output" on the guide page)."""
        p = self._params
        peak, contrast = _readout.evidence_contrast(
            self._u,
            self._s,
            p["threshold"],
            radius,
            self._stats_stride,
            self._noise,
            self._kernels["evidence_stats"],
        )
        # The packet's support: its contrast averaged over recent frames (the running mean at
        # first, then an exponential average over fallback_memory frames).
        self.support_ += max(1.0 / (t + 1), 1.0 / p["fallback_memory"]) * (contrast - self.support_)
        self.contrast_ = contrast
        tier = _readout.choose_tier(
            contrast, self.support_, p["fallback_contrast"], t, p["fallback_memory"]
        )
        out = _readout.readout(self._u, self._s, row, peak, contrast, tier, self._noise)
        self.confidence_ = float(out.max())
        return out
