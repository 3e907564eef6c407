"""The segment integral and its pieces (the ones the adjoint differentiates),
against float64 formulas, an adaptive float64 quadrature and the x -> 0
limit."""
import numpy as np
import pytest
from scipy.integrate import quad

import drjit as dr
import mitsuba as mi
from mi_tetvr.render.segment import (clip_segment, clip_segment_vjp, interval_terms,
                                     segment_integral, segment_integral_vjp,
                                     zero_opacity_derivatives)

X = np.array([0.0, 1e-7, 1e-4, 5e-3, 0.0099, 0.0101, 0.099, 0.101, 0.3, 2.0, 30.0, 1e4])


def analytic(x):
    """1 - A, h = A - (1 - A) / x and their x-derivatives in float64 (series
    below 1e-3, where the closed form cancels)."""
    x = np.asarray(x, np.float64)
    A = np.exp(-x)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(x < 1e-3, 1 - x / 2 + x**2 / 6 - x**3 / 24, -np.expm1(-x) / x)
        h = A - g
        h_over_x = np.where(x < 1e-3, -0.5 + x / 3 - x**2 / 8, h / x)
    # dg/dx = h / x, dh/dx = -A - h / x
    return -np.expm1(-x), h, A, -A - h_over_x


def test_interval_terms_value_and_derivatives():
    x = mi.Float(X)
    dr.enable_grad(x)
    A = dr.exp(-x)
    one_minus_A, h = interval_terms(x, A)
    ref_1mA, ref_h, ref_d1mA, ref_dh = analytic(X)
    np.testing.assert_allclose(np.array(one_minus_A), ref_1mA, rtol=2e-6, atol=1e-30)
    np.testing.assert_allclose(np.array(h), ref_h, rtol=2e-6, atol=1e-7)
    assert np.all(np.array(h) <= 0)
    dr.backward_from(h)
    np.testing.assert_allclose(np.array(dr.grad(x)), ref_dh, rtol=1e-5, atol=1e-7)
    # The zero-opacity limit: dh/dx = -1/2.
    np.testing.assert_allclose(ref_dh[0], -0.5, rtol=1e-12)


#: (s0, s1) over a unit length: thin, moderate, steep and opaque segments.
EXTINCTIONS = [(0, 0.1), (0, 1), (1, 0), (0, 3), (3, 0), (0.5, 2), (0, 10), (2, 20),
               (1e-6, 2e-6), (50, 60)]


def exact_segment(s0, s1, c0, c1):
    """float64 emission of a unit segment by adaptive quadrature."""
    def f(t, k):
        return ((1 - t) * c0[k] + t * c1[k]) * (s0 + (s1 - s0) * t) * np.exp(
            -(s0 * t + (s1 - s0) * t * t / 2))
    return np.array([quad(f, 0, 1, args=(k,), epsabs=1e-15, epsrel=1e-13, limit=200)[0]
                     for k in range(3)])


def segment_errors(n_sub):
    c0, c1 = [0.2, 0.5, 0.9], [0.9, 0.1, 0.4]
    s0 = mi.Float([e[0] for e in EXTINCTIONS])
    s1 = mi.Float([e[1] for e in EXTINCTIONS])
    C, T = segment_integral(dr.ones(mi.Float, len(EXTINCTIONS)), mi.Color3f(c0),
                            mi.Color3f(c1), s0, s1, n_sub)
    ref = np.stack([exact_segment(a, b, c0, c1) for a, b in EXTINCTIONS])
    np.testing.assert_allclose(np.array(T), np.exp(-(np.array(s0) + np.array(s1)) / 2),
                               rtol=1e-5, atol=1e-30)
    return np.abs(np.array(C).T - ref).max(1)


def test_segment_integral_converges():
    """Against a float64 quadrature: the transmittance is exact, one
    sub-interval errs by up to ~0.1 on steep segments, the extrapolated even
    counts converge at fourth order (about 16x per doubling where the
    sub-intervals resolve the extinction), and 4 sub-intervals err by less
    than 3e-4 wherever the extinction changes by at most 3 across the
    segment (8 sub-intervals without extrapolation err by up to 2e-3
    there)."""
    e1, e2, e4, e8 = (segment_errors(n) for n in (1, 2, 4, 8))
    assert e1.max() > 0.05
    assert np.all(e4 <= e2 + 1e-7) and np.all(e8 <= e4 + 1e-7)
    moderate = np.array([abs(b - a) <= 3 for a, b in EXTINCTIONS])
    assert e4[moderate].max() < 3e-4
    resolved = np.array([max(a, b) <= 3 and b != a for a, b in EXTINCTIONS]) & (e4 > 1e-6)
    assert np.all(e4[resolved] / e8[resolved] > 8)
    assert e8.max() < 3e-4


@pytest.mark.parametrize("n_sub", [1, 8])
def test_segment_integral_gradients_are_finite_at_zero(n_sub):
    """Zero length and zero opacity: finite derivatives with the right limit.
    The end colors stay fixed as the length shrinks, so at zero length
    dC/dlength = s (c0 + c1) / 2 and dT/dlength = -s."""
    length = mi.Float([0.0, 0.0, 1.0])
    s0, s1 = mi.Float([0.0, 2.0, 0.0]), mi.Float([0.0, 2.0, 0.0])
    c0, c1 = mi.Color3f(0.2, 0.4, 0.6), mi.Color3f(0.8, 0.6, 0.4)
    dr.enable_grad(length, s0, s1, c0, c1)
    C, T = segment_integral(length, c0, c1, s0, s1, n_sub)
    dr.backward_from(dr.sum(C) + T)
    for v in (length, s0, s1, c0, c1):
        assert np.all(np.isfinite(np.array(dr.grad(v))))
    # Row 1: zero length, s = 2; the objective sums the three channels.
    np.testing.assert_allclose(np.array(dr.grad(length))[1], 2.0 * (1.2 + 1.8) / 2 - 2.0,
                               rtol=1e-6)
    # Row 2: zero opacity over a unit length: dC/ds0 = dC/ds1 = mean color / 2.
    np.testing.assert_allclose(np.array(dr.grad(s0))[2] + np.array(dr.grad(s1))[2],
                               (1.2 + 1.8) / 2 - 1.0, rtol=1e-5)


@pytest.mark.parametrize("n_sub", [2, 4, 8])
def test_segment_integral_steep_opaque_segments(n_sub):
    """Extinction falling or rising by 1e4 across a segment (a sub-interval's
    transmittance below float's range next to one near 1): finite emission,
    its value against the float64 quadrature, the transmittance exact, and
    finite derivatives."""
    pairs = [(1e4, 0.0), (0.0, 1e4), (400.0, 1.0), (1.0, 400.0)]
    c0, c1 = [0.2, 0.5, 0.9], [0.9, 0.1, 0.4]
    s0, s1 = mi.Float([p[0] for p in pairs]), mi.Float([p[1] for p in pairs])
    length = dr.ones(mi.Float, len(pairs))
    dr.enable_grad(s0, s1, length)
    C, T = segment_integral(length, mi.Color3f(c0), mi.Color3f(c1), s0, s1, n_sub)
    C_np = np.array(C).T
    assert np.all(np.isfinite(C_np)) and np.all(np.isfinite(np.array(T)))
    ref = np.stack([exact_segment(a, b, c0, c1) for a, b in pairs])
    # Each is opaque: the emission is the entry color, resolved by the sub-intervals
    # to within the coarse scheme's error on a step of 1e4 / n_sub.
    np.testing.assert_allclose(C_np, ref, atol=0.2)
    np.testing.assert_allclose(np.array(T), np.exp(-(np.array(s0) + np.array(s1)) / 2),
                               atol=1e-30)
    dr.backward_from(dr.sum(C) + T)
    for x in (s0, s1, length):
        assert np.all(np.isfinite(np.array(dr.grad(x))))


@pytest.mark.parametrize("n_sub", [2, 4])
def test_segment_integral_derivatives_at_constant_extinction(n_sub):
    """Where the extinction is the same at both ends (a constant texel of a
    transfer function, equal vertex opacities) the derivatives w.r.t. each
    end's extinction are those of central differences (each end's share of
    the segment, not their sum split by a kink)."""
    s = [0.3, 1.7, 6.0]
    c0, c1 = [0.2, 0.5, 0.9], [0.9, 0.1, 0.4]

    def emission(a, b):
        C, _ = segment_integral(mi.Float(1.3), mi.Color3f(c0), mi.Color3f(c1), mi.Float(a),
                                mi.Float(b), n_sub)
        return np.array(C, np.float64).ravel()
    for v in s:
        s0, s1 = mi.Float(v), mi.Float(v)
        dr.enable_grad(s0, s1)
        C, _ = segment_integral(mi.Float(1.3), mi.Color3f(c0), mi.Color3f(c1), s0, s1, n_sub)
        dr.backward_from(C.x)
        h = 1e-3
        for grad, shift in ((dr.grad(s0), (h, 0.0)), (dr.grad(s1), (0.0, h))):
            fd = (emission(v + shift[0], v + shift[1])[0]
                  - emission(v - shift[0], v - shift[1])[0]) / (2 * h)
            # (float32 differences: about 1e-5 of rounding)
            assert abs(float(grad[0]) - fd) < 0.01 * abs(fd) + 3e-5, (v, grad, fd)


def _one_minus_g(x):
    """``1 - (1 - e^-x) / x`` in float64 without cancellation (series below 0.1)."""
    if x < 0.1:
        return x / 2 - x**2 / 6 + x**3 / 24 - x**4 / 120 + x**5 / 720 - x**6 / 5040
    return 1 + np.expm1(-x) / x


def _g_minus_A(x):
    """``(1 - e^-x) / x - e^-x`` in float64 without cancellation."""
    if x < 0.1:
        return x / 2 - x**2 / 3 + x**3 / 8 - x**4 / 30 + x**5 / 144 - x**6 / 840
    return -np.expm1(-x) / x - np.exp(-x)


def _pq(x):
    """``(1 - M, M - T)`` of sub-intervals of depths ``x`` (float64, sums of
    non-negative terms: ``T_i (g_i - A_i) + T_{i+1} (1 - e^{-(X_n - X_{i+1})})``)."""
    X = np.concatenate([[0.0], np.cumsum(x)])
    P = sum(-np.expm1(-X[i]) + np.exp(-X[i]) * _one_minus_g(xi) for i, xi in enumerate(x))
    Q = sum(np.exp(-X[i]) * _g_minus_A(xi) - np.exp(-X[i + 1]) * np.expm1(-(X[-1] - X[i + 1]))
            for i, xi in enumerate(x))
    return P / len(x), Q / len(x)


def discretized_float64(length, s0, s1, n):
    """``(P, Q)`` of the sub-interval scheme :func:`segment_integral` computes
    (``C = c0 P + c1 Q``), in float64 without cancellation: the mean
    transmittance of ``n`` sub-intervals of constant extinction,
    extrapolated from ``n / 2``."""
    x = [length / n * (s0 + (s1 - s0) * (i + 0.5) / n) for i in range(n)]
    P, Q = _pq(x)
    if n % 2 == 0:
        Pc, Qc = _pq([x[i] + x[i + 1] for i in range(0, n, 2)])
        P, Q = (4 * P - Pc) / 3, (4 * Q - Qc) / 3
    return P, Q


@pytest.mark.parametrize("n_sub", [1, 2, 3, 4, 8])
def test_segment_integral_vjp_against_float64_differences(n_sub):
    """The closed-form derivative of the segment integral against central
    differences of the same scheme in float64 (relative step 1e-6), over
    segments from zero to opaque, zero opacity at one end or both, and
    Dr.Jit's AD of :func:`segment_integral` where it is well conditioned;
    and the primal it returns is :func:`segment_integral`'s, bit for bit."""
    rng = np.random.default_rng(n_sub)
    k = 300
    length = np.concatenate([rng.uniform(0, 2, k // 2), 10 ** rng.uniform(-6, 1.5, k // 2)])
    s0 = np.where(rng.random(k) < 0.15, 0.0, 10 ** rng.uniform(-4, 1.5, k))
    s1 = np.where(rng.random(k) < 0.15, 0.0, 10 ** rng.uniform(-4, 1.5, k))
    c0, c1, gC = rng.random((3, k)), rng.random((3, k)), rng.normal(size=(3, k))
    args = (mi.Float(length), mi.Color3f(c0), mi.Color3f(c1), mi.Float(s0), mi.Float(s1))
    C, T, vjp = segment_integral_vjp(*args, n_sub)
    C_ref, T_ref = segment_integral(*args, n_sub)
    np.testing.assert_array_equal(np.array(C), np.array(C_ref))
    np.testing.assert_array_equal(np.array(T), np.array(T_ref))
    g_L, g_c0, g_c1, g_s0, g_s1 = (np.array(g, np.float64) for g in vjp(mi.Color3f(gC)))
    for i in range(k):
        a, b = gC[:, i] @ c0[:, i], gC[:, i] @ c1[:, i]
        P, Q = discretized_float64(length[i], s0[i], s1[i], n_sub)
        np.testing.assert_allclose(g_c0[:, i], gC[:, i] * P, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(g_c1[:, i], gC[:, i] * Q, rtol=1e-5, atol=1e-7)
        args64 = [length[i], s0[i], s1[i]]
        for j, got in enumerate((g_L[i], g_s0[i], g_s1[i])):
            def f(t):
                u = list(args64)
                u[j] = t
                P_, Q_ = discretized_float64(*u, n_sub)
                return a * P_ + b * Q_
            v, h = args64[j], 1e-4 * max(args64[j], 1e-3)
            # (central differences, one-sided of second order at zero)
            fd = ((f(v + h) - f(v - h)) / (2 * h) if v > h else
                  (-3 * f(v) + 4 * f(v + h) - f(v + 2 * h)) / (2 * h))
            # (float32 rounding of terms of the size of the color's weight times
            # the other argument, which cancel: a few ulps of them)
            terms = (abs(a) + abs(b)) * (s0[i] + s1[i] if j == 0 else length[i])
            assert abs(got - fd) <= 1e-3 * abs(fd) + 4e-6 * terms, (n_sub, i, j, got, fd)


@pytest.mark.parametrize("n_sub", [1, 2, 3, 4, 8])
def test_zero_opacity_derivatives(n_sub):
    """The constants an empty segment's adjoint takes are the closed-form
    derivative's at zero extinction, and for even counts those of the exact
    integral, ``C = length (c0 (s0/3 + s1/6) + c1 (s0/6 + s1/3))`` to first
    order in the extinction."""
    c0, c1 = mi.Color3f(1.0, 0.0, 0.0), mi.Color3f(0.0, 1.0, 0.0)
    _, _, vjp = segment_integral_vjp(mi.Float(2.0), c0, c1, mi.Float(0.0), mi.Float(0.0),
                                     n_sub)
    p0, q0, p1, q1 = zero_opacity_derivatives(n_sub)
    for g_C, (w0, w1) in ((mi.Color3f(1.0, 0.0, 0.0), (p0, p1)),
                          (mi.Color3f(0.0, 1.0, 0.0), (q0, q1))):
        _, _, _, g_s0, g_s1 = vjp(g_C)
        np.testing.assert_allclose([g_s0[0], g_s1[0]], [2.0 * w0, 2.0 * w1], rtol=1e-6)
    if n_sub % 2 == 0:
        np.testing.assert_allclose([p0, q0, p1, q1], [1 / 3, 1 / 6, 1 / 6, 1 / 3], rtol=1e-12)


def test_clip_segment_vjp_against_ad():
    """The clip's closed-form derivative against Dr.Jit's AD of
    :func:`clip_segment`: segments unclipped, clipped at the start, the end,
    both or entirely, of zero length, with an infinite end of the span."""
    from mi_tetvr.render.optical import EmissionAbsorption
    from mi_tetvr.render.pytree import scalar_leaves, tree_dot
    A = EmissionAbsorption.Attributes
    rng = np.random.default_rng(5)
    k = 4000
    t0 = rng.uniform(-1, 1, k)
    t1 = t0 + np.where(rng.random(k) < 0.05, 0.0, rng.uniform(0, 2, k))
    tb = np.where(rng.random(k) < 0.5, -10.0, rng.uniform(-1.5, 1.5, k))
    te = np.where(rng.random(k) < 0.5, np.inf, rng.uniform(-1, 3, k))

    def attributes():
        return A(mi.Color3f(rng.normal(size=(3, k))), mi.Float(rng.normal(size=k)))
    x = [mi.Float(t0), attributes(), mi.Float(t1), attributes()]
    g_len, g_b0, g_b1 = mi.Float(rng.normal(size=k)), attributes(), attributes()
    _, _, _, vjp = clip_segment_vjp(*x, mi.Float(tb), mi.Float(te))
    closed = vjp(g_len, g_b0, g_b1)
    dr.enable_grad(x)
    length, b0, b1 = clip_segment(*x, mi.Float(tb), mi.Float(te))
    dr.backward_from(g_len * length + tree_dot(g_b0, b0) + tree_dot(g_b1, b1))
    for ours, xi in zip(closed, x):
        ad = np.array(scalar_leaves(dr.grad(xi)), np.float64)
        np.testing.assert_allclose(np.array(scalar_leaves(ours), np.float64), ad, rtol=1e-5,
                                   atol=1e-5 * np.abs(ad).max())
    clipped = (t0 < tb) | (t1 > te)
    assert 0.2 < clipped.mean() < 0.8


@pytest.mark.parametrize("n_sub", [1, 4])
def test_segment_integral_skips_empty_segments(n_sub):
    """The branch an empty segment takes where nothing is differentiated:
    exactly no emission and full transmittance, and every other segment
    the scheme's value bit for bit (the closed-form derivative's forward
    pass, which has no branch)."""
    length = mi.Float([1.7, 0.3, 2.0, 0.0, 1.0])
    s0, s1 = mi.Float([0.0, 0.0, 1.5, 0.0, 0.0]), mi.Float([0.0, 2.0, 0.7, 0.0, 1e-30])
    c0, c1 = mi.Color3f(0.2, 0.5, 0.9), mi.Color3f(0.9, 0.1, 0.4)
    C, T = segment_integral(length, c0, c1, s0, s1, n_sub)
    C_ref, T_ref, _ = segment_integral_vjp(length, c0, c1, s0, s1, n_sub)
    np.testing.assert_array_equal(np.array(C), np.array(C_ref))
    np.testing.assert_array_equal(np.array(T), np.array(T_ref))
    assert np.all(np.array(C)[:, [0, 3]] == 0.0) and np.all(np.array(T)[[0, 3]] == 1.0)
