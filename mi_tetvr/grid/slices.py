"""Classical parallel-beam tomography, slice by slice, on a grid's samples: the
baselines a tet reconstruction is compared with.

Every z slice of the grid is reconstructed from its sinogram, one detector row
of each parallel-beam view, recentred so that the rotation axis lies on the
middle column (views with a detector shift, as measured scans have, are
shifted back: by whole pixels exactly, by a fraction with linear
interpolation). Methods:

* ``fbp``: filtered back-projection (scikit-image's ``iradon``, ramp filter);
* ``sart``: SART (scikit-image's ``iradon_sart``, Andersen and Kak 1984),
  values kept >= 0;
* ``sirt``: SIRT (ASTRA's ``SIRT`` on its linear (Joseph) projector, values
  kept >= 0);
* ``fista_tv``: FISTA with a total-variation proximal step (Beck and Teboulle
  2009, "Fast gradient-based algorithms for constrained total variation image
  denoising and deblurring"): gradient steps on the (weighted) least squares
  through ASTRA's projector, slice by slice, then the TV step on the whole
  stack (3D isotropic TV, scikit-image's ``denoise_tv_chambolle``: the
  slices' data are independent, their volume is not), values kept >= 0.

:func:`tuned_slices` runs an iterative method to its best iteration count (and
FISTA-TV at its best TV weight) as judged on held-out projections split from
the training views, never on a true volume, then again on all training views
with those settings: the way a user without ground truth tunes them.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.grid.xray import rotation_axis

__all__ = ["slice_sinograms", "reconstruct_slices", "tuned_slices", "validation_split",
           "METHODS", "TV_WEIGHTS"]

METHODS = ("fbp", "sart", "sirt", "fista_tv")
#: FISTA-TV's candidate TV weights, times the largest value of the FBP slice
#: stack (scikit-image's Chambolle weight per gradient step of length 1 / L).
TV_WEIGHTS = (3e-5, 1e-4, 3e-4, 1e-3, 3e-3)


def validation_split(n: int, every: int = 8):
    """Training views split for tuning: every ``every``-th one (at least 2,
    from ``every // 2``) validates, the others fit. Returns ``(fit, validate)``
    index arrays."""
    from mi_tetvr.grid.scan import held_out_split
    return held_out_split(n, max(2, min(every, n // 2)))


def slice_sinograms(grid, views, scale: float, axis=None, flux=None):
    """The recentred sinograms of ``grid``'s z slices.

    Parameters
    ----------
    grid : Volume
        The samples to reconstruct on (shape, spacing, bounds; not its values):
        pixels of the views' size, one detector row per z sample.
    views : list of View
        Parallel-beam X-ray views (alpha = 1 - transmittance).
    scale : float
        Attenuation per world unit of a value 1 (the result is in values).
    axis : (3,) float, optional
        A point of the rotation axis (default :func:`rotation_axis` of ``grid``).
    flux : float, optional
        Photons per unattenuated pixel: also return each ray's count, the
        weights of a weighted least squares.

    Returns
    -------
    dict
        ``depth`` (nz, W, views) line integrals in values x pixels, ``theta``
        (views,) scikit-image's angles in degrees, ``width`` W (odd, the axis on
        column W // 2), ``weights`` (nz, W, views) or None.
    """
    cams = [v.camera for v in views]
    cam = cams[0]
    w, s = cam.width, cam.pixel_size
    nx, ny, nz = grid.shape
    if any(not c.is_orthographic for c in cams) or cam.height != nz or \
            abs(s - grid.spacing[0]) > 1e-9 * s:
        raise ValueError("slice reconstruction needs parallel-beam views with one detector row "
                         "per z sample and pixels of the grid's spacing")
    axis = rotation_axis(grid) if axis is None else np.asarray(axis, np.float64)
    fwd = np.array([c.to_world[:3, 2] for c in cams])
    theta = np.degrees(np.arctan2(-fwd[:, 1], -fwd[:, 0])) + 90.0   # scikit-image's angle
    # the axis's detector column in each view (0: the first pixel's centre)
    cols = np.array([c.project(axis[None])[0][0, 0] - 0.5 for c in cams])
    half = int(np.ceil(max(float(np.max(cols)), float(np.max(w - 1 - cols)),
                           (max(nx, ny) - 1) / 2) - 1e-9))
    width = 2 * half + 1
    depth = np.zeros((nz, width, len(views)))
    weights = None if flux is None else np.zeros_like(depth)
    for k, (v, a) in enumerate(zip(views, cols)):
        t = np.clip(1.0 - v.image[..., 3].astype(np.float64), 0.5 / flux if flux else 1e-12,
                    None)
        d = _recentre(-np.log(t) / (scale * s), a, half, 0.0)
        depth[:, :, k] = d
        if weights is not None:
            weights[:, :, k] = np.maximum(flux * _recentre(t, a, half, 1.0), 1.0)
    return {"depth": depth, "theta": theta, "width": width, "weights": weights}


def _recentre(rows, a, half, fill):
    """Detector rows (nz, w) resampled at columns ``a - half .. a + half``
    (``fill`` beyond the detector): a whole-pixel ``a`` by indexing, a
    fractional one by a Fourier (sinc) shift, which keeps the rows' noise
    and detail (linear interpolation would smooth them, and favour
    half-pixel centres)."""
    nz, w = rows.shape
    ia = int(np.floor(a + 1e-9))
    f = a - ia
    if f > 1e-9:
        n = 2 * w
        spec = np.fft.rfft(rows - fill, n, axis=1)
        k = np.fft.rfftfreq(n)
        rows = np.fft.irfft(spec * np.exp(2j * np.pi * k * f), n, axis=1)[:, :w] + fill
    out = np.full((nz, 2 * half + 1), float(fill))
    lo, hi = ia - half, ia + half + 1               # detector columns wanted
    src = slice(max(lo, 0), min(hi, w))
    out[:, src.start - lo:src.stop - lo] = rows[:, src]
    return out


def _crop(img, grid, width):
    """Slice pixel (r, c) <-> sample (y, x): c = W//2 + x - nx//2, r = W//2 - (y - ny//2)."""
    nx, ny, _ = grid.shape
    cols = width // 2 + np.arange(nx) - nx // 2
    rows = width // 2 - (np.arange(ny) - ny // 2)
    return img[np.ix_(rows, cols)]


def _stack(images, grid, width):
    nz = len(images)
    return np.stack([_crop(images[nz - 1 - k], grid, width) for k in range(nz)])


class _Astra:
    """ASTRA's 2D parallel-beam linear projector for one set of angles on a
    W x W slice (unit pixels): the forward projection and its transpose."""

    def __init__(self, theta, width):
        with needs("tomo", "the ASTRA baselines"):
            import astra
        self.vol = astra.create_vol_geom(width, width)
        self.proj = astra.create_proj_geom("parallel", 1.0, width, np.radians(theta))
        self.id = astra.create_projector("linear", self.proj, self.vol)
        self.op = astra.OpTomo(self.id)
        self.width, self.views = width, len(theta)

    def forward(self, img):
        """(W, W) -> (W, views) sinogram (detector, angle) as scikit-image's."""
        return (self.op * img.ravel()).reshape(self.views, self.width).T

    def adjoint(self, sino):
        return (self.op.T * sino.T.ravel()).reshape(self.width, self.width)

    def norm2(self, weights=None, iterations=30):
        """``||W^(1/2) A||^2`` by power iteration."""
        x = np.random.default_rng(0).random((self.width, self.width))
        lam = 1.0
        for _ in range(iterations):
            y = self.forward(x)
            x = self.adjoint(y if weights is None else weights * y)
            lam = float(np.linalg.norm(x))
            x /= max(lam, 1e-30)
        return lam

    def free(self):
        with needs("tomo", "the ASTRA baselines"):
            import astra
        astra.projector.delete(self.id)


def _run(method, sino, passes, tv=0.0, every=None):
    """Run ``method`` on the sinograms of :func:`slice_sinograms` (``sino``),
    yielding ``(pass, images)`` after every pass when ``every`` (else after the
    last only): images (nz, W, W) in values, slice order of ``sino``."""
    with needs("tomo", "the FBP and SART baselines"):
        from skimage.transform import iradon, iradon_sart
    depth, theta, width = sino["depth"], sino["theta"], sino["width"]
    nz = len(depth)
    if method == "fbp":
        yield 0, np.stack([iradon(depth[j], theta, output_size=width, filter_name="ramp")
                           for j in range(nz)])
        return
    if method == "sart":
        imgs = [None] * nz
        for p in range(passes):
            imgs = [iradon_sart(depth[j], theta, image=imgs[j], clip=(0.0, np.inf))
                    for j in range(nz)]
            if every or p == passes - 1:
                yield p + 1, np.stack(imgs)
        return
    proj = _Astra(theta, width)
    try:
        if method == "sirt":
            # x += C A^T R (b - A x), R and C the inverse row and column sums, x >= 0
            rows = proj.forward(np.ones((width, width)))
            r = np.where(rows > 1e-9, 1.0 / np.maximum(rows, 1e-30), 0.0)
            c = proj.adjoint(np.ones((width, len(theta))))
            c = np.where(c > 1e-9, 1.0 / np.maximum(c, 1e-30), 0.0)
            x = np.zeros((nz, width, width))
            for p in range(passes):
                for j in range(nz):
                    x[j] = np.maximum(x[j] + c * proj.adjoint(r * (depth[j] - proj.forward(
                        x[j]))), 0.0)
                if every or p == passes - 1:
                    yield p + 1, x.copy()
            return
        if method == "fista_tv":
            with needs("tomo", "the FISTA-TV baseline"):
                from skimage.restoration import denoise_tv_chambolle
            wts = sino["weights"]
            if wts is not None:
                wts = wts / float(np.mean(wts))
            # one step length for the whole stack: the TV step couples the slices
            lip = max(proj.norm2(None if wts is None else wts[j]) for j in range(nz))
            x = np.zeros((nz, width, width))
            y, t = x.copy(), 1.0
            for p in range(passes):
                prev = x.copy()
                z = np.empty_like(x)
                for j in range(nz):
                    res = proj.forward(y[j]) - depth[j]
                    z[j] = y[j] - proj.adjoint(res if wts is None else wts[j] * res) / lip
                x = np.maximum(denoise_tv_chambolle(z, weight=tv) if tv > 0 else z, 0.0)
                t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
                y = x + ((t - 1.0) / t_next) * (x - prev)
                t = t_next
                if every or p == passes - 1:
                    yield p + 1, x.copy()
            return
    finally:
        proj.free()
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


def reconstruct_slices(grid, views, scale: float, method: str = "fbp", passes: int = 10,
                       tv: float = 0.0, axis=None, flux=None) -> np.ndarray:
    """A classical reconstruction of ``grid``'s samples (see the module
    docstring): ``method`` for ``passes`` passes, FISTA-TV with Chambolle
    weight ``tv`` (in values), weighted by the counts of ``flux`` (FISTA-TV).

    Returns
    -------
    (nz, ny, nx) float64, values at ``grid``'s samples (FBP may be negative).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    sino = slice_sinograms(grid, views, scale, axis, flux)
    *_, (_, imgs) = _run(method, sino, passes, tv)
    return _stack(imgs, grid, sino["width"])


def tuned_slices(grid, views, scale: float, method: str, max_passes: int, axis=None,
                 flux=None, every: int = 8, log=None):
    """``method`` (``sart``, ``sirt`` or ``fista_tv``) at the pass count (and
    FISTA-TV's TV weight among :data:`TV_WEIGHTS` times the FBP stack's largest
    value) whose reconstruction from the views left after
    :func:`validation_split` best predicts the held-out ones (mean squared
    transmittance error, ASTRA's linear projector), then run on all ``views``
    with them. Returns ``(volume (nz, ny, nx), settings dict)``."""
    fit, val = validation_split(len(views), every)
    sino_fit = slice_sinograms(grid, [views[i] for i in fit], scale, axis, flux)
    sino_val = slice_sinograms(grid, [views[i] for i in val], scale, axis, None)
    width = sino_fit["width"]
    proj = _Astra(sino_val["theta"], width)
    pix = scale * grid.spacing[0]                 # optical depth of a value 1 over a pixel
    target = np.exp(-sino_val["depth"] * pix)

    def error(imgs):
        pred = np.exp(-np.stack([proj.forward(i) for i in imgs]) * pix)
        return float(np.mean((pred - target) ** 2))

    tvs = [0.0]
    if method == "fista_tv":
        *_, (_, fbp) = _run("fbp", sino_fit, 0)
        top = float(np.percentile(fbp, 99.9))
        tvs = [w * top for w in TV_WEIGHTS]
    best = (np.inf, None, None)
    trials = []
    try:
        for tv in tvs:
            for p, imgs in _run(method, sino_fit, max_passes, tv, every=True):
                e = error(imgs)
                trials.append({"tv": tv, "passes": p, "validation_mse": e})
                if e < best[0]:
                    best = (e, p, tv)
    finally:
        proj.free()
    _, passes, tv = best
    if log:
        log(f"{method}: {passes} passes" + (f", TV weight {tv:.3g}" if method == "fista_tv"
                                           else "") + f" (held-out MSE {best[0]:.3g})")
    vol = reconstruct_slices(grid, views, scale, method, passes, tv, axis, flux)
    return vol, {"method": method, "passes": int(passes), "tv": float(tv),
                 "validation_views": len(val), "trials": trials}
