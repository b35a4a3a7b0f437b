"""flyvpr: visual place recognition for robots, with fly-inspired front ends and a CANN.

A robot drives a route once (the map); later, in another season or at night, it says for every
camera frame which place of the map it shows.  A front end scores every place for each frame:
the default ``kenyon`` (a fixed optic lobe feeding 4096 Kenyon cells, nothing trained), the
paper's FlyNet (FlyHash plus a trained linear classifier), raw pixels, or learned baselines.
The :class:`CANN` filters those scores over time: a place-velocity layer that follows a robot
at any speed, with or without odometry, and says whether it is localized; the paper's
attractor network is :class:`~flyvpr.temporal.cann.AttractorCANN` (the architecture of
Chancán et al., IEEE RA-L 2020, with parameters of flyvpr's own where the paper gives
none).  :class:`Localizer` streams one frame at a time.

``import flyvpr`` loads neither torch nor matplotlib.
"""

from ._validation import NotFittedError
from ._version import __version__
from .frontends import FRONTENDS, FlyHash, FlyNet, KenyonEncoder, PixelsEncoder
from .localization import Fix, Localizer
from .methods import METHODS, make_method
from .temporal import CANN, FILTERS, SeqSLAM

__all__ = [
    "__version__",
    "NotFittedError",
    "KenyonEncoder",
    "FlyHash",
    "FlyNet",
    "PixelsEncoder",
    "SeqSLAM",
    "CANN",
    "Localizer",
    "Fix",
    "FRONTENDS",
    "FILTERS",
    "METHODS",
    "make_method",
]
