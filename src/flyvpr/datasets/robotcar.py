"""Oxford RobotCar: the same route in Oxford driven many times, with INS/GPS poses.

The paper (Sec. Experiments) uses an overcast run as reference and day and
night runs as queries, 1000 images per traverse, and counts a match as
correct within 50 m.  This loader reads the dataset's own folder layout (as
extracted from the download tars and read by the official SDK,
``ori-mrg/robotcar-dataset-sdk``): raw Bayer GBRG images of the centre
stereo camera named by their UNIX time in microseconds, and the pose log
``gps/ins.csv`` (or ``gps/gps.csv``).  It interpolates a metric position
(northing, easting) for every image and keeps one frame every ``spacing``
metres of driven distance, so a stop at a traffic light does not produce a
run of identical places.
"""

from __future__ import annotations

import csv
import io
import logging
from pathlib import Path

import numpy as np

from .._validation import check_real
from .base import (
    Benchmark,
    Traverse,
    _check_root,
    _check_unique_columns,
    _check_window,
    _list_images_or_explain,
    _read_csv_text,
    _subfolders,
    ground_truth_from_positions,
)

__all__ = ["load_robotcar", "read_poses", "select_by_distance", "LAYOUT"]

logger = logging.getLogger(__name__)

#: Columns of ``gps/ins.csv`` as written by the dataset (and read by the SDK).
INS_COLUMNS = (
    "timestamp",
    "ins_status",
    "latitude",
    "longitude",
    "altitude",
    "northing",
    "easting",
    "down",
    "utm_zone",
    "velocity_north",
    "velocity_east",
    "velocity_down",
    "roll",
    "pitch",
    "yaw",
)
#: Columns of ``gps/gps.csv``.
GPS_COLUMNS = (
    "timestamp",
    "number_of_satellites",
    "latitude",
    "longitude",
    "altitude",
    "latitude_sigma",
    "longitude_sigma",
    "altitude_sigma",
    "northing",
    "easting",
    "down",
    "utm_zone",
)
#: Longest accepted time stamp: 18 digits always fit int64 (microseconds until year 33658).
_MAX_DIGITS = 18
#: The columns this loader reads from either file.
_NEEDED = ("timestamp", "northing", "easting")
#: the share of a run's images outside its pose log's time span from which a warning says so
#: (below it, an info line: a pose log that starts a little after the camera is usual)
_DROPPED_WARNING = 0.05


def _span(us: np.ndarray) -> str:
    """A run of microsecond time stamps as ``first..last us (seconds s)``."""
    return f"{us[0]}..{us[-1]} us ({(us[-1] - us[0]) / 1e6:.1f} s)"


#: Folder layout shown in errors and by ``flyvpr datasets``.
LAYOUT = (
    "<root>/<run>/stereo/centre/<timestamp>.png  raw Bayer GBRG 8-bit PNG, named by UNIX time "
    "in microseconds (e.g. 2014-12-09-13-21-02/stereo/centre/1418132416737115.png)\n"
    "<root>/<run>/gps/ins.csv  columns: " + ",".join(INS_COLUMNS) + "\n"
    "  or <root>/<run>/gps/gps.csv  columns: " + ",".join(GPS_COLUMNS) + "\n"
    "(ins.csv is preferred when both exist; only timestamp, northing and easting are read)"
)


def _first_bad(values: list[str], convert) -> int:
    """Index of the first string that ``convert`` rejects (the slow path, for the message)."""
    for i, v in enumerate(values):
        try:
            convert(v)
        except ValueError:
            return i
    return -1


def read_poses(path) -> tuple[np.ndarray, np.ndarray]:
    """Read time stamps and (northing, easting) from a RobotCar ``ins.csv`` or ``gps.csv``.

    Parameters
    ----------
    path : str or Path
        CSV file with a header row naming at least ``timestamp``, ``northing``
        and ``easting`` (both SDK formats do; other columns are ignored).

    Returns
    -------
    timestamps : ndarray of int64, shape (M,)
        UNIX time in microseconds, strictly increasing (as the SDK requires).
    positions : ndarray of float64, shape (M, 2)
        (northing, easting) in metres.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        For a file that is not UTF-8 text, an empty file, missing columns (named) or one
        named twice, a row with the wrong number of fields, a non-numeric, overlong (over 18
        digits) or non-increasing time stamp, or a non-numeric position (the message names
        the file and line).
    """
    path = Path(path)
    text = _read_csv_text(path, "pose file")
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        header = next((row for row in reader if row), None)
        if header is None:
            raise ValueError(f"{path}: empty file; expected a header row and pose rows")
        header = [h.strip() for h in header]
        missing = [c for c in _NEEDED if c not in header]
        if missing:
            raise ValueError(
                f"{path}: missing column(s) {', '.join(missing)}; got columns "
                f"{','.join(header)}; expected the SDK's ins.csv columns {','.join(INS_COLUMNS)} "
                f"or gps.csv columns {','.join(GPS_COLUMNS)}"
            )
        _check_unique_columns(header, _NEEDED, str(path))
        rows, lines = [], []
        for row in reader:
            if not row:
                continue
            rows.append(row)
            lines.append(reader.line_num)
    if not rows:
        raise ValueError(f"{path}: no pose rows after the header")
    width = len(header)
    bad = [i for i, row in enumerate(rows) if len(row) != width]
    if bad:
        i = bad[0]
        raise ValueError(
            f"{path}, line {lines[i]}: expected {width} fields as in the header; got {len(rows[i])}"
        )
    where = {name: header.index(name) for name in _NEEDED}
    cols = {name: [row[i].strip() for row in rows] for name, i in where.items()}

    stamps = np.array(cols["timestamp"])
    digits = np.char.isdigit(stamps) & (np.char.str_len(stamps) <= _MAX_DIGITS)
    if not digits.all():
        i = int(np.argmin(digits))
        raise ValueError(
            f"{path}, line {lines[i]}: timestamp must be an integer number of microseconds "
            f"with at most {_MAX_DIGITS} digits; got {str(stamps[i])!r}"
        )
    timestamps = stamps.astype(np.int64)
    positions = np.empty((len(rows), 2), dtype=np.float64)
    for k, name in enumerate(("northing", "easting")):
        try:
            positions[:, k] = np.array(cols[name]).astype(np.float64)
        except ValueError:
            i = _first_bad(cols[name], float)
            raise ValueError(
                f"{path}, line {lines[i]}: {name} must be a number; got {cols[name][i]!r}"
            ) from None
    finite = np.isfinite(positions).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise ValueError(f"{path}, line {lines[i]}: northing/easting is NaN or infinite")
    steps = np.diff(timestamps)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1
        raise ValueError(
            f"{path}, line {lines[i]}: timestamps must be strictly increasing; "
            f"{timestamps[i]} follows {timestamps[i - 1]}"
        )
    return timestamps, positions


def select_by_distance(positions, spacing) -> np.ndarray:
    """Indices of frames spaced ``spacing`` metres apart along the driven path.

    Keeps the first frame at or past each multiple of ``spacing`` of the
    cumulative path length (sum of straight steps between consecutive
    positions).  Frames while the vehicle stands still are skipped, and where
    frames are farther apart than ``spacing`` every frame is kept once.

    Parameters
    ----------
    positions : array-like, shape (N, 2)
    spacing : float
        Metres between kept frames, > 0.

    Returns
    -------
    ndarray of intp, strictly increasing, starting at 0

    Examples
    --------
    >>> select_by_distance([[0, 0], [0, 1], [0, 2], [0, 3], [0, 4]], 2.0).tolist()
    [0, 2, 4]
    """
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[0] == 0:
        raise ValueError(f"positions must have shape (N, 2) with N >= 1; got {pos.shape}")
    spacing = check_real(spacing, "spacing", low=0.0, inclusive=True)
    if spacing == 0:
        raise ValueError("spacing must be > 0 metres; got 0")
    travelled = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(pos, axis=0).T))))
    n_marks = int(np.floor(travelled[-1] / spacing)) + 1
    idx = np.searchsorted(travelled, np.arange(n_marks) * spacing, side="left")
    # Rounding can put the last mark a hair beyond the path's end.
    return np.unique(np.minimum(idx, pos.shape[0] - 1))


def _image_timestamps(folder: Path) -> tuple[list[Path], np.ndarray]:
    paths = _list_images_or_explain(folder, LAYOUT, extensions=(".png",))
    stems = [p.stem for p in paths]
    for p, s in zip(paths, stems, strict=True):
        if not s.isdigit() or len(s) > _MAX_DIGITS:
            raise ValueError(
                f"image file name must be a numeric timestamp in microseconds: {p} "
                f"(digits only, at most {_MAX_DIGITS})"
            )
    stamps = np.array(stems).astype(np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    dup = np.flatnonzero(np.diff(stamps) == 0)
    if dup.size:
        raise ValueError(f"two images in {folder} share the timestamp {stamps[dup[0]]}")
    return [paths[i] for i in order], stamps


def _load_run(root: Path, run, role: str, spacing: float):
    """Read one run; returns (traverse, pose file) before windowing."""
    if not isinstance(run, str) or not run:
        raise TypeError(f"{role} must be a run folder name (str); got {run!r}")
    run_dir = root / run
    if not run_dir.is_dir():
        found = _subfolders(root)
        raise FileNotFoundError(
            f"{role} run folder not found: {run_dir}; runs found in {root}: "
            f"{', '.join(found) if found else 'none'}; expected layout:\n{LAYOUT}"
        )
    image_dir = run_dir / "stereo" / "centre"
    if not image_dir.is_dir():
        raise FileNotFoundError(f"image folder not found: {image_dir}; expected layout:\n{LAYOUT}")
    for pose_name in ("ins.csv", "gps.csv"):
        pose_file = run_dir / "gps" / pose_name
        if pose_file.is_file():
            break
    else:
        raise FileNotFoundError(
            f"no pose file for run {run}: neither {run_dir / 'gps' / 'ins.csv'} nor "
            f"{run_dir / 'gps' / 'gps.csv'} exists; expected layout:\n{LAYOUT}"
        )
    paths, image_us = _image_timestamps(image_dir)
    pose_us, pose_ne = read_poses(pose_file)

    # Images outside the pose log's time span cannot be placed: they are dropped
    # (extrapolating would invent positions).
    inside = (image_us >= pose_us[0]) & (image_us <= pose_us[-1])
    if not inside.any():
        raise ValueError(
            f"no image of {image_dir} lies within the time span of {pose_file} "
            f"(images {image_us[0]}..{image_us[-1]} us, poses {pose_us[0]}..{pose_us[-1]} us)"
        )
    if not inside.all():
        # A pose log that starts a little after the camera is usual; one that leaves out a
        # twentieth of the drive or more is said louder (a log cut short, or another run's).
        dropped = int((~inside).sum())
        share = dropped / inside.size
        logger.log(
            logging.WARNING if share >= _DROPPED_WARNING else logging.INFO,
            "%s: dropped %d of %d images (%.1f%%) outside the time span of %s%s",
            run,
            dropped,
            inside.size,
            100.0 * share,
            pose_file,
            " (images " + _span(image_us) + ", poses " + _span(pose_us) + ")"
            if share >= _DROPPED_WARNING
            else "",
        )
    frame_ids = np.flatnonzero(inside)
    # Subtract the first pose time before converting, so float64 keeps microseconds.
    t = (image_us[frame_ids] - pose_us[0]).astype(np.float64)
    tp = (pose_us - pose_us[0]).astype(np.float64)
    positions = np.column_stack([np.interp(t, tp, pose_ne[:, k]) for k in range(2)])
    keep = select_by_distance(positions, spacing)
    traverse = Traverse(
        name=run,
        paths=[paths[i] for i in frame_ids[keep]],
        timestamps=image_us[frame_ids[keep]] / 1e6,
        positions=positions[keep],
        frame_ids=frame_ids[keep],
        bayer="gbrg",
    )
    return traverse, pose_file


def load_robotcar(
    root, reference, query, spacing=5.0, first=0, count=None, tolerance_m=50.0
) -> Benchmark:
    """Load two Oxford RobotCar runs, one frame every ``spacing`` metres, metric ground truth.

    Positions are linearly interpolated in time from the run's
    ``gps/ins.csv`` (preferred) or ``gps/gps.csv`` at each image time stamp;
    images outside the pose log's time span are dropped (an info line says how many; a
    warning, with both time spans, where that is a twentieth of the run or more).  Frames
    are then kept every ``spacing`` metres of driven distance (:func:`select_by_distance`),
    and ``first``/``count`` select a window of those kept frames in each run separately.  A
    query matches every reference frame within ``tolerance_m`` metres (the paper: 50 m, about
    10 frames at the default 5 m spacing).

    Parameters
    ----------
    root : str or Path
        Folder holding the run folders (see ``LAYOUT``).
    reference, query : str
        Run folder names, e.g. ``'2014-12-09-13-21-02'``.
    spacing : float
        Metres between kept frames, > 0.
    first : int
        Position of the first kept frame in the spaced sequence, >= 0.
    count : int, optional
        Number of frames per traverse (the paper: 1000); ``None``: all.
    tolerance_m : float
        Ground-truth radius in metres, >= 0.

    Returns
    -------
    Benchmark
        ``tolerance={"metres": tolerance_m}``; traverses carry ``positions``
        (northing, easting) in metres, ``timestamps`` in UNIX seconds,
        ``frame_ids`` (index in the run's sorted image list) and ``bayer='gbrg'``.

    Raises
    ------
    FileNotFoundError
        If ``root``, a run folder, its ``stereo/centre`` folder or both pose
        files are missing.
    ValueError
        For a malformed pose file (see :func:`read_poses`), image names that
        are not time stamps, no image inside the pose time span, a bad
        ``spacing``/``tolerance_m`` or a window beyond the data.
    """
    root = _check_root(root, LAYOUT)
    spacing = check_real(spacing, "spacing", low=0.0, inclusive=True)
    if spacing == 0:
        raise ValueError("spacing must be > 0 metres; got 0")
    tolerance_m = check_real(tolerance_m, "tolerance_m", low=0.0, inclusive=True)
    ref, ref_source = _load_run(root, reference, "reference", spacing)
    qry, query_source = _load_run(root, query, "query", spacing)
    windows = [
        _check_window(first, count, len(t), f"run {t.name} at {spacing:g} m spacing")
        for t in (ref, qry)
    ]
    ref, qry = (
        t.subset(slice(start, start + n)) for t, (start, n) in zip((ref, qry), windows, strict=True)
    )
    return Benchmark(
        dataset="robotcar",
        reference=ref,
        query=qry,
        ground_truth=ground_truth_from_positions(qry.positions, ref.positions, tolerance_m),
        tolerance={"metres": tolerance_m},
        root=root,
        first=windows[0][0],
        count=count,
        details={
            "spacing_m": spacing,
            "pose_source": {"reference": ref_source.name, "query": query_source.name},
        },
        sources=(ref_source, query_source),
    )
