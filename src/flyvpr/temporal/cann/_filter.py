"""The CANN filter: a place-velocity layer, its sequence test and its answer.

See "The place-velocity layer" on the user guide's CANN page for the equations and for the
data that chose the defaults; :class:`~flyvpr.temporal.cann.AttractorCANN` is the paper's
attractor network (the ``cann-paper`` filter).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..._validation import check_memory, check_positive_int, check_real
from . import _kernels
from ._input import OdometryFilter, begin_frame, normalised_input
from ._params import TRANSFORMS, _check_breaks, _check_velocities

#: candidate velocities, places per frame: standing still to 2 in steps of 1/8, then to 3.5 in
#: steps of 1/4 (a speed is followed only within about half a step of a row: the bank reaches
#: half a place beyond the 3 places per frame it is meant to follow); backwards, a coarse bank
#: of 1/2 to 2 in steps of 1/2 (a robot that turns round or reverses along its map)
LAYER_VELOCITIES = tuple(
    float(v)
    for v in np.r_[
        -np.arange(2.0, 0.25, -0.5), np.arange(0.0, 2.0, 0.125), np.arange(2.0, 3.51, 0.25)
    ]
)
#: the calibration table (see the class's docstring: fitted on Nordland 0-999, the dev window)
CALIBRATION = (0.0, 0.003, 0.004, 0.005, 0.183, 0.351, 0.536, 0.801, 0.853, 0.979, 1.0)
#: how odometry moves the layer (see the class's ``odometry`` parameter)
ODOMETRY_MODES = ("scaled", "exact")
#: learning rate of the front end's logistic model (per confident sequence answer)
_FRONT_RATE = 0.05
#: the plain z-scored row's weight, in frames, in the front end's answer read through the
#: input's adaptation (see _front_row)
_FRONT_PLAIN = 5.0
#: the least weight of the front end's model in a lost filter's answer (see _step)
_MIN_TRUST = 0.05
#: about this many places are sampled by the sequence test
_SAMPLES = 4096
#: bounds of the learned exponent of the sequence test's rank model (see _support)
_SHAPE_RANGE = (0.05, 1.0)
#: confidences at which a table is given (for ``calibration``: fourth roots of raw ones)
_KNOTS = np.linspace(0.0, 1.0, 11)
#: ``calibration`` is given at the raw confidence to the power ``1 / CALIBRATION_ROOT``
CALIBRATION_ROOT = 4
#: the rank model learns from frames whose support reaches this
_LEARN_ABOVE = 0.5
#: the rate of the odometry's running mean (a robot's recent speed, for a gap in the odometry)
_ODOMETRY_RATE = 0.2
#: a frame's odometry more than this many times the recent distance per frame (that is at
#: least one place) is a glitch, refused (see CANN._odometry_glitch)
ODOMETRY_JUMP = 8.0


def _shape(log_rank: float) -> float:
    """The rank model's exponent from the running mean of ``-log(rank)``: its inverse,
    within ``_SHAPE_RANGE`` (a mean of 0, every rank 1, gives the flat model, 1)."""
    low, high = _SHAPE_RANGE
    if log_rank * high <= 1.0:
        return high
    return max(low, 1.0 / log_rank)


def _split(weights: np.ndarray, backward: np.ndarray, share: float) -> np.ndarray:
    """``weights`` normalised so that the ``backward`` ones sum to ``share`` and the others to
    ``1 - share``; with velocities of one sign only, or where the weights leave one sign
    nothing to share it out over, normalised to sum to 1."""
    out = weights.astype(np.float64)
    if backward.any() and not backward.all():
        totals = out[backward].sum(), out[~backward].sum()
        if totals[0] > 0 and totals[1] > 0:
            out[backward] *= share / totals[0]
            out[~backward] *= (1.0 - share) / totals[1]
            return out
    return out / out.sum()


def _check_breaks_fit(breaks: np.ndarray, n: int) -> None:
    """Refuse ``breaks`` (checked, increasing) that are not places ``1 .. n - 1`` of a route of
    ``n`` places."""
    if breaks.size and breaks[-1] >= n:
        raise ValueError(
            f"breaks must be places 1 .. {n - 1} of this map of {n} places (the first "
            f"place of each stretch after a break); got {breaks.tolist()}"
        )


def _jitter_shares(jitter: float, speeds: np.ndarray) -> np.ndarray:
    """Each row's share that ends a frame a place off (see ``jitter``), for rows moving
    ``speeds`` places per frame: in proportion to the speed up to a place per frame, the whole
    share from there (a standing row: none)."""
    return jitter * np.minimum(np.abs(speeds), 1.0)


def _sigmoid(x: float) -> float:
    if x >= 0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


def _calibrate(raw: float, table) -> float:
    """``raw`` mapped through ``table`` (values at ``raw`` = 0, 0.1, ..., 1, linearly between
    them; the sequence's table is given the fourth root of its raw confidence); ``None``:
    ``raw`` itself."""
    if table is None:
        return raw
    return float(np.interp(raw, _KNOTS, table))


def table_at_roots(table, root: int) -> tuple[float, ...]:
    """A ``calibration`` table given at the raw confidence's ``root``-th root 0, 0.1, ..., 1
    (model files saved before it was given at the fourth root hold one at the raw confidence,
    ``root`` 1, or at its square root, 2) resampled at the raw confidences 0, 0.1 ** 4,
    0.2 ** 4, ..., 1 that the filter now reads it at: the same mapping at those points,
    linear between them."""
    values = np.interp(
        _KNOTS ** (CALIBRATION_ROOT / root), _KNOTS, np.asarray(table, dtype=np.float64)
    )
    return tuple(float(v) for v in values)


def _check_table(value, name: str, at: str) -> np.ndarray | None:
    """A confidence table: None, or 11 strictly increasing numbers in [0, 1] (at ``at`` 0,
    0.1, ..., 1)."""
    if value is None:
        return None
    try:
        table = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(
            f"{name} must be None or 11 numbers (at {at} 0, 0.1, ..., 1); got {value!r}"
        ) from None
    if table.shape != (_KNOTS.size,):
        raise ValueError(
            f"{name} must hold {_KNOTS.size} values (at {at} 0, 0.1, ..., 1); got shape "
            f"{table.shape}"
        )
    if not (np.isfinite(table).all() and table.min() >= 0.0 and table.max() <= 1.0):
        raise ValueError(f"{name} values must lie in [0, 1]; got {table.tolist()}")
    if (np.diff(table) <= 0).any():
        raise ValueError(f"{name} must increase strictly; got {table.tolist()}")
    return table


def _probability(value, name: str) -> float:
    """A probability: a finite real number in [0, 1]."""
    value = check_real(value, name, low=0.0, inclusive=True)
    if value > 1.0:
        raise ValueError(f"{name} must be <= 1; got {value}")
    return value


class CANN(OdometryFilter):
    """A 1-d place network with velocity: where the robot is, how fast, and whether at all.

    Every place of the route has one unit per candidate velocity; a unit's activity is the
    probability that the robot is at that place moving at that velocity (the posterior of a
    Bayes filter over position and speed).  Each frame the activity of every velocity row is
    shifted by its velocity (the paper's *shift and copy*), spreads to neighbouring
    velocities, is multiplied by the evidence ``exp(evidence_gain * x)`` of the frame's
    normalised scores ``x`` (raised to the share of it that is new, ``evidence_share_``) and
    divisively normalised (global inhibition).  A sequence test
    compares the evidence at the predicted place with the evidence at every other place; its
    outcome, the *support*, is the probability that the query is following the route.  See
    the user guide's CANN page (``docs/guide/cann.md``).

    A row of :meth:`step` or :meth:`filter`: entry ``i`` is the support times the probability
    of being within ``tolerance`` places of ``i`` (calibrated; the front end's scaled scores
    when it answers; all scaled to the confidence where the answer snapped), at most the
    answer's, which is its maximum (the confidence) and its first argmax.  With odometry
    (``velocity``) every row of the layer moves by it times the row's velocity read as a scale
    factor (``odometry="scaled"``), or by it alone (``"exact"``).

    Parameters
    ----------
    velocities : sequence of float, default -2, -1.5, -1, -0.5, 0, 1/8, ..., 2, 2.25, ..., 3.5
        Candidate movements, places per frame (each row of the layer moves by one of them;
        negative: backwards along the route).
    bidirectional : bool, default False
        Also the negative of every velocity: the full bank backwards as well as forwards.
    reverse_weight : float, default 0.1
        Share of the prior (and of a redrawn velocity) on the negative velocities, when the
        bank has both signs: driving backwards along the map is possible but rarer.
    speed_prior : float, default 1.0
        Most likely speed, places per frame, before the evidence (the map's own pace).
    speed_prior_width : float, default 0.25
        Standard deviation of the Gaussian prior over velocities around ``speed_prior``
        (it weighs the velocities the layer starts with and those of the activity re-seeded
        over the route, ``relocation`` and ``recovery``).
    velocity_change : float, default 0.02
        Probability per frame that the velocity moves to a neighbouring candidate.
    velocity_jump : float, default 0.02
        Probability per frame that the velocity is redrawn, evenly from all the candidates
        (backwards with probability ``reverse_weight``): stops, starts.
    jitter : float, default 0.0
        Uneven motion: probability per frame that a robot moving a place or more per frame
        lands one place ahead of or behind where its velocity takes it (half each way; a
        slower row in proportion to its speed, so a standing robot does not jitter).  For
        recordings that drop frames.  With scaled odometry the distance the odometry reports
        sets the speed; exact odometry is the motion itself and turns it off.  What would go
        past the route's ends, or across a break (``breaks``), is lost, as in the move.  0:
        every row moves exactly by its
        velocity (the default: see "Uneven frames" on the CANN page for what 0.15 and 0.3
        gain on such recordings and cost on steady ones).
    evidence_gain : float, default 0.4
        Gain of the normalised scores in the evidence ``exp(evidence_gain * x)``: lower
        integrates over more frames.
    adaptation : float or None, default 50.0
        Time constant, in frames, of each place's running mean input, subtracted from it;
        ``None``: off.
    adapt_variance : bool, default True
        Also divide by the square root of each place's running input variance, of the frames
        before this one (a place's peak does not damp itself).
    input_transform : {"auto", "log", "linear"}, default "auto"
        How a score row becomes the input before its z-score; ``"log"`` needs non-negative
        scores ("auto": log for rows that sum to 1).
    input_clip : float or None, default 6.0
        Bound on the normalised input, in standard deviations (chosen on the accuracy
        benchmark's views with every front end: see "Input" on the guide page).
    relocation : float, default 0.001
        Probability per frame that the robot is anywhere on the route (a kidnap).
    recovery : float, default 0.01
        Extra probability per frame of being anywhere, times the probability that the
        sequence is lost (``1 - support_``): a lost filter looks around more.
    tolerance : int, default 2
        The answer is the most probable place in the window of ``2 * tolerance + 1`` places
        that holds the most probability; the confidence starts from the probability within
        ``tolerance`` places of the answer (times the support).
    sequence_break : float, default 0.05
        Probability per new frame that the query leaves the route (the support's prior
        decay); a frame counts as ``novelty_`` of a new one, the rest of it relaxes the
        support at the same total rate towards its running mean.
    sequence_start : float, default 0.05
        Probability per new frame that a query off the route joins it.
    outlier : float, default 0.3
        Share of frames on the route whose evidence at the true place is no better than
        anywhere else (the sequence test's robustness).
    support_memory : float, default 100.0
        Frames over which the support, the test's rank model, the statistics of the front
        end's peaks and the usual likeness of consecutive frames are averaged.
    fallback : bool, default True
        Answer with the front end's best place when the front end's estimated probability of
        being right beats the sequence's (see "Output" on the guide page; with
        ``adapt_front``, its best place in the row read through the adaptation).  The front
        end's probability is a logistic model of the strength of its peak (its z-score),
        learned at run time from whether it agrees with the sequence's confident answers
        (except those whose answer snapped); before any, ``0.5 ** (2 + tolerance)``.  The
        confidence of a front-end answer is that probability shrunk towards
        ``0.5 ** (1 + tolerance)`` by the lesser of the share of localized frames over the
        last ``support_memory`` frames and ``support_`` (the probability that the query
        follows the route): a filter lost for long, or whose frames no longer follow the
        route, may be off the map, where the model (learned on the route) does not hold.
        Where the front end's place lies within ``tolerance`` of where the layer predicted
        the robot before the frame, the greater of the two is used.
    snap : bool, default True
        Answer with the front end's best place instead of the packet's when it lies near the
        packet's answer but not on it (within ``2 * (2 * tolerance + 1)`` places), moved
        with the layer since the last frame filtered (1 to ``3 |v| + 1`` places along the
        layer's mean velocity ``v`` of that frame: up to two frames dropped in a row), and
        the front end had agreed (within ``tolerance``) with a larger share of the
        sequence's confident answers before this frame than the probability the packet's
        window holds (``front_share_`` as the last frame left it; a frame whose answer snaps
        does not count in it: the packet's answer, which would judge the front end, is the
        one overruled).  A packet that fell behind a strong front end (a recording that drops
        frames) so answers where the front end does.  The answer stays the sequence's
        (``source_``), its probability of being right (``probability_``) is that share: the
        confidence is the support times it (calibrated), and the state follows from it as
        from the window's.  See "Output" on the guide page.
    adapt_front : bool, default True
        The front end's own answer (where the filter falls back to it, and for its model,
        its agreement and the snap) reads the row through the input's per-place adaptation:
        each place's score against its running mean and spread over the frames so far, so
        that a place that scores high in every frame (a hub of the map) is no answer.  The
        front end keeps statistics of its own, where each frame's share (the adaptation's
        rate) is scaled by one minus its correlation with the last row (a robot standing
        before a noisy camera gives rows that correlate almost wholly: counted whole, its
        place would read as a hub's).  The adapted row is blended with the plain z-scored
        row (its log where the input takes it), which weighs 5 frames against the frames
        those statistics hold, each counted by one minus its correlation (the first frame's
        adapted input is 0 everywhere, and a mean of a few frames is noisy).  A constant
        row reads as ties.  ``False``: the front end's row as it is.  See "Output" on the
        guide page.
    calibration : sequence of 11 float or None, default CALIBRATION
        The sequence's confidence where the fourth root of its raw confidence (support times
        ``probability_``) is 0, 0.1, ..., 1 (raw 0, 0.0001, 0.0016, ..., 1: finest
        where the lost answers lie), linearly between (strictly increasing, in [0, 1]);
        fitted on kenyon+cann's answers on the dev robot conditions (Nordland 0-999, seeds
        0-2, tolerance 2).  ``None``: the raw confidence.
    recalibration : sequence of 11 float or None, default None
        A table for a route of one's own, applied to every answer's confidence (the
        sequence's after ``calibration``, and the front end's) at confidence 0, 0.1, ...,
        1, linearly between (strictly increasing, in [0, 1]):
        :func:`~flyvpr.temporal.cann.fit_calibration` fits it from a labelled run's
        confidences and whether each answer was right.  The ``state`` stays as it is, and
        the order of the answers too (to float32 resolution where the table is nearly flat).
    hold_repeats : bool, default True
        A frame whose scores equal the last frame's, place for place, is the same image
        again: no new observation, and a robot that has not moved (a stand or a slow stretch
        recorded as repeated frames).  The filter then holds: the layer, its statistics and
        the answer stay as they were (``velocity_`` 0, ``novelty_`` 0).  Not where the map
        itself repeats a frame at the answer (places that have scored exactly alike in every
        frame so far: there the place index runs on while the image stays), nor with odometry
        (which says whether the robot moved).  A camera standing still gives frames that
        differ by sensor noise; those are filtered as new frames (their novelty is small).
        ``False``: a repeated frame is a new frame (a stream that repeats its last frame
        while the robot moves).  :func:`~flyvpr.methods.make_method` and saved models turn it
        off behind a front end whose scores repeat for frames that differ by sensor noise
        only (``repeats_on_noise``: ``flynet``, ``flyhash``), unless it is given: there a
        repeated row may be a robot standing where its map's robot also stood.
    odometry : {"scaled", "exact"}, default "scaled"
        How a frame's odometry (``velocity``, places moved) moves the layer.  ``"scaled"``:
        each row moves the odometry times the row's velocity, read as a scale factor (1: the
        odometry is right in places), so the layer learns the ratio of places moved to the
        odometry as it learns a speed without it: a map spacing or a wheel calibration that is
        off, or a robot reversing along the map while its odometry counts distance, is
        followed.  The scale drifts between neighbouring rows (``velocity_change``) but is
        never drawn afresh: the odometry carries the stops and starts.  The scales' prior is
        the speed prior's shape around 1.  A frame without odometry after frames with it
        turns the rows back into speeds (scale times the recent odometry) until the odometry is
        back, with the scales as they were.  ``"exact"``: every row
        moves by the odometry itself (the velocities stay as they are); right odometry then
        follows a little closer, odometry 10% off falls behind the filter without it.  In
        either mode a frame's odometry more than 8 times the recent distance per frame (its
        running mean over about 5 frames, taken as at least one place) is a glitch (a GPS jump):
        refused, the frame filtered as one without odometry (``n_odometry_refused_``).
    breaks : sequence of int, default ()
        Places where the map's route is broken: each is the first place of a stretch that
        does not continue the place before it (the map leaves part of the route out, or joins
        separate recordings).  Probability that a frame's move would carry across a break has
        left the mapped stretch: it is shared out equally over the rest of its own velocity
        row (the places whose move lands on the route without crossing one), as after a
        relocation, and not carried on to the far side (a robot that drives past the end of
        a stretch is off the map, or anywhere).
        :func:`flyvpr.temporal.cann.route_breaks` finds them from the places' frame numbers,
        timestamps or positions; :meth:`flyvpr.Localizer.from_map` gives a map's.  A break
        is an end of the route for the jitter's move of one place (nothing jitters across
        it; what would is lost, as at the route's ends).  Empty: the places are one route.
        (Each must lie in ``1 .. n - 1`` for a route of ``n`` places: checked on the first
        frame.)

    Attributes
    ----------
    confidence_ : float
        Probability, in [0, 1], that the last answer is right (within ``tolerance``).
    state_ : str
        ``"localized"`` when the answer comes from the sequence and the support times
        ``probability_`` (the raw confidence, before calibration) is at least 0.5,
        ``"lost"`` otherwise (the place is then a hint).
    support_ : float
        Probability that the query is following the route.
    novelty_ : float
        How much of a new frame the last one was to the sequence test, in [0, 1]: 1 for a
        frame as unlike the one before as frames usually are, near 0 for a repeat of it (a
        robot standing still); the test's evidence, and the chance of leaving or joining
        the route, count that much.
    evidence_share_ : float
        How much of the last frame's evidence the layer counted, in [0, 1]: its novelty,
        and the rest of it where the map's places around the packet differ (a repeat there
        says the robot has not moved on); near its novelty where they look alike (the map
        stood there too: the same observation again, counted once).
    front_probability_ : float
        The front end's model's probability that its own best place is right, this frame
        (before the shrinking of a front-end answer's confidence).
    front_share_ : float
        The share of the sequence's confident answers (support times window probability at
        least 0.5) whose place the front end's best place was within ``tolerance`` of, from
        a prior of ``0.5 ** (2 + tolerance)`` worth one answer (see ``snap``); counted since
        :meth:`reset`, not forgotten, but for the frames whose answer snapped.
    probability_ : float
        The probability within ``tolerance`` places of the sequence's answer: its window's,
        or ``front_share_`` where the answer snapped; 0 for a front end's answer.
    snapped_ : bool
        Whether the last answer is the front end's best place by ``snap``.
    velocity_ : float
        Mean velocity of the layer after the last step, places per frame: with odometry,
        the odometry times the layer's mean scale (``"scaled"``) or the odometry
        (``"exact"``); 0 after a held frame (``hold_repeats``).
    n_held_ : int
        Frames since :meth:`reset` that repeated the last one and were held (not counted in
        ``n_frames_``).
    n_odometry_refused_ : int
        Frames since :meth:`reset` whose odometry was refused as a glitch (see ``odometry``).
    source_ : str
        ``"sequence"`` or ``"front end"``: where the last answer came from (a snapped
        answer, the front end's place taken by the sequence, is the sequence's).
    n_frames_, n_relocations_ : int
        Frames filtered since :meth:`reset` (held ones aside); frames answered from the
        sequence whose packet's answer (before any snap) landed more than
        ``2 * tolerance + 1`` places from the predicted place (a front-end answer is never
        counted).
    compiled_ : bool
        Whether the per-frame updates run compiled by numba.

    Examples
    --------
    >>> import numpy as np
    >>> from flyvpr.temporal.cann import CANN
    >>> rng = np.random.default_rng(0)
    >>> S = rng.normal(size=(60, 200))
    >>> S[np.arange(60), 20 + np.arange(60)] += 3.0    # the true place advances 1 per frame
    >>> out = CANN().filter(S)
    >>> int(out[-1].argmax()), bool(out[-1].max() > 0.9)
    (79, True)
    """

    name = "cann"

    #: maps and models saved before ``odometry``, ``hold_repeats``, ``jitter``, ``snap``,
    #: ``adapt_front`` or ``breaks`` existed load with its default (``snap`` and
    #: ``adapt_front``: off, as they ran; see ``flyvpr.modelio``)
    _added_params = ("odometry", "hold_repeats", "jitter", "snap", "adapt_front", "breaks")

    def __init__(
        self,
        velocities=LAYER_VELOCITIES,
        bidirectional=False,
        reverse_weight=0.1,
        speed_prior=1.0,
        speed_prior_width=0.25,
        velocity_change=0.02,
        velocity_jump=0.02,
        jitter=0.0,
        evidence_gain=0.4,
        adaptation=50.0,
        adapt_variance=True,
        input_transform="auto",
        input_clip=6.0,
        relocation=0.001,
        recovery=0.01,
        tolerance=2,
        sequence_break=0.05,
        sequence_start=0.05,
        outlier=0.3,
        support_memory=100.0,
        fallback=True,
        snap=True,
        adapt_front=True,
        calibration=CALIBRATION,
        recalibration=None,
        odometry="scaled",
        hold_repeats=True,
        breaks=(),
    ):
        self.velocities = velocities
        self.bidirectional = bidirectional
        self.reverse_weight = reverse_weight
        self.speed_prior = speed_prior
        self.speed_prior_width = speed_prior_width
        self.velocity_change = velocity_change
        self.velocity_jump = velocity_jump
        self.jitter = jitter
        self.evidence_gain = evidence_gain
        self.adaptation = adaptation
        self.adapt_variance = adapt_variance
        self.input_transform = input_transform
        self.input_clip = input_clip
        self.relocation = relocation
        self.recovery = recovery
        self.tolerance = tolerance
        self.sequence_break = sequence_break
        self.sequence_start = sequence_start
        self.outlier = outlier
        self.support_memory = support_memory
        self.fallback = fallback
        self.snap = snap
        self.adapt_front = adapt_front
        self.calibration = calibration
        self.recalibration = recalibration
        self.odometry = odometry
        self.hold_repeats = hold_repeats
        self.breaks = breaks

    # -- parameters -------------------------------------------------------------
    def _check_params(self) -> dict:
        p: dict[str, Any] = {
            "speed_prior": check_real(self.speed_prior, "speed_prior", low=None),
            "speed_prior_width": check_real(self.speed_prior_width, "speed_prior_width"),
            "reverse_weight": _probability(self.reverse_weight, "reverse_weight"),
            "velocity_change": _probability(self.velocity_change, "velocity_change"),
            "velocity_jump": _probability(self.velocity_jump, "velocity_jump"),
            "jitter": _probability(self.jitter, "jitter"),
            "evidence_gain": check_real(self.evidence_gain, "evidence_gain"),
            "adaptation": None
            if self.adaptation is None
            else check_real(self.adaptation, "adaptation", low=1.0, inclusive=True),
            "input_clip": None
            if self.input_clip is None
            else check_real(self.input_clip, "input_clip"),
            "relocation": _probability(self.relocation, "relocation"),
            "recovery": _probability(self.recovery, "recovery"),
            "tolerance": check_positive_int(self.tolerance, "tolerance", minimum=0),
            "sequence_break": _probability(self.sequence_break, "sequence_break"),
            "sequence_start": _probability(self.sequence_start, "sequence_start"),
            "outlier": _probability(self.outlier, "outlier"),
            "support_memory": check_real(
                self.support_memory, "support_memory", low=1.0, inclusive=True
            ),
        }
        if p["velocity_change"] + p["velocity_jump"] > 1.0:
            raise ValueError(
                "velocity_change + velocity_jump must be <= 1; got "
                f"{p['velocity_change']} + {p['velocity_jump']}"
            )
        if p["relocation"] + p["recovery"] > 1.0:
            raise ValueError(
                f"relocation + recovery must be <= 1; got {p['relocation']} + {p['recovery']}"
            )
        if p["sequence_break"] + p["sequence_start"] > 1.0:
            raise ValueError(
                "sequence_break + sequence_start must be <= 1; got "
                f"{p['sequence_break']} + {p['sequence_start']}"
            )
        for flag in (
            "adapt_variance",
            "bidirectional",
            "fallback",
            "snap",
            "adapt_front",
            "hold_repeats",
        ):
            value = getattr(self, flag)
            if not isinstance(value, (bool, np.bool_)):
                raise TypeError(f"{flag} must be True or False; got {type(value).__name__}")
            p[flag] = bool(value)
        if self.input_transform not in TRANSFORMS:
            raise ValueError(
                f"input_transform must be one of {TRANSFORMS}; got {self.input_transform!r}"
            )
        p["input_transform"] = self.input_transform
        if self.odometry not in ODOMETRY_MODES:
            raise ValueError(f"odometry must be one of {ODOMETRY_MODES}; got {self.odometry!r}")
        p["odometry"] = self.odometry
        p["breaks"] = _check_breaks(self.breaks)
        p["calibration"] = _check_table(
            self.calibration, "calibration", "the fourth root of the raw confidence"
        )
        p["recalibration"] = _check_table(self.recalibration, "recalibration", "confidence")
        # Sorted, so that neighbouring rows are neighbouring speeds.
        vel = np.unique(_check_velocities(self.velocities, p["bidirectional"]))
        p["velocities"] = vel
        prior = np.exp(-0.5 * ((np.abs(vel) - p["speed_prior"]) / p["speed_prior_width"]) ** 2)
        if not prior.sum() > 0.0:
            raise ValueError(
                f"speed_prior={p['speed_prior']} with speed_prior_width="
                f"{p['speed_prior_width']} gives no weight to any of the velocities"
            )
        p["prior"] = _split(prior, vel < 0, p["reverse_weight"])
        # With scaled odometry a row is a scale of the odometry: 1 where it is right in places.
        # Its prior is the speed prior's shape around 1 (a robot reversing along the map while
        # its odometry counts distance: -1, as likely as driving backwards without odometry).
        scale = np.exp(-0.5 * ((np.abs(vel) - 1.0) / p["speed_prior_width"]) ** 2)
        p["scale_prior"] = (
            _split(scale, vel < 0, p["reverse_weight"]) if scale.sum() > 0.0 else p["prior"]
        )
        # A velocity drawn afresh may be any of them (a robot stops or starts at any speed),
        # backwards with probability reverse_weight.
        p["redraw"] = _split(np.ones(vel.size), vel < 0, p["reverse_weight"])
        return p

    def footprint(self, n_reference: int) -> dict:
        """Layers, parameters and neurons the filter adds on top of a front end.

        ``neurons``: one unit per place and velocity, plus the global normaliser.  ``params``
        counts connections: each unit receives its shifted predecessor, its two velocity
        neighbours (one at the bank's ends), the redrawn-velocity input from its place and
        the evidence input; every unit also feeds the normaliser and receives from it.  With
        ``jitter``, each unit of a moving row also receives from its two neighbouring places
        (one at the route's ends and on either side of a break).  ``distinct_weights``: stay,
        neighbour, redraw (one per velocity) and the evidence gain, and the jitter's two (kept,
        passed on) for each share it takes (one per speed below a place per frame, one for the
        rest).
        ``state_variables``: the units, each place's running mean and variance of its
        input (twice with ``adapt_front``: the front end's own), the last frame's row, the
        last answer's row and whether the place has tied with the one before it in every frame
        (``hold_repeats``), and 7 running numbers.
        """
        n = check_positive_int(n_reference, "n_reference")
        p = self._check_params()
        _check_breaks_fit(p["breaks"], n)
        n_v = p["velocities"].size
        units = n_v * n
        neighbours = 2 * (n_v - 1) * n
        share = _jitter_shares(p["jitter"], p["velocities"])
        jittered = int(np.count_nonzero(share))
        shares = np.unique(share[share > 0]).size
        # (pairs of neighbouring places the jitter links: none across a break)
        pairs = n - 1 - p["breaks"].size
        return {
            "layers": 1,
            "params": units + neighbours + units + units + 2 * units + 2 * jittered * pairs,
            "neurons": units + 1,
            "distinct_weights": 3 + n_v + 2 * shares,
            "state_variables": units + (7 if p["adapt_front"] else 5) * n + 7,
        }

    # -- online -----------------------------------------------------------------
    def reset(self) -> None:
        """Forget all past frames (parameters changed with ``set_params`` apply from here)."""
        self._params = self._check_params()
        self._n: int | None = None
        self.compiled_ = False
        self.n_frames_ = 0
        self.n_relocations_ = 0
        self.velocity_ = float("nan")
        self.n_held_ = 0
        self.n_odometry_refused_ = 0
        self.confidence_ = 0.0
        self.support_ = 0.5
        self.novelty_ = 1.0
        self._last_likeness = 0.0  # (the last frame's correlation with the one before)
        self._front_seen = 0.0  # (frames the front end's statistics hold, see _front_row)
        self.evidence_share_ = 1.0
        self.front_probability_ = 0.0
        self.front_share_ = 0.5 ** (2 + self._params["tolerance"])
        self.snapped_ = False
        self.probability_ = 0.0
        self.state_ = "lost"
        self.source_ = "sequence"

    def _allocate(self, n: int) -> None:
        p = self._params
        n_v = p["velocities"].size
        check_memory(
            8 * n_v * n + 68 * n,
            f"n_reference={n} places x {n_v} velocities (velocities, bidirectional)",
        )
        _check_breaks_fit(p["breaks"], n)
        self._n = n
        self._kernels, self.compiled_ = _kernels.get_kernels(n, table="layer")
        prior = p["prior"].astype(np.float32)
        self._p = np.repeat(prior[:, None] / np.float32(n), n, axis=1)
        self._spare = np.empty_like(self._p)
        self._redraw = p["redraw"]
        self._jitter = _jitter_shares(p["jitter"], p["velocities"])
        self._marginal = np.empty(n, np.float32)  # the posterior over places
        self._predicted = np.empty(n, np.float32)  # the prior over places, before the evidence
        self._weight = np.empty(n, np.float32)  # the evidence exp(gain * (x - max x))
        self._row_mass = np.empty(n_v, np.float64)  # the posterior over velocities
        self._box = np.empty(n, np.float64)
        self._mean = np.zeros(n, np.float32)
        self._var = np.ones(n, np.float32)
        self._x = np.empty(n, np.float32)
        # The front end's own reading of its rows (see _front_row): its input, and each place's
        # running mean and variance over the frames counted by how much they differ.
        self._front_x = np.empty(n, np.float32)
        self._front_mean = np.zeros(n, np.float32)
        self._front_var = np.ones(n, np.float32)
        self._front_read = np.empty(n, np.float64)  # (the row as its answer reads it)
        self._offsets = np.zeros(n_v)
        # The last frame's row and the running mean correlation of consecutive rows (see
        # _novelty).
        self._last_row = np.zeros(n, np.float64)
        self._likeness: float | None = None
        # A repeated frame's answer (see hold_repeats): the last row returned, and which places
        # have scored exactly as the place before them in every frame (the map repeats there).
        # (``_tied``: the places i, ascending, whose score has equalled place i - 1's in every
        # frame so far; it shrinks to the map's repeated frames within a few frames.)
        self._last_out = np.zeros(n, np.float32)
        self._tied = np.arange(1, n, dtype=np.int32)
        self._odometry_offset = 0.0
        # Whether the rows are scales of the odometry (scaled odometry) or speeds, the recent
        # odometry's running mean, and the scales' posterior when the odometry last stopped
        # (see _rows_for)
        self._scaled = False
        self._odometry_mean: float | None = None
        self._odometry_size: float | None = None  # the odometry's recent size (see _step)
        self._pending_odometry = 0.0  # the odometry of repeated frames since the last new one
        self._scale_mass: np.ndarray | None = None
        self._stride = max(1, n // _SAMPLES)
        # The sequence test's rank model: the share u of places at least as good as the
        # predicted one has density shape * u**(shape - 1) on the route (learned), 1 off it.
        self._log_rank = [1.0 / 0.3, 1.0 / 0.5]  # running means of -log(rank), supported frames
        self._support_mean = 0.0  # the support averaged over support_memory frames
        self._localized_mean = 0.0  # the share of localized frames, over as many frames
        # The front end's model: running mean and variance of its peak's z-score and of its
        # best raw score, and the logistic weights (prior: a weak front end, right with
        # probability 0.5 ** (2 + tolerance) whatever its peak).
        self._front_stats: list[float] | None = None
        self._front_raw_z = 0.0
        prior = 0.5 ** (2 + p["tolerance"])
        self._front_model = [math.log(prior / (1.0 - prior)), 0.0]
        # The front end's agreement with the sequence's confident answers: how many agreed
        # and how many there were (see _snaps); the last frame's best place of the front end.
        self._front_agreed = 0.0
        self._front_checked = 0.0
        self._last_front: int | None = None
        self._layer_velocity = float("nan")  # velocity_ of the last frame filtered (not held)
        self.front_share_ = prior

    @property
    def shape_(self) -> float:
        """Exponent of the sequence test's learned rank model (see :meth:`_support`)."""
        return _shape(self._log_rank[0])

    def _input(self, row: np.ndarray) -> np.ndarray:
        """The row as z-scores, adapted per place and clipped (see "Input" on the guide)."""
        return normalised_input(self, row, 1.0, prior_var=True)

    def _front_row(self, row: np.ndarray) -> np.ndarray:
        """The front end's row as its own answer reads it (float64): the row through the
        input's per-place adaptation (its log where the input takes it; each place's score
        against that place's running mean and spread, so that a place that scores high in
        every frame is no answer), with statistics of its own, to which each frame counts
        one minus its correlation with the last row (a robot standing before a noisy camera
        gives rows that correlate almost wholly, and counted whole, its place's mean would
        climb frame after frame until the place read as a hub's).  Blended with the plain
        z-scored row, which weighs ``_FRONT_PLAIN`` frames against the frames the statistics
        hold before this one, each counted as it was (``_front_seen``): the first frame's
        adapted input is 0 everywhere (its own mean), a mean of a few frames is noisy (a
        robot standing from the start has shown one view however many frames it gave), and
        the plain row breaks the ties of clipped inputs.  A constant row (a spread of at most
        1e-6, as the input takes it) reads as zeros: it says nothing.  One compiled pass
        with the adaptation's (``normalise``)."""
        seen = self._front_seen
        self._front_seen += 1.0 - self._last_likeness
        normalised_input(
            self,
            row,
            1.0,
            prior_var=True,
            buffers=(self._front_x, self._front_mean, self._front_var),
            weight=1.0 - self._last_likeness,
            read=(self._front_read, seen / (seen + _FRONT_PLAIN)),
        )
        return self._front_read

    def _front_feature(self, strength: float, raw: float, rate: float) -> float:
        """The front end's peak z-score, standardised by its running mean and spread (within
        +-4); also sets ``_front_raw_z``, the same for its best raw score."""
        if self._front_stats is None:
            self._front_stats = [strength, 1.0, raw, 1.0]
        stats = self._front_stats
        out = []
        for k, value in ((0, strength), (2, raw)):
            mean, var = stats[k], stats[k + 1]
            sd = math.sqrt(var) if var > 0 else 1.0
            out.append(max(-4.0, min(4.0, (value - mean) / sd)) if var > 0 else 0.0)
            delta = value - mean
            stats[k] = mean + rate * delta
            stats[k + 1] = (1.0 - rate) * (var + rate * delta * delta)
        self._front_raw_z = out[1]
        return out[0]

    def _snaps(
        self, front: int, packet: int, last_front: int | None, probability: float, radius: int
    ) -> bool:
        """Whether the front end's best place ``front`` answers instead of the packet's
        ``packet`` (see "Output" on the guide page): it lies within twice the sequence test's
        window of it (``2 * (2 * radius + 1)`` places) but not on it, the front end has agreed
        with more of the sequence's confident answers before this frame (``front_share_``:
        this frame's own agreement is the one in question) than the packet's window holds of
        its probability, and the front end's best place moved with the layer since the last
        frame filtered: 1 to ``3 |v| + 1`` places along the layer's mean velocity ``v`` of
        that frame (two frames dropped in a row, and a place for rounding; a front end that
        stands while the layer moves, or jumps about, is not followed)."""
        if front == packet or abs(front - packet) > 2 * (2 * radius + 1):
            return False
        if not self.front_share_ > probability or last_front is None:
            return False
        v = self._layer_velocity  # (of the last frame filtered: not a held one's 0)
        if v == 0.0 or not math.isfinite(v):  # (NaN before the first frame)
            return False
        step = (front - last_front) * (1 if v > 0 else -1)
        return 1 <= step <= 3.0 * abs(v) + 1.0

    def _leave_at_breaks(self, shifts: np.ndarray) -> None:
        """Take the probability that this frame's move would carry across a break of the map
        (``breaks``) off its units and share it out over the rest of its own velocity row: the
        robot has left the mapped stretch, and where it is now the layer does not know (as
        after a relocation).  Unit ``i`` of a row moving ``k = shifts[j]`` places crosses when a
        break ``b`` lies in ``(i, i + k]`` (forwards) or ``(i + k, i]`` (backwards); what they
        held goes in equal shares to the row's units whose move lands on the route without
        crossing one, so that the move keeps all of it (the layer's kernel
        ``leave_at_breaks``)."""
        self._kernels["leave_at_breaks"](self._p, shifts, self._params["breaks"])

    def _shifts(self, velocity: float | None) -> np.ndarray:
        """Whole places each row moves this frame (fractions accumulate, halves round up).

        A move of more than the route's length leaves it whatever its size: moves are bounded
        by twice the route's length (so that any finite odometry, however large, moves the
        layer off the route rather than past an integer's range)."""
        vel = self._params["velocities"]
        bound = 2.0 * (self._n or 0) + 2.0
        if velocity is not None and self._params["odometry"] == "scaled":
            vel = min(max(velocity, -bound), bound) * vel  # each row: odometry times its scale
        elif velocity is not None:
            total = min(max(self._odometry_offset + velocity, -bound), bound)
            k = math.floor(total + 0.5)
            self._odometry_offset = total - k
            return np.full(vel.size, k, np.int64)
        total = np.clip(self._offsets + vel, -bound, bound)
        rounded = np.floor(total + 0.5)
        self._offsets = total - rounded
        return rounded.astype(np.int64)

    def _rows_for(self, velocity: float | None, t: int, repeat: bool = False) -> None:
        """Make the rows scales of the odometry or speeds, as this frame needs (scaled
        odometry only).

        The first frame with odometry (or the first that moves, after a start without it)
        makes them scales: each place's activity shared over the rows as the scales' posterior
        was when the odometry last stopped (the scale learned before a gap), or as their prior
        at first.  A frame without odometry after frames with it makes them speeds: each row's
        activity goes to the rows of its scale times the recent odometry (its running mean
        over about ``1 / _ODOMETRY_RATE`` frames: the robot keeps the speed it had, and one
        frame's step, which may be 0 or 2 places where the odometry counts whole places, does
        not set it alone), shared linearly between the two nearest (the bank's end rows take
        what lies beyond them); before any step of the odometry (the first frame's moves
        nothing), as the speeds' prior.  The odometry of frames that ``repeat`` the one before
        (``hold_repeats``) counts with the next new frame's: without odometry repeats are
        held, and the layer moves on the new frames only, so its speed is the odometry per new
        frame.  Without this a row's scale
        would be read as a speed in a gap of the odometry (a robot at 2 places per frame would
        go on at 1), and a speed learned without odometry as a scale when it starts."""
        p = self._params
        vel = p["velocities"]
        if vel.size == 1:  # one row: a scale and a speed alike
            return
        if velocity is not None and not self._scaled and (t == 0 or velocity != 0.0):
            mass = p["scale_prior"] if self._scale_mass is None else self._scale_mass
            if t == 0:  # the layer is its prior: the scales' instead
                self._p[:] = (mass.astype(np.float32) / np.float32(self._n))[:, None]
            else:
                np.multiply(mass.astype(np.float32)[:, None], self._p.sum(axis=0), out=self._spare)
                self._p, self._spare = self._spare, self._p
            self._offsets[:] = 0.0
            self._scaled = True
        elif velocity is None and self._scaled:
            self._scale_mass = self._row_mass.copy()
            if self._odometry_mean is None:  # no step of the odometry seen: the speeds' prior
                prior = p["prior"].astype(np.float32)[:, None]
                np.multiply(prior, self._p.sum(axis=0), out=self._spare)
            else:
                target = np.clip(vel * self._odometry_mean, vel[0], vel[-1])
                upper = np.clip(np.searchsorted(vel, target, side="right"), 1, vel.size - 1)
                lower = upper - 1
                high = (target - vel[lower]) / (vel[upper] - vel[lower])
                move = np.zeros((vel.size, vel.size), np.float32)  # move[to, from]
                np.add.at(move, (lower, np.arange(vel.size)), 1.0 - high)
                np.add.at(move, (upper, np.arange(vel.size)), high)
                np.matmul(move, self._p, out=self._spare)
            self._p, self._spare = self._spare, self._p
            self._offsets[:] = 0.0
            self._pending_odometry = 0.0
            self._scaled = False
        if velocity is not None and t > 0:  # (the first frame's odometry moves nothing)
            if repeat:  # counted with the next new frame's
                self._pending_odometry += velocity
                return
            bound = 2.0 * (self._n or 0) + 2.0  # (past the bank's speeds, as the moves' bound)
            step = min(max(self._pending_odometry + velocity, -bound), bound)
            self._pending_odometry = 0.0
            mean = step if self._odometry_mean is None else self._odometry_mean
            self._odometry_mean = (1.0 - _ODOMETRY_RATE) * mean + _ODOMETRY_RATE * step

    def _odometry_glitch(self, velocity: float) -> bool:
        """Whether a frame's odometry is a glitch: more than ``ODOMETRY_JUMP`` (8) times the
        recent distance per frame (the running mean of the odometry's size over about
        ``1 / _ODOMETRY_RATE`` frames, at least one place).  A GPS that jumps, a wheel that
        spins, a fix of another robot: no robot moves so much further than it just did, and
        moving the layer by it would put the packet that far off, still `localized`.  A glitch
        is refused (counted in ``n_odometry_refused_``) and the frame filtered as one without
        odometry.  The running mean takes each frame's size, a glitch's only up to the bound:
        one glitch moves it little, and a robot that truly speeds up that much (from a stand
        to 10 places a frame) is followed after a frame or two rather than refused for good."""
        size = abs(velocity)
        recent = self._odometry_size
        if recent is None:
            self._odometry_size = size
            return False
        bound = ODOMETRY_JUMP * max(recent, 1.0)
        self._odometry_size = recent + _ODOMETRY_RATE * (min(size, bound) - recent)
        if size > bound:
            self.n_odometry_refused_ += 1
            return True
        return False

    def _holds(self, row: np.ndarray) -> bool:
        """Whether ``row`` repeats the last frame's and the map does not repeat a frame at the
        last answer (see ``hold_repeats``)."""
        if not self._kernels["repeats"](row, self._last_row):
            return False
        a = int(np.argmax(self._last_out))  # the last answer: its row's first maximum
        tied = self._tied
        return not bool(((tied == a) | (tied == a + 1)).any())

    def _hold(self) -> np.ndarray:
        """A held frame: nothing changes but ``n_held_``; the last answer again."""
        self.novelty_ = 0.0
        self.evidence_share_ = 0.0
        self.velocity_ = 0.0
        self.n_held_ += 1
        return self._last_out.copy()

    def _novelty(self, row: np.ndarray, rate: float) -> float:
        """How much of a new frame ``row`` is, in [0, 1], for the sequence test.

        ``r``: the correlation of the row with the last row (clipped to [0, 1]; 0 where
        either row is constant).  Consecutive frames of a moving robot correlate a little
        (the route's neighbouring places look alike, ``r`` about 0.4-0.8 on Nordland); a
        standing robot's frames almost entirely.  The novelty is ``(1 - r) / (1 - r_mean)``,
        at most 1, where ``r_mean`` is the running mean of ``r`` (over ``support_memory``
        frames, updated with ``rate``): a frame as new as usual counts whole, a repeat of the
        last frame hardly at all.  Every frame's row is kept (float64) for the next.
        """
        r = float(self._kernels["likeness"](row, self._last_row))
        if self.n_frames_ == 0:
            self._last_likeness = 0.0
            return 1.0
        r = self._last_likeness = min(max(r, 0.0), 1.0)
        if self._likeness is None:
            self._likeness = r
        usual = self._likeness
        self._likeness += rate * (r - usual)
        return min(1.0, (1.0 - r) / max(1.0 - usual, 1e-6))

    def _evidence_share(self, row: np.ndarray, novelty: float) -> float:
        """How much of a frame's evidence is new, in [0, 1]: its ``novelty``, plus the rest
        of it in the measure that the map's places around the packet differ from each other.

        A frame much like the last one observes the same thing again.  Where the map's places
        around the packet differ as much as along the whole map (the mean absolute difference
        of neighbouring places' scores, within ``2 * tolerance + 1`` places of the packet's
        most probable place, against the whole row's), a repeat still tells where the robot
        stands: had it moved on, the scores at its new place would differ; it counts whole.
        Where the map's places there look alike (the map's drive stood too: a station, a
        traffic light), a repeat tells nothing new, and counting the same evidence again
        would drive the packet out of such a stretch whenever the front end does not
        recognise it (an overlay or a fisheye disc); it counts only its novelty.
        """
        if novelty >= 1.0:
            return 1.0
        reach = 2 * self._params["tolerance"] + 1
        packet = int(np.argmax(self._marginal))
        lo = max(packet - reach, 0)
        hi = min(packet + reach, row.shape[0] - 1)
        whole, near = self._kernels["variation"](row, lo, hi)
        differs = min(1.0, near / whole) if whole > 0.0 else 1.0
        return novelty + (1.0 - novelty) * differs

    def _support(self, x: np.ndarray, predicted: int, novelty: float) -> None:
        """The sequence test: update ``support_`` with this frame's evidence at ``predicted``.

        Two ranks of the predicted place's evidence: ``u`` among all places (every
        ``stride``-th) and ``w`` among its neighbours within ``2 * tolerance + 1`` places.  Off
        the route both are uniform; on it, each has density ``shape * u**(shape - 1)``
        (``shape`` < 1 puts the predicted place near the top; learned per rank from the
        frames the test already supports: the maximum-likelihood value, one over the mean of
        ``-log u``) on all but an ``outlier`` share of the frames.  Two states, on and off the
        route, switch with probabilities ``sequence_break`` and ``sequence_start`` per frame.
        The frame counts as ``novelty`` of a new one (see :meth:`_novelty`): the test's
        likelihood ratio is raised to that power, and the prior step is that mixture of the
        switch between the states and a relaxation, at the same rate, towards the support's
        running mean over ``support_memory`` frames.  A repeat of the last frame so tests
        nothing and leaves the support to what the recent frames said.
        """
        p = self._params
        reach = 2 * p["tolerance"] + 1
        u = float(self._kernels["exceedance"](x, predicted, self._stride))
        lo = max(predicted - reach, 0)
        near = x[lo : predicted + reach + 1]
        w = float(np.count_nonzero(near >= x[predicted])) / near.size
        on = 1.0
        for rank, k in ((u, 0), (w, 1)):
            shape = _shape(self._log_rank[k])
            on *= (1.0 - p["outlier"]) * shape * rank ** (shape - 1.0) + p["outlier"]
        on **= novelty
        s = self.support_
        # A new frame: the query may leave or join the route.  A repeat says nothing new, so
        # the support relaxes at the same rate towards what the recent frames said (its running
        # mean) rather than towards even odds: an established support is kept through a stand,
        # a chance one at its start is not.
        rate = p["sequence_break"] + p["sequence_start"]
        new = s * (1.0 - p["sequence_break"]) + (1.0 - s) * p["sequence_start"]
        relaxed = s + rate * (self._support_mean - s)
        before = novelty * new + (1.0 - novelty) * relaxed
        self.support_ = before * on / (before * on + (1.0 - before))
        if self.support_ >= _LEARN_ABOVE:
            self._log_rank[0] += (-math.log(u) - self._log_rank[0]) / p["support_memory"]
            self._log_rank[1] += (-math.log(w) - self._log_rank[1]) / p["support_memory"]

    def _step(self, row: np.ndarray, velocity: float | None = None) -> np.ndarray:
        begin_frame(self, row)
        p = self._params
        n = row.shape[0]
        kernels = self._kernels
        t = self.n_frames_
        if row.dtype not in (np.float32, np.float64):  # (float16: not a numba type)
            row = row.astype(np.float64)
        if p["hold_repeats"] and velocity is None and t > 0 and self._holds(row):
            return self._hold()
        radius = p["tolerance"]
        x = self._input(row)  # (which refuses a row before anything changes)
        if velocity is not None and t > 0 and self._odometry_glitch(velocity):
            velocity = None  # this frame as one without odometry
        if p["odometry"] == "scaled":
            # (a repeated frame's odometry counts with the next new frame's: in a gap of the
            # odometry the layer moves on new frames only, repeats being held)
            repeat = p["hold_repeats"] and velocity is not None and t > 0 and self._holds(row)
            self._rows_for(velocity, t, repeat)
        memory = p["support_memory"]
        if self._tied.size:
            tied = self._tied
            self._tied = tied[row[tied] == row[tied - 1]]
        novelty = self.novelty_ = self._novelty(row, max(1.0 / max(t, 1), 1.0 / memory))
        if t > 0:
            floor_rate = p["relocation"] + p["recovery"] * (1.0 - self.support_)
            if velocity is None:
                change, jump = p["velocity_change"], p["velocity_jump"]
            elif p["odometry"] == "scaled":
                # The scale drifts as a velocity does; the odometry carries the stops and
                # starts, so it is never drawn afresh.
                change, jump = p["velocity_change"], 0.0
            else:  # exact odometry moves every row alike; the velocities stay as they are
                change = jump = 0.0
            shifts = self._shifts(velocity)
            if p["jitter"] > 0.0 and (
                velocity is None or (p["odometry"] == "scaled" and velocity != 0.0)
            ):
                # Uneven motion of every moving row (exact odometry is the motion itself:
                # none; odometry 0 says that the robot stands).
                if velocity is None:
                    shares = self._jitter
                else:  # each row moves the odometry times its scale
                    shares = _jitter_shares(p["jitter"], velocity * p["velocities"])
                kernels["jitter"](self._p, self._spare, shares, p["breaks"])
                self._p, self._spare = self._spare, self._p
        else:  # the first frame: the prior as it is, weighed by the evidence
            floor_rate = change = jump = 0.0
            shifts = np.zeros(p["velocities"].size, np.int64)
        share = self.evidence_share_ = self._evidence_share(row, novelty)  # (1 at first: new)
        weight = self._weight
        np.subtract(x, x.max(), out=weight)
        weight *= np.float32(p["evidence_gain"] * share)
        np.exp(weight, out=weight)
        if t > 0 and p["breaks"].size:
            self._leave_at_breaks(shifts)
        kernels["advance"](
            self._p,
            self._spare,
            shifts,
            1.0 - change - jump,
            change,
            jump,
            self._redraw,
            p["scale_prior"] if self._scaled else p["prior"],
            floor_rate,
            weight,
            self._predicted,
            self._marginal,
            self._row_mass,
        )
        self._p, self._spare = self._spare, self._p
        predicted = -1
        if t > 0:
            predicted = int(kernels["window_sums"](self._predicted, radius, self._box))
            if (shifts == shifts[0]).all() or self._layer_velocity < 0:
                # Every velocity row moved alike (exact odometry, odometry 0, or a bank of one
                # velocity), so the prediction is the posterior moved whole: a confident packet
                # on one place fills 2 * radius + 1 windows almost equally, and the first of
                # them lies radius places short of it.  The prediction is then the packet's
                # most probable place in that window.  So it is for a packet that moved towards
                # lower place numbers on the last frame filtered (a held repeat's velocity_ of
                # 0 aside: a robot reversing along its map):
                # the bank's four backward rows lie far apart and the many forward and standing
                # rows pull the window towards higher numbers, so its centre sat a place behind
                # the packet, the evidence was tested there, and the robot read `lost` while
                # right.  (Rows moved forwards by different velocities spread the prediction
                # over several places, and the window's centre is the packet's; that case is
                # left as it was calibrated: the packet's most probable place there finds
                # chance sequences in shuffled frames.)
                lo = max(predicted - radius, 0)
                predicted = lo + int(np.argmax(self._predicted[lo : predicted + radius + 1]))
            self._support(x, predicted, novelty)
        # The window holding the most probability, and in it the most probable place: the
        # answer (its own window's probability is the confidence, at most the window's).
        best = int(kernels["window_sums"](self._marginal, radius, self._box))
        lo = max(best - radius, 0)
        answer = lo + int(np.argmax(self._marginal[lo : best + radius + 1]))
        probability = float(self._box[answer])
        rate = max(1.0 / (t + 1), 1.0 / memory)
        self._support_mean += rate * (self.support_ - self._support_mean)
        # The window's probability times the support (calibrated below).
        confidence = self.support_ * probability
        # The front end's own answer and the probability that it is right: a logistic model
        # of the strength of its peak (its z-score, standardised by its running mean and
        # spread), learned from whether it agrees with the sequence's confident answers.
        given = row  # (its raw score at the answer breaks the model's ties, as given)
        if p["adapt_front"]:
            row = self._front_row(row)
        front = int(np.argmax(row))
        spread = float(row.std())
        strength = (float(row[front]) - float(row.mean())) / spread if spread > 0 else 0.0
        feature = self._front_feature(strength, float(given[front]), rate)
        front_confidence = _sigmoid(self._front_model[0] + self._front_model[1] * feature)
        # (a confident answer judges the front end below, unless the answer snaps)
        judged = confidence >= 0.5
        model_probability = front_confidence
        last_front, self._last_front = self._last_front, front
        # A tie-break that keeps the front end's own order of answers (its raw best score)
        # where the model does not separate them (no confident answers to learn from yet).
        front_confidence *= 1.0 + 1e-3 * math.tanh(self._front_raw_z)
        front_confidence = min(1.0, front_confidence)
        self.front_probability_ = front_confidence
        out = np.empty(n, np.float32)
        packet = answer  # the sequence's own answer
        self.snapped_ = False
        if p["fallback"] and self._support_mean * probability < front_confidence * (
            1.0 - self._support_mean
        ):
            self.source_ = "front end"
            # The model learned on the route; a filter lost for long may be off the map,
            # where the front end is never right.  Its probability is shrunk towards a base
            # rate by the share of recent frames that were localized, or by the probability
            # that the query follows the route if that is less (a twentieth of it kept, so
            # that the front end's own order of answers survives).
            base = 0.5 ** (1 + p["tolerance"])
            # Where the front end's place is where the layer predicted the robot before this
            # frame (within tolerance), two views agree: the query is more likely on the
            # route, and the greater of the two is kept.
            share, support = self._localized_mean, self.support_
            agree = predicted >= 0 and abs(front - predicted) <= radius
            trust = max(max(share, support) if agree else min(share, support), _MIN_TRUST)
            confidence = base + trust * (front_confidence - base)
            z = row.astype(np.float64) - float(row.mean())
            top = float(z[front])
            if top > 0:
                np.maximum(z, 0.0, out=z)
                z *= confidence / top
            else:  # a constant row: every place ties at the confidence
                z[:] = confidence
            out[:] = z
            answer = front
        else:
            self.source_ = "sequence"
            np.multiply(self._box, self.support_, out=out, casting="unsafe")
            if predicted >= 0 and abs(packet - predicted) > 2 * radius + 1:
                self.n_relocations_ += 1
            if p["snap"] and self._snaps(front, packet, last_front, probability, radius):
                # The front end's best place, near the packet and moving with it, is more
                # likely right than the packet's window: the answer moves there.
                self.snapped_ = True
                answer = front
                confidence = self.support_ * self.front_share_
        if judged and not self.snapped_:
            # Whether the front end agreed with the sequence's confident answer: a step of the
            # model towards it, and the share of such answers it agreed with (from a prior
            # worth one answer).  A frame that snapped is not counted either way: the filter
            # itself overruled the packet's answer there, so it is no reference to judge the
            # front end by (counted as a disagreement, a drop that the packet missed would
            # lower the share the next frames' snaps weigh).
            agree = float(abs(front - packet) <= radius)
            error = agree - model_probability
            self._front_model[0] += _FRONT_RATE * error
            self._front_model[1] += _FRONT_RATE * error * feature
            self._front_agreed += agree
            self._front_checked += 1.0
        prior = 0.5 ** (2 + p["tolerance"])
        self.front_share_ = (self._front_agreed + prior) / (self._front_checked + 1.0)
        if self.source_ == "front end":
            self.probability_ = 0.0
        else:  # the probability that the sequence's answer is right: the window's, or
            # where the answer snapped, the front end's share of agreement
            self.probability_ = self.front_share_ if self.snapped_ else probability
        # The sequence's raw confidence mapped through the calibration table (strictly
        # increasing: the order of its answers stays); the front end's is its model's
        # probability already.
        calibrated = confidence
        if self.source_ == "sequence" and p["calibration"] is not None:
            calibrated = _calibrate(confidence ** (1.0 / CALIBRATION_ROOT), p["calibration"])
        # Then every answer's through the route's own table, if given (also increasing).
        if p["recalibration"] is not None:
            calibrated = _calibrate(calibrated, p["recalibration"])
        if confidence > 0.0 and calibrated != confidence:
            out *= np.float32(calibrated / confidence)  # the row keeps its order
        confidence = calibrated
        # Exactly the confidence at the answer, and no other place above it or tied with it
        # ahead of it (float32 rounding of the product could make one).
        level = np.float32(confidence)
        below = np.nextafter(level, np.float32(-1.0))
        np.minimum(out, level, out=out)
        out[:answer][out[:answer] >= level] = below
        out[answer] = level
        self.confidence_ = float(level)
        localized = self.source_ == "sequence" and self.support_ * self.probability_ >= 0.5
        self.state_ = "localized" if localized else "lost"
        self._localized_mean += rate * (float(localized) - self._localized_mean)
        mean = float(self._row_mass @ p["velocities"])  # a velocity, or with odometry a scale
        if velocity is None:
            self.velocity_ = mean
        else:
            self.velocity_ = float(velocity) * (mean if p["odometry"] == "scaled" else 1.0)
        self._layer_velocity = self.velocity_
        self.n_frames_ = t + 1
        self._last_out[:] = out
        return out
