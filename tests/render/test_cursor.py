"""The cursor on its own: a client that only records where rays go, run through the
general traversal (a mesh that is not convex, rays that start inside it: the walk back,
``locate``), the convex one and the merged walk of overlapping meshes, against a numpy
brute force in float64 that clips every ray against every tet. Each (ray, tet) pair's
length inside the tet must be the walk's; the rays aim at the meshes' vertices and edges
(grazing them), at random points, and start inside and outside.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import FACES
from mi_tetvr.render.cursor import Span, traverse, traverse_merged
from mi_tetvr.render.geometry import RayFrame
from mi_tetvr.render.walk import Emission, Radiance


def clipped_lengths(V, T, o, d, t_max):
    """(rays, tets) float64: the length of each ray ``o + t d``, ``0 <= t <= t_max``
    (``d`` unit), inside each tet, by clipping against its four face planes."""
    P = V[T]                                            # (m, 4, 3)
    t0 = np.zeros((len(o), len(T)))
    t1 = np.full((len(o), len(T)), float(t_max))
    for f in range(4):
        a, b, c = (P[:, FACES[f, k]] for k in range(3))
        n = np.cross(b - a, c - a)                      # outward for a positive tet
        n *= np.sign(np.einsum("ij,ij->i", n, a - P[:, f]))[:, None]
        # n . (o + t d - a) <= 0
        num = -(o @ n.T - np.einsum("ij,ij->i", n, a)[None])      # (rays, tets)
        den = d @ n.T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        t0 = np.where(den < 0, np.maximum(t0, t), t0)
        t1 = np.where(den > 0, np.minimum(t1, t), t1)
        t1 = np.where((den == 0) & (num < 0), -np.inf, t1)      # parallel, outside
    return np.maximum(t1 - t0, 0.0)


class Recorder(Emission):
    """A client that adds each piece's length to its (ray, tet) cell: ``lengths`` holds
    ``rays * tets`` of them. It never stops a ray (its ``T`` stays 1)."""
    label = "count_walk"

    def __init__(self, ts, settings, lengths, n_tets):
        super().__init__(ts, settings)
        self.cuts = False
        self.lengths, self.n_tets = lengths, n_tets

    def piece(self, acc, p, span, fr, active):
        t0 = dr.clip(p.cur.t, span.begin, span.end)
        t1 = dr.clip(p.t1, span.begin, span.end)
        ray = dr.arange(mi.UInt32, dr.width(t0))
        dr.scatter_add(self.lengths, dr.maximum(t1 - t0, 0.0), ray * self.n_tets + p.cur.tet,
                       active)
        return acc, mi.Bool(True)

    def alive(self, acc):
        return mi.Bool(True)


class MergedRecorder:
    """The same for the merged walk: each mesh's cells in its own ``lengths``."""
    label = "count_merged"
    boundary_terms = False

    def __init__(self, tss, settings, lengths, n_tets):
        self.members = [Emission(ts, settings) for ts in tss]
        for m in self.members:
            m.cuts = False
        self.lengths, self.n_tets = lengths, n_tets

    def piece(self, acc, pc, fr, active):
        ray = dr.arange(mi.UInt32, dr.width(pc.t0))
        for k in range(len(self.members)):
            dr.scatter_add(self.lengths[k], pc.length, ray * self.n_tets[k] + pc.parts[k].cur.tet,
                           active & pc.inside[k] & (pc.length > 0))
        return acc, mi.Bool(True)


def l_shape(seed):
    """A jittered grid over [-1, 1]^3 with one octant taken out (not convex)."""
    V, T = grid_mesh(4, jitter=0.15, seed=seed)
    centre = V[T].mean(1)
    return V, T[~((centre[:, 0] > 0) & (centre[:, 1] > 0) & (centre[:, 2] > 0))]


def grazing_rays(rng, V, T, n):
    """Unit rays: from a sphere of radius 4 at vertices, at edge midpoints and at random
    points of the meshes' box; and from inside the box in random directions."""
    edges = V[T[:, [0, 1]]].mean(1)
    targets = np.concatenate([V[rng.choice(len(V), n)], edges[rng.choice(len(edges), n)],
                              rng.uniform(-0.9, 0.9, (n, 3))])
    u = rng.normal(size=(3 * n, 3))
    o = 4.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    d = targets - o
    inside_o = rng.uniform(-0.8, 0.8, (n, 3))
    inside_d = rng.normal(size=(n, 3))
    o, d = np.concatenate([o, inside_o]), np.concatenate([d, inside_d])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def walk_scene(meshes):
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          **{f"m{k}": mi_tetvr.tetmesh_dict(V, T, np.full((len(V), 3), 0.5),
                                                            np.full(len(V), 0.1))
                             for k, (V, T) in enumerate(meshes)}})
    integrator = scene.integrator()
    tets, boundaries, _ = integrator.parts.split(scene)
    return (boundaries, integrator.parts.apart(tets), integrator.tet_groups(scene),
            integrator.settings_for(scene))


T_MAX = 20.0


def recorded(meshes, o, d):
    """The walk's (rays, tets) lengths, one array per mesh."""
    boundaries, apart, groups, settings = walk_scene(meshes)
    fr = RayFrame.of(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    walked = [g.for_ray(dr.detach(fr.d)).walked() for g in groups]
    n_tets = [len(T) for _, T in meshes]
    lengths = [dr.zeros(mi.Float, len(o) * m) for m in n_tets]
    acc = Radiance(mi.Color3f(0.0), mi.Float(1.0))
    span = Span(mi.Float(0.0), mi.Float(T_MAX))
    if len(meshes) == 1:
        client = Recorder(walked[0], settings, lengths[0], n_tets[0])
        acc, _ = traverse(boundaries, [client], fr, acc, span, settings, True)
    else:
        client = MergedRecorder(walked, settings, lengths, n_tets)
        acc, _ = traverse_merged(apart, client, fr, acc, span, settings, True)
    dr.eval(acc, lengths)
    return [np.array(x).reshape(len(o), m) for x, m in zip(lengths, n_tets)]


def check(meshes, o, d):
    for (V, T), got in zip(meshes, recorded(meshes, o, d)):
        want = clipped_lengths(V, T, o, d, T_MAX)
        assert (want > 1e-3).sum() > 10 * len(o) // 4        # (the rays do cross tets)
        np.testing.assert_allclose(got, want, atol=2e-5 * T_MAX)


@pytest.mark.parametrize("convex", [False, True])
def test_one_mesh_as_the_brute_force_clips_it(convex):
    """The general traversal of a mesh that is not convex (rays leave it and come back;
    rays starting inside are walked back to their start by ``locate``) and the convex
    one, against the brute force."""
    V, T = grid_mesh(4, jitter=0.15, seed=3) if convex else l_shape(3)
    o, d = grazing_rays(np.random.default_rng(11), V, T, 48)
    check([(V, T)], o, d)


def test_overlapping_meshes_as_the_brute_force_clips_each():
    """The merged walk of two overlapping meshes (one not convex): each mesh's lengths
    per tet, as the brute force clips each mesh alone."""
    a = l_shape(4)
    V2, T2 = grid_mesh(3, jitter=0.2, seed=5)
    b = (0.7 * V2 + [0.5, 0.2, -0.1], T2)
    o, d = grazing_rays(np.random.default_rng(12), *a, 32)
    check([a, b], o, d)
