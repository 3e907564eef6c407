r"""Inversion safeguard for vertex-position steps (numpy, float64).

An optimizer step that moves vertices can invert tets. :func:`safe_step`
shortens it, per vertex (default) or globally, so that no positively
oriented tet loses more than a given fraction of its volume along the
straight path of the step.

Moving every vertex along its step ``d_i`` by a fraction ``s`` makes six
times a tet's signed volume a cubic in ``s`` (:func:`volume_cubic`); the
largest admissible fraction of a tet is the first root in ``(0, 1]`` of
``6 V(s) - r 6 V(0)`` (:func:`first_root_in_unit`), found without
``np.roots``: the stationary points of the cubic (a quadratic, closed form)
split ``[0, 1]`` into at most three monotone pieces, the first piece whose end
changes sign holds the first root, and a vectorized bisection on that bracket
(only for the tets that have one) pins it down.

Vector fields are handled as structures of arrays: ``(3, k)`` arrays, one row
per coordinate, and a tet's four corners as lists of four of them.
"""
from __future__ import annotations

import numpy as np

from mi_tetvr.mesh.topology import signed_volumes, validate_arrays

__all__ = ["volume_cubic", "first_root_in_unit", "safe_fractions", "safe_step"]


def volume_cubic(vertices, tets, step):
    """Coefficients of ``6 V_t(s)`` when every vertex moves to ``x + s d``.

    With ``a, b, c`` the edges ``p1 - p0, p2 - p0, p3 - p0`` and ``da, db, dc``
    their steps, ``6 V(s) = det(a + s da, b + s db, c + s dc)
    = k0 + k1 s + k2 s^2 + k3 s^3`` with

    * ``k0 = det(a, b, c)``
    * ``k1 = det(da, b, c) + det(a, db, c) + det(a, b, dc)``
    * ``k2 = det(a, db, dc) + det(da, b, dc) + det(da, db, c)``
    * ``k3 = det(da, db, dc)``.

    Parameters
    ----------
    vertices, step : (n, 3) float
    tets : (m, 4) int

    Returns
    -------
    (m, 4) float64: ``k0, k1, k2, k3``.
    """
    xs = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64).T)
    ds = np.ascontiguousarray(np.asarray(step, dtype=np.float64).T)
    tt = np.ascontiguousarray(np.asarray(tets).T)
    return _cubic_soa([xs[:, i] for i in tt], [ds[:, i] for i in tt])


# Structure-of-arrays helpers: a vector field is a (3, k) array.

def _cross3(u, v):
    out = np.empty_like(u)
    np.subtract(u[1] * v[2], u[2] * v[1], out=out[0])
    np.subtract(u[2] * v[0], u[0] * v[2], out=out[1])
    np.subtract(u[0] * v[1], u[1] * v[0], out=out[2])
    return out


def _dot3(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _cubic_soa(corners, steps):
    """:func:`volume_cubic` from the corner positions and the corner steps
    (lists of four (3, k) arrays)."""
    p, d = corners, steps
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    da, db, dc = d[1] - d[0], d[2] - d[0], d[3] - d[0]
    bc, dbdc = _cross3(b, c), _cross3(db, dc)
    mixed = _cross3(db, c)
    mixed += _cross3(b, dc)                       # db x c + b x dc
    out = np.empty((a.shape[1], 4))
    out[:, 0] = _dot3(a, bc)
    out[:, 1] = _dot3(da, bc) + _dot3(a, mixed)
    out[:, 2] = _dot3(a, dbdc) + _dot3(da, mixed)
    out[:, 3] = _dot3(da, dbdc)
    return out


def _volume_soa(corners):
    """Signed volumes from the corner positions (list of four (3, k) arrays)."""
    p = corners
    a, b, c = p[1] - p[0], p[2] - p[0], p[3] - p[0]
    return _dot3(a, _cross3(b, c)) / 6.0


def _horner(k, s):
    return ((k[..., 3] * s + k[..., 2]) * s + k[..., 1]) * s + k[..., 0]


def _stationary_points(k):
    """Roots of ``k1 + 2 k2 s + 3 k3 s^2`` inside (0, 1), sorted, 1 where absent: (m, 2)."""
    A, B, C = 3.0 * k[:, 3], 2.0 * k[:, 2], k[:, 1]
    out = np.ones((len(k), 2))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        disc = B * B - 4.0 * A * C
        sq = np.sqrt(np.maximum(disc, 0.0))
        qq = -0.5 * (B + np.where(B >= 0, sq, -sq))          # no cancellation
        r1 = np.where(A != 0, qq / A, np.nan)
        r2 = np.where(qq != 0, C / qq, np.nan)
        lin = (A == 0) & (B != 0)                              # derivative is linear
        r1 = np.where(lin, -C / np.where(B != 0, B, 1.0), r1)
        r2 = np.where(lin, np.nan, r2)
        has = (disc >= 0) | lin
    for j, r in enumerate((r1, r2)):
        ok = has & np.isfinite(r) & (r > 0) & (r < 1)
        out[ok, j] = r[ok]
    return np.sort(out, axis=1)


def _first_bracket(k):
    """First sign change of the cubic in (0, 1] relative to its sign at 0.

    Returns lo, hi (m,) with ``sign f(lo) == sign f(0)`` and ``f(hi)`` of the
    other sign or zero, and found (m,) bool; f is monotone on [lo, hi]."""
    m = len(k)
    st = _stationary_points(k)
    b = np.empty((m, 4))
    b[:, 0], b[:, 1:3], b[:, 3] = 0.0, st, 1.0
    f = _horner(k[:, None, :], b)                     # (m, 4)
    sgn0 = np.sign(f[:, 0])
    for j in (1, 2, 3):                      # f(0) = 0: the sign just after 0
        sgn0 = np.where(sgn0 == 0, np.sign(k[:, j]), sgn0)
    crossed = (f[:, 1:] * sgn0[:, None] <= 0) & (sgn0[:, None] != 0)   # (m, 3)
    found = crossed.any(axis=1)
    j = np.argmax(crossed, axis=1) + 1
    rows = np.arange(m)
    return b[rows, j - 1], b[rows, j], found, sgn0


def _bisect(k, lo, hi, sgn0, tol=0.0, max_iter=64):
    """Vectorized bisection on brackets with sign(f(lo)) == sgn0 != sign(f(hi))."""
    for _ in range(max_iter):
        mid = 0.5 * (lo + hi)
        same = _horner(k, mid) * sgn0 > 0
        lo = np.where(same, mid, lo)
        hi = np.where(same, hi, mid)
        if np.all(hi - lo <= np.maximum(tol, 4.0 * np.finfo(float).eps * hi)):
            break
    return lo, hi


def first_root_in_unit(coeffs, return_bracket=False):
    """Smallest root in (0, 1] of each cubic ``k0 + k1 s + k2 s^2 + k3 s^3``.

    Vectorized and robust to degenerate cubics (``k3 = 0``, ``k2 = k3 = 0``,
    double roots): the stationary points (closed-form quadratic, computed
    without cancellation) split [0, 1] into monotone pieces, the first piece
    whose end has left the sign of ``f(0)`` brackets the first root, and a
    vectorized bisection narrows that bracket to a few ulps. A root exactly at
    0 does not count (when ``k0 = 0`` the sign just after 0 is used).

    Parameters
    ----------
    coeffs : (m, 4) float
        ``k0, k1, k2, k3`` (ascending powers).
    return_bracket : bool
        Also return ``lo`` (last point before the root, same sign as ``f(0)``;
        1 where there is no root).

    Returns
    -------
    root : (m,) float64, ``inf`` where there is no root in (0, 1]
    lo : (m,) float64, only with ``return_bracket``
    """
    k = np.atleast_2d(np.asarray(coeffs, dtype=np.float64))
    root = np.full(len(k), np.inf)
    lo_all = np.ones(len(k))
    lo, hi, found, sgn0 = _first_bracket(k)
    i = np.flatnonzero(found)
    if len(i):
        ks, s0 = k[i], sgn0[i]
        l, h = lo[i], hi[i]
        l2, h2 = _bisect(ks, l, h, s0)
        # f(l2) keeps the sign of f(0) strictly; h2 is the root when f(h2) == 0
        root[i] = np.where(_horner(ks, h2) == 0, h2, 0.5 * (l2 + h2))
        lo_all[i] = l2
    return (root, lo_all) if return_bracket else root


def safe_fractions(vertices, tets, step, min_volume_ratio=0.1):
    """Largest fraction ``s_t`` in (0, 1] of ``step`` per tet such that its
    signed volume stays above ``min_volume_ratio`` times its current volume
    along the whole straight path ``x + s' step``, ``0 <= s' <= s_t``.

    Tets whose current volume is not positive are not constrained (``s_t = 1``):
    no shortening of a step can protect the sign of a flat or inverted tet.

    Parameters
    ----------
    vertices, step : (n, 3) float
    tets : (m, 4) int
    min_volume_ratio : float in [0, 1)

    Returns
    -------
    (m,) float64; 1 where the full step is safe. Where it is not, ``s_t`` is
    the last bisection point *before* the first root of
    ``6 V(s) - r 6 V(0)``, so ``V(s_t) > r V(0)`` in float64 arithmetic.
    """
    return _fractions_from_cubic(volume_cubic(vertices, tets, step),
                                 _check_ratio(min_volume_ratio))


def _check_ratio(r):
    r = float(r)
    if not 0.0 <= r < 1.0:
        raise ValueError(f"min_volume_ratio must be in [0, 1), got {r}")
    return r


def _fractions_from_cubic(k, r):
    s = np.ones(len(k))
    active = k[:, 0] > 0
    # |k1| + |k2| + |k3| < (1 - r) k0 means f(s) > 0 on [0, 1]: skip those
    maybe = active & (np.abs(k[:, 1]) + np.abs(k[:, 2]) + np.abs(k[:, 3])
                      >= (1.0 - r) * k[:, 0])
    idx = np.flatnonzero(maybe)
    if len(idx):
        kk = k[idx]
        kk[:, 0] *= 1.0 - r
        root, lo = first_root_in_unit(kk, return_bracket=True)
        hit = np.isfinite(root)
        s[idx[hit]] = lo[hit]
    return s


def _vertex_fractions(xs, ds, tets, r, constrained, floor, max_iter):
    """(n,) per-vertex step fractions that keep every constrained tet above ``floor``:
    each offending tet's largest safe fraction given to its vertices, the tets around
    shortened vertices examined again, until none offends."""
    n, m = xs.shape[1], len(tets)
    tt = np.ascontiguousarray(tets.T)              # (4, m)
    factors = np.ones(n)
    sub = np.arange(m)                              # tets to (re)examine
    it = 0
    while len(sub):
        idx = tt[:, sub]
        corners = [xs[:, i] for i in idx]
        steps = [ds[:, i] * factors[i] for i in idx]
        s_t = _fractions_from_cubic(_cubic_soa(corners, steps), r)
        # the moved positions themselves (rounding of the cubic)
        vt = _volume_soa([p + q for p, q in zip(corners, steps)])
        fail = constrained[sub] & ~((vt > floor[sub]) & (vt > 0))
        s_t = np.where(fail & (s_t >= 1.0), 0.5, s_t)
        off = s_t < 1.0
        if not off.any():
            break
        g = np.ones(n)
        np.minimum.at(g, idx[:, off].ravel(), np.tile(s_t[off], 4))
        if it >= max_iter:
            # freeze the vertices of offending tets: each round stops at
            # least one more moving vertex, and a tet whose vertices are
            # all frozen keeps its volume, so this terminates
            g[idx[:, off].ravel()] = 0.0
        factors *= g
        sub = np.flatnonzero((g < 1.0)[tets].any(axis=1))
        it += 1
    return factors


def safe_step(vertices, tets, step, min_volume_ratio=0.1, per_vertex=True, max_iter=30,
              return_factors=False):
    """Shorten an optimizer step so that no tet inverts.

    Guarantee: with ``x' = vertices + returned_step`` (float64), every tet
    that is positively oriented in ``vertices`` has ``signed_volume(x') > 0``
    and ``signed_volume(x') > 0.999 * min_volume_ratio * signed_volume(x)``;
    up to rounding of the cubic the volume stays above ``min_volume_ratio``
    times its start value all along the straight path from ``x`` to ``x'``.
    Tets that are flat or inverted on input are not constrained (no shortening
    can protect their sign). Positions rounded to float32 afterwards may move a
    volume by a few float32 ulps; keep ``min_volume_ratio`` > 0 (default 0.1)
    for a margin.

    Strategy:

    * Per tet, :func:`safe_fractions` gives the largest safe fraction ``s_t``
      of the step (first root in (0, 1] of the volume cubic minus the floor).
      Each round also evaluates the volumes of the moved positions of the same
      tets; a tet that fails that check (rounding) but whose cubic says 1 gets
      ``s_t = 0.5``.
    * ``per_vertex=False``: one global fraction ``s = min_t s_t``, applied to
      the whole step, checked again (rounds only multiply ``s`` down).
    * ``per_vertex=True``: a vertex's factor is multiplied by the minimum of
      ``s_t`` over its incident offending tets, so vertices away from trouble
      keep their whole step. The tets of a shortened vertex then move
      non-uniformly, so the fractions are recomputed (cubics of the shortened
      step) only for tets touching a vertex whose factor changed, and again
      until no tet needs shortening (typically a few rounds). After
      ``max_iter`` rounds the vertices of still-offending tets are frozen
      (factor 0); a tet whose vertices are all frozen keeps its volume, so
      this terminates with every tet checked.
    * Last, the volumes of ``x'`` are recomputed with
      :func:`mi_tetvr.mesh.signed_volumes` on the whole mesh; should rounding
      leave a tet failing, its vertices' factors (the global fraction) are
      halved, frozen after ``max_iter`` rounds, until none fails.

    Parameters
    ----------
    vertices : (n, 3) float
        Current positions.
    tets : (m, 4) int
    step : (n, 3) float
        Proposed update (new = vertices + step).
    min_volume_ratio : float in [0, 1)
        A tet's volume may not drop below this fraction of its current volume.
    per_vertex : bool
        Per-vertex factors (default) or one global fraction.
    max_iter : int
    return_factors : bool
        Also return the per-vertex factors (n,).

    Returns
    -------
    step : (n, 3) float64
        The scaled step.
    n_shortened : int
        Number of vertices with a non-zero step whose step was shortened.
    factors : (n,) float64, only with ``return_factors``
    """
    x = np.asarray(vertices, dtype=np.float64)
    d = np.asarray(step, dtype=np.float64)
    _, tets = validate_arrays(None, tets, strict=False)
    if x.shape != d.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"vertices {x.shape} and step {d.shape} must both be (n, 3)")
    if not np.all(np.isfinite(d)):
        raise ValueError("step has non-finite entries")
    r = _check_ratio(min_volume_ratio)
    n = len(x)
    v0 = signed_volumes(x, tets)
    constrained = v0 > 0
    # acceptance test on the final positions; 0.999 r absorbs the rounding
    # difference between the cubic and the volume of the moved positions
    floor = np.where(constrained, 0.999 * r * v0, np.inf)
    xs, ds = np.ascontiguousarray(x.T), np.ascontiguousarray(d.T)
    tt = np.ascontiguousarray(tets.T)              # (4, m)
    if not per_vertex:
        # one cubic per tet; a scaled step s d has coefficients k_j s^j
        k = _cubic_soa([xs[:, i] for i in tt], [ds[:, i] for i in tt])
        factors = np.full(n, float(_fractions_from_cubic(k, r).min()))
    else:
        factors = _vertex_fractions(xs, ds, tets, r, constrained, floor, max_iter)
    # final check with the public volume function on the whole mesh
    # (halving, then freezing: terminates for the reason given in _vertex_fractions)
    it = 0
    while True:
        bad = constrained & ~(signed_volumes(x + factors[:, None] * d, tets) > floor)
        if not bad.any():
            break
        scale = 0.0 if it >= max_iter else 0.5
        if per_vertex:
            factors[np.unique(tets[bad])] *= scale
        else:
            factors *= scale
        it += 1

    moving = np.any(d != 0, axis=1)
    n_short = int(np.count_nonzero(moving & (factors < 1.0)))
    out = factors[:, None] * d
    return (out, n_short, factors) if return_factors else (out, n_short)
