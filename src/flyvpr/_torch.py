"""The one import of torch, and its thread setting: for the trained front ends and the RNN."""

from __future__ import annotations

import contextlib
import os

from ._validation import check_positive_int

__all__ = ["import_torch", "check_threads", "torch_threads"]


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


def check_threads(n_threads) -> int:
    """Torch threads for an ``n_threads`` parameter: ``None`` -> 1, else capped at the cores.

    Raises
    ------
    TypeError, ValueError
        If ``n_threads`` is not None or an int >= 1.
    """
    if n_threads is None:
        return 1
    return min(check_positive_int(n_threads, "n_threads"), os.cpu_count() or 1)


@contextlib.contextmanager
def torch_threads(torch, n_threads: int):
    """Run torch on ``n_threads`` threads inside the block, then restore the setting."""
    previous = torch.get_num_threads()
    torch.set_num_threads(n_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
