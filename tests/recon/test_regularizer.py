"""Tet-quality regularizer (DiffTetVR Eq. 16-21)."""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import quality, signed_volumes
from mi_tetvr.recon.regularizer import (DEFAULT_BETA, DEFAULT_WEIGHT, QualityRegularizer,
                                        quality_penalty_np, tet_regularizer)

# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------


def f32(v):
    """Round to float32-representable float64, so float32 Dr.Jit and the float64
    reference see the same points."""
    return np.asarray(v, np.float32).astype(np.float64)


def ad_value_grad(reg, v, Float=None):
    Float = Float or mi.Float
    P = Float(np.asarray(v).ravel())
    dr.enable_grad(P)
    loss = reg(P)
    dr.backward(loss)
    return float(loss[0]), np.array(dr.grad(P), np.float64).reshape(-1, 3)


def fd_grad(v, tets, entries, beta, weight, h=1e-6):
    """Central differences of the float64 numpy reference at flat entries."""
    out = []
    for e in entries:
        vp, vm = v.copy().ravel(), v.copy().ravel()
        vp[e] += h
        vm[e] -= h
        out.append((quality_penalty_np(vp.reshape(-1, 3), tets, beta, weight)
                    - quality_penalty_np(vm.reshape(-1, 3), tets, beta, weight)) / (2 * h))
    return np.array(out)


def rel_l2(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def regular_tet():
    """A regular tet, positively oriented as (0, 1, 2, 3)."""
    return np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float) * 0.5


def flat_mesh(height):
    """Three tets; tet 1 has height ``height`` over the base (0, 1, 2)
    (``height = 0``: a zero-volume tet)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 0.9],
                  [0.4, 0.35, height], [0.2, -0.6, 0.4]], float)
    t = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 3, 5]])
    # orient positively where the volume is non-zero
    vol = signed_volumes(v, t)
    t[vol < 0] = t[vol < 0][:, [0, 1, 3, 2]]
    return v, t


# --------------------------------------------------------------------------
# regularizer
# --------------------------------------------------------------------------


def test_defaults_from_paper():
    assert (DEFAULT_BETA, DEFAULT_WEIGHT) == (100.0, 10.0)


def test_quality_matches_mesh_quality():
    v, t = grid_mesh(3, jitter=0.4, seed=3)
    v = f32(v)
    reg = QualityRegularizer(t)
    q32 = np.array(reg.quality(mi.Float(v.ravel())))
    q64 = np.array(reg.quality(mi.Float64(v.ravel())))
    ref = quality(v, t)
    assert np.allclose(q64, ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(q32, ref, rtol=1e-5, atol=1e-6)
    # the regular tet has quality 1, its inversion -1
    rt = regular_tet()
    tt = np.array([[0, 1, 2, 3], [0, 1, 3, 2]])
    assert np.allclose(np.array(QualityRegularizer(tt).quality(mi.Float64(rt.ravel()))),
                       [1, -1], atol=1e-12)


@pytest.mark.parametrize("reduce", ["sum", "mean"])
def test_value_matches_numpy(reduce):
    v, t = grid_mesh(3, jitter=0.45, seed=1)
    v = f32(v)
    for beta, weight in ((100.0, 10.0), (10.0, 0.5)):
        reg = QualityRegularizer(t, beta=beta, weight=weight, reduce=reduce)
        ref = quality_penalty_np(v, t, beta, weight, reduce)
        assert np.isclose(float(reg(mi.Float64(v.ravel()))[0]), ref, rtol=1e-12)
        assert np.isclose(float(reg(mi.Float(v.ravel()))[0]), ref, rtol=1e-5)
    # sign: inverted tets cost ~|Q| each, a regular one ~nothing (Softplus(-Q))
    rt = regular_tet()
    good = quality_penalty_np(rt, [[0, 1, 2, 3]], 100, 1)
    bad = quality_penalty_np(rt, [[0, 1, 3, 2]], 100, 1)
    assert good < 1e-40 and np.isclose(bad, 1.0)
    assert np.isclose(float(tet_regularizer(mi.Float(rt.ravel()), [[0, 1, 3, 2]], 100, 1)[0]),
                      1.0, rtol=1e-6)


@pytest.mark.parametrize("beta", [100.0, 10.0])
def test_gradient_jittered_grid(beta):
    # jitter 0.45: a few tets are nearly flat or inverted (quality -0.04 .. 0.03)
    v, t = grid_mesh(3, jitter=0.45, seed=0)
    v = f32(v)
    reg = QualityRegularizer(t, beta=beta, weight=DEFAULT_WEIGHT)
    _, g = ad_value_grad(reg, v)
    rng = np.random.default_rng(0)
    # entries of the vertices of the worst tets (where the gradient is large)
    # and random ones
    worst = np.unique(t[np.argsort(quality(v, t))[:4]])
    entries = np.unique(np.r_[(3 * worst[:, None] + np.arange(3)).ravel(),
                              rng.choice(v.size, 24, replace=False)])
    ref = fd_grad(v, t, entries, beta, DEFAULT_WEIGHT)
    assert np.linalg.norm(ref) > 1e-3
    assert rel_l2(g.ravel()[entries], ref) < 1e-3
    _, g64 = ad_value_grad(reg, v, mi.Float64)
    assert rel_l2(g64.ravel()[entries], ref) < 1e-6


@pytest.mark.parametrize("height", [1e-3, 1e-5])
def test_gradient_nearly_flat_tet(height):
    v, t = flat_mesh(height)
    v = f32(v)
    assert 0 < quality(v, t)[1] < 1e-2
    reg = QualityRegularizer(t)
    _, g = ad_value_grad(reg, v)
    entries = np.arange(v.size)
    ref = fd_grad(v, t, entries, DEFAULT_BETA, DEFAULT_WEIGHT)
    assert rel_l2(g.ravel(), ref) < 1e-3


def test_zero_volume_tets_finite():
    v, t = flat_mesh(0.0)
    assert quality(v, t)[1] == 0.0
    for Float in (mi.Float, mi.Float64):
        val, g = ad_value_grad(QualityRegularizer(t), v, Float)
        assert np.isfinite(val) and np.all(np.isfinite(g))
    # the gradient at Q = 0 exactly is right too (Softplus is smooth there)
    ref = fd_grad(v, t, np.arange(v.size), DEFAULT_BETA, DEFAULT_WEIGHT)
    _, g64 = ad_value_grad(QualityRegularizer(t), v, mi.Float64)
    assert rel_l2(g64.ravel(), ref) < 1e-6
    # four coincident vertices: Q := 0, zero gradient, no NaN
    vc = np.vstack([v, np.full((4, 3), 0.25)])
    tc = np.vstack([t, [6, 7, 8, 9]])
    val, g = ad_value_grad(QualityRegularizer(tc), vc)
    assert np.isfinite(val) and np.all(np.isfinite(g)) and np.all(g[6:] == 0)
    assert np.isclose(val, quality_penalty_np(vc, tc), rtol=1e-5)


def test_minimizing_improves_worst_quality():
    """Gradient descent on the regularizer alone unfolds an inverted tet and
    raises the worst quality of a strongly jittered grid."""
    v, t = grid_mesh(3, jitter=0.45, seed=0)
    q0 = quality(v, t)
    assert q0.min() < 0
    reg = QualityRegularizer(t, beta=10.0, weight=1.0)
    P = mi.Float(v.ravel())
    losses = []
    for _ in range(30):
        dr.enable_grad(P)
        loss = reg(P)
        dr.backward(loss)
        g = dr.grad(P)
        losses.append(float(loss[0]))
        P = dr.detach(P) - 2e-3 * g
    q1 = quality(np.array(P, np.float64).reshape(-1, 3), t)
    assert np.all(np.diff(losses) < 0)
    assert losses[-1] < 0.5 * losses[0]
    assert q1.min() > 0.1                      # from -0.037
    assert np.percentile(q1, 5) > np.percentile(q0, 5)


@pytest.mark.parametrize("mode", [dr.ReduceMode.Local, dr.ReduceMode.Direct,
                                  dr.ReduceMode.Expand])
def test_reduce_modes_agree(mode):
    v, t = grid_mesh(2, jitter=0.45, seed=0)
    v = f32(v)
    _, g_auto = ad_value_grad(QualityRegularizer(t, beta=10.0), v)
    _, g = ad_value_grad(QualityRegularizer(t, beta=10.0, reduce_mode=mode), v)
    assert np.allclose(g, g_auto, rtol=1e-5, atol=1e-7)


def test_scene_parameter_workflow():
    """The documented use: the shape's oriented tets, the traversed position
    buffer, loss = image term + regularizer, dr.backward."""
    import mi_tetvr
    v, t = grid_mesh(2, jitter=0.45, seed=0)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "volume": mi_tetvr.tetmesh_dict(v, t)})
    params = mi.traverse(scene)
    tets = scene.shapes()[0].oriented_tets()
    reg = QualityRegularizer(tets, beta=10.0, weight=1.0)
    pos = params["volume.vertex_positions"]
    dr.enable_grad(pos)
    loss = dr.mean(dr.square(pos)) + reg(pos)
    dr.backward(loss)
    g = np.array(dr.grad(pos), np.float64)
    g_img = 2 * np.array(pos, np.float64) / dr.width(pos)
    ref = fd_grad(np.array(pos, np.float64).reshape(-1, 3), tets, np.arange(g.size), 10.0, 1.0)
    assert rel_l2(g - g_img, ref) < 1e-3


def test_input_checks():
    with pytest.raises(ValueError):
        QualityRegularizer(np.zeros((3, 3), int))
    with pytest.raises(ValueError):
        QualityRegularizer([[0, 1, 2, 3]], reduce="max")
    reg = QualityRegularizer([[0, 1, 2, 3]])
    with pytest.raises(ValueError):
        reg(mi.Float(np.zeros(9)))        # 3 vertices, tet needs 4
    with pytest.raises(TypeError):
        reg(mi.Vector3f(0, 0, 0))
