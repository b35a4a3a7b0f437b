"""Running the accuracy benchmark: one task per (data set, seed).

A task loads the data set, fits every front end once (shared by the methods that use it),
scores all query frames, and then, for every view of the data set and every method, filters the
view's rows of the score matrix and scores the result at each of the view's tolerances.  Every
number is the one of ``flyvpr evaluate --method ... --seed ...`` (see :func:`_fit`).
"""

from __future__ import annotations

import copy
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.accuracy_setup import Dataset, Entry, View, fisheye
from flyvpr import metrics
from flyvpr.datasets import ground_truth_from_frames, load_benchmark
from flyvpr.methods import make_method
from flyvpr.temporal.cann import route_breaks

#: stream frames at which the kidnap test's query stream jumps KIDNAP_JUMP places ahead
KIDNAP_AT = (100, 200, 300, 400, 500, 600, 700)
KIDNAP_JUMP = 200
#: frames after each landing over which a front end's own evidence for the true place is taken
EVIDENCE_FRAMES = 30
#: bytes per trained filter parameter (float32)
_PARAM_BYTES = 4


@dataclass(frozen=True)
class Task:
    dataset: Dataset
    seed: int
    first_seed: int
    views: tuple[View, ...]
    entries: tuple[Entry, ...]
    data: Path
    kidnap: bool = True


def load_dataset(dataset: Dataset, data: Path):
    """``(reference, query, reference_ids, query_ids, protocol)`` of a data set."""
    if dataset.source == "nordland":
        bench = load_benchmark(
            "nordland",
            root=data / dataset.folder,
            reference=dataset.reference,
            query=dataset.query,
            first=dataset.first,
            count=dataset.count,
            tolerance=0,
        )
        ref, qry = bench.load_images(cache=True, progress=False)
        protocol = json.loads(json.dumps(bench.protocol(), default=str))
        protocol.pop("tolerance", None)  # each row names its own
        if dataset.mask == "fisheye":
            ref, qry = fisheye(ref), fisheye(qry)
            protocol["mask"] = "fisheye disc (benchmarks/accuracy_setup.py FISHEYE_DISC)"
        return ref, qry, bench.reference.frame_ids, bench.query.frame_ids, protocol
    if dataset.source == "synthetic":
        from flyvpr.synthetic import make_route

        route = make_route(**dataset.route)
        ids = np.arange(route.n_places)
        protocol = {
            "dataset": "synthetic",
            "make_route": dict(dataset.route),
            "reference": route.conditions[0],
            "query": route.conditions[1],
            "n_reference": route.n_places,
            "n_query": route.n_places,
        }
        return route.reference_images, route.query_images, ids, ids, protocol
    if dataset.source == "blank":
        n, value = int(dataset.route["n_places"]), float(dataset.route["value"])
        frames = np.full((n, 32, 64), value, dtype=np.float32)
        ids = np.arange(n)
        protocol = {
            "dataset": "blank",
            "reference": f"{n} frames of value {value}",
            "query": f"{n} frames of value {value}",
            "n_reference": n,
            "n_query": n,
        }
        return frames, frames.copy(), ids, ids, protocol
    raise ValueError(f"data set {dataset.key!r}: unknown source {dataset.source!r}")


def filter_bytes_per_place(model, n_reference: int) -> float:
    """Bytes per place of a filter's trained weights (float32) that grow with the route.

    Only filters trained on the reference traverse store weights (the RNN's input and readout
    columns); the CANN's connections are generated from its kernel and SeqSLAM learns nothing.
    """
    filt = model.filter
    if filt is None or not getattr(filt, "needs_reference_scores", False):
        return 0.0
    grow = filt.footprint(n_reference + 1)["params"] - filt.footprint(n_reference)["params"]
    return float(grow * _PARAM_BYTES)


def run_task(task: Task) -> dict:
    """Every (view, method, tolerance) row of one data set and seed; see the module docstring."""
    t_start, cpu_start = time.perf_counter(), time.process_time()
    ref, qry, ref_ids, qry_ids, protocol = load_dataset(task.dataset, task.data)
    n_ref = len(ref)
    rows, kidnaps, evidence, errors, fitted, reliability = [], [], [], [], [], []
    shared = {}  # front-end key -> (encoder, S, seconds)
    for entry in task.entries:
        views = [v for v in task.views if entry.runs_on(v)]
        if not views or not entry.runs_with(task.seed, task.first_seed):
            continue
        try:
            model, S, seconds = _fit(entry, task.seed, ref, qry, shared)
            bytes_pp = model.frontend.bytes_per_place() + filter_bytes_per_place(model, n_ref)
            fitted.append(
                {"method": entry.label, "fit_score_s": seconds, "bytes_per_place": bytes_pp}
            )
            for view in views:
                idx = view.indices(len(qry))
                view_model, view_S, view_ref_ids = model, S, ref_ids
                if view.gap is not None:
                    keep = gap_keep(len(ref), view.gap)
                    view_model, view_S, _ = _fit(entry, task.seed, ref[keep], qry, shared, view.gap)
                    view_ref_ids = ref_ids[keep]
                    filt = view_model.filter
                    if filt is not None and "breaks" in filt.get_params():
                        # the map's places keep their frame numbers: where they jump, the
                        # route is broken (the layer does not carry the robot across)
                        filt.set_params(breaks=route_breaks(view_ref_ids))
                frames = view_S[idx]
                if view.camera_noise:  # the front end scores the view's own noisy frames
                    frames = view_model.frontend.score(view.frames(qry, idx))
                velocity = view.odometry_steps(qry_ids[idx])
                t0 = time.perf_counter()
                filt = view_model.filter
                states = None
                if filt is None:
                    out = frames
                elif view.group == "robot" and _has_state(filt):
                    out, states = _stream(filt, frames, velocity)
                elif velocity is not None and np.isnan(velocity).any():  # outages: no odometry
                    out, _ = _stream(filt, frames, velocity)
                elif velocity is not None:
                    out = filt.filter(frames, velocity=velocity)
                else:
                    out = filt.filter(frames)
                filter_s = time.perf_counter() - t0
                top_share = float(np.bincount(out.argmax(axis=1)).max() / len(idx))
                for tol in view.tolerances:
                    gt = ground_truth_from_frames(qry_ids[idx], view_ref_ids, tol)
                    m = metrics.evaluate(out, gt, ks=(1,))
                    row = {
                        "condition": f"{view.key}@{tol}",
                        "method": entry.label,
                        "seed": task.seed,
                        "auc": m["auc"],
                        "recall_at_1": m["recall_at_1"],
                        "recall_at_100_precision": m["recall_at_100_precision"],
                        "extended_precision": m["extended_precision"],
                        "top_share": top_share,
                        "filter_s": filter_s,
                    }
                    if states is not None:
                        row["localized_share"] = float(np.mean(states))
                        if tol == min(view.tolerances):
                            reliability.append(
                                _reliability(entry.label, view.key, task.seed, out, gt)
                            )
                        if view.gap is not None and tol == min(view.tolerances):
                            row.update(_detour(qry_ids[idx], view_ref_ids, out, states, tol))
                        if tol == min(view.tolerances):
                            row.update(_stands(qry_ids[idx], view_ref_ids, out, states, tol))
                    rows.append(row)
                if task.kidnap and view.kidnap and entry.spec.filter in ("cann", "cann-paper"):
                    tol = view.tolerances[0]
                    kidnaps.append(_kidnap_row(view, entry.label, task.seed, model.filter, S, tol))
                    for label, params in _extra_cann_variants(entry):
                        variant = type(model.filter)(**{**model.filter.get_params(), **params})
                        kidnaps.append(_kidnap_row(view, label, task.seed, variant, S, tol))
                    fe = entry.spec.frontend
                    if not any(e["view"] == view.key and e["frontend"] == fe for e in evidence):
                        evidence.append(
                            {
                                "view": view.key,
                                "frontend": fe,
                                "seed": task.seed,
                                "median_rank": evidence_rank(S),
                            }
                        )
        except Exception as exc:  # recorded and reported: one method's failure keeps the others
            errors.append(
                {"method": entry.label, "seed": task.seed, "error": f"{type(exc).__name__}: {exc}"}
            )
    return {
        "dataset": task.dataset.key,
        "seed": task.seed,
        "protocol": protocol,
        "rows": rows,
        "kidnap": kidnaps,
        "evidence": evidence,
        "fitted": fitted,
        "reliability": reliability,
        "errors": errors,
        "seconds": time.perf_counter() - t_start,
        # CPU seconds of all threads: a measure of the work that does not depend on the load.
        "cpu_seconds": time.process_time() - cpu_start,
    }


def _fit(entry: Entry, seed: int, ref, qry, shared: dict, variant=None):
    """A fitted method and its front end's scores of every query frame.

    The front end is fitted once per (front end, parameters) and shared.  ``make_method`` gives
    the front end and the filter one random Generator, which the front end draws from first, in
    ``fit``; a filter that draws random numbers (the RNN) gets a copy of that Generator as the
    shared front end's fit left it, so every method's numbers are those of
    ``flyvpr evaluate --method ... --seed ...`` without fitting the front end again.
    """
    model = make_method(entry.name, seed, entry.frontend_params, entry.filter_params)
    key = (
        entry.spec.frontend,
        json.dumps(entry.frontend_params, sort_keys=True, default=str),
        repr(variant),  # a detour's map is fitted on its own places
    )
    if key not in shared:
        t0 = time.perf_counter()
        model.frontend.fit(ref)
        S = model.frontend.score(qry)
        rng = model.frontend.get_params().get("random_state")
        after = copy.deepcopy(rng) if isinstance(rng, np.random.Generator) else None
        shared[key] = (model.frontend, S, time.perf_counter() - t0, after)
    model.frontend, S, seconds, after = shared[key]
    if model.filter is not None:
        if "random_state" in model.filter.get_params():
            rng = copy.deepcopy(after) if after is not None else np.random.default_rng(seed)
            model.filter.set_params(random_state=rng)
        if getattr(model.filter, "needs_reference_scores", False):
            model.filter.fit(model.frontend.score(ref))
    return model, S, seconds


def gap_keep(n: int, gap) -> np.ndarray:
    """Indices of the reference places a detour view keeps: all but ``gap[0] n .. gap[1] n``."""
    lo, hi = int(gap[0] * n), int(gap[1] * n)
    return np.r_[0:lo, hi:n]


def _has_state(filt) -> bool:
    """Filters that say per frame whether they are localized (the CANN)."""
    from flyvpr.temporal.cann import CANN

    return isinstance(filt, CANN)


def _stream(filt, S, velocity, sources: list | None = None):
    """The filter's rows frame by frame, with whether each frame was ``localized`` (all False
    for a filter that does not say); a NaN odometry is none for that frame.  ``sources``, a
    list, gets each frame's ``source_`` (where the answer came from; None if not said)."""
    filt.reset()
    out = np.empty(S.shape, np.float32)
    states = np.zeros(len(S), bool)
    for t in range(len(S)):
        v = None if velocity is None or t == 0 or np.isnan(velocity[t]) else float(velocity[t])
        out[t] = filt.step(S[t]) if v is None else filt.step(S[t], velocity=v)
        states[t] = getattr(filt, "state_", None) == "localized"
        if sources is not None:
            sources.append(getattr(filt, "source_", None))
    return out, states


#: confidence bins of the reliability table
RELIABILITY_BINS = 10


def _reliability(label: str, view: str, seed: int, out, gt) -> dict:
    """Per confidence decile: frames, summed confidence and right answers (the row maximum is
    the confidence, the argmax the answer, right = within the tolerance)."""
    answer = out.argmax(axis=1)
    conf = out[np.arange(len(out)), answer].astype(np.float64)
    n, total, hits = metrics.reliability_counts(
        conf, gt[np.arange(len(out)), answer], RELIABILITY_BINS
    )
    return {
        "method": label,
        "view": view,
        "seed": seed,
        "n": n.tolist(),
        "confidence": total.tolist(),
        "right": hits.tolist(),
    }


def _detour(query_ids, ref_ids, out, states, tol: int) -> dict:
    """Off-map frames (whose place the map leaves out) reported ``localized``, and frames
    after rejoining the map until the answer is ``localized`` and right (within ``tol``)."""
    off = ~np.isin(query_ids, ref_ids)
    right = ground_truth_from_frames(query_ids, ref_ids, tol)[
        np.arange(len(out)), out.argmax(axis=1)
    ]
    back = None
    if off.any():
        after = np.arange(np.flatnonzero(off)[-1] + 1, len(out))
        hit = after[states[after] & right[after]]
        back = int(hit[0] - after[0]) if hit.size else None
    confidence = out.max(axis=1)[off]  # the CANN's answer holds its row's maximum
    return {
        "offmap_localized_share": float(states[off].mean()) if off.any() else None,
        "rejoin_frames": back,
        # every off-map answer is wrong: how sure of them the filter says it is
        "offmap_confidence_mean": float(confidence.mean()) if off.any() else None,
        "offmap_confident_share": float((confidence >= 0.5).mean()) if off.any() else None,
    }


#: a stand: at least this many consecutive frames at one place (a slow speed's repeats of a
#: place, 2-3 frames at 0.4-0.6 places per frame, are not stops)
STAND_FRAMES = 10


def _stands(query_ids, ref_ids, out, states, tol: int) -> dict:
    """Frames where the query stands (its true place is the frame before's, in a run of at
    least ``STAND_FRAMES`` frames at that place): how many, how many are ``localized``, how
    many of those are wrong (beyond ``tol``), and the most places a ``localized`` answer lay
    ahead of the true place on them (a lost answer is the front end's hint, from anywhere);
    nothing for a query that never stands."""
    query_ids = np.asarray(query_ids)
    starts = np.flatnonzero(np.r_[True, query_ids[1:] != query_ids[:-1]])
    lengths = np.diff(np.r_[starts, len(query_ids)])
    stand = np.zeros(len(query_ids), bool)
    for first, length in zip(starts, lengths, strict=True):
        if length >= STAND_FRAMES:
            stand[first + 1 : first + length] = True
    if not stand.any():
        return {}
    answers = out.argmax(axis=1)
    right = ground_truth_from_frames(query_ids, ref_ids, tol)[np.arange(len(out)), answers]
    ahead = np.asarray(ref_ids)[answers] - query_ids
    return {
        "stand_frames": int(stand.sum()),
        "stand_localized": int((stand & states).sum()),
        "stand_localized_wrong": int((stand & states & ~right).sum()),
        "stand_ahead_max": int(max(0, ahead[stand & states].max(initial=0))),
    }


def _extra_cann_variants(entry: Entry):
    """The paper CANN's FAST_RECOVERY preset next to flynet+cann-paper in the kidnap test."""
    if entry.label != "flynet+cann-paper":
        return []
    from flyvpr.temporal import cann

    preset = getattr(cann, "FAST_RECOVERY", None)
    return [("flynet+cann-paper[fast]", preset)] if preset else []


def jump_positions(n: int) -> list[int]:
    """The jump positions of KIDNAP_AT that leave at least 60 frames after the landing."""
    return [p for p in KIDNAP_AT if p + KIDNAP_JUMP + 60 <= n]


def _kidnap_row(view: View, label: str, seed: int, filt, S, tol: int) -> dict:
    return {
        "view": view.key,
        "method": label,
        "seed": seed,
        "jump_at": jump_positions(len(S)),
        "frames": kidnap_recovery(S, tol, filt),
    }


def kidnap_recovery(S, tol: int, filt) -> list[int | None]:
    """Frames until the filter's best place is back within ``tol`` after a jump.

    For every jump position ``p`` (stream frames) the query stream is frames ``0..p-1`` then
    ``p + KIDNAP_JUMP..n-1`` of the view (frame-aligned, so the true place of frame ``i`` is
    ``i``); the count is the number of frames after the jump until the best place is within
    ``tol`` of the true one (``None``: never).
    """
    n = S.shape[0]
    out = []
    for p in jump_positions(n):
        order = np.r_[np.arange(p), np.arange(p + KIDNAP_JUMP, n)]
        fresh = type(filt)(**filt.get_params())
        best = fresh.filter(S[order])[p:].argmax(axis=1)
        ok = np.abs(best - order[p:]) <= tol
        out.append(int(np.argmax(ok)) if ok.any() else None)
    return out


def evidence_rank(S) -> list[int]:
    """Median rank of the true place in a front end's scores over the frames after each landing.

    For every jump position ``p``, the stream lands on query frame ``p + KIDNAP_JUMP``; over
    that frame and the next ``EVIDENCE_FRAMES - 1`` the true place's rank among the references
    (1 = scored highest; frame-aligned, so the true place of frame ``i`` is ``i``) is taken per
    frame and the median reported.
    """
    rows = np.arange(S.shape[0])
    rank = 1 + (S > S[rows, rows][:, None]).sum(axis=1)
    return [
        int(np.median(rank[p + KIDNAP_JUMP : p + KIDNAP_JUMP + EVIDENCE_FRAMES]))
        for p in jump_positions(S.shape[0])
    ]
