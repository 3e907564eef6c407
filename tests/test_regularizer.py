"""Tet-quality regularizer (DiffTetVR Eq. 16-21) and the inversion safeguard."""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi

from mi_tetvr.mesh.generate import grid_mesh
from mi_tetvr.mesh.topology import quality, signed_volumes
from mi_tetvr.recon.regularizer import (DEFAULT_BETA, DEFAULT_WEIGHT, QualityRegularizer,
                                  first_root_in_unit, quality_penalty_np, safe_fractions,
                                  safe_step, tet_regularizer, volume_cubic)

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
    tets = scene.shapes()[0].topology.tets
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


# --------------------------------------------------------------------------
# cubic root finder
# --------------------------------------------------------------------------


def _roots_ref(k):
    r = np.roots(np.trim_zeros(k[::-1], "f"))
    r = r[np.abs(r.imag) < 1e-9].real
    r = r[(r > 0) & (r <= 1)]
    return r.min() if len(r) else np.inf


def test_first_root_matches_np_roots():
    rng = np.random.default_rng(1)
    k = rng.normal(size=(3000, 4))
    k[:500, 3] = 0.0                       # quadratics
    k[500:600, 2:] = 0.0                   # linear
    k[600:800] *= rng.uniform(1e-6, 1e6, (200, 1))
    got = first_root_in_unit(k)
    ref = np.array([_roots_ref(row) for row in k])
    assert np.array_equal(np.isinf(got), np.isinf(ref))
    fin = np.isfinite(ref)
    assert fin.sum() > 500
    assert np.max(np.abs(got[fin] - ref[fin])) < 1e-9
    # constructed: (s - a)(s - b)(s - c) with known roots, and a double root
    a, b, c = 0.3, 0.7, 1.5
    assert np.isclose(first_root_in_unit([-a * b * c, a * b + a * c + b * c, -(a + b + c), 1])[0],
                      0.3, atol=1e-12)
    # (s - 0.4)^2 (s + 2): touches 0 at 0.4 without crossing
    assert np.isclose(first_root_in_unit(np.polynomial.polynomial.polyfromroots(
        [0.4, 0.4, -2]))[0], 0.4, atol=1e-12)
    assert first_root_in_unit([1.0, 0, 0, 0])[0] == np.inf


def test_volume_cubic():
    v, t = grid_mesh(2, jitter=0.3, seed=0)
    d = np.random.default_rng(0).normal(size=v.shape) * 0.3
    k = volume_cubic(v, t, d)
    for s in (0.0, 0.37, 1.0):
        assert np.allclose(k @ s ** np.arange(4), 6 * signed_volumes(v + s * d, t), atol=1e-12)


# --------------------------------------------------------------------------
# safe_step
# --------------------------------------------------------------------------


@pytest.mark.parametrize("per_vertex", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_safe_step_prevents_inversion(per_vertex, seed):
    v, t = grid_mesh(5, jitter=0.2, seed=seed)
    rng = np.random.default_rng(10 + seed)
    h = 2 / 5
    d = rng.normal(size=v.shape) * h * (0.3 + 0.3 * seed)
    v0 = signed_volumes(v, t)
    assert np.all(v0 > 0)
    assert np.count_nonzero(signed_volumes(v + d, t) <= 0) > 0      # the raw step inverts
    for ratio in (0.1, 0.0):
        out, n_short, f = safe_step(v, t, d, ratio, per_vertex=per_vertex,
                                    return_factors=True)
        assert np.all((f >= 0) & (f <= 1))
        assert np.allclose(out, f[:, None] * d)
        assert n_short > 0
        v1 = signed_volumes(v + out, t)
        assert np.all(v1 > 0)
        assert np.all(v1 > 0.999 * ratio * v0)
        # the whole straight path stays valid too
        for s in np.linspace(0, 1, 9)[1:]:
            assert np.all(signed_volumes(v + s * out, t) > 0.99 * ratio * v0)
        if not per_vertex:
            assert np.all(f == f[0])
        elif seed == 0:  # moderate step: many vertices keep all of theirs
            assert np.count_nonzero(f == 1) > 0.2 * len(v)


def test_safe_step_keeps_small_steps():
    v, t = grid_mesh(4, jitter=0.2, seed=4)
    d = np.random.default_rng(3).normal(size=v.shape) * 0.002
    assert np.all(safe_fractions(v, t, d, 0.1) == 1.0)
    for per_vertex in (True, False):
        out, n_short = safe_step(v, t, d, 0.1, per_vertex=per_vertex)
        assert n_short == 0 and np.array_equal(out, d)


def test_safe_step_shortens_only_near_trouble():
    """One vertex pushed through its neighbourhood: the per-vertex mode shortens
    only vertices of the tets it would invert, the rest keep their step."""
    v, t = grid_mesh(4, jitter=0.2, seed=6)
    rng = np.random.default_rng(6)
    d = rng.normal(size=v.shape) * 0.003
    i = int(np.argmin(np.linalg.norm(v, axis=1)))              # the center vertex
    d[i] = [0.9, 0.0, 0.0]                                     # ~2 cells: inverts tets
    assert np.any(signed_volumes(v + d, t) <= 0)
    out, n_short, f = safe_step(v, t, d, 0.1, return_factors=True)
    assert np.all(signed_volumes(v + out, t) > 0)
    assert 0 < f[i] < 1
    near = np.unique(t[np.any(t == i, axis=1)])
    assert np.all(f[np.setdiff1d(np.arange(len(v)), near)] == 1)
    assert n_short <= len(near)
    # the center vertex still moves part of the way
    assert np.linalg.norm(out[i]) > 0.05


def test_safe_fractions_exact_for_single_tet():
    """A tet squashed by moving its apex straight down through the base: the
    safe fraction is exactly where the height reaches min_volume_ratio."""
    v = regular_tet()
    t = np.array([[0, 1, 2, 3]])
    if signed_volumes(v, t)[0] < 0:
        t = t[:, [0, 1, 3, 2]]
    # move vertex t[0,3] towards and through its opposite face
    a = t[0, 3]
    base = v[t[0, :3]]
    n = np.cross(base[1] - base[0], base[2] - base[0])
    n /= np.linalg.norm(n)
    height = np.dot(v[a] - base[0], n)
    d = np.zeros_like(v)
    d[a] = -2.0 * height * n                                  # lands mirrored: inverted
    s = safe_fractions(v, t, d, 0.25)[0]
    assert np.isclose(s, 0.75 / 2.0, atol=1e-12)             # height 1 - 2 s = 0.25
