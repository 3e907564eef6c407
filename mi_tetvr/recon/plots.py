"""Pictures of a reconstruction: renders next to their targets, and the
training loss and PSNR over time."""
from __future__ import annotations

import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.recon.metrics import composite

__all__ = ["save_comparison", "plot_history", "plot_transfer_functions"]


def save_comparison(path, pred_rgba, target_rgba, background, more=()):
    """Write a render and its target side by side as an sRGB PNG.

    Parameters
    ----------
    path : str or Path
    pred_rgba, target_rgba : (h, w, 4) float
        Premultiplied linear RGBA, shown composited over ``background``.
    background : None or (3,) float
        Linear RGB (``None``: black).
    more : sequence of (h, w, 3) float
        Further linear RGB panels to their right (e.g. uncertainty projections).
    """
    with needs("recon", "the fit's plots"):
        from PIL import Image

    from mi_tetvr.color import linear_to_srgb
    row = np.concatenate([composite(pred_rgba, background), composite(target_rgba, background),
                          *(np.asarray(m, np.float64)[..., :3] for m in more)], 1)
    img = (np.clip(linear_to_srgb(np.clip(row, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(img).save(path)


def plot_history(history, path, test_psnr=None):
    """Plot the training loss and PSNR over time (minutes) to ``path``.

    Parameters
    ----------
    history : dict
        Lists ``time`` (s), ``loss`` and ``psnr`` (NaN when not an L2 loss), one entry per step;
        optionally ``refinements``: ``[step, time, PSNR before, PSNR after]`` per change of
        the mesh (drawn as pairs of dots).
    path : str or Path
    test_psnr : float, optional
        Drawn as a horizontal line.
    """
    with needs("recon", "the fit's plots"):
        from matplotlib.figure import Figure
    fig = Figure(figsize=(7, 4))
    ax = fig.subplots()
    t = np.asarray(history["time"]) / 60.0
    loss = np.asarray(history["loss"])
    if len(loss):
        ax.semilogy(t, loss, color="tab:blue", alpha=0.3, lw=0.8)
        k = max(1, len(loss) // 50)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.semilogy(t[k - 1:], smooth, color="tab:blue", label="training loss")
    ax.set_xlabel("time [min]")
    ax.set_ylabel("loss", color="tab:blue")
    ps = np.asarray(history["psnr"], np.float64)
    if len(ps) and np.isfinite(ps).any():
        ax2 = ax.twinx()
        k = max(1, len(ps) // 50)
        ax2.plot(t[k - 1:], np.convolve(ps, np.ones(k) / k, mode="valid"), color="tab:red",
                 label="training PSNR")
        for i, (_, t_r, before, after) in enumerate(history.get("refinements", [])):
            # the training PSNR on whole photos just before and after each change of the mesh
            ax2.plot([t_r / 60.0] * 2, [before, after], "o-", color="black", ms=3, lw=1,
                     label="whole photos, before | after a refinement" if i == 0 else None)
        if test_psnr is not None:
            ax2.axhline(test_psnr, color="tab:red", ls="--", lw=0.8,
                        label=f"test PSNR {test_psnr:.2f} dB")
        ax2.set_ylabel("PSNR [dB] (sRGB, over the background)", color="tab:red")
        ax2.legend(loc="lower right")
    ax.set_title("mi-tetvr fit")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def plot_transfer_functions(path, tfs, value_range=(0.0, 1.0), samples=512):
    """Plot transfer functions over the scalar range to ``path``: their
    opacity curves (top) and, per function, its color as a strip under them.

    Parameters
    ----------
    path : str or Path
    tfs : dict of label to :class:`~mi_tetvr.transfer.TransferFunction`
    value_range : (float, float)
        The scalar values the normalised axis [0, 1] spans (axis labels).
    """
    with needs("recon", "the fit's plots"):
        from matplotlib.figure import Figure

    from mi_tetvr.color import linear_to_srgb
    t = (np.arange(samples) + 0.5) / samples
    x = value_range[0] + t * (value_range[1] - value_range[0])
    n = len(tfs)
    fig = Figure(figsize=(7, 3 + 0.5 * n))
    axes = fig.subplots(1 + n, 1, sharex=True, gridspec_kw={"height_ratios": [6] + [1] * n})
    for (label, tf), ax in zip(tfs.items(), axes[1:]):
        color, opacity = tf(t)
        axes[0].plot(x, opacity, label=label)
        strip = np.clip(linear_to_srgb(np.clip(color, 0, 1)), 0, 1)[None]
        ax.imshow(strip, aspect="auto", extent=(x[0], x[-1], 0, 1))
        ax.set_yticks([])
        ax.set_ylabel(label, rotation=0, ha="right", va="center", fontsize=8)
    axes[0].set_ylabel("opacity (extinction)")
    axes[0].legend()
    axes[-1].set_xlabel("scalar")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
