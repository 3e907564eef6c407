"""Topology, validation and file I/O of tet meshes (numpy only)."""
import warnings

import meshio
import numpy as np
import pytest

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.io import read_tetmesh, write_tetmesh
from mi_tetvr.mesh.topology import FACES, MeshError, TetMesh, build_topology, quality, signed_volumes


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
