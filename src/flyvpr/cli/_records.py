"""Per-frame records of ``flyvpr localize --out``: CSV, JSON Lines or MCAP, by the suffix.

One record is a ``dict`` of the run's columns (``frame``, ``timestamp``, ``place``, ...).
Numbers are exact in every format: a float is written as the shortest decimal that reads back
to the same float64 (``repr``), so Unix timestamps and positions far from the origin keep
every digit.  MCAP (:class:`McapRecords`) adds JSON schemas for Foxglove and, when asked, the
query and matched place's thumbnails.
:func:`open_records` opens the writer for ``--out`` and decides how the file reaches disk:

* By default the records go to a temporary file beside the target, renamed over it when the
  run ends well; on an error, Ctrl-C or SIGTERM the temporary file is removed and the target
  is left as it was (the rule of ``docs/guide/reliability.md``).
* ``keep_partial=True``: the same temporary file, but when the run is cut short the records
  written so far are finished and renamed over the target before the exception goes on, so an
  interrupted run keeps every processed frame.
* ``flush=True`` (live runs): the records are written straight to the target, and each is
  flushed as it is made, so ``tail -f where.csv`` follows the run.  The file holds whole
  records only and keeps every processed record whatever ends the run.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import base64
import csv
import io
import json
import math
import os
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .._io import atomic_open, make_folders, remove_folders, resolve_output
from ._common import UsageError

__all__ = [
    "COLUMN_SCHEMAS",
    "RECORD_FORMATS",
    "CsvRecords",
    "JsonlRecords",
    "McapRecords",
    "Records",
    "check_thumbnails",
    "csv_cell",
    "json_value",
    "open_records",
    "record_format",
]


def csv_cell(value):
    """A record's value as a CSV cell, exactly: the shortest text that reads back to it.

    Floats are written as ``repr`` writes them (the shortest decimal that round-trips to
    the same float64, e.g. ``1700000000.123456`` or ``1000000.25``), never rounded to a few
    significant digits; NaN and ``None`` become an empty cell; integers (also numpy's) stay
    integers.

    Examples
    --------
    >>> csv_cell(1700000000.1234567), csv_cell(1e6 + 1 / 3), csv_cell(float("nan")), csv_cell(7)
    ('1700000000.1234567', '1000000.3333333334', '', 7)
    """
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return "" if math.isnan(value) else repr(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


class Records:
    """Base class: writes one record per call of :meth:`write` to an open text file.

    Subclasses fill :meth:`_begin` (called once, before the first record), :meth:`_write_row`
    and optionally :meth:`_end` (called once when the file is finished).

    Parameters
    ----------
    fh : file object
        Open for writing text.
    columns : list of str
        The keys of every record, in the order the file shows them.
    flush : bool
        Flush the file after each record (for ``tail -f`` on a live run).
    thumbnails : bool
        Also write the images given to :meth:`write` (only formats that carry images).
    metadata : dict of str to str, optional
        About the run (map, source, method): kept by formats that have a place for it.

    Raises
    ------
    ValueError
        For ``thumbnails`` with a format that carries no images.
    """

    #: open mode and keyword arguments of the file (text by default)
    mode = "w"
    open_kwargs: dict = {"newline": "", "encoding": "utf-8"}
    #: the file suffix and whether the format can hold images besides the records
    suffix = ".csv"
    carries_images = False

    def __init__(self, fh, columns, *, flush=False, thumbnails=False, metadata=None):
        if thumbnails and not self.carries_images:
            raise ValueError(
                f"thumbnails: a {self.suffix} records file holds no images; "
                f"write {', '.join(k for k, v in RECORD_FORMATS.items() if v.carries_images)}"
            )
        self.fh, self.columns, self.flush = fh, list(columns), flush
        self.thumbnails, self.metadata = thumbnails, dict(metadata or {})
        self.n_records = 0
        self._begin()
        if flush:
            self.fh.flush()

    def write(self, row: dict, images=None) -> None:
        """Write one record.

        Parameters
        ----------
        row : dict
            Every column as a key.
        images : dict of str to ndarray, optional
            Gray uint8 images of shape (H, W) shown with the record, such as ``query`` (the
            frame as the localizer saw it) and ``match`` (the matched place's thumbnail);
            written only with ``thumbnails`` and a format that carries images.
        """
        self._write_row(row)
        if images and self.thumbnails:
            self._write_images(row, images)
        self.n_records += 1
        if self.flush:
            self.fh.flush()

    def close(self) -> None:
        """Finish the file (a format's trailer, if any); the file object stays open."""
        self._end()
        self.fh.flush()

    @classmethod
    def check_available(cls) -> None:
        """Raise ImportError, naming the pip extra, if the format's library is missing."""

    def _begin(self) -> None:
        pass

    def _write_row(self, row: dict) -> None:  # pragma: no cover - every subclass fills it
        raise NotImplementedError

    def _write_images(self, row: dict, images: dict) -> None:  # pragma: no cover
        raise NotImplementedError

    def _end(self) -> None:
        pass


class CsvRecords(Records):
    """Records as CSV: a header line of the columns, then one line per record."""

    def _begin(self) -> None:
        self.writer = csv.writer(self.fh, lineterminator="\n")
        self.writer.writerow(self.columns)

    def _write_row(self, row: dict) -> None:
        self.writer.writerow([csv_cell(row[c]) for c in self.columns])


def json_value(value):
    """A record's value for JSON: exact floats, ``null`` for NaN and infinities, plain ints."""
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


class JsonlRecords(Records):
    """Records as JSON Lines: one JSON object per line.

    Floats are exact (as ``repr`` writes them); NaN and infinities become ``null``.
    """

    suffix = ".jsonl"

    def _write_row(self, row: dict) -> None:
        clean = {k: json_value(v) for k, v in row.items()}
        self.fh.write(json.dumps(clean) + "\n")


#: JSON Schema of the known columns (one type each, as Foxglove reads them); a column whose
#: value may be unknown is left out of a message when it is (null in JSON Lines), and is not
#: ``required``; other columns get the type of their first value
COLUMN_SCHEMAS = {
    "frame": {"type": "integer", "description": "index of the frame in the recording"},
    "timestamp": {
        "type": "number",
        "description": "seconds on the recording's clock (absent when it has none)",
    },
    "place": {"type": "integer", "description": "index of the matched place in the map"},
    "confidence": {"type": "number", "description": "the localizer's confidence"},
    "state": {"type": "string", "description": "the localizer's state"},
    "relocated": {"type": "integer", "description": "1 when the filter jumped to a new place"},
    "x": {"type": "number", "description": "map x of the matched place (m)"},
    "y": {"type": "number", "description": "map y of the matched place (m)"},
    "odometry": {
        "type": "number",
        "description": "places moved since the previous frame, as the filter was given them "
        "(absent on a frame without odometry)",
    },
    "correct": {"type": "integer", "description": "1 when the place is a true match"},
}
#: the known columns that may be unknown (NaN) in a record
NULLABLE = frozenset({"timestamp", "confidence", "x", "y", "odometry"})


def _json_type(value) -> dict:
    if isinstance(value, (bool, np.bool_)):
        return {"type": "boolean"}
    if isinstance(value, (int, np.integer)):
        return {"type": "integer"}
    if isinstance(value, (float, np.floating)):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    return {}


#: foxglove.CompressedImage, as a JSON Schema (bytes in JSON are base64 text)
_COMPRESSED_IMAGE_SCHEMA = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {
                "sec": {"type": "integer", "minimum": 0},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
            },
        },
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


class McapRecords(Records):
    """Records as MCAP messages with JSON schemas, for Foxglove and other MCAP readers.

    Each record is one JSON message (the keys and exact values of JSON Lines, less those
    that are null there) on the topic ``/flyvpr/localization``, schema
    ``flyvpr.Localization`` (a JSON Schema of the columns, registered with the first record).
    Its log and publish time is the frame's timestamp in nanoseconds, or the time the record
    was written when the recording has none.  With ``thumbnails``, each image given to
    :meth:`write` goes as a PNG in a ``foxglove.CompressedImage`` message on
    ``/flyvpr/<name>`` (``/flyvpr/query``, ``/flyvpr/match``) at the same time.  The run's
    metadata is an MCAP metadata record named ``flyvpr``.  Chunks are zstd-compressed; with
    ``flush`` the messages are written one by one, unchunked, so each is on disk at once.
    """

    mode = "wb"
    open_kwargs = {}
    suffix = ".mcap"
    carries_images = True
    topic = "/flyvpr/localization"

    @classmethod
    def check_available(cls) -> None:
        try:
            import mcap.writer  # noqa: F401
        except ImportError:
            raise ImportError(
                "writing .mcap records needs the 'mcap' package: pip install 'flyvpr[recordings]'"
            ) from None

    def _begin(self) -> None:
        from mcap.writer import CompressionType, Writer

        from .._version import __version__

        if self.flush:
            self.writer = Writer(self.fh, use_chunking=False, compression=CompressionType.NONE)
        else:
            self.writer = Writer(self.fh, compression=CompressionType.ZSTD)
        self.writer.start(profile="", library=f"flyvpr {__version__}")
        self.channel: int | None = None
        self.image_channels: dict[str, int] = {}
        self.sequence = 0
        if self.metadata:
            self.writer.add_metadata("flyvpr", {k: str(v) for k, v in self.metadata.items()})

    def _channel(self, topic: str, name: str, schema: dict) -> int:
        schema_id = self.writer.register_schema(
            name=name, encoding="jsonschema", data=json.dumps(schema).encode()
        )
        return self.writer.register_channel(
            topic=topic, message_encoding="json", schema_id=schema_id
        )

    def _log_time(self, row: dict) -> int:
        t = row.get("timestamp")
        if isinstance(t, (float, int, np.floating, np.integer)) and math.isfinite(t) and t >= 0:
            return round(float(t) * 1e9)
        return time.time_ns()

    def _schema(self, row: dict) -> dict:
        return {
            "title": "flyvpr.Localization",
            "description": "One frame localized by flyvpr against a map",
            "type": "object",
            "properties": {c: COLUMN_SCHEMAS.get(c) or _json_type(row[c]) for c in self.columns},
            "required": [c for c in self.columns if c not in NULLABLE],
        }

    def _write_row(self, row: dict) -> None:
        if self.channel is None:
            self.channel = self._channel(self.topic, "flyvpr.Localization", self._schema(row))
        self.log_time = self._log_time(row)
        values = {k: json_value(row[k]) for k in self.columns}
        data = json.dumps({k: v for k, v in values.items() if v is not None}).encode()
        self._message(self.channel, data)

    def _message(self, channel: int, data: bytes) -> None:
        self.writer.add_message(
            channel_id=channel,
            log_time=self.log_time,
            publish_time=self.log_time,
            data=data,
            sequence=self.sequence,
        )
        self.sequence += 1

    def _write_images(self, row: dict, images: dict) -> None:
        sec, nsec = divmod(self.log_time, 1_000_000_000)
        for name, image in images.items():
            if name not in self.image_channels:
                self.image_channels[name] = self._channel(
                    f"/flyvpr/{name}", "foxglove.CompressedImage", _COMPRESSED_IMAGE_SCHEMA
                )
            message = {
                "timestamp": {"sec": sec, "nsec": nsec},
                "frame_id": name,
                "data": base64.b64encode(_png(image)).decode("ascii"),
                "format": "png",
            }
            self._message(self.image_channels[name], json.dumps(message).encode())

    def _end(self) -> None:
        self.writer.finish()


def _png(image) -> bytes:
    """A gray uint8 image (H, W) as PNG bytes."""
    from PIL import Image

    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 2:
        raise ValueError(f"thumbnails must be gray uint8 images (H, W); got {a.dtype} {a.shape}")
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return buf.getvalue()


#: the file suffix of ``--out`` -> its writer; any other suffix is written as CSV
RECORD_FORMATS: dict[str, type[Records]] = {
    ".csv": CsvRecords,
    ".jsonl": JsonlRecords,
    ".mcap": McapRecords,
}


def record_format(path) -> type[Records]:
    """The writer class for an ``--out`` path, chosen by its suffix (CSV when unknown)."""
    return RECORD_FORMATS.get(Path(path).suffix.lower(), CsvRecords)


def check_thumbnails(args) -> None:
    """``--mcap-thumbnails`` needs ``--out`` of a format that holds images (MCAP): a usage
    error before any work, for recordings and live sources alike."""
    if args.mcap_thumbnails and (args.out is None or not record_format(args.out).carries_images):
        raise UsageError("--mcap-thumbnails needs --out FILE.mcap (the thumbnails go in it)")


@contextmanager
def open_records(
    path,
    columns,
    *,
    flush: bool = False,
    keep_partial: bool = False,
    thumbnails: bool = False,
    metadata=None,
):
    """Open the records file ``path``; yields a :class:`Records` writer.

    Parameters
    ----------
    path : str or Path
        The file to write; its suffix picks the format (:data:`RECORD_FORMATS`).
    columns : list of str
        The keys of every record.
    flush : bool
        Write straight to ``path`` and flush each record as it is written, for ``tail -f``
        on a live run; the file keeps every record written whatever ends the run.  A run that
        writes no record leaves no file (nor the folders made for it).
    keep_partial : bool
        Without ``flush``: when the run ends by an exception (Ctrl-C, SIGTERM, an error),
        finish and keep the records written so far instead of leaving ``path`` untouched.
    thumbnails : bool
        Also write the images passed to :meth:`Records.write` (``.mcap`` only).
    metadata : dict of str to str, optional
        About the run, for formats with a place for it (MCAP's metadata record).

    Raises
    ------
    ValueError
        For ``thumbnails`` with a format that holds no images.
    ImportError
        For ``.mcap`` without the ``mcap`` package (``pip install 'flyvpr[recordings]'``).
    flyvpr._io.OutputPathError
        If ``path`` is a folder, FIFO, socket or device.
    OSError
        If writing fails; the message names ``path``.
    """
    kind = record_format(path)
    kind.check_available()  # before the target is touched
    if thumbnails and not kind.carries_images:
        raise ValueError(
            f"{path}: a {kind.suffix} records file holds no thumbnails; name an .mcap file"
        )
    if flush:
        target = resolve_output(path)
        created = make_folders(target.parent)  # here, not before: a refused run makes none
        try:
            fh = open(target, kind.mode, **kind.open_kwargs)
        except BaseException:
            remove_folders(created)
            raise
        with fh:
            records = kind(fh, columns, flush=True, thumbnails=thumbnails, metadata=metadata)
            try:
                yield records
            finally:
                records.close()
                os.fsync(fh.fileno())
        if records.n_records == 0:  # (after an exception too) no file of a header only
            target.unlink(missing_ok=True)
            remove_folders(created)
        return
    cut_short = None
    with atomic_open(path, kind.mode, **kind.open_kwargs) as fh:
        records = kind(fh, columns, thumbnails=thumbnails, metadata=metadata)
        try:
            yield records
        except BaseException as exc:
            if not keep_partial:
                raise
            cut_short = exc  # leave the with normally, so the records so far are renamed in
        records.close()
    if cut_short is not None:
        raise cut_short
