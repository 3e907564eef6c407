"""Unknowns that adapt with the trilinear field: a grid of coarse cells, those
where the volume has detail split in eight (a two-level octree).

The field is trilinear in each leaf cell, from its eight corners. The corners
of a split cell that lie on the face or edge of an unsplit neighbour (hanging
vertices) are not unknowns: they take that neighbour's trilinear value, so the
field is continuous. Every vertex of the fine grid (two cells per coarse cell
and axis) thus has a value ``u = P x`` from the unknowns ``x``
(:attr:`GradedGrid.P`); the projections walk tets of half the fine cell
(:meth:`GradedGrid.walk`), so the unknowns follow the detail and the walk is the
fine grid's, as the grid's own trilinear field is walked.

With no cell split it is the trilinear field of the coarse grid; with every
cell split, that of the fine grid, walked as :func:`half_cell_walk` walks any grid's.
"""
from __future__ import annotations

import itertools

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["GradedGrid", "fine_mesh", "half_cell_walk", "trilinear_rows"]


def trilinear_rows(half, cells):
    """The trilinear weights of points on a grid's vertices, the points given on
    the lattice of half its cells (``half``: (k, 3) int, in half cells from the
    low corner; exact, no rounding). Returns a CSR matrix (k, vertices of the grid
    of ``cells`` per axis, C order)."""
    with needs("recon", "the absorption fit"):
        from scipy.sparse import csr_matrix
    half = np.asarray(half, np.int64)
    cells = np.asarray(cells, np.int64)
    low = np.minimum(half // 2, cells - 1)             # the cell of each point
    frac = half / 2.0 - low
    rows, cols, vals = [], [], []
    for corner in itertools.product((0, 1), repeat=3):
        w = np.prod(np.where(corner, frac, 1.0 - frac), axis=1)
        i = low + corner
        col = (i[:, 0] * (cells[1] + 1) + i[:, 1]) * (cells[2] + 1) + i[:, 2]
        keep = np.nonzero(w > 0)[0]
        rows.append(keep), cols.append(col[keep]), vals.append(w[keep])
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(len(half), int(np.prod(cells + 1))))


def fine_mesh(lo, cell, fine):
    """A grid's vertices (C order) and tets (Kuhn splits of its cells): ``fine`` cells
    per axis of size ``cell`` from ``lo``."""
    from mi_tetvr.mesh.generate import grid_mesh
    lo, cell, fine = (np.asarray(a) for a in (lo, cell, fine))
    v, t = grid_mesh(tuple(int(f) for f in fine), lo, lo + fine * cell)
    return np.asarray(v, np.float64), np.asarray(t, np.int64)


def half_cell_walk(lo, hi, cells):
    """The tets that walk the trilinear field of a grid of ``cells`` per axis over the box
    ``lo``, ``hi``: the Kuhn splits of the lattice of half its cells, each vertex taking
    the field's value there, so the walked field, linear in each small tet, interpolates
    the trilinear one. Returns ``(vertices, tets, basis)``, ``basis`` (vertices, grid
    vertices) each walked vertex's trilinear weights (:func:`trilinear_rows`)."""
    from mi_tetvr.mesh.generate import grid_mesh
    lo, hi, cells = (np.asarray(a) for a in (lo, hi, cells))
    v, t = grid_mesh(tuple(int(c) for c in 2 * cells), lo, hi)
    v = np.asarray(v, np.float64)
    half = np.rint((v - lo) / ((hi - lo) / (2 * cells))).astype(np.int64)
    return v, np.asarray(t, np.int64), trilinear_rows(half, cells)


def _vertex_cells(split):
    """For the fine grid's vertices (C order) of coarse cells ``split``: their lattice
    indices, which are unknowns (the coarse corners, and the vertices every coarse cell
    about which is split), and an unsplit coarse cell about each (-1 where none)."""
    coarse = np.asarray(split.shape)
    idx = np.indices(2 * coarse + 1).reshape(3, -1).T
    even = idx % 2 == 0
    all_split = np.ones(len(idx), bool)
    unsplit = np.full((len(idx), 3), -1)
    # the coarse cells about a vertex: an odd index lies in one, an even in two
    for o in itertools.product((0, 1), repeat=3):
        c = idx // 2 - np.asarray(o) * even
        valid = np.all((c >= 0) & (c < coarse), axis=1)
        s = split[tuple(np.clip(c, 0, coarse - 1).T)]
        all_split &= ~valid | s
        unsplit[valid & ~s] = c[valid & ~s]
    return idx, np.all(even, axis=1) | all_split, unsplit


class GradedGrid:
    """Coarse cells, ``split`` ones cut in eight, with the trilinear field of their
    corners (module docstring).

    Parameters
    ----------
    lo : (3,) float
        The grid's low corner.
    cell : (3,) float
        The fine cell's size per axis (a coarse cell is two).
    split : (cx, cy, cz) bool
        The coarse cells split.

    Attributes
    ----------
    fine : (3,) int
        Fine cells per axis (twice the coarse ones).
    free : (N,) bool
        The fine grid's vertices (C order) that are unknowns: the coarse corners,
        and the vertices every coarse cell about which is split.
    P : scipy.sparse.csr_matrix (N, n)
        Each fine vertex's weights on the ``n`` unknowns.
    """

    def __init__(self, lo, cell, split):
        self.lo = np.asarray(lo, np.float64)
        self.cell = np.asarray(cell, np.float64)
        self.split = np.asarray(split, bool)
        self.fine = 2 * np.asarray(self.split.shape)
        idx, self.free, unsplit = _vertex_cells(self.split)
        self.n = int(self.free.sum())
        self.P = self._interpolation(idx, unsplit)

    def _interpolation(self, idx, unsplit):
        with needs("recon", "the absorption fit"):
            from scipy.sparse import csr_matrix
        number = np.cumsum(self.free) - 1
        dims = self.fine + 1
        hang = np.nonzero(~self.free)[0]
        c = unsplit[hang]
        t = (idx[hang] - 2 * c) / 2.0                  # in the cell: 0, 1/2 or 1 per axis
        rows, cols, vals = [np.nonzero(self.free)[0]], [np.arange(self.n)], [np.ones(self.n)]
        for corner in itertools.product((0, 1), repeat=3):
            w = np.prod(np.where(corner, t, 1.0 - t), axis=1)
            node = 2 * (c + corner)
            keep = w > 0
            rows.append(hang[keep])
            cols.append(number[np.ravel_multi_index(tuple(node[keep].T), dims)])
            vals.append(w[keep])
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(int(np.prod(dims)), self.n))

    @classmethod
    def uniform(cls, lo, cell, coarse):
        """No cell split: the coarse grid's trilinear field."""
        return cls(lo, cell, np.zeros(tuple(int(c) for c in coarse), bool))

    def fine_mesh(self):
        """The fine grid's vertices (C order) and tets (its cells' Kuhn splits)."""
        return fine_mesh(self.lo, self.cell, self.fine)

    def walk(self):
        """The tets the projections walk: with no cell split, the fine grid's (the coarse
        field walked at half its cell); else the Kuhn splits of the lattice of half the
        fine cell, everywhere (:func:`half_cell_walk`: the fine field walked at half its
        cell, as
        :func:`~mi_tetvr.recon.tomography.trilinear_grid` walks the grid's). Returns
        ``(vertices, tets, basis)``, ``basis`` (vertices, N) each walked vertex's
        trilinear weights on the fine grid's vertices (on the unknowns: ``basis @ P``).

        Split cells alone walked at half the fine cell, made conforming with the unsplit
        ones by bisecting the fine grid's tets about the vertices within them, cost 0.28 dB
        with every cell split (the phantom at 24 views and 10^4 photons: 34.84 against the
        grid's 35.12, and 35.14 on these tets): that bisection's children are not the half
        cells' Kuhn tets, and interpolate the trilinear field less well."""
        if self.split.any():
            return half_cell_walk(self.lo, self.lo + self.fine * self.cell, self.fine)
        v, t = self.fine_mesh()
        half = np.rint((v - self.lo) / (0.5 * self.cell)).astype(np.int64)
        return v, t, trilinear_rows(half, self.fine)

    @classmethod
    def refined(cls, lo, cell, coarse, u, budget: int):
        """The cells of a coarse grid split where the fine-grid field ``u`` ((N,), C
        order) changes most across them (its range over the cell's 27 vertices),
        as many as keep the unknowns within ``budget`` (never one where it is flat)."""
        coarse = np.asarray(coarse, np.int64)
        u = np.asarray(u, np.float64).reshape(tuple(2 * coarse + 1))
        lo_hi = [np.full(tuple(coarse), np.inf), np.full(tuple(coarse), -np.inf)]
        for d in itertools.product(range(3), repeat=3):
            s = u[d[0]:d[0] + 2 * coarse[0]:2, d[1]:d[1] + 2 * coarse[1]:2,
                  d[2]:d[2] + 2 * coarse[2]:2]
            lo_hi = [np.minimum(lo_hi[0], s), np.maximum(lo_hi[1], s)]
        change = (lo_hi[1] - lo_hi[0]).ravel()
        order = np.argsort(-change, kind="stable")
        order = order[change[order] > 0]                # a flat cell gains nothing split

        def split(k):
            s = np.zeros(int(np.prod(coarse)), bool)
            s[order[:k]] = True
            return s.reshape(tuple(coarse))

        # the unknowns grow with the cells split: the most within the budget (counted
        # without building the interpolation)
        lo_k, hi_k = 0, len(order)
        while lo_k < hi_k:
            k = (lo_k + hi_k + 1) // 2
            count = int(_vertex_cells(split(k))[1].sum())
            lo_k, hi_k = (k, hi_k) if count <= budget else (lo_k, k - 1)
        return cls(lo, cell, split(lo_k))
