"""Nordland: one train journey filmed in four seasons, frame-aligned.

The paper (Sec. Experiments) trains on summer and queries fall and winter,
1000 frames per traverse, and counts a match as correct within 20 frames.
Frame k of every season shows the same place, so ground truth compares frame
positions (:func:`~flyvpr.datasets.base.ground_truth_from_frames`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .._validation import check_positive_int
from .base import (
    Benchmark,
    Traverse,
    _check_root,
    _check_window,
    _list_images_or_explain,
    _subfolders,
    ground_truth_from_frames,
)

__all__ = ["load_nordland", "LAYOUT"]

#: Folder layout shown in errors and by ``flyvpr datasets``.
LAYOUT = (
    "<root>/<season>/images-NNNNN.png  (e.g. summer/images-00010.png, winter/images-00010.png)\n"
    "or <root>/<season>/<i>.png        (e.g. summer/0.png ... summer/99.png)\n"
    "one folder per season; the same frame number in two seasons is the same place"
)

_FRAME_NUMBER = re.compile(r"(\d+)$")


def _frame_numbers(paths: list[Path]) -> dict[int, Path]:
    """Map the frame number at the end of each file name to its file."""
    frames: dict[int, Path] = {}
    for path in paths:
        match = _FRAME_NUMBER.search(path.stem)
        if match is None:
            raise ValueError(
                f"cannot read a frame number from the file name {path}: the name must end "
                f"in digits; expected layout:\n{LAYOUT}"
            )
        number = int(match.group(1))
        if number in frames:
            raise ValueError(
                f"frame number {number} appears twice in {path.parent}: "
                f"{frames[number].name} and {path.name}"
            )
        frames[number] = path
    return frames


def _season(root: Path, season, role: str) -> dict[int, Path]:
    if not isinstance(season, str) or not season:
        raise TypeError(f"{role} must be a season folder name (str); got {season!r}")
    folder = root / season
    if not folder.is_dir():
        found = _subfolders(root)
        raise FileNotFoundError(
            f"{role} season folder not found: {folder}; seasons found in {root}: "
            f"{', '.join(found) if found else 'none'}; expected layout:\n{LAYOUT}"
        )
    return _frame_numbers(_list_images_or_explain(folder, LAYOUT))


def load_nordland(
    root, reference="summer", query="winter", first=0, count=None, tolerance=20
) -> Benchmark:
    """Load a frame-aligned Nordland pair of seasons.

    Files are paired by the frame number at the end of their name
    (``images-00010.png`` -> 10, ``7.png`` -> 7); both seasons must hold the
    same set of numbers.  ``first`` and ``count`` select a window of the sorted
    common frames by *position* (0-based), not by file number.  Ground truth
    is ``|i - j| <= tolerance`` over positions in the season's sorted sequence,
    so the tolerance is in frames of *this folder*: in a copy that keeps every
    10th video frame (``nordland_64x32``), 20 positions span 200 video frames.

    Parameters
    ----------
    root : str or Path
        Folder holding one sub-folder per season (see ``LAYOUT``).
    reference, query : str
        Season folder names; the paper uses summer as reference, fall and
        winter as queries.
    first : int
        Position of the first frame kept, >= 0.
    count : int, optional
        Number of frames kept (the paper: 1000); ``None`` keeps all from ``first``.
    tolerance : int
        Largest accepted frame difference (the paper: 20).

    Returns
    -------
    Benchmark
        ``tolerance={"frames": tolerance}``; each traverse has ``frame_ids``
        (positions in the sorted sequence) and no positions; ``details`` holds
        ``frame_number_range``, the first and last file frame numbers kept.

    Raises
    ------
    FileNotFoundError
        If ``root`` or a season folder is missing (lists the seasons found).
    ValueError
        If a folder holds no images, a file name has no frame number, the
        seasons hold different frame numbers, or the window lies beyond the data.
    """
    root = _check_root(root, LAYOUT)
    tolerance = check_positive_int(tolerance, "tolerance", minimum=0)
    ref_frames = _season(root, reference, "reference")
    query_frames = _season(root, query, "query")
    ref_numbers = np.array(sorted(ref_frames), dtype=np.int64)
    query_numbers = np.array(sorted(query_frames), dtype=np.int64)
    if not np.array_equal(ref_numbers, query_numbers):
        only_ref = np.setdiff1d(ref_numbers, query_numbers)
        only_query = np.setdiff1d(query_numbers, ref_numbers)
        problems = []
        if only_ref.size:
            problems.append(
                f"{only_ref.size} frame(s) of {root / reference} are missing from "
                f"{root / query}, the first being {ref_frames[int(only_ref[0])].name}"
            )
        if only_query.size:
            problems.append(
                f"{only_query.size} frame(s) of {root / query} are missing from "
                f"{root / reference}, the first being {query_frames[int(only_query[0])].name}"
            )
        raise ValueError(
            f"Nordland seasons must be frame-aligned (the same frame numbers in both folders): "
            f"{'; '.join(problems)} ({ref_numbers.size} vs {query_numbers.size} frames)"
        )
    first, count = _check_window(
        first, count, ref_numbers.size, f"{root / reference} and {root / query}"
    )
    kept = ref_numbers[first : first + count]
    frame_ids = np.arange(first, first + count, dtype=np.int64)
    ref = Traverse(reference, [ref_frames[int(k)] for k in kept], frame_ids=frame_ids)
    qry = Traverse(query, [query_frames[int(k)] for k in kept], frame_ids=frame_ids)
    return Benchmark(
        dataset="nordland",
        reference=ref,
        query=qry,
        ground_truth=ground_truth_from_frames(frame_ids, frame_ids, tolerance),
        tolerance={"frames": tolerance},
        root=root,
        first=first,
        count=count,
        details={"frame_number_range": [int(kept[0]), int(kept[-1])]},
    )
