"""The walk is generic over the optical model: an absorption-only model,
plugged into the same walk and adjoint, against the float64 reference
(its transmittance) and central finite differences of that reference."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from tests.helpers import make_scene, rays_at
from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.render.adjoint import Adjoint, Derivative
from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.optical import Absorption
from mi_tetvr.render.walk import trace
from tests.reference import reference_render


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(7)
    V, T = grid_mesh(4, jitter=0.15, seed=3)
    C = rng.uniform(0, 1, (len(V), 3))
    S = rng.uniform(0, 2.0, len(V))
    scene = make_scene((V, T, C, S), min_transmittance=0.0)
    o, d = rays_at(rng, 256)
    return scene, V, T, S, o, d


def absorption_scene(scene, opacity):
    """The scene's tet meshes under the absorption-only model, with the given
    extinction buffer (the shapes carry color too; the model ignores it)."""
    integrator = scene.integrator()
    ts = integrator.tet_group(scene)
    return TetGroup(ts.shapes, ts.face_offsets, ts.buf, Absorption(), Absorption.Params(opacity))


def rays(o, d):
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return mi.Ray3f(mi.Point3f(*o.astype(np.float32).T), mi.Vector3f(*d.astype(np.float32).T))


def reference_alpha(V, T, S, o, d):
    return reference_render(V, T, np.zeros((len(V), 3)), S, o, d)[1]


def test_absorption_transmittance_matches_reference(problem):
    scene, V, T, S, o, d = problem
    ts = absorption_scene(scene, mi.Float(S.astype(np.float32)))
    settings = scene.integrator().settings_for(scene)
    C, Tr, steps, _ = trace(scene, ts, rays(o, d), settings, True)
    assert np.asarray(C).max() == 0.0
    ref = 1.0 - reference_alpha(V, T, S, o, d)
    assert np.asarray(steps).max() > 5
    # The segment transmittance is exact (no sub-intervals): float rounding only.
    np.testing.assert_allclose(np.asarray(Tr), ref, atol=5e-6)


def test_absorption_adjoint_matches_finite_differences(problem):
    scene, V, T, S, o, d = problem
    rng = np.random.default_rng(11)
    weights = rng.uniform(-1, 1, len(o))
    opacity = mi.Float(S.astype(np.float32))
    dr.enable_grad(opacity)
    ts = absorption_scene(scene, opacity)
    settings = scene.integrator().settings_for(scene)
    ray = rays(o, d)
    with dr.suspend_grad():
        _, Tr, _, _ = trace(scene, ts.detached(), ray, settings, True)
    adj = Adjoint(mi.Color3f(0.0), mi.Float(Tr), mi.Color3f(0.0),
                  mi.Float(weights.astype(np.float32)))
    trace(scene, ts.detached(), ray, settings, True, grad=(Derivative(dr.ADMode.Backward, [ts]),
                                                           adj))
    grad = np.asarray(dr.grad(opacity), np.float64)

    def loss(s):
        return float(weights @ reference_alpha(V, T, s, o, d))

    h = 1e-4
    picks = np.argsort(-np.abs(grad))[:8]
    fd = np.array([(loss(S + h * np.eye(len(S))[i]) - loss(S - h * np.eye(len(S))[i])) / (2 * h)
                   for i in picks])
    assert np.abs(fd).max() > 1e-2
    np.testing.assert_allclose(grad[picks], fd, rtol=1e-4)


def test_a_lookup_reads_inside_its_table_whatever_the_coordinate():
    """The piece of a transfer function or table that a coordinate reads: the
    one holding it, the first or last beyond the samples, and the first for a
    NaN (an inactive lane's coordinate), never an index outside the table
    (such a read crashed a forward-mode pass)."""
    from mi_tetvr.render.optical import piece_of
    x = [np.nan, -np.inf, -3.0, 0.0, 0.5, 1.0, 2.7, 3.0, 9.0, np.inf]
    k = np.array(piece_of(mi.Float(np.array(x, np.float32)), 4))
    assert k.tolist() == [0, 0, 0, 0, 0, 1, 2, 2, 2, 2]
