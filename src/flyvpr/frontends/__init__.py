"""Single-frame encoders (front ends): reference images in, a score matrix out.

``FRONTENDS`` maps a method name to its encoder class; the CLI's choices and the
method registry are built from it.
"""

from .base import Encoder
from .flyhash import FlyHash, winner_take_all
from .flynet import FlyNet
from .pixels import PixelsEncoder

__all__ = ["Encoder", "FlyHash", "FlyNet", "PixelsEncoder", "winner_take_all", "FRONTENDS"]

#: name -> encoder class
FRONTENDS: dict[str, type[Encoder]] = {cls.name: cls for cls in (PixelsEncoder, FlyHash, FlyNet)}
