"""Any two folders of images: frame-index ground truth, or metric from a positions CSV.

Without positions, frame i of the query folder is taken to show the same
place as frame i of the reference folder (both sorted by name), and the
ground truth is ``|i - j| <= tolerance``.  The folders may hold different
numbers of images; the ground truth is then simply non-square.

With positions, one CSV file gives a metric position to every image of both
folders and the ground truth is ``distance <= radius``.  Its header must name
the columns ``traverse,filename,x,y`` (extra columns are ignored):

- ``traverse``: ``reference`` or ``query``;
- ``filename``: the image's file name inside that folder;
- ``x``, ``y``: position in metres (any metric frame, e.g. easting/northing).

Every image of both folders needs exactly one row.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from .._validation import check_positive_int, check_real
from .base import (
    Benchmark,
    Traverse,
    _check_unique_columns,
    _check_window,
    _list_images_or_explain,
    _read_csv_text,
    ground_truth_from_frames,
    ground_truth_from_positions,
)

__all__ = ["load_generic", "read_positions_csv", "LAYOUT", "CSV_COLUMNS"]

#: Header columns required in the positions CSV.
CSV_COLUMNS = ("traverse", "filename", "x", "y")

#: Folder layout shown in errors and by ``flyvpr datasets``.
LAYOUT = (
    "<root>/<reference>/<images>  reference images, in name order (natural sort)\n"
    "<root>/<query>/<images>      query images; frame i matches reference i +- tolerance\n"
    "optional positions CSV (header traverse,filename,x,y; traverse is 'reference' or "
    "'query', x/y in metres; one row per image): ground truth within radius metres"
)


def _folder(root, name, role: str) -> Path:
    if not isinstance(name, (str, Path)):
        raise TypeError(f"{role} must be a folder path (str or Path); got {type(name).__name__}")
    return Path(name) if root is None else Path(root) / name


def read_positions_csv(path, reference_paths, query_paths):
    """Positions of the reference and query images from a ``traverse,filename,x,y`` CSV.

    Parameters
    ----------
    path : str or Path
        The CSV file (see the module docstring).
    reference_paths, query_paths : sequence of Path
        Images of each traverse; ``filename`` is matched against their names.

    Returns
    -------
    reference_positions : ndarray, shape (n_reference, 2)
    query_positions : ndarray, shape (n_query, 2)

    Raises
    ------
    FileNotFoundError
        If the CSV is missing.
    ValueError
        For a file that is not UTF-8 text (a byte-order mark is fine), missing columns or
        one named twice, an unknown traverse, a non-numeric position, a file named twice or
        not in its folder, or an image without a row (the message names the CSV, the line
        and the file).
    """
    path = Path(path)
    text = _read_csv_text(path, "positions CSV")
    index = {
        "reference": {p.name: i for i, p in enumerate(reference_paths)},
        "query": {p.name: i for i, p in enumerate(query_paths)},
    }
    out = {role: np.full((len(files), 2), np.nan) for role, files in index.items()}
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        header = [h.strip() for h in next(reader, [])]
        missing = [c for c in CSV_COLUMNS if c not in header]
        if missing:
            raise ValueError(
                f"{path}: missing column(s) {', '.join(missing)} in the header; "
                f"expected the header {','.join(CSV_COLUMNS)}"
            )
        _check_unique_columns(header, CSV_COLUMNS, str(path))
        col = {c: header.index(c) for c in CSV_COLUMNS}
        for row in reader:
            if not row:
                continue
            where = f"{path}, line {reader.line_num}"
            if len(row) != len(header):
                raise ValueError(
                    f"{where}: expected {len(header)} fields as in the header; got {len(row)}"
                )
            role, name = row[col["traverse"]].strip(), row[col["filename"]].strip()
            if role not in index:
                raise ValueError(f"{where}: traverse must be 'reference' or 'query'; got {role!r}")
            if name not in index[role]:
                raise ValueError(f"{where}: {role} folder holds no image named {name!r}")
            try:
                xy = [float(row[col["x"]]), float(row[col["y"]])]
            except ValueError:
                raise ValueError(
                    f"{where}: x and y must be numbers; got {row[col['x']]!r}, {row[col['y']]!r}"
                ) from None
            if not np.isfinite(xy).all():
                raise ValueError(f"{where}: x and y must be finite; got {xy}")
            i = index[role][name]
            if not np.isnan(out[role][i, 0]):
                raise ValueError(f"{where}: {role} image {name!r} has a second row")
            out[role][i] = xy
    for role, files in (("reference", reference_paths), ("query", query_paths)):
        lacking = np.flatnonzero(np.isnan(out[role][:, 0]))
        if lacking.size:
            raise ValueError(
                f"{path}: {lacking.size} {role} image(s) have no row, the first being "
                f"{files[lacking[0]]}"
            )
    return out["reference"], out["query"]


def load_generic(
    root=None,
    reference="reference",
    query="query",
    tolerance=None,
    positions_csv=None,
    radius=None,
    first=0,
    count=None,
) -> Benchmark:
    """Load two folders of images as a benchmark.

    Parameters
    ----------
    root : str or Path, optional
        Folder that ``reference``, ``query`` and ``positions_csv`` are
        relative to; ``None`` takes them as given.
    reference, query : str or Path
        Image folders, each sorted by name (natural sort).
    tolerance : int, optional
        Frame ground truth ``|i - j| <= tolerance`` (default 0: same index
        only).  Not allowed together with ``positions_csv``.
    positions_csv : str or Path, optional
        CSV with columns ``traverse,filename,x,y`` (see the module
        docstring); switches to metric ground truth.
    radius : float, optional
        Metres; required with ``positions_csv`` and only allowed with it.
    first : int
        Position of the first frame kept in each folder, >= 0.
    count : int, optional
        Frames kept per folder; ``None`` keeps all from ``first``.

    Returns
    -------
    Benchmark
        ``tolerance={"frames": tolerance}`` or ``{"metres": radius}``;
        ``frame_ids`` are the positions in each sorted folder.

    Raises
    ------
    FileNotFoundError
        If a folder or the CSV is missing.
    ValueError
        For an empty folder, an inconsistent choice of ``tolerance`` /
        ``positions_csv`` / ``radius``, a malformed CSV (see
        :func:`read_positions_csv`) or a window beyond the data.
    """
    if positions_csv is None:
        if radius is not None:
            raise ValueError("radius needs positions_csv (metric ground truth); got no CSV")
        tolerance = check_positive_int(0 if tolerance is None else tolerance, "tolerance", 0)
    else:
        if tolerance is not None:
            raise ValueError(
                "give either tolerance (frame ground truth) or positions_csv with radius "
                f"(metric ground truth), not both; got tolerance={tolerance!r}"
            )
        if radius is None:
            raise ValueError("radius (metres) is required with positions_csv")
        radius = check_real(radius, "radius", low=0.0, inclusive=True)
    if root is not None and not isinstance(root, (str, Path)):
        raise TypeError(f"root must be None, a str or Path; got {type(root).__name__}")
    ref_dir = _folder(root, reference, "reference")
    query_dir = _folder(root, query, "query")
    ref_paths = _list_images_or_explain(ref_dir, LAYOUT)
    query_paths = _list_images_or_explain(query_dir, LAYOUT)
    ref_pos = query_pos = None
    sources: tuple[Path, ...] = ()
    if positions_csv is not None:
        csv_path = _folder(root, positions_csv, "positions_csv")
        sources = (csv_path,)
        ref_pos, query_pos = read_positions_csv(csv_path, ref_paths, query_paths)

    ref = Traverse(ref_dir.name, ref_paths, positions=ref_pos, frame_ids=np.arange(len(ref_paths)))
    qry = Traverse(
        query_dir.name, query_paths, positions=query_pos, frame_ids=np.arange(len(query_paths))
    )
    windows = [
        _check_window(first, count, len(t), str(folder))
        for t, folder in ((ref, ref_dir), (qry, query_dir))
    ]
    ref, qry = (t.subset(slice(s, s + n)) for t, (s, n) in zip((ref, qry), windows, strict=True))
    if positions_csv is None:
        gt = ground_truth_from_frames(qry.frame_ids, ref.frame_ids, tolerance)
        tol = {"frames": tolerance}
    else:
        gt = ground_truth_from_positions(qry.positions, ref.positions, radius)
        tol = {"metres": radius}
    return Benchmark(
        dataset="generic",
        reference=ref,
        query=qry,
        ground_truth=gt,
        tolerance=tol,
        root=None if root is None else Path(root),
        first=windows[0][0],
        count=count,
        details={"reference_dir": str(ref_dir), "query_dir": str(query_dir)},
        sources=sources,
    )
