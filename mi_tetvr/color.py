"""sRGB encoding (IEC 61966-2-1): the one place it is written."""
from __future__ import annotations

import numpy as np

__all__ = ["srgb_to_linear", "linear_to_srgb"]


def srgb_to_linear(c):
    """Convert sRGB-encoded values to linear RGB (IEC 61966-2-1).

    Uses the exact piecewise definition::

        c / 12.92                       if c <= 0.04045
        ((c + 0.055) / 1.055) ** 2.4    otherwise

    Parameters
    ----------
    c : array_like, any shape
        sRGB-encoded channel values, nominally in ``[0, 1]``.

    Returns
    -------
    numpy.ndarray, float64, same shape as ``c``
        Linear-RGB channel values.
    """
    c = np.asarray(c, dtype=np.float64)
    # np.maximum keeps the unused branch free of NaN warnings for c < -0.055.
    high = ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(c <= 0.04045, c / 12.92, high)


def linear_to_srgb(c):
    """Convert linear RGB to sRGB-encoded values (the inverse of
    :func:`srgb_to_linear`), inputs clipped at 0.

    A Dr.Jit array or tensor gives one of the same type (differentiable; the
    slope is finite at 0), anything else a float64 numpy array.
    """
    if type(c).__module__.startswith("drjit"):
        import drjit as dr
        c = dr.maximum(c, 0.0)
        # dr.maximum keeps the power's derivative finite on the linear branch.
        high = 1.055 * dr.power(dr.maximum(c, 0.0031308), 1.0 / 2.4) - 0.055
        return dr.select(c <= 0.0031308, c * 12.92, high)
    c = np.maximum(np.asarray(c, dtype=np.float64), 0.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
