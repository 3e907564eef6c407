"""Absorption tomography on tets as the linear problem it is.

The optical depth of a pixel's ray, ``b = -log(I / I0)``, is linear in the
per-vertex attenuation ``x``: ``b = A x`` with ``A[r, i]`` the integral along
ray ``r`` of vertex ``i``'s hat function (linear inside each tet). The tet
walk is ``A`` (``tetvr``'s ``absorption`` model with no early termination,
:class:`Projector`) and its reverse-mode derivative is ``A^T`` (the walk's
adjoint), so the classical algebraic methods run on the mesh as they run on
voxels:

* :class:`PenalizedLS` (the default, ``solver="pwls"``): penalized weighted
  least squares, the statistical model of log-transmission data (Poisson
  counts as weights) plus the exact total variation of the tets' linear
  field (smoothed by a hyperbola), by ordered subsets with separable
  quadratic surrogates and momentum; its weight chosen on held-out views;
* :func:`sart`: (ordered-subset) SART, Andersen and Kak 1984: per subset of
  views ``x += relaxation * (A_s^T W R (b_s - A_s x)) / (A_s^T W 1)`` with
  ``R`` the inverse row sums (each ray's length in the mesh) and ``W`` the
  statistical weights (Poisson counts; 1 without noise), ``x >= 0`` after
  each update. One view per subset is SART as scikit-image's ``iradon_sart``
  runs it per slice; all views in one subset is SIRT.
* :func:`least_squares`: CGLS/LSQR (``scipy.sparse.linalg.lsqr``) on the
  weighted operator :meth:`Projector.operator`, then ``x >= 0``.

The unknowns may be fewer than the walked vertices, ``x = E u``
(:func:`basis_matrix`): a one-row slab's tied layers, a grid's trilinear
field walked on tets of twice its cells (:func:`trilinear_grid`), or that of a
graded grid whose cells are split where the volume has detail
(:class:`~mi_tetvr.recon.octree.GradedGrid`).

The default was chosen by measurement (``benchmarks/bench_tomography.py``,
see ``benchmarks/README.md``). :class:`LinearCourse` is ``mi-tetvr fit
--model absorption``'s course in the fit's one pipeline
(:func:`mi_tetvr.recon.pipeline.run`): a tet mesh over the scanned box and the
solver, where an image fit has its steps; the same outputs as every fit.
"""
from __future__ import annotations

import copy
import dataclasses
import time

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["Projector", "depths", "statistical_weights", "sart", "least_squares",
           "TetGradient", "PenalizedLS", "tied_unknowns", "basis_matrix", "trilinear_grid",
           "coarse_grid", "adaptive_mesh",
           "aligned_resolution", "detector_cell", "LinearCourse", "DEFAULT_PASSES", "STALL",
           "HeldOut", "MAX_PASSES", "EDGE", "LAMBDA_DEFAULT", "LAMBDA_START", "LAMBDA_STEP",
           "LAMBDA_RANGE"]

#: Passes over the views when the config gives none: the solver's count where
#: the measured volume PSNR stopped rising (``benchmarks/bench_tomography.py``).
DEFAULT_PASSES = {"pwls": 24, "sart": 15, "sirt": 200, "lsqr": 12}
#: Held-out tuning: the most passes tried (the solve stops earlier once the
#: held-out views stop improving).
MAX_PASSES = {"sart": 30, "sirt": 300}
#: The default basis is trilinear where its walk (48 tets per grid cell) has at most
#: this many tets (a grid of about 70^3 cells, about 8 GB), else linear: a fit's memory
#: peaks at about 500 bytes per walked tet (2.8 GB on the 5.6M of a 47x61x41-cell grid's
#: walk, against 0.9 GB for the linear field's 0.7M tets).
TRILINEAR_TETS = 16_000_000
#: The trilinear field's ``--adapt``: the coarse grid, whose field only chooses the cells
#: to split (the graded grid starts from zero), is solved for this share of the passes
#: (at 24 views and 10^4 photons, a third against all of them: engine 32.87 against
#: 32.82 dB, head MR 31.44 against 31.52, phantom 34.83 against 34.84; the fit in 0.94-1.02x
#: the grid's time, where it took 1.2-1.3x; measured on the bisection walk before the
#: graded grid was walked as the grid is).
COARSE_PASSES = 1 / 3
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
    basis : (n,) int or scipy.sparse matrix (n, k), optional
        The vertices' values from the unknowns ``u``, ``x = E u``
        (:func:`basis_matrix`): each vertex's unknown (:func:`tied_unknowns`), or
        each vertex's weights on them (:func:`trilinear_grid`). ``A`` then acts
        on ``u`` and its adjoint is ``E^T A^T`` (default: one unknown per vertex).
    """

    KEY = "volume.vertex_opacity"

    def __init__(self, vertices, tets, cameras, topology=None, basis=None):
        import mitsuba as mi

        import mi_tetvr
        from mi_tetvr.mesh.topology import build_topology
        if topology is None:
            topology = build_topology(vertices, tets)
        self.basis = None if basis is None else basis_matrix(basis, len(vertices))
        self._basis_t = None if basis is None else self.basis.T.tocsr()
        self.vertices = len(vertices)
        self.n = len(vertices) if basis is None else self.basis.shape[1]
        # the shape's tets are the oriented ones: their topology is this one, built once
        shape = mi_tetvr.tetmesh_shape(
            mi_tetvr.tetmesh_dict(vertices, topology.tets, opacity=np.zeros(len(vertices)),
                                  model="absorption"),
            topology=dataclasses.replace(topology, n_flipped=0))
        # no early termination: the depth stays linear however large it gets
        self.scene = mi.load_dict({"type": "scene",
                                   "integrator": {"type": "tetvr", "min_transmittance": 0.0},
                                   "volume": shape})
        self.params = mi.traverse(self.scene)
        self.cameras = list(cameras)
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
        x = np.ravel(x) if self.basis is None else self.basis @ np.ravel(x)
        self.params[self.KEY] = mi.Float(np.asarray(x, np.float32))
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
        x = dr.zeros(mi.Float, self.vertices)
        dr.enable_grad(x)
        self.params[self.KEY] = x
        self.params.update()
        k = 0
        for i in views:
            image = mi.render(self.scene, self.params, sensor=self.sensors[i], spp=1)
            w = mi.Float(y[k:k + self.pixels[i]].astype(np.float32))
            k += self.pixels[i]
            dr.backward(dr.sum(-dr.log(1.0 - image[..., 3].array) * w))
        g = np.array(dr.grad(x), np.float64)
        self.params[self.KEY] = dr.detach(x)
        self.params.update()
        # E^T: each unknown gathers its vertices' derivatives
        return g if self.basis is None else self._basis_t @ g

    def operator(self, weights=None):
        """``W^(1/2) A`` as a ``scipy.sparse.linalg.LinearOperator`` (``W`` the
        statistical weights, identity by default)."""
        with needs("recon", "the absorption fit"):
            from scipy.sparse.linalg import LinearOperator
        s = None if weights is None else np.sqrt(np.asarray(weights, np.float64))
        return LinearOperator(
            self.shape, dtype=np.float64,
            matvec=lambda x: self.forward(np.ravel(x)) * (1 if s is None else s),
            rmatvec=lambda y: self.adjoint(np.ravel(y) * (1 if s is None else s)))


def tied_unknowns(vertices, axis: int = 2) -> np.ndarray:
    """One unknown per line of vertices along ``axis`` (those that share the
    other two coordinates): the unknowns of a slab one cell thick over a
    detector with one row, whose rays see only the mean of the slab's two
    vertex layers (their difference would be unknowns no ray measures).
    Returns each vertex's unknown, (n,) int."""
    v = np.asarray(vertices, np.float64)
    other = np.delete(v, axis, axis=1)
    scale = max(float(np.ptp(other)), 1e-30)
    _, inv = np.unique(np.round(other / scale * 1e9).astype(np.int64), axis=0,
                       return_inverse=True)
    return inv.ravel().astype(np.int64)


def basis_matrix(basis, vertices: int):
    """:class:`Projector`'s ``basis`` as a CSR matrix ``E`` (``vertices`` rows, one
    column per unknown): an int array (each vertex's unknown) gives a 1 per row."""
    with needs("recon", "the absorption fit"):
        from scipy.sparse import csr_matrix, issparse
    if issparse(basis):
        E = csr_matrix(basis, dtype=np.float64)
    else:
        index = np.asarray(basis)
        if index.shape != (vertices,) or not np.issubdtype(index.dtype, np.integer) or \
                index.min() < 0:
            raise ValueError(f"basis must be {vertices} unknown indices >= 0 or a sparse "
                             f"matrix, got an array of shape {index.shape}, {index.dtype}")
        E = csr_matrix((np.ones(vertices), (np.arange(vertices), index)),
                       shape=(vertices, int(index.max()) + 1))
    if E.shape[0] != vertices:
        raise ValueError(f"basis has {E.shape[0]} rows for {vertices} vertices")
    return E


def trilinear_grid(box, resolution: int):
    """The tets that walk the trilinear field of :func:`~mi_tetvr.mesh.initial.grid_init`
    ``(box, resolution)``'s vertex values: a grid of twice its cells per axis whose
    vertices take that field's values (the grid's own vertices theirs; an edge's,
    a face's, a cell's midpoint the mean of its 2, 4, 8), so the walked field, linear
    in each small tet, interpolates the trilinear one. Its error against the
    trilinear field is a quarter of the grid's own tets' (h^2 scaling), and unlike
    theirs it has no preferred diagonal (each cell's Kuhn split).

    Returns
    -------
    vertices : (N, 3) float64
    tets : (M, 4) int64
    basis : scipy.sparse.csr_matrix (N, n)
        Each vertex's trilinear weights on the grid's ``n`` vertices
        (:class:`Projector`'s ``basis``).
    """
    from mi_tetvr.mesh.initial import grid_shape
    from mi_tetvr.mesh.topology import check_bounds
    from mi_tetvr.recon.octree import half_cell_walk
    box = check_bounds(box)
    return half_cell_walk(box[0], box[1], grid_shape(box, resolution))


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
         relaxation: float = 1.0, x0=None, deadline=None, callback=None, views=None,
         held_out: HeldOut | None = None, stop_at_noise: bool = True):
    """Ordered-subset SART with ``x >= 0`` (``subset_size`` views per update;
    all of them: SIRT).

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


class TetGradient:
    """The gradient of the piecewise-linear field in each tet, ``G`` (3m, n),
    and the total variation built on it.

    A field linear in each tet has a constant gradient there, ``G_t x`` (the
    barycentric gradients of its 4 vertices), so its total variation is
    exactly ``sum_t vol_t |G_t x|``: isotropic, and the same on a graded mesh
    as on a grid (small tets weigh little). :meth:`penalty` is its smooth
    (hyperbola) form, ``sum_t vol_t psi(|G_t x|)`` with
    ``psi(s) = delta^2 (sqrt(1 + (s / delta)^2) - 1)``: quadratic for
    gradients under ``delta``, linear (total variation) above, so that noise
    is smoothed and edges kept (an edge-preserving potential of the
    penalized-likelihood CT literature, e.g. Fessler's).

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    unknowns : (n,) int, optional
        Each vertex's unknown, as :class:`Projector`'s: ``G`` then acts on them
        (weights on them: :meth:`on`).
    """

    def __init__(self, vertices, tets, unknowns=None):
        with needs("recon", "the absorption fit"):
            from scipy.sparse import csr_matrix
        v = np.asarray(vertices, np.float64)
        t = np.asarray(tets, np.int64)
        edges = v[t[:, 1:]] - v[t[:, :1]]                       # (m, 3, 3), rows: edges
        det = np.linalg.det(edges)
        bad = np.abs(det) <= 1e-12 * np.max(np.abs(edges)) ** 3
        if np.any(bad):
            raise ValueError(f"{int(bad.sum())} flat tets: the field's gradient is undefined")
        inv = np.linalg.inv(edges)                              # columns: grad lambda_1..3
        grads = np.concatenate([-inv.sum(2, keepdims=True), inv], axis=2)   # (m, 3, 4)
        m, n = len(t), len(v)
        rows = np.repeat((3 * np.arange(m)[:, None] + np.arange(3))[:, :, None], 4, axis=2)
        cols = np.broadcast_to(t[:, None, :], (m, 3, 4))
        self.volumes = np.abs(det) / 6.0
        if unknowns is not None:
            cols = np.asarray(unknowns, np.int64)[cols]
            n = int(np.max(unknowns)) + 1
        self._set(csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n)))

    def _set(self, G):
        self.G = G
        self.G_abs = abs(self.G)
        self._row_abs = np.asarray(self.G_abs.sum(axis=1)).ravel()
        self._abs_T = self.G_abs.T.tocsr()
        self._T = self.G.T.tocsr()

    def on(self, basis) -> TetGradient:
        """This gradient acting on unknowns ``u`` whose vertex values are ``x = E u``
        (``basis``: a scipy.sparse matrix, as :class:`Projector`'s)."""
        other = copy.copy(self)
        other._set((self.G @ basis).tocsr())
        return other

    def total_variation(self, x) -> float:
        """``sum_t vol_t |G_t x|``."""
        g = (self.G @ np.asarray(x, np.float64)).reshape(-1, 3)
        return float(np.sum(self.volumes * np.linalg.norm(g, axis=1)))

    def penalty(self, x, delta: float):
        """The smooth total variation at ``x``: ``(value, gradient (n,),
        curvature (n,))``, the curvature a diagonal bound of Huber's quadratic
        majorizer (``G^T diag(vol psi'(s) / s) G``, bounded row by row by
        ``|G|^T diag(...) |G| 1``): a separable surrogate's denominator."""
        g = (self.G @ np.asarray(x, np.float64)).reshape(-1, 3)
        s = np.linalg.norm(g, axis=1)
        q = np.sqrt(1.0 + (s / delta) ** 2)
        omega = np.repeat(self.volumes / q, 3)
        value = float(np.sum(self.volumes * delta * delta * (q - 1.0)))
        return value, self._T @ (omega * g.ravel()), self._abs_T @ (omega * self._row_abs)

    def hessian_diagonal(self, x, delta: float) -> np.ndarray:
        """(n,) the diagonal of the smooth total variation's Hessian at ``x``,
        exactly: ``sum_t vol_t (|G_t e_i|^2 / q_t + (1 / q_t^3 - 1 / q_t) (u_t . G_t
        e_i)^2)``, ``q_t = sqrt(1 + (s_t / delta)^2)``, ``u_t`` the unit gradient (the
        Hessian of ``psi(|g|)`` is ``I / q + (1 / q^3 - 1 / q) u u^T``)."""
        with needs("recon", "the total variation's curvature"):
            from scipy.sparse import csr_matrix
        g = (self.G @ np.asarray(x, np.float64)).reshape(-1, 3)
        s = np.linalg.norm(g, axis=1)
        q = np.sqrt(1.0 + (s / delta) ** 2)
        u = g / np.maximum(s, 1e-300)[:, None]
        first = self.G.multiply(self.G).T @ np.repeat(self.volumes / q, 3)
        m = len(s)
        # rows 3t + k scaled by u_tk and summed over k: u_t . G_t e_i
        sums = csr_matrix((u.ravel(), (np.repeat(np.arange(m), 3), np.arange(3 * m))),
                          shape=(m, 3 * m)) @ self.G
        second = sums.multiply(sums).T @ (self.volumes * (q ** -3 - 1.0 / q))
        return np.asarray(first + second).ravel()

    def curvature_scale(self) -> np.ndarray:
        """The penalty's curvature where the field is flat (its largest)."""
        return self._abs_T @ (np.repeat(self.volumes, 3) * self._row_abs)


#: The hyperbola's corner ``delta`` of :class:`PenalizedLS`: this fraction of
#: the unregularized start's 99.5th percentile per cell (measured on the head
#: MR at 24 views and 10^4 photons: 0.02 gave 31.84 dB, 0.005 and 0.1 at
#: their best weights 31.2 and 31.0).
EDGE = 0.02
#: Held-out tuning of the penalty weight: the first weights tried, and the
#: factor between neighbours (the search walks on while the held-out error
#: falls, within ``LAMBDA_RANGE``).
LAMBDA_START = (0.1, 0.3, 0.03)
#: The penalty's relative weight by default. Relative to the count-weighted data's
#: curvature, one value holds across noise levels, view counts and arcs: measured
#: against the volume (engine, head MR, phantom; noise-free, 10^5 and 10^4 photons; 24
#: and 64 views; 90 degrees), 0.1 was the best weight tried, or within 1 dB of it, where
#: the weight chosen on held-out views fell 0.6-1.3 dB below it at low noise.
LAMBDA_DEFAULT = 0.1
LAMBDA_STEP = 3.0
LAMBDA_RANGE = (1e-3, 10.0)


class PenalizedLS:
    """Penalized weighted least squares on the tets,
    ``min_{x >= 0} 1/2 sum_i w_i (b_i - [A x]_i)^2 + beta TV_delta(x)``
    (``TV_delta``: :meth:`TetGradient.penalty`), by ordered subsets of views
    with separable quadratic surrogates (OS-SQS: Erdogan and Fessler 1999,
    "Ordered subsets algorithms for transmission tomography"): per subset
    ``s`` of ``M``

    ``x <- max(0, z - (M A_s^T W_s (A_s z - b_s) + beta grad R(z)) / (d + beta c(z)))``

    with ``d = A^T W A 1`` the data term's separable curvature and ``c`` the
    penalty's, and Nesterov's momentum from pass to pass (``z``; momentum per
    subset diverged with 12 subsets, as Kim, Ramani and Fessler 2015 warn).
    ``W`` are the Poisson counts (:func:`statistical_weights`), the right
    weights of log-transmission data (Sauer and Bouman 1993); 1 without noise.

    The weight is relative, ``beta = lam * beta0``, ``beta0`` the ratio of
    the data's mean curvature to the penalty's where the field is flat: at
    ``lam`` 1 the penalty is as stiff as the data for small gradients.
    ``delta`` is :data:`EDGE` times the unregularized start's 99.5th
    percentile per cell (:meth:`start`).

    Parameters
    ----------
    projector : Projector
    b : (rays,) float
        Optical depths (:func:`depths`).
    weights : (rays,) float or None
    gradient : TetGradient
    views : list of int, optional
        The projector's views fitted (default all).
    subsets : int
        ``M`` (at most the views; each subset interleaves views spread over
        the scan).
    reference : (beta0, cell) or (beta0, cell, E), optional
        Another mesh's ``beta0`` and cell size (:func:`grid_penalty_scale`:
        the detector's grid) for this one's: the weight and the corner are then
        absolute, the same penalty as on that mesh. ``E`` (sparse, that grid's
        vertices by these unknowns): the grid's values, whose percentile sets
        ``delta`` (a graded grid's unknowns crowd where the volume has
        detail). A graded mesh's own mean curvatures are its coarse cells'
        (the data's grows as ``h^3``, the penalty's as ``h``: 4 times the ratio
        at twice the cell): its ``beta0`` would be larger, the penalty stiffer
        where it is fine.
    """

    def __init__(self, projector: Projector, b, weights, gradient: TetGradient, views=None,
                 subsets: int = 12, reference=None):
        self.projector, self.gradient = projector, gradient
        self.b = np.asarray(b, np.float64)
        self.w = np.ones_like(self.b) if weights is None else np.asarray(weights, np.float64)
        self.views = np.arange(len(projector.sensors)) if views is None else np.asarray(views)
        m = max(1, min(int(subsets), len(self.views)))
        self.groups = [np.sort(self.views[k::m]) for k in range(m)]
        self.order = np.random.default_rng(0).permutation(m)
        rows = projector.rows(self.views)
        self.d = projector.adjoint(self.w[rows] * projector.forward(np.ones(projector.n),
                                                                     self.views), self.views)
        self.beta0 = float(np.mean(self.d)) / max(float(np.mean(gradient.curvature_scale())),
                                                  1e-30)
        cell = float(np.cbrt(6.0 * np.median(gradient.volumes)))   # a Kuhn cube's side
        self.values = None
        if reference is not None:
            self.beta0, cell = (float(r) for r in reference[:2])
            self.values = reference[2] if len(reference) > 2 else None
        self.delta, self.cell = None, cell

    def start(self, passes: int = 2, x0=None, callback=None):
        """Unregularized passes from ``x0`` (default 0); sets ``delta`` from
        their result, which it returns."""
        x = self.solve(0.0, passes, x0, callback=callback)
        grid = x if self.values is None else self.values @ x
        self.delta = EDGE * max(float(np.percentile(grid, 99.5)), 1e-12) / self.cell
        return x

    def solve(self, lam: float, passes: int, x0=None, held_out: HeldOut | None = None,
              deadline=None, callback=None):
        """``passes`` passes at relative weight ``lam`` from ``x0`` (default
        0). ``held_out`` stops once its views stop improving and returns their
        best ``x``; ``deadline()`` True stops; ``callback`` as :func:`sart`'s."""
        if lam > 0 and self.delta is None:
            raise ValueError("call start() first: the penalty's corner comes from its result")
        pr, b, w, m = self.projector, self.b, self.w, len(self.groups)
        beta = lam * self.beta0
        x = np.zeros(pr.n) if x0 is None else np.maximum(np.asarray(x0, np.float64), 0.0)
        z, t = x.copy(), 1.0
        n_rays = len(pr.rows(self.views))
        for p in range(passes):
            sq, total, t_sq = 0.0, 0.0, 0.0
            x_pass = x.copy()
            for k in self.order:
                s = self.groups[k]
                r = pr.rows(s)
                ax = pr.forward(z, s)
                res = ax - b[r]
                sq += float(np.sum(w[r] * res * res))
                total += float(np.sum(w[r]))
                t_sq += float(np.sum((np.exp(-ax) - np.exp(-b[r])) ** 2))
                num, den = m * pr.adjoint(w[r] * res, s), self.d
                if beta > 0:
                    _, g, c = self.gradient.penalty(z, self.delta)
                    num, den = num + beta * g, den + beta * c
                z = x = np.maximum(z - num / np.maximum(den, 1e-30), 0.0)
                if deadline is not None and deadline():
                    break
            t_new = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t * t))
            z = x + ((t - 1.0) / t_new) * (x - x_pass)
            t = t_new
            if callback is not None:
                callback(p, x, np.sqrt(sq / max(total, 1e-30)), t_sq / n_rays)
            if deadline is not None and deadline():
                break
            if held_out is not None and held_out(p + 1, x):
                break
        if held_out is not None and held_out.best[2] is not None:
            return held_out.best[2]
        return x

    def tune(self, held_out_views, passes: int, x0=None, deadline=None, callback=None,
             lams=None, first=LAMBDA_START):
        """The relative weight whose solution best predicts ``held_out_views``
        (mean squared transmittance error): ``first`` (:data:`LAMBDA_START`), then
        on by :data:`LAMBDA_STEP` from the best while the error falls (only
        ``lams`` when given). The first trial runs ``passes`` passes from
        ``x0``, each other half as many from the solution of the nearest
        weight tried (continuation); each is scored once solved, so that no
        weight wins by being stopped early. Returns ``(best trial, trials)``:
        a trial is ``{"lam", "passes", "held_out_mse", "x"}``."""
        trials = {}
        target = np.exp(-self.b[self.projector.rows(held_out_views)])

        def trial(lam):
            near = min(trials.values(), key=lambda r: abs(np.log(r["lam"] / lam)),
                       default=None)
            n = passes if near is None else max(1, passes // 2)
            x = self.solve(lam, n, x0 if near is None else near["x"], deadline=deadline,
                           callback=callback)
            err = np.exp(-self.projector.forward(x, held_out_views)) - target
            trials[lam] = {"lam": lam, "passes": n, "held_out_mse": float(np.mean(err * err)),
                           "x": x}

        def best():
            return min(trials.values(), key=lambda r: r["held_out_mse"])

        def out_of_time():
            return deadline is not None and deadline()

        for lam in first if lams is None else lams:
            if trials and out_of_time():
                break
            trial(lam)
        lo, hi = LAMBDA_RANGE
        while lams is None and not out_of_time():
            # the best at an end of what was tried: one step beyond it
            tried, lam = sorted(trials), best()["lam"]
            if lam == tried[0] and lam / LAMBDA_STEP >= lo:
                trial(lam / LAMBDA_STEP)
            elif lam == tried[-1] and lam * LAMBDA_STEP <= hi:
                trial(lam * LAMBDA_STEP)
            else:
                break
        return best(), sorted(trials.values(), key=lambda r: r["lam"])


def least_squares(projector: Projector, b, iterations: int, weights=None, x0=None,
                  callback=None):
    """CGLS/LSQR (``scipy.sparse.linalg.lsqr``) on ``W^(1/2) A x = W^(1/2) b``
    for ``iterations`` iterations (early stopping is its regularization),
    then ``x >= 0``. ``callback(iterations, x, residual, mse)`` once at the end
    (as :func:`sart`'s, of the final ``x``)."""
    with needs("recon", "the absorption fit"):
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


def coarse_grid(box, resolution: int):
    """A grid of half the cells of ``grid_init(box, resolution)`` per axis
    whose vertices are every other vertex of that grid (the box extended by
    one fine cell along an axis with an odd count): what :func:`adaptive_mesh`
    refines back to the fine grid's vertices where it splits."""
    from mi_tetvr.mesh.generate import grid_mesh
    from mi_tetvr.mesh.initial import grid_shape
    box = np.asarray(box, np.float64)
    fine = np.asarray(grid_shape(box, resolution))
    cell = (box[1] - box[0]) / fine
    half = (fine + 1) // 2
    v, t = grid_mesh(tuple(int(c) for c in half), box[0], box[0] + 2 * half * cell)
    return v.astype(np.float64), t.astype(np.int64)


def adaptive_mesh(vertices, tets, x, gradient: TetGradient, budget: int):
    """Unknowns where the field has detail: the vertices of ``tets`` are
    ranked by the largest change of ``x`` across a tet around them
    (``|G_t x| h_t``, ``h_t`` the tet's size) and the edges about the
    top-ranked ones split (:func:`~mi_tetvr.mesh.refine.split_vertices`,
    conforming), as many as keep the vertex count within ``budget``. On
    :func:`coarse_grid` the midpoints are the fine grid's vertices: flat
    regions keep the coarse cells, detailed ones get the fine vertices.

    Returns
    -------
    vertices, tets, x (the field at the new vertices, linear: exact), the
    number of vertices split about.
    """
    from mi_tetvr.mesh.refine import split_vertices
    from mi_tetvr.mesh.topology import unique_edges
    change = np.linalg.norm((gradient.G @ x).reshape(-1, 3), axis=1) * \
        np.cbrt(6.0 * gradient.volumes)
    score = np.zeros(len(vertices))
    np.maximum.at(score, np.asarray(tets).ravel(), np.repeat(change, 4))
    order = np.argsort(-score, kind="stable")
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    # an edge gets a midpoint once either end is among the first k: the vertex count
    # after splitting about the first k is n + #edges whose first end ranks below k
    edges = unique_edges(tets)
    first = np.sort(np.minimum(rank[edges[:, 0]], rank[edges[:, 1]]))
    k = np.arange(len(order) + 1)
    count = len(vertices) + np.searchsorted(first, k, side="left")
    k = int(k[count <= budget].max()) if count[0] <= budget else 0
    res = split_vertices(vertices, tets, order[:k], {"x": x})
    return res.vertices, res.tets, res.point_data["x"], k


def grid_penalty_scale(box, resolution, cameras, b, weights):
    """:class:`PenalizedLS`'s ``(beta0, cell)`` on ``grid_init(box, resolution)``:
    the penalty a mesh graded from that grid's vertices (:func:`adaptive_mesh`)
    keeps (its ``reference``). One pass's worth of projections on the grid."""
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.mesh.topology import build_topology
    v, t = grid_init(box, resolution)
    topology = build_topology(v, t)
    pls = PenalizedLS(Projector(v, topology.tets, cameras, topology), b, weights,
                      TetGradient(v, topology.tets))
    return pls.beta0, pls.cell


def fine_penalty_scale(projector, weights, gradient):
    """:class:`PenalizedLS`'s ``(beta0, cell)`` with one unknown per vertex of
    ``gradient``'s grid (its plain :class:`TetGradient`), from a ``projector`` over the
    same box with any basis whose rows sum to 1 (:class:`~mi_tetvr.recon.octree.GradedGrid`'s):
    the data's curvatures ``A^T W A 1`` then sum to ``sum_i w_i L_i^2`` (``L_i`` a
    ray's length in the box) whatever the unknowns, so one projection gives their
    mean over the grid's vertices. The penalty a graded grid keeps, as
    :func:`grid_penalty_scale`'s."""
    length = projector.forward(np.ones(projector.n))
    w = np.ones_like(length) if weights is None else np.asarray(weights, np.float64)
    d = float(np.sum(w * length * length)) / gradient.G.shape[1]
    return (d / max(float(np.mean(gradient.curvature_scale())), 1e-30),
            float(np.cbrt(6.0 * np.median(gradient.volumes))))


def _pwls_stage(projector, b, weights, gradient, x0, config, passes, tune, tune_deadline,
                solve, log, near=None, reference=None):
    """One mesh's :class:`PenalizedLS` solve for :class:`LinearCourse`:
    with ``tune``, the penalty weight searched on every
    ``config.solver.validation``-th view held out, then all views from the
    tuning's solution (the search starts about ``near``, an earlier mesh's
    weight, when given); else ``config.solver.tv`` (default :data:`LAMBDA_DEFAULT`)
    for ``passes``. Returns ``(x, record)``: the weight (``tv``), how it was
    chosen, the absolute weight ``beta`` and corner ``delta`` solved with, and the
    tuning's trials. ``reference``: :class:`PenalizedLS`'s."""
    if not tune:
        pls = PenalizedLS(projector, b, weights, gradient, reference=reference)
        start = pls.start(x0=x0, callback=solve["callback"])
        given = isinstance(config.solver.tv, (int, float))
        lam = config.solver.tv if given else LAMBDA_DEFAULT
        log(f"penalty weight {lam:g} ({'given' if given else 'the default rule'})")
        return pls.solve(lam, passes, start, **solve), \
            {"tv": lam, "chosen": "given" if given else "the default rule",
             "beta": lam * pls.beta0, "delta": pls.delta}
    from mi_tetvr.grid.slices import validation_split
    fit_views, val_views = validation_split(len(projector.cameras), config.solver.validation)
    pls = PenalizedLS(projector, b, weights, gradient, views=fit_views, reference=reference)
    start = pls.start(x0=x0, callback=solve["callback"])
    best, trials = pls.tune(val_views, passes, start, deadline=tune_deadline,
                            callback=solve["callback"],
                            first=LAMBDA_START if near is None else
                            (near, near * LAMBDA_STEP, near / LAMBDA_STEP))
    log(f"held out {len(val_views)} of {len(projector.cameras)} views: " + ", ".join(
        f"weight {r['lam']:g}: MSE {r['held_out_mse']:.4g}" for r in trials)
        + f"; all views with weight {best['lam']:g}")
    full = PenalizedLS(projector, b, weights, gradient, reference=reference)
    full.delta = pls.delta
    # on from the tuning's solution, with the held-out views back in
    x = full.solve(best["lam"], max(1, passes // 2), best["x"], **solve)
    record = {"validation_views": len(val_views), "tv": best["lam"],
              "chosen": "on held-out views", "delta": pls.delta,
              "beta": best["lam"] * full.beta0,
              "trials": [{k: r[k] for k in ("lam", "passes", "held_out_mse")}
                         for r in trials]}
    return x, record


class LinearCourse:
    """The course of an X-ray fit with a linear solver (``mi-tetvr fit --model
    absorption``; ``config.solver.solver`` ``pwls``, ``sart``, ``sirt`` or ``lsqr``), run
    by :func:`mi_tetvr.recon.pipeline.run` where an image fit's steps run (its
    ``_Loop``), its outputs written by the same code (``attenuation.vtu``,
    ``metrics.json``, ``test/*.png``, ``progress.png``, ``checkpoint.npz``,
    ``config.json``, ``plan.json``): the plan of grids (coarse to fine, or a coarse grid
    and its adaptive refinement) and the solve on each.

    The grid's cells are the detector's pixels (:func:`detector_cell`) unless
    ``config.mesh.grid_resolution`` says otherwise; with ``config.strategy.stages`` of
    ``{"grid": r}`` entries each grid is solved in turn, starting from the previous
    one's field (coarse to fine). ``config.data.xray_flux`` or the data set's weights
    the rays by their counts. ``config.trainer.time_budget`` (minutes) bounds the
    passes; ``resume`` goes on from ``out``'s checkpoint."""

    def __init__(self, dataset, out, config, resume=True, progress=True, log=print,
                 now=time.perf_counter):
        from mi_tetvr.recon.plan import data_bounds
        self.t_start = self.train_begin = now()
        self.trainer = self.bar = None
        self.dataset, self.out, self.log, self.now = dataset, out, log, now
        self.progress = progress
        out.mkdir(parents=True, exist_ok=True)
        # the scanned box the data set records (a volume's), else the region the views show
        bounds = np.asarray(dataset.bbox, np.float64) if config.mesh.bounds is None and \
            dataset.bbox is not None else data_bounds(config.mesh, dataset)
        cell = detector_cell(dataset, bounds)
        minutes = config.trainer.time_budget
        self.budget = None if minutes is None else 60.0 * minutes
        self.solver = config.linear_solver
        self.passes = config.solver.passes or DEFAULT_PASSES[self.solver]
        flux = config.data.xray_flux if config.data.xray_flux is not None else dataset.xray_flux
        # the box a hair larger than the data's: rays along its faces run inside
        self.box = np.stack([bounds[0] - 1e-3 * cell, bounds[1] + 1e-3 * cell])
        self.resolution = config.mesh.grid_resolution or aligned_resolution(bounds, cell)
        self.config = config.replaced(bounds=np.asarray(bounds).tolist(),
                                      grid_resolution=self.resolution, xray_flux=flux)
        # coarse to fine: each stage's grid (one without: the fit's), the fit's last
        grids = [int(st.get("grid") or self.resolution) for st in (config.strategy.stages or [])]
        self.grids = [g for g in grids if g != self.resolution] + [self.resolution]
        self.ckpt = out / "checkpoint.npz"
        self.b = depths(dataset.train, flux)
        self.weights = statistical_weights(dataset.train, flux)
        self.cameras = [v.camera for v in dataset.train]
        self.history = {"step": [], "time": [], "loss": [], "psnr": []}
        self.one_row = all(c.height == 1 and c.is_orthographic for c in self.cameras)
        # held-out tuning (on the last grid) of the passes, and of pwls's penalty weight
        self.tuning = config.solver.validation > 0 and len(self.cameras) >= 6 and (
            (self.solver == "pwls" and config.solver.tv == "heldout") or
            (self.solver in ("sart", "sirt") and config.solver.passes is None))
        if self.solver == "pwls" and config.solver.tv == "heldout" and not self.tuning:
            log(f"{len(self.cameras)} views are too few to hold some out: the penalty's "
                f"weight by the default rule")
        self.max_passes = MAX_PASSES[self.solver] if self.tuning and self.solver != "pwls" \
            else self.passes
        self.saved = self.tuned = self.weight = self.reference = None
        self.octree = None                           # the graded grid (--adapt, trilinear)
        self.vertex_basis, self.basis_given = None, config.solver.basis
        self.set_basis(config.solver.basis or self.default_basis())
        self.x0 = self.resumed() if resume else None
        #: What the plan says of the budget (:func:`~mi_tetvr.recon.plan.write_settings`).
        self.said = dict(budget_seconds=self.budget)

    def run(self):
        """Solve (:meth:`solve`); :attr:`trainer` holds the attenuation (checkpointed)."""
        self.finish(*self.solve(self.x0))

    def close(self):
        if self.bar is not None:
            self.bar.close()

    def default_basis(self):
        """Trilinear where the grid's walk has at most :data:`TRILINEAR_TETS` tets (a
        graded grid's: its cells made even), else linear; logged."""
        from mi_tetvr.mesh.initial import grid_shape
        cells = np.asarray(grid_shape(self.box, self.resolution))
        if self.graded:
            cells = 2 * ((cells + 1) // 2)
        walked = 48 * int(np.prod(cells))
        why = f"its walk would have {walked:,} tets, more than {TRILINEAR_TETS:,}" \
            if walked > TRILINEAR_TETS else None
        basis = "trilinear" if why is None else "linear"
        self.log(f"basis {basis} (the default" + (f": {why})" if why else ")"))
        return basis

    def set_basis(self, basis):
        """The field between the unknowns, in the config the fit saves."""
        self.config = self.config.replaced(basis=basis)

    @property
    def trilinear(self):
        return self.config.solver.basis == "trilinear"

    def deadline(self, share):
        """A function that says when ``share`` of the time budget is spent (None: no budget)."""
        if self.budget is None:
            return None
        return lambda: self.now() - self.t_start > share * self.budget

    def resumed(self):
        """The checkpointed attenuation to go on from (None: none); its mesh is kept."""
        from mi_tetvr.recon.checkpoint import load_checkpoint
        from mi_tetvr.recon.checkpoint import check_resume
        if not self.ckpt.is_file():
            return None
        # the default basis is the saved fit's (linear before there was a choice)
        given = self.basis_given
        settings = check_resume(self.config.replaced(basis=given), self.ckpt)
        if given is None and (settings.get("basis") or "linear") != self.config.solver.basis:
            self.set_basis(settings.get("basis") or "linear")
            self.log(f"basis {self.config.solver.basis}: the resumed fit's")
        saved = load_checkpoint(self.ckpt, self.dataset, self.config)
        self.saved = saved.arrays()[:2]
        self.grids = self.grids[-1:]
        self.log(f"resumed from {self.ckpt}: more passes from its attenuation")
        return saved.arrays()[2]["attenuation"]

    @property
    def graded(self):
        """Whether the fit's meshes are graded (``--adapt`` with the penalized
        solver on a detector of more than one row): a coarse grid split where it
        has detail, or a resumed such mesh."""
        return (self.config.solver.adapt_share is not None and self.solver == "pwls"
                and not self.one_row)

    def plan(self, x0):
        """The meshes solved in turn, as ``(kind, grid resolution)``."""
        if self.config.solver.adapt_share is not None and not self.graded:
            self.log("adapt: " + ("a one-row detector's slab has no cells to coarsen"
                                  if self.one_row else f"solver {self.solver} solves on the grid"))
        if x0 is not None and not self.trilinear:
            if self.graded:
                self.log("adapt: the resumed fit goes on on its own mesh")
            return [("saved", self.resolution)]
        stages = [("grid", g) for g in self.grids]
        if self.graded:
            # the last grid's unknowns, spent where a grid of twice its cells finds detail
            # (the trilinear field's cells split anew from a resumed one's field)
            stages[-1:] = [("coarse", self.resolution)] * (x0 is None) + \
                [("adaptive", self.resolution)]
        return stages

    def progress_bar(self, progress, stages):
        from mi_tetvr.progress import progress_bar as tqdm
        total = 0
        for kind, g in stages:
            passes, tuned = self.stage_solve(kind, (kind, g) == stages[-1])
            if self.solver == "pwls":
                # the unregularized start's 2 passes, the tuning's trials, the solve
                total += 2 + (passes * (len(LAMBDA_START) + 2) // 2 if tuned else passes)
            else:
                total += self.max_passes * 2 if tuned else passes
        return tqdm(total=total, disable=not progress, unit="pass",
                    desc=f"{self.solver} ({len(self.cameras)} views)")

    def stage_solve(self, kind, last):
        """A planned mesh's passes (the trilinear field's coarse grid, whose field only
        chooses the cells to split: :data:`COARSE_PASSES` of the fit's) and whether they
        (and pwls's weight) are tuned on held-out views: on the last mesh and the coarse
        grid."""
        passes = max(2, round(COARSE_PASSES * self.passes)) \
            if kind == "coarse" and self.trilinear else self.passes
        return passes, self.tuning and (last or kind == "coarse")

    def mesh(self, kind, g, prev):
        """The vertices and tets of a planned mesh, and (adaptive) the field on it."""
        from mi_tetvr.mesh.initial import grid_init, grid_shape
        if self.trilinear and kind in ("coarse", "adaptive"):
            return self.graded_grid(kind, g, prev)
        if kind == "adaptive":
            grid_vertices = int(np.prod(np.asarray(grid_shape(self.box, g)) + 1))
            share = self.config.solver.adapt_share
            v, t, x, split = adaptive_mesh(*prev, int(share * grid_vertices))
            self.log(f"adaptive mesh: split about {split:,} of the coarse grid's "
                     f"{len(prev[0]):,} vertices, where its field changes most: {len(v):,} "
                     f"vertices ({len(v) / grid_vertices:.0%} of the grid's {grid_vertices:,})")
            return v, t, x
        if kind == "coarse":
            return (*coarse_grid(self.box, g), None)
        if kind == "saved":
            return (*self.saved, None)
        return (*grid_init(self.box, g), None)

    def graded_grid(self, kind, g, prev):
        """The trilinear field's graded grid (:class:`~mi_tetvr.recon.octree.GradedGrid`,
        :attr:`octree`) over the cells of ``grid_init(box, g)``, two per coarse cell: none
        split (``coarse``), or split where ``prev``'s field changes most, within
        ``config.solver.adapt`` of the grid's unknowns. Returns the fine grid's vertices and
        tets (its penalty's) and the field to start from: none after the coarse grid
        (whose field only chooses the cells split: the graded grid starts from zero, as
        the grid does), a resumed fit's on its vertices."""
        from mi_tetvr.mesh.initial import grid_shape
        from mi_tetvr.mesh.sample import sample_field
        from mi_tetvr.recon.octree import GradedGrid, fine_mesh
        fine = np.asarray(grid_shape(self.box, g))
        cell, coarse = (self.box[1] - self.box[0]) / fine, (fine + 1) // 2
        if kind == "coarse":
            self.octree = GradedGrid.uniform(self.box[0], cell, coarse)
            return (*self.octree.fine_mesh(), None)
        v, t = fine_mesh(self.box[0], cell, 2 * coarse)
        # after the coarse grid its field is on these vertices; a resumed walk's, sampled
        resumed = self.octree is None
        u = sample_field(*prev[:3], v) if resumed else prev[2]
        grid = int(np.prod(fine + 1))                  # the grid's unknowns
        self.octree = GradedGrid.refined(self.box[0], cell, coarse, u,
                                         int(self.config.solver.adapt_share * grid))
        split = self.octree.split
        self.log(f"adaptive grid: split {int(split.sum()):,} of the {split.size:,} coarse "
                 f"cells, where the field changes most: {self.octree.n:,} unknowns "
                 f"({self.octree.n / grid:.0%} of the grid's {grid:,})")
        return v, t, u if resumed else None

    def solve(self, x0):
        """Every planned mesh solved in turn, each from the last one's field. Returns
        the last mesh's ``(vertices, tets, topology, attenuation)``."""
        from mi_tetvr.mesh.initial import grid_shape
        from mi_tetvr.mesh.sample import sample_field
        from mi_tetvr.mesh.topology import build_topology
        stages = self.plan(x0)
        self.bar = self.progress_bar(self.progress, stages)
        if self.graded and not self.trilinear:
            # the coarse and the graded mesh (a resumed one too) keep the penalty of the
            # grid they stand for (the trilinear field's: :meth:`penalty`)
            self.reference = grid_penalty_scale(self.box, stages[-1][1], self.cameras, self.b,
                                                self.weights)
        self.train_begin = self.now()
        x, prev, lam = x0, None, None
        if x0 is not None and self.trilinear:
            # the saved walk's field, sampled at the grid's vertices (where it is exact)
            prev, x = (*self.saved, x0), None
        for kind, g in stages:
            last = (kind, g) == stages[-1]
            v, t, adapted = self.mesh(kind, g, prev)
            topology = build_topology(v, t)
            graded = self.trilinear and kind in ("coarse", "adaptive")
            # a slab over a one-row detector: one unknown per vertical pair of vertices
            unknowns = self.octree.P if graded else tied_unknowns(v) \
                if self.one_row and grid_shape(self.box, g)[2] == 1 else None
            walk = self.walk(v, t, topology, g, unknowns, last, graded)
            if kind == "adaptive":
                x = adapted                          # None: the graded grid from zero
            elif prev is not None:
                x = sample_field(*prev[:3], v)
            if x is not None and unknowns is not None:
                x = x[self.octree.free] if graded else \
                    np.bincount(unknowns, x) / np.bincount(unknowns)
            self.projector = Projector(*walk[:2], self.cameras, *walk[2:])
            gradient = self.penalty(v, topology, unknowns, graded)
            # a graded grid's corner from its fine grid's values
            reference = (*self.reference, unknowns) if graded else self.reference
            x, lam = self.solve_mesh(x, gradient, *self.stage_solve(kind, last), lam,
                                     reference)
            if unknowns is not None:
                x = unknowns @ x if graded else x[unknowns]       # the vertices' values
            prev = (v, topology.tets, x, gradient)
        if self.trilinear:
            # the walked mesh and its values: the field the projections were fitted with
            return *walk[:3], self.vertex_basis @ x
        return v, t, topology, x

    def penalty(self, v, topology, unknowns, graded):
        """pwls's :class:`TetGradient` on the mesh's tets, on its unknowns (None for
        the other solvers). A graded grid's is its fine grid's on the unknowns, its
        weight that grid's (:func:`fine_penalty_scale`, :attr:`reference`)."""
        if self.solver != "pwls":
            return None
        if not graded:
            return TetGradient(v, topology.tets, unknowns)
        fine = TetGradient(v, topology.tets)
        if self.reference is None:
            self.reference = fine_penalty_scale(self.projector, self.weights, fine)
        return fine.on(unknowns)

    def walk(self, v, t, topology, g, unknowns, last, graded=False):
        """The tets the projections walk and the unknowns' basis on them, as
        :class:`Projector`'s ``(vertices, tets, topology, basis)``: the grid's own tets
        and its vertices (tied on a slab), :func:`trilinear_grid`'s, or (``graded``)
        :attr:`octree`'s. Logs the last mesh's summary."""
        from mi_tetvr.mesh.topology import build_topology, format_summary, geometry_summary
        basis = unknowns
        if self.trilinear:
            v, t, basis = self.octree.walk() if graded else trilinear_grid(self.box, g)
            topology = build_topology(v, t)
            self.vertex_basis = basis                # on the grid's vertices, not tied
            if unknowns is not None:
                basis = basis @ basis_matrix(unknowns, basis.shape[1])
        if last:
            self.log(format_summary(geometry_summary(v, topology)))
            if unknowns is not None and not graded:
                self.log(f"one detector row: {unknowns.max() + 1:,} unknowns, the slab's "
                         f"two vertex layers alike")
            if self.trilinear:
                self.log(f"basis trilinear: the {'graded ' * graded}grid's {basis.shape[1]:,} "
                         f"unknowns, their trilinear field walked on {len(t):,} tets")
        return v, t, topology, basis

    def record(self, p, x, residual, mse):
        """A pass done: the history and the progress bar."""
        from mi_tetvr.recon.metrics import psnr
        h = self.history
        h["step"].append(len(h["step"]) + 1)
        h["time"].append(self.now() - self.train_begin)
        h["loss"].append(residual ** 2)
        h["psnr"].append(psnr(mse))        # the training projections'
        self.bar.update(1)
        self.bar.set_postfix(residual=f"{residual:.3g}")

    def solve_mesh(self, x, gradient, passes, tune, lam, reference=None):
        """The solver on the current projector from ``x`` for ``passes``, its passes
        (and pwls's weight, near ``lam``) tuned on held-out views when ``tune``; pwls's
        penalty scaled by ``reference`` (:class:`PenalizedLS`'s). Returns the
        attenuation and the weight chosen."""
        projector, b, weights, config = self.projector, self.b, self.weights, self.config
        solve = dict(deadline=self.deadline(0.9), callback=self.record)
        if self.solver == "lsqr":
            return least_squares(projector, b, passes, weights, x, self.record), lam
        if self.solver == "pwls":
            # the tuning leaves a third of the time budget to the final solve
            x, record = _pwls_stage(projector, b, weights, gradient, x, config, passes,
                                    tune, self.deadline(0.6), solve, self.log, near=lam,
                                    reference=reference)
            # (the penalty's absolute weight and corner: what its curvature needs)
            self.weight = {k: record[k] for k in ("tv", "chosen", "beta", "delta")}
            self.tuned = record if tune else None
            return x, record["tv"]
        subset = len(self.cameras) if self.solver == "sirt" else 1
        if tune:
            return self.tuned_sart(x, subset, solve), lam
        return sart(projector, b, passes, weights, subset_size=subset, x0=x,
                    relaxation=config.solver.relaxation, **solve), lam

    def tuned_sart(self, x, subset, solve):
        """SART/SIRT: the passes chosen on held-out views, then all views solved as long
        (or, out of time before that, the held-out run's best)."""
        from mi_tetvr.grid.slices import validation_split
        projector, b, weights, config = self.projector, self.b, self.weights, self.config
        fit_views, val_views = validation_split(len(self.cameras), config.solver.validation)
        held = HeldOut(projector, b, val_views, patience=3)
        kept = sart(projector, b, self.max_passes, weights,
                    subset_size=len(fit_views) if self.solver == "sirt" else 1, x0=x,
                    relaxation=config.solver.relaxation, views=fit_views, held_out=held,
                    deadline=self.deadline(0.6), callback=self.record)
        self.log(f"held out {len(val_views)} of {len(self.cameras)} views: {held.best[1]} "
                 f"passes, MSE {held.best[0]:.3g}; all views as long")
        self.tuned = {"validation_views": len(val_views), "passes": held.best[1],
                      "trials": [{"passes": held.best[1], "held_out_mse": held.best[0],
                                  "errors": held.errors}]}
        done = len(self.history["step"])
        x = sart(projector, b, held.best[1], weights, subset_size=subset, x0=x,
                 relaxation=config.solver.relaxation, stop_at_noise=False, **solve)
        if len(self.history["step"]) - done < held.best[1]:
            # out of time before all views were solved as long: the held-out run's best
            self.log("time ran out in the final solve: keeping the tuning's best attenuation")
            self.tuned["final"] = "time ran out: the tuning's best (without the held-out views)"
            x = kept
        return x

    def finish(self, v, t, topology, x):
        """The fit as a :class:`~mi_tetvr.recon.trainer.Trainer` on the last mesh
        (:attr:`trainer`, what the outputs are written from), checkpointed."""
        from mi_tetvr.recon.checkpoint import save_checkpoint
        from mi_tetvr.recon.trainer import RunState, Trainer
        config, history = self.config, self.history
        state = RunState(rng=np.random.default_rng(config.trainer.seed),
                         step=len(history["step"]), elapsed=self.now() - self.train_begin,
                         history=history)
        self.trainer = Trainer(self.dataset, v, t, config.for_stage(0), {"attenuation": x},
                               state=state, topology=topology)
        save_checkpoint(self.trainer, self.ckpt)

    def metrics(self, seconds):
        """What the solver adds to the fit's metrics: its unknowns and its solve."""
        return {"unknowns": self.projector.n,
                "solver": {"method": self.solver, "passes": len(self.history["step"]),
                           "weights": "Poisson counts" if self.weights is not None else "none",
                           "basis": self.config.solver.basis, "tuning": self.tuned,
                           **({"penalty": self.weight} if self.weight else {})}}
