"""Initial meshes: grid, fTetWild, Delaunay, reports."""

import numpy as np
import pytest

from mi_tetvr.mesh.initial import (delaunay_init, grid_init, grid_sample, retriangulate,
                                   tetwild_init)
from mi_tetvr.mesh.topology import (MeshError, build_topology, format_summary, geometry_summary,
                           signed_volumes)


def _boundary_area(v, topo):
    f = v[topo.boundary_faces]
    return 0.5 * np.linalg.norm(np.cross(f[:, 1] - f[:, 0], f[:, 2] - f[:, 0]), axis=1).sum()


def _check_valid(v, t):
    assert v.dtype == np.float64 and t.dtype == np.int64
    assert v.shape[1] == 3 and t.shape[1] == 4 and len(t) > 0
    vol = signed_volumes(v, t)
    assert np.all(vol > 0)
    assert np.array_equal(np.unique(t), np.arange(len(v)))  # no unreferenced vertex
    topo = build_topology(v, t, warn=False)                 # raises if non-manifold
    assert topo.n_flipped == 0 and not topo.flat.any()
    return topo, vol


# ----------------------------------------------------------------------------- grid
def test_grid_init_counts_and_coverage():
    b = np.array([[-1.0, 0.0, 2.0], [3.0, 1.0, 4.2]])      # extents 4, 1, 2.2
    v, t = grid_init(b, 8)
    shape = (8, 2, 4)                                        # 8 * 1/4 = 2, 8 * 2.2/4 = 4.4
    assert len(t) == 6 * np.prod(shape)
    assert len(v) == np.prod(np.array(shape) + 1)
    for a in range(3):
        assert len(np.unique(v[:, a])) == shape[a] + 1
    topo, vol = _check_valid(v, t)
    box_vol = np.prod(b[1] - b[0])
    assert abs(vol.sum() - box_vol) <= 1e-9 * box_vol
    bf = v[topo.boundary_faces]                              # every boundary face on the box
    on = np.any(np.all(np.isclose(bf, b[0]), axis=1) | np.all(np.isclose(bf, b[1]), axis=1), axis=1)
    assert on.all()
    assert np.isclose(_boundary_area(v, topo), 2 * (4 * 1 + 4 * 2.2 + 1 * 2.2))
    # a thin box still gets one cell along its short axes; jitter keeps the box
    v, t = grid_init([[0, 0, 0], [1, 0.01, 0.5]], 4, jitter=0.3)
    assert len(t) == 6 * 4 * 1 * 2
    _, vol = _check_valid(v, t)
    assert np.isclose(vol.sum(), 0.005)
    with pytest.raises(ValueError):
        grid_init([[0, 0, 0], [1, 0, 1]], 4)


def _barycentric_field(v, t, values, points):
    """Reference: the P1 field of (v, t) at points, by solving for every
    tet's barycentric coordinates in float64 and taking the containing tet."""
    P = v[t]
    T = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]], -1)
    out = []
    for p in points:
        lam = np.linalg.solve(T, (p - P[:, 0])[..., None])[..., 0]
        bary = np.column_stack([1 - lam.sum(1), lam])
        i = np.argmax(bary.min(1))
        assert bary[i].min() > -1e-9
        out.append(bary[i] @ values[t[i]])
    return np.array(out)


def test_grid_sample_is_the_meshs_linear_field():
    b = np.array([[-1.0, 0.0, 2.0], [3.0, 1.0, 4.2]])
    v, t = grid_init(b, 5)
    rng = np.random.default_rng(0)
    values = rng.uniform(size=(len(v), 3))
    pts = b[0] + rng.uniform(size=(300, 3)) * (b[1] - b[0])
    pts[:20] = v[rng.choice(len(v), 20)]                     # on vertices, edges of cells
    np.testing.assert_allclose(grid_sample(b, 5, values, pts),
                               _barycentric_field(v, t, values, pts), atol=1e-12)
    # (n,) values give (p,) results; outside the box the nearest point's value
    s = values[:, 0]
    out = np.array([[-5.0, 0.5, 3.0], [10.0, 10.0, 10.0]])
    np.testing.assert_allclose(grid_sample(b, 5, s, out),
                               grid_sample(b, 5, s, np.clip(out, b[0], b[1])))
    # a grid of twice the resolution nests the coarse one's tets: its sampled
    # field is the coarse field everywhere
    fine, _ = grid_init(b, 10)
    fine_values = grid_sample(b, 5, s, fine)
    np.testing.assert_allclose(grid_sample(b, 10, fine_values, pts), grid_sample(b, 5, s, pts),
                               atol=1e-12)
    with pytest.raises(ValueError, match="values for a grid"):
        grid_sample(b, 6, s, pts)


# ----------------------------------------------------------------------------- fTetWild
def test_tetwild_box_and_sphere(tmp_path):
    pytest.importorskip("pytetwild")
    trimesh = pytest.importorskip("trimesh")
    b = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    v, t = tetwild_init(bounds=b, edge_length_fac=0.1, num_threads=1)
    _, vol = _check_valid(v, t)
    assert abs(vol.sum() - 1.0) < 0.01
    assert np.all(v >= -1e-6) and np.all(v <= 1 + 1e-6)

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    s.apply_translation([1.0, 2.0, 3.0])
    v, t = tetwild_init(s, edge_length_fac=0.1, num_threads=1)
    _, vol = _check_valid(v, t)
    assert abs(vol.sum() / (4 / 3 * np.pi * 0.5 ** 3) - 1) < 0.03
    assert np.all(v >= s.bounds[0] - 0.01) and np.all(v <= s.bounds[1] + 0.01)
    # a surface given as a file trimesh loads
    trimesh.creation.box(bounds=[[0, 0, 0], [2, 1, 1]]).export(tmp_path / "box.stl")
    v, t = tetwild_init(tmp_path / "box.stl", edge_length_fac=0.1, num_threads=1)
    _, vol = _check_valid(v, t)
    assert abs(vol.sum() - 2.0) < 0.02
    with pytest.raises(ValueError):
        tetwild_init()


# ----------------------------------------------------------------------------- Delaunay
def test_delaunay_outliers_and_hull():
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(1)
    inliers = rng.normal(size=(400, 3)) * [1.0, 0.5, 0.3]
    outliers = np.array([[20.0, 0, 0], [0, -15, 3], [8, 8, 8], [-30, 1, 1], [0, 0, 25]])
    v, t = delaunay_init(np.concatenate([inliers, outliers]), outlier_std=2.0)
    # no outlier survives
    d = np.linalg.norm(v[:, None] - outliers[None], axis=2)
    assert d.min() > 1.0
    topo, vol = _check_valid(v, t)
    hull = ConvexHull(v)
    assert np.isclose(vol.sum(), hull.volume, rtol=1e-9)               # fills its hull
    assert np.isclose(_boundary_area(v, topo), hull.area, rtol=1e-9)   # no internal boundary
    assert len(v) >= 0.97 * len(inliers)                               # few inliers lost
    assert vol.sum() > 0.95 * ConvexHull(inliers).volume
    # padded box corners: the hull is the padded bounding box
    v, t = delaunay_init(inliers, outlier_std=None, padding=0.1)
    lo, hi = inliers.min(0), inliers.max(0)
    _, vol = _check_valid(v, t)
    assert np.isclose(vol.sum(), np.prod(1.2 * (hi - lo)), rtol=1e-3)
    with pytest.raises(MeshError):
        delaunay_init([[0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(MeshError):                                      # coplanar
        delaunay_init(np.c_[rng.uniform(size=(30, 2)), np.zeros(30)], outlier_std=None)


def test_delaunay_degenerate_lattice_stays_conforming():
    # a lattice is maximally degenerate: qhull emits flat tets that glue
    # differently triangulated quads; they must not leave holes
    a = np.linspace(0, 1, 5)
    p = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    v, t = delaunay_init(p, outlier_std=None)
    topo, vol = _check_valid(v, t)
    assert len(v) == len(p)
    assert np.abs(v - p[np.argmin(np.linalg.norm(v[:, None] - p[None], axis=2), 1)]).max() < 0.01
    assert abs(vol.sum() - 1) < 0.01
    assert abs(_boundary_area(v, topo) - 6) < 0.05     # only the cube's faces are boundary


def test_retriangulate_moved_vertices_is_their_delaunay_mesh():
    """Vertices moved until the old tets invert: the new tets are positive, conforming,
    fill the moved points' convex hull (scipy's ConvexHull: volume and area), have empty
    circumspheres, and each vertex keeps its data (found again by position)."""
    from scipy.spatial import ConvexHull
    rng = np.random.default_rng(3)
    v, t = delaunay_init(rng.uniform(-1, 1, (300, 3)), outlier_std=None)
    moved = v + rng.normal(0, 0.15, v.shape)
    assert (signed_volumes(moved, t) <= 0).any()              # the old mesh is broken
    data = {"color": rng.uniform(size=(len(v), 3)), "opacity": rng.uniform(size=len(v))}
    v2, t2, d2, parent = retriangulate(moved, data)
    topo, vol = _check_valid(v2, t2)
    hull = ConvexHull(moved)
    assert np.isclose(vol.sum(), hull.volume, rtol=1e-9)
    assert np.isclose(_boundary_area(v2, topo), hull.area, rtol=1e-9)
    assert len(v2) == len(v)                                  # no vertex lost
    np.testing.assert_array_equal(v2, moved[parent])
    for k in data:
        np.testing.assert_array_equal(d2[k], data[k][parent])
    # Delaunay: no vertex strictly inside a tet's circumsphere
    p = v2[t2]
    a = p[:, 1:] - p[:, :1]
    rhs = 0.5 * (a ** 2).sum(-1)
    centre = p[:, 0] + np.linalg.solve(a, rhs[..., None])[..., 0]
    radius = np.linalg.norm(p[:, 0] - centre, axis=1)
    dist = np.linalg.norm(v2[None] - centre[:, None], axis=2)
    assert (dist >= radius[:, None] * (1 - 1e-9)).all()
    with pytest.raises(MeshError):
        retriangulate(moved[:3])


# ----------------------------------------------------------------------------- report
def test_geometry_summary_on_grid():
    v, t = grid_init([[0, 0, 0], [2, 1, 1]], 4)     # 4 x 2 x 2 cells
    r = geometry_summary(v, build_topology(v, t))
    assert r["vertices"] == 5 * 3 * 3 and r["tets"] == 6 * 16
    assert r["boundary_faces"] == 2 * 2 * (4 * 2 + 4 * 2 + 2 * 2)
    assert r["zero_volume_tets"] == 0 and r["inverted_tets_fixed"] == 0
    assert r["unused_vertices"] == 0
    assert r["bounds_min"] == [0, 0, 0] and r["bounds_max"] == [2, 1, 1]
    assert np.isclose(r["volume"], 2.0)
    # Kuhn tets of a cube are congruent: edges 1, 1, 1, sqrt2, sqrt2, sqrt3 (cell 0.5 here)
    q = 6 * np.sqrt(2) * (1 / 6) / (10 / 6) ** 1.5
    for k in ("quality_min", "quality_mean", "quality_p01", "quality_p05", "quality_p50"):
        assert np.isclose(r[k], q)
    text = format_summary(r)
    assert "tets" in text and "quality_mean" in text and len(text.splitlines()) == len(r)


def test_unbounded_init_contains_cameras_and_grows_with_distance():
    """Sparse points of a scene and cameras around it: every camera and
    kept point lies in the mesh (scipy's point location in its own Delaunay
    of the vertices: the hull is convex), the scene points are vertices, and
    the cells on the shells grow in proportion to their radius."""
    from scipy.spatial import Delaunay

    from mi_tetvr.mesh.initial import unbounded_init
    from mi_tetvr.mesh.topology import build_topology, unique_edges
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (800, 3))
    angle = rng.uniform(0, 2 * np.pi, 12)
    cameras = np.stack([2 * np.cos(angle), 2 * np.sin(angle), rng.uniform(-0.5, 0.5, 12)], -1)
    V, T, shell = unbounded_init(points, cameras, far=8.0, shells=4, outlier_std=None)
    topo = build_topology(V, T)
    assert topo.n_flipped == 0
    assert Delaunay(V).find_simplex(cameras).min() >= 0
    # the scene points are vertices (up to the joggle of degenerate spots)
    d = np.linalg.norm(V[~shell][:, None] - points[None], axis=-1).min(1)
    assert (~shell).sum() == len(points) and d.max() < 1e-3
    # shells: 4 radii r0 * 8^(k/3), as many points on each; edges between shell
    # vertices of one shell scale with the radius
    center = np.median(np.concatenate([cameras, points]), 0)
    r = np.linalg.norm(V[shell] - center, axis=1)
    radii = np.unique(np.round(r / r.min(), 3))
    np.testing.assert_allclose(radii, 8.0 ** (np.arange(4) / 3), rtol=1e-3)
    e = unique_edges(T)
    both = shell[e[:, 0]] & shell[e[:, 1]]
    ra = np.linalg.norm(V[e[both, 0]] - center, axis=1)
    rb = np.linalg.norm(V[e[both, 1]] - center, axis=1)
    same = np.abs(ra - rb) < 1e-6 * ra
    length = np.linalg.norm(V[e[both, 0]] - V[e[both, 1]], axis=1)[same] / ra[same]
    k = np.round(np.log(ra[same] / r.min()) / np.log(8.0) * 3).astype(int)
    medians = [np.median(length[k == i]) for i in range(4)]
    np.testing.assert_allclose(medians, medians[0], rtol=0.1)


def test_contracted_grid_points_are_a_grid_in_contracted_space():
    """mip-NeRF 360's contraction (written here from its paper) of the points
    lands between radius 1 and 2 - 1/far, with nearest neighbours about one
    grid cell apart everywhere (a uniform grid there), so in world space the
    spacing grows with the square of the distance; the unbounded init with
    ``outer="contracted"`` keeps the cameras inside."""
    from scipy.spatial import cKDTree

    from mi_tetvr.mesh.initial import contracted_grid_points, unbounded_init
    center, r0, far = np.array([0.5, -1.0, 2.0]), 3.0, 8.0
    q = contracted_grid_points(center, r0, far, 6000, seed=1)
    x = (q - center) / r0
    n = np.linalg.norm(x, axis=1, keepdims=True)
    c = np.where(n <= 1, x, (2 - 1 / n) * x / n)
    cn = np.linalg.norm(c, axis=1)
    assert cn.min() >= 1.0 and cn.max() <= 2.0 - 1.0 / far
    assert 0.8 * 6000 < len(q) < 1.5 * 6000
    nn = cKDTree(c).query(c, k=2)[0][:, 1]
    cell = (4 / 3 * np.pi * ((2 - 1 / far) ** 3 - 1) / len(q)) ** (1 / 3)   # volume per point
    assert 0.5 * cell < np.median(nn) < 1.1 * cell
    near, far_ = cn < 1.2, cn > 1.7
    assert abs(np.median(nn[near]) / np.median(nn[far_]) - 1) < 0.15
    rng = np.random.default_rng(3)
    points = rng.uniform(-1, 1, (500, 3))
    angle = rng.uniform(0, 2 * np.pi, 8)
    cameras = np.stack([2 * np.cos(angle), 2 * np.sin(angle), rng.uniform(-0.5, 0.5, 8)], -1)
    from scipy.spatial import Delaunay
    V, T, shell = unbounded_init(points, cameras, outer="contracted", outlier_std=None)
    assert Delaunay(V).find_simplex(cameras).min() >= 0 and (~shell).sum() == len(points)
    with pytest.raises(ValueError, match="outer"):
        unbounded_init(points, cameras, outer="cube")
