"""View-dependent color: per-vertex spherical harmonics (``tetmesh`` ``sh``, the
:class:`~mi_tetvr.render.optical.ViewDependent` media), against SciPy's spherical
harmonics, the float64 reference renderer (each ray's vertex colors evaluated here at its
direction, integrated as the reference integrates color), finite differences, and the
plain color mesh they reduce to at degree 0."""
import numpy as np
import pytest

import mitsuba as mi

import mi_tetvr
from mi_tetvr.mesh.generate import blob_field, grid_mesh
from mi_tetvr.render.optical import sh_basis
from tests.helpers import Problem, check_along, rays_at, render_rays
from tests.reference import reference_render, reference_render_meshes

Y0 = 0.28209479177387814


def scipy_real_sh(d, degree):
    """The real spherical harmonics (Condon-Shortley phase, as 3DGS orders them:
    degree by degree, m from -l to l) from SciPy's complex ones: sqrt(2) Im Y_l^|m|
    for m < 0, Y_l^0, sqrt(2) Re Y_l^m for m > 0."""
    from scipy.special import sph_harm_y
    polar = np.arccos(np.clip(d[:, 2], -1, 1))
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), polar, azimuth)
            out.append(np.sqrt(2) * y.imag if m < 0 else
                       y.real if m == 0 else np.sqrt(2) * y.real)
    return np.stack(out, 1)


def test_the_basis_is_the_real_spherical_harmonics():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ours = np.stack(sh_basis(d, 3), 1)
    ref = scipy_real_sh(d, 3)
    assert np.abs(ours - ref).max() < 1e-12
    # and orthonormal over the sphere (a Fibonacci lattice of 20k points)
    n = 20000
    z = 1 - (2 * np.arange(n) + 1) / n
    phi = np.pi * (3 - np.sqrt(5)) * np.arange(n)
    q = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    Y = np.stack(sh_basis(q, 3), 1)
    assert np.abs(4 * np.pi * Y.T @ Y / n - np.eye(16)).max() < 1e-3


def colors_seen(sh, d):
    """(k, n, 3): each vertex's color seen along each of the directions ``d``."""
    Y = np.stack(sh_basis(d, int(round(np.sqrt(sh.shape[1]))) - 1), 1)   # (k, K)
    return np.maximum(np.einsum("rk,nkc->rnc", Y, sh) + 0.5, 0.0)


@pytest.fixture(scope="module")
def mesh():
    V, T = grid_mesh(4, jitter=0.1, seed=1)
    _, S = blob_field(V)
    sh = np.random.default_rng(2).normal(scale=0.35, size=(len(V), 16, 3))
    return V, T, S, sh


def scene_of(*shapes, **integrator):
    return mi.load_dict({"type": "scene", "integrator": {"type": "tetvr", **integrator},
                         **{f"m{k}": s for k, s in enumerate(shapes)}})


def test_render_matches_the_reference(mesh):
    """Degree 3 (16 RGB triples per vertex), some colors clamped at 0: within 1e-3 of
    the float64 reference on random rays."""
    V, T, S, sh = mesh
    o, d = rays_at(np.random.default_rng(3), 64)
    rgb, alpha = render_rays(scene_of(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=sh)), o, d)
    seen = colors_seen(sh, d)
    assert (seen == 0).any() and np.ptp(seen, axis=0).max() > 0.5   # clamped; view-dependent
    for r in range(len(o)):
        ref_rgb, ref_alpha = reference_render(V, T, seen[r], S, o[r:r + 1], d[r:r + 1])
        assert np.abs(rgb[r] - ref_rgb[0]).max() < 1e-3, r
        assert abs(alpha[r] - ref_alpha[0]) < 1e-3, r
    assert np.abs(rgb).max() > 0.1


def test_degree_zero_is_the_plain_color(mesh):
    V, T, S, _ = mesh
    C, _ = blob_field(V)
    o, d = rays_at(np.random.default_rng(4), 64)
    a = render_rays(scene_of(mi_tetvr.tetmesh_dict(V, T, opacity=S,
                                                   sh=((C - 0.5) / Y0)[:, None])), o, d)
    b = render_rays(scene_of(mi_tetvr.tetmesh_dict(V, T, C, S)), o, d)
    assert np.abs(a[0] - b[0]).max() < 1e-6 and np.abs(a[0]).max() > 0.1


def test_overlapping_a_color_mesh(mesh):
    """Walked with a color mesh it overlaps (the merged walk): against the reference of
    both as one medium."""
    V, T, S, sh = mesh
    VB, TB = grid_mesh(2, lo=(-0.4, -1.2, -0.3), hi=(1.3, 0.5, 1.1), jitter=0.1, seed=4)
    rng = np.random.default_rng(5)
    cB, oB = rng.uniform(0, 1, (len(VB), 3)), rng.uniform(0, 1.5, len(VB))
    scene = scene_of(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=sh),
                     mi_tetvr.tetmesh_dict(VB, TB, cB, oB))
    o, d = rays_at(rng, 24)
    rgb, alpha = render_rays(scene, o, d)
    seen = colors_seen(sh, d)
    for r in range(len(o)):
        ref, ref_a = reference_render_meshes(
            [dict(vertices=V, tets=T, color=seen[r], opacity=S),
             dict(vertices=VB, tets=TB, color=cB, opacity=oB)], o[r:r + 1], d[r:r + 1])
        assert np.abs(rgb[r] - ref[0]).max() < 3e-3 and abs(alpha[r] - ref_a[0]) < 3e-3, r


@pytest.mark.parametrize("key, h", [("m0.vertex_sh", 1e-3), ("m0.vertex_opacity", 1e-3)])
def test_gradients_against_finite_differences(mesh, key, h):
    """Reverse mode against central differences (5 %) along random directions, forward
    against reverse (1 %); degree 1 (its coefficients small enough that no color is
    clamped)."""
    V, T, S, sh = mesh
    small = 0.2 * sh[:, :4]
    rng = np.random.default_rng(6)
    o, d = rays_at(rng, 48)
    assert colors_seen(small, d).min() > 0
    problem = Problem(None, o, d, rng, keys=("m0.vertex_sh", "m0.vertex_opacity"),
                      scene=scene_of(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=small)))
    check_along(problem, key, h, rng)


def test_a_mesh_file_carries_its_coefficients(mesh, tmp_path):
    """A mesh file with a point array ``sh`` (n, 3 K) loads view-dependent, and renders
    as the tensors do; ``mi.traverse`` names them ``<id>.vertex_sh``."""
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    V, T, S, sh = mesh
    path = tmp_path / "sh.vtu"
    write_tetmesh(path, TetMesh(V, T, None, S, {"sh": sh.reshape(len(V), -1)}))
    from_file = scene_of({"type": "tetmesh", "filename": str(path)})
    assert "m0.vertex_sh" in mi.traverse(from_file).keys()
    o, d = rays_at(np.random.default_rng(7), 32)
    a = render_rays(from_file, o, d)[0]
    b = render_rays(scene_of(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=sh)), o, d)[0]
    assert np.abs(a - b).max() < 1e-6


def test_refusals(mesh):
    V, T, S, sh = mesh
    with pytest.raises(Exception, match="1, 4, 9 or 16"):
        mi.load_dict(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=sh[:, :5]))
    with pytest.raises(Exception, match="no transfer function, albedo"):
        mi.load_dict(mi_tetvr.tetmesh_dict(V, T, opacity=S, sh=sh, albedo=0.5))
