"""Meshes the project generates: regular tet grids (optionally jittered) and
analytic fields on them, for the default scenes, tests and benchmarks."""
from __future__ import annotations

import numpy as np

from mi_tetvr.mesh.tetmesh import TetMesh

#: Kuhn (Freudenthal) split of a cube into 6 tets sharing the main diagonal;
#: corners are numbered i*4 + j*2 + k for offsets (i, j, k) in {0, 1}^3;
#: all six are positively oriented.
KUHN_TETS = np.array([[0, 3, 1, 7], [0, 1, 5, 7], [0, 2, 3, 7],
                      [0, 6, 2, 7], [0, 5, 4, 7], [0, 4, 6, 7]])


def grid_tets(shape):
    """Tets of a regular grid of ``shape = (nx, ny, nz)`` cells, 6 per cell.

    Returns
    -------
    (6 nx ny nz, 4) int64 indices into the (nx+1)(ny+1)(nz+1) grid points
    ordered with x slowest (``np.meshgrid(..., indexing='ij')``).
    """
    nx, ny, nz = shape
    idx = np.arange((nx + 1) * (ny + 1) * (nz + 1)).reshape(nx + 1, ny + 1, nz + 1)
    corners = np.stack([idx[i:i + nx, j:j + ny, k:k + nz].ravel()
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=1)
    return corners[:, KUHN_TETS].reshape(-1, 4)


def grid_mesh(shape, lo=(-1.0, -1.0, -1.0), hi=(1.0, 1.0, 1.0), jitter=0.0, seed=0):
    """A regular tet grid over the box [lo, hi].

    Parameters
    ----------
    shape : int or (3,) int
        Cells per axis.
    jitter : float
        Interior vertices move uniformly by up to ``jitter`` times the cell size
        per axis; boundary vertices stay, so the box is unchanged. Up to 0.2
        keeps every Kuhn tet positive in practice (0.25 already inverts a few,
        which :func:`mi_tetvr.mesh.build_topology` re-orients with a warning).

    Returns
    -------
    vertices (n, 3) float64, tets (m, 4) int64
    """
    shape = (shape,) * 3 if np.isscalar(shape) else tuple(shape)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.linspace(lo[a], hi[a], shape[a] + 1) for a in range(3)]
    v = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    if jitter:
        h = (hi - lo) / np.asarray(shape)
        rng = np.random.default_rng(seed)
        on_bnd = np.any(np.isclose(v, lo) | np.isclose(v, hi), axis=1)
        v[~on_bnd] += rng.uniform(-jitter, jitter, (np.count_nonzero(~on_bnd), 3)) * h
    return v, grid_tets(shape)


def blob_field(vertices, scale=4.0):
    """A smooth analytic volume: a few soft colored blobs.

    Returns
    -------
    color (n, 3) float64 in [0, 1], opacity (n,) float64 >= 0
    """
    p = np.asarray(vertices, float)
    centers = np.array([[0.35, 0.0, 0.0], [-0.3, 0.3, 0.1], [0.0, -0.35, -0.2]])
    colors = np.array([[0.9, 0.3, 0.1], [0.1, 0.6, 0.9], [0.3, 0.9, 0.2]])
    w = np.exp(-np.sum((p[:, None, :] - centers[None]) ** 2, -1) / 0.08)
    opacity = scale * w.sum(1)
    color = (w @ colors + 0.02) / (w.sum(1, keepdims=True) + 0.02 / 0.7)
    return np.clip(color, 0, 1), opacity


def blob_mesh(cells=24, jitter=0.15, seed=0, scale=4.0) -> TetMesh:
    """The default scene's volume: :func:`blob_field` on a jittered grid."""
    v, t = grid_mesh(cells, jitter=jitter, seed=seed)
    c, o = blob_field(v, scale)
    return TetMesh(v, t, c, o)
