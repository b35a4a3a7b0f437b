"""Slow, independent implementations that the tests compare the package's fast ones against."""

from __future__ import annotations

import numpy as np
from scipy import fft as sfft


def gabor_energy(images, bank) -> np.ndarray:
    """Energy ``|image * kernel|`` of every image under every complex kernel ("same" size):
    a linear convolution (zero padding) by FFT, in single precision.

    images : (N, H, W); bank : complex (n_kernels, s, s), ``s`` odd.  Returns float32
    (N, n_kernels, H, W).
    """
    x = np.asarray(images, dtype=np.float32)
    n, h, w = x.shape
    s = bank.shape[1]
    shape = (sfft.next_fast_len(h + s - 1), sfft.next_fast_len(w + s - 1))
    spectra = sfft.fft2(bank, s=shape, axes=(1, 2)).astype(np.complex64)
    r = s // 2
    full = sfft.ifft2(sfft.fft2(x, s=shape, axes=(1, 2))[:, None] * spectra[None], axes=(2, 3))
    return np.abs(full[:, :, r : r + h, r : r + w]).astype(np.float32)


def odometry_scale(cann) -> float:
    """A CANN's mean odometry scale after its last step (scaled odometry: its ``velocity_``
    is the odometry times it), from its velocity rows' posterior mass."""
    return float(cann._row_mass @ cann._params["velocities"])
