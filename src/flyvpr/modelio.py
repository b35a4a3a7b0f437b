"""Save and load fitted methods as ``.npz`` files that cannot execute code when loaded.

A model file is a NumPy ``.npz`` archive (uncompressed zip) read without pickle:

* ``__meta__``: a UTF-8 JSON document (stored as a uint8 array) with the format name and
  version, the flyvpr version, the method name, the front end's and the filter's registry names
  and constructor parameters, the pre-processing settings (image size, gray conversion, resize
  rule) and a SHA-256 checksum of everything else in the file;
* one array per saved attribute, named ``frontend/<attr>`` or ``filter/<attr>`` (nested parts
  such as FlyNet's hash layer add another level: ``frontend/hash_/connections_``);
* the zip comment: the SHA-256 (hex) of every byte before it, so a change anywhere in the file,
  even in zip fields numpy ignores, is refused.

Classes are looked up by their registry names only, never by an import path from the file, and
scalar attributes live in the JSON, so nothing in the file is ever unpickled or evaluated.

Loading trusts nothing in the file, not even a recomputed checksum: every field of the JSON
must be present with the right type; the method name must match the saved front end and
filter; each part's saved state must hold exactly the attributes its class declares
(``_state_scalars`` and ``_state_arrays``), each scalar in range and each array with the
declared dtype and shape, which is checked on the array's header before its data are read
(so a header or a deflate bomb that claims gigabytes costs nothing); and the restored method
must score a test frame.  Every refusal is a :class:`ModelFileError` (a ValueError) whose one
line names the file and the field.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from ._io import ZipWriter, atomic_open, raise_interruption
from ._npy import ArrayFileError, npz_member_header, read_npz_member
from ._validation import ArraySpec, PartSpec, check_memory
from ._version import __version__
from .frontends import FRONTENDS
from .images import DEFAULT_SIZE
from .methods import METHODS, Method, hold_default
from .temporal import FILTERS
from .temporal.base import OnlineFilter
from .temporal.cann._filter import CALIBRATION_ROOT, table_at_roots

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "ModelFileError",
    "save_method",
    "load_method",
    "preprocessing_settings",
]

FORMAT = "flyvpr-model"
#: bumped whenever the layout of saved state changes incompatibly
FORMAT_VERSION = 2
#: length of the file checksum (hex SHA-256) kept in the zip comment
_TRAILER = 64
#: largest accepted ``__meta__`` entry
_MAX_META = 1 << 20
_META_FIELDS: dict[str, type | tuple[type, ...]] = {
    "format": str,
    "format_version": int,
    "flyvpr_version": str,
    "method": str,
    "preprocessing": dict,
    "frontend": dict,
    "filter": (dict, type(None)),
    "checksum": str,
}
#: optional fields (files from before them have none): the int seed the method was made with
_OPTIONAL_FIELDS = ("seed",)
#: optional sections that extend a model file (a map adds ``map``, read by flyvpr.localization.maps)
_SECTIONS = ("map",)


class ModelFileError(ValueError):
    """A model file that is not a valid flyvpr model (the message names file and field)."""


#: what restoring a part, or scoring a test frame with it, raises on parameters or state that
#: no fit produces (a file edited and sealed again); each becomes a ModelFileError
_RESTORE_ERRORS = (
    ValueError,
    TypeError,
    KeyError,
    IndexError,
    AttributeError,
    RuntimeError,
    ArithmeticError,
    FileNotFoundError,
)


def preprocessing_settings(size=DEFAULT_SIZE) -> dict:
    """The pre-processing a saved model expects its input images to have had."""
    from .images import _PREPROCESS_VERSION

    return {
        "image_size": [int(size[0]), int(size[1])],
        "gray": "ITU-R BT.601 luma (0.299 R + 0.587 G + 0.114 B), values in [0, 1]",
        "resize": "area averaging (exact area weights)",
        "preprocess_version": _PREPROCESS_VERSION,
    }


# ---------------------------------------------------------------------------
# saving
# ---------------------------------------------------------------------------
def _flatten(obj, prefix: str, arrays: dict) -> dict:
    """Split ``obj``'s saved state into JSON-able scalars and arrays (added to ``arrays``)."""
    meta: dict = {}
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
                "state": _flatten(value, key + "/", arrays),
            }
        else:
            meta[name] = {"value": _json_value(value, key)}
    return meta


def _json_value(value, key):
    if isinstance(value, (np.integer, np.floating, np.bool_)):
        return value.item()
    if isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
        # a parameter given as an array (velocities=np.arange(...)): a list of its numbers,
        # which the parameter takes as well
        return value.tolist()
    if isinstance(value, (tuple, list)):
        return [_json_value(v, key) for v in value]
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if value is None or isinstance(value, (bool, int, float, str, dict)):
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


def _file_digest(fh, n_bytes: int) -> str:
    """SHA-256 (hex) of the first ``n_bytes`` of ``fh``, read in chunks."""
    h = hashlib.sha256()
    fh.seek(0)
    left = n_bytes
    while left > 0:
        chunk = fh.read(min(1 << 20, left))
        if not chunk:
            break
        h.update(chunk)
        left -= len(chunk)
    return h.hexdigest()


def save_method(method: Method, path, *, size=DEFAULT_SIZE, sections=None) -> Path:
    """Write a fitted method to ``path`` (``.npz``, atomically).

    Parameters
    ----------
    method : Method
        Fitted (``fit`` was called).
    path : str or Path
        Destination; parent folders are created.  A symlink is followed; a folder, FIFO or
        device is refused (see :func:`flyvpr._io.atomic_open`).
    size : (int, int)
        The (H, W) the images were pre-processed to.
    sections : dict, optional
        Extra sections, name -> (JSON-able dict, arrays named ``<name>/...``); a map file's
        ``map`` section (see :mod:`flyvpr.localization.maps`).

    Returns
    -------
    Path
    """
    if not isinstance(method, Method):
        raise TypeError(
            f"method must be a flyvpr Method (flyvpr.methods.make_method); got "
            f"{type(method).__name__} (a compact map keeps its encoder in the map file)"
        )
    method.frontend._check_fitted()
    arrays: dict = {}
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "flyvpr_version": __version__,
        "method": method.name,
        # the int seed make_method was given (every random part's), None for another source
        "seed": method.seed if type(method.seed) is int else None,
        "preprocessing": preprocessing_settings(size),
        "frontend": {
            "name": method.frontend.name,
            "params": _json_params(method.frontend.get_params()),
            "state": _flatten(method.frontend, "frontend/", arrays),
        },
        "filter": None,
    }
    if method.filter is not None:
        meta["filter"] = {
            "name": method.filter.name,
            "params": _json_params(method.filter.get_params()),
            "state": _flatten(method.filter, "filter/", arrays),
            **_filter_extra(method.filter),
        }
    for name, (section, section_arrays) in (sections or {}).items():
        if name not in _SECTIONS or not all(k.startswith(name + "/") for k in section_arrays):
            raise ValueError(f"unknown model file section {name!r} or misnamed arrays")
        meta[name] = section
        arrays.update(section_arrays)
    return _write_archive(Path(path), meta, arrays)


def _write_archive(path: Path, meta: dict, arrays: dict) -> Path:
    """Seal ``meta`` (content checksum added) and ``arrays`` into a model file at ``path``."""
    meta = {k: v for k, v in meta.items() if k != "checksum"}
    meta["checksum"] = _checksum(meta, arrays)
    blob = json.dumps(meta).encode()
    payload = {"__meta__": np.frombuffer(blob, dtype=np.uint8), **arrays}
    with atomic_open(path, "w+b") as fh:
        zf = None
        try:
            with ZipWriter(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
                for key, value in payload.items():
                    with zf.open(key + ".npy", "w", force_zip64=True) as member:
                        np.lib.format.write_array(member, np.asarray(value), allow_pickle=False)
                zf.comment = b"0" * _TRAILER
        except Exception as exc:
            # A Ctrl-C or SIGTERM inside a member's close leaves the archive's close to raise
            # ValueError over it: the interruption is what ends the write.  The archive is
            # dropped (the temporary file goes with atomic_open), so that its __del__, run when
            # the traceback is freed, does not try the same close again and print it.
            if zf is not None:
                zf.fp = None
            raise_interruption(exc)
            raise
        fh.flush()
        end = fh.seek(0, 2)
        digest = _file_digest(fh, end - _TRAILER)
        fh.seek(end - _TRAILER)
        fh.write(digest.encode("ascii"))
    return path


# ---------------------------------------------------------------------------
# loading
# ---------------------------------------------------------------------------
class _Reader:
    """State of one load: the open archive and the arrays read so far."""

    def __init__(self, path: Path, zf: zipfile.ZipFile, what: str = "model file"):
        self.path = path
        self.zf = zf
        self.what = what  # what the file is to the user: "model file" or "map file"
        self.arrays: dict = {}

    def error(self, field: str | None, problem: str) -> ModelFileError:
        where = f"{self.what} {self.path}" + (f": {field}" if field else "")
        return ModelFileError(f"{where}: {problem}")

    def array(self, key: str, field: str, spec: ArraySpec | None) -> np.ndarray:
        try:
            arr = read_npz_member(
                self.zf,
                key,
                f"{self.what} {self.path}",
                dtype=None if spec is None else spec.dtype,
                shape=None if spec is None else spec.shape,
            )
        except ArrayFileError as exc:
            raise self.error(field, str(exc).split(": ", 1)[-1]) from None
        if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
            raise self.error(field, f"entry {key!r} must hold numbers; got dtype {arr.dtype}")
        finite = True if spec is None else spec.finite
        if finite and np.issubdtype(arr.dtype, np.inexact) and not np.isfinite(arr).all():
            raise self.error(field, f"entry {key!r} contains NaN or infinite values")
        self.arrays[key] = arr
        return arr

    def part(self, name, params, state, field: str, registry: dict, kind: str, prefix: str):
        """Build one saved part (front end, filter or nested part) after checking every field."""
        if not isinstance(name, str) or name not in registry:
            raise self.error(f"{field}.name", f"unknown {kind} {name!r}")
        cls = registry[name]
        if not isinstance(params, dict):
            raise self.error(f"{field}.params", f"must be a JSON object; got {params!r}")
        allowed = cls._param_names()
        for key in params:
            if key not in allowed:
                raise self.error(f"{field}.params.{key}", f"not a parameter of {name}")
        for key in allowed:
            if key not in params and key not in cls._added_params:
                raise self.error(f"{field}.params.{key}", "missing")
        obj = cls(**params)  # (a parameter newer than the file: its default)
        if not isinstance(state, dict):
            raise self.error(f"{field}.state", f"must be a JSON object; got {state!r}")
        scalars = {}
        # (state added after files were first written: a file from before has none)
        added = getattr(cls, "_added_state", ())
        for key, spec in cls._state_scalars.items():
            entry = state.get(key)
            if entry is None and key in added and key not in state:
                continue
            if entry is None:
                raise self.error(f"{field}.state.{key}", "missing")
            if not isinstance(entry, dict) or set(entry) != {"value"}:
                raise self.error(f"{field}.state.{key}", f"must be a value; got {entry!r}")
            try:
                scalars[key] = spec.check(entry["value"], key)
            except ValueError as exc:
                raise self.error(f"{field}.state.{key}", str(exc)) from None
        try:
            declared = obj._state_arrays(scalars)
        except (ValueError, TypeError, ArithmeticError) as exc:
            raise self.error(
                f"{field}", f"state does not fit the parameters ({_problem(exc)})"
            ) from None
        restored = dict(scalars)
        for key, entry in state.items():
            if key in scalars:
                continue
            sub = f"{field}.state.{key}"
            spec = _lookup(declared, key)
            if declared is not None and spec is None:
                raise self.error(sub, f"not part of a saved {name}")
            if not isinstance(entry, dict):
                raise self.error(sub, f"malformed entry {entry!r}")
            if set(entry) == {"array"}:
                if entry["array"] != prefix + key:
                    raise self.error(
                        sub, f"must name entry {prefix + key!r}; got {entry['array']!r}"
                    )
                if declared is not None and not isinstance(spec, ArraySpec):
                    raise self.error(sub, "must be a nested part, not an array")
                restored[key] = self.array(prefix + key, sub, spec)
            elif set(entry) == {"object", "params", "state"}:
                if declared is not None and (
                    not isinstance(spec, PartSpec) or entry["object"] not in spec.names
                ):
                    raise self.error(sub, f"unexpected nested part {entry['object']!r}")
                restored[key] = self.part(
                    entry["object"], entry["params"], entry["state"], sub, FRONTENDS, "part",
                    prefix + key + "/",
                )  # fmt: skip
            elif set(entry) == {"value"} and declared is None:
                restored[key] = entry["value"]
            else:
                raise self.error(sub, f"malformed entry {entry!r}")
        for key in declared or {}:
            if not key.endswith("*") and key not in state:
                raise self.error(f"{field}.state.{key}", "missing")
        try:
            obj._set_state(restored)
        except _RESTORE_ERRORS as exc:
            # (FileNotFoundError: a file the part is rebuilt from, such as NetVLAD's
            # backbone weights, is gone; ArithmeticError: parameters that overflow)
            raise self.error(
                f"{field}.state", f"does not restore a {name} ({_problem(exc)})"
            ) from None
        return obj


def _problem(exc: Exception) -> str:
    """What went wrong restoring a part, in the words of a ModelFileError."""
    if isinstance(exc, KeyError):
        return f"missing {exc}"
    if isinstance(exc, ArithmeticError):
        return f"a parameter or value out of range: {type(exc).__name__}: {exc}"
    return str(exc)


def _lookup(declared: dict | None, key: str):
    if declared is None:
        return None
    if key in declared:
        return declared[key]
    for pattern, spec in declared.items():
        if pattern.endswith("*") and fnmatch.fnmatchcase(key, pattern):
            return spec
    return None


def _read_meta(r: _Reader) -> dict:
    try:
        shape, _, dtype, info = npz_member_header(r.zf, "__meta__", f"{r.what} {r.path}")
    except ArrayFileError:
        raise r.error(None, "has no flyvpr metadata: not a flyvpr model") from None
    if dtype != np.uint8 or len(shape) != 1 or info.file_size > _MAX_META:
        raise r.error("__meta__", "must be a JSON document of at most 1 MB")
    raw = r.array("__meta__", "__meta__", ArraySpec("uint8", (None,)))
    del r.arrays["__meta__"]
    try:
        meta = json.loads(raw.tobytes().decode("utf-8"))
    except ValueError:  # not UTF-8, not JSON, or an integer past Python's digit limit
        raise r.error("__meta__", "metadata is not valid JSON (file modified?)") from None
    except RecursionError:
        # json recurses once per level: "[" * 100000 fits in 1 MB but not on the stack
        raise r.error(
            "__meta__",
            "metadata is malformed: JSON nested too deeply to read; a flyvpr model's "
            "metadata is a JSON object a few levels deep (file modified?)",
        ) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise r.error("format", f"not a flyvpr model ({FORMAT!r} expected)")
    return meta


def _check_version(r: _Reader, meta: dict) -> None:
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise r.error(
            "format_version",
            f"the file has format version {version!r}; this flyvpr ({__version__}) reads "
            f"version {FORMAT_VERSION}: "
            "re-fit and save the model with this version",
        )


def _filter_extra(filt) -> dict:
    """What a filter's section holds besides its name, params and state: for a filter with a
    ``calibration`` table, the root of the raw confidence the table is given at (files
    without it gave it at the raw confidence or its square root: see ``load_method``)."""
    return {"calibration_root": CALIBRATION_ROOT} if "calibration" in filt.get_params() else {}


_HEX = frozenset(b"0123456789abcdef")


def _seal(path: Path) -> str:
    """``"ok"`` when the file ends with the SHA-256 (hex) of every byte before it;
    ``"broken"`` when it ends with 64 hex digits that are not that checksum (a sealed file
    changed since); ``"absent"`` when it ends otherwise (no flyvpr model, or one cut short)."""
    size = path.stat().st_size
    if size <= _TRAILER:
        return "absent"
    with open(path, "rb") as fh:
        fh.seek(size - _TRAILER)
        trailer = fh.read(_TRAILER)
        if not set(trailer) <= _HEX:
            return "absent"
        digest = _file_digest(fh, size - _TRAILER)
    return "ok" if trailer == digest.encode("ascii") else "broken"


def _damaged(path: Path, what: str = "model file") -> str:
    return f"{what} {path} failed its file checksum: it was modified or is damaged"


def _check_fields(r: _Reader, meta: dict, size) -> tuple[int, int]:
    for key, kind in _META_FIELDS.items():
        if key not in meta:
            raise r.error(key, "missing")
        if not isinstance(meta[key], kind) or isinstance(meta[key], bool):
            raise r.error(key, f"has the wrong type: {type(meta[key]).__name__}")
    extra = sorted(set(meta) - set(_META_FIELDS) - set(_SECTIONS) - set(_OPTIONAL_FIELDS))
    if extra:
        raise r.error(extra[0], "not a field of a flyvpr model")
    from .images import _PREPROCESS_VERSION

    pre = meta["preprocessing"]
    if pre.get("preprocess_version") != _PREPROCESS_VERSION:
        raise r.error(
            "preprocessing.preprocess_version",
            f"{pre.get('preprocess_version')!r}; this flyvpr uses {_PREPROCESS_VERSION}: "
            "re-fit the model",
        )
    saved = pre.get("image_size")
    if (
        not isinstance(saved, list)
        or len(saved) != 2
        or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in saved)
    ):
        raise r.error("preprocessing.image_size", f"must be [H, W]; got {saved!r}")
    expected = preprocessing_settings(saved)
    for key in sorted(set(pre) | set(expected)):
        if pre.get(key) != expected.get(key):
            raise r.error(
                f"preprocessing.{key}",
                f"{pre.get(key)!r}; this flyvpr pre-processes as {expected.get(key)!r}",
            )
    if size is not None and tuple(size) != tuple(saved):
        raise r.error(
            None,
            f"was fitted on {saved[0]}x{saved[1]} images; got size {size[0]}x{size[1]} (the "
            "size to load it at: --size, or size=)",
        )
    spec = METHODS.get(meta["method"])
    front = meta["frontend"].get("name")
    filt = None if meta["filter"] is None else meta["filter"].get("name")
    if spec is None:
        raise r.error("method", f"unknown method {meta['method']!r}")
    if (spec.frontend, spec.filter) != (front, filt):
        raise r.error(
            "method",
            f"{meta['method']!r} is {spec.frontend}"
            + (f"+{spec.filter}" if spec.filter else "")
            + f", but the file holds front end {front!r} and filter {filt!r}",
        )
    fields = {"name", "params", "state"}
    for part, optional in (("frontend", set()), ("filter", {"calibration_root"})):
        if meta[part] is not None and not fields <= set(meta[part]) <= fields | optional:
            may = f" (and may hold {', '.join(sorted(optional))})" if optional else ""
            raise r.error(part, f"must hold exactly name, params and state{may}")
    return tuple(saved)


def _probe(r: _Reader, method: Method, image_shape) -> None:
    """The restored method must score two test frames into finite (2, n_reference) rows."""
    h, w = image_shape
    ramp = np.linspace(0.0, 1.0, h * w, dtype=np.float32).reshape(1, h, w)
    frames = np.concatenate([ramp, ramp[:, ::-1, ::-1]])
    n = method.frontend.n_reference_
    try:
        S = method.frontend.score(frames)
        if S.shape != (2, n) or not np.isfinite(S).all():
            raise ValueError(f"scores of shape {S.shape} (finite: {np.isfinite(S).all()})")
        if method.filter is not None:
            F = method.filter.filter(S)
            if F.shape != (2, n) or not np.isfinite(F).all():
                raise ValueError(f"filtered scores of shape {F.shape}")
            if isinstance(method.filter, OnlineFilter):
                method.filter.reset()
    except _RESTORE_ERRORS as exc:
        raise r.error(None, f"the restored model fails on a test frame ({_problem(exc)})") from None


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
    ModelFileError
        (a ValueError) If it is not a regular file or not a flyvpr model file, comes from an
        incompatible format version, was saved for another image size, fails its file or
        content checksum, misses a field or entry, holds an array of another dtype or shape,
        an unknown or inconsistent method, front end, filter or parameter, or does not score a
        test frame; for a NetVLAD model, also if its backbone's weights file is gone or holds
        other weights than those it was fitted with.  The message names the file and the
        field.
    flyvpr._validation.InsufficientMemoryError
        If the arrays it declares would not fit in the available memory.
    """
    return _load(path, size, {})[0]


def _load(path, size, readers: dict, what: str = "model file"):
    """Load a model file and its sections: ``readers`` maps a section name to a function
    ``(reader, section_dict) -> object`` that reads (and checks) that section's arrays.

    A section present in the file without a reader is refused, so ``load_method`` never
    accepts a file with more in it than it understands.  ``what`` names the file in messages
    (a map is a model file with a map section, but to its user a "map file").
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} not found: {path}")
    if not path.is_file():
        raise ModelFileError(f"{what} {path} is not a regular file")
    seal = _seal(path)
    try:
        zf = zipfile.ZipFile(path)
    except Exception as exc:  # zipfile raises many kinds on damaged directories
        if seal == "broken":  # a flyvpr file whose zip structure was damaged
            raise ModelFileError(_damaged(path, what)) from None
        raise ModelFileError(
            f"{what} {path} is not a readable .npz archive ({type(exc).__name__}: {exc})"
        ) from None
    with zf:
        r = _Reader(path, zf, what)
        try:
            meta = _read_meta(r)
        except ModelFileError:
            # A sealed file whose metadata no longer reads was damaged, not made by
            # something else: its checksum says so.
            if seal == "broken":
                raise ModelFileError(_damaged(path, what)) from None
            raise
        _check_version(r, meta)  # says why a file is not a model of this format version
        if seal != "ok":
            raise ModelFileError(_damaged(path, what))
        image_shape = _check_fields(r, meta, size)
        check_memory(sum(info.file_size for info in zf.infolist()), f"{what} {path} (its arrays)")
        front = meta["frontend"]
        frontend = r.part(
            front["name"], front["params"], front["state"], "frontend", FRONTENDS, "front end",
            "frontend/",
        )  # fmt: skip
        if "mask_pooling" not in front["params"] and "mask_pooling" in frontend.get_params():
            frontend.set_params(mask_pooling=False)  # a file from before: fitted without it
        if tuple(frontend.image_shape_) != image_shape:
            raise r.error(
                "frontend.state.image_shape_",
                f"{frontend.image_shape_} differs from preprocessing.image_size {image_shape}",
            )
        filt = None
        if meta["filter"] is not None:
            fm = meta["filter"]
            filt = r.part(
                fm["name"], fm["params"], fm["state"], "filter", FILTERS, "filter", "filter/"
            )
            if "hold_repeats" not in fm["params"]:  # a file from before repeated frames held
                hold_default(frontend, filt, fm["params"])
            if "snap" not in fm["params"] and "snap" in filt.get_params():
                filt.set_params(snap=False)  # a file from before the snap: it runs as it ran
            if "adapt_front" not in fm["params"] and "adapt_front" in filt.get_params():
                filt.set_params(adapt_front=False)  # (the same)
            # Files from before the root was saved gave the table at the raw confidence
            # (before repeated frames held) or at its square root.
            root = fm.get("calibration_root", 2 if "hold_repeats" in fm["params"] else 1)
            if type(root) is not int or root not in (1, 2, CALIBRATION_ROOT):
                raise r.error(
                    "filter.calibration_root", f"{root!r}: 1, 2 or {CALIBRATION_ROOT} expected"
                )
            if getattr(filt, "calibration", None) is not None and root != CALIBRATION_ROOT:
                filt.set_params(calibration=table_at_roots(filt.calibration, root))
        found = {}
        for name in _SECTIONS:
            if name in meta and name not in readers:
                raise r.error(
                    name, f"the file is a flyvpr {name}, not a bare model: load it as a {name}"
                )
            if name in readers:
                if not isinstance(meta.get(name), dict):
                    raise r.error(
                        name,
                        f"missing: not a flyvpr {name} file (a bare model, as `flyvpr fit` "
                        f"writes; build one with `flyvpr {name}`)",
                    )
                found[name] = readers[name](r, meta[name])
        expected = {"__meta__.npy"} | {key + ".npy" for key in r.arrays}
        extra = sorted(set(zf.namelist()) - expected)
        if extra:
            raise r.error(None, f"entry {extra[0]!r} is not part of the saved model")
        stored = meta.pop("checksum")
        if stored != _checksum(meta, r.arrays):
            raise r.error("checksum", "content checksum mismatch: modified or damaged")
    seed = meta.get("seed")  # (files from before the seed was kept have none)
    if seed is not None and (type(seed) is not int or seed < 0):
        raise r.error("seed", f"expected an integer >= 0 or null; got {seed!r}")
    # (the parts hold their fitted state: a refit draws afresh, the seed is a record)
    method = Method(meta["method"], frontend, filt, seed=seed)
    _probe(r, method, image_shape)
    return method, found
