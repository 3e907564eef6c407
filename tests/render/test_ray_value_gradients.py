"""Derivatives of the ``tetproj`` images (isosurfaces, slices, maximum and
minimum intensity projections) through ``mi.render``: forward mode against
central finite differences of the rendered images on the pixels where the
image is smooth in the parameter (differences at steps h and h/2, and on
either side, agree: not across a silhouette, the slice's rim, a tie of the
maximum or a kink of the transfer function), and
reverse mode against forward mode."""
import mitsuba as mi
import numpy as np
import pytest

from tests.helpers import check_derivatives, grid_field_scene

SIZE = 24
RANGE = (-1.0, 1.0)
RESOLUTION = 64
#: Mid-texel, so that the isovalue's color is linear in it around here.
ISO = RANGE[0] + 38.0 * (RANGE[1] - RANGE[0]) / RESOLUTION


def scene_of(mode, tf, **integrator):
    return grid_field_scene({"type": "tetproj", "mode": mode, **integrator}, tf, SIZE,
                            RESOLUTION)


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
