"""Intensity projections and slices (the ``tetproj`` integrator) against the
float64 references (``tests.reference.reference_projection``: every ray
clipped against every tet, the scalar's maximum, minimum and mean along it;
``reference_slice``: the point where the ray meets the plane located in
every tet)."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import project_rays, rays_at
from tests.reference import reference_projection, reference_slice

RANGE = (-1.0, 1.0)
RESOLUTION = 64


@pytest.fixture(scope="module")
def field():
    """A jittered grid and a smooth scalar with extremes inside the tets'
    faces (not only at vertices)."""
    V, T = grid_mesh(4, jitter=0.12, seed=7)
    scalar = np.sin(2.2 * V[:, 0] + 1.3 * V[:, 1]) * np.cos(1.7 * V[:, 2])
    return V, T, scalar


def scene_of(field, mode, integrator=None, **props):
    V, T, scalar = field
    return mi.load_dict({"type": "scene",
                         "integrator": {"type": "tetproj", "mode": mode, **(integrator or {})},
                         "mesh0": mi_tetvr.tetmesh_dict(
                             V, T, scalar=scalar, transfer_function="gray",
                             value_min=RANGE[0], value_max=RANGE[1],
                             tf_resolution=RESOLUTION, **props)})


@pytest.mark.parametrize("mode", ["max", "min", "mean"])
def test_projection_against_the_reference(field, mode):
    """Random rays (some missing the mesh): the projected scalar within 1e-5
    of the float64 reference's (max, min: the ends of the pieces; mean: the
    trapezoids over the length), the same rays met; the pixel is the
    transfer function's color at that value (here gray: its sRGB value is
    the normalised scalar, closed form)."""
    V, T, scalar = field
    o, d = rays_at(np.random.default_rng(11), 256, target_extent=1.3)
    ref, ref_met = reference_projection(V, T, scalar, o, d, mode)
    scene = scene_of(field, mode)
    color, met, value = project_rays(scene, o, d)
    assert 0 < np.count_nonzero(ref_met) < len(o)
    np.testing.assert_array_equal(met, ref_met)
    np.testing.assert_allclose(value[met], ref[met], atol=1e-5)
    from mi_tetvr.color import linear_to_srgb
    rgb = linear_to_srgb(color.T)
    # gray shows the normalised value t as the sRGB grey t (the texels hold it at
    # their centres, linear in between: within 2e-3), constant beyond the end texels
    t = (ref[met] - RANGE[0]) / (RANGE[1] - RANGE[0])
    t = np.clip(t, 0.5 / RESOLUTION, 1 - 0.5 / RESOLUTION)
    np.testing.assert_allclose(rgb[met], np.repeat(t[:, None], 3, 1), atol=2e-3)
    assert np.all(color[:, ~met] == 0)


@pytest.mark.parametrize("plane", [((0.1, -0.2, 0.05), (0.3, 0.5, 1.0)),
                                   ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))])
def test_slice_against_the_reference(field, plane):
    """A slice: the scalar where each ray meets the plane inside the mesh,
    equal to the float64 reference (the point's barycentric coordinates in
    every tet) to float32's rounding of the meeting point, which grows as
    the ray grazes the plane: 2e-6 / |d . n|; the same rays met, away from
    the mesh's boundary (where float32 and float64 may disagree on a point
    on it)."""
    V, T, scalar = field
    origin, normal = plane
    o, d = rays_at(np.random.default_rng(5), 256, target_extent=1.3)
    ref, ref_met = reference_slice(V, T, scalar, o, d, origin, normal)
    scene = scene_of(field, "slice", {"origin": list(origin), "normal": list(normal)})
    _, met, value = project_rays(scene, o, d)
    t = ((np.asarray(origin) - o) @ np.asarray(normal)) / (d @ np.asarray(normal))
    p = o + t[:, None] * d
    clear = np.all(np.abs(np.abs(p) - 1.0) > 1e-4, axis=1)      # not on the box's faces
    assert 0 < np.count_nonzero(ref_met & clear) < np.count_nonzero(clear)
    np.testing.assert_array_equal(met[clear], ref_met[clear])
    both = met & ref_met
    graze = np.abs(d @ (np.asarray(normal) / np.linalg.norm(normal)))
    assert np.all(np.abs(value[both] - ref[both]) <= 2e-6 / graze[both])


def test_projection_renders_and_refuses(field, tmp_path):
    """mi.render writes rgba (alpha where the mesh is met); a scene without a
    scalar, a second shape or a bad mode are refused with what to do; the
    mean's derivative passes say they do not exist."""
    V, T, scalar = field
    scene = scene_of(field, "max")
    sensor = mi.load_dict({"type": "orthographic", "to_world": mi.ScalarTransform4f().look_at(
        origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]) @ mi.ScalarTransform4f().scale(
        [1.5, 1.5, 1]), "film": {"type": "hdrfilm", "width": 12, "height": 12,
                                  "pixel_format": "rgba"}})
    img = np.array(mi.render(scene, sensor=sensor))
    assert img.shape == (12, 12, 4)
    assert img[6, 6, 3] == 1.0 and img[0, 0, 3] == 0.0
    plain = mi.load_dict({"type": "scene", "integrator": {"type": "tetproj"},
                          "m": mi_tetvr.tetmesh_dict(V, T)})
    # (Mitsuba's render wraps the error; the traceback shows it, chained)
    assert "transfer_function" in _raised(lambda: mi.render(plain, sensor=sensor))
    with pytest.raises(Exception, match="mode must be one of"):
        mi.load_dict({"type": "tetproj", "mode": "sum"})
    mean = scene_of(field, "mean")
    params = mi.traverse(mean)
    dr.enable_grad(params["mesh0.vertex_scalar"])
    assert "mean intensity projection is not differentiable" in _raised(
        lambda: dr.backward(mi.render(mean, params, sensor=sensor)))


def _raised(fn):
    """The messages of the exception ``fn`` raises and of those it chains."""
    try:
        fn()
    except Exception as e:          # noqa: BLE001 (the chain is what is checked)
        out, seen = [], e
        while seen is not None:
            out.append(str(seen))
            seen = seen.__cause__ or seen.__context__
        return " | ".join(out)
    raise AssertionError("nothing was raised")
