"""Several tet meshes with different optical models in one scene: a color
mesh, two scalar meshes post-classified by different transfer functions and
an absorption-only mesh, disjoint, each walked with its own model; against
the float64 reference of several meshes (every mesh's pieces merged in depth
order, ``tests.reference.reference_render_meshes``)."""
import numpy as np
import pytest

import mitsuba as mi
import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from tests.helpers import Problem, rays_at, render_rays
from tests.reference import reference_render_meshes
from tests.render.test_gradients import check_fd, check_forward_reverse

TOL = 3e-3
RESOLUTION = 32
BG = (0.2, 0.3, 0.4)
#: Each mesh's box (lo, hi): disjoint.
BOXES = {"color": ((-2.2, -1.0, -1.0), (-0.2, 1.0, 1.0)),
         "peaks": ((0.2, -1.0, -1.0), (2.2, 1.0, 1.0)),
         "ramp": ((-1.0, 1.3, -1.0), (1.0, 2.3, 1.0)),
         "xray": ((-1.0, -2.3, -1.0), (1.0, -1.3, 1.0))}
TFS = {"peaks": ([[0.0, 0.2, 0.2, 0.9], [0.5, 0.9, 0.2, 0.1], [1.0, 0.1, 0.9, 0.2]],
                 [[0.0, 0.1], [0.45, 0.2], [0.5, 6.0], [0.55, 0.2], [1.0, 0.5]], (-1.0, 1.0)),
       "ramp": ([[0.0, 0.9, 0.8, 0.1], [1.0, 0.1, 0.3, 0.9]],
                [[0.0, 0.0], [1.0, 2.5]], (-0.5, 2.0))}


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """name -> (vertices, tets, dict entry, the mesh for the reference)."""
    import json
    from mi_tetvr.transfer import read_transfer_function
    rng = np.random.default_rng(50)
    out = {}
    for name, (lo, hi) in BOXES.items():
        V, T = grid_mesh(3, lo=lo, hi=hi, jitter=0.1, seed=len(out))
        if name in TFS:
            color, opacity, vr = TFS[name]
            path = tmp_path_factory.mktemp("tf") / f"{name}.json"
            path.write_text(json.dumps({"color": color, "opacity": opacity,
                                        "colorspace": "linear"}))
            scalar = np.sin(2.0 * V[:, 0] + 1.1 * V[:, 1]) + 0.5 * V[:, 2]
            entry = mi_tetvr.tetmesh_dict(V, T, scalar=scalar, transfer_function=str(path),
                                          value_min=vr[0], value_max=vr[1],
                                          tf_resolution=RESOLUTION)
            tc, to = read_transfer_function(path).texels(RESOLUTION)
            ref = dict(vertices=V, tets=T, scalar=scalar, tf_color=tc, tf_opacity=to,
                       value_range=vr)
        else:
            color = rng.uniform(0, 1, (len(V), 3))
            opacity = rng.uniform(0, 2, len(V))
            model = "absorption" if name == "xray" else "emission"
            entry = mi_tetvr.tetmesh_dict(V, T, color if model == "emission" else None,
                                          opacity, model=model)
            if model == "absorption":
                color = np.zeros_like(color)
            ref = dict(vertices=V, tets=T, color=color, opacity=opacity)
        out[name] = (V, T, entry, ref)
    return out


def entry_t(o, d, lo, hi):
    """Where each ray enters the box (inf where it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (np.asarray(lo) - o) / d
        b = (np.asarray(hi) - o) / d
    t0 = np.nanmax(np.minimum(a, b), 1)
    t1 = np.nanmin(np.maximum(a, b), 1)
    return np.where(t1 >= np.maximum(t0, 0), t0, np.inf)


def scene_of(meshes, names):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                         "env": {"type": "constant", "radiance": {"type": "rgb", "value": BG}},
                         **{n: meshes[n][2] for n in names}})


def test_four_models_in_one_scene(meshes):
    """A color mesh, two post-classified meshes with their own transfer
    functions and value ranges, an absorption mesh: one image."""
    names = list(BOXES)
    scene = scene_of(meshes, names)
    assert len(scene.integrator().tet_groups(scene)) == 4
    rng = np.random.default_rng(51)
    o, d = rays_at(rng, 384, radius=6.0, target_extent=2.0)
    rgb, alpha = render_rays(scene, o, d)
    ref_rgb, ref_alpha = reference_render_meshes([meshes[n][3] for n in names], o, d,
                                                 background=BG)
    seen = [(entry_t(o, d, *BOXES[n]) < np.inf).sum() for n in names]
    assert min(seen) > 30, seen
    # rays through two meshes, in either order
    assert (np.isfinite(np.stack([entry_t(o, d, *BOXES[n]) for n in names], 1)).sum(1)
            > 1).sum() > 30
    err = np.abs(rgb - ref_rgb).max()
    assert err < TOL, f"max |rgb - reference| = {err:.2e}"
    assert np.abs(alpha - ref_alpha).max() < TOL


def test_gradients_across_models(meshes):
    """Colors of one mesh, the scalar of a post-classified one and the texels
    of another, in one scene: adjoint against finite differences, forward
    against reverse."""
    names = ["color", "peaks", "ramp"]
    scene = scene_of(meshes, names)
    keys = ("color.vertex_color", "peaks.vertex_scalar", "ramp.tf_opacity")
    rng = np.random.default_rng(52)
    o, d = rays_at(rng, 96, radius=6.0, target_extent=1.8)
    problem = Problem(meshes["color"][:2], o, d, rng, scene=scene, keys=keys)
    check_forward_reverse(problem, check_fd(problem, rng, keys=keys), rng, trials=1)
