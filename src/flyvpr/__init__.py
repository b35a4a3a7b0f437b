"""flyvpr: visual place recognition with FlyNet+CANN.

FlyNet (a fly-inspired sparse binary hash and a linear classifier) scores every
reference place for each query frame; a 1-d continuous attractor network
(CANN) filters those scores over time (Chancán et al., IEEE RA-L 2020).

``import flyvpr`` loads neither torch nor matplotlib.
"""

from ._validation import NotFittedError
from .frontends import FRONTENDS, FlyHash, FlyNet, PixelsEncoder
from .methods import METHODS, make_method
from .temporal import CANN, FILTERS, SeqSLAM

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "NotFittedError",
    "FlyHash",
    "FlyNet",
    "PixelsEncoder",
    "SeqSLAM",
    "CANN",
    "FRONTENDS",
    "FILTERS",
    "METHODS",
    "make_method",
]
