"""What the dev window's frames allow: same-image stretches and the robot must-shows they bound.

Usage::

    python benchmarks/robot_limits.py --json benchmarks/robot-limits.json [--data DIR]

Protocol: Nordland 64x32 summer (the map) -> winter (the query), frames 0-999, the dev window
of the robot views of ``benchmarks/accuracy.py``; ``kenyon+cann`` with its defaults, seeds 0-2
(the front end's random projection), tolerance 2.

* **Same-image stretches.**  Two consecutive frames of a traverse show *the same image* when
  their mean absolute gray difference is below ``SAME`` (1% of the gray range); a stretch is a
  maximal run of such frames (the train standing in a station, or a tunnel's dark frames).
  Within a stretch of the map no front end can tell the places apart: only the motion model
  can say where in it the query is.
* **Stop-and-go** (``r-stopgo``: 1 place per frame, standing 30 frames after every 150):
  kenyon+cann's AUC as the accuracy benchmark scores it, and the same answers scored with
  the places of one same-image stretch of the map counted as one place (an answer is right
  when it lies within the tolerance of the true place, or in a map stretch holding a place
  within the tolerance).  Which stops fall in a map stretch.
* **Detour** (``r-detour``: the map leaves out places 400-699, the query drives through them;
  the CANN is given the break its places' frame numbers show, as in the accuracy benchmark):
  frames after rejoining until the answer is ``localized`` and right (as the accuracy
  benchmark counts them), the map stretches in the 30 places after the rejoin, and the front
  end's rank of the true place (places scoring strictly higher) over the 30 frames after it;
  the same ranks from each front end of ``REJOIN_FRONT_ENDS`` fitted on the same map.
* **The rejoin with more to go on**: the same detour, kenyon+cann's filter fed by ``kenyon``
  and by :class:`PixelEdges` (the benchmark's own front end: Sobel edges compared pixel for
  pixel, which Nordland's frame-aligned traverses reward), each without and with exact
  odometry (``EVIDENCE_RUNS``): frames until the answers are right, until ``localized`` and
  right, and the off-map share ``localized``; and both front ends alone on the dev window
  and on the viewpoint set's same frames (``EDGES_VIEWPOINT``), where the edges' pixel
  alignment is gone.
* **Cold start at 1x** (``r-1x``): the first frame ``localized`` and right, the query's first
  same-image stretch, and the first frame whose true place the front end ranks first.
* **Uneven frames** (``r-uneven``: a speed drawn afresh every frame, uniform in 0-2 places;
  ``r-drops``: 1 place per frame with a fifth of the frames dropped; and steady views for
  the cost): kenyon+cann's AUC with the CANN's ``jitter`` at each of ``JITTERS`` (0 is the
  default), on the same front-end scores.
* **Sequence matchers on the same scores**: how many frames each needs before its answers
  are right, on the cold start at 1x (``r-1x``, from the first frame), the same through the
  fisheye disc (``r-fisheye``) and the detour (``r-detour``, from the rejoin).  A matcher is
  *right from* frame ``t`` when its answers at ``t`` and the ``RUN - 1`` frames after it are
  all within the tolerance; the figure is ``t`` minus the first frame.  On the front end's
  scores of each seed: kenyon+cann (its defaults), kenyon+cann given the true motion as
  exact odometry (1 place per frame), and causal SeqSLAM-60 (``SEQ_LENGTH``) told the speed
  exactly (1 place per frame: a matcher that knows what the CANN must find out), with
  OpenSeqSLAM's 0.8-1.2 and with the robot speeds 0.25-3 of the accuracy benchmark.
* **The detour's rejoin moved** (not views of the accuracy benchmark): the map leaves out
  places ``REJOIN_FIRST`` up to each end of ``REJOIN_ENDS`` (700 is ``r-detour``), the query
  drives frames 0-999 in order, and the CANN is given the break.  Per end and seed: frames
  after rejoining until the answer is ``localized`` and right, and the share of off-map
  frames ``localized`` (both as the accuracy benchmark counts them), with the map's
  same-image stretches in the ``AFTER`` places from the end.
* **The fisheye start moved** (not views of the accuracy benchmark): the query at 1x from
  each frame of ``START_FRAMES`` on (0 is ``r-fisheye``), on full frames and through the
  fisheye disc, on the same front-end scores as the cold starts above: kenyon+cann's AUC at
  tolerance 2 and 20, and the fisheye gap (full frames' AUC minus the disc's).
* **Forwards and reversing** (``r-1x`` and ``r-reversed``, the dev window driven backwards):
  the share of answers right, of frames ``localized``, of the ``localized`` and of the
  ``lost`` answers right, and the mean confidence of a right answer, with the default bank and
  with ``bidirectional=True``.
* **A slow robot with a noisy camera** (not views of the accuracy benchmark): query frame
  ``k`` shows place ``floor(v k)`` for each constant speed ``v`` of ``SLOW_SPEEDS``, through
  the camera noise of the accuracy benchmark's noisy views (``SLOW_NOISE`` gray levels, seed
  ``SLOW_NOISE_SEED``), so that a place's frames are near-repeats, never exact ones (a camera
  whose frame rate is high for the map's place spacing).  Per speed: the front end's AUC
  alone, kenyon+cann's without and with odometry (places moved since the last frame, as the
  accuracy benchmark's odometry views give it), and its shares of answers right and of
  frames ``localized``.
* **The random profiles drawn again** (``r-walk`` and ``r-uneven`` draw their speeds,
  ``r-drops`` its dropped frames, from ``numpy.random.default_rng(0)``): kenyon+cann's AUC
  with the same profiles drawn from ``numpy.random.default_rng(d)`` for each ``d`` of
  ``PROFILE_SEEDS`` (draw 0: the accuracy benchmark's own), with the CANN's ``jitter`` at
  each of ``JITTERS``, on the 1x view's front-end scores of each seed.
* **Parked** (not a view of the accuracy benchmark): the query drives at 1 place per frame to
  place ``a``, stands there ``PARK_FRAMES`` frames (its one winter frame repeated, as a
  robot's camera sees a parked scene), then drives on ``PARK_AFTER`` frames.  ``PARK_PLACES``
  stop places drawn with ``numpy.random.default_rng(PARK_SEED)`` from 200-799, none within 3
  places of a map stretch.  Per stand length: the share of the stand's answers right and
  ``localized``, split by whether the front end ranks the stop's true place within the
  tolerance first (its single-frame answer there), and the share right over the frames after.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import machine, machine_sentence, run_page_benchmark  # noqa: E402
from benchmarks.accuracy_run import _detour, _stream, gap_keep, load_dataset  # noqa: E402
from benchmarks.accuracy_setup import (  # noqa: E402
    DATASETS,
    ROBOT_SPEEDS,
    ROBOT_VIEWS,
    camera_frames,
    fisheye,
    motion_places,
)
from flyvpr import metrics  # noqa: E402
from flyvpr.datasets import ground_truth_from_frames  # noqa: E402
from flyvpr.methods import make_method  # noqa: E402
from flyvpr.temporal.cann import route_breaks  # noqa: E402
from flyvpr.temporal.seqslam import SeqSLAM  # noqa: E402

DATASET = "n64-0"
SEEDS = (0, 1, 2)
TOLERANCE = 2
#: consecutive frames are the same image below this mean absolute gray difference
SAME = 0.01
#: the CANN's jitter values compared on uneven and steady frames (0: the default)
JITTERS = (0.0, 0.15, 0.3)
#: the views they are compared on: uneven frames first, then steady ones (what it costs)
JITTER_VIEWS = ("r-uneven", "r-drops", "r-1x", "r-2.5x", "r-walk", "r-stopgo")
#: the reversing runs of the state table: (view, bank, the filter's parameters)
REVERSING = (
    ("r-1x", "bidirectional", {"bidirectional": True}),
    ("r-reversed", "default", {}),
    ("r-reversed", "bidirectional", {"bidirectional": True}),
)
#: frames after the rejoin that the detour's figures cover (the must-show's bound)
AFTER = 30
#: a matcher is right from a frame when that frame and the RUN - 1 after it are all right
RUN = 10
#: SeqSLAM's sequence length in the matcher comparison (the accuracy benchmark's best)
SEQ_LENGTH = 60
#: the SeqSLAM speed ranges compared (places per frame): the true speed, OpenSeqSLAM's range
#: and the accuracy benchmark's robot range
SEQ_SPEEDS = {
    "exact speed (1)": {"v_min": 1.0, "v_max": 1.0, "v_step": 0.125},
    "0.8-1.2": {"v_min": 0.8, "v_max": 1.2, "v_step": 0.1},
    "0.25-3": ROBOT_SPEEDS,
}
#: a slow robot with a noisy camera: constant speeds (places per frame), the camera noise (sd,
#: gray levels of 255) and the seed that draws it (the accuracy benchmark's noisy views')
SLOW_SPEEDS = (0.2, 0.33, 0.5, 1.0)
SLOW_NOISE = 1.0
SLOW_NOISE_SEED = 0
#: the random speed profiles drawn again: their motions and the seeds that draw them (0 is the
#: accuracy benchmark's own draw)
PROFILE_KINDS = ("walk", "uneven", "drops")
PROFILE_SEEDS = tuple(range(8))
#: the benchmark's own pixel-aligned front end (:class:`PixelEdges`), not one of the library
EDGES = "Sobel edges, pixel for pixel (this benchmark only)"
#: the window where the pixel-aligned front end meets a camera that moved (the viewpoint set)
EDGES_VIEWPOINT = "vp-0"
#: the front ends compared after the detour's rejoin: (label, method, front-end parameters,
#: whether it takes a seed: one without is run for the first seed only)
REJOIN_FRONT_ENDS = (
    ("kenyon", "kenyon", {}, True),
    ("kenyon, intensity channel", "kenyon", {"intensity": True}, True),
    ("pixels", "pixels", {}, False),
    ("flyhash", "flyhash", {}, True),
    ("flynet", "flynet", {}, True),
    (EDGES, "edges", {}, False),
)
#: the detour again with more to go on: (front end of REJOIN_FRONT_ENDS, exact odometry)
EVIDENCE_RUNS = (("kenyon", False), ("kenyon", True), ("edges", False), ("edges", True))
#: the detour's rejoin moved: the map leaves out places REJOIN_FIRST to end - 1 for each end
#: (700: the accuracy benchmark's r-detour)
REJOIN_FIRST = 400
REJOIN_ENDS = (600, 650, 680, 690, 700, 710, 720, 730, 750, 800, 850)
#: the fisheye cold start moved: the 1x query from each of these frames on (0: r-fisheye)
START_FRAMES = (0, 25, 50, 100, 200, 300, 400)
#: the tolerances of the fisheye start's figures (the must-show's two)
START_TOLERANCES = (2, 20)
#: parked robot: stand lengths (frames), stop places, the seed that draws them, frames after
PARK_FRAMES = (30, 100, 300, 1000)
PARK_PLACES = 12
PARK_SEED = 5
PARK_AFTER = 100


def same_image_stretches(images: np.ndarray, same: float = SAME) -> list[tuple[int, int]]:
    """(first, last) frame of every maximal run of consecutive frames whose mean absolute
    difference is below ``same``."""
    flat = images.reshape(len(images), -1).astype(np.float64)
    still = np.abs(np.diff(flat, axis=0)).mean(axis=1) < same  # frame i+1 repeats frame i
    out, start = [], None
    for i, s in enumerate(still):
        if s and start is None:
            start = i
        elif not s and start is not None:
            out.append((start, i))
            start = None
    if start is not None:
        out.append((start, len(still)))
    return out


def place_groups(n: int, stretches) -> np.ndarray:
    """A group per place: the places of one stretch share one, every other place has its own."""
    group = np.arange(n)
    for first, last in stretches:
        group[first : last + 1] = first
    return group


def as_one(gt: np.ndarray, group: np.ndarray) -> np.ndarray:
    """``gt`` with every place of a group right where any place of the group is."""
    ids, inverse = np.unique(group, return_inverse=True)
    onehot = np.zeros((len(group), len(ids)), bool)
    onehot[np.arange(len(group)), inverse] = True
    return (gt.astype(np.float32) @ onehot.astype(np.float32) > 0)[:, inverse]


def parked_places(stop: int, frames: int, after: int, n: int) -> np.ndarray:
    """True place per query frame: 1 place per frame from 0 to ``stop``, ``frames`` frames at
    ``stop`` (the first of them the arrival), then on for ``after`` frames (within ``n``)."""
    if not 0 <= stop < n:
        raise ValueError(f"stop must be in [0, {n}); got {stop}")
    drive_on = np.arange(stop + 1, min(stop + 1 + after, n))
    return np.concatenate([np.arange(stop), np.full(frames, stop), drive_on]).astype(np.int64)


def stop_places(in_stretch: np.ndarray, count: int, seed: int, margin: int = 3) -> list[int]:
    """``count`` distinct places of the middle 60% of the map, drawn with ``seed``, none
    within ``margin`` places of a place in a same-image stretch (``in_stretch``)."""
    n = in_stretch.size
    near = np.convolve(in_stretch.astype(int), np.ones(2 * margin + 1, int), mode="same") > 0
    allowed = np.flatnonzero(~near[int(0.2 * n) : int(0.8 * n)]) + int(0.2 * n)
    if allowed.size < count:
        raise ValueError(f"only {allowed.size} places away from the stretches; need {count}")
    rng = np.random.default_rng(seed)
    return sorted(int(a) for a in rng.choice(allowed, size=count, replace=False))


def _parked(seed: int, ref, qry, stops) -> list[dict]:
    """Per stand length, kenyon+cann's answers through every stop (see the module's text)."""
    method = make_method("kenyon+cann", seed, {}, {})
    method.frontend.fit(ref)
    S = method.frontend.score(qry)
    n = len(ref)
    filt = method.filter
    fe_right = {a: abs(int(np.argmax(S[a])) - a) <= TOLERANCE for a in stops}
    rows = []
    for frames in PARK_FRAMES:
        during = {True: [], False: []}
        localized = {True: [], False: []}
        after = []
        for a in stops:
            truth = parked_places(a, frames, PARK_AFTER, n)
            filt.reset()
            right = np.empty(len(truth), bool)
            state = np.empty(len(truth), bool)
            for t, place in enumerate(truth):
                right[t] = abs(int(np.argmax(filt.step(S[place]))) - place) <= TOLERANCE
                state[t] = filt.state_ == "localized"
            during[fe_right[a]].append(right[a : a + frames].mean())
            localized[fe_right[a]].append(state[a : a + frames].mean())
            after.append(right[a + frames :].mean())
        row = {"seed": seed, "frames": frames, "right_after": float(np.mean(after))}
        for key, flag in (("front_right", True), ("front_wrong", False)):
            row[f"stops_{key}"] = len(during[flag])
            row[f"right_{key}"] = float(np.mean(during[flag])) if during[flag] else None
            row[f"localized_{key}"] = float(np.mean(localized[flag])) if during[flag] else None
        rows.append(row)
    return rows


class PixelEdges:
    """A front end of this benchmark only: every pixel's Sobel gradient magnitude (the frame's
    own, 3x3), the vector centred and scaled to unit length per frame, scored by cosine.

    Nothing is pooled, so a query frame scores high only against a map frame whose edges lie
    on the same pixels: it uses that Nordland's two traverses were filmed from one mount,
    frame-aligned.  It is here to ask what a filter does with evidence that kenyon's pooled,
    shift-tolerant codes do not give on the detour's rejoin, not as a front end for cameras
    that move (its figures on the viewpoint set say why).
    """

    def fit(self, images) -> PixelEdges:
        self.reference_ = self._encode(images)
        return self

    def score(self, images) -> np.ndarray:
        return (self._encode(images) @ self.reference_.T).astype(np.float32)

    @staticmethod
    def _encode(images) -> np.ndarray:
        x = np.asarray(images, np.float32)
        # derivative along one image axis, smoothing along the other: never across frames
        gx = ndimage.correlate1d(ndimage.correlate1d(x, [-1, 0, 1], axis=2), [1, 2, 1], axis=1)
        gy = ndimage.correlate1d(ndimage.correlate1d(x, [-1, 0, 1], axis=1), [1, 2, 1], axis=2)
        g = np.hypot(gx, gy).reshape(len(x), -1)
        g -= g.mean(axis=1, keepdims=True)
        norm = np.linalg.norm(g, axis=1, keepdims=True)
        return g / np.where(norm > 0, norm, 1)


def _plain_labels() -> dict[str, str]:
    """Each front end's label in REJOIN_FRONT_ENDS with its default parameters."""
    return {name: label for label, name, params, _ in REJOIN_FRONT_ENDS if not params}


def _front_end(name: str, seed: int, params: dict):
    """An unfitted front end of REJOIN_FRONT_ENDS."""
    return PixelEdges() if name == "edges" else make_method(name, seed, params).frontend


def _view(key: str):
    return next(v for v in ROBOT_VIEWS if v.key == key)


def _run(seed: int, view, ref, qry, ref_ids, qry_ids, filter_params=None):
    """kenyon+cann (its filter with ``filter_params``) over the view: rows, localized flags,
    the front end's scores and ground truth, and the map's place ids."""
    keep = np.arange(len(ref)) if view.gap is None else gap_keep(len(ref), view.gap)
    filter_params = dict(filter_params or {})
    if view.gap is not None:  # (the map's places keep their frame numbers: its break)
        filter_params["breaks"] = route_breaks(ref_ids[keep])
    method = make_method("kenyon+cann", seed, {}, filter_params)
    method.frontend.fit(ref[keep])
    idx = view.indices(len(qry))
    S = method.frontend.score(view.frames(qry, idx))
    filt = method.filter
    filt.reset()
    out = np.empty(S.shape, np.float32)
    localized = np.zeros(len(S), bool)
    for t in range(len(S)):
        out[t] = filt.step(S[t])
        localized[t] = filt.state_ == "localized"
    gt = ground_truth_from_frames(qry_ids[idx], ref_ids[keep], TOLERANCE)
    return out, localized, S, gt, ref_ids[keep], qry_ids[idx]


def _jitter_rows(seed: int, S: np.ndarray, qry_ids, ref_ids) -> list[dict]:
    """kenyon+cann's AUC on each of JITTER_VIEWS with each of JITTERS, from the front end's
    scores ``S`` of every query frame (a motion view's frames are query frames)."""
    rows = []
    for key in JITTER_VIEWS:
        idx = _view(key).indices(len(S))
        gt = ground_truth_from_frames(qry_ids[idx], ref_ids, TOLERANCE)
        for jitter in JITTERS:
            filt = make_method("kenyon+cann", seed, {}, {"jitter": jitter}).filter
            out = filt.filter(S[idx])
            rows.append(
                {
                    "seed": seed,
                    "view": key,
                    "jitter": jitter,
                    "auc": metrics.evaluate(out, gt, ks=(1,))["auc"],
                }
            )
    return rows


def _profile_rows(seed: int, S: np.ndarray, qry_ids, ref_ids) -> list[dict]:
    """kenyon+cann's AUC on each of PROFILE_KINDS drawn from each of PROFILE_SEEDS, with the
    CANN's ``jitter`` at each of JITTERS, from the front end's scores ``S`` of every query
    frame in order."""
    rows = []
    for kind in PROFILE_KINDS:
        for draw in PROFILE_SEEDS:
            idx = motion_places(kind, len(S), draw)
            gt = ground_truth_from_frames(qry_ids[idx], ref_ids, TOLERANCE)
            for jitter in JITTERS:
                filt = make_method("kenyon+cann", seed, {}, {"jitter": jitter}).filter
                rows.append(
                    {
                        "seed": seed,
                        "motion": kind,
                        "draw": draw,
                        "jitter": jitter,
                        "auc": metrics.evaluate(filt.filter(S[idx]), gt, ks=(1,))["auc"],
                    }
                )
    return rows


def slow_places(speed: float, n: int) -> np.ndarray:
    """The true place of every query frame of a robot at ``speed`` places per frame."""
    places = np.floor(speed * np.arange(int(np.ceil(n / speed)) + 1)).astype(np.int64)
    return places[places < n]


def _slow_rows(seed: int, ref, qry, ref_ids, qry_ids) -> list[dict]:
    """kenyon+cann at each of SLOW_SPEEDS through a noisy camera, without and with
    odometry (see the module's docstring)."""
    frontend = make_method("kenyon", seed, {}, {}).frontend
    frontend.fit(ref)
    rows = []
    for speed in SLOW_SPEEDS:
        idx = slow_places(speed, len(qry))
        S = frontend.score(camera_frames(qry[idx], SLOW_NOISE, SLOW_NOISE_SEED))
        gt = ground_truth_from_frames(qry_ids[idx], ref_ids, TOLERANCE)
        alone = metrics.evaluate(S, gt, ks=(1,))["auc"]
        steps = np.abs(np.diff(qry_ids[idx], prepend=qry_ids[idx][:1])).astype(np.float64)
        for odometry in (False, True):
            filt = make_method("kenyon+cann", seed, {}, {}).filter
            filt.reset()
            out = np.empty(S.shape, np.float32)
            localized = np.zeros(len(S), bool)
            for t in range(len(S)):
                v = float(steps[t]) if odometry and t > 0 else None
                out[t] = filt.step(S[t]) if v is None else filt.step(S[t], velocity=v)
                localized[t] = filt.state_ == "localized"
            right = gt[np.arange(len(out)), out.argmax(axis=1)]
            rows.append(
                {
                    "seed": seed,
                    "speed": speed,
                    "odometry": odometry,
                    "frames": len(idx),
                    "auc_front_end": alone,
                    "auc": metrics.evaluate(out, gt, ks=(1,))["auc"],
                    "right": float(right.mean()),
                    "localized": float(localized.mean()),
                }
            )
    return rows


def state_row(seed: int, view: str, bank: str, out, localized, gt) -> dict:
    """How right the answers of one run are, and how its state and confidence say so."""
    right = gt[np.arange(len(out)), out.argmax(axis=1)]
    confidence = out.max(axis=1).astype(np.float64)

    def share(mask):
        return float(right[mask].mean()) if mask.any() else None

    return {
        "seed": seed,
        "view": view,
        "bank": bank,
        "right": float(right.mean()),
        "localized": float(localized.mean()),
        "right_when_localized": share(localized),
        "right_when_lost": share(~localized),
        "confidence_when_right": float(confidence[right].mean()) if right.any() else None,
    }


def stretches_from(stretches, first: int, count: int = AFTER) -> list[tuple[int, int]]:
    """The stretches (first, last) that hold a place of ``first .. first + count - 1``."""
    return [(a, b) for a, b in stretches if b >= first and a < first + count]


def _front_end_rows(seed: int, ref, qry, ref_ids, qry_ids) -> list[dict]:
    """Each of REJOIN_FRONT_ENDS on the detour's map: its rank of the true place (places
    scoring strictly higher) over the AFTER frames from the rejoin on (a front end without a
    seed on the first of SEEDS only)."""
    view = _view("r-detour")
    keep = gap_keep(len(ref), view.gap)
    back = int(view.gap[1] * len(ref))
    left_out = [int(ref_ids[i]) for i in np.setdiff1d(np.arange(len(ref)), keep)[[0, -1]]]
    frames = view.indices(len(qry))[back : back + AFTER]
    rows = []
    for label, name, params, seeded in REJOIN_FRONT_ENDS:
        if not seeded and seed != SEEDS[0]:
            continue
        frontend = _front_end(name, seed, params)
        frontend.fit(ref[keep])
        rank = _true_rank(frontend.score(view.frames(qry, frames)), qry_ids[frames], ref_ids[keep])
        rows.append(
            {
                "seed": seed,
                "front_end": label,
                "map_leaves_out": left_out,
                "seeded": seeded,
                "rank_median": float(np.median(rank)),
                "rank_best": int(rank.min()),
                "top10_frames": int((rank < 10).sum()),
                "top1_frames": int((rank == 0).sum()),
            }
        )
    return rows


def _evidence_rows(seed: int, ref, qry, ref_ids, qry_ids, scores=None) -> list[dict]:
    """The detour of kenyon+cann's filter (given the map's break) fed by each front end of
    EVIDENCE_RUNS, without and with exact odometry (1 place per frame, none on the first
    frame): frames from the rejoin until the answers are right (``right_from``) and until
    the answer is ``localized`` and right, the off-map share ``localized``, and the share of
    the ``2 AFTER`` frames from the rejoin whose answer is the front end's (the filter's
    ``source_``: a hint handed on, never ``localized``).  The benchmark's PixelEdges has no
    seed: on the first of SEEDS only.  ``scores``: front-end scores of the view already
    computed, by name (the detour run's kenyon scores), not computed again."""
    view = _view("r-detour")
    keep = gap_keep(len(ref), view.gap)
    back = int(view.gap[1] * len(ref))
    idx = view.indices(len(qry))
    gt = ground_truth_from_frames(qry_ids[idx], ref_ids[keep], TOLERANCE)
    params = {"breaks": route_breaks(ref_ids[keep])}
    labels = _plain_labels()
    scores = dict(scores or {})
    rows = []
    for name, exact in EVIDENCE_RUNS:
        if name == "edges" and seed != SEEDS[0]:
            continue
        if name not in scores:
            frontend = _front_end(name, seed, {})
            frontend.fit(ref[keep])
            scores[name] = frontend.score(view.frames(qry, idx))
        filt = make_method(
            "kenyon+cann", seed, {}, {**params, "odometry": "exact"} if exact else params
        ).filter
        S = scores[name]
        sources: list = []
        out, localized = _stream(filt, S, np.ones(len(S)) if exact else None, sources)
        detour = _detour(qry_ids[idx], ref_ids[keep], out, localized, TOLERANCE)
        after = sources[back : back + 2 * AFTER]
        rows.append(
            {
                "seed": seed,
                "front_end": labels[name],
                "exact_odometry": exact,
                "right_from": right_from(gt[np.arange(len(out)), out.argmax(axis=1)], back),
                "rejoin_frames": detour["rejoin_frames"],
                "offmap_localized_share": detour["offmap_localized_share"],
                "front_end_answers": float(np.mean([s == "front end" for s in after]))
                if after
                else None,
            }
        )
    return rows


def _alone_rows(seed: int, views: dict) -> list[dict]:
    """kenyon and PixelEdges alone (no filter) on each window of ``views`` (key: reference,
    query, their ids): AUC and R@1 at the tolerance, the whole query against the whole map.
    PixelEdges on the first of SEEDS only."""
    labels = _plain_labels()
    rows = []
    for key, (ref, qry, ref_ids, qry_ids) in views.items():
        gt = ground_truth_from_frames(qry_ids, ref_ids, TOLERANCE)
        for name in ("kenyon", "edges"):
            if name == "edges" and seed != SEEDS[0]:
                continue
            frontend = _front_end(name, seed, {})
            frontend.fit(ref)
            S = frontend.score(qry)
            result = metrics.evaluate(S, gt, ks=(1,))
            rows.append(
                {
                    "seed": seed,
                    "window": key,
                    "front_end": labels[name],
                    "auc": result["auc"],
                    "recall_at_1": result["recall_at_1"],
                }
            )
    return rows


def _rejoin_rows(seed: int, ref, qry, ref_ids, qry_ids) -> list[dict]:
    """kenyon+cann on the detour for each end of REJOIN_ENDS (see the module's text)."""
    rows = []
    for end in REJOIN_ENDS:
        keep = np.r_[0:REJOIN_FIRST, end : len(ref)]
        breaks = route_breaks(ref_ids[keep])
        method = make_method("kenyon+cann", seed, {}, {"breaks": breaks})
        method.frontend.fit(ref[keep])
        out, localized = _stream(method.filter, method.frontend.score(qry), None)
        detour = _detour(qry_ids, ref_ids[keep], out, localized, TOLERANCE)
        rows.append(
            {
                "seed": seed,
                "first": REJOIN_FIRST,
                "end": end,
                "rejoin_frames": detour["rejoin_frames"],
                "offmap_localized_share": detour["offmap_localized_share"],
            }
        )
    return rows


def _start_rows(seed: int, full: np.ndarray, disc: np.ndarray, qry_ids, ref_ids) -> list[dict]:
    """kenyon+cann from each frame of START_FRAMES on, on the 1x view's scores of the full
    frames (``full``) and through the fisheye disc (``disc``): AUC per tolerance."""
    rows = []
    for start in START_FRAMES:
        row: dict = {"seed": seed, "start": start}
        for name, S in (("full", full), ("fisheye", disc)):
            out, _ = _stream(make_method("kenyon+cann", seed).filter, S[start:], None)
            for tol in START_TOLERANCES:
                gt = ground_truth_from_frames(qry_ids[start:], ref_ids, tol)
                row[f"{name}_auc_{tol}"] = metrics.evaluate(out, gt, ks=(1,))["auc"]
        rows.append(row)
    return rows


def right_from(right: np.ndarray, start: int = 0, run: int = RUN) -> int | None:
    """Frames from ``start`` to the first frame ``t >= start`` whose answer and the ``run - 1``
    answers after it are all right (``right``: bool per frame); None if there is none."""
    if run < 1:
        raise ValueError(f"run must be >= 1; got {run}")
    if start < 0:
        raise ValueError(f"start must be >= 0; got {start}")
    ok = np.asarray(right, bool)[start:]
    if ok.size < run:
        return None
    window = np.convolve(ok.astype(np.int64), np.ones(run, np.int64), mode="valid")
    hits = np.flatnonzero(window == run)
    return int(hits[0]) if hits.size else None


def _matchers(
    seed: int, key: str, start: int, S: np.ndarray, gt: np.ndarray, out, breaks=()
) -> dict:
    """Frames until each matcher of the comparison is right (see ``right_from``), on the
    front end's scores ``S`` of one view (``out``: kenyon+cann's rows on them; ``breaks``:
    the map's, for the CANN)."""
    frames = np.arange(len(S))

    def from_rows(rows) -> int | None:
        return right_from(gt[frames, np.asarray(rows).argmax(axis=1)], start)

    row = {"seed": seed, "view": key, "start": start, "kenyon+cann": from_rows(out)}
    odo = make_method("kenyon+cann", seed, {}, {"odometry": "exact", "breaks": breaks}).filter
    odo.reset()
    # (no odometry for the first frame, as the accuracy benchmark streams it)
    steps = [odo.step(s, velocity=None if t == 0 else 1.0) for t, s in enumerate(S)]
    row["kenyon+cann, exact odometry"] = from_rows(steps)
    for label, speeds in SEQ_SPEEDS.items():
        seq = SeqSLAM(sequence_length=SEQ_LENGTH, **speeds)
        row[f"SeqSLAM-{SEQ_LENGTH}, {label}"] = from_rows(seq.filter(S.astype(np.float64)))
    return row


def _true_rank(S: np.ndarray, truth: np.ndarray, map_ids: np.ndarray) -> np.ndarray:
    """Per frame, the number of map places scoring strictly higher than the true place (-1
    where the true place is not in the map)."""
    col = {int(p): j for j, p in enumerate(map_ids)}
    out = np.full(len(S), -1)
    for t, p in enumerate(truth):
        j = col.get(int(p))
        if j is not None:
            out[t] = int((S[t] > S[t, j]).sum())
    return out


def run(data: Path, progress: bool = True) -> dict:
    dataset = {d.key: d for d in DATASETS}[DATASET]
    ref, qry, ref_ids, qry_ids, _ = load_dataset(dataset, data)
    map_stretches = same_image_stretches(ref)
    query_stretches = same_image_stretches(qry)
    group = place_groups(len(ref), map_stretches)
    in_stretch = np.zeros(len(ref), bool)
    for first, last in map_stretches:
        in_stretch[first : last + 1] = True

    stopgo, detour, cold, parked, uneven, matchers, states = [], [], [], [], [], [], []
    slow: list[dict] = []
    profiles: list[dict] = []
    rejoins: list[dict] = []
    front_ends: list[dict] = []
    starts: list[dict] = []
    vp = load_dataset({d.key: d for d in DATASETS}[EDGES_VIEWPOINT], data)
    windows = {DATASET: (ref, qry, ref_ids, qry_ids), EDGES_VIEWPOINT: vp[:4]}
    evidence: list[dict] = []
    alone: list[dict] = []
    fish_ref, fish_qry = fisheye(ref), fisheye(qry)
    park_stops = stop_places(in_stretch, PARK_PLACES, PARK_SEED)
    for seed in SEEDS:
        if progress:
            print(f"  seed {seed}", file=sys.stderr, flush=True)
        # stop-and-go
        out, _, _, gt, _, truth = _run(seed, _view("r-stopgo"), ref, qry, ref_ids, qry_ids)
        places, counts = np.unique(truth, return_counts=True)
        stops = [int(p) for p in places[counts > 1]]
        stopgo.append(
            {
                "seed": seed,
                "auc": metrics.evaluate(out, gt, ks=(1,))["auc"],
                "auc_same_image_as_one": metrics.evaluate(out, as_one(gt, group), ks=(1,))["auc"],
                "stops": stops,
                "stops_in_a_map_stretch": [p for p in stops if in_stretch[p]],
            }
        )
        # detour
        view = _view("r-detour")
        out, localized, S, gt, map_ids, truth = _run(seed, view, ref, qry, ref_ids, qry_ids)
        back = int(view.gap[1] * len(ref))  # the first frame on the map again
        right = gt[np.arange(len(out)), out.argmax(axis=1)]
        hit = np.flatnonzero(localized[back:] & right[back:])
        rank = _true_rank(S[back : back + AFTER], truth[back : back + AFTER], map_ids)
        matchers.append(_matchers(seed, "r-detour", back, S, gt, out, route_breaks(map_ids)))
        front_ends += _front_end_rows(seed, ref, qry, ref_ids, qry_ids)
        evidence += _evidence_rows(seed, ref, qry, ref_ids, qry_ids, {"kenyon": S})
        alone += _alone_rows(seed, windows)
        detour.append(
            {
                "seed": seed,
                "rejoin_frames": int(hit[0]) if hit.size else None,
                "front_rank_median": float(np.median(rank)),
                "front_rank_top10_frames": int((rank < 10).sum()),
                "first_front_top1": next((i for i, r in enumerate(rank) if r == 0), None),
            }
        )
        # cold start at 1x
        view = _view("r-1x")
        out, localized, S, gt, map_ids, truth = _run(seed, view, ref, qry, ref_ids, qry_ids)
        right = gt[np.arange(len(out)), out.argmax(axis=1)]
        hit = np.flatnonzero(localized & right)
        rank = _true_rank(S, truth, map_ids)
        matchers.append(_matchers(seed, "r-1x", 0, S, gt, out))
        cold.append(
            {
                "seed": seed,
                "first_localized_right": int(hit[0]) if hit.size else None,
                "first_front_top1": int(np.flatnonzero(rank == 0)[0]),
                "right_share": float(right.mean()),
            }
        )
        # the same cold start through the fisheye disc
        fish_run = _run(seed, _view("r-fisheye"), fish_ref, fish_qry, ref_ids, qry_ids)
        matchers.append(_matchers(seed, "r-fisheye", 0, fish_run[2], fish_run[3], fish_run[0]))
        starts += _start_rows(seed, S, fish_run[2], qry_ids, ref_ids)
        rejoins += _rejoin_rows(seed, ref, qry, ref_ids, qry_ids)
        parked += _parked(seed, ref, qry, park_stops)
        # forwards and reversing, with the default bank and the mirrored one
        states.append(state_row(seed, "r-1x", "default", out, localized, gt))
        for key, bank, params in REVERSING:
            run_ = _run(seed, _view(key), ref, qry, ref_ids, qry_ids, params)
            states.append(state_row(seed, key, bank, run_[0], run_[1], run_[3]))
        # (the 1x view's scores: every query frame, in order, against the whole map)
        assert S.shape == (len(qry), len(ref))
        uneven += _jitter_rows(seed, S, qry_ids, ref_ids)
        slow += _slow_rows(seed, ref, qry, ref_ids, qry_ids)
        profiles += _profile_rows(seed, S, qry_ids, ref_ids)
    back = int(_view("r-detour").gap[1] * len(ref))
    return {
        "benchmark": "robot-limits",
        "protocol": {
            "method": "kenyon+cann (defaults)",
            "data": "nordland_64x32 summer (map) -> winter (query), frames 0-999 (dev window)",
            "seeds": list(SEEDS),
            "tolerance": TOLERANCE,
            "same_image": f"consecutive frames with a mean absolute gray difference below {SAME}",
            "views": ["r-stopgo", "r-detour", "r-1x", "r-fisheye"],
            "matchers": f"right from a frame: it and the {RUN - 1} frames after it right; "
            f"SeqSLAM-{SEQ_LENGTH} causal, on kenyon's scores of the seed",
            "detour_after": f"the {AFTER} frames after the rejoin (frame {back})",
            "parked": f"1 place per frame to a stop, stand, then {PARK_AFTER} frames on; "
            f"{PARK_PLACES} stops drawn with seed {PARK_SEED} from places 200-799 at least 4 "
            "places from a map stretch",
            "profiles": "draw d: the profile drawn with numpy.random.default_rng(d), "
            f"d in {list(PROFILE_SEEDS)}; draw 0 is the accuracy benchmark's own",
            "rejoin_evidence": "the map without 400-699, the CANN given its break; "
            "kenyon+cann's filter fed by kenyon and by the benchmark's pixel-aligned Sobel "
            f"edges (no seed: run with seed {SEEDS[0]} only), without and with exact odometry "
            "(1 place per frame)",
            "front_ends_alone": f"kenyon (seeds {', '.join(map(str, SEEDS))}) and the Sobel "
            f"edges alone on {DATASET} (the dev window) and {EDGES_VIEWPOINT} (the same frames, "
            "winter seen from a drifting viewpoint): the whole query against the whole map",
            "rejoins": f"The map leaves out places {REJOIN_FIRST} to end - 1, end in "
            f"{list(REJOIN_ENDS)} (700: r-detour); the query drives frames 0-999 at 1x",
            "starts": f"The 1x query from frame s on, s in {list(START_FRAMES)} (0: r-fisheye); "
            f"full frames and the fisheye disc; tolerances {list(START_TOLERANCES)}",
            "slow": f"query frame k shows place floor(v k), v in {list(SLOW_SPEEDS)}, camera "
            f"noise sd {SLOW_NOISE:g} gray levels (seed {SLOW_NOISE_SEED}); odometry: places "
            "moved since the last frame",
        },
        "machine": machine(),
        "map_stretches": [list(s) for s in map_stretches],
        "query_stretches": [list(s) for s in query_stretches],
        "map_places_in_stretches": int(in_stretch.sum()),
        "rejoin_map_stretches": [
            list(s) for s in map_stretches if s[1] >= back and s[0] < back + AFTER
        ],
        "stopgo": stopgo,
        "detour": detour,
        "cold_start": cold,
        "parked_stops": park_stops,
        "parked": parked,
        "jitter": uneven,
        "matchers": matchers,
        "rejoin_front_ends": front_ends,
        "rejoin_evidence": evidence,
        "front_ends_alone": alone,
        "states": states,
        "slow": slow,
        "profiles": profiles,
        "rejoins": rejoins,
        "rejoin_stretches": {
            str(end): [list(t) for t in stretches_from(map_stretches, end)] for end in REJOIN_ENDS
        },
        "starts": starts,
    }


def _stretches(s) -> str:
    return ", ".join(f"{a}-{b}" for a, b in s) or "none"


def parked_summary(rows: list[dict]) -> list[dict]:
    """Per stand length, the parked rows of all seeds pooled: shares weighted by their stops."""
    out = []
    for frames in sorted({r["frames"] for r in rows}):
        mine = [r for r in rows if r["frames"] == frames]
        row = {"frames": frames, "right_after": float(np.mean([r["right_after"] for r in mine]))}
        for key in ("front_right", "front_wrong"):
            count = sum(r[f"stops_{key}"] for r in mine)
            row[f"stops_{key}"] = count
            for name in ("right", "localized"):
                total = sum(
                    r[f"{name}_{key}"] * r[f"stops_{key}"] for r in mine if r[f"stops_{key}"]
                )
                row[f"{name}_{key}"] = total / count if count else None
        out.append(row)
    return out


def _share(value) -> str:
    return "-" if value is None else f"{value:.2f}"


def _parked_table(data: dict) -> list[str]:
    lines = [
        "",
        "## Parked",
        "",
        f"{data['protocol']['parked']}: places {', '.join(map(str, data['parked_stops']))}.  "
        "Shares over the stand's frames, the stops pooled over the seeds, split by the front "
        "end's own answer at the stop.",
        "",
        "| frames standing | front end right at the stop: stops / right / localized | "
        "front end wrong: stops / right / localized | right after it |",
        "|---|---|---|---|",
    ]
    for r in parked_summary(data["parked"]):
        lines.append(
            f"| {r['frames']} | {r['stops_front_right']} / {_share(r['right_front_right'])} / "
            f"{_share(r['localized_front_right'])} | {r['stops_front_wrong']} / "
            f"{_share(r['right_front_wrong'])} / {_share(r['localized_front_wrong'])} | "
            f"{r['right_after']:.2f} |"
        )
    return lines


def _jitter_table(data: dict) -> list[str]:
    """Mean AUC over the seeds per view (rows) and jitter (columns)."""
    rows = data["jitter"]
    jitters = sorted({r["jitter"] for r in rows})
    views = list(dict.fromkeys(r["view"] for r in rows))
    labels = {v.key: v.label for v in ROBOT_VIEWS}
    lines = [
        "",
        "## Uneven frames: the CANN's jitter",
        "",
        "AUC, mean over the seeds, kenyon+cann with `jitter` at each value (0: the default).",
        "",
        "| view | " + " | ".join(f"jitter {j:g}" for j in jitters) + " |",
        "|---|" + "---|" * len(jitters),
    ]
    for view in views:
        cells = []
        for j in jitters:
            aucs = [r["auc"] for r in rows if r["view"] == view and r["jitter"] == j]
            cells.append(f"{np.mean(aucs):.3f}")
        lines.append(f"| {labels.get(view, view)} | " + " | ".join(cells) + " |")
    return lines


def _states_table(data: dict) -> list[str]:
    """Per view and bank, the shares of :func:`state_row`, mean over the seeds."""
    rows = data["states"]
    labels = {v.key: v.label for v in ROBOT_VIEWS}
    keys = (
        "right",
        "localized",
        "right_when_localized",
        "right_when_lost",
        "confidence_when_right",
    )
    lines = [
        "",
        "## Forwards and reversing: what the state says",
        "",
        "kenyon+cann on the dev window driven forwards and backwards, with the default bank "
        "(backwards: -2 to -0.5 in steps of 0.5) and with `bidirectional=True` (the whole bank "
        "mirrored); mean over the seeds.  Right: within the tolerance.",
        "",
        "| view | bank | right | `localized` | right when `localized` | right when `lost` | "
        "mean confidence of a right answer |",
        "|---|---|---|---|---|---|---|",
    ]
    for view, bank in dict.fromkeys((r["view"], r["bank"]) for r in rows):
        picked = [r for r in rows if r["view"] == view and r["bank"] == bank]
        cells = []
        for key in keys:
            values = [r[key] for r in picked if r[key] is not None]
            cells.append(f"{np.mean(values):.3f}" if values else "-")
        lines.append(f"| {labels.get(view, view)} | {bank} | " + " | ".join(cells) + " |")
    return lines


def _profiles_table(data: dict) -> list[str]:
    """Per motion, the AUC of each draw of its profile (mean over the seeds)."""
    rows = data["profiles"]
    draws = sorted({r["draw"] for r in rows})
    labels: dict[str, str] = {}
    for v in ROBOT_VIEWS:  # the dev window's view of each motion, as the robot page names it
        if v.dataset == DATASET and v.motion and not (v.odometry or v.camera_noise):
            labels.setdefault(v.motion, v.label)
    lines = [
        "",
        "## The random profiles drawn again",
        "",
        f"kenyon+cann's AUC with each random profile drawn again ({data['protocol']['profiles']}"
        "), with the CANN's `jitter` at each value (0: the default), on the same front-end "
        "scores; mean over the front end's seeds.",
        "",
        "| motion | jitter | " + " | ".join(f"draw {d}" for d in draws) + " | lowest | mean |",
        "|---|---|" + "---|" * (len(draws) + 2),
    ]
    for motion, jitter in dict.fromkeys((r["motion"], r.get("jitter", 0.0)) for r in rows):
        picked = [r for r in rows if r["motion"] == motion and r.get("jitter", 0.0) == jitter]
        means = [float(np.mean([r["auc"] for r in picked if r["draw"] == d])) for d in draws]
        cells = " | ".join(f"{m:.3f}" for m in means)
        lines.append(
            f"| {labels.get(motion, motion)} | {jitter:g} | {cells} | {min(means):.3f} | "
            f"{np.mean(means):.3f} |"
        )
    return lines


def _slow_table(data: dict) -> list[str]:
    """Per speed, without and with odometry: mean over the seeds."""
    rows = data["slow"]
    lines = [
        "",
        "## A slow robot with a noisy camera",
        "",
        f"Protocol: {data['protocol']['slow']}.  A place's frames differ by the camera's noise "
        "only, so none is held as a repeat.  Mean over the seeds.",
        "",
        "| speed (places per frame) | frames | odometry | kenyon alone | kenyon+cann | right | "
        "`localized` |",
        "|---|---|---|---|---|---|---|",
    ]
    for speed, odometry in dict.fromkeys((r["speed"], r["odometry"]) for r in rows):
        picked = [r for r in rows if r["speed"] == speed and r["odometry"] == odometry]
        mean = {k: float(np.mean([r[k] for r in picked])) for k in picked[0] if k != "seed"}
        lines.append(
            f"| {speed:g} | {picked[0]['frames']} | {'yes' if odometry else 'no'} | "
            f"{mean['auc_front_end']:.3f} | {mean['auc']:.3f} | {mean['right']:.3f} | "
            f"{mean['localized']:.3f} |"
        )
    return lines


_MATCHER_VIEWS = {
    "r-1x": "cold start at 1x",
    "r-fisheye": "cold start at 1x, fisheye disc",
    "r-detour": "detour, from the rejoin",
}


def _matcher_table(data: dict) -> list[str]:
    """Per view and matcher, the frames until it is right, per seed."""
    rows = data["matchers"]
    seeds = sorted({r["seed"] for r in rows})
    names = [k for k in rows[0] if k not in ("seed", "view", "start")]
    lines = [
        "",
        "## Sequence matchers on the same scores",
        "",
        f"Frames from the first frame (the rejoin, for the detour) until the answers are right "
        f"({data['protocol']['matchers']}), per seed.  Every matcher reads the same front-end "
        "scores; the rows given the exact speed know what the CANN must find out.",
        "",
        "| view | matcher | " + " | ".join(f"seed {s}" for s in seeds) + " |",
        "|---|---|" + "---|" * len(seeds),
    ]
    for key, label in _MATCHER_VIEWS.items():
        mine = {r["seed"]: r for r in rows if r["view"] == key}
        if not mine:
            continue
        for name in names:
            cells = [
                "-" if s not in mine else "never" if mine[s][name] is None else str(mine[s][name])
                for s in seeds
            ]
            lines.append(f"| {label} | {name} | " + " | ".join(cells) + " |")
    return lines


def _front_end_table(data: dict) -> list[str]:
    """Per front end, its rank of the true place after the rejoin, pooled over the seeds."""
    rows = data["rejoin_front_ends"]
    first, last = rows[0]["map_leaves_out"]
    lines = [
        "",
        f"Every front end on the same frames (the {AFTER} from the rejoin on; the map without "
        f"{first}-{last}): its rank of the true place (the places scoring higher than it: 0 "
        "is first), the median of the per-seed medians and the best, and the frames with the "
        "true place in its top 10 and first, summed over the seeds: the evidence a filter has "
        "to go on there.",
        "",
        "| front end | seeds | rank of the true place (median) | best rank | frames in the "
        "top 10 | frames first |",
        "|---|---|---|---|---|---|",
    ]
    for label in dict.fromkeys(r["front_end"] for r in rows):
        mine = [r for r in rows if r["front_end"] == label]
        seeds = ", ".join(str(r["seed"]) for r in mine) if mine[0]["seeded"] else "none"
        lines.append(
            f"| {label} | {seeds} | {np.median([r['rank_median'] for r in mine]):.1f} | "
            f"{min(r['rank_best'] for r in mine)} | {sum(r['top10_frames'] for r in mine)} "
            f"of {AFTER * len(mine)} | {sum(r['top1_frames'] for r in mine)} |"
        )
    return lines


def _evidence_table(data: dict) -> list[str]:
    """The detour's rejoin with each front end and odometry, and the front ends alone."""
    p = data["protocol"]
    rows = data["rejoin_evidence"]
    seeds = " / ".join(str(s) for s in sorted({r["seed"] for r in rows}))
    lines = [
        "",
        "## The rejoin with more to go on",
        "",
        f"The same detour with more to go on ({p['rejoin_evidence']}).  Per seed, frames from "
        f"the rejoin until the answers are right (a frame and the {RUN - 1} after it) and until "
        "the answer is `localized` and right (the must-show's figure), and the share of the "
        f"{2 * AFTER} frames from the rejoin on answered from the front end (handed on as a "
        "`lost` hint); the share of the off-map frames `localized` is the mean over the seeds.",
        "",
        f"| front end | odometry | right from (seed {seeds}) | localized and right (seed "
        f"{seeds}) | answers from the front end (seed {seeds}) | off-map frames `localized` |",
        "|---|---|---|---|---|---|",
    ]
    for label in dict.fromkeys(r["front_end"] for r in rows):
        for exact in (False, True):
            mine = sorted(
                (r for r in rows if r["front_end"] == label and r["exact_odometry"] == exact),
                key=lambda r: r["seed"],
            )
            if not mine:
                continue
            right, rejoin = (
                " / ".join("never" if r[key] is None else str(r[key]) for r in mine)
                for key in ("right_from", "rejoin_frames")
            )
            hints = " / ".join(
                "-"
                if r.get("front_end_answers") is None
                else f"{100 * r['front_end_answers']:.0f}%"
                for r in mine
            )
            share = np.mean([r["offmap_localized_share"] for r in mine])
            odometry = "exact" if exact else "none"
            lines.append(
                f"| {label} | {odometry} | {right} | {rejoin} | {hints} | {100 * share:.1f}% |"
            )
    alone = data.get("front_ends_alone") or []
    if alone:
        windows = list(dict.fromkeys(r["window"] for r in alone))
        lines += [
            "",
            f"The front ends alone: {p['front_ends_alone']}; AUC and R@1 at tolerance "
            f"{p['tolerance']}, the mean over the seeds.",
            "",
            "| front end | " + " | ".join(f"{w}: AUC / R@1" for w in windows) + " |",
            "|---" * (len(windows) + 1) + "|",
        ]
        for label in dict.fromkeys(r["front_end"] for r in alone):
            cells = []
            for w in windows:
                mine = [r for r in alone if r["front_end"] == label and r["window"] == w]
                cells.append(
                    f"{np.mean([r['auc'] for r in mine]):.3f} / "
                    f"{np.mean([r['recall_at_1'] for r in mine]):.3f}"
                )
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def _rejoin_table(data: dict) -> list[str]:
    """Per end of the left-out stretch, the rejoin of each seed and the off-map share."""
    rows = data["rejoins"]
    seeds = sorted({r["seed"] for r in rows})
    lines = [
        "",
        "## The detour's rejoin moved",
        "",
        f"{data['protocol']['rejoins']}; the CANN is given the map's break.  Frames from the "
        "first frame on the map again until the answer is `localized` and right, per seed "
        "(as the accuracy benchmark counts them), and the share of the off-map frames "
        f"`localized` (mean over the seeds).  Map stretches: those holding a place of the "
        f"{AFTER} from the rejoin on.",
        "",
        "| map leaves out | map stretches from the rejoin on | frames until localized and right "
        f"({' / '.join(f'seed {s}' for s in seeds)}) | off-map frames `localized` |",
        "|---|---|---|---|",
    ]
    for first, end in sorted({(r["first"], r["end"]) for r in rows}):
        mine = {r["seed"]: r for r in rows if (r["first"], r["end"]) == (first, end)}
        back = " / ".join(
            "never" if mine[s]["rejoin_frames"] is None else str(mine[s]["rejoin_frames"])
            for s in seeds
        )
        share = float(np.mean([mine[s]["offmap_localized_share"] for s in seeds]))
        stretches = _stretches(data["rejoin_stretches"][str(end)])
        lines.append(f"| {first}-{end - 1} | {stretches} | {back} | {100 * share:.1f}% |")
    return lines


def _start_table(data: dict) -> list[str]:
    """Per start frame, the AUC of the full frames and of the disc, and the fisheye gap."""
    rows = data["starts"]
    tols = [int(k.rsplit("_", 1)[1]) for k in rows[0] if k.startswith("full_auc_")]
    lines = [
        "",
        "## The fisheye start moved",
        "",
        f"{data['protocol']['starts']}: kenyon+cann's AUC, mean over the seeds; the fisheye "
        "gap is the full frames' AUC minus the disc's.",
        "",
        "| query from frame | "
        + " | ".join(f"full frames, tol {t} | disc, tol {t} | gap, tol {t}" for t in tols)
        + " |",
        "|---|" + "---|---|---|" * len(tols),
    ]
    for start in sorted({r["start"] for r in rows}):
        mine = [r for r in rows if r["start"] == start]
        cells = []
        for t in tols:
            full = float(np.mean([r[f"full_auc_{t}"] for r in mine]))
            disc = float(np.mean([r[f"fisheye_auc_{t}"] for r in mine]))
            cells += [f"{full:.4f}", f"{disc:.4f}", f"{full - disc:+.4f}"]
        lines.append(f"| {start} | " + " | ".join(cells) + " |")
    return lines


def render_markdown(data: dict) -> str:
    """The protocol, the stretches and the three tables (headings from level 2)."""
    p = data["protocol"]
    lines = [
        "## Protocol",
        "",
        f"{p['method']} on {p['data']}; seeds {', '.join(map(str, p['seeds']))}; tolerance "
        f"{p['tolerance']}.  Same image: {p['same_image']}.  Detour figures: "
        f"{p['detour_after']}.",
        "",
        "## Same-image stretches",
        "",
        f"- Map (summer): {_stretches(data['map_stretches'])} "
        f"({data['map_places_in_stretches']} places).",
        f"- Query (winter): {_stretches(data['query_stretches'])}.",
        "",
        "Within a stretch of the map every place shows one image: no front end can tell them "
        "apart, only the motion model places the query in it.",
        "",
        "## Stop-and-go",
        "",
        "| seed | AUC | AUC, a map stretch counted as one place | stops in a map stretch |",
        "|---|---|---|---|",
    ]
    for r in data["stopgo"]:
        inside = ", ".join(map(str, r["stops_in_a_map_stretch"])) or "none"
        lines.append(
            f"| {r['seed']} | {r['auc']:.3f} | {r['auc_same_image_as_one']:.3f} | "
            f"{inside} (of {len(r['stops'])}) |"
        )
    lines += [
        "",
        "## Detour: after the rejoin",
        "",
        f"Map stretches there: {_stretches(data['rejoin_map_stretches'])}.",
        "",
        "| seed | frames until localized and right | front end's rank of the true place "
        "(median) | frames with it in the top 10 | first frame it is first |",
        "|---|---|---|---|---|",
    ]
    for r in data["detour"]:
        first = "never" if r["first_front_top1"] is None else r["first_front_top1"]
        lines.append(
            f"| {r['seed']} | {r['rejoin_frames']} | {r['front_rank_median']:.1f} | "
            f"{r['front_rank_top10_frames']} | {first} |"
        )
    if data.get("rejoin_front_ends"):
        lines += _front_end_table(data)
    if data.get("rejoin_evidence"):
        lines += _evidence_table(data)
    lines += [
        "",
        "## Cold start at 1x",
        "",
        "| seed | first frame localized and right | first frame the front end ranks the "
        "true place first | answers right |",
        "|---|---|---|---|",
    ]
    for r in data["cold_start"]:
        lines.append(
            f"| {r['seed']} | {r['first_localized_right']} | {r['first_front_top1']} | "
            f"{r['right_share']:.3f} |"
        )
    if data.get("matchers"):
        lines += _matcher_table(data)
    if data.get("rejoins"):
        lines += _rejoin_table(data)
    if data.get("starts"):
        lines += _start_table(data)
    if data.get("parked"):
        lines += _parked_table(data)
    if data.get("jitter"):
        lines += _jitter_table(data)
    if data.get("states"):
        lines += _states_table(data)
    if data.get("profiles"):
        lines += _profiles_table(data)
    if data.get("slow"):
        lines += _slow_table(data)
    lines.append("")
    if machine_sentence(data):
        lines.append(machine_sentence(data))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    return run_page_benchmark(__doc__, run, render_markdown, argv)


if __name__ == "__main__":
    raise SystemExit(main())
