"""Merge a partial accuracy run into an earlier benchmark JSON (``accuracy.py --merge FILE``).

A full run of every method on every condition takes about an hour and a half of CPU on a small
machine. When only some methods changed, ``--methods A B --merge benchmarks/accuracy.json``
re-runs those and keeps every other method's rows from the earlier file.  The merged document
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


def merge_runs(old: dict, new: dict, order_methods: list[str], order_conditions: list[str]) -> dict:
    """``new`` with every method it did not run taken from ``old``.

    Rows, kidnap rows, errors and bytes per place of a method come wholly from one run: the new
    one when it ran that method.  The front ends' evidence rows are kept from ``old`` for
    (view, front end) pairs the new run did not measure.
    """
    ran = {m["label"] for m in new["methods"]}
    keep = [m for m in old["methods"] if m["label"] not in ran]
    methods = keep + new["methods"]
    rank = {label: i for i, label in enumerate(order_methods)}
    methods.sort(key=lambda m: rank.get(m["label"], len(rank)))

    def old_only(items):
        return [x for x in items if x.get("method") not in ran]

    conditions = {c["key"]: c for c in old["conditions"]}
    conditions.update({c["key"]: c for c in new["conditions"]})
    crank = {key: i for i, key in enumerate(order_conditions)}
    mrank = {m["label"]: i for i, m in enumerate(methods)}
    rows = old_only(old["rows"]) + new["rows"]
    rows.sort(key=lambda r: (crank.get(r["condition"], len(crank)), mrank[r["method"]], r["seed"]))
    fresh = {(e["view"], e["frontend"]) for e in new.get("evidence", [])}
    evidence = [e for e in old.get("evidence", []) if (e["view"], e["frontend"]) not in fresh]
    bytes_pp = {k: v for k, v in old.get("bytes_per_place", {}).items() if k not in ran}
    bytes_pp.update(new.get("bytes_per_place", {}))
    notes = {k: v for k, v in old.get("bytes_note", {}).items() if k not in ran}
    notes.update(new.get("bytes_note", {}))
    skipped = [s for s in old.get("skipped", []) if s["method"] not in ran]
    skipped += new.get("skipped", [])
    merged = dict(new)
    merged.update(
        {
            "methods": methods,
            "skipped": skipped,
            "conditions": sorted(
                conditions.values(), key=lambda c: crank.get(c["key"], len(crank))
            ),
            "rows": rows,
            "bytes_per_place": bytes_pp,
            "bytes_note": notes,
            "kidnap": old_only(old.get("kidnap", [])) + new.get("kidnap", []),
            "evidence": evidence + new.get("evidence", []),
            "errors": old_only(old.get("errors", [])) + new.get("errors", []),
            "parts": old.get("parts", [_part(old)]) + [_part(new)],
            "elapsed_s": (old.get("elapsed_s") or 0) + (new.get("elapsed_s") or 0),
        }
    )
    return merged
