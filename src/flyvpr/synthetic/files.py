"""Writing a route to disk as PNG files in the Nordland layout."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from PIL import Image

from .._io import atomic_open
from .route import SyntheticRoute

__all__ = ["save_route"]

#: Pattern of the file names written by :func:`save_route` (Nordland layout).
_FILE_RE = re.compile(r"^images-\d{5,}\.png$")


def _save_png_atomic(array: np.ndarray, path: Path) -> None:
    data = np.clip(np.rint(array * 255.0), 0, 255).astype(np.uint8)
    with atomic_open(path, "wb") as fh:
        Image.fromarray(data).save(fh, format="PNG")


def save_route(
    route: SyntheticRoute, folder, *, rgb: bool | None = None, overwrite: bool = False
) -> dict[str, list[Path]]:
    """Write a route as 8-bit PNGs in the Nordland layout.

    Files are ``<folder>/<condition>/images-00000.png``, ``images-00001.png``,
    ...: one folder per condition, the same file name for the same place.

    Parameters
    ----------
    route : SyntheticRoute
    folder : str or Path
        Created if missing.
    rgb : bool, optional
        Write colour PNGs (needs a route made with ``return_rgb=True``); by
        default colour when the route has it, gray otherwise.
    overwrite : bool
        Replace earlier ``images-NNNNN.png`` files of a condition folder
        (all of them, so no stale frame of a longer route is left behind);
        other files are never touched.

    Returns
    -------
    dict of str to list of Path
        The files written per condition, in route order.

    Raises
    ------
    TypeError
        If ``route`` is not a :class:`SyntheticRoute`.
    ValueError
        If ``rgb=True`` and the route has no colour frames.
    FileExistsError
        If a condition folder already holds route images and ``overwrite`` is False.
    ValueError
        Also for a condition whose name is not a plain folder name (a path, ``..``).
    """
    if not isinstance(route, SyntheticRoute):
        raise TypeError(f"route must be a SyntheticRoute; got {type(route).__name__}")
    if rgb is None:
        rgb = route.rgb is not None
    elif rgb and route.rgb is None:
        raise ValueError("rgb=True needs a route made with make_route(..., return_rgb=True)")
    folder = Path(folder)
    for name in route.conditions:
        if not name or name in (".", "..") or any(c in name for c in "/\\\0"):
            raise ValueError(
                f"condition name {name!r} is not a plain folder name: save_route writes each "
                "condition to a folder of that name inside folder"
            )
    targets = {name: folder / name for name in route.conditions}
    # Check every folder before writing anything, so a refusal leaves no half-written route.
    for sub in targets.values():
        if sub.is_dir():
            existing = [p for p in sub.iterdir() if _FILE_RE.match(p.name)]
            if existing and not overwrite:
                raise FileExistsError(
                    f"{sub} already holds {len(existing)} route images; "
                    "pass overwrite=True to replace them"
                )
    written = {}
    for name, sub in targets.items():
        sub.mkdir(parents=True, exist_ok=True)
        for p in sub.iterdir():
            if _FILE_RE.match(p.name):
                p.unlink()
        # (rgb is true only for a route with colour frames: checked above)
        frames = route.rgb[name] if rgb and route.rgb is not None else route.images[name]
        paths = []
        for i, frame in enumerate(frames):
            path = sub / f"images-{i:05d}.png"
            _save_png_atomic(frame, path)
            paths.append(path)
        written[name] = paths
    return written
