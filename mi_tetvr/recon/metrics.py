"""Image metrics as the field reports them, and compositing over a background.

Images are premultiplied linear RGBA (what ``tetvr`` renders over black, with
its ``alpha`` AOV). PSNR and SSIM are computed on RGB composited over a
background and clipped to [0, 1].
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["composite", "psnr", "ssim", "image_metrics"]


def composite(rgba, background=None):
    """RGB of a premultiplied RGBA image over a constant background:
    ``rgb + (1 - alpha) * background``.

    Parameters
    ----------
    rgba : (..., 4) numpy array or Dr.Jit tensor (e.g. ``mi.TensorXf``)
        Premultiplied linear RGB and alpha.
    background : None, float or (3,) float
        Linear RGB of the background; ``None`` is black. A numpy array is
        used with its own dtype; anything else is float64 for a numpy image
        and float32 for a Dr.Jit tensor.

    Returns
    -------
    (..., 3) array of the same kind as ``rgba`` (numpy: the dtype numpy
    promotes the image and the background to).
    """
    if isinstance(background, np.ndarray):
        bg = background
    else:
        bg = np.asarray(0.0 if background is None else background, np.float64)
    bg = np.broadcast_to(bg, (3,))
    if not isinstance(rgba, np.ndarray):  # a Dr.Jit tensor: the background as one too
        bg = type(rgba)(np.ascontiguousarray(bg, np.float32))
    return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * bg


def psnr(mse):
    """PSNR in dB of a mean squared error of values in [0, 1] (inf for 0)."""
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def ssim(a, b):
    """Structural similarity of two (h, w, 3) RGB images with values in [0, 1]."""
    from skimage.metrics import structural_similarity
    return float(structural_similarity(a, b, channel_axis=2, data_range=1.0))


def image_metrics(pred_rgba, target_rgba, background):
    """PSNR, SSIM and MSE of RGB composited over ``background``.

    Parameters
    ----------
    pred_rgba, target_rgba : (h, w, 4) float
        Premultiplied linear RGBA.
    background : None or (3,) float
        Linear RGB (``None``: black). The composited images are clipped to
        [0, 1] and compared in float64.

    Returns
    -------
    dict with ``psnr`` (dB), ``ssim`` and ``mse``.
    """
    bg = None if background is None else np.asarray(background, np.float64)
    a = np.clip(composite(pred_rgba, bg), 0, 1)
    b = np.clip(composite(target_rgba, bg), 0, 1)
    mse = float(np.mean((a - b) ** 2))
    return {"psnr": psnr(mse), "ssim": ssim(a, b), "mse": mse}
