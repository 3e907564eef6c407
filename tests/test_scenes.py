"""Scenes the project builds itself: the ``tetmesh`` shape built in Python
(:func:`mi_tetvr.tetmesh_shape`) with the topology handed to it, and a plugin's
refusal as its own exception when Mitsuba builds the scene."""
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
import mi_tetvr.mesh.topology
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import rays_at, render_rays


@pytest.fixture(scope="module")
def arrays():
    """A jittered 3^3 grid with three tets listed inverted (re-oriented by
    the topology: its tets differ from the arrays'), random colors and opacities."""
    v, t = grid_mesh(3, jitter=0.15, seed=1)
    t = t.copy()
    t[[0, 7, 20]] = t[[0, 7, 20]][:, [1, 0, 2, 3]]
    rng = np.random.default_rng(3)
    return v, t, rng.uniform(0, 1, (len(v), 3)), rng.uniform(0, 3, len(v))


def scene_of(volume):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"}, "volume": volume})


def no_topology_built(monkeypatch):
    """Every topology built from here on raises (however build_topology was imported)."""
    def refuse(*args, **kwargs):
        raise AssertionError("topology built again")
    monkeypatch.setattr(mi_tetvr.mesh.topology, "_build_topology", refuse)


def test_a_handed_topology_is_not_built_again(arrays, monkeypatch):
    """A shape built from a TetMesh (its topology), or from a dict entry and the
    topology of its arrays, builds no topology, is named by its key in the scene,
    and renders what the same arrays loaded by Mitsuba render."""
    v, t, color, opacity = arrays
    o, d = rays_at(np.random.default_rng(0), 200)
    with pytest.warns(UserWarning, match="re-oriented"):
        loaded = scene_of(mi_tetvr.tetmesh_dict(v, t, color, opacity))
    expected = render_rays(loaded, o, d)
    assert expected[1].max() > 0.5          # the rays see the volume
    with pytest.warns(UserWarning, match="re-oriented"):
        mesh = mi_tetvr.TetMesh(v, t, color, opacity)
        topology = mesh.topology
    oriented = mi_tetvr.tetmesh_dict(v, topology.tets, color, opacity)

    no_topology_built(monkeypatch)
    with pytest.raises(AssertionError, match="built again"):     # the guard holds
        mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t, color, opacity))
    for shape in (mi_tetvr.tetmesh_shape(mesh),
                  mi_tetvr.tetmesh_shape(oriented, topology=topology)):
        scene = scene_of(shape)
        assert scene.shapes()[0].id() == "volume"
        assert sorted(mi.traverse(scene).keys()) == sorted(mi.traverse(loaded).keys())
        rgb, alpha = render_rays(scene, o, d)
        np.testing.assert_allclose(rgb, expected[0], atol=1e-6)
        np.testing.assert_allclose(alpha, expected[1], atol=1e-6)


def test_a_handed_topology_must_be_that_of_the_arrays(arrays):
    v, t, color, opacity = arrays
    other = mi_tetvr.build_topology(*grid_mesh(2), warn=False)
    with pytest.raises(ValueError, match="not that of these tets"):
        mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t, color, opacity), topology=other)
    with pytest.raises(ValueError, match="not with a 'filename'"):
        mi_tetvr.tetmesh_shape({"type": "tetmesh", "filename": "x.vtu"}, topology=other)


def test_a_built_shape_reads_its_properties_as_mitsuba_does():
    """Properties are checked as ``mi.load_dict`` checks them: one the shape
    does not read is refused (``repair`` is read with a file only), and the
    shape's own checks raise their ValueError."""
    small = mi_tetvr.TetMesh(*grid_mesh(1))
    with pytest.raises(RuntimeError, match="unreferenced property"):
        mi.load_dict(mi_tetvr.tetmesh_dict(small.vertices, small.tets, repair=True))
    with pytest.raises(ValueError, match=r"^tetmesh: unknown property 'repair'$"):
        mi_tetvr.tetmesh_shape(small, repair=True)
    with pytest.raises(ValueError, match=r"^tetmesh: model must be one of"):
        mi_tetvr.tetmesh_shape(small, model="xray")
    shape = mi_tetvr.tetmesh_shape(small, model="absorption",
                                   to_world=mi.ScalarTransform4f().translate([0, 0, 2]))
    assert shape.optical_model.__name__ == "Absorption"
    assert np.array(shape.bbox().min) == pytest.approx([-1, -1, 1])
