"""Merge a partial accuracy run into an earlier benchmark JSON (``accuracy.py --merge FILE``).

A full run of every method on every condition takes about an hour and a half of CPU on a small
machine. When only some methods changed, ``--methods A B --merge benchmarks/accuracy.json``
re-runs those (on the views given, or all) and keeps every other (method, view) pair's rows
from the earlier file.  The merged document
records each part's command, code version and elapsed time under ``parts``, so a reader can see
which rows came from which run; parts must share the seeds (the summary's mean/worst/spread are
over the same seeds for every method).
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["merge_runs", "load_previous"]


def load_previous(path: Path, seeds: list[int]) -> dict:
    """The earlier benchmark JSON at ``path``, checked to be mergeable with a run over ``seeds``."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"--merge {path}: cannot read it as JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("benchmark") != "flyvpr accuracy":
        raise ValueError(f"--merge {path}: not a flyvpr accuracy benchmark JSON")
    for key in ("rows", "conditions", "methods", "seeds"):
        if key not in data:
            raise ValueError(f"--merge {path}: no {key!r} (written by an older benchmark?)")
    if list(data["seeds"]) != list(seeds):
        raise ValueError(
            f"--merge {path}: it was run with seeds {data['seeds']}, this run with {seeds}; "
            "merged rows must share the seeds"
        )
    return data


def _part(data: dict) -> dict:
    return {
        "command": data.get("command"),
        "versions": data.get("versions", {}),
        "methods": [m["label"] for m in data.get("methods", [])],
        "elapsed_s": data.get("elapsed_s"),
    }


def _base(label: str) -> str:
    """The method a kidnap row's label belongs to: ``flynet+cann[fast]`` -> ``flynet+cann``."""
    return label.split("[", 1)[0] if label.endswith("]") and "[" in label else label


def merge_runs(old: dict, new: dict, order_methods: list[str], order_conditions: list[str]) -> dict:
    """``new`` with every (method, condition) it did not run taken from ``old``.

    A (method, view) pair comes wholly from one run: the new one when it ran that method on that
    view (rows at every tolerance, kidnap rows).  Errors and bytes per place of a method re-run
    are the new run's.  The front ends' evidence rows are kept from ``old`` for (view, front end)
    pairs the new run did not measure.
    """
    ran = {m["label"] for m in new["methods"]}
    new_views = {c["view_key"] for c in new["conditions"]}
    methods = {m["label"]: m for m in old["methods"]}
    methods.update({m["label"]: m for m in new["methods"]})
    rank = {label: i for i, label in enumerate(order_methods)}
    methods = sorted(methods.values(), key=lambda m: rank.get(m["label"], len(rank)))
    view_of = {c["key"]: c["view_key"] for c in old["conditions"] + new["conditions"]}

    def replaced(method: str, view: str) -> bool:
        return method in ran and view in new_views

    conditions = {c["key"]: c for c in old["conditions"]}
    conditions.update({c["key"]: c for c in new["conditions"]})
    crank = {key: i for i, key in enumerate(order_conditions)}
    mrank = {m["label"]: i for i, m in enumerate(methods)}
    rows = [r for r in old["rows"] if not replaced(r["method"], view_of[r["condition"]])]
    rows += new["rows"]
    rows.sort(key=lambda r: (crank.get(r["condition"], len(crank)), mrank[r["method"]], r["seed"]))
    kidnap = [k for k in old.get("kidnap", []) if not replaced(_base(k["method"]), k["view"])]
    reliability = [x for x in old.get("reliability", []) if not replaced(x["method"], x["view"])]
    fresh = {(e["view"], e["frontend"]) for e in new.get("evidence", [])}
    evidence = [e for e in old.get("evidence", []) if (e["view"], e["frontend"]) not in fresh]
    merged = dict(new)
    merged.update(
        {
            "methods": methods,
            "skipped": [s for s in old.get("skipped", []) if s["method"] not in ran]
            + new.get("skipped", []),
            "conditions": sorted(
                conditions.values(), key=lambda c: crank.get(c["key"], len(crank))
            ),
            "rows": rows,
            "bytes_per_place": {**old.get("bytes_per_place", {}), **new.get("bytes_per_place", {})},
            "bytes_note": {**old.get("bytes_note", {}), **new.get("bytes_note", {})},
            "kidnap": kidnap + new.get("kidnap", []),
            "reliability": reliability + new.get("reliability", []),
            "evidence": evidence + new.get("evidence", []),
            "errors": [e for e in old.get("errors", []) if e["method"] not in ran]
            + new.get("errors", []),
            "parts": old.get("parts", [_part(old)]) + [_part(new)],
            "elapsed_s": (old.get("elapsed_s") or 0) + (new.get("elapsed_s") or 0),
        }
    )
    return merged
