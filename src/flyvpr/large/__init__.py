"""What a map of millions of places needs: compact codes, indexes, memory-mapped map files.

* :mod:`~flyvpr.large.codes`: :class:`CompactEncoder` (256-bit codes from the ``kenyon``
  front end's optic lobe) and Hamming similarity over all places, a range or a list;
* :mod:`~flyvpr.large.index`: indexes returning the top ``k`` candidate places
  (exhaustive, multi-index hashing, faiss binary IVF / HNSW) and :func:`pool_candidates`;
* :mod:`~flyvpr.large.mapfile`: map files written in chunks and opened memory-mapped;
* :mod:`~flyvpr.large.localizer`: :class:`LargeLocalizer`, the windowed CANN with an index
  for relocation;
* :mod:`~flyvpr.large.recording`: compact maps of a robot's own recording (``flyvpr map
  --compact``) and a localizer on them (``flyvpr localize --map``);
* :mod:`~flyvpr.large.synthetic`: huge tiled maps for benchmarks.

See ``docs/guide/large-maps.md``.  Importing this package imports neither numba nor faiss.
"""

from .codes import (
    PROJECTIONS,
    CompactEncoder,
    hamming_distance,
    hamming_similarity,
    hamming_similarity_at,
)
from .index import (
    INDEXES,
    CandidateIndex,
    ExhaustiveIndex,
    FaissHNSWIndex,
    FaissIVFIndex,
    MultiIndexHash,
    pool_candidates,
)
from .localizer import LargeFixes, LargeLocalizer
from .mapfile import (
    ForeignIndexError,
    LargeMap,
    LargeMapWriter,
    MapFileError,
    load_index,
    open_large_map,
    save_index,
    write_large_map,
)
from .synthetic import tile_mask, tile_queries, write_tiled_map

__all__ = [
    "LargeLocalizer",
    "LargeFixes",
    "INDEXES",
    "PROJECTIONS",
    "CandidateIndex",
    "CompactEncoder",
    "ExhaustiveIndex",
    "FaissHNSWIndex",
    "FaissIVFIndex",
    "ForeignIndexError",
    "LargeMap",
    "LargeMapWriter",
    "MapFileError",
    "MultiIndexHash",
    "hamming_distance",
    "hamming_similarity",
    "hamming_similarity_at",
    "load_index",
    "open_large_map",
    "pool_candidates",
    "save_index",
    "tile_mask",
    "tile_queries",
    "write_large_map",
    "write_tiled_map",
]
