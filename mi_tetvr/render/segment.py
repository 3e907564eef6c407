"""Segment integrals of the emission-absorption model (pure Dr.Jit).

The segment integral (DiffTetVR Eq. 1)
--------------------------------------
Inside a tet, color ``c`` and extinction ``s`` are linear along the ray. Over
a segment of length ``L`` with optical depth ``tau(t)``, since
``s e^{-tau} = -d/dt e^{-tau}``, integration by parts reduces the emission
to one scalar integral, exactly::

    C = int_0^L c(t) s(t) e^{-tau(t)} dt = c0 (1 - M) + c1 (M - T)

with ``T = exp(-tau(L)) = exp(-L (s0 + s1) / 2)`` and ``M`` the mean
transmittance over the segment, ``M = (1/L) int_0^L e^{-tau(t)} dt`` (a
Gaussian integral: T <= M <= 1). Only ``M`` is approximated; the colors enter
exactly and ``T`` is exact.

``M`` is computed as DiffTetVR's Alg. 1 does it in effect: ``n`` sub-intervals
of constant extinction (its value at their midpoints, so the transmittance
stays exact), on which the integral is closed-form, ``g(x) = (1 - e^{-x}) /
x`` for a sub-interval of optical depth ``x`` (the printed Alg. 3 is exact
only for ``t = 1``). Its error falls as ``1/n^2``; for even ``n`` the same
exponentials give the estimate with ``n / 2`` sub-intervals too, and
Richardson's extrapolation ``(4 M_n - M_{n/2}) / 3`` leaves an error of order
``1/n^4`` (``tests/render/test_segment.py`` checks it against a float64
quadrature). On a unit segment whose extinction changes by at most 3, ``n``
= 4 errs by at most 3e-4 in the emission, where 8 sub-intervals without the
extrapolation (the scheme before) err by up to 2e-3, with half the
exponentials. Over 2M random segments (depths from 1e-8 to 1e5) both
``1 - M`` and ``M - T`` came out >= 0 and summed to ``1 - T`` within 5e-7, so
no clamp is needed (it would bend the derivative at zero opacity).

``1 - M`` and ``M - T`` are both of the order of the optical depth; they are
accumulated as sums of non-negative terms (prefix and suffix products of the
sub-intervals' transmittances, Taylor series of ``g`` and ``h = e^{-x} - g``
below ``x`` = 0.1) so that neither cancels as ``tau -> 0``. The derivatives
that the adjoint takes by Dr.Jit's AD stay finite there: at zero opacity
``dC/dtau = (c0 + c1) / 2``.
"""
from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.pytree import tree_dot, tree_lerp, tree_map

#: Below this optical depth a sub-interval's integral uses Taylor series (to
#: x^4; truncation < 2e-6 relative). Above it the closed form loses at most
#: ~eps / x^2 to cancellation.
_SMALL_X = 0.1


def _interval(x: mi.Float, A: mi.Float) -> tuple[mi.Bool, mi.Float, mi.Float]:
    """``(small, g, h)`` of a sub-interval of optical depth ``x >= 0`` and
    transmittance ``A = exp(-x)``: its mean transmittance ``g = (1 - A) / x``
    and ``h = A - g`` (Taylor series where ``small``, below :data:`_SMALL_X`)."""
    small = x < _SMALL_X
    x2 = x * x
    g_series = 1.0 - x * 0.5 + x2 * (1.0 / 6.0) - x2 * x * (1.0 / 24.0) + x2 * x2 * (1.0 / 120.0)
    h_series = -x * 0.5 + x2 * (1.0 / 3.0) - x2 * x * 0.125 + x2 * x2 * (1.0 / 30.0)
    g = dr.select(small, g_series, (1.0 - A) / dr.select(small, 1.0, x))
    return small, g, dr.select(small, h_series, A - g)


def interval_terms(x: mi.Float, A: mi.Float) -> tuple[mi.Float, mi.Float]:
    """``(1 - A, h)`` of a sub-interval of optical depth ``x >= 0`` and
    transmittance ``A = exp(-x)``: ``h = A - g`` with ``g = (1 - A) / x`` its
    mean transmittance, both without cancellation (``h <= 0``)."""
    _, g, h = _interval(x, A)
    return x * g, h


def _mean_derivatives(x: list, A: list) -> list:
    """``dM/dx_k`` of the mean transmittance ``M = mean_i T_i g_i`` of ``n``
    sub-intervals of optical depths ``x`` (``T_i = A_0 ... A_{i-1}`` in front
    of sub-interval ``i``): ``(T_k g'(x_k) - sum_{i>k} T_i g_i) / n``, with
    ``g' = h / x`` (its Taylor series, ``-1/2 + x/3 - ...``, where ``x`` is
    small). Both terms are negative: nothing cancels."""
    n = len(x)
    T = [1.0]
    for Ai in A[:-1]:
        T.append(T[-1] * Ai)
    out = [None] * n
    U = 0.0                                  # sum_{i>k} T_i g_i
    for k in reversed(range(n)):
        small, g, h = _interval(x[k], A[k])
        xk = x[k]
        x2 = xk * xk
        dg_series = -0.5 + xk * (1.0 / 3.0) - x2 * 0.125 + x2 * xk * (1.0 / 30.0) \
            - x2 * x2 * (1.0 / 144.0)
        dg = dr.select(small, dg_series, h / dr.select(small, 1.0, xk))
        out[k] = (T[k] * dg - U) * (1.0 / n)
        U = U + T[k] * g
    return out


def _moments(x, A):
    """``(1 - M_n, M_n - T)`` of ``n`` equal sub-intervals of optical depths
    ``x`` and transmittances ``A`` (lists), as sums of non-negative terms:
    with ``T_i`` the transmittance in front of sub-interval ``i``,
    ``1 - M = mean_i [(1 - T_i) + T_i (1 - g_i)]`` and
    ``M - T = mean_i [T_{i+1} (1 - A_{i+1} ... A_{n-1}) - T_i h_i]``."""
    n = len(x)
    terms = [interval_terms(xi, Ai) for xi, Ai in zip(x, A)]
    T = [None] * (n + 1)          # T[i]: transmittance in front of sub-interval i
    D = [None] * (n + 1)          # D[i] = 1 - T[i]
    T[0], D[0] = 1.0, 0.0
    for i in range(n):
        T[i + 1] = T[i] * A[i]
        D[i + 1] = D[i] + T[i] * terms[i][0]
    S = 0.0                        # 1 - A_{i+1} ... A_{n-1}
    P = Q = 0.0
    for i in reversed(range(n)):
        one_minus_A, h = terms[i]
        P += D[i] + T[i] * (one_minus_A + h)      # 1 - g = (1 - A) + h
        Q += T[i + 1] * S - T[i] * h
        S = one_minus_A + A[i] * S
    return P * (1.0 / n), Q * (1.0 / n), T[n]


def segment_integral(length: mi.Float, c0: mi.Color3f, c1: mi.Color3f, s0: mi.Float,
                     s1: mi.Float, n_sub: int) -> tuple[mi.Color3f, mi.Float]:
    """Emission-absorption integral over a segment with linear color and
    extinction (see the module docstring).

    Parameters
    ----------
    length : Float
        Segment length (>= 0).
    c0, c1 : Color3f
        Color at entry and exit.
    s0, s1 : Float
        Extinction at entry and exit.
    n_sub : int
        Sub-intervals of the mean transmittance (a Python int: the loop is
        unrolled); even values are extrapolated from ``n_sub`` and
        ``n_sub / 2``.

    Returns
    -------
    (Color3f, Float)
        Emission seen from the entry side and the segment's transmittance.

    Where nothing is differentiated (a primal walk), a segment of zero
    extinction at both ends (empty space: exactly ``C = 0``, ``T = 1``) is a
    branch of the kernel that a packet of such segments takes without an
    exponential. (Differentiated, the scheme has a derivative w.r.t. the
    extinction there, which the adjoint's own branch gives in closed form:
    ``segment_adjoint``.)
    """
    def medium():
        P, Q, T, _ = _emission_weights(length, s0, s1, n_sub)
        return P, Q, T
    if dr.grad_enabled(length, c0, c1, s0, s1):
        P, Q, T = medium()
    else:
        P, Q, T = dr.if_stmt((), (s0 != 0.0) | (s1 != 0.0), medium,
                             lambda: (mi.Float(0.0), mi.Float(0.0), mi.Float(1.0)),
                             label="segment_integral")
    return c0 * P + c1 * Q, T


def _emission_weights(length: mi.Float, s0: mi.Float, s1: mi.Float,
                      n_sub: int) -> tuple[mi.Float, mi.Float, mi.Float, tuple]:
    """``(P, Q, T, (sigma, x, A, pairs))`` of the scheme of
    :func:`segment_integral` (``C = c0 P + c1 Q``): its sub-intervals'
    extinctions at their midpoints, optical depths and transmittances, and
    the pairs' ``(x, A)`` where ``n_sub`` is even (else None)."""
    dt = length * (1.0 / n_sub)
    sigma = [dr.lerp(s0, s1, (i + 0.5) / n_sub) for i in range(n_sub)]
    x = [dt * si for si in sigma]
    A = [dr.exp(-xi) for xi in x]
    P, Q, T = _moments(x, A)
    pairs = None
    if n_sub % 2 == 0:
        # The same segment in n_sub / 2 sub-intervals: midpoint depths add.
        pairs = ([x[i] + x[i + 1] for i in range(0, n_sub, 2)],
                 [A[i] * A[i + 1] for i in range(0, n_sub, 2)])
        Pc, Qc, _ = _moments(*pairs)
        P = (4.0 * P - Pc) * (1.0 / 3.0)
        Q = (4.0 * Q - Qc) * (1.0 / 3.0)
    return P, Q, T, (sigma, x, A, pairs)


def emission_weights_vjp(length: mi.Float, s0: mi.Float, s1: mi.Float,
                         n_sub: int) -> tuple[mi.Float, mi.Float, mi.Float, Any]:
    """The weights of :func:`segment_integral`'s emission, ``C = c0 P + c1
    Q``, its transmittance, and their reverse-mode derivative in closed
    form: ``(P, Q, T, vjp)`` where ``vjp(g_P, g_Q)`` gives the gradients
    ``(g_length, g_s0, g_s1)`` of ``g_P P + g_Q Q``.

    ``P = 1 - M`` and ``Q = M - T`` (``M`` the mean transmittance,
    extrapolated as :func:`segment_integral` does), so the sub-intervals'
    optical depths ``x_k = (length / n) lerp(s0, s1, (k + 1/2) / n)`` take
    ``(g_Q - g_P) dM/dx_k + g_Q T`` (:func:`_mean_derivatives`). The same
    function as Dr.Jit's AD of :func:`segment_integral`, in about half of
    its instructions (1,708 -> 1,295 per step of the adjoint's walk).
    """
    n = n_sub
    dt = length * (1.0 / n)
    m = [(i + 0.5) / n for i in range(n)]
    P, Q, T, (sigma, x, A, pairs) = _emission_weights(length, s0, s1, n)

    def vjp(g_P: mi.Float, g_Q: mi.Float) -> tuple[mi.Float, mi.Float, mi.Float]:
        dM = _mean_derivatives(x, A)
        if pairs is not None:
            dMc = _mean_derivatives(*pairs)
            dM = [(4.0 * dM[k] - dMc[k // 2]) * (1.0 / 3.0) for k in range(n)]
        g_M, g_T = g_Q - g_P, g_Q * T
        g_x = [g_M * d + g_T for d in dM]
        g_L = sum(g * si for g, si in zip(g_x, sigma)) * (1.0 / n)
        g_s1 = sum(g * mk for g, mk in zip(g_x, m))
        g_s0 = sum(g_x) - g_s1
        return g_L, dt * g_s0, dt * g_s1
    return P, Q, T, vjp


def segment_integral_vjp(length: mi.Float, c0: mi.Color3f, c1: mi.Color3f, s0: mi.Float,
                         s1: mi.Float, n_sub: int) -> tuple[mi.Color3f, mi.Float, Any]:
    """:func:`segment_integral` and its reverse-mode derivative in closed
    form: ``(C, T, vjp)`` where ``vjp(g_C)`` gives the gradients ``(g_length,
    g_c0, g_c1, g_s0, g_s1)`` of ``g_C . C`` (the transmittance is
    differentiated through the optical depth, which is linear): ``g_c0 =
    g_C P``, ``g_c1 = g_C Q`` and :func:`emission_weights_vjp` with ``g_P =
    g_C . c0``, ``g_Q = g_C . c1``."""
    P, Q, T, back = emission_weights_vjp(length, s0, s1, n_sub)

    def vjp(g_C: mi.Color3f) -> tuple[mi.Float, mi.Color3f, mi.Color3f, mi.Float, mi.Float]:
        g_L, g_s0, g_s1 = back(dr.dot(g_C, c0), dr.dot(g_C, c1))
        return g_L, g_C * P, g_C * Q, g_s0, g_s1
    return c0 * P + c1 * Q, T, vjp


def zero_opacity_derivatives(n_sub: int) -> tuple[float, float, float, float]:
    """``(dP/ds0, dQ/ds0, dP/ds1, dQ/ds1)`` per unit length of the scheme of
    :func:`segment_integral` (``C = c0 P + c1 Q``) where the extinction is
    zero at both ends: with ``m_k = (k + 1/2) / n``, sub-interval ``k``'s
    depth takes ``dP/dx_k = 1 - m_k`` and ``dQ/dx_k = m_k``, and ``dx_k /
    ds0 = (1 - m_k) / n``, ``dx_k / ds1 = m_k / n``; even counts extrapolated
    as the integral is (which gives the exact 1/3 and 1/6). Constants: the
    adjoint of an empty segment needs no exponential."""
    def raw(n):
        m = [(k + 0.5) / n for k in range(n)]
        return (sum((1 - mk) ** 2 for mk in m) / n, sum(mk * (1 - mk) for mk in m) / n,
                sum((1 - mk) * mk for mk in m) / n, sum(mk * mk for mk in m) / n)
    d = raw(n_sub)
    if n_sub % 2 == 0:
        d = tuple((4.0 * f - c) / 3.0 for f, c in zip(d, raw(n_sub // 2)))
    return d


def clip_segment(t0: mi.Float, x0: Any, t1: mi.Float, x1: Any, t_begin: mi.Float,
                 t_end: mi.Float) -> tuple[mi.Float, Any, Any]:
    """Restrict a segment with linear attributes (``t0 -> t1``, values ``x0 ->
    x1``: any Dr.Jit array or ``DRJIT_STRUCT`` of them) to ``[t_begin,
    t_end]``. Returns ``(length, x_begin, x_end)``; unclipped segments pass
    through bit-exactly, never divides by a zero length."""
    span = t1 - t0
    inv = dr.select(span > 0, dr.rcp(dr.select(span > 0, span, 1.0)), 0.0)
    lo = t0 < t_begin
    hi = t1 > t_end
    f0 = dr.select(lo, dr.clip((t_begin - t0) * inv, 0.0, 1.0), 0.0)
    f1 = dr.select(hi, dr.clip((t_end - t0) * inv, 0.0, 1.0), 1.0)
    f1 = dr.maximum(f1, f0)
    length = dr.select(lo | hi, (f1 - f0) * span, span)
    return length, tree_lerp(x0, x1, f0), tree_lerp(x0, x1, f1)


def clip_segment_vjp(t0: mi.Float, x0: Any, t1: mi.Float, x1: Any, t_begin: mi.Float,
                     t_end: mi.Float) -> tuple[mi.Float, Any, Any, Any]:
    """:func:`clip_segment` and its reverse-mode derivative in closed form:
    ``(length, x_begin, x_end, vjp)`` where ``vjp(g_length, g_begin, g_end)``
    gives the gradients ``(g_t0, g_x0, g_t1, g_x1)``. An unclipped segment
    passes them through (``-g_length, g_begin, g_length, g_end``); a clipped
    one also through the clip's fractions of the segment, constant where
    they are clamped (as Dr.Jit's AD of :func:`clip_segment`, which this
    replaces in the adjoint's loop at a fraction of its instructions)."""
    span = t1 - t0
    pos = span > 0
    inv = dr.select(pos, dr.rcp(dr.select(pos, span, 1.0)), 0.0)
    lo = t0 < t_begin
    hi = t1 > t_end
    r0 = (t_begin - t0) * inv
    r1 = (t_end - t0) * inv
    f0 = dr.select(lo, dr.clip(r0, 0.0, 1.0), 0.0)
    f1_hi = dr.select(hi, dr.clip(r1, 0.0, 1.0), 1.0)
    f1 = dr.maximum(f1_hi, f0)
    clipped = lo | hi
    length = dr.select(clipped, (f1 - f0) * span, span)

    def vjp(g_length: mi.Float, g_begin: Any, g_end: Any) -> tuple[mi.Float, Any, mi.Float, Any]:
        g_x0 = tree_map(lambda b, e: (1.0 - f0) * b + (1.0 - f1) * e, g_begin, g_end)
        g_x1 = tree_map(lambda b, e: f0 * b + f1 * e, g_begin, g_end)
        step = tree_map(lambda a, b: b - a, x0, x1)
        g_f0 = tree_dot(g_begin, step) - dr.select(clipped, g_length * span, 0.0)
        g_f1 = tree_dot(g_end, step) + dr.select(clipped, g_length * span, 0.0)
        g_span = dr.select(clipped, g_length * (f1 - f0), g_length)
        # (max(f1, f0): the larger takes the gradient; clip: none where clamped)
        high = f1_hi >= f0
        g_f0 = g_f0 + dr.select(high, 0.0, g_f1)
        in0 = lo & (r0 > 0.0) & (r0 < 1.0)
        in1 = hi & high & (r1 > 0.0) & (r1 < 1.0)
        g_r0 = dr.select(in0, g_f0, 0.0)
        g_r1 = dr.select(in1, g_f1, 0.0)
        # (a span's end may be infinite where it clips nothing)
        g_inv = dr.select(in0, r0 * g_r0, 0.0) + dr.select(in1, r1 * g_r1, 0.0)
        g_inv = g_inv * span
        g_span = g_span - dr.select(pos, inv * inv * g_inv, 0.0)
        g_t0 = -g_span - inv * (g_r0 + g_r1)
        return g_t0, g_x0, g_span, g_x1
    return length, tree_lerp(x0, x1, f0), tree_lerp(x0, x1, f1), vjp


#: Below this optical depth the moments of a sub-interval use their series.
_SERIES_X = 0.5
#: Terms of the moments' series (truncation below 1e-9 at x = 0.5).
_SERIES_TERMS = 9


def _exp_moments(x, A):
    """``m_j = int_0^1 u^j e^{-x u} du`` for ``j = 0, 1, 2`` (``A = e^{-x}``):
    series below :data:`_SERIES_X`, else the recurrence ``m_j = (j m_{j-1} -
    A) / x``."""
    small = x < _SERIES_X
    xs = dr.select(small, x, 0.0)
    series = [0.0, 0.0, 0.0]
    term = 1.0                          # (-x)^n / n!
    for n in range(_SERIES_TERMS):
        for j in range(3):
            series[j] = series[j] + term * (1.0 / (n + j + 1))
        term = term * (-xs) * (1.0 / (n + 1))
    inv = dr.rcp(dr.select(small, 1.0, x))
    m0 = (1.0 - A) * inv
    m1 = (m0 - A) * inv
    m2 = (2.0 * m1 - A) * inv
    return tuple(dr.select(small, s, m) for s, m in zip(series, (m0, m1, m2)))


def merged_integral(length: mi.Float,
                    media: list[tuple[mi.Color3f, mi.Color3f, mi.Float, mi.Float]],
                    n_sub: int) -> tuple[mi.Color3f, mi.Float]:
    """Emission and transmittance of a piece where several media overlap,
    each with linear color and extinction (``media``: ``(c0, c1, s0, s1)``
    per medium): extinctions add, and so do emissions ``s_k c_k``::

        C = int_0^L sum_k s_k(t) c_k(t) e^{-tau(t)} dt,    tau' = sum_k s_k

    On ``n_sub`` sub-intervals the summed extinction is taken constant (its
    midpoint value, so that the transmittance stays exact) and the quadratic
    emission density is integrated exactly against the exponential
    (:func:`_exp_moments`); as :func:`segment_integral`, even ``n_sub`` are
    extrapolated from ``n_sub`` and ``n_sub / 2`` (error ~ 1/n^4). For one
    medium the integral is :func:`segment_integral`'s (by another scheme).

    Returns ``(C : Color3f, T : Float)``.
    """
    def run(n):
        dt = length * (1.0 / n)
        C, T = 0.0, 1.0
        for i in range(n):
            ua, ub, um = i / n, (i + 1) / n, (i + 0.5) / n
            x = 0.0
            e = [0.0, 0.0, 0.0]
            for c0, c1, s0, s1 in media:
                sa, sb = dr.lerp(s0, s1, ua), dr.lerp(s0, s1, ub)
                ca, cb = dr.lerp(c0, c1, ua), dr.lerp(c0, c1, ub)
                x = x + dt * dr.lerp(s0, s1, um)
                # s(u') c(u') over the sub-interval, u' in [0, 1]: e0 + e1 u' + e2 u'^2
                e[0] = e[0] + sa * ca
                e[1] = e[1] + sa * (cb - ca) + (sb - sa) * ca
                e[2] = e[2] + (sb - sa) * (cb - ca)
            A = dr.exp(-x)
            m = _exp_moments(x, A)
            C = C + T * dt * (e[0] * m[0] + e[1] * m[1] + e[2] * m[2])
            T = T * A
        return C, T
    C, T = run(n_sub)
    if n_sub % 2 == 0:
        C = (4.0 * C - run(n_sub // 2)[0]) * (1.0 / 3.0)
    return C, T
