"""Summaries and tables of the accuracy benchmark's JSON: pure functions, no I/O.

:func:`summarise` turns the per-seed rows into per-(condition, method) statistics;
:func:`render_markdown` and :func:`render_text` turn the whole JSON document (as written by
``python benchmarks/accuracy.py --json FILE``) into Markdown tables and an aligned terminal
table.  Nothing here imports flyvpr, so a docs build can call :func:`render_markdown` on a
stored JSON file without the data.
"""

from __future__ import annotations

import statistics

__all__ = ["summarise", "render_markdown", "render_text", "GROUP_TITLES"]

#: report sections, in order: view group -> title
GROUP_TITLES = {
    "nordland": "Nordland 64x32 summer -> winter, tolerance 20 frames",
    "held-out": "Held-out window (tuned nothing)",
    "tolerance": "Stricter tolerances (2 and 10 frames) on the same runs",
    "reverse": "Winter -> summer",
    "subset": "FlyNet's 100-place subset (tolerance 2)",
    "speed": "Query driven faster than the reference (tolerance 20)",
    "synthetic": "Built-in synthetic route, hardest conditions",
    "viewpoint": "Nordland with a drifting viewpoint (nordland_64x32_viewpoint)",
    "robot": "A robot's motion and camera: speeds, stops, a detour, odometry, a fisheye disc, "
    "camera noise "
    "(tolerance 2 and 20)",
    "control": "Control rows",
}

_METRICS = ("auc", "recall_at_1", "recall_at_100_precision", "extended_precision", "top_share")


def summarise(rows: list[dict]) -> list[dict]:
    """Per (condition, method): seeds, AUC mean / worst / spread (max - min) and metric means.

    ``top_share`` reports the largest share of frames any one reference took (the worst seed).
    Rows keep the order in which each (condition, method) first appears.
    """
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["condition"], row["method"]), []).append(row)
    out = []
    for (condition, method), rs in groups.items():
        rs = sorted(rs, key=lambda r: r["seed"])
        auc = [r["auc"] for r in rs]
        entry = {
            "condition": condition,
            "method": method,
            "seeds": [r["seed"] for r in rs],
            "auc_mean": statistics.fmean(auc),
            "auc_worst": min(auc),
            "auc_spread": max(auc) - min(auc),
        }
        for key in _METRICS[1:-1]:
            entry[f"{key}_mean"] = statistics.fmean(r[key] for r in rs)
        entry["top_share_max"] = max(r["top_share"] for r in rs)
        for key in (
            "localized_share",
            "offmap_localized_share",
            "offmap_confidence_mean",
            "offmap_confident_share",
        ):
            values = [r[key] for r in rs if r.get(key) is not None]
            if values:
                entry[key if key.endswith("_mean") else f"{key}_mean"] = statistics.fmean(values)
        for key in ("stand_frames", "stand_localized", "stand_localized_wrong"):
            if any(key in r for r in rs):
                entry[key] = sum(r.get(key, 0) for r in rs)  # counts: pooled over the seeds
        if any("stand_ahead_max" in r for r in rs):
            entry["stand_ahead_max"] = max(r.get("stand_ahead_max", 0) for r in rs)
        rejoin = [r.get("rejoin_frames") for r in rs if "rejoin_frames" in r]
        if rejoin:
            entry["rejoin_frames"] = rejoin
        out.append(entry)
    return out


# -- tables -------------------------------------------------------------------------------------
def _f(x, digits: int = 3) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _conditions(data: dict) -> dict:
    return {c["key"]: c for c in data.get("conditions", [])}


def _method_order(data: dict) -> list[str]:
    return [m["label"] for m in data.get("methods", [])]


def _summary(data: dict) -> list[dict]:
    return data.get("summary") or summarise(data.get("rows", []))


def _main_tables(data: dict) -> list[tuple[str, str, list[str], list[list[str]]]]:
    """(group, title, header, rows) of the result tables, one per view group."""
    conditions = _conditions(data)
    order = {m: i for i, m in enumerate(_method_order(data))}
    cond_order = {k: i for i, k in enumerate(conditions)}
    header = [
        "condition",
        "method",
        "AUC mean",
        "AUC worst",
        "AUC spread",
        "R@1",
        "R@100%P",
        "EP",
        "top share",
        "seeds",
    ]
    by_group: dict[str, list] = {}
    for s in _summary(data):
        cond = conditions.get(s["condition"], {"group": "other", "label": s["condition"]})
        by_group.setdefault(cond["group"], []).append((cond, s))
    tables = []
    for group in [*GROUP_TITLES, *sorted(set(by_group) - set(GROUP_TITLES))]:
        if group not in by_group:
            continue
        items = sorted(
            by_group[group],
            key=lambda cs: (cond_order.get(cs[0].get("key"), 1e9), order.get(cs[1]["method"], 1e9)),
        )
        rows = [
            [
                cond["label"],
                s["method"],
                _f(s["auc_mean"]),
                _f(s["auc_worst"]),
                _f(s["auc_spread"]),
                _f(s["recall_at_1_mean"]),
                _f(s["recall_at_100_precision_mean"]),
                _f(s["extended_precision_mean"]),
                _f(s["top_share_max"], 2),
                _seeds(s["seeds"]),
            ]
            for cond, s in items
        ]
        tables.append((group, GROUP_TITLES.get(group, group), header, rows))
    return tables


def _seeds(seeds: list[int]) -> str:
    if len(seeds) > 2 and seeds == list(range(seeds[0], seeds[-1] + 1)):
        return f"{seeds[0]}-{seeds[-1]}"
    return ",".join(str(s) for s in seeds)


def _bytes_table(data: dict):
    header = ["method", "bytes per reference place", "what is stored per place"]
    rows = []
    per_method = data.get("bytes_per_place", {})
    for label in _method_order(data):
        if label in per_method:
            value = per_method[label]
            rows.append([label, f"{value:,.0f}", data.get("bytes_note", {}).get(label, "")])
    return header, rows


def _control_checks(data: dict) -> list[str]:
    """Verdicts of the control rows, computed from the summary."""
    lines = []
    summary = _summary(data)
    blank = [s for s in summary if s["condition"].startswith("blank@")]
    if blank:
        bad = [
            s["method"]
            for s in blank
            if s["auc_mean"] > 0.1 or s["auc_worst"] > 0.1 or s["recall_at_100_precision_mean"] > 0
        ]
        worst = max(blank, key=lambda s: s["auc_mean"])
        lines.append(
            f"Blank frames (every method should give AUC <= 0.1 and R@100%P = 0): "
            f"{len(blank) - len(bad)} of {len(blank)} methods pass; "
            + (f"fail: {', '.join(bad)}" if bad else "none fails")
            + f" (highest mean AUC {worst['auc_mean']:.3f}, {worst['method']})."
        )
    shuffled = {s["method"]: s for s in summary if s["condition"].startswith("shuffled@")}
    if shuffled:
        parts = []
        frontends = {m["label"]: m for m in data.get("methods", [])}
        for label, s in shuffled.items():
            method = frontends.get(label, {}).get("method", label)
            if "+" not in method and not method.startswith("seqslam"):
                continue
            front = "pixels" if method.startswith("seqslam") else method.split("+")[0]
            if front in shuffled:
                base = shuffled[front]["auc_mean"]
                verdict = "ok" if s["auc_mean"] >= base - 0.005 else "below its front end"
                parts.append(f"{label} {s['auc_mean']:.3f} vs {front} {base:.3f} ({verdict})")
        if parts:
            lines.append(
                "Shuffled queries (a filter should fall back to its front end's evidence, no "
                "lower; AUC means): " + "; ".join(parts) + "."
            )
    return lines


def _kidnap_lines(data: dict) -> list[str]:
    kid = data.get("kidnap", [])
    if not kid:
        return []
    conditions = _conditions(data)
    lines = []
    jump = data.get("kidnap_protocol", {})
    for view in dict.fromkeys(k["view"] for k in kid):
        label = conditions.get(f"{view}@20", {}).get("label", view)
        for method in dict.fromkeys(k["method"] for k in kid if k["view"] == view):
            entries = [k for k in kid if k["view"] == view and k["method"] == method]
            frames = [f for k in entries for f in k["frames"]]
            finite = [f for f in frames if f is not None]
            if not frames:
                continue
            within = sum(1 for f in finite if f <= 30) / len(frames)
            median = statistics.median(finite) if finite else float("nan")
            worst = max(finite) if finite else float("nan")
            seeds = _seeds(sorted({k["seed"] for k in entries}))
            lines.append(
                f"{label}, {method}: {len(frames)} jumps of +{jump.get('jump', '?')} places over "
                f"seeds {seeds}; frames until the best place is within tolerance again: median "
                f"{median:.0f}, max {worst:.0f}, never {len(frames) - len(finite)}, "
                f"{within:.0%} within 30 frames."
            )
    for e in data.get("evidence", []):
        label = conditions.get(f"{e['view']}@20", {}).get("label", e["view"])
        lines.append(
            f"{label}, {e['frontend']} seed {e['seed']}: median rank of the true place over the "
            f"{jump.get('evidence_frames', '?')} frames after each landing (1 = best): "
            f"{e['median_rank']}"
        )
    return lines


#: the sets of robot views the reliability tables pool: those whose window chose the
#: defaults and fitted the calibration table, the held-out window's, and the subset's (a
#: front end right on almost every frame); a view's set is named by the start of its
#: condition's ``tuning`` text ("held out", "subset"; anything else: "dev")
RELIABILITY_SETS = (
    ("dev", "the dev views (frames 0-999: they chose the defaults and fitted the calibration)"),
    ("held out", "the held-out views (frames 2000-2399: they tuned nothing)"),
    (
        "subset",
        "the 100-place subset's robot views (summer -> fall, where the front end alone is "
        "right on almost every frame: they tuned nothing)",
    ),
)


def _view_sets(data: dict) -> dict[str, str]:
    """Each view key's reliability set (see ``RELIABILITY_SETS``), from its tuning text."""
    sets = {}
    for c in data.get("conditions", []):
        if "view_key" not in c:
            continue
        tuning = str(c.get("tuning", ""))
        named = [k for k, _ in RELIABILITY_SETS[1:] if tuning.startswith(k)]
        sets[c["view_key"]] = named[0] if named else "dev"
    return sets


def reliability_table(data: dict, method: str, views: str | None = None) -> list[list[str]]:
    """Rows (confidence bin, frames, mean confidence, share right, gap) of ``method``'s answers
    on the robot views at their strictest tolerance, pooled over views and seeds; ``views``:
    a set of ``RELIABILITY_SETS`` (``"dev"``, ``"held out"``, ``"subset"``) pools only those,
    None all."""
    sets = _view_sets(data)
    parts = [
        x
        for x in data.get("reliability", [])
        if x["method"] == method and (views is None or sets.get(x["view"], "dev") == views)
    ]
    if not parts:
        return []
    bins = len(parts[0]["n"])
    rows = []
    for b in range(bins):
        n = sum(x["n"][b] for x in parts)
        if not n:
            continue
        conf = sum(x["confidence"][b] for x in parts) / n
        right = sum(x["right"][b] for x in parts) / n
        rows.append(
            [f"{b / bins:.1f}-{(b + 1) / bins:.1f}", str(n), _f(conf), _f(right), _f(right - conf)]
        )
    return rows


def _robot_lines(data: dict) -> list[str]:
    """Verdicts of the robot views: each filter against its front end alone, the detour."""
    conditions = _conditions(data)
    summary = [
        s for s in _summary(data) if conditions.get(s["condition"], {}).get("group") == "robot"
    ]
    if not summary:
        return []
    by = {(s["condition"], s["method"]): s for s in summary}
    methods = {m["label"]: m for m in data.get("methods", [])}
    lines, below = [], []
    for (cond, label), s in by.items():
        method = methods.get(label, {}).get("method", label)
        if "+" not in method:
            continue
        front = by.get((cond, method.split("+")[0]))
        if front is not None and s["auc_mean"] < front["auc_mean"] - 0.01:
            below.append(
                f"{conditions[cond]['label']}: {label} {s['auc_mean']:.3f} < "
                f"{front['method']} {front['auc_mean']:.3f}"
            )
    lines.append(
        "Every filter against its front end alone (AUC mean, allowed 0.01 below): "
        + ("; ".join(below) + "." if below else "none is below.")
    )
    for s in summary:
        if "offmap_localized_share_mean" in s:
            rejoin = s.get("rejoin_frames", [])
            shown = ", ".join("never" if r is None else str(r) for r in rejoin)
            sure = ""
            if s.get("offmap_confidence_mean") is not None:
                sure = (
                    f" (every off-map answer is wrong: their mean confidence "
                    f"{s['offmap_confidence_mean']:.2f}, "
                    f"{s['offmap_confident_share_mean']:.0%} of them at 0.5 or more)"
                )
            lines.append(
                f"{conditions[s['condition']]['label']}, {s['method']}: "
                f"{s['offmap_localized_share_mean']:.1%} of the off-map frames localized{sure}; "
                f"frames after rejoining the map until localized and right, per seed: {shown}."
            )
    for s in summary:
        if s.get("stand_frames"):
            n, loc, wrong = s["stand_frames"], s["stand_localized"], s["stand_localized_wrong"]
            share = f" ({wrong / loc:.0%})" if loc else ""
            lines.append(
                f"{conditions[s['condition']]['label']}, {s['method']}: of {n} frames standing "
                f"(seeds pooled), {loc} localized and {wrong} of those wrong{share}; a localized "
                f"answer lay up to {s['stand_ahead_max']} places ahead of the stand."
            )
    return lines


def _unmasked_twin(condition: dict) -> tuple:
    """What a condition's frames are, less a camera mask: the protocol without ``mask``, the
    view without its group and tolerances, and the tolerance."""
    protocol = {k: v for k, v in condition.get("protocol", {}).items() if k != "mask"}
    view = {k: v for k, v in condition.get("view", {}).items() if k not in ("group", "tolerances")}
    return repr(sorted(protocol.items())), repr(sorted(view.items())), condition.get("tolerance")


def _mask_lines(data: dict) -> list[str]:
    """For every condition seen through a camera mask (its protocol has ``mask``) whose frames
    are also run without it: each filtered method's AUC mean without the mask minus through it
    (the mask's cost; issue 19 asks at most 0.01 of the fisheye disc)."""
    conditions = _conditions(data)
    unmasked: dict[tuple, str] = {}
    for key, c in conditions.items():
        if "mask" not in c.get("protocol", {}):
            unmasked.setdefault(_unmasked_twin(c), key)
    by = {(s["condition"], s["method"]): s["auc_mean"] for s in _summary(data)}
    lines = []
    for key, c in conditions.items():
        twin = unmasked.get(_unmasked_twin(c)) if "mask" in c.get("protocol", {}) else None
        if twin is None:
            continue
        gaps = [
            f"{method} {by[(twin, method)] - by[(key, method)]:+.4f}"
            for method in _method_order(data)
            if "+" in method and (key, method) in by and (twin, method) in by
        ]
        if gaps:
            lines.append(
                f"{c['label']}: AUC mean on the same frames without the mask "
                f"({conditions[twin]['label']}) minus through it: " + ", ".join(gaps) + "."
            )
    return lines


def _protocol_lines(data: dict) -> list[str]:
    lines = []
    for c in data.get("conditions", []):
        if c.get("tolerance") != c.get("tolerances", [None])[0]:
            continue  # one line per view
        view = c.get("view", {})
        extra = ", ".join(f"{k} {v}" for k, v in view.items() if k not in ("group", "tolerances"))
        p = c.get("protocol", {})
        # The folder's name, not this machine's path to it.
        where = (p.get("root") or p.get("dataset", "")).replace("\\", "/").rsplit("/", 1)[-1]
        first, count = p.get("first"), p.get("count")
        span = f" frames {first}-{first + count - 1}," if first is not None and count else ""
        route = p.get("make_route")
        if route:
            span = " " + ", ".join(f"{k}={v}" for k, v in route.items()) + ","
        lines.append(
            f"{c['label']}: {where}{span} reference {p.get('reference')}, query "
            f"{p.get('query')}, tolerances {c.get('tolerances')} frames; "
            f"{c.get('tuning', '')}" + (f"; {extra}" if extra else "")
        )
    return lines


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def _text_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]

    def line(cells) -> str:
        return "  ".join(str(c).ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()

    lines = [line(header), line("-" * w for w in widths)]
    lines += [line(r) for r in rows]
    return "\n".join(lines)


def _intro(data: dict) -> list[str]:
    m = data.get("machine", {})
    versions = ", ".join(f"{k} {v}" for k, v in data.get("versions", {}).items())
    seeds = data.get("seeds", [])
    return [
        f"Seeds {_seeds(seeds)}{' (--quick)' if data.get('quick') else ''}; deterministic "
        "methods run once; methods marked first-seed-only run with the first seed only: "
        + ", ".join(x["label"] for x in data.get("methods", []) if x.get("seeds") == "first"),
        f"Machine: {m.get('processor') or m.get('machine', '?')}, {m.get('cpu_count', '?')} "
        f"CPUs, {m.get('platform', '')}; {versions}; total {data.get('elapsed_s', 0):.0f} s.",
        *(
            [
                "Made in parts (`--merge`); the rows of a method on a view come wholly from "
                "one part: "
                + "; ".join(
                    f"`{' '.join(p.get('command') or [])}` at git "
                    + str(p.get("versions", {}).get("git", "?"))
                    for p in data["parts"]
                )
                + "."
            ]
            if data.get("parts")
            else []
        ),
        "AUC: trapezoidal area under the precision-recall curve of each query's best match "
        "(anchored at the first point's precision); R@1: recall at 1; R@100%P: largest recall "
        "at precision 1; EP: VPR-Bench's extended precision (P at the lowest recall + R@100%P) "
        "/ 2; spread: max - min over seeds; top share: the largest share of a condition's "
        "frames that any one reference place took (worst seed). See docs/guide/metrics.md.",
    ]


def _check_document(data: dict) -> None:
    if not isinstance(data, dict) or "conditions" not in data or "rows" not in data:
        raise ValueError(
            "not an accuracy benchmark document: expected the JSON written by "
            "`python benchmarks/accuracy.py --json FILE` (keys 'conditions' and 'rows')"
        )
    missing = [
        k for k in ("extended_precision", "top_share") if data["rows"] and k not in data["rows"][0]
    ]
    if missing:
        raise ValueError(
            f"the benchmark document's rows lack {missing}: it was written by an older "
            "benchmarks/accuracy.py; run it again"
        )


def render_markdown(data: dict) -> str:
    """Markdown tables of a benchmark JSON document (pure: no I/O, no flyvpr import).

    Parameters
    ----------
    data : dict
        The document written by ``python benchmarks/accuracy.py --json FILE``.

    Returns
    -------
    str
        Markdown: the protocol, one table per view group, bytes per place, the control
        verdicts, the kidnap test and any errors.

    Raises
    ------
    ValueError
        If ``data`` is not such a document (or one written by an older version).
    """
    _check_document(data)
    parts = ["## Accuracy benchmark", "", *(f"{line}\n" for line in _intro(data))]
    for _group, title, header, rows in _main_tables(data):
        parts += [f"### {title}", "", _md_table(header, rows), ""]
    header, rows = _bytes_table(data)
    if rows:
        parts += ["### Bytes per reference place", "", _md_table(header, rows), ""]
    checks = _control_checks(data)
    if checks:
        parts += ["### Control verdicts", "", *(f"- {c}" for c in checks), ""]
    robot = _robot_lines(data) + _mask_lines(data)
    if robot:
        parts += ["### Robot verdicts", "", *(f"- {line}" for line in robot), ""]
    for method in dict.fromkeys(x["method"] for x in data.get("reliability", [])):
        parts += [
            f"### Reliability of {method}'s confidence",
            "",
            "Its answers on the robot views (tolerance 2), pooled over views and seeds, by "
            "confidence: a calibrated confidence is right as often as it says (gap near 0).",
            "",
        ]
        for key, what in RELIABILITY_SETS:
            rows = reliability_table(data, method, key)
            if rows:
                parts += [
                    f"On {what}:",
                    "",
                    _md_table(
                        ["confidence", "frames", "mean confidence", "share right", "gap"], rows
                    ),
                    "",
                ]
    kid = _kidnap_lines(data)
    if kid:
        p = data.get("kidnap_protocol", {})
        parts += [
            "### Kidnap: recovery after a jump",
            "",
            f"The query stream jumps +{p.get('jump', '?')} places at stream frames "
            f"{p.get('at', '?')}; tolerance 20.",
            "",
            *(f"- {line}" for line in kid),
            "",
        ]
    errors = data.get("errors", [])
    if errors:
        parts += [
            "### Errors",
            "",
            *(
                f"- {e['method']} (seed {e['seed']}, {e.get('dataset', '')}): {e['error']}"
                for e in errors
            ),
            "",
        ]
    skipped = data.get("skipped", [])
    if skipped:
        parts += ["### Not run", "", *(f"- {s['method']}: {s['reason']}" for s in skipped), ""]
    protocol = _protocol_lines(data)
    if protocol:
        parts += ["### Protocol per condition", "", *(f"- {line}" for line in protocol), ""]
    return "\n".join(parts).rstrip() + "\n"


def render_text(data: dict) -> str:
    """The same tables as :func:`render_markdown`, aligned for a terminal."""
    _check_document(data)
    parts = [*_intro(data), ""]
    for _group, title, header, rows in _main_tables(data):
        parts += [title, _text_table(header, rows), ""]
    header, rows = _bytes_table(data)
    if rows:
        parts += ["Bytes per reference place", _text_table(header, rows), ""]
    parts += _control_checks(data)
    parts += _robot_lines(data)
    parts += _mask_lines(data)
    for method in dict.fromkeys(x["method"] for x in data.get("reliability", [])):
        for key, what in RELIABILITY_SETS:
            rows = reliability_table(data, method, key)
            if rows:
                parts += [
                    "",
                    f"Reliability of {method}'s confidence (tolerance 2) on {what}:",
                    _text_table(
                        ["confidence", "frames", "mean confidence", "share right", "gap"], rows
                    ),
                ]
    kid = _kidnap_lines(data)
    if kid:
        parts += ["", "Kidnap:", *kid]
    for e in data.get("errors", []):
        parts.append(f"ERROR {e['method']} seed {e['seed']} {e.get('dataset', '')}: {e['error']}")
    for s in data.get("skipped", []):
        parts.append(f"not run: {s['method']}: {s['reason']}")
    return "\n".join(parts).rstrip() + "\n"
