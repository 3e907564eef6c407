"""The walk's geometric kernels (:mod:`mi_tetvr.render.geometry`) and segment
clipping (:func:`mi_tetvr.render.segment.clip_segment`) against float64 numpy
twins, on random and adversarial inputs, values and gradients.

Each ``*_np`` function below restates one kernel in float64 numpy. The
kernels run in float32 on the current variant, so the comparison is exact on
inputs whose arithmetic is exact in float32 (small integers and halves: exact
ties, rays through vertices and edges) and within float32 round-off on random
inputs (where decisions are compared only away from ties). Derivatives are
compared with central differences of the float64 twins, weighted by random
cotangents.

What the tests assume of the kernels' interfaces:

* ``edge_function(i, pi, j, pj) -> (Float, Bool)``, ``face_weights(ea, eb, ec)
  -> (wa, wb, wc)``, ``crossing(ids, P, p, o, d) -> (t, (w0, w1, w2))``,
  ``ray_frame(d) -> (u, v)``, ``project(p, o, u, v) -> Point2f``;
* ``clip_segment(t0, x0, t1, x1, t_begin, t_end) -> (length, x_begin, x_end)``
  with ``x`` any structure of Dr.Jit arrays (a tuple here), see :func:`clip`;
* ``RayFrame.of(o, d)``, the frame of rays;
* ``face_entry(buf, face, frame, active) -> (tet, f, outward)`` and
  ``walk_step(buf, tet, f_in, frame, active)`` with the fields ``t, w,
  link, f_out, exit`` (a link is ``< 0`` on the boundary and decoded by
  :func:`mi_tetvr.render.buffers.unpack_link`); the buffers come from
  :func:`mesh_buffers`, the only place that builds them; the twin of
  ``face_entry`` takes as many steps as ``BOUNDARY_WALK_STEPS``.

"""
import itertools

import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import FACES, build_topology
from mi_tetvr.render.buffers import (MeshBuffers, far_links, links_of, morton_order,
                                     shape_index_arrays, tets_of, unpack_link)
from mi_tetvr.render.geometry import (BOUNDARY_WALK_STEPS, RayFrame, crossing, edge_function,
                                      face_entry, face_weights, project, ray_frame, walk_step)
from mi_tetvr.render.segment import clip_segment
from tests.helpers import rays_at

# ----------------------------------------------------------------------------
# Adapters: the one place that knows how to call / build the kernels' inputs
# ----------------------------------------------------------------------------


def mesh_buffers(vertices, tets):
    """The walk's buffers of one tet mesh (global = local indices) and its
    topology, as the ``tetmesh`` shape hands them to the integrator. The
    tets are given in the buffers' (Morton) order, so that the twins'
    tet indices are the kernels'."""
    tets = np.asarray(tets)[morton_order(np.asarray(vertices)[tets].mean(1))]
    topo = build_topology(vertices, tets, warn=False)
    idx = shape_index_arrays(topo, vertices)
    np.testing.assert_array_equal(tets_of(idx["cells"]), topo.tets)
    typed = {k: (mi.Int32 if idx[k].dtype == np.int32 else mi.UInt32)(idx[k])
             for k in ("cells", "boundary", "faces", "face_adj")}
    positions = mi.Float(np.asarray(vertices, np.float32).ravel())
    return MeshBuffers(**typed, positions=positions), topo


def clip(t0, x0, t1, x1, t_begin, t_end):
    """:func:`clip_segment` on attributes ``x`` = (Color3f, Float)."""
    return clip_segment(t0, x0, t1, x1, t_begin, t_end)


# ----------------------------------------------------------------------------
# Conversions
# ----------------------------------------------------------------------------

def f32(x):
    """float64 copy of ``x`` rounded to float32 (what the kernels see)."""
    return np.asarray(x, np.float32).astype(np.float64)


def p2(a):
    return mi.Point2f(*np.asarray(a, np.float32).T)


def p3(a):
    return mi.Point3f(*np.asarray(a, np.float32).T)


def v3(a):
    return mi.Vector3f(*np.asarray(a, np.float32).T)


def u32(a):
    return mi.UInt32(np.asarray(a, np.uint32))


def arr(x):
    """numpy float64 (k,) or (k, n) of a Dr.Jit array or vector."""
    a = np.asarray(x, np.float64)
    return a.T if a.ndim == 2 else a


# ----------------------------------------------------------------------------
# float64 twins
# ----------------------------------------------------------------------------

def edge_function_np(i, pi, j, pj):
    """Twice the signed area of (origin, pi, pj) and the side of ``i -> j`` on
    which the ray passes, with the ray moved symbolically to (eps, eps^2)
    when the area is exactly zero, evaluated in the order lower index first."""
    i, j = np.asarray(i), np.asarray(j)
    swap = i > j
    P = np.where(swap[:, None], pj, pi)
    Q = np.where(swap[:, None], pi, pj)
    e = P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]
    # Area with the origin at (eps, eps^2): e + eps (Py - Qy) + eps^2 (Qx - Px);
    # its sign is that of the first non-zero coefficient.
    c1, c2 = P[:, 1] - Q[:, 1], Q[:, 0] - P[:, 0]
    pos = np.where(e != 0, e > 0, np.where(c1 != 0, c1 > 0, c2 > 0))
    return np.where(swap, -e, e), pos ^ swap


def face_weights_np(ea, eb, ec):
    """Barycentric weights from the three edge functions: the positive parts of
    ``e / sum(e)`` renormalized; thirds when that is undefined."""
    e = np.stack([ea, eb, ec], -1)
    s = e.sum(-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.maximum(np.where(s != 0, e / np.where(s != 0, s, 1), 0), 0)
        n = w.sum(-1, keepdims=True)
        w = np.where((s != 0) & (n > 0), w / np.where(n > 0, n, 1), 1 / 3)
    return w[:, 0], w[:, 1], w[:, 2]


def ray_frame_np(d):
    """Mitsuba's ``coordinate_system`` (Duff et al. 2017) and ``v = d x u``."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    u = np.stack([1 + sign * x * x * a, sign * b, -sign * x], -1)
    return u, np.cross(d, u)


def project_np(P, o, u, v):
    q = P - o
    return np.stack([(q * u).sum(-1), (q * v).sum(-1)], -1)


def crossing_np(ids, P, p, o, d):
    (i0, i1, i2), (P0, P1, P2), (q0, q1, q2) = ids, P, p
    e0, _ = edge_function_np(i1, q1, i2, q2)
    e1, _ = edge_function_np(i2, q2, i0, q0)
    e2, _ = edge_function_np(i0, q0, i1, q1)
    w = face_weights_np(e0, e1, e2)
    X = w[0][:, None] * P0 + w[1][:, None] * P1 + w[2][:, None] * P2
    return ((X - o) * d).sum(-1), w


def crossing_from_positions_np(ids, P, o, d):
    """What the walk computes for a face: frame, projections, crossing."""
    u, v = ray_frame_np(d)
    return crossing_np(ids, P, [project_np(Pi, o, u, v) for Pi in P], o, d)


def clip_segment_np(t0, x0, t1, x1, t_begin, t_end):
    """The part of the segment ``[t0, t1]`` inside ``[t_begin, t_end]``: its
    length and the linear attributes at its ends (``x`` (k, n))."""
    a = np.clip(t_begin, np.minimum(t0, t1), t1)
    b = np.maximum(np.clip(t_end, np.minimum(t0, t1), t1), a)
    span = t1 - t0
    with np.errstate(divide="ignore", invalid="ignore"):
        fa = np.where(span > 0, (a - t0) / np.where(span > 0, span, 1), 0)[:, None]
        fb = np.where(span > 0, (b - t0) / np.where(span > 0, span, 1), 0)[:, None]
    return b - a, x0 + fa * (x1 - x0), x0 + fb * (x1 - x0)


class MeshNP:
    """The topology of a mesh as numpy arrays, for the twins of the walk."""

    def __init__(self, vertices, topo):
        self.V = f32(vertices)
        self.tets = topo.tets.astype(np.int64)
        self.nbr = topo.neighbors.astype(np.int64)
        self.nbr_face = topo.neighbor_faces.astype(np.int64)
        self.faces = topo.boundary_faces.astype(np.int64)
        self.face_adj = topo.boundary_adjacency.astype(np.int64)
        self.btet = topo.boundary_tets.astype(np.int64)
        self.bface = topo.boundary_local_faces.astype(np.int64)
        n = np.cross(self.V[self.faces[:, 1]] - self.V[self.faces[:, 0]],
                     self.V[self.faces[:, 2]] - self.V[self.faces[:, 0]])
        self.normal = n  # outward, unnormalized

    def face_signs(self, face, o, u, v):
        """Edge functions and signs (bc, ca, ab) of boundary faces ``face``."""
        ia, ib, ic = self.faces[face].T
        pa, pb, pc = (project_np(self.V[i], o, u, v) for i in (ia, ib, ic))
        return (edge_function_np(ib, pb, ic, pc), edge_function_np(ic, pc, ia, pa),
                edge_function_np(ia, pa, ib, pb))


def face_entry_np(mesh, face, o, u, v, d, steps=BOUNDARY_WALK_STEPS):
    """Walk over the boundary surface from ``face`` to the face that the ray
    passes through by the consistent predicate (crossing the first edge whose
    sign disagrees with the face's projected orientation)."""
    face = np.array(face, np.int64)
    for _ in range(steps):
        (e_bc, s_bc), (e_ca, s_ca), (e_ab, s_ab) = mesh.face_signs(face, o, u, v)
        back = (e_bc + e_ca + e_ab) > 0
        adj = np.where(s_bc != back, 0, np.where(s_ca != back, 1, 2))
        move = (s_bc != back) | (s_ca != back) | (s_ab != back)
        nxt = mesh.face_adj[face, adj]
        face = np.where(move & (nxt >= 0), nxt, face)
    outward = (mesh.normal[face] * d).sum(-1) > 0
    return mesh.btet[face], mesh.bface[face], outward, face


def boundary_hits_np(mesh, o, u, v, d):
    """For each ray, the boundary faces it passes through by the consistent
    predicate: ``(entry, exit)`` (faces facing against / along the ray; -1
    where none, -2 where several)."""
    k, b = len(o), len(mesh.faces)
    face = np.tile(np.arange(b), k)
    rep = lambda a: np.repeat(a, b, axis=0)  # noqa: E731
    (e_bc, s_bc), (e_ca, s_ca), (e_ab, s_ab) = mesh.face_signs(face, rep(o), rep(u), rep(v))
    back = (e_bc + e_ca + e_ab) > 0
    inside = ((s_bc == back) & (s_ca == back) & (s_ab == back)).reshape(k, b)
    facing = (mesh.normal[None] * d[:, None]).sum(-1)  # (k, b)
    out = []
    for sel in (inside & (facing < 0), inside & (facing > 0)):
        n = sel.sum(1)
        out.append(np.where(n == 1, sel.argmax(1), np.where(n == 0, -1, -2)))
    return out


FACE_ORDER_NP = np.array([[f, *FACES[f]] for f in range(4)])  # apex, then the face


def walk_step_np(mesh, tet, f_in, o, u, v, d):
    """One step of the walk: the exit face of ``tet`` entered through ``f_in``.
    Returns (t, w, (next tet, its face) or -1, local exit face, exit ids)."""
    loc = FACE_ORDER_NP[f_in]                       # (k, 4) local indices
    ids = np.take_along_axis(mesh.tets[tet], loc, 1)
    P = [mesh.V[ids[:, j]] for j in range(4)]
    p = [project_np(Pj, o, u, v) for Pj in P]
    (ik, ia, ib, ic), (pk, pa, pb, pc) = ids.T, p
    ea, sa = edge_function_np(ik, pk, ia, pa)
    eb, sb = edge_function_np(ik, pk, ib, pb)
    ec, sc = edge_function_np(ik, pk, ic, pc)
    opp_c, opp_a, opp_b = sb & ~sa, sc & ~sb, sa & ~sc
    none = ~(opp_a | opp_b | opp_c)
    s_c, s_a, s_b = np.minimum(eb, -ea), np.minimum(ec, -eb), np.minimum(ea, -ec)
    best_c = (s_c >= s_a) & (s_c >= s_b)
    best_a = ~best_c & (s_a >= s_b)
    opp_c |= none & best_c
    opp_a |= none & best_a
    opp_b |= none & ~best_c & ~best_a
    # exit face (k, x, y) opposite local vertex z: (k,b,a) / (k,c,b) / (k,a,c)
    jx = np.where(opp_c, 2, np.where(opp_a, 3, 1))
    jy = np.where(opp_c, 1, np.where(opp_a, 2, 3))
    jz = np.where(opp_c, 3, np.where(opp_a, 1, 2))
    rows = np.arange(len(tet))
    exit_ids = (ik, ids[rows, jx], ids[rows, jy])
    Pst = np.stack(P, 1)
    pst = np.stack(p, 1)
    t, w = crossing_np(exit_ids, (P[0], Pst[rows, jx], Pst[rows, jy]),
                       (p[0], pst[rows, jx], pst[rows, jy]), o, d)
    lz = loc[rows, jz]
    return t, w, mesh.nbr[tet, lz], mesh.nbr_face[tet, lz], lz, exit_ids


# ----------------------------------------------------------------------------
# Test data
# ----------------------------------------------------------------------------

def random_unit(rng, k):
    d = rng.normal(size=(k, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def axis_rays(lo=0.0, hi=2.0, step=0.25, dist=5.0):
    """Rays along +-x, +-y, +-z through a lattice of points of a face of the
    box [lo, hi]^3 (through vertices, along and across edges, in between):
    every coordinate and projection is exact in float32."""
    offs = np.arange(lo, hi + step / 2, step)
    o, d = [], []
    for axis, sgn in itertools.product(range(3), (1.0, -1.0)):
        a, b = [x for x in range(3) if x != axis]
        for s, t in itertools.product(offs, offs):
            p = np.zeros(3)
            p[a], p[b] = s, t
            p[axis] = (lo - dist) if sgn > 0 else (hi + dist)
            dd = np.zeros(3)
            dd[axis] = sgn
            o.append(p)
            d.append(dd)
    return np.array(o), np.array(d)


def kernel_frame(d):
    """The kernels' own (float32) ray frame, as float64 arrays."""
    u, v = ray_frame(v3(d))
    return arr(u), arr(v)


#: Shears of the box along x and y by -z and by +z (determinant 1: integer
#: vertices stay integer): seen along +z (or -z) three of its sides face the
#: ray, so axis rays meet edges and corners shared by front faces on
#: different sides.
SHEARS = {"shear-": np.array([[1, 0, -1], [0, 1, -1], [0, 0, 1]]),
          "shear+": np.array([[1, 0, 1], [0, 1, 1], [0, 0, 1]])}


@pytest.fixture(scope="module", params=["box", "shear-", "shear+"])
def exact_mesh(request):
    """2^3 Kuhn cells over [0, 2]^3 (integer vertices), as they are or
    sheared, and axis rays through a lattice of quarter points around them.
    Returns (buffers, MeshNP, origins, directions)."""
    V, T = grid_mesh(2, lo=(0, 0, 0), hi=(2, 2, 2))
    if request.param in SHEARS:
        V = V @ SHEARS[request.param].T
    buf, topo = mesh_buffers(V, T)
    o, d = axis_rays(lo=V.min(), hi=V.max())
    return buf, MeshNP(V, topo), o, d


@pytest.fixture(scope="module")
def jittered():
    V, T = grid_mesh(3, jitter=0.2, seed=3)
    buf, topo = mesh_buffers(V, T)
    return buf, MeshNP(V, topo)


# ----------------------------------------------------------------------------
# edge_function
# ----------------------------------------------------------------------------

def run_edge(i, pi, j, pj):
    e, s = edge_function(u32(i), p2(pi), u32(j), p2(pj))
    return arr(e), np.asarray(s, bool)


def test_edge_function_random():
    rng = np.random.default_rng(0)
    k = 4000
    pi, pj = f32(rng.normal(size=(k, 2)) * 3), f32(rng.normal(size=(k, 2)) * 3)
    i, j = rng.integers(0, 50, k), rng.integers(0, 50, k)
    e, s = run_edge(i, pi, j, pj)
    e_np, s_np = edge_function_np(i, pi, j, pj)
    scale = np.abs(pi[:, 0] * pj[:, 1]) + np.abs(pi[:, 1] * pj[:, 0])
    assert np.all(np.abs(e - e_np) <= 1e-6 * scale)
    clear = np.abs(e_np) > 1e-5 * scale
    assert clear.mean() > 0.99
    np.testing.assert_array_equal(s[clear], s_np[clear])


def test_edge_function_exact_ties():
    """Small integer coordinates: every zero area, equal y and coincident
    projection occurs; results must match the twin bit for bit, whichever
    of the two indices is lower."""
    g = np.arange(-2, 3, dtype=np.float64)
    pts = np.array(list(itertools.product(g, g)))
    a, b = np.array(list(itertools.product(range(len(pts)), repeat=2))).T
    pi, pj = pts[a], pts[b]
    for i, j in ((np.full(len(a), 3), np.full(len(a), 7)), (np.full(len(a), 7), np.full(len(a), 3)),
                 (np.full(len(a), 5), np.full(len(a), 5))):
        e, s = run_edge(i, pi, j, pj)
        e_np, s_np = edge_function_np(i, pi, j, pj)
        np.testing.assert_array_equal(e, e_np)
        np.testing.assert_array_equal(s, s_np)
    assert np.count_nonzero(e_np == 0) > 50   # ties were exercised


def test_edge_function_antisymmetric():
    """The two directions of an edge give exactly opposite results (the
    canonical order makes the predicate identical in every tet of an edge)."""
    rng = np.random.default_rng(1)
    k = 2000
    pts = np.concatenate([rng.normal(size=(k // 2, 2)),
                          rng.integers(-2, 3, (k // 2, 2)).astype(float)])
    qts = np.concatenate([rng.normal(size=(k // 2, 2)),
                          rng.integers(-2, 3, (k // 2, 2)).astype(float)])
    i = rng.integers(0, 100, k)
    j = (i + rng.integers(1, 100, k)) % 100
    e1, s1 = run_edge(i, pts, j, qts)
    e2, s2 = run_edge(j, qts, i, pts)
    np.testing.assert_array_equal(e1, -e2)
    np.testing.assert_array_equal(s1, ~s2)


@pytest.mark.parametrize("offset", [(0, 0), (0.5, 0), (0, 0.5), (0.5, 0.5), (0.25, 0.75)])
def test_edge_function_one_triangle_of_a_fan(offset):
    """A ray through a vertex, an edge or a face of a planar triangulation
    passes inside exactly one of its triangles, whatever the vertex numbering."""
    g = np.arange(-2, 3, dtype=np.float64)
    pts = np.array(list(itertools.product(g, g))) - np.asarray(offset)
    n = len(g)
    tris = []
    for x, y in itertools.product(range(n - 1), repeat=2):
        a, b, c, dd = x * n + y, (x + 1) * n + y, (x + 1) * n + y + 1, x * n + y + 1
        if (x + y) % 2:   # both diagonal directions
            tris += [(a, b, c), (a, c, dd)]
        else:
            tris += [(a, b, dd), (b, c, dd)]
    tris = np.array(tris)     # counter-clockwise
    rng = np.random.default_rng(2)
    for _ in range(5):
        gid = rng.permutation(1000)[:len(pts)]
        ia, ib, ic = (gid[tris[:, m]] for m in range(3))
        pa, pb, pc = (pts[tris[:, m]] for m in range(3))
        _, s_bc = run_edge(ib, pb, ic, pc)
        _, s_ca = run_edge(ic, pc, ia, pa)
        _, s_ab = run_edge(ia, pa, ib, pb)
        inside = s_bc & s_ca & s_ab
        assert inside.sum() == 1
        np.testing.assert_array_equal(inside, edge_function_np(ib, pb, ic, pc)[1]
                                      & edge_function_np(ic, pc, ia, pa)[1]
                                      & edge_function_np(ia, pa, ib, pb)[1])


# ----------------------------------------------------------------------------
# face_weights
# ----------------------------------------------------------------------------

def run_weights(e):
    w = face_weights(*(mi.Float(np.asarray(x, np.float32)) for x in e.T))
    return np.stack([arr(x) for x in w], -1)


def test_face_weights():
    rng = np.random.default_rng(3)
    e = f32(np.concatenate([rng.uniform(0.01, 1, (500, 3)), -rng.uniform(0.01, 1, (500, 3)),
                            rng.normal(size=(1000, 3))]))
    w = run_weights(e)
    w_np = np.stack(face_weights_np(*e.T), -1)
    np.testing.assert_allclose(w, w_np, rtol=1e-5, atol=1e-6)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(1), 1, rtol=1e-6)


def test_face_weights_degenerate():
    e = f32([[0, 0, 0], [1, -1, 0], [2, -1, -1], [1, 0, 0], [0, -2, 0], [3, -1, 0],
             [-3, 1, 0], [1e-30, 1e-30, 1e-30], [1e30, 1e30, -1e30], [-0.0, 0, 0]])
    w = run_weights(e)
    np.testing.assert_allclose(w, np.stack(face_weights_np(*e.T), -1), rtol=1e-6)
    np.testing.assert_array_equal(w[:3], np.float32(1 / 3))         # edge-on triangles
    np.testing.assert_array_equal(w[3], [1, 0, 0])
    np.testing.assert_array_equal(w[4], [0, 1, 0])
    np.testing.assert_array_equal(w[5], [1, 0, 0])                   # clamped and renormalized
    np.testing.assert_array_equal(w[6], [1, 0, 0])
    np.testing.assert_array_equal(w[8], [0.5, 0.5, 0])


# ----------------------------------------------------------------------------
# ray_frame, project
# ----------------------------------------------------------------------------

def test_ray_frame_and_project():
    rng = np.random.default_rng(4)
    d = f32(random_unit(rng, 2000))
    u, v = kernel_frame(d)
    u_np, v_np = ray_frame_np(d)
    np.testing.assert_allclose(u, u_np, atol=2e-6)
    np.testing.assert_allclose(v, v_np, atol=2e-6)
    np.testing.assert_allclose(np.cross(u, v), d, atol=3e-6)
    np.testing.assert_allclose((u * v).sum(1), 0, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1, atol=2e-6)
    P, o = f32(rng.normal(size=(2000, 3)) * 2), f32(rng.normal(size=(2000, 3)) * 4)
    p = arr(project(p3(P), p3(o), v3(u), v3(v)))
    np.testing.assert_allclose(p, project_np(P, o, u, v), atol=1e-5)


def test_ray_frame_axes():
    """Axis directions (signed zeros included) give exact frames."""
    d = np.array([[0, 0, 1], [0, 0, -1], [0, 0, -0.0], [1, 0, 0], [-1, 0, 0], [0, 1, 0],
                  [0, -1, 0], [-1, -0.0, 0], [0, 1, -0.0]])
    u, v = kernel_frame(d)
    u_np, v_np = ray_frame_np(d)
    np.testing.assert_array_equal(u, u_np)
    np.testing.assert_array_equal(v, v_np)


# ----------------------------------------------------------------------------
# crossing: values, symmetry, gradients
# ----------------------------------------------------------------------------

def random_crossings(rng, k, inside=0.1):
    """Rays and triangles that they cross with every weight >= ``inside``."""
    d = random_unit(rng, k)
    d = d[np.abs(d[:, 2]) > 0.1][: k // 2]   # away from the frame's switch at d.z = 0
    k = len(d)
    o = rng.normal(size=(k, 3)) * 2
    X = o + rng.uniform(0.5, 3, (k, 1)) * d
    w = rng.uniform(inside, 1, (k, 3))
    w /= w.sum(1, keepdims=True)
    # corners around X, then shifted so that X has the weights w
    C = rng.normal(size=(k, 3, 3)) * 0.5
    C += (X - np.einsum("kj,kjc->kc", w, C))[:, None]
    ids = np.stack([rng.permutation(100)[:3] for _ in range(k)])
    return ids, f32(C), f32(o), f32(d)


def run_crossing(ids, P, p, o, d):
    t, w = crossing(tuple(u32(x) for x in ids), tuple(p3(x) for x in P),
                    tuple(p2(x) for x in p), p3(o), v3(d))
    return arr(t), np.stack([arr(x) for x in w], -1)


def test_crossing_random():
    rng = np.random.default_rng(5)
    ids, C, o, d = random_crossings(rng, 4000, inside=0.0)
    u, v = kernel_frame(d)
    P = [C[:, j] for j in range(3)]
    p = [f32(project_np(Pj, o, u, v)) for Pj in P]
    t, w = run_crossing(ids.T, P, p, o, d)
    t_np, w_np = crossing_np(tuple(ids.T), P, p, o, d)
    w_np = np.stack(w_np, -1)
    # projected area: the weights' condition number
    e1, e2 = p[1] - p[0], p[2] - p[0]
    area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    ok = area > 1e-2
    np.testing.assert_allclose(w[ok], w_np[ok], atol=1e-4)
    np.testing.assert_allclose(t[ok], t_np[ok], atol=1e-4 * np.abs(t_np[ok]).max())
    # the crossing point lies on the ray, up to the weights' round-off
    X = np.einsum("kj,kjc->kc", w, C)
    np.testing.assert_allclose((o + t[:, None] * d)[ok], X[ok], atol=2e-4)


def test_crossing_exact():
    """Integer triangles crossed by axis rays at vertices, on edges, inside,
    outside (clamped weights), and seen edge-on (equal weights)."""
    rng = np.random.default_rng(6)
    k = 3000
    C = rng.integers(-2, 3, (k, 3, 3)).astype(np.float64)
    o = rng.integers(-2, 3, (k, 3)).astype(np.float64) / 2
    o[:, 2] = -5
    d = np.tile([0.0, 0.0, 1.0], (k, 1))
    ids = np.stack([rng.permutation(10)[:3] for _ in range(k)])
    u, v = kernel_frame(d)
    P = [C[:, j] for j in range(3)]
    p = [project_np(Pj, o, u, v) for Pj in P]
    t, w = run_crossing(ids.T, P, p, o, d)
    t_np, w_np = crossing_np(tuple(ids.T), P, p, o, d)
    w_np = np.stack(w_np, -1)
    # Weights are quotients of exact integers, so both round them once the
    # same way except for the reciprocal; compare tightly.
    np.testing.assert_allclose(w, w_np, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(t, t_np, rtol=1e-6, atol=1e-6)
    on_edge = np.any(w_np == 0, axis=1) & ~np.all(w_np == 1 / 3, axis=1)
    edge_on = np.all(w_np == 1 / 3, axis=1)
    assert on_edge.sum() > 100 and edge_on.sum() > 10


def test_crossing_same_from_both_sides():
    """Rotating or reversing a face's vertices permutes the weights and keeps
    the ray parameter (the edge functions are canonical)."""
    rng = np.random.default_rng(7)
    ids, C, o, d = random_crossings(rng, 2000, inside=0.0)
    u, v = kernel_frame(d)
    P = [C[:, j] for j in range(3)]
    p = [f32(project_np(Pj, o, u, v)) for Pj in P]
    t, w = run_crossing(ids.T, P, p, o, d)
    for perm in ((1, 2, 0), (2, 0, 1), (0, 2, 1), (2, 1, 0)):
        t2, w2 = run_crossing(ids.T[list(perm)], [P[j] for j in perm], [p[j] for j in perm],
                              o, d)
        np.testing.assert_allclose(w2, w[:, list(perm)], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(t2, t, rtol=1e-6, atol=1e-6)


def test_crossing_gradient():
    """Reverse-mode derivatives of (t, w) w.r.t. the face's corners, the ray
    origin and direction (through the ray frame and the projections), with
    random cotangents, against central differences of the float64 twin."""
    rng = np.random.default_rng(8)
    ids, C, o, d = random_crossings(rng, 1000, inside=0.1)
    n = np.cross(C[:, 1] - C[:, 0], C[:, 2] - C[:, 0])
    steep = np.abs((n * d).sum(1)) > 0.3 * np.linalg.norm(n, axis=1)   # not seen edge-on
    ids, C, o, d = ids[steep], C[steep], o[steep], d[steep]
    k = len(d)
    ct_t, ct_w = rng.normal(size=k), rng.normal(size=(k, 3))

    P_dr = [p3(C[:, j]) for j in range(3)]
    o_dr, d_dr = p3(o), v3(d)
    dr.enable_grad(P_dr, o_dr, d_dr)
    u_dr, v_dr = ray_frame(d_dr)
    t, w = crossing(tuple(u32(x) for x in ids.T), tuple(P_dr),
                    tuple(project(Pj, o_dr, u_dr, v_dr) for Pj in P_dr), o_dr, d_dr)
    loss = t * mi.Float(np.float32(ct_t)) + sum(wj * mi.Float(np.float32(ct_w[:, j]))
                                                 for j, wj in enumerate(w))
    dr.backward(loss)
    grad = np.concatenate([arr(dr.grad(x)) for x in (*P_dr, o_dr, d_dr)], 1)   # (k, 15)

    x0 = np.concatenate([C[:, 0], C[:, 1], C[:, 2], o, d], 1)

    def f(x):
        P = [x[:, 3 * j:3 * j + 3] for j in range(3)]
        t, w = crossing_from_positions_np(tuple(ids.T), P, x[:, 9:12], x[:, 12:15])
        return t * ct_t + sum(wj * ct_w[:, j] for j, wj in enumerate(w))

    h = 1e-6
    fd = np.stack([(f(x0 + h * np.eye(15)[c]) - f(x0 - h * np.eye(15)[c])) / (2 * h)
                   for c in range(15)], 1)
    scale = np.abs(fd).max(1, keepdims=True)
    assert np.all(np.abs(grad - fd) <= 2e-3 * scale + 1e-5)


# ----------------------------------------------------------------------------
# clip_segment: values, pass-through, gradients
# ----------------------------------------------------------------------------

def random_segments(rng, k, margin=0.0):
    """Segments before, across the start of, inside, across the end of,
    covering and after the window ``[t_begin, t_end]``, at least ``margin``
    away from its ends."""
    m = margin
    tb = rng.uniform(0, 1, k)
    te = tb + rng.uniform(0.5, 2, k)
    r = lambda: rng.uniform(0, 1, k)  # noqa: E731
    inner = lambda: tb + m + r() * (te - tb - 2 * m)  # noqa: E731
    kind = rng.integers(0, 6, k)
    before, after = tb - m - r(), te + m + r()
    t0 = np.choose(kind, [before - 0.1 - r(), before, tb + m + 0.4 * r() * (te - tb - 2 * m),
                          inner(), before, after])
    t1 = np.choose(kind, [before, inner(), te - m - 0.4 * r() * (te - tb - 2 * m),
                          after, after, after + 0.1 + r()])
    x0, x1 = rng.uniform(0, 1, (k, 4)), rng.uniform(0, 1, (k, 4))
    return f32(t0), f32(x0), f32(t1), f32(x1), f32(tb), f32(te)


def run_clip(t0, x0, t1, x1, tb, te):
    def attrs(x):
        return (mi.Color3f(*np.asarray(x[:, :3], np.float32).T), mi.Float(np.float32(x[:, 3])))
    length, xb, xe = clip(mi.Float(np.float32(t0)), attrs(x0), mi.Float(np.float32(t1)),
                          attrs(x1), mi.Float(np.float32(tb)), mi.Float(np.float32(te)))
    flat = lambda a: np.concatenate([arr(a[0]), arr(a[1])[:, None]], 1)  # noqa: E731
    return arr(length), flat(xb), flat(xe)


def test_clip_segment_random():
    rng = np.random.default_rng(9)
    args = random_segments(rng, 6000)
    length, xb, xe = run_clip(*args)
    l_np, xb_np, xe_np = clip_segment_np(*args)
    np.testing.assert_allclose(length, l_np, atol=2e-6)
    np.testing.assert_allclose(xb, xb_np, atol=2e-6)
    np.testing.assert_allclose(xe, xe_np, atol=2e-6)
    assert np.all(length >= 0)


def test_clip_segment_exact():
    """Unclipped segments pass bit-exactly; empty and zero-length ones give
    length 0 and finite attributes (never a division by zero)."""
    rng = np.random.default_rng(10)
    k = 500
    x0, x1 = f32(rng.uniform(0, 1, (k, 4))), f32(rng.uniform(0, 1, (k, 4)))
    t0 = f32(rng.uniform(1, 2, k))
    t1 = f32(t0 + rng.uniform(0, 1, k))
    # inside [0, 3]; window ends exactly at the segment's ends
    for tb, te in ((np.zeros(k), np.full(k, 3.0)), (t0, t1), (t0, np.full(k, 3.0))):
        length, xb, xe = run_clip(t0, x0, t1, x1, tb, te)
        np.testing.assert_array_equal(length, f32(np.float32(t1) - np.float32(t0)))
        np.testing.assert_array_equal(xb, x0)
        np.testing.assert_array_equal(xe, x1)
    # zero-length segments, inside, clipped and outside the window
    for tb, te in ((np.zeros(k), np.full(k, 3.0)), (t0 + 0.5, t0 + 1), (t0 - 1, t0 - 0.5)):
        length, xb, xe = run_clip(t0, x0, t0, x1, f32(tb), f32(te))
        np.testing.assert_array_equal(length, 0)
        assert np.all(np.isfinite(xb)) and np.all(np.isfinite(xe))
        np.testing.assert_array_equal(xb, x0)
    # segments entirely before / after the window
    for tb, te, at in ((t1 + 0.5, t1 + 1, x1), (t0 - 1, t0 - 0.5, x0)):
        length, xb, xe = run_clip(t0, x0, t1, x1, f32(tb), f32(te))
        np.testing.assert_array_equal(length, 0)
        np.testing.assert_allclose(xb, at, atol=1e-6)
        np.testing.assert_allclose(xe, at, atol=1e-6)


def test_clip_segment_gradient():
    """Reverse-mode derivatives w.r.t. all inputs with random cotangents
    against central differences of the float64 twin (away from the kinks at
    the window's ends)."""
    rng = np.random.default_rng(11)
    t0, x0, t1, x1, tb, te = random_segments(rng, 3000, margin=0.05)
    k = len(t0)
    ct_l, ct_b, ct_e = rng.normal(size=k), rng.normal(size=(k, 4)), rng.normal(size=(k, 4))

    ins = [mi.Float(np.float32(t0)), mi.Color3f(*np.float32(x0[:, :3]).T),
           mi.Float(np.float32(x0[:, 3])), mi.Float(np.float32(t1)),
           mi.Color3f(*np.float32(x1[:, :3]).T), mi.Float(np.float32(x1[:, 3])),
           mi.Float(np.float32(tb)), mi.Float(np.float32(te))]
    dr.enable_grad(*ins)
    length, (cb, sb), (ce, se) = clip(ins[0], (ins[1], ins[2]), ins[3], (ins[4], ins[5]),
                                      ins[6], ins[7])
    F = lambda x: mi.Float(np.float32(x))  # noqa: E731
    C3 = lambda x: mi.Color3f(*np.float32(x).T)  # noqa: E731
    loss = (length * F(ct_l) + dr.dot(cb, C3(ct_b[:, :3])) + sb * F(ct_b[:, 3])
            + dr.dot(ce, C3(ct_e[:, :3])) + se * F(ct_e[:, 3]))
    dr.backward(loss)
    g = [arr(dr.grad(x)) for x in ins]
    grad = np.concatenate([x if x.ndim == 2 else x[:, None] for x in g], 1)  # (k, 12)

    xin = np.concatenate([t0[:, None], x0, t1[:, None], x1, tb[:, None], te[:, None]], 1)

    def f(x):
        length, xb, xe = clip_segment_np(x[:, 0], x[:, 1:5], x[:, 5], x[:, 6:10], x[:, 10],
                                         x[:, 11])
        return length * ct_l + (xb * ct_b).sum(1) + (xe * ct_e).sum(1)

    h = 1e-6
    fd = np.stack([(f(xin + h * np.eye(12)[c]) - f(xin - h * np.eye(12)[c])) / (2 * h)
                   for c in range(12)], 1)
    scale = np.abs(fd).max(1, keepdims=True)
    assert np.all(np.abs(grad - fd) <= 1e-3 * scale + 1e-5)


# ----------------------------------------------------------------------------
# face_entry: the boundary face (and tet) a ray starts in
# ----------------------------------------------------------------------------

def run_face_entry(buf, face, o, d):
    tet, f, outward = face_entry(buf, u32(face), RayFrame.of(p3(o), v3(d)), mi.Bool(True))
    return (np.asarray(tet, np.int64), np.asarray(f, np.int64), np.asarray(outward, bool))


def incident_faces(mesh, X, d, facing):
    """Boundary faces whose closed triangle contains the point ``X`` (on the
    boundary) and that face against (``facing < 0``) or along the ray."""
    A, B, C = (mesh.V[mesh.faces[:, j]] for j in range(3))
    n = mesh.normal
    out = []
    for x, dd in zip(X, d):
        on_plane = np.isclose(((x - A) * n).sum(1), 0, atol=1e-9)
        la = (np.cross(B - x, C - x) * n).sum(1)
        lb = (np.cross(C - x, A - x) * n).sum(1)
        lc = (np.cross(A - x, B - x) * n).sum(1)
        inside = on_plane & (la >= -1e-9) & (lb >= -1e-9) & (lc >= -1e-9)
        out.append(np.flatnonzero(inside & ((n * dd).sum(1) * facing > 0)))
    return out


def test_face_entry_exact(exact_mesh):
    """Axis rays through the vertices, edges and faces of the boundary:
    starting from *any* front (or back, for the exit) face that contains the
    hit point (the face Mitsuba's ray tracer reports is any of them), the
    result is the one face that the consistent predicate picks, and the
    kernel agrees with its twin exactly."""
    buf, mesh, o, d = exact_mesh
    u, v = kernel_frame(d)
    entry, exit_ = boundary_hits_np(mesh, o, u, v, d)
    assert np.all(entry != -2) and np.all(exit_ != -2)      # never two faces
    np.testing.assert_array_equal(entry >= 0, exit_ >= 0)    # in and out again
    hit = np.flatnonzero(entry >= 0)
    assert len(hit) > 0.3 * len(o)
    for faces, want_out in ((entry, False), (exit_, True)):
        # where the ray meets the plane of the face the predicate picks
        A, n = mesh.V[mesh.faces[faces[hit], 0]], mesh.normal[faces[hit]]
        X = o[hit] + (((A - o[hit]) * n).sum(1) / (d[hit] * n).sum(1))[:, None] * d[hit]
        starts = incident_faces(mesh, X, d[hit], 1 if want_out else -1)
        lanes = np.concatenate([np.full(len(s), r) for r, s in zip(hit, starts)])
        start = np.concatenate(starts)
        assert len(start) > 1.5 * len(hit)            # rays through shared edges / vertices
        tet, f, outward = run_face_entry(buf, start, o[lanes], d[lanes])
        tet_np, f_np, out_np, _ = face_entry_np(mesh, start, o[lanes], u[lanes], v[lanes],
                                                d[lanes])
        np.testing.assert_array_equal(tet, tet_np)
        np.testing.assert_array_equal(f, f_np)
        np.testing.assert_array_equal(outward, out_np)
        # The boundary walk, given enough steps, always ends on that face ...
        want = faces[lanes]
        _, _, _, reached = face_entry_np(mesh, start, o[lanes], u[lanes], v[lanes], d[lanes],
                                         steps=64)
        np.testing.assert_array_equal(reached, want)
        # ... and the kernel's does within its BOUNDARY_WALK_STEPS.
        np.testing.assert_array_equal(tet, mesh.btet[want])
        np.testing.assert_array_equal(f, mesh.bface[want])
        np.testing.assert_array_equal(outward, np.full(len(want), want_out))


def test_face_entry_random(jittered):
    """Random rays into a jittered mesh, from the face they cross and, when
    they hit it near an edge (where a float32 ray tracer may report either
    face), from the face across that edge in the same plane. Rays whose edge functions are
    within round-off of zero are left out: float32 and float64 may pick
    different sides there."""
    buf, mesh = jittered
    rng = np.random.default_rng(12)
    o, d = rays_at(rng, 4000, radius=4.0, target_extent=0.9)
    o, d = f32(o), f32(d)
    u, v = kernel_frame(d)
    entry, _ = boundary_hits_np(mesh, o, u, v, d)
    assert np.all(entry >= 0)
    # hit point and its distance to the edge opposite each corner of the entry face
    A, n = mesh.V[mesh.faces[entry, 0]], mesh.normal[entry]
    X = o + (((A - o) * n).sum(1) / (d * n).sum(1))[:, None] * d
    corners = [mesh.V[mesh.faces[entry, j]] for j in range(3)]
    for j, start in enumerate([None, 0, 1, 2]):
        if start is None:
            face = entry
            lanes = np.ones(len(o), bool)
        else:   # the neighbour in the same plane, when the ray hits near the shared edge
            face = mesh.face_adj[entry, start]
            a, b = corners[(start + 1) % 3], corners[(start + 2) % 3]
            dist = np.linalg.norm(np.cross(X - a, b - a), axis=1) / np.linalg.norm(b - a, axis=1)
            coplanar = np.linalg.norm(np.cross(mesh.normal[face], n), axis=1) == 0
            lanes = (dist < 0.05) & coplanar
        for e, _ in (*mesh.face_signs(entry, o, u, v), *mesh.face_signs(face, o, u, v)):
            lanes &= np.abs(e) > 1e-4
        assert lanes.sum() > (0.9 * len(o) if start is None else 200)
        tet, f, outward = run_face_entry(buf, face[lanes], o[lanes], d[lanes])
        np.testing.assert_array_equal(tet, mesh.btet[entry[lanes]])
        np.testing.assert_array_equal(f, mesh.bface[entry[lanes]])
        assert not outward.any()


# ----------------------------------------------------------------------------
# walk_step: whole walks of the twin, one kernel step per visited tet
# ----------------------------------------------------------------------------

def walk_np(mesh, tet, f_in, o, u, v, d, max_steps=200):
    """Every (ray, tet, entry face) of twin walks; the faces they leave by."""
    lanes, tets, fins = [], [], []
    lane = np.arange(len(o))
    last = np.full(len(o), -1)
    for _ in range(max_steps):
        if not len(lane):
            break
        lanes.append(lane)
        tets.append(tet)
        fins.append(f_in)
        _, _, nt, nf, _, ids = walk_step_np(mesh, tet, f_in, o[lane], u[lane], v[lane], d[lane])
        done = nt < 0
        # leaving the mesh: which boundary face (by its vertices)
        key = np.sort(np.stack(ids, 1)[done], 1)
        fkeys = np.sort(mesh.faces, 1)
        last[lane[done]] = [int(np.flatnonzero((fkeys == kk).all(1))[0]) for kk in key]
        lane, tet, f_in = lane[~done], nt[~done], nf[~done]
    assert not len(lane), "walk did not end"
    return (np.concatenate(lanes), np.concatenate(tets), np.concatenate(fins)), last


def test_walk_step_exact(exact_mesh):
    """Axis rays through vertices and along edges and faces: the kernel's step
    agrees exactly with the twin's on every state of the twin's walks, and
    each walk leaves through the one exit face of the predicate."""
    buf, mesh, o, d = exact_mesh
    check_walk_step(buf, mesh, o, d, exact=True)


def test_walk_step_random(jittered):
    """Random rays through a jittered mesh: as above, decisions compared away
    from ties."""
    buf, mesh = jittered
    o, d = rays_at(np.random.default_rng(13), 1000, radius=4.0, target_extent=0.9)
    check_walk_step(buf, mesh, f32(o), f32(d), exact=False)


def check_walk_step(buf, mesh, o, d, exact):
    u, v = kernel_frame(d)
    entry, exit_ = boundary_hits_np(mesh, o, u, v, d)
    hit = np.flatnonzero(entry >= 0)
    (lanes, tets, fins), last = walk_np(mesh, mesh.btet[entry[hit]], mesh.bface[entry[hit]],
                                        o[hit], u[hit], v[hit], d[hit])
    np.testing.assert_array_equal(last, exit_[hit])
    lanes = hit[lanes]
    t_np, w_np, nt, nf, lz, ids = walk_step_np(mesh, tets, fins, o[lanes], u[lanes], v[lanes],
                                               d[lanes])
    st = walk_step(buf, u32(tets), u32(fins), RayFrame.of(p3(o[lanes]), v3(d[lanes])),
                   mi.Bool(True))
    link = np.asarray(st.link, np.int64)
    n_tet, n_face = (np.asarray(x, np.int64) for x in unpack_link(st.link))
    f_out = np.asarray(st.f_out, np.int64)
    exit_ids = np.stack([np.asarray(x, np.int64) for x in st.exit], 1)
    t, w = arr(st.t), np.stack([arr(x) for x in st.w], -1)
    if not exact:   # decisions agree away from ties
        near = np.zeros(len(lanes), bool)
        loc = FACE_ORDER_NP[fins]
        vid = np.take_along_axis(mesh.tets[tets], loc, 1)
        pk = project_np(mesh.V[vid[:, 0]], o[lanes], u[lanes], v[lanes])
        for j in (1, 2, 3):
            pj = project_np(mesh.V[vid[:, j]], o[lanes], u[lanes], v[lanes])
            near |= np.abs(edge_function_np(vid[:, 0], pk, vid[:, j], pj)[0]) < 1e-4
        assert near.mean() < 0.05
        keep = ~near
    else:
        keep = np.ones(len(lanes), bool)
    np.testing.assert_array_equal(f_out[keep], lz[keep])
    # The exit face and its weights, vertex by vertex (in any corner order).
    twin_ids, w_np = np.stack(ids, 1), np.stack(w_np, -1)
    order, twin_order = np.argsort(exit_ids, 1), np.argsort(twin_ids, 1)
    exit_ids, twin_ids = (np.take_along_axis(x, o_, 1) for x, o_ in
                          ((exit_ids, order), (twin_ids, twin_order)))
    w, w_np = np.take_along_axis(w, order, 1), np.take_along_axis(w_np, twin_order, 1)
    np.testing.assert_array_equal(exit_ids[keep], twin_ids[keep])
    np.testing.assert_array_equal(link[keep] < 0, nt[keep] < 0)
    inner = keep & (nt >= 0)
    np.testing.assert_array_equal(n_tet[inner], nt[inner])
    np.testing.assert_array_equal(n_face[inner], nf[inner])
    np.testing.assert_allclose(w[keep], w_np[keep], atol=1e-4)
    np.testing.assert_allclose(t[keep], t_np[keep], atol=1e-5 * np.abs(t_np).max())


def test_index_arrays_in_morton_order():
    """The walk's tet records of a shuffled mesh in Morton order: every link
    is mutual and names the same triangle from both sides, every boundary
    link names its boundary face, the tets are those of the mesh, and
    neighbours sit much closer in memory than in the shuffled input. The
    order is chosen for a scattered mesh only."""
    V, T = grid_mesh(16, jitter=0.1, seed=4)
    grid_topo = build_topology(V, T, warn=False)
    assert far_links(grid_topo.neighbors) < 0.2
    keep = shape_index_arrays(grid_topo, V)
    np.testing.assert_array_equal(tets_of(keep["cells"]), grid_topo.tets)
    rng = np.random.default_rng(5)
    T = T[rng.permutation(len(T))]
    topo = build_topology(V, T, warn=False)
    assert far_links(topo.neighbors) > 0.9
    idx = shape_index_arrays(topo, V)
    tets = tets_of(idx["cells"]).astype(np.int64)
    assert sorted(map(tuple, np.sort(tets, 1))) == sorted(map(tuple, np.sort(topo.tets, 1)))
    link = links_of(idx["cells"]).astype(np.int64)
    t, f = np.nonzero(link >= 0)
    t2, f2 = link[t, f] // 4, link[t, f] % 4
    np.testing.assert_array_equal(link[t2, f2], 4 * t + f)
    face = np.sort(tets[t[:, None], FACES[f]], 1)
    np.testing.assert_array_equal(face, np.sort(tets[t2[:, None], FACES[f2]], 1))
    b = idx["boundary"].astype(np.int64)
    np.testing.assert_array_equal(np.sort(tets[(b // 4)[:, None], FACES[b % 4]], 1),
                                  np.sort(idx["faces"].reshape(-1, 3), 1))
    assert np.all(link[b // 4, b % 4] < 0)
    shuffled = topo.neighbors.astype(np.int64)
    ts_, fs_ = np.nonzero(shuffled >= 0)
    assert np.abs(t2 - t).mean() < 0.2 * np.abs(shuffled[ts_, fs_] - ts_).mean()


def test_crossing_vjp_matches_ad():
    """The closed-form reverse derivative of a crossing (what the adjoint
    uses) against Dr.Jit's AD of :func:`crossing_at` and of the
    interpolated values, on random triangles and cotangents."""
    from mi_tetvr.render.geometry import Corner, crossing_at, crossing_vjp, face_edges
    rng = np.random.default_rng(31)
    # triangles the ray crosses (they hold the origin of the 2D frame, as
    # in the walk, away from their edges: no weight is clamped), depths, values
    ang = np.sort(rng.uniform(0, 2 * np.pi, (20000, 3)), 1)
    gaps = np.diff(np.concatenate([ang, ang[:, :1] + 2 * np.pi], 1), axis=1)
    ang = ang[gaps.max(1) < 0.8 * np.pi][:400]
    k = len(ang)
    assert k == 400
    rad = rng.uniform(0.2, 1.0, (k, 3))
    px, py = rad * np.cos(ang), rad * np.sin(ang)
    z = rng.uniform(1, 3, (k, 3))
    val = rng.uniform(0, 1, (k, 3))
    g_t, g_a = rng.normal(size=k), rng.normal(size=k)
    ids = [u32(np.arange(k) * 3 + j) for j in range(3)]
    P = [mi.Point2f(f32(px[:, j]), f32(py[:, j])) for j in range(3)]
    Z = [mi.Float(f32(z[:, j])) for j in range(3)]
    V = [mi.Float(f32(val[:, j])) for j in range(3)]
    dr.enable_grad(P, Z, V)
    c = tuple(Corner(ids[j], P[j], Z[j]) for j in range(3))
    t, w = crossing_at(c)
    a = w[0] * V[0] + w[1] * V[1] + w[2] * V[2]
    dr.backward_from(t * mi.Float(g_t) + a * mi.Float(g_a))
    with dr.suspend_grad():
        cd = tuple(Corner(ids[j], dr.detach(P[j]), dr.detach(Z[j])) for j in range(3))
        out = crossing_vjp(cd, face_edges(cd), tuple(dr.detach(x) for x in V),
                           mi.Float(g_t), mi.Float(g_a))
    for j, (dp, dz, dv) in enumerate(out):
        np.testing.assert_allclose(arr(dp.x), arr(dr.grad(P[j]).x), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(arr(dp.y), arr(dr.grad(P[j]).y), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(arr(dz), arr(dr.grad(Z[j])), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(arr(dv), arr(dr.grad(V[j])), rtol=1e-5, atol=1e-6)
