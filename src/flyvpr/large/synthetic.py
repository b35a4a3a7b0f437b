"""Huge maps for benchmarks: a route's codes tiled with perturbations, streamed to disk.

The map is ``n_places`` places in tiles of the base route (e.g. the 2,400 Nordland summer
frames): tile ``t`` is the base codes XOR a random mask of the tile (each bit flipped with
probability ``tile_flip``) XOR independent per-place noise (``place_flip``).  The tile mask
makes every tile a different stretch of line with the same statistics: XOR with a fixed mask
keeps every Hamming distance within the tile, so a query driven along tile ``t`` (the query
route's codes XOR the same mask, :func:`tile_queries`) sees tile ``t`` as the real route, and
the other tiles as places with the same structure but other codes.  The per-place noise makes
no two places identical.  Masks are derived from ``(random_state, tile)`` alone, so the
queries of any tile can be made without the map.
"""

from __future__ import annotations

import numpy as np

from .._validation import check_fraction, check_positive_int
from .codes import as_words
from .mapfile import LargeMapWriter

__all__ = ["tile_mask", "tile_queries", "write_tiled_map"]


def _probability(value, name: str) -> float:
    """``value`` in [0, 1] (0 allowed: no flips)."""
    if value == 0 and not isinstance(value, bool):
        return 0.0
    return check_fraction(value, name)


def _seed(random_state) -> int:
    if isinstance(random_state, bool) or not isinstance(random_state, (int, np.integer)):
        raise TypeError(
            f"random_state must be an int (tile masks are derived from it); got "
            f"{type(random_state).__name__}"
        )
    if random_state < 0:
        raise ValueError(f"random_state must be >= 0; got {random_state}")
    return int(random_state)


def tile_mask(n_bytes: int, tile: int, tile_flip: float, random_state: int = 0) -> np.ndarray:
    """The XOR mask of tile ``tile``: each of ``8 * n_bytes`` bits set with probability
    ``tile_flip``.

    Returns
    -------
    ndarray of uint8, shape (n_bytes,)
    """
    n_bytes = check_positive_int(n_bytes, "n_bytes")
    tile = check_positive_int(tile, "tile", minimum=0)
    p = _probability(tile_flip, "tile_flip")
    rng = np.random.default_rng([_seed(random_state), 0, tile])
    return np.packbits(rng.random(8 * n_bytes) < p)


def tile_queries(query_codes, tile: int, tile_flip: float, random_state: int = 0) -> np.ndarray:
    """Query codes as seen on tile ``tile`` of a map from :func:`write_tiled_map`.

    Returns
    -------
    ndarray of uint8, the shape of ``query_codes``
    """
    q = np.asarray(query_codes)
    as_words(q, "query_codes")
    return q ^ tile_mask(q.shape[-1], tile, tile_flip, random_state)


def write_tiled_map(
    path,
    base_codes,
    n_places: int,
    tile_flip: float = 0.25,
    place_flip: float = 0.02,
    random_state: int = 0,
    metadata=None,
):
    """Write a map of ``n_places`` places tiled from ``base_codes`` (see the module docstring).

    Memory: one tile of codes and its noise at a time; the file is written tile by tile.

    Parameters
    ----------
    path : str or Path
        The map file (written atomically).
    base_codes : ndarray of uint8, shape (n_base, n_bytes)
        One route's compact codes.
    n_places : int
        Places in the map; the last tile may be cut short.
    tile_flip, place_flip : float in [0, 1]
        Bit-flip probabilities of the tile masks and of the per-place noise.
    random_state : int
    metadata : dict, optional
        Written with the map, besides the generator's settings (key ``"tiled"``).

    Returns
    -------
    Path
    """
    base = np.asarray(base_codes)
    as_words(base, "base_codes")
    n_places = check_positive_int(n_places, "n_places")
    p_place = _probability(place_flip, "place_flip")
    _probability(tile_flip, "tile_flip")
    seed = _seed(random_state)
    n_base, n_bytes = base.shape
    meta = dict(metadata or {})
    meta["tiled"] = {
        "n_base": int(n_base),
        "tile_flip": float(tile_flip),
        "place_flip": p_place,
        "random_state": seed,
    }
    with LargeMapWriter(path, n_places, n_bytes, metadata=meta) as writer:
        for tile in range(-(-n_places // n_base)):
            m = min(n_base, n_places - tile * n_base)
            codes = base[:m] ^ tile_mask(n_bytes, tile, tile_flip, seed)
            if p_place > 0:
                rng = np.random.default_rng([seed, 1, tile])
                noise = rng.random((m, 8 * n_bytes), dtype=np.float32) < p_place
                codes ^= np.packbits(noise, axis=1)
            writer.append(codes)
    return writer.path
