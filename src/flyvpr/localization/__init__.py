"""Localization: what runs on the robot, after the front ends and filters.

The last stages of the pipeline, built on :mod:`flyvpr.methods` (a front end and a filter)
and :mod:`flyvpr.sources` (recordings and streams):

* :mod:`~flyvpr.localization.localizer`: :class:`Localizer`, one frame in, a :class:`Fix`
  (place, confidence, ``localized`` or ``lost``) out; exported here.
* :mod:`~flyvpr.localization.maps`: :class:`~flyvpr.localization.maps.Map`, a reference
  map built from a recording (the method, and per place its time and position), saved to
  and loaded from one file.
* :mod:`~flyvpr.localization.tracking`: a source driven through a map's localizer in
  batches, with its ground truth from frame numbers or positions.
* :mod:`~flyvpr.localization.trace`: what the localizer did, drawn as a video or an HTML
  page.

Only the localizer is imported with the package (``import flyvpr`` stays light); the other
modules are imported from their own paths.
"""

from .localizer import LOCALIZED, LOST, Fix, Fixes, Localizer

__all__ = ["Localizer", "Fix", "Fixes", "LOCALIZED", "LOST"]
