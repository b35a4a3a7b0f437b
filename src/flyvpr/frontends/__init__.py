"""Single-frame encoders (front ends): reference images in, a score matrix out.

``FRONTENDS`` maps a method name to its encoder class; the CLI's choices and the
method registry are built from it.  The torch networks import torch only when used.
"""

from .base import Encoder
from .flyhash import FlyHash, winner_take_all
from .flynet import FlyNet
from .kenyon import KenyonEncoder
from .netvlad import NetVLADNet
from .pixels import PixelsEncoder
from .torch_nets import ConvNet, FCDropoutNet, FCNet

__all__ = [
    "Encoder",
    "FlyHash",
    "FlyNet",
    "KenyonEncoder",
    "PixelsEncoder",
    "FCNet",
    "FCDropoutNet",
    "ConvNet",
    "NetVLADNet",
    "winner_take_all",
    "FRONTENDS",
]

#: name -> encoder class
FRONTENDS: dict[str, type[Encoder]] = {
    cls.name: cls
    for cls in (
        PixelsEncoder,
        FlyHash,
        FlyNet,
        KenyonEncoder,
        FCNet,
        FCDropoutNet,
        ConvNet,
        NetVLADNet,
    )
}
