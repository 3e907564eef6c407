"""Reading real mesh files: the VTK fallback, cell data, repairs and the
diagnostics that name the problem (numpy, meshio, pyvista; no Mitsuba)."""
import warnings

import meshio
import numpy as np
import pytest

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.io import read_mesh_file, read_tetmesh, write_tetmesh
from mi_tetvr.mesh.refine import select_by_attribute
from mi_tetvr.mesh.tetmesh import TetMesh
from mi_tetvr.mesh.topology import (FACES, MeshError, build_topology, face_keys, repair_tets,
                                    signed_volumes)

#: A legacy VTK file with an id array (``vtkIdType``, as ParaView and VTK
#: write global ids), which meshio does not know.
LEGACY_WITH_IDS = """# vtk DataFile Version 3.0
written by a solver
ASCII
DATASET UNSTRUCTURED_GRID
POINTS 5 float
0 0 0 1 0 0 0 1 0 0 0 1 1 1 1
CELLS 2 10
4 0 1 2 3
4 1 2 3 4
CELL_TYPES 2
10 10
POINT_DATA 5
SCALARS pressure float
LOOKUP_TABLE default
0 1 2 3 4
SCALARS GlobalNodeId vtkIdType
LOOKUP_TABLE default
10 11 12 13 14
"""


def test_legacy_vtk_meshio_rejects_is_read_by_vtk(tmp_path):
    p = tmp_path / "legacy.vtk"
    p.write_text(LEGACY_WITH_IDS)
    with pytest.raises(KeyError):       # the reason the fallback exists
        meshio.read(p)
    m = read_tetmesh(p)
    np.testing.assert_array_equal(m.tets, [[0, 1, 2, 3], [1, 2, 3, 4]])
    np.testing.assert_allclose(m.point_data["pressure"], [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(m.point_data["GlobalNodeId"], [10, 11, 12, 13, 14])


def test_string_arrays_are_dropped_with_a_warning(tmp_path):
    import pyvista as pv
    import vtk
    v, t = grid_mesh(1)
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: t}, v)
    grid.point_data["s"] = np.arange(len(v), dtype=float)
    names = vtk.vtkStringArray()
    names.SetName("label")
    for i in range(len(v)):
        names.InsertNextValue(f"node{i}")
    grid.GetPointData().AddArray(names)
    p = tmp_path / "strings.vtu"
    grid.save(p)
    with pytest.warns(UserWarning, match=r"non-numeric point arrays \['label'\]"):
        m = read_tetmesh(p)
    np.testing.assert_allclose(m.point_data["s"], np.arange(len(v)))
    assert "label" not in m.point_data


@pytest.mark.parametrize("name", ["empty.vtk", "empty.vtu", "empty.msh"])
def test_unreadable_file_raises_with_reasons(tmp_path, name):
    p = tmp_path / name
    p.write_text("")
    with pytest.raises(MeshError, match="cannot read mesh") as e:
        read_tetmesh(p)             # an exception, not meshio's SystemExit
    assert "meshio:" in str(e.value)
    assert ("VTK:" in str(e.value)) == name.endswith((".vtk", ".vtu"))
    with pytest.raises(FileNotFoundError):
        read_mesh_file(tmp_path / "missing.vtu")


def test_cell_data_listed_and_averaged_onto_vertices(tmp_path):
    v, t = grid_mesh(2, jitter=0.1)
    stress = np.random.default_rng(0).random(len(t))
    p = tmp_path / "fea.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)], cell_data={"stress": [stress]}))
    m = read_tetmesh(p)
    info = m.summary()["arrays"]["stress"]
    assert info["kind"] == "cell" and info["shape"] == [len(t)]
    assert info["range"] == pytest.approx([stress.min(), stress.max()])
    # a transfer function cannot use it until it is point data, and says so
    from mi_tetvr.transfer import TransferFunction
    tf = TransferFunction([0, 1], [[0, 0, 0], [1, 1, 1]], [0, 1], [0, 1])
    with pytest.raises(MeshError, match="cell_to_point"):
        read_tetmesh(p, transfer_function=tf, scalar="stress")
    m = read_tetmesh(p, cell_to_point=True)
    # reference: the mean over the tets around each vertex
    total, count = np.zeros(len(v)), np.zeros(len(v))
    for tet, value in zip(t, stress):
        total[tet] += value
        count[tet] += 1
    np.testing.assert_allclose(m.point_data["stress"], total / count, rtol=1e-6)
    assert m.summary()["arrays"]["stress"]["kind"] == "point"
    # cell data survive writing
    write_tetmesh(tmp_path / "out.vtu", read_tetmesh(p))
    np.testing.assert_allclose(read_tetmesh(tmp_path / "out.vtu").cell_data["stress"], stress)


def folded_grid():
    """A 3^3 grid with one interior vertex pushed through the opposite faces
    of two of its tets: exactly those two are inverted."""
    v, t = grid_mesh(3)
    v = v.copy()
    centre = np.flatnonzero(np.all(np.isclose(v, -1 / 3), axis=1))[0]
    for step in np.linspace(0, 1, 201)[1:]:
        moved = v.copy()
        moved[centre] += step * np.array([0.9, 0.5, 0.2])
        if (signed_volumes(moved, t) < 0).sum() >= 2:
            return moved, t
    raise AssertionError("no fold")


def test_folded_tets_refused_then_repaired(tmp_path):
    v, t = folded_grid()
    inverted = np.flatnonzero(signed_volumes(v, t) < 0)
    assert len(inverted) == 2
    with pytest.raises(MeshError, match="folds over itself.*repair"):
        build_topology(v, t, warn=False)
    keep, report = repair_tets(v, t)
    assert report["folded"] == inverted.tolist()
    assert report["flat"] == report["duplicate"] == report["repeated_vertex"] == []
    topo = build_topology(v, t[keep], warn=False)
    # the two tets' faces that were interior are now boundary faces
    b0, b1 = report["boundary_faces"]
    assert b0 == len(build_topology(*grid_mesh(3), warn=False).boundary_faces)
    assert b1 == len(topo.boundary_faces) > b0
    p = tmp_path / "folded.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)]))
    with pytest.warns(UserWarning, match="repair dropped 2 of 162 tets"):
        m = read_tetmesh(p, repair=True)
    assert len(m.tets) == 160 and m.topology.n_tets == 160


def test_repair_duplicates_and_degenerate():
    v, t = grid_mesh(1)
    t = np.concatenate([t, t[:1], [[0, 0, 1, 2]]])
    flat_v = np.concatenate([v, [[0.0, 0.0, -1.0]]])           # in the plane z = -1
    t = np.concatenate([t, [[0, 2, 4, len(v)]]])
    keep, report = repair_tets(flat_v, t)
    assert report["duplicate"] == [6] and report["repeated_vertex"] == [7]
    assert report["flat"] == [8] and keep.sum() == 6
    with pytest.raises(MeshError, match="duplicate tets.*repair"):
        TetMesh(flat_v, t[[0, 1, 2, 3, 4, 5, 6]])


def test_small_tets_are_not_zero_volume():
    """Tets 1e-5 times the size of others in the same mesh (volumes ~1e-17,
    far below 1e-12 times the bounding-box diagonal cubed) are not flat."""
    v, t = grid_mesh(3)
    v = np.concatenate([v, v * 1e-5 + 3.0])
    t = np.concatenate([t, t + len(v) // 2])
    assert signed_volumes(v, t).min() < 1e-12 * 3.0 ** 3 * 1e-3
    s = TetMesh(v, t).summary()
    assert s["zero_volume_tets"] == 0 and s["inverted_tets_fixed"] == 0
    assert s["slivers"] == 0 and s["quality_min"] > 0.5


def test_unused_settings_are_errors(tmp_path):
    v, t = grid_mesh(1)
    p = tmp_path / "s.vtu"
    meshio.write(p, meshio.Mesh(v, [("tetra", t)],
                                point_data={"s": np.arange(len(v), dtype=float)}))
    for kw in ({"scalar": "s"}, {"value_range": (0, 1)}, {"opacity_scale": 2.0}):
        with pytest.raises(ValueError, match="no transfer function"):
            read_tetmesh(p, **kw)


def test_refine_selection_by_magnitude_or_value():
    data = {"f": np.array([0.5, -3.0, 2.0, 1.0])}
    assert select_by_attribute(data, "f", 0.25).tolist() == [1]
    assert select_by_attribute(data, "f", 0.25, rank="value").tolist() == [2]
    assert select_by_attribute(data, "f", 0.5, rank="value").tolist() == [2, 3]
    with pytest.raises(ValueError, match="rank it by magnitude"):
        select_by_attribute({"c": np.ones((4, 3))}, "c", 0.5, rank="value")


def test_face_keys_of_repaired_boundary_are_faces_of_dropped_tets():
    v, t = folded_grid()
    keep, _ = repair_tets(v, t)
    def boundary(tt):
        keys, counts = np.unique(face_keys(tt[:, FACES].reshape(-1, 3)), return_counts=True)
        return set(keys[counts == 1])
    opened = boundary(t[keep]) - boundary(t)
    dropped = set(face_keys(t[~keep][:, FACES].reshape(-1, 3)))
    assert opened and opened <= dropped
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        build_topology(v, t[keep])


def test_reading_in_parallel_leaves_stdout_and_stderr_alone(tmp_path):
    """Mitsuba loads a scene's shapes on several threads; the reader's
    capture of meshio's messages must leave ``sys.stdout``/``sys.stderr`` as
    they were (a race left the process writing into a reader's buffer, and
    the command line's error messages vanished)."""
    import sys
    from concurrent.futures import ThreadPoolExecutor
    v, t = grid_mesh(3)
    path = tmp_path / "m.vtu"
    write_tetmesh(path, TetMesh(v, t))
    out, err = sys.stdout, sys.stderr
    with ThreadPoolExecutor(8) as pool:
        meshes = list(pool.map(lambda _: read_tetmesh(path), range(64)))
    assert all(len(m.tets) == len(t) for m in meshes)
    assert sys.stdout is out and sys.stderr is err
