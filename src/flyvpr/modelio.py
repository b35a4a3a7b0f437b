"""Save and load fitted methods as ``.npz`` files that cannot execute code when loaded.

A model file is a NumPy ``.npz`` archive read with ``allow_pickle=False``:

* ``__meta__``: a UTF-8 JSON document (stored as a uint8 array) with the format name and
  version, the flyvpr version, the method name, the front end's and the filter's registry names
  and constructor parameters, the pre-processing settings (image size, gray conversion, resize
  rule) and a SHA-256 checksum of everything else in the file;
* one array per saved attribute, named ``frontend/<attr>`` or ``filter/<attr>`` (nested parts
  such as FlyNet's hash layer add another level: ``frontend/hash_/connections_``).

Classes are looked up by their registry names only, never by an import path from the file, and
scalar attributes live in the JSON, so nothing in the file is ever unpickled or evaluated.
A file from another format version, for another image size, or whose checksum does not match
(modified or truncated) is refused with a ValueError naming the file.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from . import __version__
from ._io import atomic_open
from .frontends import FRONTENDS
from .images import DEFAULT_SIZE
from .methods import Method
from .temporal import FILTERS

__all__ = ["FORMAT", "FORMAT_VERSION", "save_method", "load_method", "preprocessing_settings"]

FORMAT = "flyvpr-model"
#: bumped whenever the layout of saved state changes incompatibly
FORMAT_VERSION = 1


def preprocessing_settings(size=DEFAULT_SIZE) -> dict:
    """The pre-processing a saved model expects its input images to have had."""
    from .images import _PREPROCESS_VERSION

    return {
        "image_size": [int(size[0]), int(size[1])],
        "gray": "ITU-R BT.601 luma (0.299 R + 0.587 G + 0.114 B), values in [0, 1]",
        "resize": "area averaging (Pillow BOX)",
        "preprocess_version": _PREPROCESS_VERSION,
    }


# ---------------------------------------------------------------------------
# state <-> (json, arrays)
# ---------------------------------------------------------------------------
def _flatten(obj, prefix: str, arrays: dict, registry_of) -> dict:
    """Split ``obj``'s saved state into JSON-able scalars and arrays (added to ``arrays``)."""
    meta = {}
    for name, value in obj._get_state().items():
        key = f"{prefix}{name}"
        if isinstance(value, np.ndarray):
            if value.dtype == object:
                raise TypeError(f"cannot save object array {key}")
            arrays[key] = value
            meta[name] = {"array": key}
        elif hasattr(value, "_get_state"):
            meta[name] = {
                "object": type(value).name,
                "params": _json_params(value.get_params()),
                "state": _flatten(value, key + "/", arrays, registry_of),
            }
        else:
            meta[name] = {"value": _json_value(value, key)}
    return meta


def _unflatten(meta: dict, arrays, path: Path) -> dict:
    state = {}
    for name, entry in meta.items():
        if "array" in entry:
            state[name] = arrays[entry["array"]]
        elif "object" in entry:
            cls = FRONTENDS.get(entry["object"])
            if cls is None:
                raise ValueError(f"model file {path}: unknown part {entry['object']!r}")
            part = cls(**entry["params"])
            part._set_state(_unflatten(entry["state"], arrays, path))
            state[name] = part
        else:
            state[name] = entry["value"]
    return state


def _json_value(value, key):
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, tuple):
        return [_json_value(v, key) for v in value]
    if value is None or isinstance(value, (bool, int, float, str, list, dict)):
        return value
    raise TypeError(f"cannot save attribute {key} of type {type(value).__name__}")


def _json_params(params: dict) -> dict:
    out = {}
    for key, value in params.items():
        if isinstance(value, np.random.Generator):
            value = None  # the fitted state holds everything the seed produced
        out[key] = _json_value(value, key)
    return out


def _checksum(meta: dict, arrays: dict) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(meta, sort_keys=True).encode())
    for key in sorted(arrays):
        a = np.ascontiguousarray(arrays[key])
        h.update(f"{key}|{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------
def save_method(method: Method, path, *, size=DEFAULT_SIZE) -> Path:
    """Write a fitted method to ``path`` (``.npz``, atomically).

    Parameters
    ----------
    method : Method
        Fitted (``fit`` was called).
    path : str or Path
        Destination; parent folders are created.
    size : (int, int)
        The (H, W) the images were pre-processed to.

    Returns
    -------
    Path
    """
    method.frontend._check_fitted()
    arrays: dict = {}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "flyvpr_version": __version__,
        "method": method.name,
        "preprocessing": preprocessing_settings(size),
        "frontend": {
            "name": method.frontend.name,
            "params": _json_params(method.frontend.get_params()),
            "state": _flatten(method.frontend, "frontend/", arrays, FRONTENDS),
        },
        "filter": None,
    }
    if method.filter is not None:
        meta["filter"] = {
            "name": method.filter.name,
            "params": _json_params(method.filter.get_params()),
            "state": _flatten(method.filter, "filter/", arrays, FILTERS),
        }
    meta["checksum"] = _checksum(meta, arrays)
    blob = json.dumps(meta).encode()
    payload = {"__meta__": np.frombuffer(blob, dtype=np.uint8), **arrays}
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        np.savez(fh, **payload)
    return path


def load_method(path, *, size=None) -> Method:
    """Read a model file written by :func:`save_method`.

    Parameters
    ----------
    path : str or Path
    size : (int, int), optional
        The image size the caller will feed; a model saved for another size is refused.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a flyvpr model file, comes from an incompatible format version, was
        saved for another image size, or fails its checksum (modified or truncated).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise ValueError(f"model file {path} is not a readable .npz archive ({exc})") from None
    raw = arrays.pop("__meta__", None)
    if raw is None or raw.dtype != np.uint8 or raw.ndim != 1:
        raise ValueError(f"model file {path} has no flyvpr metadata: not a flyvpr model")
    try:
        meta = json.load(io.BytesIO(raw.tobytes()))
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise ValueError(
            f"model file {path}: metadata is not valid JSON (file modified?)"
        ) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"model file {path} is not a flyvpr model (format {FORMAT!r} expected)")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(
            f"model file {path} has format version {version}; this flyvpr ({__version__}) reads "
            f"version {FORMAT_VERSION}: re-fit and save the model with this version"
        )
    expected = meta.pop("checksum", None)
    if expected != _checksum(meta, arrays):
        raise ValueError(f"model file {path} failed its checksum: it was modified or is damaged")
    from .images import _PREPROCESS_VERSION

    if meta["preprocessing"].get("preprocess_version") != _PREPROCESS_VERSION:
        raise ValueError(
            f"model file {path} expects pre-processing version "
            f"{meta['preprocessing'].get('preprocess_version')}; this flyvpr uses "
            f"{_PREPROCESS_VERSION}: re-fit the model"
        )
    saved_size = tuple(meta["preprocessing"]["image_size"])
    if size is not None and tuple(size) != saved_size:
        raise ValueError(
            f"model file {path} was fitted on {saved_size[0]}x{saved_size[1]} images; "
            f"got --size {size[0]}x{size[1]}"
        )
    front_meta = meta["frontend"]
    if front_meta["name"] not in FRONTENDS:
        raise ValueError(f"model file {path}: unknown front end {front_meta['name']!r}")
    frontend = FRONTENDS[front_meta["name"]](**front_meta["params"])
    frontend._set_state(_unflatten(front_meta["state"], arrays, path))
    filt = None
    if meta["filter"] is not None:
        filt_meta = meta["filter"]
        if filt_meta["name"] not in FILTERS:
            raise ValueError(f"model file {path}: unknown filter {filt_meta['name']!r}")
        filt = FILTERS[filt_meta["name"]](**filt_meta["params"])
        filt._set_state(_unflatten(filt_meta["state"], arrays, path))
    return Method(meta["method"], frontend, filt)
