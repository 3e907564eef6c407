"""Absorption tomography on tets as the linear problem it is.

The optical depth of a pixel's ray, ``b = -log(I / I0)``, is linear in the
per-vertex attenuation ``x``: ``b = A x`` with ``A[r, i]`` the integral along
ray ``r`` of vertex ``i``'s hat function (linear inside each tet). The tet
walk is ``A`` (``tetvr``'s ``absorption`` model with no early termination,
:class:`Projector`) and its reverse-mode derivative is ``A^T`` (the walk's
adjoint), so the classical algebraic methods run on the mesh as they run on
voxels:

* :func:`sart`: (ordered-subset) SART, Andersen and Kak 1984: per subset of
  views ``x += relaxation * (A_s^T W R (b_s - A_s x)) / (A_s^T W 1)`` with
  ``R`` the inverse row sums (each ray's length in the mesh) and ``W`` the
  statistical weights (Poisson counts; 1 without noise), ``x >= 0`` after
  each update. One view per subset is SART as scikit-image's ``iradon_sart``
  runs it per slice; all views in one subset is SIRT. Optionally a few
  total-variation descent steps on the mesh's edges after each pass (the
  ASD-POCS scheme of Sidky and Pan 2008, :func:`tv_gradient`).
* :func:`least_squares`: CGLS/LSQR (``scipy.sparse.linalg.lsqr``) on the
  weighted operator :meth:`Projector.operator`, then ``x >= 0``.

The default (``solver="sart"``, one view per subset, no TV) was chosen by
measurement (``benchmarks/bench_tomography.py``, see ``benchmarks/README.md``).
:func:`fit_attenuation` is ``mi-tetvr fit --model absorption``'s run: a tet
grid whose vertices lie on the detector's pixel grid, the solver, and the
same outputs as every fit.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

__all__ = ["Projector", "depths", "statistical_weights", "sart", "least_squares",
           "tv_gradient", "aligned_resolution", "detector_cell", "fit_attenuation",
           "DEFAULT_PASSES", "STALL", "HeldOut", "MAX_PASSES", "TV_CANDIDATES", "SPARSE_VIEWS"]

#: Passes over the views when the config gives none: the solver's count where
#: the measured volume PSNR stopped rising (``benchmarks/bench_tomography.py``).
DEFAULT_PASSES = {"sart": 15, "sirt": 200, "lsqr": 12}
#: Held-out tuning: the most passes tried (the solve stops earlier once the
#: held-out views stop improving).
MAX_PASSES = {"sart": 30, "sirt": 300}
#: Held-out tuning: the ASD-POCS TV weights tried on noisy or sparse data.
TV_CANDIDATES = (0.1, 0.3)
#: Fewer training views than this are sparse: TV weights are tried.
SPARSE_VIEWS = 48
#: Noisy data: the passes stop when the weighted residual falls by less than
#: this fraction in a pass (on the head MR at 10^4 photons the volume PSNR
#: peaked there, at 6 passes of SART).
STALL = 0.01


def depths(views, flux=None):
    """The training data ``b``: optical depth ``-log T`` of every pixel of
    ``views`` (X-ray views: alpha = 1 - T), float64, concatenated; with a
    ``flux``, a pixel that counted no photon counts half of one."""
    floor = 0.5 / float(flux) if flux else 1e-12
    return np.concatenate([-np.log(np.clip(1.0 - v.image[..., 3].astype(np.float64), floor,
                                           None)).ravel() for v in views])


def statistical_weights(views, flux):
    """Weights of the weighted least squares that goes with Poisson counts:
    the variance of ``-log(N / N0)`` is ``1 / N``, so each ray weighs its
    count ``N = flux * T`` (at least one photon); ``None`` without a flux
    (noise-free data: every ray alike)."""
    if not flux:
        return None
    t = np.concatenate([1.0 - v.image[..., 3].astype(np.float64).ravel() for v in views])
    return np.maximum(float(flux) * t, 1.0)


class Projector:
    """``A``: the optical depths of the pixel rays of ``cameras`` through a tet
    mesh holding a per-vertex attenuation, and its transpose.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    cameras : list of mi_tetvr.camera.Camera
    topology : mi_tetvr.mesh.Topology, optional
        ``build_topology(vertices, tets)`` when the caller has it.
    """

    KEY = "volume.vertex_opacity"

    def __init__(self, vertices, tets, cameras, topology=None):
        import mitsuba as mi

        import mi_tetvr
        from mi_tetvr.mesh.topology import build_topology
        if topology is None:
            topology = build_topology(vertices, tets)
        self.n = len(vertices)
        # the shape's tets are the oriented ones: their topology is this one, built once
        shape = mi_tetvr.tetmesh_shape(
            mi_tetvr.tetmesh_dict(vertices, topology.tets, opacity=np.zeros(self.n),
                                  model="absorption"),
            topology=dataclasses.replace(topology, n_flipped=0))
        # no early termination: the depth stays linear however large it gets
        self.scene = mi.load_dict({"type": "scene",
                                   "integrator": {"type": "tetvr", "min_transmittance": 0.0},
                                   "volume": shape})
        self.params = mi.traverse(self.scene)
        self.sensors = []
        for cam in cameras:
            self.sensors.append(mi.load_dict(cam.sensor_dict(sampler="stratified",
                                                             jitter=False)))
        self.pixels = np.array([c.width * c.height for c in cameras])
        self.offsets = np.concatenate([[0], np.cumsum(self.pixels)])

    @property
    def shape(self):
        """``(rays, vertices)``."""
        return int(self.offsets[-1]), self.n

    def rows(self, views):
        """Indices into ``b`` of the rays of ``views`` (view indices)."""
        return np.concatenate([np.arange(self.offsets[i], self.offsets[i + 1]) for i in views])

    def _views(self, views):
        return range(len(self.sensors)) if views is None else views

    def _set(self, x):
        import mitsuba as mi
        self.params[self.KEY] = x if isinstance(x, mi.Float) else \
            mi.Float(np.asarray(x, np.float32).ravel())
        self.params.update()

    def forward(self, x, views=None) -> np.ndarray:
        """``A x`` over the rays of ``views`` (default all), float64."""
        import drjit as dr
        import mitsuba as mi
        if np.shape(x) != (self.n,):
            raise ValueError(f"expected {self.n} vertex values, got shape {np.shape(x)}")
        self._set(x)
        out = []
        with dr.suspend_grad():
            for i in self._views(views):
                image = mi.render(self.scene, sensor=self.sensors[i], spp=1)
                out.append(np.array(-dr.log(1.0 - image[..., 3].array), np.float64))
        return np.concatenate(out)

    def adjoint(self, y, views=None) -> np.ndarray:
        """``A^T y`` for ``y`` over the rays of ``views`` (default all), float64:
        the reverse-mode derivative of ``<A x, y>``, walked back by ``tetvr``."""
        import drjit as dr
        import mitsuba as mi
        views = list(self._views(views))
        y = np.asarray(y, np.float64).ravel()
        if len(y) != int(self.pixels[views].sum()):
            raise ValueError(f"expected {int(self.pixels[views].sum())} ray values, got "
                             f"{len(y)}")
        x = dr.zeros(mi.Float, self.n)
        dr.enable_grad(x)
        self._set(x)
        k = 0
        for i in views:
            image = mi.render(self.scene, self.params, sensor=self.sensors[i], spp=1)
            w = mi.Float(y[k:k + self.pixels[i]].astype(np.float32))
            k += self.pixels[i]
            dr.backward(dr.sum(-dr.log(1.0 - image[..., 3].array) * w))
        g = np.array(dr.grad(x), np.float64)
        self._set(dr.detach(x))
        return g

    def operator(self, weights=None):
        """``W^(1/2) A`` as a ``scipy.sparse.linalg.LinearOperator`` (``W`` the
        statistical weights, identity by default)."""
        from scipy.sparse.linalg import LinearOperator
        s = None if weights is None else np.sqrt(np.asarray(weights, np.float64))
        return LinearOperator(
            self.shape, dtype=np.float64,
            matvec=lambda x: self.forward(np.ravel(x)) * (1 if s is None else s),
            rmatvec=lambda y: self.adjoint(np.ravel(y) * (1 if s is None else s)))


def tv_gradient(x, edges, eps):
    """Gradient of the smoothed total variation on the mesh's edges,
    ``sum_e sqrt((x_i - x_j)^2 + eps^2)``."""
    d = x[edges[:, 0]] - x[edges[:, 1]]
    g = d / np.sqrt(d * d + eps * eps)
    return np.bincount(edges[:, 0], g, len(x)) - np.bincount(edges[:, 1], g, len(x))


class HeldOut:
    """Early stopping on held-out projections: after each pass the mean
    squared transmittance error of ``views`` (indices into the projector's
    views, left out of the solve) is measured; the best ``x`` is kept and the
    solve stops once ``patience`` passes have not improved on it.

    Attributes
    ----------
    errors : list of float
        The error after each pass.
    best : (float, int, ndarray or None)
        The least error, its pass (1-based) and its ``x``.
    """

    def __init__(self, projector, b, views, patience: int = 3):
        self.projector, self.views, self.patience = projector, list(views), patience
        self.target = np.exp(-np.asarray(b, np.float64)[projector.rows(self.views)])
        self.errors = []
        self.best = (np.inf, 0, None)

    def __call__(self, p, x) -> bool:
        """Record pass ``p``'s ``x``; True when the solve should stop."""
        e = float(np.mean((np.exp(-self.projector.forward(x, self.views)) - self.target) ** 2))
        self.errors.append(e)
        if e < self.best[0]:
            self.best = (e, p, x.copy())
        return p - self.best[1] >= self.patience


def sart(projector: Projector, b, passes: int, weights=None, subset_size: int = 1,
         relaxation: float = 1.0, x0=None, tv: float = 0.0, edges=None, tv_steps: int = 5,
         deadline=None, callback=None, views=None, held_out: HeldOut | None = None,
         stop_at_noise: bool = True):
    """Ordered-subset SART with ``x >= 0`` (``subset_size`` views per update;
    all of them: SIRT), optionally followed in each pass by ``tv_steps``
    total-variation descent steps of ``tv`` times the pass's change (ASD-POCS).

    Parameters
    ----------
    projector : Projector
    b : (rays,) float
        Optical depths (:func:`depths`).
    passes : int
    weights : (rays,) float, optional
        Statistical weights (:func:`statistical_weights`).
    deadline : callable, optional
        Returns True when time is up (checked after each subset).

    With ``weights`` (Poisson counts) the passes stop once the weighted
    residual is down to the noise, ``sum w (b - A x)^2 <= rays`` (Morozov's
    discrepancy principle), or falls by less than :data:`STALL` in a pass:
    further passes would fit the noise.
    callback : callable, optional
        ``callback(pass_index, x, residual, mse)`` after each pass: ``residual``
        the weighted RMS of ``b - A x`` over the pass's subsets (each before its
        update), ``mse`` the mean squared transmittance error alike.
    views : list of int, optional
        The projector's views solved for (default all).
    held_out : HeldOut, optional
        Stop when the held-out views stop improving, and return the best
        ``x`` they saw (instead of the noise rule).
    stop_at_noise : bool
        With ``weights``, stop by the discrepancy rule above (default).

    Returns
    -------
    (n,) float64
    """
    b = np.asarray(b, np.float64)
    views = np.arange(len(projector.sensors)) if views is None else np.asarray(views)
    order = views[np.random.default_rng(0).permutation(len(views))] \
        if subset_size < len(views) else views
    subsets = [np.sort(order[k:k + subset_size]) for k in range(0, len(views), subset_size)]
    n_rays = len(projector.rows(views))
    w = np.ones_like(b) if weights is None else np.asarray(weights, np.float64)
    ones = np.ones(projector.n)
    lengths = projector.forward(ones)
    inv_len = np.where(lengths > 1e-9, 1.0 / np.maximum(lengths, 1e-30), 0.0)
    cols = []
    for s in subsets:
        c = projector.adjoint(w[projector.rows(s)], s)
        cols.append(np.where(c > 1e-12, 1.0 / np.maximum(c, 1e-30), 0.0))
    x = np.zeros(projector.n) if x0 is None else np.maximum(np.asarray(x0, np.float64), 0.0)
    last_chi2 = np.inf
    for p in range(passes):
        before = x.copy()
        sq, total, t_sq = 0.0, 0.0, 0.0
        for s, c in zip(subsets, cols):
            r = projector.rows(s)
            ax = projector.forward(x, s)
            res = b[r] - ax
            sq += float(np.sum(w[r] * res * res))
            total += float(np.sum(w[r]))
            t_sq += float(np.sum((np.exp(-ax) - np.exp(-b[r])) ** 2))
            x = np.maximum(x + relaxation * c * projector.adjoint(w[r] * res * inv_len[r], s),
                           0.0)
            if deadline is not None and deadline():
                break
        if tv > 0 and edges is not None:
            change = np.linalg.norm(x - before)
            for _ in range(tv_steps):
                g = tv_gradient(x, edges, 1e-3 * max(float(x.max()), 1e-30))
                norm = np.linalg.norm(g)
                if norm > 0:
                    x = np.maximum(x - tv * change * g / norm, 0.0)
        if callback is not None:
            callback(p, x, np.sqrt(sq / max(total, 1e-30)), t_sq / n_rays)
        if deadline is not None and deadline():
            break
        if held_out is not None:
            if held_out(p + 1, x):
                break
            continue
        chi2 = sq / n_rays
        if weights is not None and stop_at_noise and (chi2 <= 1.0 or
                                                      chi2 > (1.0 - STALL) * last_chi2):
            # the residual is down to the noise (with counts as weights each ray's
            # weighted squared residual is 1: Morozov's discrepancy principle), or
            # what is left of it is the model's mismatch: further passes fit noise
            break
        last_chi2 = chi2
    if held_out is not None and held_out.best[2] is not None:
        return held_out.best[2]
    return x


def least_squares(projector: Projector, b, iterations: int, weights=None, x0=None,
                  callback=None):
    """CGLS/LSQR (``scipy.sparse.linalg.lsqr``) on ``W^(1/2) A x = W^(1/2) b``
    for ``iterations`` iterations (early stopping is its regularization),
    then ``x >= 0``. ``callback(iterations, x, residual, mse)`` once at the end
    (as :func:`sart`'s, of the final ``x``)."""
    from scipy.sparse.linalg import lsqr
    b = np.asarray(b, np.float64)
    s = np.ones_like(b) if weights is None else np.sqrt(np.asarray(weights, np.float64))
    op = projector.operator(weights)
    start = np.zeros(projector.n) if x0 is None else np.asarray(x0, np.float64)
    sol = lsqr(op, s * b - op.matvec(start), iter_lim=int(iterations))
    x = np.maximum(start + sol[0], 0.0)
    if callback is not None:
        ax = projector.forward(x)
        res = s * (b - ax)
        callback(int(sol[2]), x, float(np.sqrt(np.sum(res * res) / np.sum(s * s))),
                 float(np.mean((np.exp(-ax) - np.exp(-b)) ** 2)))
    return x


def detector_cell(dataset, bounds) -> float:
    """The size of one detector pixel at the box's centre: the pixel of a
    parallel-beam view, a perspective pixel's footprint at the distance of the
    box's centre (the median over the training views)."""
    centre = np.mean(np.asarray(bounds, np.float64), axis=0)
    sizes = []
    for v in dataset.train:
        c = v.camera
        if c.is_orthographic:
            sizes.append(c.pixel_size)
        else:
            depth = float(np.dot(centre - c.to_world[:3, 3], c.to_world[:3, 2]))
            sizes.append(depth / np.sqrt(c.fx * c.fy))
    return float(np.median(sizes))


def aligned_resolution(bounds, cell: float) -> int:
    """The :func:`~mi_tetvr.mesh.initial.grid_init` resolution whose cells over
    ``bounds`` are ``cell`` wide: its vertices then lie on the grid of that
    spacing from the box's low corner (a parallel-beam detector's pixel grid,
    on which the classical methods reconstruct too)."""
    b = np.asarray(bounds, np.float64).reshape(2, 3)
    return max(1, int(round(float(np.max(b[1] - b[0])) / cell)))


def fit_attenuation(dataset, out_dir, config, resume=True, progress=True, log=print,
                    now=time.perf_counter):
    """``mi-tetvr fit --model absorption`` with a linear solver
    (``config.solver`` ``sart``, ``sirt`` or ``lsqr``): an attenuation on a
    tet grid from X-ray projections, written as every fit writes its results
    (``attenuation.vtu``, ``metrics.json``, ``test/*.png``, ``progress.png``,
    ``checkpoint.npz``, ``config.json``). Returns the metrics.

    The grid's cells are the detector's pixels (:func:`detector_cell`) unless
    ``config.grid_resolution`` says otherwise; with ``config.stages`` of
    ``{"grid": r}`` entries each grid is solved in turn, starting from the
    previous one's field (coarse to fine). ``config.xray_flux`` or the data
    set's weights the rays by their counts. ``config.time_budget`` (minutes)
    bounds the passes.
    """
    from mi_tetvr.mesh.initial import grid_init, grid_sample
    from mi_tetvr.mesh.topology import (build_topology, format_summary, geometry_summary,
                                        unique_edges)
    from mi_tetvr.progress import progress_bar as tqdm
    from mi_tetvr.recon.checkpoint import load_checkpoint, save_checkpoint
    from mi_tetvr.recon.metrics import psnr
    from mi_tetvr.recon.pipeline import data_bounds, write_outputs
    from mi_tetvr.recon.trainer import RunState, Trainer

    t_start = now()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # the scanned box the data set records (a volume's), else the region the views show
    bounds = np.asarray(dataset.bbox, np.float64) if config.bounds is None and \
        dataset.bbox is not None else data_bounds(config, dataset)
    cell = detector_cell(dataset, bounds)
    budget = None if config.time_budget is None else 60.0 * config.time_budget
    deadline = None if budget is None else (lambda: now() - t_start > 0.9 * budget)
    solver = config.linear_solver
    passes = config.passes or DEFAULT_PASSES[solver]
    flux = config.xray_flux if config.xray_flux is not None else dataset.xray_flux
    # the box a hair larger than the data's: rays along its faces run inside
    box = np.stack([bounds[0] - 1e-3 * cell, bounds[1] + 1e-3 * cell])
    resolution = config.grid_resolution or aligned_resolution(bounds, cell)
    config = dataclasses.replace(config, bounds=np.asarray(bounds).tolist(),
                                 grid_resolution=resolution, xray_flux=flux)
    # coarse to fine: each stage's grid (one without: the fit's), the fit's last
    grids = [int(st.get("grid") or resolution) for st in (config.stages or [])]
    grids = [g for g in grids if g != resolution] + [resolution]
    ckpt = out / "checkpoint.npz"
    x0 = None
    if resume and ckpt.is_file():
        from mi_tetvr.recon.pipeline import check_resume
        check_resume(config, ckpt)
        saved = load_checkpoint(ckpt, dataset, config)
        x0 = saved.arrays()[2]["attenuation"]
        grids = grids[-1:]
        log(f"resumed from {ckpt}: more passes from its attenuation")
    b = depths(dataset.train, flux)
    weights = statistical_weights(dataset.train, flux)
    cameras = [v.camera for v in dataset.train]
    history = {"step": [], "time": [], "loss": [], "psnr": []}
    x, prev = x0, None
    train_begin = now()
    # held-out tuning of the passes and the TV weight (on the last grid)
    tuning = solver in ("sart", "sirt") and config.validation > 0 and len(cameras) >= 6 and \
        (config.passes is None or config.tv is None)
    if config.tv is not None:
        tvs = [config.tv]
    elif tuning and (flux or len(cameras) < SPARSE_VIEWS):
        tvs = [0.0, *TV_CANDIDATES]
    else:
        tvs = [0.0]
    max_passes = config.passes or MAX_PASSES[solver] if tuning else passes
    tuned = None
    bar = tqdm(total=passes * (len(grids) - 1) + max_passes * (len(tvs) + 1 if tuning else 1),
               disable=not progress, unit="pass", desc=f"{solver} ({len(cameras)} views)")
    for g in grids:
        v, t = grid_init(box, g)
        topology = build_topology(v, t)
        if g == grids[-1]:
            log(format_summary(geometry_summary(v, topology)))
        if prev is not None:
            x = grid_sample(box, *prev, v)
        projector = Projector(v, t, cameras, topology)

        def record(p, xx, residual, mse):
            history["step"].append(len(history["step"]) + 1)
            history["time"].append(now() - train_begin)
            history["loss"].append(residual ** 2)
            history["psnr"].append(psnr(mse))        # the training projections'
            bar.update(1)
            bar.set_postfix(residual=f"{residual:.3g}")

        edges = unique_edges(topology.tets) if max(tvs) > 0 else None
        solve = dict(weights=weights, relaxation=config.relaxation, x0=x, edges=edges,
                     deadline=deadline, callback=record)
        subset = len(cameras) if solver == "sirt" else 1
        if solver == "lsqr":
            x = least_squares(projector, b, passes, weights, x, record)
        elif tuning and g == grids[-1]:
            from mi_tetvr.grid.slices import validation_split
            fit_views, val_views = validation_split(len(cameras), config.validation)
            trials, kept = [], {}
            # the tuning leaves a third of the time budget to the final solve
            tune_deadline = None if budget is None else \
                (lambda: now() - t_start > 0.6 * budget)
            for tv in tvs:
                held = HeldOut(projector, b, val_views,
                               patience=max_passes if config.passes else 3)
                sart(projector, b, max_passes, subset_size=min(subset, len(fit_views)), tv=tv,
                     views=fit_views, held_out=held, **{**solve, "deadline": tune_deadline})
                trials.append({"tv": tv, "passes": held.best[1], "held_out_mse": held.best[0],
                               "errors": held.errors})
                kept[tv] = held.best[2]
                if tune_deadline is not None and tune_deadline():
                    break
            best = min(trials, key=lambda r: r["held_out_mse"])
            log(f"held out {len(val_views)} of {len(cameras)} views: " + ", ".join(
                f"TV {r['tv']:g}: {r['passes']} passes, MSE {r['held_out_mse']:.3g}"
                for r in trials) + f"; all views with TV {best['tv']:g}, {best['passes']} "
                f"passes")
            tuned = {"validation_views": len(val_views), "tv": best["tv"],
                     "passes": best["passes"], "trials": trials}
            done = len(history["step"])
            x = sart(projector, b, best["passes"], subset_size=subset, tv=best["tv"],
                     stop_at_noise=False, **solve)
            if len(history["step"]) - done < best["passes"] and kept[best["tv"]] is not None:
                # out of time before all views were solved as long: the held-out run's best
                log("time ran out in the final solve: keeping the tuning's best attenuation")
                tuned["final"] = "time ran out: the tuning's best (without the held-out views)"
                x = kept[best["tv"]]
        else:
            x = sart(projector, b, passes, subset_size=subset, tv=tvs[0], **solve)
        prev = (g, x)
    bar.close()
    optimization = now() - train_begin
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2))
    state = RunState(rng=np.random.default_rng(config.seed), step=len(history["step"]),
                     elapsed=optimization, history=history)
    trainer = Trainer(dataset, v, t, config.for_stage(0), {"attenuation": x},
                      state=state, topology=topology)
    save_checkpoint(trainer, ckpt)
    result = write_outputs(trainer, out)
    result["solver"] = {"method": solver, "passes": len(history["step"]),
                        "weights": "Poisson counts" if weights is not None else "none",
                        "tuning": tuned}
    result["optimization_seconds"] = optimization
    result["wall_seconds"] = now() - t_start
    (out / "metrics.json").write_text(json.dumps(result, indent=2))
    return result
