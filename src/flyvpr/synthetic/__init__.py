"""A procedurally generated route: the default data set that needs no download.

The same sequence of places is rendered under several appearance conditions
(``'summer'``, ``'fall'``, ``'winter'``, ``'night'``), frame-aligned like the
Nordland traverses the paper uses (Sec. Experiments): frame ``i`` of every
condition shows place ``i``.

The package follows the steps of making a route:

* :mod:`~flyvpr.synthetic.world`: the places, as parallax layers of material
  labels and textures (mountains, forest, fields, trees, farms, poles, track);
* :mod:`~flyvpr.synthetic.conditions`: what each material looks like in a
  season or at night (:class:`Condition`, :data:`CONDITIONS`);
* :mod:`~flyvpr.synthetic.render`: the camera (viewpoint jitter, exposure,
  headlight, sensor noise) and the gray and colour frames;
* :mod:`~flyvpr.synthetic.route`: :func:`make_route`, which ties them
  together under one ``random_state``, and :class:`SyntheticRoute` with its
  ground truth;
* :mod:`~flyvpr.synthetic.files`: :func:`save_route` writes the frames in
  the Nordland layout, so every command that reads a folder can use them.

Examples
--------
>>> from flyvpr.synthetic import make_route
>>> route = make_route(50, conditions=("summer", "winter"), random_state=1)
>>> route.reference_images.shape
(50, 32, 64)
"""

from .conditions import CONDITIONS, MATERIALS, Condition
from .files import save_route
from .route import SyntheticRoute, make_route

__all__ = [
    "MATERIALS",
    "Condition",
    "CONDITIONS",
    "SyntheticRoute",
    "make_route",
    "save_route",
]
