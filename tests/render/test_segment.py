"""The segment integral's closed form and its derivatives (the ones the
adjoint uses), against float64 formulas and the x -> 0 limit."""
import numpy as np
import pytest

import drjit as dr
import mitsuba as mi
from mi_tetvr.render.segment import accumulate, segment_integral

X = np.array([0.0, 1e-7, 1e-4, 5e-3, 0.0099, 0.0101, 0.099, 0.101, 0.3, 2.0, 30.0, 1e4])


def analytic(x, c0, c1):
    """C, dC/dx, dC/dc0, dC/dc1 in float64 (series below 1e-3, where the
    closed form cancels)."""
    x = np.asarray(x, np.float64)[:, None]
    A = np.exp(-x)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(x < 1e-3, 1 - x / 2 + x**2 / 6 - x**3 / 24, -np.expm1(-x) / x)
        h = A - g
        h_over_x = np.where(x < 1e-3, -0.5 + x / 3 - x**2 / 8, h / x)
    C = (x * g) * c0 + h * (c0 - c1)
    dC_dx = A * c0 - (A + h_over_x) * (c0 - c1)
    return C, dC_dx, (1 - A + h) + 0 * c0, -h + 0 * c0


def test_accumulate_value_and_derivatives():
    rng = np.random.default_rng(0)
    c0, c1 = rng.uniform(0, 1, (len(X), 3)), rng.uniform(0, 1, (len(X), 3))
    x = mi.Float(X)
    a, b = mi.Color3f(*c0.T), mi.Color3f(*c1.T)
    dr.enable_grad(x, a, b)
    C, A = accumulate(x, a, b)
    ref_C, ref_dx, ref_d0, ref_d1 = analytic(X, c0, c1)
    np.testing.assert_allclose(np.array(C).T, ref_C, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(np.array(A), np.exp(-X), rtol=2e-6, atol=1e-30)
    for k in range(3):  # one color channel at a time: d C_k / d(x, c0_k, c1_k)
        dr.clear_grad((x, a, b))
        dr.backward_from(accumulate(x, a, b)[0][k])
        np.testing.assert_allclose(np.array(dr.grad(x)), ref_dx[:, k], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(np.array(dr.grad(a))[k], ref_d0[:, k], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(np.array(dr.grad(b))[k], ref_d1[:, k], rtol=1e-5, atol=1e-7)
    # The zero-opacity limit: emission rate (c0 + c1) / 2.
    np.testing.assert_allclose(ref_dx[0], (c0[0] + c1[0]) / 2, rtol=1e-12)


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
