"""Compact maps of a robot's own recording, and localizing new recordings against them.

:func:`build_compact_map` reads a recording (image folder, video or ROS bag) twice: a first
pass keeps an evenly spaced sample of at most ``fit_frames`` frames, on which a
:class:`~flyvpr.large.CompactEncoder` learns its pixel mask, feature mean and projection; the
second pass encodes every kept frame, in chunks of :data:`flyvpr._chunks.CHUNK` frames (on
local processes or a Dask cluster if asked: the same file, byte for byte, either way), and
streams the codes into a map file (:mod:`flyvpr.large.mapfile`).  Memory stays bounded by the
sample and one batch of frames, plus 16 bytes per place for the timestamps and frame numbers.

The map file keeps what a later run needs to encode its frames exactly as the places were
encoded: the encoder's settings (in the JSON metadata) and its arrays (``encoder.*``), each
place's ``timestamps`` and source ``frames``, and ``positions`` when the recording had them.
The metadata also says where the places came from (``source``, ``source_kind``, ``topic``,
``every``, ``positions_from``) and, for a video, how its frames were decoded
(``video_decode``, as in a full map: :mod:`flyvpr.localization.maps`); all of it is covered
by the file's ``map_id``.
:func:`open_compact_map` checks all of it; :func:`compact_localizer` puts a
:class:`~flyvpr.large.LargeLocalizer` on it.  ``flyvpr map --compact`` and ``flyvpr
localize --map`` are the command line of this module.

Examples
--------
>>> from flyvpr.large.recording import build_compact_map, compact_localizer, open_compact_map
>>> build_compact_map("runs/summer", "summer.fvmap")              # doctest: +SKIP
>>> cmap = open_compact_map("summer.fvmap")                        # doctest: +SKIP
>>> loc = compact_localizer(cmap)                                  # doctest: +SKIP
>>> fix = loc.update(frame)          # a (H, W) gray frame in [0, 1] # doctest: +SKIP
"""

from __future__ import annotations

import functools
import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import _chunks
from .._chunks import ChunkRunner
from .._validation import check_memory
from .._version import __version__
from ..images import DEFAULT_SIZE
from ..localization.maps import _warn_unrotated, spacing_of
from ..sources import Positions, RecordingError, Source, open_source, parse_every, read_positions
from ..sources.video import _DECODE_VERSION as _VIDEO_DECODE
from .codes import CompactEncoder
from .mapfile import MAGIC, LargeMap, LargeMapWriter, MapFileError, open_large_map

__all__ = [
    "FIT_FRAMES",
    "CompactMap",
    "build_compact_map",
    "compact_localizer",
    "index_path",
    "is_compact_map",
    "open_compact_map",
]

logger = logging.getLogger(__name__)

#: most frames the encoder is fitted on (an evenly spaced sample of a longer recording)
FIT_FRAMES = 10_000
#: chunks of frames read per batch (chunks start at the same frames whoever encodes them)
_BATCH_CHUNKS = 16
#: what the metadata says the file is
KIND = "recording"
_ENCODER_ARRAYS = ("valid_pixels", "feature_mean", "projection")
_INFO = ("source", "source_kind", "topic", "every", "positions_from")


def is_compact_map(path) -> bool:
    """Whether ``path`` is a map file of compact codes (by its first bytes; False for a
    missing or unreadable file, which the caller's own open then reports)."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a pipe would block the read
            return False
        with open(path, "rb") as fh:
            return fh.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


def index_path(path) -> Path:
    """Where ``build_compact_map(..., index="mih")`` writes the map's multi-index hash tables:
    ``X.fvmap`` -> ``X.mih``; any other name gets ``.mih`` added (``route.v1`` ->
    ``route.v1.mih``), so that two maps never share one."""
    path = Path(path)
    if path.suffix == ".fvmap":
        return path.with_suffix(".mih")
    return path.with_name(path.name + ".mih")


@dataclass
class CompactMap:
    """An opened compact map of a recording (see :func:`open_compact_map`).

    Attributes
    ----------
    large_map : LargeMap
        The memory-mapped codes (and positions).
    encoder : CompactEncoder
        Fitted as at the build: it encodes new frames as the places were encoded.
    timestamps : ndarray of float64, shape (n_places,)
        Seconds; NaN where the recording had no clock.
    frames : ndarray of int64, shape (n_places,)
        Each place's frame in the recording.
    positions : ndarray of float64, shape (n_places, 2), or None
    info : dict
        ``source``, ``source_kind``, ``topic``, ``every``, ``positions_from``, ``seed``,
        ``fit_frames``; for a video, ``video_decode`` (how its frames were decoded).
    """

    large_map: LargeMap
    encoder: CompactEncoder
    timestamps: np.ndarray
    frames: np.ndarray
    positions: np.ndarray | None
    info: dict

    @property
    def path(self) -> Path:
        return self.large_map.path

    @property
    def n_places(self) -> int:
        return self.large_map.n_places

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) the frames are pre-processed to."""
        h, w = self.encoder.image_shape_
        return int(h), int(w)

    @functools.cached_property
    def breaks(self) -> tuple[int, ...]:
        """Places where the map's route is broken, read from its positions as
        :attr:`flyvpr.localization.Map.breaks` reads a map's (each place more than 5 times the
        usual step around it from the place before; empty without positions):
        :func:`compact_localizer` gives them to the windowed CANN, which does not carry the
        robot across them.  Read once per opened map (2.4 s for 10^7 places on the
        2-core machine of the benchmarks)."""
        from ..temporal.cann._route import position_breaks

        return position_breaks(self.positions)

    @property
    def place_spacing(self) -> float | None:
        """Metres between consecutive places: the median over neighbouring places that both
        have a position (None without positions, or when it is 0 or undefined); it turns
        odometry in metres into places."""
        return spacing_of(self.positions)


def _batch() -> int:
    return _BATCH_CHUNKS * _chunks.CHUNK


def _encode_rows(encoder: CompactEncoder, images: np.ndarray) -> np.ndarray:
    """Codes of ``images``, CHUNK frames at a time (the chunks a ChunkRunner hands out)."""
    out = np.empty((len(images), encoder.projection_.shape[1] // 8), np.uint8)
    chunk = _chunks.CHUNK
    for lo in range(0, len(images), chunk):
        out[lo : lo + chunk] = encoder.encode(images[lo : lo + chunk])
    return out


def _sample(src: Source, size, every, positions, fit_frames: int, progress: bool):
    """(the fitting sample, the number of kept frames): every ``stride``-th kept frame,
    the stride doubled whenever the sample would outgrow ``fit_frames``."""
    from tqdm.auto import tqdm

    stride, n = 1, 0
    kept: list[np.ndarray] = []  # images of the kept frames, in order
    at: list[np.ndarray] = []  # their numbers among the recording's kept frames
    with tqdm(desc="reading frames (1 of 2)", unit="frame", disable=not progress) as bar:
        for b in src.batches(size, every=every, positions=positions, batch=_batch()):
            number = np.arange(n, n + len(b))
            pick = number % stride == 0
            kept.append(b.images[pick])
            at.append(number[pick])
            n += len(b)
            while sum(len(a) for a in at) > fit_frames:
                stride *= 2
                keep = [a % stride == 0 for a in at]
                kept = [k[m] for k, m in zip(kept, keep, strict=True)]
                at = [a[m] for a, m in zip(at, keep, strict=True)]
            bar.update(len(b))
    if n == 0:
        raise RecordingError(f"{src.describe()}: every={every} keeps no frame")
    return np.concatenate(kept), n


def build_compact_map(
    source,
    path,
    *,
    n_bits: int = 256,
    size=DEFAULT_SIZE,
    topic: str | None = None,
    every=None,
    positions=None,
    position_topic: str | None = None,
    random_state: int = 0,
    fit_frames: int = FIT_FRAMES,
    index: str | None = None,
    progress: bool = False,
    n_jobs: int | None = None,
    scheduler=None,
) -> CompactMap:
    """Encode every kept frame of a recording into a compact map file (atomically).

    Parameters
    ----------
    source : str, Path or Source
        Image folder, video file or ROS bag (:func:`flyvpr.sources.open_source`); read twice.
    path : str or Path
        The map file to write (conventionally ``.fvmap``).
    n_bits : int, default 256
        Bits per place (a multiple of 64 up to 512).
    size, topic, every, positions, position_topic
        As :meth:`flyvpr.localization.maps.Map.build`.
    random_state : int, default 0
        Seed of the encoder's rotation.
    fit_frames : int, default FIT_FRAMES
        Most frames the encoder is fitted on: an evenly spaced sample of a longer recording
        (all of a shorter one).
    index : {None, "mih"}
        ``"mih"``: also write the multi-index hash tables to :func:`index_path` (``path``
        with the suffix ``.mih``), which ``compact_localizer(..., index="mih")`` then opens
        instead of building them.
    progress : bool
        Progress bars on stderr.
    n_jobs, scheduler
        Encode the chunks on local processes or a Dask cluster (as ``Map.build``); the file
        is the same, byte for byte.

    Returns
    -------
    CompactMap
        The written map, opened.

    Raises
    ------
    RecordingError
        If the recording cannot be read, keeps fewer than 2 frames, or changes between the
        two passes.
    ValueError, TypeError
        For a bad ``n_bits``, ``fit_frames``, ``index``, ``n_jobs`` or ``scheduler``; with
        ``index="mih"``, when :func:`index_path` holds the tables of another map than the
        one ``path`` replaces (``X`` and ``X.fvmap`` share ``X.mih``): raised before any
        work, and that file is never written over (nor, without it, removed).
    """
    from tqdm.auto import tqdm

    from .index import MultiIndexHash
    from .mapfile import save_index

    if isinstance(fit_frames, bool) or not isinstance(fit_frames, (int, np.integer)):
        raise TypeError(f"fit_frames must be an int >= 2; got {type(fit_frames).__name__}")
    if fit_frames < 2:
        raise ValueError(f"fit_frames must be >= 2; got {fit_frames}")
    if index not in (None, "mih"):
        raise ValueError(f"index must be None or 'mih'; got {index!r}")
    path = Path(path)
    sidecar = index_path(path)
    # the tables beside the map's name: stale ones (of the map this build replaces, or of an
    # earlier one), or another map's (X and X.fvmap share X.mih): never written over nor removed
    owner = _map_id(sidecar, "mih")
    other = _other_owner(path, sidecar, owner)
    if index == "mih" and other is not None:
        raise ValueError(
            f"{sidecar}, where the tables of {path} go, holds those of the map {other}; name "
            "this map otherwise"
        )
    encoder = CompactEncoder(n_bits=n_bits, random_state=random_state)
    encoder._check_params()
    h, w = size
    # the sample, its optic-lobe features (about as large) and a batch of frames
    check_memory(
        (2 * int(fit_frames) + _batch()) * int(h) * int(w) * 4,
        f"fit_frames={fit_frames} (a sample of {h}x{w} frames to fit the encoder on)",
    )
    runner = ChunkRunner(n_jobs, scheduler)
    src = source if isinstance(source, Source) else open_source(source, topic=topic)
    every = parse_every(every)
    pos = positions if isinstance(positions, Positions) else None
    if pos is None:
        bag = src.path if src.kind == "bag" else None
        pos = read_positions(positions, bag=bag, topic=position_topic)
    path = Path(path)
    with runner:
        sample, n = _sample(src, size, every, pos, int(fit_frames), progress)
        if n < 2:
            raise RecordingError(f"{src.describe()}: a map needs at least 2 places; got {n}")
        encoder.fit(sample)
        del sample
        meta = {
            "flyvpr": __version__,
            "kind": KIND,
            "encoder": encoder.state()[0],
            "seed": int(random_state),
            "fit_frames": int(encoder.n_reference_),
            "source": str(src.path),
            "source_kind": src.kind,
            "topic": getattr(src, "topic", None),
            "every": str(every),
            "positions_from": None if pos is None else pos.origin,
        }
        if src.kind == "video":
            meta["video_decode"] = _VIDEO_DECODE
        encode = functools.partial(_encode_rows, encoder)
        timestamps, frames = [], []
        written = placed = 0
        n_bytes = int(n_bits) // 8
        with (
            LargeMapWriter(path, n, n_bytes, None if pos is None else 2, meta) as writer,
            tqdm(desc="encoding (2 of 2)", unit="frame", total=n, disable=not progress) as bar,
        ):
            for b in src.batches(size, every=every, positions=pos, batch=_batch()):
                if written + len(b) > n:
                    raise RecordingError(
                        f"{src.describe()}: more frames on the second pass than the {n} of "
                        "the first (the recording changed while it was read)"
                    )
                codes = runner(encode, b.images) if runner.parallel else encode(b.images)
                # between rows, as for a full map (Map.build) and the query's odometry
                xy = None if pos is None else pos.at(b.indices, b.timestamps, interpolate=True)
                if xy is not None:
                    placed += int(np.isfinite(xy).all(axis=1).sum())
                writer.append(codes, xy)
                timestamps.append(b.timestamps)
                frames.append(b.indices)
                written += len(b)
                bar.update(len(b))
            if written != n:
                raise RecordingError(
                    f"{src.describe()}: {written} frames on the second pass, {n} on the first "
                    "(the recording changed while it was read)"
                )
            if pos is not None and not placed:  # (the writer removes its temporary file)
                pos.check_covers(
                    np.full((n, 2), np.nan), np.concatenate(frames), np.concatenate(timestamps),
                    src.describe(),
                )  # fmt: skip
            writer.add_array("timestamps", np.concatenate(timestamps).astype(np.float64))
            writer.add_array("frames", np.concatenate(frames).astype(np.int64))
            for name, array in encoder.state()[1].items():
                writer.add_array(f"encoder.{name}", array)
    cmap = open_compact_map(path)
    if index == "mih":
        save_index(sidecar, MultiIndexHash(radius=1).build(cmap.large_map.codes), cmap.large_map)
    elif other is not None:
        logger.warning(
            "%s holds the tables of the map %s (left as it is): `--index mih` on %s builds "
            "its tables in memory; a map of another name gets its own file",
            sidecar, other, path,
        )  # fmt: skip
    elif owner is not None and owner != cmap.large_map.map_id:
        # the tables of the map this one replaced (or of an earlier one): they index nothing
        sidecar.unlink(missing_ok=True)
        logger.warning("removed %s: it indexed the map %s replaced", sidecar, path)
    logger.info("compact map: %d places from %s", n, src.describe())
    return cmap


def _other_owner(path: Path, sidecar: Path, owner: str | None) -> Path | None:
    """The other map whose tables the index file ``sidecar`` (recording ``owner``, its map's
    id) holds, if one is there: ``X`` and ``X.fvmap`` share ``X.mih``; None where the file
    indexes no map beside ``path`` (stale, or ``path``'s own)."""
    if owner is None:
        return None
    stem = sidecar.with_suffix("")
    for other in (stem.with_name(stem.name + ".fvmap"), stem):
        if other != path and index_path(other) == sidecar and _map_id(other, "map") == owner:
            return other
    return None


def _map_id(path: Path, kind: str) -> str | None:
    """The ``map_id`` a flyvpr ``kind`` file (``"map"`` or ``"mih"``) at ``path`` records:
    the map's own, or the indexed map's; None where there is no such file (or another file,
    which is left to its owner)."""
    from .mapfile import _read_container

    try:
        header, _ = _read_container(path, kind)
    except (OSError, ValueError):
        return None
    return str(header.get("map_id") or "") or None


def open_compact_map(path, verify: bool = True) -> CompactMap:
    """Open a map written by :func:`build_compact_map`, every field checked.

    Parameters
    ----------
    verify : bool, default True
        Also read the whole file and check its content against its ``map_id``
        (:meth:`~flyvpr.large.LargeMap.verify`: SHA-256, about a second per GB of codes), so
        that a file changed after it was written is refused rather than answering from
        damaged codes.  ``False`` opens in milliseconds whatever the size, reading only what
        the run touches.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    MapFileError
        If it is not such a map, or anything in it is missing or does not fit (the message
        names the file and the field), or, with ``verify``, its content does not match.

    Notes
    -----
    A map of a video built before flyvpr applied a video's rotation (no ``video_decode``)
    opens with a warning, as :meth:`flyvpr.localization.maps.Map.load` says it.
    """
    m = open_large_map(path)
    meta = m.metadata
    if not isinstance(meta, dict) or meta.get("kind") != KIND or "encoder" not in meta:
        raise MapFileError(
            f"{path}: a map of compact codes without an encoder (not written by `flyvpr map "
            "--compact`): frames cannot be encoded against it"
        )
    for key in _INFO:
        if key not in meta or not isinstance(meta[key], (str, type(None))):
            raise MapFileError(f"{path}: metadata.{key} is missing or not a string")
    decode = meta.get("video_decode", 1)  # (maps of a video from before it have none)
    if type(decode) is not int or decode < 1:
        raise MapFileError(f"{path}: metadata.video_decode must be an integer >= 1; got {decode!r}")
    arrays = {name: m.arrays.get(f"encoder.{name}") for name in _ENCODER_ARRAYS}
    missing = [f"encoder.{k}" for k, v in arrays.items() if v is None]
    if missing:
        raise MapFileError(f"{path}: array {missing[0]} is missing")
    try:
        encoder = CompactEncoder.from_state(meta["encoder"], arrays, m.codes)
    except (TypeError, ValueError) as exc:
        raise MapFileError(f"{path}: {exc}") from None
    n = m.n_places
    columns = {}
    for name, dtype in (("timestamps", np.float64), ("frames", np.int64)):
        a = m.arrays.get(name)
        if a is None or a.dtype != dtype or a.shape != (n,):
            raise MapFileError(
                f"{path}: array {name} must be {np.dtype(dtype).name} of shape ({n},)"
            )
        columns[name] = a
    pos = m.positions
    if pos is not None and pos.shape != (n, 2):
        raise MapFileError(f"{path}: positions must have shape ({n}, 2); got {pos.shape}")
    info = {key: meta[key] for key in _INFO}
    info["seed"] = meta.get("seed")
    info["fit_frames"] = meta.get("fit_frames")
    if "video_decode" in meta:
        info["video_decode"] = decode
    if verify:
        m.verify()
    _warn_unrotated(path, info, "flyvpr map --compact")
    return CompactMap(m, encoder, columns["timestamps"], columns["frames"], pos, info)


def compact_localizer(cmap: CompactMap, index: str = "exhaustive", **params):
    """A :class:`~flyvpr.large.LargeLocalizer` on an opened compact map, with its encoder.

    Parameters
    ----------
    cmap : CompactMap
    index : {"exhaustive", "mih"}
        The relocation index: an exact scan of every code, or multi-index hashing (radius
        1), whose tables are read from :func:`index_path` when that file exists (and belongs
        to this map) and built otherwise.
    **params
        ``LargeLocalizer``'s (``window``, ``k``, ...) and the CANN's parameters;
        ``place_spacing`` defaults to the map's (:attr:`CompactMap.place_spacing`: None
        without positions), and ``breaks`` to the map's (:attr:`CompactMap.breaks`; ``()``
        reads the map as one route).

    Returns
    -------
    LargeLocalizer
        Its ``update(image, velocity=None, *, distance=None)`` takes a pre-processed frame
        of ``cmap.size``;
        its ``index_source_`` says in words where its index came from (the exact scan, the
        tables of :func:`index_path`, or tables built in memory, where that file is missing
        or indexes another map: a warning says so).

    Raises
    ------
    ValueError
        For an unknown ``index``.
    MapFileError
        If the index file is corrupt or indexes another map.
    """
    from .index import CandidateIndex, ExhaustiveIndex, MultiIndexHash
    from .localizer import LargeLocalizer
    from .mapfile import ForeignIndexError, load_index

    codes = cmap.large_map.codes
    source = "exact scan"
    found: CandidateIndex | None = None
    if index == "exhaustive":
        found = ExhaustiveIndex().build(codes)
    elif index == "mih":
        sidecar = index_path(cmap.path)
        if sidecar.exists():
            try:
                found = load_index(sidecar, cmap.large_map)
                source = f"multi-index hashing from {sidecar.name}"
            except ForeignIndexError:
                other = _other_owner(cmap.path, sidecar, _map_id(sidecar, "mih"))
                logger.warning(
                    "%s indexes another map than %s: its tables are built in memory instead (%s)",
                    sidecar, cmap.path,
                    f"they are the map {other}'s: a map of another name gets its own file"
                    if other is not None
                    else "they are stale: `flyvpr map --compact --mih` writes this map's",
                )  # fmt: skip
                source = f"multi-index hashing, tables built ({sidecar.name} indexes another map)"
        else:
            source = f"multi-index hashing, tables built (no {sidecar.name})"
        if found is None:
            found = MultiIndexHash(radius=1).build(codes)
    else:
        raise ValueError(f"index must be 'exhaustive' or 'mih'; got {index!r}")
    assert found is not None
    params.setdefault("place_spacing", cmap.place_spacing)
    if params.get("breaks") is None:
        params["breaks"] = cmap.breaks
    loc = LargeLocalizer(codes, found, encoder=cmap.encoder, **params)
    loc.index_source_ = source
    return loc
