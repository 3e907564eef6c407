"""Topology, validation and file I/O of tet meshes (numpy only)."""
import warnings

import meshio
import numpy as np
import pytest

from tests.helpers import shared_data

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.io import read_tetmesh, write_tetmesh
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.topology import (CONVEX_RTOL, EDGES, FACES, FLAT_TOLERANCE, MeshError,
                                    bbox_diagonal, build_topology, convex_boundary,
                                    edge_lengths, face_keys, flip_tets, mean_edge_length,
                                    orient_tets, quality, signed_volumes, validate_arrays)



def reverse_some(t, fraction, seed):
    """Copy of tets with a random fraction given in reversed orientation."""
    flip = np.random.default_rng(seed).random(len(t)) < fraction
    t = t.copy()
    t[flip] = t[flip][:, [1, 0, 2, 3]]
    return t, flip


def test_topology_properties():
    v, t = grid_mesh(3, jitter=0.15, seed=0)
    t, flip = reverse_some(t, 0.3, seed=0)
    with pytest.warns(UserWarning, match="inverted"):
        topo = build_topology(v, t)
    assert topo.n_flipped == flip.sum()
    assert np.all(signed_volumes(v, topo.tets) > 0)
    # Neighbour links are symmetric and the shared faces have the same vertices.
    m = topo.n_tets
    for i in range(4):
        inner = topo.neighbors[:, i] >= 0
        nb, nf = topo.neighbors[inner, i], topo.neighbor_faces[inner, i]
        assert np.all(topo.neighbors[nb, nf] == np.flatnonzero(inner))
        a = np.sort(topo.tets[inner][:, FACES[i]], axis=1)
        b = np.sort(topo.tets[nb[:, None], FACES[nf]], axis=1)
        assert np.array_equal(a, b)
    # Boundary faces point outward and cover the box surface (area 24).
    f = v[topo.boundary_faces]
    n = np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0])
    inward = v[topo.tets[topo.boundary_tets]].mean(1) - f.mean(1)
    assert np.all(np.einsum("ij,ij->i", n, inward) < 0)
    assert np.linalg.norm(n, axis=1).sum() / 2 == pytest.approx(24.0)
    assert (topo.neighbors < 0).sum() == len(topo.boundary_faces)
    assert np.all(topo.boundary_adjacency >= 0)  # closed surface
    assert topo.volumes.sum() == pytest.approx(8.0)
    assert m == 6 * 27


def test_quality_regular_tet():
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    # this vertex order is negatively oriented (det < 0)
    assert signed_volumes(v, [[0, 1, 2, 3]])[0] < 0
    assert quality(v, [[0, 2, 1, 3]])[0] == pytest.approx(1.0)
    assert quality(v, [[0, 1, 2, 3]])[0] == pytest.approx(-1.0)


@pytest.mark.parametrize("tets, match", [
    ([[0, 1, 2, 9]], "out of range"),
    ([[0, 1, 2, -1]], "out of range"),
    ([[0, 1, 2, 2]], "repeated vertex"),
    ([[0, 1, 2, 3], [3, 2, 1, 0]], "duplicate tets"),
    ([[0, 1, 2]], "shape"),
])
def test_bad_tets(tets, match):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    with pytest.raises(MeshError, match=match):
        build_topology(v, np.array(tets))


def test_bad_vertices_and_attributes():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    t = [[0, 1, 2, 3]]
    bad = v.copy()
    bad[2, 1] = np.nan
    with pytest.raises(MeshError, match="non-finite.*vertices 2"):
        TetMesh(bad, t)
    with pytest.raises(MeshError, match="negative opacity.*vertices 1"):
        TetMesh(v, t, opacity=[0, -1, 0, 0])
    with pytest.raises(MeshError, match="color must have shape"):
        TetMesh(v, t, color=np.zeros((4, 2)))
    with pytest.raises(MeshError, match="non-finite color"):
        TetMesh(v, t, color=np.full((4, 3), np.inf))


def test_non_manifold_face():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1]], float)
    with pytest.raises(MeshError, match="shared by more than two tets"):
        build_topology(v, np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]]))


def test_folded_mesh_is_refused():
    # Two tets on the same side of their shared face overlap.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.5]], float)
    with pytest.raises(MeshError, match="folds over itself"):
        build_topology(v, np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))


def test_flat_tets_oriented_consistently():
    v, t = grid_mesh(2)
    v = v.copy()
    v[np.isclose(v[:, 0], 0.0), 0] = -1.0  # collapse a layer: 24 flat tets
    t, _ = reverse_some(t, 0.5, seed=1)
    with pytest.warns(UserWarning, match="24 zero-volume"):
        topo = build_topology(v, t)
    assert topo.flat.sum() == 24
    # Every interior face is shared with opposite windings after orientation.
    from mi_tetvr.mesh.topology import _face_parity
    faces = topo.tets[:, FACES].reshape(-1, 3)
    inner = np.flatnonzero(topo.neighbors.ravel() >= 0)
    other = topo.neighbors.ravel()[inner] * 4 + topo.neighbor_faces.ravel()[inner]
    assert np.all(_face_parity(faces[inner]) != _face_parity(faces[other]))


@pytest.mark.parametrize("suffix", [".vtu", ".vtk"])
def test_io_round_trip(tmp_path, suffix):
    v, t = grid_mesh(2, jitter=0.1)
    rng = np.random.default_rng(2)
    mesh = TetMesh(v, t, rng.random((len(v), 3)), rng.random(len(v)))
    p = tmp_path / f"m{suffix}"
    write_tetmesh(p, mesh)
    back = read_tetmesh(p)
    np.testing.assert_allclose(back.vertices, mesh.vertices)
    assert np.array_equal(back.tets, mesh.tets)
    np.testing.assert_allclose(back.color, mesh.color)
    np.testing.assert_allclose(back.opacity, mesh.opacity)


@pytest.mark.parametrize("suffix", [".msh", ".mesh"])
def test_geometry_only_formats(tmp_path, suffix):
    v, t = grid_mesh(2, jitter=0.1)
    p = tmp_path / f"m{suffix}"
    with pytest.warns(UserWarning, match="only the geometry"):
        write_tetmesh(p, TetMesh(v, t))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        back = read_tetmesh(p)
    np.testing.assert_allclose(back.vertices, v)
    assert np.array_equal(back.tets, t)


def test_medit_geometry_and_defaults(tmp_path):
    v, t = grid_mesh(1)
    p = tmp_path / "m.mesh"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)]))
    m = read_tetmesh(p)
    assert np.array_equal(m.tets, t)
    assert np.all(m.color == 1.0) and np.all(m.opacity == 1.0)  # documented defaults


def test_quadratic_and_other_cells(tmp_path):
    v, t = grid_mesh(1)
    mid = np.zeros((len(t), 6), int)  # mid-edge nodes (ignored)
    p = tmp_path / "q.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra10", np.concatenate([t, mid], 1))]))
    with pytest.warns(UserWarning, match="linearized"):
        m = read_tetmesh(p)
    assert np.array_equal(m.tets, t)
    p = tmp_path / "h.vtu"
    meshio.write(p, meshio.Mesh(v, [("hexahedron", np.arange(8)[None])]))
    with pytest.raises(MeshError, match="hexahedron"):
        read_tetmesh(p)


def test_transfer_function_shading(tmp_path):
    from mi_tetvr.transfer import TransferFunction
    v, t = grid_mesh(1)
    s = np.linspace(0, 1, len(v))
    p = tmp_path / "s.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)], point_data={"density": s}))
    tf = TransferFunction([0, 1], [[0, 0, 0], [1, 0.5, 0.25]], [0, 1], [0, 2])
    m = read_tetmesh(p, transfer_function=tf, opacity_scale=3.0)
    np.testing.assert_allclose(m.opacity, 6.0 * s)
    np.testing.assert_allclose(m.color, s[:, None] * [1, 0.5, 0.25])
    with pytest.raises(MeshError, match="no point-data array"):
        read_tetmesh(p, transfer_function=tf, scalar="nope")


# --------------------------------------------------------------------------- primitives
def test_edges_table():
    """EDGES holds each of the six vertex pairs of a tet once, in the order
    01, 02, 03, 12, 13, 23, and every face's edges are among them."""
    pairs = [tuple(e) for e in EDGES.tolist()]
    assert pairs == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    assert len(set(map(frozenset, pairs))) == 6
    for f in FACES.tolist():
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            assert (min(a, b), max(a, b)) in pairs


def test_edge_lengths():
    v, t = grid_mesh(2, jitter=0.2, seed=3)
    lengths = edge_lengths(v, t)
    assert lengths.shape == (len(t), 6)
    for k, (i, j) in enumerate(EDGES):
        np.testing.assert_array_equal(lengths[:, k],
                                      np.linalg.norm(v[t[:, i]] - v[t[:, j]], axis=1))
    assert mean_edge_length(v, t) == pytest.approx(lengths.mean())
    # l_rms from the same edges gives quality 1 for the regular tet
    reg = np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float)
    np.testing.assert_allclose(edge_lengths(reg, [[0, 1, 2, 3]]), np.sqrt(8.0))


def test_flip_tets():
    v, t = grid_mesh(2, jitter=0.1, seed=2)
    mask = np.random.default_rng(0).random(len(t)) < 0.5
    out = flip_tets(t, mask)
    assert out is not t and out.dtype == t.dtype
    vol, vol_out = signed_volumes(v, t), signed_volumes(v, out)
    np.testing.assert_allclose(vol_out[mask], -vol[mask])
    np.testing.assert_array_equal(out[~mask], t[~mask])
    np.testing.assert_array_equal(out[:, :2], t[:, :2])
    np.testing.assert_array_equal(np.sort(out, axis=1), np.sort(t, axis=1))


def test_orient_tets_against_signed_volumes():
    v, t = grid_mesh(3, jitter=0.15, seed=0)
    t, flip = reverse_some(t, 0.4, seed=5)
    vol = signed_volumes(v, t)
    o = orient_tets(v, t)
    np.testing.assert_array_equal(o.volumes, vol)
    np.testing.assert_array_equal(o.flipped, vol < 0)
    np.testing.assert_array_equal(o.flipped, flip)
    assert not o.flat.any()
    assert np.all(signed_volumes(v, o.tets) > 0)
    np.testing.assert_allclose(signed_volumes(v, o.tets), np.abs(vol))
    np.testing.assert_array_equal(o.tets[~o.flipped], t[~o.flipped])
    # the orientation of build_topology is this one
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        np.testing.assert_array_equal(build_topology(v, t).tets, o.tets)


def test_orient_tets_flat_tolerance():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.3, 0.3, -1e-9]], float)
    t = np.array([[0, 2, 1, 3], [0, 1, 2, 4]])     # inverted, nearly flat (volume < 0)
    vol = signed_volumes(v, t)
    assert vol[0] < 0 and -1e-9 < vol[1] < 0
    o = orient_tets(v, t, 1e-8)                      # the second one is flat: left as given
    np.testing.assert_array_equal(o.flat, [False, True])
    np.testing.assert_array_equal(o.flipped, [True, False])
    np.testing.assert_array_equal(o.tets[1], t[1])
    o = orient_tets(v, t, 0.0)                       # no tolerance: both flipped
    np.testing.assert_array_equal(o.flipped, [True, True])
    assert np.all(signed_volumes(v, o.tets) > 0)
    # the tolerance is relative to each tet's own size: scaled down by 1e-6
    # (far below the old 1e-12 x diagonal^3 cut-off) nothing changes
    small = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.3, 0.3, -1e-9]]) * 1e-6
    np.testing.assert_array_equal(orient_tets(small, t, 1e-8).flat, [False, True])
    np.testing.assert_array_equal(orient_tets(small + 1e3, t, 1e-8).flat, [False, True])
    # a graded mesh: tiny valid tets beside big ones are not flat by default
    graded = np.concatenate([v[:4], v[:4] * 1e-5 + 0.5])
    assert not orient_tets(graded, np.array([[0, 1, 2, 3], [4, 5, 6, 7]])).flat.any()
    assert bbox_diagonal(np.zeros((0, 3))) == 1.0 and bbox_diagonal(np.ones((3, 3))) == 1.0


def test_face_keys():
    rng = np.random.default_rng(4)
    tri = rng.integers(0, 30, (400, 3))
    tri = tri[(tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])]
    keys = face_keys(tri)
    perm = tri[:, rng.permutation(3)]
    np.testing.assert_array_equal(face_keys(perm), keys)        # order of the vertices
    s = np.sort(tri, axis=1)
    same = (s[:, None] == s[None]).all(-1)
    np.testing.assert_array_equal(keys[:, None] == keys[None], same)
    # keys sort as the sorted triples do, also above 2**21 vertices: packed with
    # the spans c - a (offset numbers) or ranked (numbers spread over 2**25)
    for k in (keys, face_keys(s + 2 ** 21), face_keys(s * 2 ** 20)):
        np.testing.assert_array_equal(np.argsort(k, kind="stable"),
                                      np.lexsort((s[:, 2], s[:, 1], s[:, 0])))
    assert face_keys(np.zeros((0, 3), int)).shape == (0,)
    # the faces of a conforming mesh: each interior key twice, boundary keys once
    v, t = grid_mesh(2)
    _, counts = np.unique(face_keys(t[:, FACES].reshape(-1, 3)), return_counts=True)
    assert set(counts.tolist()) == {1, 2}
    assert np.count_nonzero(counts == 1) == len(build_topology(v, t).boundary_faces)


def test_validate_arrays_modes():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    t = np.array([[0, 1, 2, 3]], np.int64)
    vs, ts = validate_arrays(v, t)
    assert vs is not v and ts is not t                     # strict: copies
    vl, tl = validate_arrays(v, t, strict=False)
    assert vl is v and tl is t                             # cheap: no copies
    assert validate_arrays(None, t, strict=False)[0] is None
    with pytest.raises(MeshError, match="no tetrahedra"):
        validate_arrays(v, np.zeros((0, 4), int), strict=False)
    assert len(validate_arrays(v, np.zeros((0, 4), int), strict=False, allow_empty=True)[1]) == 0
    with pytest.raises(MeshError, match="out of range.*in tets 1"):
        validate_arrays(v, [[0, 1, 2, 3], [0, 1, 2, 4]], strict=False)
    with pytest.raises(MeshError, match="shape"):
        validate_arrays(None, [[0, 1, 2]], strict=False)
    # the strict checks are skipped in the cheap mode
    validate_arrays(v, [[0, 1, 2, 2]], strict=False)
    with pytest.raises(MeshError, match="repeated vertex"):
        validate_arrays(v, [[0, 1, 2, 2]])
    with pytest.raises(MeshError, match="must be integers"):
        validate_arrays(v, [[0, 1, 2, 2.5]])


# --------------------------------------------------------------------------- TetMesh
def test_tetmesh_cached_properties():
    v, t = grid_mesh(2, jitter=0.15, seed=1)
    t, _ = reverse_some(t, 0.3, seed=2)
    mesh = TetMesh(v, t)
    np.testing.assert_array_equal(mesh.volumes, signed_volumes(v, t))
    np.testing.assert_array_equal(mesh.quality, quality(v, t))
    np.testing.assert_array_equal(mesh.edge_lengths, edge_lengths(v, t))
    assert mesh.mean_edge_length == mean_edge_length(v, t)
    np.testing.assert_array_equal(mesh.bounds, [v.min(0), v.max(0)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo = mesh.topology
        np.testing.assert_array_equal(topo.tets, build_topology(v, t).tets)
    # computed once, kept, read-only
    assert mesh.topology is topo and mesh.volumes is mesh.volumes
    with pytest.raises(ValueError):
        mesh.volumes[0] = 1.0
    with pytest.raises(AttributeError):
        mesh.quality = None
    # assigning the arrays validates them and drops the caches
    old_volumes = mesh.volumes
    mesh.vertices = 2.0 * v
    assert mesh.volumes is not old_volumes
    np.testing.assert_allclose(mesh.volumes, 8.0 * old_volumes)
    assert mesh.mean_edge_length == pytest.approx(2.0 * mean_edge_length(v, t))
    with pytest.warns(UserWarning, match="inverted"):
        assert mesh.topology is not topo
    mesh.tets = topo.tets
    assert np.all(mesh.volumes > 0) and mesh.tets.dtype == np.int64
    with pytest.raises(MeshError, match="out of range"):
        mesh.tets = [[0, 1, 2, len(v)]]
    with pytest.raises(ValueError, match="keep their shape"):
        mesh.vertices = v[:-1]
    # arrays are copied on construction
    assert mesh.vertices is not v and not np.shares_memory(TetMesh(v, t).vertices, v)


def test_mesh_package_imports_without_variant():
    """The mesh sub-package is numpy only: its public API imports without a
    Mitsuba variant and without the renderer."""
    import subprocess
    import sys
    code = ("import sys, mi_tetvr.mesh as m; [getattr(m, n) for n in m.__all__]; "
            "assert 'mi_tetvr.render' not in sys.modules; "
            "assert 'mi_tetvr.render.walk' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


# -- the linear-time topology against the implementation it replaced ---------------------
def _test_meshes():
    """Meshes with boundaries and holes, shuffled, inverted, flat, folded,
    non-manifold and duplicate tets."""
    rng = np.random.default_rng(3)
    v, t = grid_mesh((5, 4, 3), jitter=0.15)
    perm = rng.permutation(len(v))
    rank = np.empty_like(perm)
    rank[perm] = np.arange(len(v))
    shuffled = (v[perm], rank[t][rng.permutation(len(t))])
    inverted = (v, flip_tets(t, rng.random(len(t)) < 0.3))
    holes = (v, t[rng.random(len(t)) > 0.2])
    moved = v.copy()
    moved[len(v) // 2] = moved[t[0, :3]].mean(0)      # a vertex dragged across its tets
    folded_v = v.copy()
    folded_v[t[40, 0]] += 2.0 * (v[t[40, 1]] - v[t[40, 0]])
    # a flat tet on a face of the z = -1 side (its 4th vertex the face's centroid)
    faces = t[:, FACES].reshape(-1, 3)
    low = faces[np.all(np.isclose(v[faces][..., 2], -1.0), axis=1)][0]
    flat = (np.r_[v, [v[low].mean(0)]], np.r_[t, [[*low, len(v)]]])
    # an interior face given a third tet
    inner = faces[~np.any(np.isclose(np.abs(v[faces]), 1.0).all(1), axis=1)][0]
    shared = (np.r_[v, [[5.0, 5.0, 5.0]]], np.r_[t, [[*inner, len(v)]]])
    return {"grid": (v, t), "shuffled": shuffled, "inverted": inverted, "holes": holes,
            "flat tet": flat, "moved vertex": (moved, t), "folded": (folded_v, t),
            "duplicate": (v, np.r_[t, t[[7, 9]][:, [1, 0, 2, 3]]]), "non-manifold": shared}


def _det_volumes(v, t):
    """Signed volumes in float64, written out here (not the package's)."""
    a, b, c, d = (np.asarray(v, np.float64)[t[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", b - a, np.cross(c - a, d - a)) / 6.0


def _faces_by_vertices(t):
    """``{sorted vertex triple: [(tet, local face), ...]}`` by a plain search."""
    owners = {}
    for i, tet in enumerate(np.asarray(t).tolist()):
        for f in range(4):
            owners.setdefault(tuple(sorted(tet[:f] + tet[f + 1:])), []).append((i, f))
    return owners


def _winding(tri):
    """+1 or -1: the cyclic order of a triangle's three vertex numbers."""
    a, b, c = tri
    return 1 if (a < b < c or b < c < a or c < a < b) else -1


def _check_topology(topo, v, t):
    """The topology against the properties it must have, each found here by brute force:
    the input's tets (same order) positively oriented but the flat ones, their volumes;
    each face's neighbour by searching every face with the same three vertices; the
    boundary as the faces of one tet, wound outwards; the boundary edges' neighbours;
    shared faces wound oppositely on their two sides (flat tets oriented to agree)."""
    t = np.asarray(t)
    m = len(t)
    assert topo.tets.shape == (m, 4)
    np.testing.assert_array_equal(np.sort(topo.tets, 1), np.sort(t, 1))
    vol = _det_volumes(v, topo.tets)
    longest = np.max([np.linalg.norm(v[topo.tets[:, i]] - v[topo.tets[:, j]], axis=1)
                      for i in range(4) for j in range(i + 1, 4)], axis=0)
    np.testing.assert_array_equal(topo.flat, ~(np.abs(vol) > FLAT_TOLERANCE * longest ** 3))
    assert np.all(vol[~topo.flat] > 0)
    np.testing.assert_allclose(topo.volumes, np.abs(vol), rtol=1e-12, atol=1e-15)
    flipped = _det_volumes(v, t) < 0
    assert topo.n_flipped == int(np.count_nonzero(flipped & ~topo.flat))
    owners = _faces_by_vertices(topo.tets)
    assert all(len(o) <= 2 for o in owners.values())
    tets = topo.tets.tolist()
    boundary = []
    for i in range(m):
        for f in range(4):
            key = tuple(sorted(tets[i][:f] + tets[i][f + 1:]))
            other = [o for o in owners[key] if o != (i, f)]
            if other:
                (j, g), = other
                assert (topo.neighbors[i, f], topo.neighbor_faces[i, f]) == (j, g), (i, f)
                mine = [tets[i][k] for k in FACES[f]]
                theirs = [tets[j][k] for k in FACES[g]]
                assert _winding(mine) == -_winding(theirs), (i, f, j, g)
            else:
                assert (topo.neighbors[i, f], topo.neighbor_faces[i, f]) == (-1, -1), (i, f)
                boundary.append((i, f))
    got = sorted(zip(topo.boundary_tets.tolist(), topo.boundary_local_faces.tolist()))
    assert got == sorted(boundary)
    for k, (i, f) in enumerate(zip(topo.boundary_tets, topo.boundary_local_faces)):
        tri = topo.boundary_faces[k]
        assert sorted(tri.tolist()) == sorted(tets[i][:f] + tets[i][f + 1:])
        if not topo.flat[i]:            # wound counter-clockwise seen from outside
            a, b, c = v[tri]
            assert np.dot(np.cross(b - a, c - a), v[tets[i][f]] - a) < 0, k
    # a boundary face's neighbour across the edge opposite each corner: a boundary face
    # with that edge, -1 where none has it
    by_edge = {}
    for k, tri in enumerate(topo.boundary_faces.tolist()):
        for c in range(3):
            by_edge.setdefault(tuple(sorted(tri[:c] + tri[c + 1:])), []).append(k)
    for k, tri in enumerate(topo.boundary_faces.tolist()):
        for c in range(3):
            others = [q for q in by_edge[tuple(sorted(tri[:c] + tri[c + 1:]))] if q != k]
            a = topo.boundary_adjacency[k, c]
            assert (a in others) if others else a == -1, (k, c)


def _error_of(v, t):
    """build_topology's error message for a mesh it refuses (asserted to refuse it)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(MeshError) as e:
            build_topology(v, t)
    return str(e.value)


def _listed(message, after):
    """The numbers a message lists after ``after`` (up to the next ';' or ')')."""
    part = message.split(after, 1)[1]
    part = part.split(")")[0].split(";")[0]
    return sorted(int(x) for x in part.replace(",", " ").split() if x.isdigit())


@pytest.mark.parametrize("hashed", [False, True])
def test_topology_has_its_properties(monkeypatch, hashed):
    """build_topology on meshes with boundaries, holes, shuffled, inverted and flat tets
    has the properties a brute-force search finds (:func:`_check_topology`), and refuses
    the meshes it must with the tets a plain search finds: a face of three tets, two tets
    of the same vertices, a fold (shared faces wound the same way after orienting every
    tet). ``hashed``: with the face keys hashed as for meshes whose vertex numbers are too
    far apart to pack."""
    from mi_tetvr.mesh import topology as topo
    if hashed:
        monkeypatch.setattr(topo, "KEY_BITS", 0)
    meshes = _test_meshes()
    for name in ("grid", "shuffled", "inverted", "holes", "flat tet"):
        v, t = meshes[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _check_topology(topo.build_topology(v, t), v, t)
    # the grid's boundary is one closed sphere: each edge in two faces, V - E + F = 2
    v, t = meshes["grid"]
    faces = topo.build_topology(v, t).boundary_faces
    edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), 1)
    _, per_edge = np.unique(edges, axis=0, return_counts=True)
    assert np.all(per_edge == 2)
    assert len(np.unique(faces)) - len(per_edge) + len(faces) == 2
    # a face shared by more than two tets: those tets
    v, t = meshes["non-manifold"]
    shared = [o for o in _faces_by_vertices(t).values() if len(o) > 2]
    message = _error_of(v, t)
    assert f"{len(shared)} face(s) shared by more than two tets" in message
    assert _listed(message, "tets involved:") == sorted(i for o in shared for i, _ in o)
    # duplicate tets: every tet whose four vertices another has too
    v, t = meshes["duplicate"]
    rows = [tuple(sorted(r)) for r in t.tolist()]
    twins = sorted(i for i, r in enumerate(rows) if rows.count(r) > 1)
    assert _listed(_error_of(v, t), "(same four vertices):") == twins
    # folds: the interior faces wound the same way on both sides of tets oriented by the
    # sign of their volume
    for name in ("moved vertex", "folded"):
        v, t = meshes[name]
        oriented = np.where((_det_volumes(v, t) < 0)[:, None], t[:, [1, 0, 2, 3]], t)
        bad, tets_of_bad = 0, set()
        for pair in _faces_by_vertices(oriented).values():
            if len(pair) == 2:
                (i, f), (j, g) = pair
                if _winding([oriented[i][k] for k in FACES[f]]) == \
                        _winding([oriented[j][k] for k in FACES[g]]):
                    bad += 1
                    tets_of_bad |= {i, j}
        message = _error_of(v, t)
        assert bad > 0 and message.startswith(f"{bad} interior face(s) are not shared"), name
        listed = _listed(message, "(tets ")
        assert listed and set(listed) <= tets_of_bad, name


def test_topology_with_vertex_numbers_past_2_21():
    """Meshes of more than 2**21 vertices: face keys packed exactly when the
    numbers of a face's vertices lie close (an offset mesh), hashed when they
    do not (spread at random over 2**22): both have the topology's properties,
    on the mesh renumbered."""
    from mi_tetvr.mesh import topology as topo
    v, t = _test_meshes()["holes"]
    n = 1 << 22
    rng = np.random.default_rng(5)
    small = topo.build_topology(v, t)
    for label, idx in (("offset", np.arange(len(v)) + n - len(v)),
                       ("spread", rng.choice(n, len(v), replace=False))):
        big = np.zeros((n, 3))
        big[idx] = v
        keys, pairs = topo._tet_face_keys(idx[t], n)
        assert (pairs is None) == (label == "offset"), label
        got = topo.build_topology(big, idx[t])
        # the same topology as the small mesh's, renumbered (checked against the search)
        np.testing.assert_array_equal(got.tets, idx[small.tets])
        np.testing.assert_array_equal(got.neighbors, small.neighbors)
        np.testing.assert_array_equal(got.neighbor_faces, small.neighbor_faces)
        np.testing.assert_array_equal(got.boundary_faces, idx[small.boundary_faces])
    _check_topology(small, v, t)


def test_topology_survives_colliding_face_hashes(monkeypatch):
    """Hashed face keys that collide are caught and the exact grouping takes
    over: two boundary faces given one key (confirmed by their vertex pairs),
    and keys modulo 7 (groups of many)."""
    from mi_tetvr.mesh import topology as topo
    monkeypatch.setattr(topo, "KEY_BITS", 0)
    real = topo._tet_face_keys
    v, t = _test_meshes()["holes"]
    boundary = np.flatnonzero(topo.build_topology(v, t).neighbors.ravel() < 0)

    def two_collide(tets, n):
        keys, pairs = real(tets, n)
        keys = keys.copy()
        keys[boundary[0]] = keys[boundary[-1]]
        return keys, pairs

    for fake in (two_collide, lambda tets, n: (real(tets, n)[0] % 7, real(tets, n)[1])):
        monkeypatch.setattr(topo, "_tet_face_keys", fake)
        _check_topology(topo.build_topology(v, t), v, t)


@pytest.mark.parametrize("path", ["spx/spx.vtk", "bluntfin/bluntfin_tets.vtu", "post/post.vtk",
                                  "a-grid/a_grid.vtk", "sfepy/cube_cylinder.mesh",
                                  "sfepy/wheelset.vtk"])
def test_topology_has_its_properties_on_real_meshes(path):
    """The same on the real meshes of ../shared/data/tets (all of them valid; the Blunt
    Fin's 77 flat tets oriented to agree with their neighbours)."""
    full = shared_data("tets", path)
    m = meshio.read(full)
    t = np.concatenate([c.data for c in m.cells if c.type == "tetra"])
    v = np.asarray(m.points, np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo = build_topology(v, t)
    _check_topology(topo, v, t)


def _convexity_cases():
    """Meshes whose boundary is convex or not, each with a name."""
    rng = np.random.default_rng(3)
    cube_v, cube_t = grid_mesh(4)
    cent = cube_v[cube_t].mean(1)
    yield "cube", cube_v, cube_t
    yield "jittered inside", *grid_mesh(5, jitter=0.15, seed=2)
    yield "L", cube_v, cube_t[~((cent[:, 0] > 0) & (cent[:, 1] > 0))]
    yield "cavity", cube_v, cube_t[np.abs(cent).max(1) > 0.5]
    yield "two cubes", np.concatenate([cube_v, cube_v + 3]), np.concatenate(
        [cube_t, cube_t + len(cube_v)])
    yield "corner tet off", cube_v, np.delete(cube_t, np.argmax(cent.sum(1)), 0)
    for name, shift in (("dent", -1e-3), ("bump", 1e-3)):
        v = cube_v.copy()
        v[np.argmin(np.abs(v - [1.0, 0.0, 0.0]).sum(1)), 0] += shift
        yield name, v, cube_t
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    yield "rotated", (cube_v @ R.T).astype(np.float32).astype(np.float64), cube_t
    try:
        from scipy.spatial import Delaunay
    except ImportError:
        return
    for i in range(3):
        p = rng.normal(size=(60, 3)) * [1.0, 0.5, 2.0]
        yield f"Delaunay {i}", p, Delaunay(p).simplices


@pytest.mark.parametrize("case", list(_convexity_cases()), ids=lambda c: c[0])
def test_convex_boundary_against_the_convex_hull(case):
    """A boundary is convex exactly where the mesh fills its convex hull
    (scipy's Qhull: equal volumes, to float32 rounding of the positions, as
    :data:`CONVEX_RTOL`), whatever its tets inside."""
    ConvexHull = pytest.importorskip("scipy.spatial").ConvexHull
    _, v, t = case
    topo = build_topology(v, t, warn=False)
    hull = ConvexHull(v[np.unique(topo.tets)]).volume
    fills = np.isclose(signed_volumes(v, topo.tets).sum(), hull, rtol=CONVEX_RTOL, atol=0)
    assert convex_boundary(v, topo.boundary_faces, topo.boundary_adjacency) == fills


def test_convex_boundary_refuses_an_open_surface():
    v, t = grid_mesh(2)
    topo = build_topology(v, t)
    faces, adj = topo.boundary_faces, topo.boundary_adjacency.copy()
    assert convex_boundary(v, faces, adj)
    adj[0, 0] = -1                              # (an edge with one face)
    assert not convex_boundary(v, faces, adj)
