"""Checks of the brute-force reference renderer against closed forms / scipy quadrature."""

import numpy as np
import pytest
from scipy import integrate

from tests.reference import reference_render

UNIT_TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
UNIT_TET_T = np.array([[0, 1, 2, 3]])
# second tet sharing the face x+y+z=1 with the unit tet
TWO_TET_V = np.vstack([UNIT_TET_V, [[1.0, 1.0, 1.0]]])
TWO_TET_T = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def _unit_tet_general_ray():
    """Ray o=(0.1,0.2,-1), d~(0.1,0.05,1): enters z=0 at u=1, exits x+y+z=1 at u=1.7/1.15."""
    o = np.array([0.1, 0.2, -1.0])
    dr = np.array([0.1, 0.05, 1.0])
    u_in, u_out = 1.0, 1.7 / 1.15
    return o, dr, o + u_in * dr, o + u_out * dr, (u_out - u_in) * np.linalg.norm(dr)


# (1) constant color and opacity ---------------------------------------------------------
@pytest.mark.parametrize("a", [0.0, 0.3, 2.0, 25.0, 1e4])
def test_constant_single_tet(a):
    c = np.array([0.2, 0.5, 0.9])
    o1, d1 = np.array([0.1, 0.1, -1.0]), np.array([0.0, 0.0, 3.0])   # L = 0.8
    o2, d2, _, _, L2 = _unit_tet_general_ray()
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, np.tile(c, (4, 1)), np.full(4, a),
                                  [o1, o2], [d1, d2])
    for i, L in enumerate([0.8, L2]):
        A = np.exp(-a * L)
        np.testing.assert_allclose(rgb[i], c * (1 - A), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(alpha[i], 1 - A, rtol=1e-12, atol=1e-14)


# (2) zero opacity / misses -----------------------------------------------------------------
def test_zero_opacity_and_miss():
    bg = np.array([0.3, 0.6, 0.1])
    col = np.random.default_rng(0).random((4, 3))
    o = [[0.1, 0.1, -1.0], [2.0, 2.0, -1.0], [0.1, 0.1, 2.0]]   # hit, miss, behind
    d = [[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]]
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, col, np.zeros(4), o, d, background=bg)
    np.testing.assert_array_equal(rgb, np.tile(bg, (3, 1)))
    np.testing.assert_array_equal(alpha, 0.0)
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, col, np.ones(4), o, d, background=bg)
    assert alpha[0] > 0.5
    np.testing.assert_array_equal(rgb[1:], np.tile(bg, (2, 1)))
    np.testing.assert_array_equal(alpha[1:], 0.0)


# (3) linear color, constant opacity ------------------------------------------------------
def _affine_color(p):
    M = np.array([[0.7, -0.2, 0.4], [0.1, 0.9, -0.3], [-0.5, 0.3, 0.8]])
    return p @ M.T + np.array([0.2, 0.1, 0.6])


@pytest.mark.parametrize("a", [0.05, 1.0, 7.0, 300.0])
def test_linear_color_constant_opacity(a):
    o, dr, p_in, p_out, L = _unit_tet_general_ray()
    c0, c1 = _affine_color(p_in), _affine_color(p_out)
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, _affine_color(UNIT_TET_V),
                                  np.full(4, a), [o], [dr])
    A = np.exp(-a * L)
    expect = (1 - A) * c0 + (A - (1 - A) / (a * L)) * (c0 - c1)
    np.testing.assert_allclose(rgb[0], expect, rtol=1e-11, atol=1e-13)
    np.testing.assert_allclose(alpha[0], 1 - A, rtol=1e-12)


# (4) constant color, linear opacity ------------------------------------------------------
@pytest.mark.parametrize("scale", [0.01, 1.0, 20.0, 5e3])
def test_constant_color_linear_opacity(scale):
    c = np.array([0.9, 0.4, 0.05])
    g = np.array([2.0, -0.5, 3.0])

    def sigma(p):  # affine, vanishes at the origin vertex, >= 0 on the tet
        return scale * (p @ np.maximum(g, 0.0))

    o, dr, p_in, p_out, L = _unit_tet_general_ray()
    o2, d2 = np.array([-0.1, -0.3, -1.0]), np.array([0.1, 0.3, 1.0])  # enters at vertex 0 (u=1)
    p2_in = np.zeros(3)
    u_out = 1.0 + 1.0 / 1.4  # x+y+z = 1.4 (u - 1) = 1
    p2_out = o2 + u_out * d2
    L2 = (u_out - 1.0) * np.linalg.norm(d2)
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, np.tile(c, (4, 1)), sigma(UNIT_TET_V),
                                  [o, o2], [dr, d2])
    for i, (pa, pb, LL) in enumerate([(p_in, p_out, L), (p2_in, p2_out, L2)]):
        tau = 0.5 * LL * (sigma(pa) + sigma(pb))
        np.testing.assert_allclose(rgb[i], c * (1 - np.exp(-tau)), rtol=1e-11, atol=1e-14)
        np.testing.assert_allclose(alpha[i], 1 - np.exp(-tau), rtol=1e-11, atol=1e-14)


def test_linear_color_and_opacity_vs_scipy():
    o, dr, p_in, p_out, L = _unit_tet_general_ray()
    sv = np.array([0.3, 4.0, 0.0, 2.5])
    cv = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.5]], dtype=float)
    # barycentrics of the unit tet: (1-x-y-z, x, y, z)
    bary = lambda p: np.array([1 - p.sum(), p[0], p[1], p[2]])  # noqa: E731
    u = (p_out - p_in) / L
    sig = lambda s: bary(p_in + s * u) @ sv  # noqa: E731
    tau = lambda s: integrate.quad(sig, 0, s, epsabs=1e-14, epsrel=1e-13)[0]  # noqa: E731
    expect = [integrate.quad(lambda s: sig(s) * (bary(p_in + s * u) @ cv[:, ch]) * np.exp(-tau(s)),
                             0, L, epsabs=1e-14, epsrel=1e-12)[0] for ch in range(3)]
    rgb, alpha = reference_render(UNIT_TET_V, UNIT_TET_T, cv, sv, [o], [dr])
    np.testing.assert_allclose(rgb[0], expect, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(alpha[0], 1 - np.exp(-tau(L)), rtol=1e-11)


# (5) two tets sharing a face, origin inside, t_max ---------------------------------------------
def _two_tet_bary(p):
    """Barycentrics of p w.r.t. tet 2 = ((1,0,0),(0,1,0),(0,0,1),(1,1,1))."""
    d = (p.sum() - 1.0) / 2.0
    return np.array([p[0] - d, p[1] - d, p[2] - d, d])


def _lin_seg(c0, c1, a, L):
    A = np.exp(-a * L)
    return (1 - A) * c0 + (A - (1 - A) / (a * L)) * (c0 - c1), A


def test_two_tets_composited_by_hand():
    rng = np.random.default_rng(1)
    col = rng.random((5, 3))
    a = 1.7
    # ray x=0.1, y=0.2 along +z: tet1 for z in [0,0.7], tet2 for z in [0.7,0.9]
    pa, pb, pc = np.array([0.1, 0.2, 0.0]), np.array([0.1, 0.2, 0.7]), np.array([0.1, 0.2, 0.9])
    b1 = lambda p: np.array([1 - p.sum(), p[0], p[1], p[2]])  # noqa: E731
    ca, cb1 = b1(pa) @ col[:4], b1(pb) @ col[:4]
    cb2, cc = _two_tet_bary(pb) @ col[1:], _two_tet_bary(pc) @ col[1:]
    np.testing.assert_allclose(cb1, cb2, rtol=1e-13)  # continuity across the shared face
    C1, A1 = _lin_seg(ca, cb1, a, 0.7)
    C2, A2 = _lin_seg(cb2, cc, a, 0.2)
    bg = np.array([0.05, 0.1, 0.2])
    expect = C1 + A1 * C2 + A1 * A2 * bg
    # ray from below, ray from above (reversed order), ray starting inside tet 1
    o = [[0.1, 0.2, -2.0], [0.1, 0.2, 3.0], [0.1, 0.2, 0.3]]
    d = [[0, 0, 1.0], [0, 0, -0.5], [0, 0, 1.0]]
    rgb, alpha = reference_render(TWO_TET_V, TWO_TET_T, col, np.full(5, a), o, d, background=bg)
    np.testing.assert_allclose(rgb[0], expect, rtol=1e-11)
    np.testing.assert_allclose(alpha[0], 1 - np.exp(-a * 0.9), rtol=1e-12)
    Cr2, Ar2 = _lin_seg(cc, cb2, a, 0.2)
    Cr1, Ar1 = _lin_seg(cb1, ca, a, 0.7)
    np.testing.assert_allclose(rgb[1], Cr2 + Ar2 * Cr1 + Ar1 * Ar2 * bg, rtol=1e-11)
    # starting inside: z from 0.3 (t=0) to 0.9
    pi = np.array([0.1, 0.2, 0.3])
    C1i, A1i = _lin_seg(b1(pi) @ col[:4], cb1, a, 0.4)
    np.testing.assert_allclose(rgb[2], C1i + A1i * C2 + A1i * A2 * bg, rtol=1e-11)
    np.testing.assert_allclose(alpha[2], 1 - np.exp(-a * 0.6), rtol=1e-12)


def test_origin_inside_and_t_max_constant():
    c, a = np.array([0.3, 0.7, 1.0]), 2.3
    col = np.tile(c, (5, 1))
    o = [[0.1, 0.2, 0.3], [0.1, 0.2, 0.3], [0.1, 0.2, -1.0], [0.1, 0.2, -1.0]]
    d = [[0, 0, 1.0], [0, 0, -1.0], [0, 0, 2.0], [0, 0, 1.0]]
    tmax = np.array([np.inf, np.inf, 1.5, 0.5])
    rgb, alpha = reference_render(TWO_TET_V, TWO_TET_T, col, np.full(5, a), o, d, t_max=tmax)
    for i, L in enumerate([0.6, 0.3, 0.5, 0.0]):
        np.testing.assert_allclose(rgb[i], c * (1 - np.exp(-a * L)), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(alpha[i], 1 - np.exp(-a * L), rtol=1e-12, atol=1e-15)


def _kuhn_cube():
    """Unit cube split into 6 Kuhn/Freudenthal tets, all sharing the diagonal (0,0,0)-(1,1,1)."""
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    idx = {tuple(p.astype(int)): n for n, p in enumerate(corners)}
    tets = []
    for perm in [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]:
        p = np.zeros(3, dtype=int)
        path = [idx[tuple(p)]]
        for ax in perm:
            p[ax] = 1
            path.append(idx[tuple(p)])
        tets.append(path)
    return corners, np.array(tets)


# affine color / opacity: exactly representable on any tet mesh
def _cube_sig(p):
    return 0.5 + 1.5 * p[..., 0] + 0.7 * p[..., 1] + 2.0 * p[..., 2]


def _cube_col(p):
    return np.stack([0.2 + 0.8 * p[..., 0], 1.0 - 0.5 * p[..., 1], 0.3 + 0.3 * p[..., 2]], -1)


def _cube_chord_expect(o, d, sig_f=_cube_sig, col_f=_cube_col):
    """1D emission-absorption integral of an affine field over the chord of the closed unit cube."""
    u = d / np.linalg.norm(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (0 - o) / u, (1 - o) / u
    par = u == 0.0
    assert np.all((o[par] >= 0.0) & (o[par] <= 1.0))  # parallel axes: inside the slab
    t0 = max(0.0, np.max(np.where(par, -np.inf, np.minimum(ta, tb))))
    t1 = np.min(np.where(par, np.inf, np.maximum(ta, tb)))
    assert t1 > t0
    # along the chord sigma is affine: tau(s) = s0 s + (s1 - s0) s^2 / (2 L)
    L = t1 - t0
    s0, s1 = sig_f(o + t0 * u), sig_f(o + t1 * u)
    tau = lambda s: s0 * s + (s1 - s0) * s * s / (2 * L)  # noqa: E731
    rgb = [integrate.quad(lambda s: sig_f(o + (t0 + s) * u) * col_f(o + (t0 + s) * u)[ch]
                          * np.exp(-tau(s)), 0, L, epsabs=1e-14, epsrel=1e-12)[0]
           for ch in range(3)]
    return np.array(rgb), 1 - np.exp(-tau(L)), L


def test_cube_subdivision_affine_fields_vs_scipy():
    """Cube split into 6 Kuhn tets with affine color/opacity == 1D quadrature over the chord."""
    corners, tets = _kuhn_cube()
    rng = np.random.default_rng(7)
    o = rng.uniform(-1, 2, (6, 3))
    target = rng.uniform(0.2, 0.8, (6, 3))
    d = target - o
    rgb, alpha = reference_render(corners, tets, _cube_col(corners), _cube_sig(corners), o, d)
    for r in range(6):
        expect, expect_alpha, _ = _cube_chord_expect(o[r], d[r])
        np.testing.assert_allclose(rgb[r], expect, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(alpha[r], expect_alpha, rtol=1e-11)


# rays inside faces / along edges shared by several tets: counted once, not once per tet
_SHARED_RAYS = {
    # main diagonal: edge shared by all 6 tets (both directions, origin outside and inside)
    "diagonal": ([-0.5, -0.5, -0.5], [1.0, 1.0, 1.0]),
    "diagonal_reversed": ([2.0, 2.0, 2.0], [-1.0, -1.0, -1.0]),
    "diagonal_from_inside": ([0.25, 0.25, 0.25], [1.0, 1.0, 1.0]),
    # inside the interior plane x = y (faces shared by (x>=y>=z, y>=x>=z), then by
    # (z>=x>=y, z>=y>=x)), crossing the diagonal at (0.5, 0.5, 0.5)
    "face_x_eq_y": ([0.05, 0.05, -0.4], [1.0, 1.0, 2.0]),
    # inside the interior plane y = z, not through the diagonal except at a vertex
    "face_y_eq_z": ([-0.3, 0.2, 0.2], [1.0, 0.25, 0.25]),
    # axis-parallel ray inside the interior plane x = z (y=0.3 < x=z=0.6: shared face)
    "face_x_eq_z_axis": ([0.6, -1.0, 0.6], [0.0, 1.0, 0.0]),
}
_BOUNDARY_EDGE_RAYS = {
    # boundary edge x=y=0 (along z), shared by the 2 tets z>=x>=y and z>=y>=x
    "edge_z_shared2": ([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]),
    # boundary edge y=z=1 (along x, reversed), shared by 2 tets
    "edge_x_shared2": ([3.0, 1.0, 1.0], [-1.0, 0.0, 0.0]),
    # boundary edge x=1, z=0 (along y), in the single tet x>=y>=z
    "edge_y_single": ([1.0, -0.5, 0.0], [0.0, 2.0, 0.0]),
    # bottom face diagonal (0,0,0)-(1,1,0): boundary-face edge shared by 2 tets
    "face_diagonal_z0": ([-1.0, -1.0, 0.0], [1.0, 1.0, 0.0]),
}


@pytest.mark.parametrize("name", list(_SHARED_RAYS) + list(_BOUNDARY_EDGE_RAYS))
def test_cube_rays_in_shared_faces_and_edges(name):
    o, d = (np.array(v, dtype=float) for v in {**_SHARED_RAYS, **_BOUNDARY_EDGE_RAYS}[name])
    corners, tets = _kuhn_cube()
    bg = np.array([0.05, 0.1, 0.2])
    expect, expect_alpha, L = _cube_chord_expect(o, d)
    rgb, alpha = reference_render(corners, tets, _cube_col(corners), _cube_sig(corners),
                                  [o], [d], background=bg)
    np.testing.assert_allclose(alpha[0], expect_alpha, rtol=1e-11)
    np.testing.assert_allclose(rgb[0], expect + (1 - expect_alpha) * bg, rtol=1e-9, atol=1e-12)
    # same field on a single big tet containing the cube gives the same answer; restrict
    # it to the cube's chord with an origin at the entry point and t_max = chord length
    big_v = np.array([[-0.1, -0.1, -0.1], [3.5, -0.1, -0.1], [-0.1, 3.5, -0.1], [-0.1, -0.1, 3.5]])
    u = d / np.linalg.norm(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (0 - o) / u, (1 - o) / u
    t0 = max(0.0, np.max(np.where(u == 0.0, -np.inf, np.minimum(ta, tb))))
    rgb_b, alpha_b = reference_render(big_v, UNIT_TET_T, _cube_col(big_v), _cube_sig(big_v),
                                      [o + t0 * u], [u], background=bg, t_max=L)
    np.testing.assert_allclose(alpha[0], alpha_b[0], rtol=1e-11)
    np.testing.assert_allclose(rgb[0], rgb_b[0], rtol=1e-10, atol=1e-13)


def test_cube_unjittered_grid_rays_union():
    """Many rays through grid lines/faces of a 2x2x2 Kuhn grid == the 1D integral on the chord."""
    corners, tets = _kuhn_cube()
    V = np.vstack([corners + np.array(s) for s in np.ndindex(2, 2, 2)]) / 2.0
    T = np.vstack([tets + 8 * n for n in range(8)])  # duplicated vertices are harmless
    g = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    X, Y = np.meshgrid(g, g, indexing="ij")
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, -1.0)], -1)
    d = np.tile([0.0, 0.0, 1.0], (X.size, 1))
    o = np.vstack([o, o[:, [2, 0, 1]], [[-1.0, -1.0, -1.0], [0.0, -1.0, -1.0]]])
    d = np.vstack([d, d[:, [2, 0, 1]], [[1.0, 1.0, 1.0], [0.0, 1.0, 1.0]]])
    rgb, alpha = reference_render(V, T, _cube_col(V), _cube_sig(V), o, d)
    for r in range(len(o)):
        expect, expect_alpha, _ = _cube_chord_expect(o[r], d[r])
        np.testing.assert_allclose(alpha[r], expect_alpha, rtol=1e-11, err_msg=str(r))
        np.testing.assert_allclose(rgb[r], expect, rtol=1e-9, atol=1e-12, err_msg=str(r))


def test_overlap_partial_clip_interpolates():
    """Overlapping tets (not a valid mesh, but same affine field): union, not sum."""
    # unit tet and the same tet shifted by 0.3 along z: the ray x=0.1, y=0.2 sees
    # z in [0, 0.7] and z in [0.3, 1.0]; union = [0, 1.0]
    V = np.vstack([UNIT_TET_V, UNIT_TET_V + [0.0, 0.0, 0.3]])
    T = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    f_sig = lambda p: 0.4 + 0.9 * p[..., 0] + 0.3 * p[..., 1] + 1.1 * p[..., 2]  # noqa: E731
    rgb, alpha = reference_render(V, T, _cube_col(V), f_sig(V), [[0.1, 0.2, -1.0]], [[0, 0, 1.0]])
    p0 = np.array([0.1, 0.2, 0.0])
    s0, s1 = f_sig(p0), f_sig(p0 + [0, 0, 1.0])
    tau = lambda s: s0 * s + (s1 - s0) * s * s / 2  # noqa: E731
    expect = [integrate.quad(lambda s: f_sig(p0 + [0, 0, s]) * _cube_col(p0 + [0, 0, s])[ch]
                             * np.exp(-tau(s)), 0, 1.0, epsabs=1e-14, epsrel=1e-12)[0]
              for ch in range(3)]
    np.testing.assert_allclose(alpha[0], 1 - np.exp(-tau(1.0)), rtol=1e-11)
    np.testing.assert_allclose(rgb[0], expect, rtol=1e-9, atol=1e-12)


# (6) orientation independence, degenerate tets ------------------------------------------------
def test_orientation_and_degenerate_independence():
    rng = np.random.default_rng(3)
    col = rng.random((5, 3))
    sig = rng.uniform(0.0, 3.0, 5)
    o = rng.uniform(-1.0, 2.0, (64, 3))
    d = rng.uniform(0.1, 0.7, (64, 3)) - o
    bg = (0.1, 0.2, 0.3)
    rgb, alpha = reference_render(TWO_TET_V, TWO_TET_T, col, sig, o, d, background=bg)
    assert np.count_nonzero(alpha > 0) > 20
    for perm in [(1, 0, 2, 3), (3, 2, 1, 0), (2, 3, 0, 1), (0, 2, 1, 3)]:
        t = TWO_TET_T[:, perm]
        rgb2, alpha2 = reference_render(TWO_TET_V, t, col, sig, o, d, background=bg)
        np.testing.assert_allclose(rgb2, rgb, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(alpha2, alpha, rtol=1e-12, atol=1e-14)
    # flat tets (coplanar / repeated vertices) are ignored; tet order does not matter
    t = np.vstack([TWO_TET_T[::-1], [[0, 1, 2, 2]], [[0, 1, 2, 0]]])
    v = TWO_TET_V.copy()
    rgb3, alpha3 = reference_render(v, t, col, sig, o, d, background=bg)
    np.testing.assert_allclose(rgb3, rgb, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(alpha3, alpha, rtol=1e-12, atol=1e-14)


# (n) several meshes merged as one medium --------------------------------------------------
def _grid(lo, hi, seed):
    from mi_tetvr.mesh.generate import grid_mesh
    return grid_mesh(3, lo=lo, hi=hi, jitter=0.1, seed=seed)


def _rays(rng, k):
    o = rng.normal(size=(k, 3))
    o *= 5.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-1.5, 1.5, (k, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_meshes_disjoint_are_composited_in_depth_order():
    """Two meshes side by side: the merged reference is the single-mesh
    references composited front to back (which one is in front follows the
    ray's x direction: the meshes are separated by the plane x = 0)."""
    from tests.reference import reference_render_meshes
    rng = np.random.default_rng(60)
    meshes = []
    for i, (lo, hi) in enumerate((((-1.6, -1, -1), (-0.1, 1, 1)), ((0.1, -1, -1), (1.6, 1, 1)))):
        V, T = _grid(lo, hi, i)
        meshes.append(dict(vertices=V, tets=T, color=rng.uniform(0, 1, (len(V), 3)),
                           opacity=rng.uniform(0, 2, len(V))))
    o, d = _rays(rng, 200)
    rgb, alpha = reference_render_meshes(meshes, o, d, background=(0.1, 0.2, 0.3))
    parts = [reference_render(m["vertices"], m["tets"], m["color"], m["opacity"], o, d)
             for m in meshes]
    left_first = d[:, 0] > 0
    front = [np.where(left_first[:, None], parts[0][0], parts[1][0]),
             np.where(left_first, parts[0][1], parts[1][1])]
    back = [np.where(left_first[:, None], parts[1][0], parts[0][0]),
            np.where(left_first, parts[1][1], parts[0][1])]
    T = (1 - front[1]) * (1 - back[1])
    expected = front[0] + (1 - front[1])[:, None] * back[0] + T[:, None] * [0.1, 0.2, 0.3]
    assert (np.minimum(parts[0][1], parts[1][1]) > 0.05).sum() > 10   # rays through both
    np.testing.assert_allclose(rgb, expected, atol=1e-9)
    np.testing.assert_allclose(alpha, 1 - T, atol=1e-9)


def test_meshes_overlapping_add_extinction_and_emission():
    """Two meshes over the same box but with different tets (a coarse and a
    fine grid), extinctions alpha sigma and (1 - alpha) sigma of one linear
    sigma, colors c_A, c_B linear: the medium's emission sigma (alpha c_A +
    (1 - alpha) c_B) is that of one mesh with extinction sigma and that
    linear color."""
    from mi_tetvr.mesh.generate import grid_mesh
    from tests.reference import reference_render_meshes
    rng = np.random.default_rng(61)
    sigma = lambda p: 1.2 + 0.5 * p[:, 0] - 0.3 * p[:, 1] + 0.2 * p[:, 2]   # noqa: E731
    cA = lambda p: np.stack([0.5 + 0.3 * p[:, 0], 0.2 + 0.1 * p[:, 2], 0.7 + 0 * p[:, 1]], 1)  # noqa: E731
    cB = lambda p: np.stack([0.1 + 0 * p[:, 0], 0.6 - 0.2 * p[:, 1], 0.3 + 0.2 * p[:, 2]], 1)  # noqa: E731
    alpha = 0.3
    VA, TA = grid_mesh(2)
    VB, TB = grid_mesh(3, jitter=0.1, seed=4)
    meshes = [dict(vertices=VA, tets=TA, color=cA(VA), opacity=alpha * sigma(VA)),
              dict(vertices=VB, tets=TB, color=cB(VB), opacity=(1 - alpha) * sigma(VB))]
    o, d = _rays(rng, 100)
    rgb, a = reference_render_meshes(meshes, o, d)
    Vf, Tf = grid_mesh(4)
    ref, ref_a = reference_render(Vf, Tf, alpha * cA(Vf) + (1 - alpha) * cB(Vf), sigma(Vf), o, d)
    assert (ref_a > 0.3).sum() > 30
    np.testing.assert_allclose(rgb, ref, atol=1e-7)
    np.testing.assert_allclose(a, ref_a, atol=1e-9)
