"""A scalar field whose transfer-function colors match given ones: the start
of a scalar reconstruction under a known transfer function.

Fitting the scalar directly is non-convex when the transfer function is not
monotonic (DiffDVR Sec. 5.4, Fig. 12: beyond a peak the gradient points away
from the solution). DiffDVR's remedy, built here: fit per-vertex colors and
opacities first (a convex-enough problem), then give every vertex the scalar
whose classified color and extinction match its fitted ones
(:func:`match_scalars`, DiffDVR Eq. 13), then fit the scalar from there.

Eq. 13 per vertex ``i`` and candidate value ``d`` (normalised to [0, 1]):
``|C_i - C(d)|^2 + alpha log(1 + |tau_i - tau(d)|) + beta sum_j (d - d_j)^2``
over the mesh neighbours ``j`` (edges), with ``alpha = 1 / max tau``. The
candidates are the ``candidates`` evenly spaced values (DiffDVR drew 256 at
random); the neighbour term is minimised by Jacobi sweeps (every vertex
against its neighbours' previous values) until fewer than 0.1 % of the
vertices change or ``iterations`` sweeps.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.mesh.topology import unique_edges

__all__ = ["match_scalars"]


def match_scalars(color, opacity, transfer_function, value_range, tets, h=1.0, beta=1.0,
                  candidates=256, iterations=10, chunk=65536):
    """Per-vertex scalars whose classified color and extinction match ``color``
    and ``opacity`` (DiffDVR Eq. 13; see the module docstring).

    Parameters
    ----------
    color : (n, 3) float
        Fitted linear RGB per vertex.
    opacity : (n,) float
        Fitted extinction per unit length.
    transfer_function : callable
        ``t -> (color (k, 3), extinction (k,))`` on the normalised axis
        (a :class:`~mi_tetvr.transfer.TransferFunction` in world units).
    value_range : (float, float)
        The scalar values of ``t = 0`` and ``t = 1``.
    tets : (m, 4) int
        The mesh (its edges are the neighbourhoods).
    h : float
        A cell's size: extinctions are compared as optical depths per cell.
    beta : float
        Weight of the neighbour term (on normalised values).

    Returns
    -------
    (n,) float64 scalars in ``value_range``.
    """
    color = np.asarray(color, np.float64).reshape(-1, 3)
    tau = np.asarray(opacity, np.float64).reshape(-1) * h
    n = len(tau)
    d = (np.arange(candidates) + 0.5) / candidates
    c_d, tau_d = transfer_function(d)
    tau_d = np.asarray(tau_d, np.float64) * h
    alpha = 1.0 / max(float(tau.max()), 1e-12)
    data = np.empty((n, candidates), np.float32)
    for s in range(0, n, chunk):
        sl = slice(s, s + chunk)
        data[sl] = (np.sum((color[sl, None, :] - c_d[None]) ** 2, -1)
                    + alpha * np.log1p(np.abs(tau[sl, None] - tau_d[None])))
    edges = unique_edges(tets)
    degree = np.bincount(edges.ravel(), minlength=n).astype(np.float64)
    best = np.argmin(data, 1)
    for _ in range(iterations):
        cur = d[best]
        total = np.bincount(edges[:, 0], cur[edges[:, 1]], n) + \
            np.bincount(edges[:, 1], cur[edges[:, 0]], n)
        # sum_j (d - d_j)^2 = deg d^2 - 2 d sum_j d_j + const
        new = np.empty(n, np.int64)
        for s in range(0, n, chunk):
            sl = slice(s, s + chunk)
            cost = data[sl] + beta * (degree[sl, None] * d[None] ** 2
                                      - 2.0 * total[sl, None] * d[None])
            new[sl] = np.argmin(cost, 1)
        changed = int(np.count_nonzero(new != best))
        best = new
        if changed < 1e-3 * n:
            break
    lo, hi = value_range
    return lo + d[best] * (hi - lo)
