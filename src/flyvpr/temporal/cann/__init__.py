"""A 1-d continuous attractor neural network (CANN) over the reference places.

Paper, Sec. "FlyNet+CANN" (Fig. "FlyNet baselines" (d)): FlyNet's output for each query frame
is injected into a 1-d CANN with pre-assigned (never trained) weights: every place unit excites
itself and its neighbours, all place units are inhibited through one global inhibitor unit, and
movement along the route is a direct *shift and copy* of the activity packet (no velocity
units).  What the network computes, its readout, its parameters and the data that tuned their
defaults are on the user guide's CANN page (``docs/guide/cann.md``).

The package follows the design: ``_params`` (defaults and validation), ``_kernels`` (the
excitation kernel and the per-frame updates, compiled with numba where it can be),
``_speed`` (the online speed estimate), ``_readout`` (answer and confidence) and ``_filter``
(the :class:`CANN` class that holds the state).
"""

from ._attractor import AttractorCANN
from ._filter import CANN, LAYER_VELOCITIES
from ._kernels import excitation_kernel
from ._params import FAST_RECOVERY

__all__ = ["CANN", "AttractorCANN", "FAST_RECOVERY", "LAYER_VELOCITIES", "excitation_kernel"]
