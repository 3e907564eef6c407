"""Independent brute-force reference renderer for tetrahedral emission-absorption volumes.

Pure numpy, float64, deliberately simple and slow.  It is used by the test suite to
check the real (Dr.Jit) renderer and shares no code with it.

Model (per ray, direction normalised so that t is a distance):

* every ray is clipped against every tetrahedron.  A tetrahedron is the set where
  its four barycentric coordinates are >= 0; along the ray each coordinate is an
  affine function ``lambda_i(t) = a_i + t * b_i`` so this is exactly Cyrus-Beck
  clipping against the four face half-spaces.  Only ``0 <= t <= t_max`` counts.
* inside tet ``j`` the color and the extinction are the barycentric interpolation
  of the vertex values, hence linear along the segment ``[t0, t1]``.
* segment emission ``C_seg = int_0^L sigma(s) c(s) exp(-tau(s)) ds`` with the optical
  depth ``tau(s)`` (a quadratic) in closed form, integrated with composite
  Gauss-Legendre quadrature (sub-intervals of optical depth <= 0.5 each); the
  part of a segment beyond optical depth ``_TAU_CUT`` is skipped for the emission
  (its weight is below exp(-_TAU_CUT)).  ``T_seg = exp(-tau(L))``.
* segments of a ray are sorted by ``t0`` and reduced to the union of their
  intervals: each start is clipped to the largest end of the preceding segments
  (fully covered segments vanish, partially covered ones keep their uncovered part,
  attributes at the new start interpolated linearly).  So a ray inside a face or
  along an edge shared by several tets is not counted once per tet; the result is
  right because the per-vertex field is continuous across faces.
* the remaining segments are composited front to back:
  ``C += T * C_seg; T *= T_seg``;  ``rgb = C + T * background``, ``alpha = 1 - T``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["reference_render", "reference_render_classified", "reference_render_meshes"]

# Optical depth beyond which the rest of a segment's emission is ignored
# (relative contribution < exp(-80) ~ 2e-35).
_TAU_CUT = 80.0
# Target optical depth of one quadrature sub-interval.
_TAU_SUB = 0.5
# Ray/tet pairs handled at once during clipping (~ 250 MB of temporaries).
_PAIR_BUDGET = 1_000_000
# Quadrature sub-intervals handled at once.
_SUB_BUDGET = 100_000


def _prepare_tets(vertices, tets):
    """Drop degenerate tets; return (tets, v0, G) with G (m,3,3) = inverse edge matrix."""
    m = tets.shape[0]
    if m == 0:
        return tets, np.zeros((0, 3)), np.zeros((0, 3, 3))
    used = vertices[np.unique(tets)]
    scale = float(np.max(used.max(axis=0) - used.min(axis=0)))
    if not np.isfinite(scale) or scale <= 0.0:
        scale = 1.0
    v0 = vertices[tets[:, 0]]
    # E columns: v1-v0, v2-v0, v3-v0
    E = np.stack([vertices[tets[:, i]] - v0 for i in (1, 2, 3)], axis=-1)
    vol = np.linalg.det(E) / 6.0
    keep = np.abs(vol) > 1e-14 * scale**3
    tets, v0, E = tets[keep], v0[keep], E[keep]
    G = np.linalg.inv(E) if len(tets) else np.zeros((0, 3, 3))
    return tets, v0, G


def _clip(o, d, tmax, v0, G):
    """Clip rays (kc) against tets (mc).

    Returns pair indices (ray, tet), t0, t1 and barycentrics at t0, t1 (S,4)."""
    diff = o[:, None, :] - v0[None, :, :]                 # (kc, mc, 3)
    a = np.einsum("kmj,mij->kmi", diff, G)                # lambda_1..3 at t = 0
    b = np.einsum("kj,mij->kmi", d, G)                    # d lambda_1..3 / dt
    del diff
    a = np.concatenate([1.0 - a.sum(-1, keepdims=True), a], axis=-1)  # (kc, mc, 4)
    b = np.concatenate([-b.sum(-1, keepdims=True), b], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -a / b
    lo = np.where(b > 0.0, root, -np.inf).max(-1)
    hi = np.where(b < 0.0, root, np.inf).min(-1)
    del root
    parallel_out = ((b == 0.0) & (a < 0.0)).any(-1)
    t0 = np.maximum(lo, 0.0)
    t1 = np.minimum(hi, tmax[:, None])
    hit = (t1 > t0) & ~parallel_out
    ki, mi = np.nonzero(hit)
    t0 = t0[ki, mi]
    t1 = t1[ki, mi]
    a = a[ki, mi]
    b = b[ki, mi]
    l0 = a + t0[:, None] * b
    l1 = a + t1[:, None] * b
    return ki, mi, t0, t1, _renorm(l0), _renorm(l1)


def _union_clip(ray, tet, t0, t1, l0, l1):
    """Reduce the segments of every ray to the union of their intervals.

    Input sorted by (ray, t0).  Each segment's start is clipped to the running maximum
    of the ends of the previous segments of the same ray: a fully covered segment is
    dropped, a partially covered one keeps its uncovered tail, with barycentrics at the
    new start interpolated linearly along the segment (exact: attributes are affine in a
    tet).  This removes double counting where a ray runs inside a face or along an edge
    shared by several tets; the field is continuous across faces, so which tet supplies
    a shared piece does not matter."""
    S = ray.shape[0]
    if S < 2:
        return ray, tet, t0, t1, l0, l1
    # segmented running max of t1, done exactly on integer keys: rank of t1 among all
    # ends, offset per ray (ray is non-decreasing, so groups never mix in the max)
    by_end = np.argsort(t1, kind="stable")
    rank = np.empty(S, dtype=np.int64)
    rank[by_end] = np.arange(S)
    key = np.maximum.accumulate(ray.astype(np.int64) * S + rank)
    run_end = t1[by_end[key - ray.astype(np.int64) * S]]  # max end over [group start, i]
    prev_end = np.empty(S)
    prev_end[0] = -np.inf
    prev_end[1:] = run_end[:-1]
    prev_end[1:][ray[1:] != ray[:-1]] = -np.inf
    keep = prev_end < t1
    clip = keep & (prev_end > t0)
    if np.any(clip):
        f = (prev_end[clip] - t0[clip]) / (t1[clip] - t0[clip])
        l0 = l0.copy()
        l0[clip] = _renorm(l0[clip] + f[:, None] * (l1[clip] - l0[clip]))
        t0 = t0.copy()
        t0[clip] = prev_end[clip]
    return ray[keep], tet[keep], t0[keep], t1[keep], l0[keep], l1[keep]


def _renorm(lam):
    lam = np.clip(lam, 0.0, None)
    s = lam.sum(-1, keepdims=True)
    return lam / np.where(s > 0.0, s, 1.0)


def _segment_integrals(L, s0, s1, xq, wq):
    """For each segment return (I0, I1, tau) with
    I0 = int_0^L sigma e^{-tau} ds, I1 = int_0^L sigma e^{-tau} (s/L) ds, tau = tau(L)."""
    S = L.shape[0]
    ds = s1 - s0
    tau_tot = 0.5 * L * (s0 + s1)
    q = 0.5 * ds / L                                      # tau(s) = s0 s + q s^2
    # effective integration length: where tau reaches _TAU_CUT (stable root)
    Le = L.copy()
    big = tau_tot > _TAU_CUT
    if np.any(big):
        disc = np.maximum(s0[big] ** 2 + 4.0 * q[big] * _TAU_CUT, 0.0)
        Le[big] = np.minimum(2.0 * _TAU_CUT / (s0[big] + np.sqrt(disc)), L[big])
    tau_e = s0 * Le + q * Le * Le
    nsub = np.ceil(2.0 * tau_e / _TAU_SUB).astype(np.int64)
    nsub = np.clip(nsub, 1, int(np.ceil(2.0 * _TAU_CUT / _TAU_SUB)) + 1)

    I0 = np.zeros(S)
    I1 = np.zeros(S)
    cum = np.cumsum(nsub)
    start = 0
    while start < S:
        base = cum[start - 1] if start > 0 else 0
        stop = int(np.searchsorted(cum, base + _SUB_BUDGET, side="right"))
        stop = max(stop, start + 1)
        idx = np.arange(start, stop)
        n = nsub[idx]
        seg = np.repeat(idx, n)                           # segment of every sub-interval
        first = np.repeat(np.cumsum(n) - n, n)
        k = np.arange(seg.shape[0]) - first               # sub-interval number
        h = Le[seg] / n.repeat(n)
        sa = k * h                                        # sub-interval start
        s = sa[:, None] + (0.5 * (xq[None, :] + 1.0)) * h[:, None]   # (nsub_tot, nq)
        Ls, s0s, qs, dss = L[seg][:, None], s0[seg][:, None], q[seg][:, None], ds[seg][:, None]
        u = s / Ls
        sig = s0s + dss * u
        tau = s0s * s + qs * s * s
        g = sig * np.exp(-tau) * (0.5 * h[:, None]) * wq[None, :]
        g0 = g.sum(-1)
        g1 = (g * u).sum(-1)
        I0[start:stop] = np.bincount(seg - start, weights=g0, minlength=stop - start)
        I1[start:stop] = np.bincount(seg - start, weights=g1, minlength=stop - start)
        start = stop
    return I0, I1, tau_tot


def _color_pieces(color, opacity):
    """Linear pieces of a mesh with per-vertex color (n,3) and extinction (n,)."""
    col = np.asarray(color, dtype=np.float64).reshape(-1, 3)
    sig = np.asarray(opacity, dtype=np.float64).reshape(-1)
    if col.shape[0] != sig.shape[0]:
        raise ValueError("color/opacity must have one entry per vertex")
    if np.any(sig < 0.0):
        raise ValueError("opacity must be >= 0")

    def pieces(ray, tet, t0, t1, l0, l1, vid):
        return (ray, t0, t1, np.einsum("si,sic->sc", l0, col[vid]),
                np.einsum("si,sic->sc", l1, col[vid]), np.einsum("si,si->s", l0, sig[vid]),
                np.einsum("si,si->s", l1, sig[vid]))
    return col.shape[0], pieces


def _classified_pieces(scalar, tf_color, tf_opacity, value_range, light=None):
    """Linear pieces of a scalar mesh classified after interpolation: each
    segment cut where the scalar crosses a texel centre. ``light = (G,
    directions, (ambient, diffuse, specular, power))``: the colors lit by a
    headlight at each tet's gradient ``G`` (m, 3)."""
    sca = np.asarray(scalar, dtype=np.float64).reshape(-1)
    tc = np.asarray(tf_color, dtype=np.float64).reshape(-1, 3)
    to = np.asarray(tf_opacity, dtype=np.float64).reshape(-1)
    if tc.shape[0] != to.shape[0] or tc.shape[0] < 2:
        raise ValueError("tf_color (R,3) and tf_opacity (R,) with R >= 2")
    if np.any(to < 0.0):
        raise ValueError("tf_opacity must be >= 0")
    lo, hi = (float(x) for x in value_range)
    R = tc.shape[0]
    centres = lo + (np.arange(R) + 0.5) * (hi - lo) / R

    def tf(v):
        return (np.stack([np.interp(v, centres, tc[:, j]) for j in range(3)], -1),
                np.interp(v, centres, to))

    def pieces(ray, tet, t0, t1, l0, l1, vid):
        v0 = np.einsum("si,si->s", l0, sca[vid])
        v1 = np.einsum("si,si->s", l1, sca[vid])
        a = np.searchsorted(centres, np.minimum(v0, v1), side="right")
        b = np.searchsorted(centres, np.maximum(v0, v1), side="left")
        cuts = np.maximum(b - a, 0)                       # centres strictly inside
        n = cuts + 1                                      # pieces per segment
        seg = np.repeat(np.arange(ray.shape[0]), n)
        j = np.arange(seg.shape[0]) - np.repeat(np.cumsum(n) - n, n)   # piece number

        def frac(k):                                      # boundary k of each piece's segment
            up = v1[seg] >= v0[seg]
            knot = np.where(up, a[seg] + k - 1, b[seg] - k)   # the k-th cut, in t order
            kv = centres[np.clip(knot, 0, R - 1)]
            dv = v1[seg] - v0[seg]
            f = (kv - v0[seg]) / np.where(dv != 0.0, dv, 1.0)
            f = np.where(k == 0, 0.0, np.where(k == n[seg], 1.0, f))
            return np.clip(f, 0.0, 1.0)
        fa, fb = frac(j), frac(j + 1)
        L = (t1 - t0)[seg]
        va = v0[seg] + fa * (v1 - v0)[seg]
        vb = v0[seg] + fb * (v1 - v0)[seg]
        ca, sa = tf(va)
        cb, sb = tf(vb)
        if light is not None:
            G, D, (ka, kd, ks, power) = light
            g, d = G[tet][seg], D[ray[seg]]
            for c in (ca, cb):
                norm = np.linalg.norm(g, axis=1)
                cos = np.abs(np.einsum("sc,sc->s", g, d)) / np.where(norm > 0, norm, 1.0)
                lit = c * (ka + kd * cos)[:, None] + (ks * cos ** power)[:, None]
                c[:] = np.where((norm > 0)[:, None], lit, c)
        return ray[seg], t0[seg] + fa * L, t0[seg] + fb * L, ca, cb, sa, sb
    return sca.shape[0], pieces


def reference_render(vertices, tets, color, opacity, origins, directions,
                     background=(0, 0, 0), t_max=np.inf, n_quad=48):
    """Brute-force float64 reference of emission-absorption rendering of a tet mesh.

    vertices (n,3) float, tets (m,4) int (any orientation; tets with
    |volume| <= 1e-14 * scale^3 are skipped, scale = largest bounding-box extent of
    the referenced vertices), color (n,3) linear RGB per vertex (emission per unit
    extinction), opacity (n,) extinction per unit length >= 0, origins (k,3),
    directions (k,3) (normalised inside; a zero direction hits nothing).
    background: RGB triple (or (k,3)); t_max: scalar or (k,) distance limit.
    Returns rgb (k,3) float64 and alpha (k,) float64.
    """
    return _render(vertices, tets, _color_pieces(color, opacity), origins, directions,
                   background, t_max, n_quad)


def reference_render_classified(vertices, tets, scalar, tf_color, tf_opacity, value_range,
                                origins, directions, background=(0, 0, 0), t_max=np.inf,
                                n_quad=48):
    """The same reference for a per-vertex scalar classified *after*
    interpolation by a transfer function held as R texels.

    scalar (n,); tf_color (R,3) linear RGB and tf_opacity (R,) extinction per
    unit length at the texel centres ``lo + (k + 0.5) (hi - lo) / R`` of
    ``value_range = (lo, hi)``, linear between centres and constant outside.
    Along each tet segment the scalar is linear; the segment is cut where it
    crosses a texel centre, and on each piece color and extinction are linear
    in t and integrated as above.
    """
    return _render(vertices, tets, _classified_pieces(scalar, tf_color, tf_opacity,
                                                      value_range),
                   origins, directions, background, t_max, n_quad)


def reference_tet_gradients(vertices, tets, scalar):
    """(m, 3) float64: the constant gradient of a per-vertex scalar in each
    tet, solved from its edges (zero in flat tets)."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(tets, np.int64)
    s = np.asarray(scalar, np.float64)
    E = np.stack([v[t[:, k]] - v[t[:, 0]] for k in (1, 2, 3)], 1)
    ds = np.stack([s[t[:, k]] - s[t[:, 0]] for k in (1, 2, 3)], 1)
    ok = np.abs(np.linalg.det(E)) > 0
    g = np.zeros((len(t), 3))
    g[ok] = np.linalg.solve(E[ok], ds[ok][..., None])[..., 0]
    return g


def reference_render_shaded(vertices, tets, scalar, tf_color, tf_opacity, value_range,
                            lighting, origins, directions, n_quad=48):
    """:func:`reference_render_classified` with the colors lit by a headlight
    (``lighting = (ambient, diffuse, specular, power)``) at each tet's
    gradient of the scalar (:func:`reference_tet_gradients`)."""
    D = np.asarray(directions, np.float64).reshape(-1, 3)
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    G = reference_tet_gradients(vertices, tets, scalar)
    return _render(vertices, tets, _classified_pieces(scalar, tf_color, tf_opacity, value_range,
                                                      (G, D, lighting)),
                   origins, directions, (0, 0, 0), np.inf, n_quad)


def reference_projection(vertices, tets, scalar, origins, directions, mode="max"):
    """Intensity projections of a per-vertex scalar along rays, in float64:
    every ray clipped against every tet (the union of the covered intervals,
    :func:`_pieces`), the scalar at each piece's ends by its barycentrics;
    ``max`` / ``min`` of those ends (a linear function's extremes on a
    segment), ``mean`` the length-weighted trapezoid sum over the total
    length. Returns ``(value (k,), met (k,) bool)``, value NaN where a ray
    meets no tet."""
    sca = np.asarray(scalar, dtype=np.float64).reshape(-1)

    def pieces(ray, tet, t0, t1, l0, l1, vid):
        return (ray, t1 - t0, np.einsum("si,si->s", l0, sca[vid]),
                np.einsum("si,si->s", l1, sca[vid]))

    k = np.asarray(origins).reshape(-1, 3).shape[0]
    value = np.full(k, np.nan)
    out = _pieces(vertices, tets, (len(sca), pieces), origins, directions, np.inf)
    if out is None:
        return value, np.zeros(k, bool)
    ray, length, s0, s1 = out
    met = np.bincount(ray, minlength=k) > 0
    if mode == "max":
        np.fmax.at(value, ray, np.maximum(s0, s1))
    elif mode == "min":
        np.fmin.at(value, ray, np.minimum(s0, s1))
    elif mode == "mean":
        total = np.bincount(ray, length, minlength=k)
        value = np.where(met, np.bincount(ray, length * 0.5 * (s0 + s1), minlength=k)
                         / np.where(met, total, 1.0), np.nan)
    else:
        raise ValueError(f"mode must be max, min or mean, got {mode!r}")
    return value, met


def reference_slice(vertices, tets, scalar, origins, directions, origin, normal, tol=1e-9):
    """The scalar where each ray meets the plane through ``origin`` with
    ``normal``, in float64: the meeting point (ahead of the ray), the tets
    whose barycentric coordinates there are all >= -tol, the scalar
    interpolated in the first of them. Returns ``(value (k,), met (k,))``,
    value NaN where the point lies in no tet (or the ray misses the plane)."""
    V = np.asarray(vertices, np.float64).reshape(-1, 3)
    sca = np.asarray(scalar, np.float64).reshape(-1)
    O = np.asarray(origins, np.float64).reshape(-1, 3)
    D = np.asarray(directions, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((np.asarray(origin, np.float64) - O) @ n) / (D @ n)
    ahead = np.isfinite(t) & (t > 0)
    P = O + np.where(ahead, t, 0.0)[:, None] * D
    Tt, v0, G = _prepare_tets(V, np.asarray(tets, np.int64).reshape(-1, 4))
    lam = np.einsum("mij,kmj->kmi", G, P[:, None, :] - v0[None])        # (k, m, 3)
    lam = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], -1)   # (k, m, 4)
    inside = np.all(lam >= -tol, axis=-1) & ahead[:, None]
    met = inside.any(1)
    first = np.argmax(inside, axis=1)
    rows = np.arange(len(O))
    value = np.einsum("ki,ki->k", lam[rows, first], sca[Tt[first]])
    return np.where(met, value, np.nan), met


def reference_vertex_gradients(vertices, tets, scalar):
    """(n, 3) float64: each vertex's gradient of a per-vertex scalar, the
    gradients of the tets around it averaged by their volumes."""
    v = np.asarray(vertices, np.float64)
    t = np.asarray(tets, np.int64)
    G = reference_tet_gradients(v, t, scalar)
    vol = np.abs(np.linalg.det(np.stack([v[t[:, k]] - v[t[:, 0]] for k in (1, 2, 3)], 1)))
    total, weight = np.zeros((len(v), 3)), np.zeros(len(v))
    for k in range(4):
        np.add.at(total, t[:, k], G * vol[:, None])
        np.add.at(weight, t[:, k], vol)
    return total / np.where(weight > 0, weight, 1.0)[:, None]


def reference_isosurface(vertices, tets, scalar, origins, directions, value, t_min=0.0):
    """The first point past ``t_min`` (scalar or per ray) where each ray's
    interpolated scalar equals ``value``, in float64: every ray clipped
    against every tet, the scalar linear along each piece, its crossing
    solved there. Returns ``t (k,)`` (inf where there is none) and the
    smooth normal there ``(k, 3)`` (:func:`reference_vertex_gradients`
    interpolated by the crossing's barycentrics)."""
    sca = np.asarray(scalar, np.float64).reshape(-1)
    Gv = reference_vertex_gradients(vertices, tets, sca)
    k = np.asarray(origins).reshape(-1, 3).shape[0]
    lo = np.broadcast_to(np.asarray(t_min, np.float64), (k,))

    def pieces(ray, tet, t0, t1, l0, l1, vid):
        s0 = np.einsum("si,si->s", l0, sca[vid])
        s1 = np.einsum("si,si->s", l1, sca[vid])
        with np.errstate(divide="ignore", invalid="ignore"):
            f = (value - s0) / (s1 - s0)
        ok = (s1 != s0) & (f >= 0) & (f <= 1)
        f = np.where(ok, f, 0.0)
        t = t0 + f * (t1 - t0)
        ok &= t > lo[ray]
        lam = l0 + f[:, None] * (l1 - l0)
        n = np.einsum("si,sij->sj", lam, Gv[vid])
        return ray[ok], t[ok], n[ok]

    t_hit, normal = np.full(k, np.inf), np.zeros((k, 3))
    out = _pieces(vertices, tets, (len(sca), pieces), origins, directions, np.inf)
    if out is None:
        return t_hit, normal
    ray, t, n = out
    order = np.lexsort((t, ray))
    ray, t, n = ray[order], t[order], n[order]
    first = np.r_[True, ray[1:] != ray[:-1]] if ray.size else np.zeros(0, bool)
    t_hit[ray[first]] = t[first]
    normal[ray[first]] = n[first]
    return t_hit, normal


def reference_render_meshes(meshes, origins, directions, background=(0, 0, 0), t_max=np.inf,
                            n_quad=16):
    """The reference for several meshes in one scene, as one medium.

    ``meshes``: a list of dicts, each ``{"vertices", "tets", "color", "opacity"}``
    (emission-absorption; ``color`` may be zeros for absorption only) or
    ``{"vertices", "tets", "scalar", "tf_color", "tf_opacity", "value_range"}``
    (post-classified; with ``"lighting"``, lit as
    :func:`reference_render_shaded` lights it). Every mesh's linear pieces
    along a ray (as in the
    single-mesh references) are merged in depth order: the ray is cut at
    every piece end of every mesh, and on each resulting interval the
    extinctions of the meshes that cover it add and so do their emissions
    ``sigma_k c_k``; the interval's emission ``int sum_k sigma_k c_k e^{-tau}``
    (``tau`` the optical depth of the summed extinction, in closed form) is
    integrated by composite Gauss-Legendre quadrature (sub-intervals of
    optical depth <= 0.5), and the intervals are composited front to back.
    Where the meshes do not overlap this is the single-mesh reference's
    compositing. Returns rgb (k,3) and alpha (k,).
    """
    O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    k = O.shape[0]
    parts = []
    for m in meshes:
        if "scalar" in m:
            light = None
            if "lighting" in m:
                D = np.asarray(directions, np.float64).reshape(-1, 3)
                light = (reference_tet_gradients(m["vertices"], m["tets"], m["scalar"]),
                         D / np.linalg.norm(D, axis=1, keepdims=True), m["lighting"])
            spec = _classified_pieces(m["scalar"], m["tf_color"], m["tf_opacity"],
                                      m["value_range"], light)
        else:
            spec = _color_pieces(m["color"], m["opacity"])
        p = _pieces(m["vertices"], m["tets"], spec, origins, directions, t_max)
        if p is not None:
            parts.append(p)
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), (k, 3))
    C = np.zeros((k, 3))
    T = np.ones(k)
    if not parts:
        return C + T[:, None] * bg, 1.0 - T
    ray, t0, t1, c0, c1, s0, s1 = (np.concatenate(x) for x in zip(*parts))
    keep = t1 > t0
    ray, t0, t1, c0, c1, s0, s1 = (x[keep] for x in (ray, t0, t1, c0, c1, s0, s1))
    xq, wq = np.polynomial.legendre.leggauss(int(n_quad))
    order = np.argsort(ray, kind="stable")
    bounds = np.searchsorted(ray[order], np.arange(k + 1))
    for r in range(k):
        sel = order[bounds[r]:bounds[r + 1]]
        if not len(sel):
            continue
        P = [x[sel] for x in (t0, t1, c0, c1, s0, s1)]
        cuts = np.unique(np.concatenate([P[0], P[1]]))
        for a, b in zip(cuts[:-1], cuts[1:]):
            if T[r] < 1e-30:
                break
            mid = 0.5 * (a + b)
            cover = (P[0] <= mid) & (P[1] >= mid)
            if not cover.any():
                continue
            pa, pb, pc0, pc1, ps0, ps1 = (x[cover] for x in P)
            span = pb - pa

            def at(t):                                   # sigma_k, sigma_k c_k at t (q,)
                f = (t[None, :] - pa[:, None]) / span[:, None]
                sig = ps0[:, None] + f * (ps1 - ps0)[:, None]
                col = pc0[:, None, :] + f[..., None] * (pc1 - pc0)[:, None, :]
                return sig.sum(0), (sig[..., None] * col).sum(0)
            S0, S1 = at(np.array([a, b]))[0]
            L = b - a
            tau_L = 0.5 * L * (S0 + S1)
            n = int(min(np.ceil(tau_L / _TAU_SUB), 2 * _TAU_CUT / _TAU_SUB)) + 1
            h = L / n
            s = (np.arange(n)[:, None] * h + 0.5 * (xq[None, :] + 1.0) * h).ravel()
            tau = S0 * s + 0.5 * (S1 - S0) / L * s * s
            _, emit = at(a + s)
            w = np.tile(wq, n) * 0.5 * h
            C[r] += T[r] * (emit * (w * np.exp(-tau))[:, None]).sum(0)
            T[r] *= np.exp(-tau_L)
    return C + T[:, None] * bg, 1.0 - T


def _pieces(vertices, tets, spec, origins, directions, t_max):
    """Every ray clipped against every tet, reduced to the union of the
    covered intervals; ``spec = (n_values, pieces)`` with ``pieces(ray, tet,
    t0, t1, l0, l1, vid) -> (ray, t0, t1, c0, c1, s0, s1)`` the linear pieces
    of the segments, in front-to-back order per ray. Returns the pieces of
    all rays (None if there are none)."""
    n_values, piece = spec
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    Tt = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    D = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    k = O.shape[0]
    if D.shape[0] != k:
        raise ValueError("origins and directions must have the same length")
    if n_values != V.shape[0]:
        raise ValueError("the vertex values must have one entry per vertex")
    tmax = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (k,)).copy()

    norm = np.linalg.norm(D, axis=1)
    valid = norm > 0.0
    D = D / np.where(valid, norm, 1.0)[:, None]
    tmax[~valid] = -1.0                                   # no hits for zero directions

    Tt, v0, G = _prepare_tets(V, Tt)
    m = Tt.shape[0]
    if m == 0 or k == 0:
        return None
    out = []
    mc = min(m, _PAIR_BUDGET)
    kc = max(1, _PAIR_BUDGET // mc)
    for r0 in range(0, k, kc):
        r1 = min(k, r0 + kc)
        parts = []
        for m0 in range(0, m, mc):
            m1 = min(m, m0 + mc)
            ki, mi, t0, t1, l0, l1 = _clip(O[r0:r1], D[r0:r1], tmax[r0:r1],
                                           v0[m0:m1], G[m0:m1])
            if ki.size:
                parts.append((ki + r0, mi + m0, t0, t1, l0, l1))
        if not parts:
            continue
        ray, tet, t0, t1, l0, l1 = (np.concatenate(x) for x in zip(*parts))
        # sort by (ray, t0) and keep only the union of the covered intervals
        order = np.lexsort((t0, ray))
        ray, tet, t0, t1 = ray[order], tet[order], t0[order], t1[order]
        l0, l1 = l0[order], l1[order]
        ray, tet, t0, t1, l0, l1 = _union_clip(ray, tet, t0, t1, l0, l1)
        if ray.size:
            out.append(piece(ray, tet, t0, t1, l0, l1, Tt[tet]))
    if not out:
        return None
    return tuple(np.concatenate(x) for x in zip(*out))


def _render(vertices, tets, spec, origins, directions, background, t_max, n_quad):
    """One mesh: its linear pieces (:func:`_pieces`) integrated (Eq. 1 by
    quadrature) and composited front to back."""
    O = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    k = O.shape[0]
    bg = np.broadcast_to(np.asarray(background, dtype=np.float64), (k, 3))
    xq, wq = np.polynomial.legendre.leggauss(int(n_quad))
    C = np.zeros((k, 3))
    T = np.ones(k)
    p = _pieces(vertices, tets, spec, origins, directions, t_max)
    if p is not None:
        ray, t0, t1, c0, c1, s0, s1 = p
        I0, I1, tau = _segment_integrals(t1 - t0, s0, s1, xq, wq)
        Cseg = c0 * I0[:, None] + (c1 - c0) * I1[:, None]
        Tseg = np.exp(-tau)
        # front-to-back compositing, pieces are sorted by (ray, t)
        new_group = np.ones(ray.shape[0], dtype=bool)
        new_group[1:] = ray[1:] != ray[:-1]
        group_start = np.maximum.accumulate(np.where(new_group, np.arange(ray.shape[0]), 0))
        rank = np.arange(ray.shape[0]) - group_start
        by_rank = np.argsort(rank, kind="stable")
        counts = np.bincount(rank)
        pos = 0
        for cnt in counts:
            sel = by_rank[pos:pos + cnt]
            pos += cnt
            rr = ray[sel]                              # unique within one rank
            C[rr] += T[rr, None] * Cseg[sel]
            T[rr] *= Tseg[sel]
    rgb = C + T[:, None] * bg
    alpha = 1.0 - T
    return rgb, alpha
