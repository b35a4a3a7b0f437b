"""Per-frame records of ``flyvpr localize --out``: CSV or JSON Lines, chosen by the suffix.

One record is a ``dict`` of the run's columns (``frame``, ``timestamp``, ``place``, ...).
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

import csv
import json
import math
import os
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .._io import atomic_open, resolve_output

__all__ = ["RECORD_FORMATS", "Records", "csv_cell", "json_value", "open_records", "record_format"]


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
    """

    #: open mode and keyword arguments of the file (text by default)
    mode = "w"
    open_kwargs = {"newline": "", "encoding": "utf-8"}

    def __init__(self, fh, columns, *, flush: bool = False):
        self.fh, self.columns, self.flush = fh, list(columns), flush
        self.n_records = 0
        self._begin()
        if flush:
            self.fh.flush()

    def write(self, row: dict) -> None:
        """Write one record (a dict with every column as a key)."""
        self._write_row(row)
        self.n_records += 1
        if self.flush:
            self.fh.flush()

    def close(self) -> None:
        """Finish the file (a format's trailer, if any); the file object stays open."""
        self._end()
        self.fh.flush()

    def _begin(self) -> None:
        pass

    def _write_row(self, row: dict) -> None:  # pragma: no cover - every subclass fills it
        raise NotImplementedError

    def _end(self) -> None:
        pass


class CsvRecords(Records):
    """Records as CSV: a header line of the columns, then one line per record."""

    def _begin(self) -> None:
        self.writer = csv.writer(self.fh, lineterminator="\n")
        self.writer.writerow(self.columns)

    def _write_row(self, row: dict) -> None:
        self.writer.writerow(
            [csv_cell(row[c]) for c in self.columns]
        )


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

    def _write_row(self, row: dict) -> None:
        clean = {k: json_value(v) for k, v in row.items()}
        self.fh.write(json.dumps(clean) + "\n")


#: the file suffix of ``--out`` -> its writer; any other suffix is written as CSV
RECORD_FORMATS: dict[str, type[Records]] = {".csv": CsvRecords, ".jsonl": JsonlRecords}


def record_format(path) -> type[Records]:
    """The writer class for an ``--out`` path, chosen by its suffix (CSV when unknown)."""
    return RECORD_FORMATS.get(Path(path).suffix.lower(), CsvRecords)


@contextmanager
def open_records(path, columns, *, flush: bool = False, keep_partial: bool = False):
    """Open the records file ``path``; yields a :class:`Records` writer.

    Parameters
    ----------
    path : str or Path
        The file to write; its suffix picks the format (:data:`RECORD_FORMATS`).
    columns : list of str
        The keys of every record.
    flush : bool
        Write straight to ``path`` and flush each record as it is written, for ``tail -f``
        on a live run; the file keeps every record written whatever ends the run.
    keep_partial : bool
        Without ``flush``: when the run ends by an exception (Ctrl-C, SIGTERM, an error),
        finish and keep the records written so far instead of leaving ``path`` untouched.

    Raises
    ------
    flyvpr._io.OutputPathError
        If ``path`` is a folder, FIFO, socket or device.
    OSError
        If writing fails; the message names ``path``.
    """
    kind = record_format(path)
    if flush:
        target = resolve_output(path)
        with open(target, kind.mode, **kind.open_kwargs) as fh:
            records = kind(fh, columns, flush=True)
            try:
                yield records
            finally:
                records.close()
                os.fsync(fh.fileno())
        return
    cut_short = None
    with atomic_open(path, kind.mode, **kind.open_kwargs) as fh:
        records = kind(fh, columns)
        try:
            yield records
        except BaseException as exc:
            if not keep_partial:
                raise
            cut_short = exc  # leave the with normally, so the records so far are renamed in
        records.close()
    if cut_short is not None:
        raise cut_short
