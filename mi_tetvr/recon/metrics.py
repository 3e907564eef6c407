"""Image metrics as the field reports them, and compositing over a background.

Images are premultiplied linear RGBA (what ``tetvr`` renders over black, with
its ``alpha`` AOV). PSNR and SSIM are computed as NeRF, 3D Gaussian splatting
and DiffTetVR report them: on the RGB composited over a background, clipped
to [0, 1] and sRGB-encoded (the 8-bit picture one looks at). The PSNR of the
linear values is kept as ``psnr_linear``; on dark volume renders it is
several dB higher than the sRGB figure, so the two must not be compared.
"""
from __future__ import annotations

import math

import numpy as np

from mi_tetvr.color import linear_to_srgb
from mi_tetvr.extras import needs

__all__ = ["composite", "display_rgb", "psnr", "ssim", "ssim_map", "image_metrics",
           "transmittance_metrics", "tomography_scores"]


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
    """Structural similarity of two (h, w, c) images with values in [0, 1]
    (scikit-image's 7x7 window, smaller for images under 7 pixels; NaN under 3)."""
    return _ssim(a, b, False)


def ssim_map(a, b):
    """(h, w) the structural similarity of two (h, w, c) images in [0, 1] at each pixel
    (scikit-image's map, :func:`ssim`'s window; the mean over channels); ones for images
    under 3 pixels."""
    out = _ssim(a, b, True)
    return np.ones(a.shape[:2]) if out is None else out[1].mean(axis=2)


def _ssim(a, b, full):
    with needs("recon", "SSIM"):
        from skimage.metrics import structural_similarity
    win = min(7, a.shape[0], a.shape[1])
    win -= 1 - win % 2
    if win < 3:
        return None if full else float("nan")
    out = structural_similarity(a, b, channel_axis=2, data_range=1.0, win_size=win, full=full)
    return out if full else float(out)


def _over_background(rgba, background):
    """RGB over ``background`` clipped to [0, 1]: float64 numpy for a numpy
    image, the same Dr.Jit tensor type for a Dr.Jit one."""
    if isinstance(rgba, np.ndarray) or not type(rgba).__module__.startswith("drjit"):
        bg = None if background is None else np.asarray(background, np.float64)
        return np.clip(composite(np.asarray(rgba, np.float64), bg), 0.0, 1.0)
    import drjit as dr
    return dr.clip(composite(rgba, background), 0.0, 1.0)


def display_rgb(rgba, background=None):
    """The picture of a premultiplied linear RGBA image that the metrics
    compare: RGB over ``background`` (linear, ``None``: black), clipped to
    [0, 1], sRGB-encoded; (h, w, 3) float64 for a numpy image, the same
    tensor type for a Dr.Jit one."""
    return linear_to_srgb(_over_background(rgba, background))


def image_metrics(pred_rgba, target_rgba, background):
    """PSNR and SSIM of the sRGB pictures (:func:`display_rgb`) of two images.

    Parameters
    ----------
    pred_rgba, target_rgba : (h, w, 4) float
        Premultiplied linear RGBA.
    background : None or (3,) float
        Linear RGB (``None``: black).

    Returns
    -------
    dict with ``psnr`` (dB) and ``ssim`` of the sRGB pictures, ``mse`` of
    theirs, and ``psnr_linear`` of the clipped linear RGB.
    """
    lin = [_over_background(x, background) for x in (pred_rgba, target_rgba)]
    a, b = linear_to_srgb(lin[0]), linear_to_srgb(lin[1])
    mse = float(np.mean((a - b) ** 2))
    return {"psnr": psnr(mse), "ssim": ssim(a, b), "mse": mse,
            "psnr_linear": psnr(float(np.mean((lin[0] - lin[1]) ** 2)))}


def transmittance_metrics(pred_rgba, target_rgba):
    """PSNR and SSIM of the transmittance ``1 - alpha`` of two X-ray images
    (values in [0, 1], linear: a measurement, not a picture).

    Returns
    -------
    dict with ``psnr``, ``ssim``, ``mse`` and (the same) ``psnr_linear``.
    """
    a, b = (np.clip(1.0 - np.asarray(x, np.float64)[..., 3:4], 0.0, 1.0)
            for x in (pred_rgba, target_rgba))
    mse = float(np.mean((a - b) ** 2))
    return {"psnr": psnr(mse), "ssim": ssim(a, b), "mse": mse, "psnr_linear": psnr(mse)}


def tomography_scores(volume=None, truth=None, projections=None, targets=None) -> dict:
    """The one yardstick of a tomographic reconstruction, whatever made it
    (FBP, SART, FDK or a tet fit): every method's numbers come from here, on
    the same arrays.

    Parameters
    ----------
    volume, truth : (nz, ny, nx) float, optional
        The reconstruction at the true volume's samples (a tet field sampled
        there) and the true volume, normalised so that its values lie in [0, 1].
        The reconstruction is clipped to [0, 1] (FBP goes negative).
    projections, targets : list of (h, w) float, optional
        Held-out transmittance images (``I / I0`` in [0, 1]): each reconstruction
        projected, and the measured ones.

    Returns
    -------
    dict
        ``volume_psnr`` (dB, peak 1), ``slice_ssim`` (mean over the z slices of
        scikit-image's SSIM, data range 1), ``projection_psnr_views`` (the mean
        of each view's PSNR: what a fit's ``metrics.json`` reports as ``psnr``)
        and ``projection_psnr_pixels`` (the PSNR of the mean squared error over
        all pixels of all views), for what was given.
    """
    out = {}
    if volume is not None:
        v = np.clip(np.asarray(volume, np.float64), 0.0, 1.0)
        t = np.asarray(truth, np.float64)
        if v.shape != t.shape:
            raise ValueError(f"reconstruction of shape {v.shape}, truth of shape {t.shape}")
        out["volume_psnr"] = psnr(float(np.mean((v - t) ** 2)))
        out["slice_ssim"] = float(np.mean([ssim(v[k][..., None], t[k][..., None])
                                           for k in range(len(t))]))
    if projections is not None:
        if len(projections) != len(targets) or not len(targets):
            raise ValueError(f"{len(projections)} projections for {len(targets)} targets")
        sq = [(np.clip(np.asarray(p, np.float64), 0.0, 1.0)
               - np.asarray(q, np.float64)) ** 2 for p, q in zip(projections, targets)]
        out["projection_psnr_views"] = float(np.mean([psnr(float(np.mean(e))) for e in sq]))
        out["projection_psnr_pixels"] = psnr(float(np.mean(np.concatenate(
            [e.ravel() for e in sq]))))
    return out
