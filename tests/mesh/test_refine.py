"""Mesh refinement (mi_tetvr.mesh.refine): conformity, midpoints, prisms, pruning."""
import itertools
import warnings

import numpy as np
import pytest

from tests.helpers import shared_data

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.topology import EDGES, MeshError, build_topology, signed_volumes
from mi_tetvr.mesh.refine import (bisection_order, prune_empty, prune_mesh, refine_mesh,
                                  select_by_attribute, select_top_fraction, split_vertices)

ORDERS = ("longest", "hash")


# --------------------------------------------------------------------------- helpers
def edge_keys(tets, n):
    e = np.sort(tets[:, EDGES].reshape(-1, 2), axis=1)
    return np.unique(e[:, 0] * n + e[:, 1])


def tri_area(v, f):
    p = v[f]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)


def old_support(res, n):
    """(n_new, 2): the old vertices each new vertex lies on (itself twice, or
    the endpoints of its edge)."""
    sup = np.concatenate([np.stack([np.arange(n)] * 2, 1), res.midpoint_edges])
    return sup


def check_refinement(v0, t0, res, selected):
    """Every property split_vertices promises, checked on one result."""
    v0 = np.asarray(v0, float)
    t0 = np.asarray(t0, np.int64)
    n, m = len(v0), len(t0)
    sel = np.zeros(n, bool)
    sel[np.asarray(selected, dtype=np.int64)] = True
    v, t = res.vertices, res.tets
    assert len(v) == n + len(res.midpoint_edges)
    np.testing.assert_array_equal(v[:n], v0)

    # conforming: faces shared by <= 2 tets, consistent orientation, no flips
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo0 = build_topology(v0, t0, warn=False)
        topo = build_topology(v, t, warn=False)
    vol0 = signed_volumes(v0, t0)
    vol = signed_volumes(v, t)
    # no inverted or flat tets beyond the children of flat input tets
    nonflat_parent = ~topo0.flat[res.parent]
    assert np.all(vol[nonflat_parent] > 0)
    assert topo.n_flipped == 0
    # volume preserved, per parent and in total
    np.testing.assert_allclose(np.bincount(res.parent, np.abs(vol), minlength=m),
                               np.abs(vol0), rtol=1e-9, atol=1e-15 * np.abs(vol0).max())
    assert abs(np.abs(vol).sum() - np.abs(vol0).sum()) <= 1e-9 * np.abs(vol0).sum()

    # parent mapping: covers all old tets, each child lies in its parent
    assert np.array_equal(np.unique(res.parent), np.arange(m))
    sup = old_support(res, n)
    child_old = sup[t].reshape(len(t), 8)
    assert np.all((child_old[:, :, None] == t0[res.parent][:, None, :]).any(axis=2))
    # tets without a selected vertex are kept as they were (one child, same tuple)
    untouched = ~sel[t0].any(axis=1)
    cnt = np.bincount(res.parent, minlength=m)
    assert np.all(cnt[untouched] == 1)
    first = np.searchsorted(res.parent, np.arange(m))
    assert np.array_equal(np.sort(t[first[untouched]], 1), np.sort(t0[untouched], 1))
    assert np.all(cnt[~untouched] >= 4)

    # boundary: area equal, every new boundary face lies on one old boundary
    # face, whose area its sub-faces add up to (no new boundary inside)
    a0, a1 = tri_area(v0, topo0.boundary_faces), tri_area(v, topo.boundary_faces)
    assert abs(a1.sum() - a0.sum()) <= 1e-9 * a0.sum()
    bsup = sup[topo.boundary_faces].reshape(-1, 6)
    bsup.sort(axis=1)
    uniq = [np.unique(r) for r in bsup]
    assert all(len(u) == 3 for u in uniq)
    key_new = np.array([(u[0] * n + u[1]) * n + u[2] for u in uniq])
    ob = np.sort(topo0.boundary_faces.astype(np.int64), 1)
    key_old = (ob[:, 0] * n + ob[:, 1]) * n + ob[:, 2]
    pos = np.searchsorted(np.sort(key_old), key_new)
    order = np.argsort(key_old)
    assert np.all(pos < len(key_old))
    assert np.array_equal(np.sort(key_old)[pos], key_new)
    per_old = np.bincount(order[pos], a1, minlength=len(key_old))
    np.testing.assert_allclose(per_old, a0, rtol=1e-9)
    assert len(topo.boundary_faces) >= len(topo0.boundary_faces)

    # every edge incident to a selected vertex is split at its midpoint; the
    # other old edges survive; every vertex is referenced
    old_e = np.stack(np.divmod(edge_keys(t0, n), n), 1)
    split = sel[old_e[:, 0]] | sel[old_e[:, 1]]
    me = res.midpoint_edges
    assert np.array_equal(me, old_e[split])
    np.testing.assert_allclose(v[n:], 0.5 * (v0[me[:, 0]] + v0[me[:, 1]]), rtol=0, atol=1e-15)
    N = len(v)
    new_keys = edge_keys(t, N)
    assert not np.isin(old_e[split, 0] * N + old_e[split, 1], new_keys).any()
    assert np.isin(old_e[~split, 0] * N + old_e[~split, 1], new_keys).all()
    mids = np.arange(n, N)
    assert np.isin(me[:, 0] * N + mids, new_keys).all()
    assert np.isin(me[:, 1] * N + mids, new_keys).all()
    assert np.array_equal(np.unique(t), np.unique(np.r_[np.unique(t0), mids]))
    return topo


def reference_refine(v, t, selected, rank_of):
    """Slow reference: each tet on its own, its split edges bisected one after
    the other in the order ``rank_of(parent, (a, b))``; returns
    {(parent, sorted child)} and the midpoint table it used."""
    n = len(v)
    sel = set(int(i) for i in np.atleast_1d(selected))
    edges = sorted({tuple(sorted((int(x[i]), int(x[j])))) for x in t for i, j in EDGES
                    if x[i] in sel or x[j] in sel})
    mid = {e: n + k for k, e in enumerate(edges)}
    out = set()
    for p, x in enumerate(t.tolist()):
        mine = [e for e in edges if e[0] in x and e[1] in x]
        mine.sort(key=lambda e: rank_of(p, e))
        cur = [list(x)]
        for a, b in mine:
            nxt = []
            for c in cur:
                if a in c and b in c:
                    nxt.append([mid[(a, b)] if w == b else w for w in c])
                    nxt.append([mid[(a, b)] if w == a else w for w in c])
                else:
                    nxt.append(c)
            cur = nxt
        out |= {(p, *sorted(c)) for c in cur}
    return out, np.array(edges, dtype=np.int64).reshape(-1, 2)


def single_tet():
    return (np.array([[0.1, 0.0, 0.0], [1.3, 0.2, 0.1], [0.2, 1.1, -0.1], [0.3, 0.2, 0.9]]),
            np.array([[0, 1, 2, 3]]))


def grid(cells=4, seed=0):
    return grid_mesh(cells, jitter=0.15, seed=seed)


@pytest.fixture(scope="module")
def tetwild_mesh():
    pytest.importorskip("pytetwild")
    from mi_tetvr.mesh.initial import tetwild_init
    v, t = tetwild_init(bounds=np.array([[0, 0, 0], [1, 1, 1]]), edge_length_fac=0.2)
    return v, t


# --------------------------------------------------------------------------- single tet
@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("a", range(4))
def test_one_corner_is_corner_tet_plus_prism(a, order):
    v, t = single_tet()
    res = split_vertices(v, t, [a], order=order)
    check_refinement(v, t, res, [a])
    assert len(res.tets) == 4 and len(res.midpoint_edges) == 3
    V = signed_volumes(v, t)[0]
    mids = {tuple(e): 4 + i for i, e in enumerate(res.midpoint_edges)}
    others = [b for b in range(4) if b != a]
    m_ab = [mids[tuple(sorted((a, b)))] for b in others]
    vol = signed_volumes(res.vertices, res.tets)
    sets = [set(x) for x in res.tets.tolist()]
    corner = [i for i, s in enumerate(sets) if s == {a, *m_ab}]
    assert len(corner) == 1
    np.testing.assert_allclose(vol[corner[0]], V / 8, rtol=1e-12)
    prism = set(m_ab) | set(others)
    rest = [i for i in range(4) if i != corner[0]]
    assert all(sets[i] <= prism for i in rest)
    assert np.all(vol[rest] > 0)
    np.testing.assert_allclose(vol[rest].sum(), 7 * V / 8, rtol=1e-12)
    # the three prism tets: each quad face of the prism is cut by one diagonal
    # (from a midpoint to a far corner), never both, and the two tets adjacent
    # to a quad face share that diagonal
    for b, c in itertools.combinations(others, 2):
        mb, mc = mids[tuple(sorted((a, b)))], mids[tuple(sorted((a, c)))]
        d1 = any({mb, c} <= sets[i] for i in rest)
        d2 = any({mc, b} <= sets[i] for i in rest)
        assert d1 != d2


def test_single_tet_all_patterns():
    v, t = single_tet()
    for k in range(1, 5):
        for sel in itertools.combinations(range(4), k):
            for order in ORDERS:
                res = split_vertices(v, t, list(sel), order=order)
                check_refinement(v, t, res, list(sel))
                assert len(res.midpoint_edges) == (3, 5, 6, 6)[k - 1]
                assert len(res.tets) in ({4}, {6, 7}, {8}, {8})[k - 1]


def test_negative_input_orientation_is_fixed():
    v, t = grid(3)
    t = t.copy()
    t[::2] = t[::2][:, [1, 0, 2, 3]]
    sel = np.arange(0, len(v), 3)
    res = split_vertices(v, t, sel)
    assert np.all(signed_volumes(res.vertices, res.tets) > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_topology(res.vertices, res.tets)


# --------------------------------------------------------------------------- grids
def test_grid_one_selected_tets_become_four():
    v, t = grid(4)
    rng = np.random.default_rng(1)
    sel = rng.choice(len(v), 12, replace=False)
    res = split_vertices(v, t, sel)
    check_refinement(v, t, res, sel)
    mask = np.zeros(len(v), bool)
    mask[sel] = True
    nsel = mask[t].sum(1)
    cnt = np.bincount(res.parent, minlength=len(t))
    assert np.any(nsel == 1)
    assert np.all(cnt[nsel == 1] == 4)
    assert np.all(cnt[nsel == 0] == 1)
    # each one-corner tet: one corner tet at the selected vertex (1/8 volume)
    vol0 = signed_volumes(v, t)
    vol = signed_volumes(res.vertices, res.tets)
    for p in np.flatnonzero(nsel == 1):
        a = t[p][mask[t[p]]][0]
        kids = np.flatnonzero(res.parent == p)
        has_a = kids[(res.tets[kids] == a).any(1)]
        assert len(has_a) == 1
        np.testing.assert_allclose(vol[has_a[0]], vol0[p] / 8, rtol=1e-9)


def adversarial_selections(v, t):
    n = len(v)
    e = t[0, :2]
    return {
        "all": np.arange(n),
        "two_neighbours": e,
        "one_tet": t[len(t) // 2],
        "every_other": np.arange(0, n, 2),
        "single": np.array([n // 2]),
        "boundary_vertex": np.array([0]),
        "none": np.zeros(0, np.int64),
    }


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("case", ["all", "two_neighbours", "one_tet", "every_other",
                                  "single", "boundary_vertex", "none"])
def test_adversarial_selections_grid(case, order):
    v, t = grid(4)
    sel = adversarial_selections(v, t)[case]
    res = split_vertices(v, t, sel, order=order)
    check_refinement(v, t, res, sel)
    if case == "all":
        assert len(res.tets) == 8 * len(t)   # every tet has all 6 edges split


@pytest.mark.parametrize("seed", range(4))
def test_random_selections_grid(seed):
    v, t = grid(3, seed=seed)
    rng = np.random.default_rng(seed)
    sel = rng.choice(len(v), rng.integers(1, len(v) // 2), replace=False)
    check_refinement(v, t, split_vertices(v, t, sel, order=ORDERS[seed % 2]), sel)


def test_repeated_refinement_stays_conforming():
    v, t = grid(3)
    rng = np.random.default_rng(3)
    for _ in range(3):
        sel = rng.choice(len(v), max(1, len(v) // 10), replace=False)
        res = split_vertices(v, t, sel)
        check_refinement(v, t, res, sel)
        v, t = res.vertices, res.tets


def test_selection_forms_and_independence_of_tet_order():
    v, t = grid(3)
    sel = np.array([5, 17, 17, 30])
    mask = np.zeros(len(v), bool)
    mask[sel] = True
    r1 = split_vertices(v, t, sel)
    r2 = split_vertices(v, t, mask)
    assert np.array_equal(r1.tets, r2.tets) and r1.n_selected == 3
    perm = np.random.default_rng(0).permutation(len(t))
    r3 = split_vertices(v, t[perm], sel)
    assert np.array_equal(r3.vertices, r1.vertices)
    s1 = {(p, *sorted(x)) for p, x in zip(r1.parent.tolist(), r1.tets.tolist())}
    s3 = {(p, *sorted(x)) for p, x in zip(perm[r3.parent].tolist(), r3.tets.tolist())}
    assert s1 == s3


def test_attribute_interpolation():
    v, t = grid(2)
    n = len(v)
    rng = np.random.default_rng(0)
    pd = {"s": rng.random(n), "c": rng.random((n, 3)), "m": rng.random((n, 2, 2)),
          "f32": rng.random(n).astype(np.float32), "label": np.arange(n)}
    res = split_vertices(v, t, [4, 13], pd)
    e0, e1 = res.midpoint_edges.T
    for k, a in pd.items():
        out = res.point_data[k]
        assert out.shape == (len(res.vertices),) + a.shape[1:]
        np.testing.assert_array_equal(out[:n], a)
        np.testing.assert_allclose(out[n:], 0.5 * (a[e0].astype(float) + a[e1]), rtol=1e-6)
    assert res.point_data["f32"].dtype == np.float32
    assert res.point_data["label"].dtype == np.float64
    with pytest.raises(MeshError):
        split_vertices(v, t, [0], {"bad": np.zeros(n + 1)})
    with pytest.raises(ValueError):
        split_vertices(v, t, [n])


@pytest.mark.parametrize("order", ORDERS)
def test_matches_sequential_reference(order):
    """The vectorized rounds give exactly the tets of bisecting each tet's
    split edges one by one in the global order."""
    v, t = grid(3, seed=2)
    rng = np.random.default_rng(5)
    sel = rng.choice(len(v), 20, replace=False)
    res = split_vertices(v, t, sel, order=order)
    edges = res.midpoint_edges
    rank = dict(zip(map(tuple, edges.tolist()), bisection_order(v, edges, order).tolist()))
    ref, ref_edges = reference_refine(v, t, sel, lambda p, e: rank[e])
    assert np.array_equal(ref_edges, edges)
    got = {(p, *sorted(x)) for p, x in zip(res.parent.tolist(), res.tets.tolist())}
    assert got == ref


def test_checker_catches_inconsistent_prism_diagonals():
    """Per-tet orders (each tet bisects its edges by its own local slot order,
    as an independent per-prism diagonal choice would) leave mismatched quad
    diagonals on shared faces: the conformity checks must fail."""
    v, t = grid(3, seed=2)
    sel = np.arange(0, len(v), 7)
    ref, edges = reference_refine(
        v, t, sel, lambda p, e: (t[p].tolist().index(e[0]) + t[p].tolist().index(e[1]))
        * 7 + (p % 3) * (e[0] + 2 * e[1]) % 5)
    tets = np.array([r[1:] for r in sorted(ref)])
    parent = np.array([r[0] for r in sorted(ref)])
    mids = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
    vv = np.concatenate([v, mids])
    flip = signed_volumes(vv, tets) < 0
    tets[flip] = tets[flip][:, [0, 1, 3, 2]]

    class Fake:
        pass
    fake = Fake()
    fake.vertices, fake.tets, fake.parent, fake.midpoint_edges = vv, tets, parent, edges
    with pytest.raises((AssertionError, MeshError)):
        check_refinement(v, t, fake, sel)


# --------------------------------------------------------------------------- fTetWild
@pytest.mark.parametrize("case", ["all", "two_neighbours", "one_tet", "every_other", "random"])
def test_tetwild_mesh(tetwild_mesh, case):
    v, t = tetwild_mesh
    sels = adversarial_selections(v, t)
    sels["random"] = select_top_fraction(np.random.default_rng(0).random(len(v)), 0.05)
    sel = sels[case]
    check_refinement(v, t, split_vertices(v, t, sel), sel)


# --------------------------------------------------------------------------- real meshes
@pytest.mark.parametrize("path", ["spx/spx.vtk", "a-grid/a_grid.vtk", "post/post.vtk"])
def test_real_meshes(data_dir, path):
    from mi_tetvr.mesh.io import read_tetmesh
    f = shared_data("tets", path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh = read_tetmesh(f)
    v, t = mesh.vertices, mesh.tets
    sel = select_top_fraction(np.random.default_rng(1).random(len(v)), 0.05)
    res = split_vertices(v, t, sel, {"opacity": mesh.opacity})
    check_refinement(v, t, res, sel)


# --------------------------------------------------------------------------- selection
def test_select_top_fraction():
    s = np.array([0.0, 5.0, 1.0, 5.0, 0.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    assert select_top_fraction(s, 0.2).tolist() == [1, 3]          # tie: lower index first
    assert select_top_fraction(s, 0.3).tolist() == [1, 3, 6]
    assert select_top_fraction(s, 0.01).tolist() == [1]            # at least one
    assert select_top_fraction(s, 1.0).tolist() == [1, 3, 6, 5, 2]  # zeros never
    assert len(select_top_fraction(s, 0.0)) == 0
    assert len(select_top_fraction(np.zeros(10), 0.5)) == 0
    big = np.random.default_rng(0).random(1000)
    top = select_top_fraction(big, 0.05)
    assert len(top) == 50 and big[top].min() >= np.sort(big)[-50]
    vec = np.array([[3.0, 4.0], [0.0, 1.0], [1.0, 1.0]])
    assert select_top_fraction(vec, 0.34).tolist() == [0]
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError):
            select_top_fraction(s, bad)
    with pytest.raises(ValueError):
        select_top_fraction(np.array([1.0, np.nan]), 0.5)


def test_select_by_attribute():
    pd = {"grad": np.array([[-3.0, 0, 0], [1, 0, 0], [0, 0, 2], [0, 0, 0]])}
    assert select_by_attribute(pd, "grad", 0.5).tolist() == [0, 2]
    with pytest.raises(KeyError):
        select_by_attribute(pd, "nope", 0.5)


def test_refine_mesh():
    v, t = grid(3)
    rng = np.random.default_rng(0)
    mesh = TetMesh(v, t, rng.random((len(v), 3)), rng.random(len(v)),
                   {"grad": rng.random(len(v))})
    out = refine_mesh(mesh, "grad", 0.05)
    sel = select_top_fraction(mesh.point_data["grad"], 0.05)
    res = split_vertices(v, t, sel)
    assert np.array_equal(out.tets, res.tets) and np.allclose(out.vertices, res.vertices)
    e0, e1 = res.midpoint_edges.T
    n = len(v)
    np.testing.assert_allclose(out.color[n:], 0.5 * (mesh.color[e0] + mesh.color[e1]))
    np.testing.assert_allclose(out.opacity[n:], 0.5 * (mesh.opacity[e0] + mesh.opacity[e1]))
    np.testing.assert_allclose(out.point_data["grad"][:n], mesh.point_data["grad"])
    assert out.topology.n_tets == len(res.tets)
    out2 = refine_mesh(mesh, "opacity", 0.1)
    assert len(out2.tets) > len(t)
    same = refine_mesh(mesh, "grad", 0.0)
    assert np.array_equal(same.tets, mesh.tets)


# --------------------------------------------------------------------------- pruning
def test_prune_empty():
    v, t = grid(4)
    n = len(v)
    op = np.where(np.linalg.norm(v - [0.4, 0.0, -0.2], axis=1) < 0.8, 1.0, 0.0)
    op[3] = 0.05
    pd = {"c": np.arange(n, dtype=float)[:, None] * [1, 2, 3]}
    res = prune_empty(v, t, op, threshold=0.05, point_data=pd)
    nonempty = (op[t] > 0.05).any(1)
    assert 0 < nonempty.sum() < len(t)
    assert np.array_equal(res.parent, np.flatnonzero(nonempty))
    # kept tets' vertex tuples are exactly the non-empty ones
    assert np.array_equal(res.vertex_parent[res.tets], t[nonempty])
    np.testing.assert_array_equal(res.vertices, v[res.vertex_parent])
    np.testing.assert_array_equal(res.point_data["c"], pd["c"][res.vertex_parent])
    assert np.array_equal(np.unique(res.tets), np.arange(len(res.vertices)))
    assert np.all(res.vertex_map[res.vertex_parent] == np.arange(len(res.vertices)))
    assert np.all(np.delete(res.vertex_map, res.vertex_parent) == -1)
    topo = build_topology(res.vertices, res.tets, warn=False)
    assert topo.n_flipped == 0 and not topo.flat.any()
    assert res.counts()["removed_tets"] == len(t) - nonempty.sum()
    with pytest.raises(MeshError):
        prune_empty(v, t, np.zeros(n), 0.0)
    # nothing empty: unchanged
    same = prune_empty(v, t, np.ones(n), 0.0)
    assert np.array_equal(same.tets, t)


def test_prune_reports_nonmanifold_edges():
    # two tets that share only an edge once the tet between them is removed
    v = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0.2, 0.0],
                  [0.5, -1, 0.0]], float)
    t = np.array([[0, 1, 2, 3], [0, 1, 3, 4], [0, 1, 4, 5]])
    t = np.array([x if signed_volumes(v, [x])[0] > 0 else x[[1, 0, 2, 3]] for x in t])
    op = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 1.0])
    res = prune_empty(v, t, op, 0.0)
    assert res.parent.tolist() == [0, 2]
    assert res.n_nonmanifold_edges == 1
    build_topology(res.vertices, res.tets, warn=False)


def test_prune_mesh_then_refine():
    v, t = grid(3)
    op = np.clip(v[:, 0], 0, None)
    mesh = TetMesh(v, t, None, op)
    pruned = prune_mesh(mesh, 0.0)
    assert len(pruned.tets) < len(t)
    assert np.all(pruned.opacity[pruned.tets].max(1) > 0)
    out = refine_mesh(pruned, "opacity", 0.2)
    build_topology(out.vertices, out.tets, warn=False)
