"""The graded grid of the trilinear field (two-level octree): its unknowns, its
hanging vertices, the tets it walks and the cells it splits, against closed forms
and a brute-force evaluation cell by cell."""
import itertools

import numpy as np
import pytest

from mi_tetvr.recon.octree import GradedGrid, trilinear_rows

LO, CELL = np.array([-1.0, -0.5, 0.2]), np.array([0.1, 0.12, 0.07])


def trilinear(p):
    """A trilinear function of the position (with the xyz term): every cell's field
    reproduces it exactly, whatever is split."""
    return (1 + p[:, 0]) * (2 + 3 * p[:, 1]) * (3 - p[:, 2]) + p[:, 0] * p[:, 1] * p[:, 2]


def random_split(seed, shape=(3, 4, 2), share=0.4):
    return np.random.default_rng(seed).random(shape) < share


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trilinear_functions_are_reproduced(seed):
    """The unknowns at a trilinear function's values give it back at every fine
    vertex (the hanging ones by their unsplit neighbour) and at every walked vertex."""
    g = GradedGrid(LO, CELL, random_split(seed))
    v_fine, _ = g.fine_mesh()
    x = trilinear(v_fine[g.free])
    np.testing.assert_allclose(g.P @ x, trilinear(v_fine), rtol=0, atol=1e-12)
    v, t, basis = g.walk()
    np.testing.assert_allclose(basis @ (g.P @ x), trilinear(v), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(basis.sum(axis=1)).ravel(), 1.0, atol=1e-12)


def leaf_values(g, u):
    """Every leaf cell's trilinear interpolation of its own corners' values, at every
    fine vertex it holds: {vertex: [values]}, brute force, cell by cell."""
    dims = tuple(g.fine + 1)
    u = u.reshape(dims)
    seen = {}
    for c in itertools.product(*[range(n) for n in g.split.shape]):
        size = 1 if g.split[c] else 2
        leaves = [tuple(2 * np.asarray(c) + o) for o in itertools.product((0, 1), repeat=3)] \
            if g.split[c] else [tuple(2 * np.asarray(c))]
        for low in leaves:
            corners = {o: u[tuple(np.asarray(low) + size * np.asarray(o))]
                       for o in itertools.product((0, 1), repeat=3)}
            for d in itertools.product(range(size + 1), repeat=3):
                f = np.asarray(d) / size
                val = sum(np.prod(np.where(o, f, 1 - f)) * corners[o] for o in corners)
                seen.setdefault(tuple(np.asarray(low) + d), []).append(val)
    return seen


@pytest.mark.parametrize("seed", [0, 3])
def test_the_field_is_continuous_across_split_and_unsplit_cells(seed):
    """Random unknowns: at every fine vertex, every leaf holding it (a split cell's
    eighths, an unsplit cell whole) gives the same value, the fine vertex's own: the
    hanging vertices on an unsplit cell's faces and edges take its values."""
    g = GradedGrid(LO, CELL, random_split(seed))
    u = g.P @ np.random.default_rng(seed).normal(size=g.n)
    hanging = 0
    for vertex, values in leaf_values(g, u).items():
        i = np.ravel_multi_index(vertex, tuple(g.fine + 1))
        np.testing.assert_allclose(values, u[i], rtol=0, atol=1e-12)
        hanging += not g.free[i] and len(values) > 1
    assert hanging > 0                    # the split met unsplit cells


@pytest.mark.parametrize("seed", [None, 5])
def test_none_and_every_cell_split(seed):
    """No cell split: the coarse grid's vertices are the unknowns, walked on the fine
    grid's 6 tets per cell. Every cell split (``seed`` None), or some (a random split):
    the fine grid's vertices are the unknowns or hang, walked on 48 tets per fine cell,
    as :func:`trilinear_grid` walks them."""
    coarse = (3, 4, 2)
    g = GradedGrid.uniform(LO, CELL, coarse)
    assert g.n == 4 * 5 * 3 and np.all(g.free.reshape(7, 9, 5)[::2, ::2, ::2])
    v, t, _ = g.walk()
    assert len(v) == 7 * 9 * 5 and len(t) == 6 * 6 * 8 * 4
    split = np.ones(coarse, bool) if seed is None else random_split(seed, coarse)
    g = GradedGrid(LO, CELL, split)
    if seed is None:
        assert g.n == 7 * 9 * 5 and (g.P != 0).nnz == g.n
    else:
        assert 4 * 5 * 3 < g.n < 7 * 9 * 5
    v, t, basis = g.walk()
    assert len(v) == 13 * 17 * 9 and len(t) == 48 * 6 * 8 * 4
    # the walked vertices are the lattice of half cells, and take the fine grid's field
    half = np.rint((v - LO) / (CELL / 2)).astype(int)
    assert len(np.unique(half, axis=0)) == len(v) and half.max(0).tolist() == [12, 16, 8]
    assert (basis != trilinear_rows(half, g.fine)).nnz == 0
    # the Kuhn split of each half cell: every edge one of a half cell's 7 steps from its
    # low corner, (0 or 1) per axis, all one way (the other diagonals are another split)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    step = np.concatenate([half[t[:, j]] - half[t[:, i]] for i, j in pairs])
    step *= np.where(np.any(step < 0, axis=1) & ~np.any(step > 0, axis=1), -1, 1)[:, None]
    assert step.min() == 0 and step.max() == 1


def test_walk_is_a_conforming_cover_of_the_box():
    """The walked tets fill the box once (volumes sum to it, all positive) and their
    boundary faces are the box's faces only (a hanging vertex would leave holes)."""
    from mi_tetvr.mesh.topology import build_topology
    g = GradedGrid(LO, CELL, random_split(4))
    v, t, _ = g.walk()
    e = v[t[:, 1:]] - v[t[:, :1]]
    vol = np.linalg.det(e) / 6
    box = g.fine * CELL
    assert np.all(vol > 0) and np.sum(vol) == pytest.approx(np.prod(box), rel=1e-12)
    topo = build_topology(v, t)
    f = v[topo.boundary_faces]                                  # (b, 3, 3)
    centre = f.mean(1)
    on_face = np.isclose(centre, LO, atol=1e-9) | np.isclose(centre, LO + box, atol=1e-9)
    assert np.all(on_face.any(axis=1))
    area = 0.5 * np.sum(np.linalg.norm(np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), axis=1))
    assert area == pytest.approx(2 * (box[0] * box[1] + box[1] * box[2] + box[0] * box[2]),
                                 rel=1e-12)


def test_refined_splits_where_the_field_changes_within_the_budget():
    """A step across the box: the cells split are the ones the step crosses, as
    many as the budget holds (one more would exceed it)."""
    coarse = np.array([6, 6, 6])
    g0 = GradedGrid.uniform(LO, CELL, coarse)
    v, _ = g0.fine_mesh()
    u = (v[:, 0] > LO[0] + 5.5 * CELL[0]).astype(float)        # inside coarse cells x = 2
    g = GradedGrid.refined(LO, CELL, coarse, u, budget=g0.n + 200)
    assert g.n <= g0.n + 200
    crossed = np.zeros(tuple(coarse), bool)
    crossed[2] = True
    assert np.array_equal(g.split, crossed)           # the whole slab fits in the budget
    few = GradedGrid.refined(LO, CELL, coarse, u, budget=g0.n + 20)
    assert few.split.sum() > 0 and np.all(few.split <= crossed) and few.n <= g0.n + 20
    more = few.split.copy()
    more[tuple(np.argwhere(crossed & ~few.split)[0])] = True
    assert GradedGrid(LO, CELL, more).n > g0.n + 20
