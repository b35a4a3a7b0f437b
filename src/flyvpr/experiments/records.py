"""The files of an experiment, read and checked: a file is used whole or refused in one line.

``experiment.json`` and the run files in ``runs/`` are written by
:func:`flyvpr.experiments.run_experiment`; the report and a resumed experiment
read them back here.  A file that is not UTF-8, not JSON, or lacks a key the
report needs raises a ValueError naming the file and what was expected, rather
than a traceback later or a run silently left out of a table.  Config files go
through :func:`read_text` too, so a stray Latin-1 byte is reported with its line.
"""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["read_text", "read_json", "read_experiment", "read_run", "MalformedJSONError"]


class MalformedJSONError(ValueError):
    """A file that should hold JSON cannot be parsed at all: not UTF-8, or not JSON.

    Kept apart from a parsed file that lacks a key, because a resumed experiment treats a
    run file cut short as a run not done, while a file of another shape stops it.
    """


_NUMBER = ((int, float), "a number")
_NUMBER_OR_NULL = ((int, float, type(None)), "a number or null")
_INT = ((int,), "an integer")
_STR = ((str,), "a string")
_LIST = ((list,), "a list")
_DICT = ((dict,), "an object")

#: keys every experiment.json holds (dotted: inside an object)
_EXPERIMENT_KEYS = {
    "config_text": _STR,
    "config": _DICT,
    "config.base_dir": _STR,
    "sessions": _LIST,
}
#: keys of one entry of experiment.json's plan (grid name -> list of entries)
_PLAN_KEYS = {"run_id": _STR, "dataset": _STR, "method": _STR, "seed": _INT, "combo": _DICT}
#: keys of every run file, and of a finished (status "ok") run by task
_RUN_KEYS = {"run_id": _STR, "status": _STR, "spec": _DICT, "spec.task": _STR}
_FINISHED_RUN_KEYS = {"protocol": _DICT, "spec.image_size": _LIST}
_FAILED_RUN_KEYS = {"error": _STR}
_EVALUATE_KEYS = {
    "result": _DICT,
    "result.auc": _NUMBER_OR_NULL,
    "result.recall_at_1": _NUMBER_OR_NULL,
    "result.recall_at_100_precision": _NUMBER_OR_NULL,
    "result.precision": _LIST,
    "result.recall": _LIST,
    "result.n_query": _INT,
    "result.n_reference": _INT,
    "result.timing": _DICT,
    "result.timing.fit_s": _NUMBER,
    "result.timing.encode_s": _NUMBER,
    "result.timing.match_s": _NUMBER,
    "result.footprint": _DICT,
    "result.footprint.layers": _INT,
    "result.footprint.params": _INT,
    "result.footprint.neurons": _INT,
    "predictions": _LIST,
    "correct": _LIST,
}
_TASK_KEYS: dict[str, dict] = {
    "evaluate": _EVALUATE_KEYS,
    "timing": _EVALUATE_KEYS,
    "train": {
        "result": _DICT,
        "result.accuracy_history": _LIST,
        "result.fit_s": _NUMBER,
        "result.footprint": _DICT,
    },
}


def read_text(path) -> str:
    """A file's text, which must be UTF-8.

    Raises
    ------
    FileNotFoundError
        If the file is missing.
    ValueError
        If it is not UTF-8 (the message names the file, the line and the byte).
    """
    path = Path(path)
    data = path.read_bytes()
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: {_not_utf8(data, exc)}; save the file as UTF-8") from None


def _not_utf8(data: bytes, exc: UnicodeDecodeError) -> str:
    """Where ``data`` stops being UTF-8: ``"line 3: not UTF-8 text (byte 0xe9)"``."""
    line = data[: exc.start].count(b"\n") + 1
    return f"line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x})"


def read_json(path, what: str):
    """Parse a JSON file; ``what`` names it in the error (``"a run file of ..."``).

    Raises
    ------
    FileNotFoundError
        If the file is missing.
    MalformedJSONError
        A ValueError: if it is not UTF-8 or not JSON (truncated, garbled); the
        message names the file, the line (and column), and what the file should be.
    """
    path = Path(path)
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MalformedJSONError(
            f"{path}: expected {what} (JSON); {_not_utf8(data, exc)}: garbled"
        ) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        # json's "Unterminated string starting at" expects the position to follow it
        reason = exc.msg.removesuffix(" at")
        raise MalformedJSONError(
            f"{path}: expected {what} (JSON); it is not valid JSON ({reason} at line "
            f"{exc.lineno}, column {exc.colno}: truncated or garbled)"
        ) from None


def _check_keys(record, keys: dict, path, what: str, context: str = "") -> None:
    """Raise a ValueError naming ``path`` for the first key missing or of the wrong type."""
    if not isinstance(record, dict):
        got = "a list" if isinstance(record, list) else json.dumps(record)[:40]
        raise ValueError(f"{path}: expected {what} (a JSON object); got {got}")
    for dotted, (types, expected) in keys.items():
        value, found = record, True
        for part in dotted.split("."):
            if not isinstance(value, dict) or part not in value:
                found = False
                break
            value = value[part]
        if not found:
            raise ValueError(f"{path}: expected {what} with key {dotted!r}{context}; it has none")
        if isinstance(value, bool) or not isinstance(value, types):
            raise ValueError(
                f"{path}: expected {what}; its {dotted!r} must be {expected}, got "
                f"{json.dumps(value)[:40]}"
            )


def read_experiment(path) -> dict:
    """``experiment.json`` of a results folder, checked.

    Returns
    -------
    dict
        With ``config_text``, ``config`` (``base_dir``), ``sessions`` and, when
        present, a ``plan`` whose entries have ``run_id``, ``dataset``,
        ``method``, ``seed`` and ``combo``.

    Raises
    ------
    FileNotFoundError
        If the file is missing.
    ValueError
        For a file that is not UTF-8 JSON or lacks one of those keys (the
        message names the file and the key).
    """
    what = "the record of `flyvpr experiment`"
    record = read_json(path, what)
    _check_keys(record, _EXPERIMENT_KEYS, path, what)
    for i, session in enumerate(record["sessions"]):
        _check_keys(session, {}, path, f"{what}, sessions[{i}]")
    plan = record.get("plan")
    if plan is not None:
        _check_keys(record, {"plan": _DICT}, path, what)
        for grid, entries in plan.items():
            _check_keys({"entries": entries}, {"entries": _LIST}, path, f"{what} (plan.{grid})")
            for entry in entries:
                _check_keys(entry, _PLAN_KEYS, path, f"{what}, plan.{grid} entries")
    return record


def read_run(path) -> dict:
    """One run file, checked against what its task and status promise.

    A finished run (``status`` ``"ok"``) must hold the ``result`` keys the
    report reads for its task; a failed one its ``error``; and the file name
    must be ``<run_id>.json``.

    Raises
    ------
    FileNotFoundError
        If the file is missing.
    ValueError
        For a file that is not UTF-8 JSON, another run's file, an unknown
        status or task, or a missing key (the message names the file and the key).
    """
    path = Path(path)
    what = "a run file of `flyvpr experiment`"
    record = read_json(path, what)
    _check_keys(record, _RUN_KEYS, path, what)
    if record["run_id"] != path.stem:
        raise ValueError(f"{path}: holds run {record['run_id']!r}, not the run its name says")
    status, task = record["status"], record["spec"]["task"]
    if status == "error":
        _check_keys(record, _FAILED_RUN_KEYS, path, what, " (status 'error')")
    elif status != "ok":
        raise ValueError(
            f"{path}: expected {what}; its status must be 'ok' or 'error', not {status!r}"
        )
    elif task not in _TASK_KEYS:
        raise ValueError(f"{path}: expected {what}; unknown task {task!r} in its spec")
    else:
        keys = {**_FINISHED_RUN_KEYS, **_TASK_KEYS[task]}
        _check_keys(record, keys, path, what, f" (a finished {task} run)")
    return record
