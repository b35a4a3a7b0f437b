"""Reference maps built from a robot's own recording: a fitted method plus where each place is.

A :class:`Map` is the method fitted on the kept frames of one recording (the reference
traverse) together with, per place, the frame's timestamp, its index in the recording, its
position (x, y in metres) when known, and a small gray thumbnail (the pre-processed frame as
8-bit) for traces.  It is saved as a model file (see :mod:`flyvpr.modelio`) with one more
section, ``map``: the same safe, versioned and checksummed format, no pickle.  The section
says where the places came from (``source``, ``source_kind``, ``topic``, ``every``,
``positions_from``) and, for a video, how its frames were decoded (``video_decode``, the
version of :mod:`flyvpr.sources.video`'s decoding).  A map of a video without it was built
before flyvpr applied a video's rotation, and loading it warns: rebuild it if the video was
recorded rotated.

Examples
--------
>>> from flyvpr.localization.maps import Map
>>> m = Map.build("runs/summer.mp4", every="0.5s")            # doctest: +SKIP
>>> m.save("route.map")                                        # doctest: +SKIP
>>> from flyvpr.localization.localizer import Localizer
>>> loc = Localizer.from_map("route.map")                      # doctest: +SKIP
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .._chunks import ChunkRunner
from .._validation import ArraySpec, check_memory
from ..images import DEFAULT_SIZE
from ..methods import DEFAULT_METHOD
from ..modelio import _load, save_method
from ..sources import (
    Batch,
    Positions,
    RecordingError,
    Source,
    open_source,
    parse_every,
    read_positions,
)
from ..sources.video import _DECODE_VERSION as _VIDEO_DECODE
from .localizer import online_method

__all__ = ["Map", "MAP_VERSION", "MapFileError"]

logger = logging.getLogger(__name__)

#: bumped whenever the ``map`` section changes incompatibly
MAP_VERSION = 1
_MAP_FIELDS: dict[str, type | tuple[type, ...]] = {
    "map_version": int,
    "n_places": int,
    "source": str,
    "source_kind": str,
    "topic": (str, type(None)),
    "every": str,
    "positions_from": (str, type(None)),
    "video_decode": int,
}
#: fields a file may lack: maps not of a video have no ``video_decode``, nor maps of a video
#: from before flyvpr applied its rotation (read as version 1, the frames as stored)
_OPTIONAL_MAP_FIELDS = ("video_decode",)


def spacing_of(positions) -> float | None:
    """Metres between consecutive places of a map with ``positions`` (``(n_places, 2)``, NaN
    where unknown, or None): the median step between neighbouring places that both have a
    position; None without positions, or when that median is 0 or undefined.  (Maps of
    :class:`Map` and compact maps alike.)"""
    if positions is None:
        return None
    steps = np.hypot(*np.diff(np.asarray(positions, dtype=np.float64), axis=0).T)
    steps = steps[np.isfinite(steps)]
    if steps.size == 0:
        return None
    spacing = float(np.median(steps))
    return spacing if spacing > 0 else None


class MapFileError(ValueError):
    """A file that is not a valid flyvpr map (the message names the file and the field)."""


class Map:
    """A fitted method and its places.

    Parameters
    ----------
    method : Method
        Fitted on the places' images.
    size : (int, int)
        (H, W) the images were pre-processed to.
    timestamps : ndarray, shape (n_places,)
        Seconds; NaN where the recording has no clock.
    source_index : ndarray, shape (n_places,)
        Index of each place's frame in the recording.
    positions : ndarray, shape (n_places, 2), optional
        x, y in metres (NaN where unknown).
    thumbnails : ndarray, shape (n_places, H, W), uint8, optional
    info : dict, optional
        ``source``, ``source_kind``, ``topic``, ``every``, ``positions_from`` (where they came
        from); for a video, ``video_decode`` (how its frames were decoded).
    """

    def __init__(
        self, method, size, timestamps, source_index, positions=None, thumbnails=None, info=None
    ):
        self.method = method
        self.size = (int(size[0]), int(size[1]))
        self.source_index = np.asarray(source_index, np.int64)
        n = self.source_index.shape[0] if self.source_index.ndim == 1 else -1
        fitted = getattr(getattr(method, "frontend", None), "n_reference_", None)
        if n < 1 or (fitted is not None and n != fitted):
            places = "" if fitted is None else f"{fitted} (the method's places)"
            raise ValueError(
                f"source_index must have shape ({places or 'n_places'},), one frame index a "
                f"place; got {self.source_index.shape}"
            )
        self.timestamps = np.asarray(timestamps, np.float64)
        self.positions = None if positions is None else np.asarray(positions, np.float64)
        self.thumbnails = thumbnails
        for name, value, shape in (
            ("timestamps", self.timestamps, (n,)),
            ("positions", self.positions, (n, 2)),
            ("thumbnails", thumbnails, (n, None, None)),
        ):
            got = None if value is None else np.shape(value)
            if got is not None and (
                len(got) != len(shape)
                or any(want is not None and g != want for g, want in zip(got, shape, strict=True))
            ):
                want = ", ".join(
                    "H" if w is None and i == 1 else "W" if w is None else str(w)
                    for i, w in enumerate(shape)
                )
                raise ValueError(
                    f"{name} must have shape ({want}{',' if len(shape) == 1 else ''}), one "
                    f"entry a place ({n} places); got {got}"
                )
        self.info = {
            "source": "",
            "source_kind": "",
            "topic": None,
            "every": "1",
            "positions_from": None,
            **(info or {}),
        }

    @property
    def n_places(self) -> int:
        return int(self.source_index.shape[0])

    @property
    def has_positions(self) -> bool:
        return self.positions is not None

    @property
    def place_spacing(self) -> float | None:
        """Metres between consecutive places: the median over neighbouring places that both
        have a position (None without positions, or when that median is 0 or undefined).

        It turns odometry in metres into places for the localizer
        (:meth:`flyvpr.localization.Localizer.from_map`).
        """
        return spacing_of(self.positions)

    @property
    def breaks(self) -> tuple[int, ...]:
        """Places where the map's route is broken: each place whose position lies more than
        :data:`flyvpr.temporal.cann.BREAK_FACTOR` (5) times the usual step around it from the
        place before it (the median of the steps up to 5 places on either side: a stretch of
        the route left out, a jump of the position fix; a stretch driven faster is none), as
        :func:`flyvpr.temporal.cann.route_breaks` reads positions; a step with an unknown
        position at either end is not judged.  Empty without positions.

        :meth:`flyvpr.localization.Localizer.from_map` gives them to the CANN (its
        ``breaks``), which does not carry the robot across them.  A glitch of the positions
        (a fix that jumps away and back) makes false ones: the filter then loses the robot for
        a few frames each time it passes there (``flyvpr localize --no-breaks``, or
        ``Localizer.from_map(path, breaks=())``, reads the map as one route).
        """
        from ..temporal.cann._route import position_breaks

        return position_breaks(self.positions)

    # -- building ---------------------------------------------------------------------------
    @classmethod
    def build(
        cls,
        source,
        method=DEFAULT_METHOD,
        *,
        size=DEFAULT_SIZE,
        topic: str | None = None,
        every=None,
        positions=None,
        position_topic: str | None = None,
        random_state=0,
        frontend_params=None,
        filter_params=None,
        progress: bool = False,
        n_jobs: int | None = None,
        scheduler=None,
    ) -> Map:
        """Fit ``method`` on the kept frames of a recording.

        Parameters
        ----------
        source : str, Path or Source
            Image folder, video file or ROS bag (see :func:`flyvpr.sources.open_source`).
        method : str or Method
            Default :data:`flyvpr.methods.DEFAULT_METHOD`.
        size : (int, int)
        topic : str, optional
            Image topic of a bag.
        every : str or Every, optional
            ``3``, ``0.5s`` or ``2m`` (see :func:`flyvpr.sources.parse_every`).
        positions : str, Path or Positions, optional
            A ``timestamp,x,y`` or ``frame,x,y`` CSV.  A place gets the straight line between
            the rows on either side of its frame (by timestamp or by index), none outside the
            rows or inside a gap between them (:mod:`flyvpr.sources.positions`).
        position_topic : str, optional
            A NavSatFix or Odometry topic of the same bag (read the same way).
        progress : bool
            Show a progress bar (on stderr) of the frames read (and, with ``n_jobs`` or
            ``scheduler``, of each pass over them).
        n_jobs : int, optional
            Encode the frames in chunks on this many local processes (-1: all cores).
        scheduler : str or dask.distributed.Client, optional
            Encode the chunks on a Dask cluster: its scheduler's address
            (``tcp://host:8786``) or a connected Client.  Needs the ``dask`` extra.

        Notes
        -----
        With ``n_jobs`` or ``scheduler`` the frames are still read in this process; what the
        front end learns from the whole traverse (kenyon's static-pixel mask and feature mean)
        is learned here too, and the per-frame work (kenyon's optic lobe and codes, pixels'
        patch normalisation) goes to the workers in chunks of
        :data:`flyvpr._chunks.CHUNK` frames.  The map is the same, byte for byte, as the
        one-process build.  Front ends that cannot split their fit (flyhash, the trained
        networks) fit in this process.

        Raises
        ------
        RecordingError
            If the recording cannot be read or ``every`` keeps fewer than 2 frames.
        ValueError, TypeError
            For a bad ``n_jobs`` or ``scheduler``, or both given.
        ImportError
            If ``scheduler`` is given and the ``dask`` extra is not installed.
        ConnectionError
            If the scheduler cannot be reached (checked before any frame is read).
        """
        runner = ChunkRunner(n_jobs, scheduler, progress=progress)
        m = online_method(method, random_state, frontend_params, filter_params)
        src = source if isinstance(source, Source) else open_source(source, topic=topic)
        every = parse_every(every)
        pos = positions if isinstance(positions, Positions) else None
        if pos is None:
            bag = src.path if src.kind == "bag" else None
            pos = read_positions(positions, bag=bag, topic=position_topic)
        with runner:
            frames = _read_frames(src, size, every, pos, progress)
            n = len(frames)
            if n < 2:
                raise RecordingError(f"{src.describe()}: a map needs at least 2 places; got {n}")
            check_memory(n * n * 8 * 2, f"a map of {n} places from {src.path}")
            if runner.parallel and m.frontend._fits_in_chunks:
                logger.info("map: encoding %d frames on %s", n, runner.describe())
                m._fit_checked(frames.images, runner)
            else:
                if runner.parallel:
                    logger.warning(
                        "map: the %s front end cannot split its fit; fitting in one process",
                        m.frontend.name,
                    )
                m.fit(frames.images)
        # between rows, as the query's odometry reads them: a position topic slower than the
        # camera gives each place its own point on the way, not the nearest row's
        xy = None if pos is None else pos.at(frames.indices, frames.timestamps, interpolate=True)
        if pos is not None:
            pos.check_covers(xy, frames.indices, frames.timestamps, src.describe())
        thumbs = np.rint(frames.images * 255.0).astype(np.uint8)
        info = {
            "source": str(src.path),
            "source_kind": src.kind,
            "topic": getattr(src, "topic", None),
            "every": str(every),
            "positions_from": None if pos is None else pos.origin,
        }
        if src.kind == "video":
            info["video_decode"] = _VIDEO_DECODE
        logger.info("map: %d places from %s", n, src.describe())
        return cls(m, size, frames.timestamps, frames.indices, xy, thumbs, info)

    # -- files ------------------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the map (atomically) as a model file with a ``map`` section."""
        meta = {"map_version": MAP_VERSION, "n_places": self.n_places, **self.info}
        arrays = {"map/timestamps": self.timestamps, "map/source_index": self.source_index}
        if self.positions is not None:
            arrays["map/positions"] = self.positions
        if self.thumbnails is not None:
            arrays["map/thumbnails"] = np.asarray(self.thumbnails, np.uint8)
        return save_method(self.method, path, size=self.size, sections={"map": (meta, arrays)})

    @classmethod
    def load(cls, path, *, size=None) -> Map:
        """Read a map written by :meth:`save`.

        Raises
        ------
        FileNotFoundError
            If the file does not exist.
        flyvpr.modelio.ModelFileError
            For anything wrong with the model part (another format version, image size, a
            failed checksum ...), and for a bare model file without a map.

        Notes
        -----
        A map of a video built before flyvpr applied a video's rotation (no ``video_decode``)
        loads with a warning: its places are the frames as stored, so rebuild it if the video
        was recorded rotated.
        """
        method, found = _load(path, size, {"map": _read_section}, "map file")
        section = found["map"]
        n = method.frontend.n_reference_
        if section["n_places"] != n:
            raise MapFileError(
                f"map file {path}: map.n_places is {section['n_places']} but the model has "
                f"{n} places"
            )
        image_size = tuple(method.frontend.image_shape_)
        info = {
            k: section[k]
            for k in _MAP_FIELDS
            if k in section and k not in ("map_version", "n_places")
        }
        m = cls(
            method,
            image_size,
            section["timestamps"],
            section["source_index"],
            section.get("positions"),
            section.get("thumbnails"),
            info,
        )
        _warn_unrotated(path, m.info)
        return m


def _warn_unrotated(path, info: dict, command: str = "flyvpr map") -> None:
    """Warn of a map of a video whose frames were decoded as stored: built before flyvpr
    applied a video's display matrix, so its places may be sideways or upside down against
    the upright frames a query now gives (also said of compact maps, with their ``command``)."""
    if info.get("source_kind") != "video" or info.get("video_decode", 1) >= _VIDEO_DECODE:
        return
    logger.warning(
        "map file %s was built from a video before flyvpr applied a video's rotation: its "
        "places are the frames as stored, while query frames now come upright; if the video "
        "was recorded rotated (a phone held sideways, a camera mounted upside down), rebuild "
        "the map with `%s`",
        path, command,
    )  # fmt: skip


def _read_frames(src: Source, size, every, positions, progress: bool):
    """Every kept frame of ``src`` in one batch, with a progress bar when asked."""
    if not progress:
        return src.read_all(size, every=every, positions=positions)
    from tqdm.auto import tqdm

    parts = []
    with tqdm(desc="reading frames", unit="frame") as bar:
        for b in src.batches(size, every=every, positions=positions):
            parts.append(b)
            bar.update(len(b))
    if not parts:
        raise RecordingError(f"{src.describe()}: every={every} keeps no frame")
    return Batch(
        np.concatenate([b.images for b in parts]),
        np.concatenate([b.timestamps for b in parts]),
        np.concatenate([b.indices for b in parts]),
    )


def _read_section(r, section: dict) -> dict:
    """Check the ``map`` section of a model file and read its arrays (``r`` is modelio's reader)."""
    for key, kind in _MAP_FIELDS.items():
        if key not in section and key in _OPTIONAL_MAP_FIELDS:
            continue
        if key not in section:
            raise r.error(f"map.{key}", "missing")
        if not isinstance(section[key], kind) or isinstance(section[key], bool):
            raise r.error(f"map.{key}", f"has the wrong type: {type(section[key]).__name__}")
    extra = sorted(set(section) - set(_MAP_FIELDS))
    if extra:
        raise r.error(f"map.{extra[0]}", "not a field of a flyvpr map")
    if section["map_version"] != MAP_VERSION:
        raise r.error(
            "map.map_version",
            f"the file has map version {section['map_version']}; this flyvpr reads version "
            f"{MAP_VERSION}: rebuild the map with `flyvpr map`",
        )
    n = section["n_places"]
    if n < 1:
        raise r.error("map.n_places", f"must be >= 1; got {n}")
    if section.get("video_decode", 1) < 1:
        raise r.error("map.video_decode", f"must be >= 1; got {section['video_decode']}")
    out = dict(section)
    out["timestamps"] = r.array(
        "map/timestamps", "map.timestamps", ArraySpec("float64", (n,), False)
    )
    out["source_index"] = r.array("map/source_index", "map.source_index", ArraySpec("int64", (n,)))
    names = set(r.zf.namelist())
    if "map/positions.npy" in names:
        spec = ArraySpec("float64", (n, 2), False)
        out["positions"] = r.array("map/positions", "map.positions", spec)
    if "map/thumbnails.npy" in names:
        spec = ArraySpec("uint8", (n, None, None))
        out["thumbnails"] = r.array("map/thumbnails", "map.thumbnails", spec)
    return out
