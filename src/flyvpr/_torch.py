"""The one import of torch: the optional dependency of the trained front ends and the RNN."""

from __future__ import annotations

__all__ = ["import_torch"]


def import_torch(who: str, extra: str = "torch"):
    """Import torch, or raise ImportError naming the pip extra that installs it.

    Parameters
    ----------
    who : str
        What needs torch, for the message (e.g. ``"FCNet (method 'fc')"``).
    extra : str, default "torch"
        The extra to name (``"netvlad"`` installs torch with the NetVLAD backbone's packages).
    """
    try:
        import torch
    except ImportError as exc:
        raise ImportError(f"{who} needs PyTorch: pip install 'flyvpr[{extra}]'") from exc
    return torch
