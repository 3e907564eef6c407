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


def test_isosurface_gradients(iso_scene):
    """W.r.t. the scalars, the isovalues, the positions and the transfer
    function's colors."""
    params = mi.traverse(iso_scene)
    rng = np.random.default_rng(1)

    def along(key):
        return rng.normal(size=len(np.array(params[key])))
    check_derivatives(iso_scene, {
        "m.vertex_scalar": (along("m.vertex_scalar"), 2e-3, 0.8),
        "integrator.iso": ([1.0, 0.5], 2e-3, 0.8),
        "m.vertex_positions": (along("m.vertex_positions"), 2e-3, 0.7),
        "m.tf_color": (along("m.tf_color"), 1e-2, 0.95)})


@pytest.mark.parametrize("mode, integrator", [
    ("slice", {"origin": [0.1, 0.0, -0.05], "normal": [0.3, 0.2, 1.0]}),
    ("max", {}), ("min", {})])
def test_slice_and_projection_gradients(mode, integrator):
    """W.r.t. the scalars and the positions."""
    scene = scene_of(mode, "gray", **integrator)
    params = mi.traverse(scene)
    rng = np.random.default_rng(5)
    check_derivatives(scene, {key: (rng.normal(size=len(np.array(params[key]))), 2e-3, 0.7)
                              for key in ("m.vertex_scalar", "m.vertex_positions")})
