"""Temporal filters over a score matrix: SeqSLAM, the CANN, and (with torch) an RNN.

``FILTERS`` maps a registry name to its filter class.
"""

from .base import OnlineFilter, TemporalFilter
from .cann import CANN, AttractorCANN
from .rnn import RNNFilter
from .seqslam import SeqSLAM

__all__ = [
    "TemporalFilter",
    "OnlineFilter",
    "SeqSLAM",
    "CANN",
    "AttractorCANN",
    "RNNFilter",
    "FILTERS",
]

#: name -> filter class
FILTERS: dict[str, type[TemporalFilter]] = {
    cls.name: cls for cls in (SeqSLAM, CANN, AttractorCANN, RNNFilter)
}
