"""How sure a fit is of each vertex value, and which view would add the most.

The Laplace approximation of a fit: around the fitted values ``x`` the
posterior is Gaussian, its precision the Gauss-Newton (Fisher) information
of the fit's own image loss plus its prior's curvature. Its diagonal gives
each vertex value a variance,

``var_i = 1 / (diag(J^T W J)_i / sigma^2 + prior_i)``,

``J`` the Jacobian of what the loss compares (sRGB pixels, an X-ray's optical
depth) w.r.t. the values, ``W`` the pixels' weights (the Poisson counts of
X-ray data, then ``sigma = 1``; else 1, and ``sigma^2`` the training
residuals' mean square), ``prior_i`` the curvature of the fit's prior
(its smoothing) and an empirical-Bayes floor: the values' own variance over
the mesh, what a vertex no ray sees keeps.

``diag(J^T W J)`` comes from the renderer's adjoint by *probing*
(Bekas, Kokiopoulou and Saad 2007; Tang and Saad 2012): a probe ``v`` over
the pixels gives ``(J^T v)_i^2``, whose mean over random signs is the
diagonal (Hutchinson's estimator). Rays touch only the vertices of the
tets they cross, so pixels further apart than any vertex's star projects
share no vertex; probing them in groups (pixels ``(x, y)`` with equal
``(x mod s, y mod s)``, one compared channel at a time, :func:`stride`)
leaves no cross terms and the estimate is *exact*, with random signs on top
unbiased where the stride is capped. A probe renders its group's rays only
(:func:`~mi_tetvr.rays.render_rays`), so one pass over all groups costs one
render and one adjoint per view and channel, whatever the stride.

The next view, as FisherRF (Jiang, Lei and Daniilidis 2024) chooses it: the
trace of the information gain ``tr(H_c Sigma)`` of each candidate (no image
needed), on the posterior's diagonal (``sum_i H_c,ii var_i``, ``diag(H_c)``
probed the same way on its rays) or, for an X-ray fit, on draws of the whole
posterior projected through the candidate (:func:`rank_views`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

__all__ = ["Information", "Uncertainty", "stride", "information", "noise_variance",
           "prior_curvature", "fit_penalty", "laplace", "rank_views", "posterior_samples",
           "rank_by_samples", "POSTERIORS",
           "candidate_cameras",
           "projection", "write",
           "MAX_STRIDE", "STD_SUFFIX", "CROSSINGS"]

#: The largest probing stride (``s^2`` groups of pixels per view): beyond it a
#: view's groups are many small launches, and random signs keep the estimate
#: unbiased where the stride falls short of a star's footprint.
MAX_STRIDE = 12
#: A value's standard deviation is written as the point array ``<value>_std``.
STD_SUFFIX = "_std"
#: The point array of how many training rays cross each vertex's tets.
CROSSINGS = "rays_crossing"


@dataclass
class Information:
    """The diagonal information of a set of views (:func:`information`).

    Attributes
    ----------
    diagonal : dict of (n, c) float64
        ``diag(J^T W J)`` by value name (the field's per-vertex arrays).
    crossings : (n,) float64
        Rays that reach each vertex's tets (exact where :attr:`exact`).
    renders : float
        The work, in renders of the views (a primal and an adjoint each).
    exact : bool
        Whether every view's stride separated all vertex stars (no cross terms).
    strides : list of int
    """
    diagonal: dict
    crossings: np.ndarray
    renders: float
    exact: bool
    strides: list = field(default_factory=list)
    seconds: float = 0.0


@dataclass
class Uncertainty:
    """A fit's Laplace approximation (:func:`laplace`).

    Attributes
    ----------
    variance : dict of (n, c) float64
        Per value name.
    information : Information
        Of the training views.
    sigma2 : float
        The noise variance of what the loss compares (1 with Poisson weights).
    prior : dict of (n, c) float64
        The prior's curvature (the fit's smoothing and the floor).
    """
    variance: dict
    information: Information
    sigma2: float
    prior: dict

    def std(self) -> dict:
        """``{<name>_std: (n,)}``: each vertex's standard deviation, the root mean
        square over its value's channels (what :func:`write` adds to the mesh)."""
        return {f"{k}{STD_SUFFIX}": np.sqrt(v.mean(axis=1)) for k, v in self.variance.items()}


def _values(trainer):
    """``{name: (key, channels)}`` of the field's per-vertex unknowns."""
    arrays = trainer.field.point_arrays
    if not arrays:
        raise ValueError(f"uncertainty: a {type(trainer.field).__name__} fit has no per-vertex "
                         f"values (a transfer function's texels): nothing to give a variance")
    if not callable(getattr(trainer.scene.integrator(), "program", None)):
        raise ValueError(f"uncertainty: the fit renders with "
                         f"{type(trainer.scene.integrator()).__name__}, whose rays cannot be "
                         f"probed one by one (color and attenuation fits, rendered by tetvr, can)")
    return arrays


def _stars(tets):
    """The tets' corners sorted by vertex: ``(order, starts)``, each vertex's star (its
    tets' corners) a run of ``order`` beginning at ``starts`` (vertices in no tet left
    out)."""
    flat = np.asarray(tets, np.int64).ravel()
    order = np.argsort(flat, kind="stable")
    return order, np.unique(flat[order], return_index=True)[1]


def stride(camera, vertices, tets, cap: int = MAX_STRIDE, stars=None) -> tuple[int, bool]:
    """The probing stride of ``camera`` over the mesh: one more than the widest
    projected box of a vertex's star (its tets) inside the image, in pixels, at most
    ``cap``; and whether it separates every star (a star reaching behind a pinhole
    camera does not count as separable). ``stars``: :func:`_stars` of the tets."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(tets, np.int64)
    uv, z = camera.project(v)
    if camera.pixel_size is None and np.any(z[t].min(axis=1) <= 0):
        return int(cap), False
    if len(t) == 0:
        return 1, True
    order, starts = stars if stars is not None else _stars(t)
    tlo, thi = uv[t].min(axis=1), uv[t].max(axis=1)          # each tet's box
    # (only the pixel centres inside the image count)
    size = np.array([camera.width, camera.height], np.float64)
    tlo, thi = np.clip(tlo, 0.0, size), np.clip(thi, 0.0, size)
    corner_tet = order // 4
    lo = np.minimum.reduceat(tlo[corner_tet], starts, axis=0)
    hi = np.maximum.reduceat(thi[corner_tet], starts, axis=0)
    need = int(np.floor(float(np.max(hi - lo)))) + 1
    return int(min(need, cap)), need <= cap


def _pixel_weights(view, flux, predicted=None):
    """(h w,) the pixels' weights: Poisson counts ``flux T`` of an X-ray view (its
    image's transmittance, or ``predicted`` for a view without one), else None."""
    if not flux:
        return None
    t = 1.0 - np.asarray(view.image[..., 3] if predicted is None else predicted, np.float64)
    return np.maximum(float(flux) * t.ravel(), 1.0)


def _channels(trainer) -> int:
    """How many values the loss compares per pixel (RGB, RGBA, an optical depth)."""
    return int(trainer._compared(mi.TensorXf(np.zeros((1, 4), np.float32))).shape[-1])


def _probe(trainer, arrays, o, d, photo, channel, weights, rng, diag, crossings, draws):
    """One probe: the rays ``o, d`` rendered, channel ``channel`` of what the loss
    compares times random signs (times the square roots of ``weights``) through the
    adjoint; the squared gradients added to ``diag``, the vertices they reach to
    ``crossings`` (once per group, on channel 0)."""
    from mi_tetvr.rays import render_rays
    opt = trainer.opt
    n = opt.n_vertices
    opt.clear_grads()
    rgba = render_rays(trainer.scene, o, d, params=trainer.params,
                       seed=int(rng.integers(2 ** 31)))
    if photo is not None:
        rgba = trainer._transformed(rgba, photo)
    c = trainer._compared(rgba)
    signs = np.zeros((len(o), c.shape[-1]))
    signs[:, channel] = rng.choice([-1.0, 1.0], size=len(o))
    if weights is not None:
        signs *= np.sqrt(weights)[:, None]
    dr.backward(dr.sum(c * mi.TensorXf(signs.astype(np.float32)), axis=None))
    seen = np.zeros(n, bool)
    for name, (key, ch) in arrays.items():
        g = np.array(dr.grad(opt[key]), np.float64).reshape(n, ch)
        diag[name] += g ** 2 / draws
        seen |= np.any(g != 0, axis=1)
    if channel == 0:
        crossings += seen / draws


def information(trainer, views, *, weights=None, strides=None, draws: int = 1, seed: int = 0,
                cap: int = MAX_STRIDE, progress=False) -> Information:
    """``diag(J^T W J)`` of the fit's compared quantity over ``views`` (training
    views, or candidate cameras: any objects with a ``camera``), by probing.

    Parameters
    ----------
    trainer : Trainer
        The fit (its scene, field, background and color transforms).
    views : list
        Views (``.camera``); a training view of a fit with color transforms is
        seen through its own.
    weights : list of (h w,) float or None, optional
        Each view's pixel weights ``W`` (e.g. Poisson counts); default 1.
    strides : list of int, optional
        Each view's stride (default :func:`stride`); 1 is Hutchinson's plain
        estimator over the whole image.
    draws : int
        Random sign draws per group (their mean).
    """
    from mi_tetvr.progress import progress_bar
    arrays = _values(trainer)
    t0 = time.perf_counter()
    vertices, tets, _ = trainer.arrays()
    n = len(vertices)
    diag = {name: np.zeros((n, c)) for name, (_, c) in arrays.items()}
    crossings = np.zeros(n)
    rng = np.random.default_rng(seed)
    stars = _stars(tets)
    found = [stride(v.camera, vertices, tets, cap if strides is None else 10 ** 6, stars)
             for v in views]
    exact = all(ok for _, ok in found)
    if strides is None:
        strides = [s for s, _ in found]
    else:
        strides = [int(s) for s in strides]
        exact &= all(s >= need for s, (need, _) in zip(strides, found))
    draws = int(draws)
    if draws < 1 or min(strides, default=1) < 1:
        raise ValueError(f"probing needs draws >= 1 and strides >= 1, got {draws} and "
                         f"{min(strides)}")
    channels = _channels(trainer)
    pbar = progress_bar(total=sum(s * s for s in strides) * draws, desc="probing",
                        unit="group", disable=not progress)
    for i, view in enumerate(views):
        cam, s = view.camera, strides[i]
        o, d = cam.rays()
        px = cam.pixel_centers().astype(np.int64)
        group = (px[:, 1] % s) * s + (px[:, 0] % s)
        w = None if weights is None else weights[i]
        photo = trainer.appearance_index.get(id(view))
        for _ in range(draws):
            for g in range(s * s):
                sel = np.nonzero(group == g)[0]
                for ch in range(channels):
                    if sel.size:
                        _probe(trainer, arrays, o[sel], d[sel], photo, ch,
                               None if w is None else w[sel], rng, diag, crossings, draws)
                pbar.update(1)
    trainer.opt.clear_grads()
    pbar.close()
    return Information(diag, crossings, float(len(views) * draws * channels), bool(exact), strides,
                       time.perf_counter() - t0)


def noise_variance(trainer, views=None) -> float:
    """The mean square of the training residuals of what the loss compares: the
    noise variance ``sigma^2`` of a Gaussian likelihood (its maximum-likelihood
    value at the fit)."""
    from mi_tetvr.rays import render_rays
    total, count = 0.0, 0
    with dr.suspend_grad():
        for view in (views or trainer.train):
            o, d = view.camera.rays()
            rgba = render_rays(trainer.scene, o, d, params=trainer.params)
            photo = trainer.appearance_index.get(id(view))
            if photo is not None:
                rgba = trainer._transformed(rgba, photo)
            target = mi.TensorXf(np.ascontiguousarray(view.image, np.float32).reshape(-1, 4))
            r = np.array(trainer._compared(rgba) - trainer._compared(target), np.float64)
            total, count = total + float(np.sum(r ** 2)), count + r.size
    return total / max(count, 1)


def _colors(tets, n, seed=0):
    """(n,) a coloring of the mesh's vertices in which no two vertices of one tet
    share a color (Jones-Plassmann rounds with random priorities)."""
    from mi_tetvr.extras import needs
    from mi_tetvr.mesh.topology import unique_edges
    with needs("recon", "the prior's curvature"):
        from scipy.sparse import coo_matrix
    e = unique_edges(tets)
    adj = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                     shape=(n, n)).tocsr()
    prio = np.random.default_rng(seed).permutation(n).astype(np.float64) + 1.0
    color = np.full(n, -1)
    k = 0
    while np.any(color < 0):
        free = color < 0
        p = np.where(free, prio, 0.0)
        top = adj.multiply(p[None, :]).max(axis=1).toarray().ravel()
        pick = free & (p > top)
        color[pick] = k
        k += 1
    return color


def prior_curvature(trainer, scale: float) -> dict:
    """``{name: (n, c)}``: the diagonal of ``scale`` times the Hessian of the fit's
    prior (:meth:`Field.prior <mi_tetvr.recon.fields.Field.prior>`), exact for its
    quadratic smoothing: Hessian-vector products (differences of the prior's
    gradient) on groups of vertices of which no two share a tet. Zeros without
    a prior."""
    arrays = _values(trainer)
    n = trainer.opt.n_vertices
    out = {name: np.zeros((n, c)) for name, (_, c) in arrays.items()}
    if trainer.field.prior(trainer.opt) is None:
        return out
    opt = trainer.opt

    def gradients():
        opt.clear_grads()
        dr.backward(trainer.field.prior(opt))
        return {name: np.array(dr.grad(opt[key]), np.float64).reshape(n, c)
                for name, (key, c) in arrays.items()}

    base = {key: dr.detach(opt[key]) for key, _ in arrays.values()}
    g0 = gradients()
    color = _colors(trainer.tets, n)
    try:
        for name, (key, c) in arrays.items():
            x = np.array(base[key], np.float64).reshape(n, c)
            eps = max(float(np.abs(x).max()), 1e-6) * 1e-2
            for j in range(c):
                for k in range(int(color.max()) + 1):
                    v = np.zeros((n, c))
                    v[color == k, j] = eps
                    opt[key] = mi.Float((x + v).ravel().astype(np.float32))
                    g1 = gradients()[name]
                    out[name][color == k, j] += (g1 - g0[name])[color == k, j] / eps
                opt[key] = base[key]
    finally:
        for key, _ in arrays.values():
            opt[key] = base[key]
        opt.clear_grads()
    return {k: np.maximum(v * scale, 0.0) for k, v in out.items()}


def _flux(trainer):
    cfg = trainer.config.data.xray_flux
    return cfg if cfg is not None else getattr(trainer.dataset, "xray_flux", None)


def fit_penalty(fit_dir):
    """``(beta, delta)``: the absolute weight and corner of the total-variation
    penalty an X-ray fit in ``fit_dir`` solved with (its ``metrics.json``), or None."""
    import json
    from pathlib import Path
    path = Path(fit_dir) / "metrics.json"
    if not path.is_file():
        return None
    penalty = json.loads(path.read_text()).get("solver", {}).get("penalty") or {}
    if penalty.get("beta") is None or penalty.get("delta") is None:
        return None
    return float(penalty["beta"]), float(penalty["delta"])


def laplace(trainer, *, penalty=None, strides=None, draws: int = 1, seed: int = 0,
            cap: int = MAX_STRIDE, progress=False) -> Uncertainty:
    """The Laplace approximation of a fit (see the module docstring), from its
    training views at the fit's scale (:attr:`Trainer.train`). ``penalty``: an X-ray
    fit's total variation ``(beta, delta)`` (:func:`fit_penalty`), whose exact
    curvature at the fitted field (:meth:`TetGradient.hessian_diagonal
    <mi_tetvr.recon.tomography.TetGradient.hessian_diagonal>`) joins the prior."""
    arrays = _values(trainer)
    views = trainer.train
    flux = _flux(trainer) if trainer.field.scored == "transmittance" else None
    weights = [_pixel_weights(v, flux) for v in views] if flux else None
    info = information(trainer, views, weights=weights, strides=strides, draws=draws,
                       seed=seed, cap=cap, progress=progress)
    sigma2 = 1.0 if flux else max(noise_variance(trainer, views), 1e-12)
    if trainer.field.scored == "transmittance":
        # an X-ray fit is a linear solve whose penalty is its solver's, not the field's:
        # 1/2 sum w r^2 + beta TV (with the counts as weights, sigma = 1)
        prior = {name: np.zeros((trainer.opt.n_vertices, c)) for name, (_, c) in arrays.items()}
        if penalty is not None:
            from mi_tetvr.recon.tomography import TetGradient
            beta, delta = penalty
            vertices, tets, values = trainer.arrays()
            curv = TetGradient(vertices, tets).hessian_diagonal(values["attenuation"], delta)
            prior["attenuation"] += beta * curv[:, None] / sigma2
    else:
        # the loss is a mean over each view's compared values, the prior added once per
        # step: over all V views of M values the posterior's exponent is
        # (sum r^2 + V M P) / (2 sigma^2), its curvature J^T J / sigma^2 + V M P'' / (2 sigma^2)
        m = views[0].camera.height * views[0].camera.width * _channels(trainer)
        prior = prior_curvature(trainer, len(views) * m / (2.0 * sigma2))
    _, _, values = trainer.arrays()
    variance = {}
    for name, (_, c) in arrays.items():
        # the empirical-Bayes floor: the values' own spread over the mesh
        x = np.asarray(values[name], np.float64).reshape(-1, c)
        prior[name] = prior[name] + 1.0 / np.maximum(x.var(axis=0), 1e-12)[None, :]
        variance[name] = 1.0 / (info.diagonal[name] / sigma2 + prior[name])
    return Uncertainty(variance, info, sigma2, prior)


#: How :func:`rank_views` takes the posterior: ``auto`` (``samples`` for an X-ray
#: fit, else ``diagonal``), ``diagonal`` (FisherRF's), ``samples``.
POSTERIORS = ("auto", "diagonal", "samples")


def rank_views(trainer, uncertainty: Uncertainty, cameras, *, posterior: str = "auto",
               stride: int | None = None, draws: int = 1, samples: int = 4,
               iterations: int = 20, seed: int = 0, cap: int = MAX_STRIDE,
               progress=False) -> list[dict]:
    """Candidate ``cameras`` ranked by the information they would add to the fit:
    FisherRF's trace of the information gain, ``tr(H_c Sigma)`` (``H_c`` the
    candidate's Gauss-Newton information, with the Poisson counts the fit's current
    transmittance predicts for an X-ray view). ``posterior``:

    * ``diagonal`` (FisherRF's): ``Sigma``'s diagonal, the variances;
      ``sum_i diag(H_c)_i var_i``, ``diag(H_c)`` probed as :func:`information` does
      (``stride``: every candidate's, default :func:`stride`'s; ``draws``);
    * ``samples``: an X-ray fit's whole ``Sigma``, by ``samples`` draws of the
      posterior (:func:`posterior_samples`, ``iterations`` of conjugate gradients)
      projected through each candidate (:func:`rank_by_samples`). The diagonal
      cannot see which directions the scan has not measured: a new angle adds about
      as much to each vertex's own information wherever it lies;
    * ``auto``: ``samples`` for an X-ray fit, else ``diagonal``.

    Returns ``[{"index", "gain", "renders", "exact"}]``, best first."""
    from types import SimpleNamespace

    from mi_tetvr.progress import progress_bar
    if posterior not in POSTERIORS:
        raise ValueError(f"posterior must be one of {', '.join(POSTERIORS)}, got {posterior!r}")
    xray = trainer.field.scored == "transmittance"
    if posterior == "samples" or (posterior == "auto" and xray):
        z = posterior_samples(trainer, uncertainty, samples, iterations, seed, progress)
        return rank_by_samples(trainer, uncertainty, cameras, z)
    flux = _flux(trainer) if xray else None
    rows = []
    for i, cam in enumerate(progress_bar(cameras, desc="candidates", unit="view",
                                         disable=not progress)):
        view = SimpleNamespace(camera=cam)
        weights = None
        if flux:
            predicted = trainer.render_camera(cam)[..., 3]
            weights = [_pixel_weights(view, flux, predicted)]
        info = information(trainer, [view], weights=weights, draws=draws, seed=seed + i,
                           strides=None if stride is None else [stride], cap=cap)
        gain = sum(float(np.sum(info.diagonal[k] / uncertainty.sigma2 * v))
                   for k, v in uncertainty.variance.items())
        rows.append({"index": i, "gain": gain, "renders": info.renders,
                     "exact": info.exact})
    return sorted(rows, key=lambda r: -r["gain"])


def _projector(trainer, cameras):
    """The walk of the fit's mesh through ``cameras`` as the linear operator ``A``
    (:class:`~mi_tetvr.recon.tomography.Projector`)."""
    from mi_tetvr.recon.tomography import Projector
    vertices, tets, _ = trainer.arrays()
    return Projector(vertices, tets, cameras)


def posterior_samples(trainer, uncertainty: Uncertainty, k: int = 4, iterations: int = 40,
                      seed: int = 0, progress=False) -> np.ndarray:
    """(k, n) draws from the Laplace posterior of an X-ray fit with its *full*
    precision ``H = A^T W A / sigma^2 + diag(prior)`` (not only its diagonal): each
    ``z = H^-1 (A^T W^(1/2) e1 / sigma + prior^(1/2) e2)``, ``e`` standard normal
    (perturbation sampling: its covariance is ``H^-1``), solved by conjugate gradients
    preconditioned by the exact diagonal (:attr:`Uncertainty.variance`). The model is
    linear, so ``H`` is the fit's own curvature; the walk is ``A``, its adjoint ``A^T``."""
    from mi_tetvr.progress import progress_bar
    if trainer.field.scored != "transmittance":
        raise ValueError("posterior samples need the linear model of an X-ray fit (an "
                         "image fit's ranking uses the diagonal)")
    views = trainer.train
    proj = _projector(trainer, [v.camera for v in views])
    flux = _flux(trainer)
    w = np.concatenate([_pixel_weights(v, flux) for v in views]) if flux else \
        np.ones(proj.shape[0])
    w = w / uncertainty.sigma2
    prior = uncertainty.prior["attenuation"][:, 0]
    precond = uncertainty.variance["attenuation"][:, 0]

    def H(x):
        return proj.adjoint(w * proj.forward(x)) + prior * x

    rng = np.random.default_rng(seed)
    out = np.zeros((int(k), proj.n))
    bar = progress_bar(total=int(k) * int(iterations), desc="posterior samples",
                       unit="step", disable=not progress)
    for j in range(int(k)):
        b = proj.adjoint(np.sqrt(w) * rng.standard_normal(proj.shape[0])) + \
            np.sqrt(prior) * rng.standard_normal(proj.n)
        x = precond * b
        r = b - H(x)
        z = precond * r
        p, rz = z.copy(), float(r @ z)
        for _ in range(int(iterations)):
            hp = H(p)
            alpha = rz / max(float(p @ hp), 1e-300)
            x += alpha * p
            r -= alpha * hp
            z = precond * r
            rz, rz_old = float(r @ z), rz
            p = z + (rz / max(rz_old, 1e-300)) * p
            bar.update(1)
        out[j] = x
    bar.close()
    return out


def rank_by_samples(trainer, uncertainty: Uncertainty, cameras, samples) -> list[dict]:
    """Candidates ranked by the trace of the information gain with the sampled
    posterior: ``sum_r w_r E[(a_r^T z)^2] / sigma^2`` over each candidate's rays,
    ``a_r^T z`` the walk's projection of a draw ``z`` (:func:`posterior_samples`),
    ``w_r`` the counts the fit's transmittance predicts. Returns :func:`rank_views`'s
    rows."""
    flux = _flux(trainer)
    proj = _projector(trainer, list(cameras))
    var = np.mean([proj.forward(z) ** 2 for z in samples], axis=0)
    rows = []
    for i, cam in enumerate(cameras):
        v = var[proj.offsets[i]:proj.offsets[i + 1]]
        w = _pixel_weights(None, flux, trainer.render_camera(cam)[..., 3]) if flux else 1.0
        rows.append({"index": i, "gain": float(np.sum(w * v)) / uncertainty.sigma2,
                     "renders": float(len(samples)), "exact": False})
    return sorted(rows, key=lambda r: -r["gain"])


def candidate_cameras(cameras, n: int) -> list:
    """``n`` candidate cameras around a fit's training ``cameras``: for X-ray
    (orthographic) ones, the first one turned about the scan's axis (the normal of
    the view directions' plane, through the point they look at) in steps of
    ``180 / n`` degrees; for pinhole ones, a Fibonacci sphere around that point at
    the cameras' median distance, with the first one's intrinsics."""
    import dataclasses

    from mi_tetvr.camera import cameras_focus, fibonacci_cameras
    if n < 1:
        raise ValueError(f"the candidates must be at least 1, got {n}")
    ref = cameras[0]
    focus = cameras_focus(cameras)
    if ref.pixel_size is None:
        radius = float(np.median([np.linalg.norm(c.center - focus) for c in cameras]))
        # (the cameras' mean up; fibonacci_cameras normalizes it)
        up = np.mean([c.to_world[:3, 1] for c in cameras], axis=0)
        if np.linalg.norm(up) < 1e-6:
            up = np.array([0.0, 0.0, 1.0])
        return fibonacci_cameras(n, radius, res=(ref.width, ref.height), fov=ref.fov_x,
                                 up=tuple(up), target=tuple(focus))
    if len(cameras) < 2:
        raise ValueError("X-ray candidates turn about the scan's axis: the fit needs two "
                         "training angles or more to know it")
    dirs = np.array([c.to_world[:3, 2] for c in cameras], np.float64)
    axis = np.linalg.svd(dirs)[2][-1]
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    out = []
    for i in range(n):
        a = np.pi * i / n
        rot = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * (k @ k)
        m = np.array(ref.to_world, np.float64).copy()
        m[:3, :3] = rot @ m[:3, :3]
        m[:3, 3] = focus + rot @ (m[:3, 3] - focus)
        out.append(dataclasses.replace(ref, to_world=m))
    return out


def projection(vertices, tets, values, camera, mode: str = "max", value_range=None,
               colormap: str = "viridis") -> np.ndarray:
    """(h, w, 3) linear RGB: the per-vertex ``values`` (an uncertainty) projected
    through ``camera`` by ``tetproj`` (``mode`` max or mean along each ray, exact
    on the tets' linear field), colored by ``colormap`` over ``value_range``
    (default 0 to the values' maximum); black where no ray meets the mesh."""
    import mi_tetvr
    if mode not in ("max", "mean"):
        raise ValueError(f"an uncertainty projection is max or mean, got {mode!r}")
    values = np.asarray(values, np.float64).ravel()
    lo, hi = value_range or (0.0, float(values.max()) if values.size else 1.0)
    hi = hi if hi > lo else lo + 1.0
    shape = mi_tetvr.tetmesh_dict(vertices, tets, scalar=values, transfer_function=colormap,
                                  value_min=float(lo), value_max=float(hi))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetproj", "mode": mode},
                          "mesh": shape,
                          "sensor": camera.sensor_dict(spp=1, sampler="stratified",
                                                       jitter=False)})
    with dr.suspend_grad():
        image = np.array(mi.render(scene, spp=1), np.float64)
    return image[..., :3]


def write(uncertainty: Uncertainty, path, out=None):
    """Add each value's standard deviation (``<name>_std``, :meth:`Uncertainty.std`)
    and the training rays crossing each vertex (``rays_crossing``) to the point
    arrays of the mesh file ``path`` (a fit's ``.vtu``), keeping the others; written
    back to ``path``, or to ``out`` (any format meshio writes with point data)."""
    import meshio

    from mi_tetvr.mesh.io import read_mesh_file
    mesh = read_mesh_file(path)
    n = len(mesh.points)
    arrays = {**uncertainty.std(), CROSSINGS: uncertainty.information.crossings}
    for a in arrays.values():
        if len(a) != n:
            raise ValueError(f"{path} has {n} vertices and the uncertainty {len(a)}: it is not "
                             f"the fit's mesh")
    mesh.point_data.update({k: np.asarray(a, np.float64) for k, a in arrays.items()})
    meshio.write(out or path, mesh)
