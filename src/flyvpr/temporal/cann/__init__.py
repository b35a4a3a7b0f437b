"""The CANN: a network over the reference places that filters a front end's scores over time.

:class:`CANN` (filter ``cann``, the default) is a place-velocity layer: one unit per place and
candidate speed whose activity is the probability that the robot is there moving at that speed;
rows move by their speed (the paper's *shift and copy*) or by odometry, the front end's
evidence multiplies them and global divisive inhibition normalises them.  A sequence test says
whether the query follows the route at all; the answer comes with a calibrated confidence and a
``localized``/``lost`` state (user guide, ``docs/guide/cann.md``).

:class:`AttractorCANN` (filter ``cann-paper``) is the paper's 1-d continuous attractor network
(Sec. "FlyNet+CANN"), kept for reproducing the paper (``docs/guide/cann-paper.md``).

Modules: ``_filter`` (:class:`CANN`), ``_layer`` (its per-frame kernels), ``_window``
(:class:`WindowedCANN`: the layer on a window of a large map), ``_attractor``
(:class:`AttractorCANN`) with ``_params``, ``_speed`` and ``_readout``; ``_calibration``
(:func:`fit_calibration`: the confidence table fitted on a labelled route of one's own);
``_route`` (:func:`route_breaks`: where a map's route is broken, the ``breaks`` parameter);
``_kernels`` holds the attractor's kernels, the input normalisation both use, and the numba
compilation of both tables.
"""

from ._attractor import AttractorCANN
from ._calibration import fit_calibration
from ._filter import CANN, LAYER_VELOCITIES, ODOMETRY_JUMP
from ._kernels import excitation_kernel
from ._params import FAST_RECOVERY
from ._route import BREAK_FACTOR, route_breaks
from ._window import WindowedCANN

__all__ = [
    "CANN",
    "AttractorCANN",
    "BREAK_FACTOR",
    "FAST_RECOVERY",
    "LAYER_VELOCITIES",
    "ODOMETRY_JUMP",
    "WindowedCANN",
    "excitation_kernel",
    "fit_calibration",
    "route_breaks",
]
