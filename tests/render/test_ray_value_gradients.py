"""Derivatives of the ``tetproj`` images (isosurfaces, slices, maximum and
minimum intensity projections) through ``mi.render``: forward mode against
central finite differences of the rendered images on the pixels where the
image is smooth in the parameter (differences at steps h and h/2, and on
either side, agree: not across a silhouette, the slice's rim, a tie of the
maximum or a kink of the transfer function), and
reverse mode against forward mode."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import check_derivatives

SIZE = 24
RANGE = (-1.0, 1.0)
RESOLUTION = 64
#: Mid-texel, so that the isovalue's color is linear in it around here.
ISO = RANGE[0] + 38.0 * (RANGE[1] - RANGE[0]) / RESOLUTION


def field_of(V):
    return np.sin(2.2 * V[:, 0] + 1.3 * V[:, 1]) * np.cos(1.7 * V[:, 2])


def scene_of(mode, tf, **integrator):
    V, T = grid_mesh(4, jitter=0.12, seed=7)
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetproj", "mode": mode, **integrator},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=[2.5, 1.5, 3.0], target=[0, 0, 0], up=[0, 1, 0])
                   @ mi.ScalarTransform4f().scale([1.6, 1.6, 1]),
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE,
                            "pixel_format": "rgb", "rfilter": {"type": "box"}}},
        "m": mi_tetvr.tetmesh_dict(V, T, scalar=field_of(V), transfer_function=tf,
                                   value_min=RANGE[0], value_max=RANGE[1],
                                   tf_resolution=RESOLUTION)})


@pytest.fixture(scope="module")
def iso_scene():
    return scene_of("iso", "viridis", iso=f"{ISO},-0.5")


def test_isosurface_gradient_wrt_scalars(iso_scene):
    n = len(np.array(mi.traverse(iso_scene)["m.vertex_scalar"]))
    direction = np.random.default_rng(1).normal(size=n)
    check_derivatives(iso_scene, "m.vertex_scalar", direction, 2e-3, 0.8)


def test_isosurface_gradient_wrt_the_isovalues(iso_scene):
    check_derivatives(iso_scene, "integrator.iso", [1.0, 0.5], 2e-3, 0.8)


def test_isosurface_gradient_wrt_positions(iso_scene):
    n = len(np.array(mi.traverse(iso_scene)["m.vertex_positions"]))
    direction = np.random.default_rng(2).normal(size=n)
    check_derivatives(iso_scene, "m.vertex_positions", direction, 2e-3, 0.7)


def test_isosurface_gradient_wrt_the_transfer_function(iso_scene):
    n = len(np.array(mi.traverse(iso_scene)["m.tf_color"]))
    direction = np.random.default_rng(4).normal(size=n)
    check_derivatives(iso_scene, "m.tf_color", direction, 1e-2, 0.95)


@pytest.mark.parametrize("mode, integrator", [
    ("slice", {"origin": [0.1, 0.0, -0.05], "normal": [0.3, 0.2, 1.0]}),
    ("max", {}), ("min", {})])
@pytest.mark.parametrize("key", ["m.vertex_scalar", "m.vertex_positions"])
def test_slice_and_projection_gradients(mode, integrator, key):
    scene = scene_of(mode, "gray", **integrator)
    n = len(np.array(mi.traverse(scene)[key]))
    direction = np.random.default_rng(5).normal(size=n)
    check_derivatives(scene, key, direction, 2e-3, 0.7)
