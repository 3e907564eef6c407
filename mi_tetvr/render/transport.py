"""Light transport in tet volumes: exact free-flight sampling, exact
transmittance, and a volumetric path tracer with path replay.

Extinction ``s`` is linear inside a tet, so along a ray it is linear on each
piece between two face crossings and the optical depth of a piece of length
``l`` from ``s0`` to ``s1`` is ``tau(x) = s0 x + (s1 - s0) x^2 / (2 l)``. A
free-flight distance is sampled by drawing ``tau* = -log(1 - u)`` and walking
tet to tet until the accumulated depth reaches it, then solving the
quadratic in the piece (:func:`solve_depth`): the distance has exactly the
density ``s(t) exp(-tau(t))``. No majorant, no null collisions. The
transmittance of a shadow ray is ``exp(-tau)`` walked exactly to its end.

A scattered ray starts inside the tet where the collision happened: the walk
needs the face through which the ray's line enters that tet
(:func:`inside_face`), found by the walk's own edge predicate, so a path
never re-locates its point.

The path tracer (:func:`sample`) follows Mitsuba's ``prbvolpath``: free
flights, collisions that emit (the medium's emission per unit extinction,
as ``tetvr``'s color) and scatter with probability of the albedo, next-event
estimation to the scene's emitters with multiple importance sampling
against the phase function and the BSDFs, Russian roulette; surfaces (the
scene's other shapes) with their BSDFs on the same paths, their shadow rays
attenuated by the volume. Its derivative modes replay each path with the
same random numbers (path replay backpropagation, Vicini et al. 2021):
memory is constant per path. With ``w`` the weight a vertex multiplies the
path by and ``L`` the radiance the path gathers after it, the vertex adds
``L dw / w``: for a free flight ``-L dtau`` along the walked interval (a
second walk that differentiates each piece's optical depth) and ``L ds / s``
at a collision, ``L da / a`` for the albedo, ``beta dc`` for the emission,
``-C dtau`` along a shadow ray that carried the contribution ``C``, and the
phase function's ``L dp / p``. Positions get the derivative of the
integrand (the crossings move, the field at a sampled point moves); like
``prbvolpath``, nothing of the boundary terms of a moving silhouette.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_tetvr.mesh.topology import FACES
from mi_tetvr.render.buffers import unpack_link
from mi_tetvr.render.geometry import (crossing_at, edge_function, entry_carry,
                                      face_crossing, project, ray_frame, walk_step)
from mi_tetvr.render.linear import TetFrame
from mi_tetvr.render.pytree import weighted_sum
from mi_tetvr.render.segment import clip_segment
from mi_tetvr.render.walk import WalkSettings, enter

#: A walk for transmittance stops at this optical depth (T < 1e-13).
TAU_STOP = 30.0


def solve_depth(s0, s1, length, r):
    """The distance ``x`` in ``[0, length]`` at which a piece whose
    extinction goes linearly from ``s0`` to ``s1`` reaches optical depth
    ``r``: the root of ``s0 x + (s1 - s0) x^2 / (2 length) = r`` (in the
    form without cancellation, ``2 r / (s0 + sqrt(s0^2 + 2 k r))``)."""
    k = (s1 - s0) * dr.rcp(dr.select(length > 0, length, 1.0))
    disc = dr.maximum(s0 * s0 + 2.0 * k * r, 0.0)
    den = s0 + dr.safe_sqrt(disc)
    x = dr.select(den > 0, 2.0 * r * dr.rcp(dr.select(den > 0, den, 1.0)), length)
    return dr.clip(x, 0.0, length)


def inside_face(buf, tet, o, u, v, d, active=True):
    """The local face through which the line of a ray from ``o`` (a point of
    ``tet``) in direction ``d`` enters ``tet``: the face the line passes
    through (its three canonical edge functions agree) that faces the ray
    (projected clockwise in the ray frame: an outward normal against ``d``).
    Where round-off puts ``o`` just outside and the line misses the tet, the
    face closest to being crossed."""
    rec = dr.gather(mi.Array4u, buf.tets, tet, active)
    ids = (rec.x, rec.y, rec.z, rec.w)
    p = [project(buf.position(i, active), o, u, v) for i in ids]
    best = mi.UInt32(0)
    best_score = mi.Float(-dr.inf)
    for f in range(4):
        a, b, c = (int(k) for k in FACES[f])
        e_bc, s_bc = edge_function(ids[b], p[b], ids[c], p[c])
        e_ca, s_ca = edge_function(ids[c], p[c], ids[a], p[a])
        e_ab, s_ab = edge_function(ids[a], p[a], ids[b], p[b])
        entry = ~s_bc & ~s_ca & ~s_ab
        # How far from passing through it as an entry face (0 or more when it does).
        score = dr.select(entry, dr.inf, -dr.maximum(dr.maximum(e_bc, e_ca), e_ab))
        take = score > best_score
        best = dr.select(take, f, best)
        best_score = dr.select(take, score, best_score)
    return best


class Flight:
    """What a walk along a ray found (:func:`flight`).

    tau : the optical depth walked (to the collision, or to the end).
    hit : whether it reached the target depth (a collision).
    t, tet, s : the collision's ray parameter, tet and the extinction
        there (the other attributes: :func:`attributes_at`).
    """

    def __init__(self, tau, hit, t, tet, s):
        self.tau, self.hit, self.t, self.tet, self.s = tau, hit, t, tet, s


def extinction(params, i, active=True, reduce=dr.ReduceMode.Auto):
    """The extinction of vertex ``i`` (every scattering and emission model's
    ``opacity``): all that a free flight reads per vertex. ``reduce``: the
    scatter strategy of the gather's derivative."""
    return dr.gather(mi.Float, params.opacity, i, active, mode=reduce)


def _piece_depth(ts_ad, st, entry_w, o, u, v, d, t0, t1, t_begin, t_stop, active, geometric,
                 reduce):
    """The optical depth of the piece of the segment ``st`` crossed over
    ``[t_begin, t_stop]``, attached to the parameters' AD graph (the
    crossings computed again from the attached buffers where vertices move,
    else at the walk's own ray parameters with attached attributes)."""
    with dr.resume_grad():
        if geometric:
            t0, w0 = face_crossing(ts_ad.buf, st.entry, o, u, v, d, active, reduce)
            t1, w1 = face_crossing(ts_ad.buf, st.exit, o, u, v, d, active, reduce)
        else:
            w0, w1 = entry_w, st.w
        s0 = weighted_sum(w0, [extinction(ts_ad.params, i, active, reduce) for i in st.entry])
        s1 = weighted_sum(w1, [extinction(ts_ad.params, i, active, reduce) for i in st.exit])
        length, b0, b1 = clip_segment(t0, s0, t1, s1, t_begin, t_stop)
        return length * (b0 + b1) * 0.5


@dr.syntax
def walk_depth(ts, tet, f_in, o, u, v, d, t_begin, t_stop, tau, target, settings: WalkSettings,
               active, grad=None):
    """Walk from ``tet`` (entered through its local face ``f_in``) over
    ``[t_begin, t_stop]``, adding each piece's optical depth to ``tau``,
    until it reaches ``target`` (a collision), the ray leaves the mesh, or
    ``t_stop``.

    ``grad`` (a derivative pass): ``(mode, ts_ad, seed)``; backward mode
    propagates ``seed * tau_walked`` into the parameters, forward mode
    returns the tangent of the walked depth. Returns ``(tau, hit, t_hit,
    tet_hit, s_hit, t_end, dtau)``. The walk reads only the extinction.
    """
    buf, params = ts.buf, ts.params

    def gather(i, active):
        return extinction(params, i, active)

    tet = mi.UInt32(tet)
    f_in = mi.UInt32(f_in)
    tau = mi.Float(tau)
    active = mi.Bool(active)
    carry = entry_carry(buf, tet, f_in, o, u, v, d, active, gather)
    t, w = crossing_at(carry[0], carry[2])
    a = weighted_sum(w, carry[1])
    hit = mi.Bool(False)
    t_hit = mi.Float(dr.inf)
    tet_hit = mi.UInt32(tet)
    s_hit = mi.Float(0.0)
    dtau = mi.Float(0.0)
    steps = mi.UInt32(0)
    derivative = grad is not None
    if dr.hint(derivative, mode="scalar"):
        mode, ts_ad, seed = grad
        backward = mode == dr.ADMode.Backward
        with dr.resume_grad():
            geometric = dr.grad_enabled(ts_ad.buf.positions)
    while dr.hint(active, label="tetpath_depth"):
        st = walk_step(buf, tet, f_in, o, u, v, d, active, carry, gather)
        a_out = weighted_sum(st.w, st.carry[1])
        t_out = dr.maximum(st.t, t)
        length, a0, a1 = clip_segment(t, a, t_out, a_out, t_begin, t_stop)
        t0 = dr.clip(t, t_begin, t_stop)
        tau_seg = length * (a0 + a1) * 0.5
        r = target - tau
        here = active & (tau_seg >= r)
        x = solve_depth(a0, a1, length, r)
        t_hit = dr.select(here, t0 + x, t_hit)
        frac = dr.select(length > 0, x * dr.rcp(dr.select(length > 0, length, 1.0)), 0.0)
        s_hit = dr.select(here, dr.lerp(a0, a1, frac), s_hit)
        tet_hit = dr.select(here, tet, tet_hit)
        if dr.hint(derivative, mode="scalar"):
            stop = dr.select(here, t0 + x, t_stop)
            with dr.resume_grad():
                piece = _piece_depth(ts_ad, st, carry_w(carry), o, u, v, d, t, t_out, t_begin,
                                     stop, active, geometric, settings.reduce)
                flags = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
                if dr.hint(backward, mode="scalar"):
                    dr.backward_from(dr.select(active, seed, 0.0) * piece, flags=flags)
                else:
                    dtau += dr.select(active, dr.forward_to(piece, flags=flags), 0.0)
        tau = dr.select(here, target, tau + tau_seg)
        hit |= here
        carry = st.carry
        t = t_out
        a = a_out
        steps += 1
        tet, f_in = unpack_link(st.link)
        active &= ~here & (st.link >= 0) & (t_out < t_stop) & (steps < settings.max_steps)
        active &= tau < TAU_STOP
    return tau, hit, t_hit, tet_hit, s_hit, t, dtau


def carry_w(carry):
    """The barycentric weights of the crossing of the face a walk carries."""
    return crossing_at(carry[0], carry[2])[1]


@dr.syntax
def flight(ts, walk_scene, o, d, t_max, target, tet0, inside, settings: WalkSettings, active,
           grad=None):
    """Walk a ray through the tet meshes (all of ``ts``, one group) up to
    ``t_max``, until the optical depth reaches ``target`` (``inf``: the
    transmittance ``exp(-tau)`` of the whole ray).

    The ray starts at ``o``: inside the tet ``tet0`` where ``inside`` (a
    scattered ray), else wherever Mitsuba's ray tracer finds the meshes'
    boundary (entering, or leaving when ``o`` lies inside: the start tet is
    then found by walking back). Leaving a mesh, it traces again for
    re-entry. ``grad``: see :func:`walk_depth`. Returns a :class:`Flight`
    and the walked depth's tangent (forward mode, else 0).
    """
    buf = ts.buf
    o = mi.Point3f(o)
    d = mi.Vector3f(d)
    t_max = mi.Float(t_max)
    u, v = ray_frame(d)
    tau = mi.Float(0.0)
    hit = mi.Bool(False)
    t_hit = mi.Float(dr.inf)
    tet_hit = mi.UInt32(0)
    s_hit = mi.Float(0.0)
    dtau = mi.Float(0.0)
    start = mi.Float(0.0)
    first = mi.Bool(inside) & mi.Bool(active)
    active = mi.Bool(active)
    while dr.hint(active, label="tetpath_flight"):
        trace = active & ~first
        si = walk_scene.ray_intersect_preliminary(mi.Ray3f(o + d * start, d, t_max - start),
                                                  active=trace)
        found = trace & si.is_valid()
        tet_b, f_b, _ = enter(buf, ts.boundary_face(si), o, u, v, d, start, settings.max_steps,
                              found)
        f_i = inside_face(buf, tet0, o, u, v, d, first)
        go = first | found
        tet = dr.select(first, tet0, tet_b)
        f = dr.select(first, f_i, f_b)
        tau, here, t_g, tet_g, s_g, t_end, dt = walk_depth(ts, tet, f, o, u, v, d, start, t_max,
                                                        tau, target, settings, go, grad)
        t_hit = dr.select(here, t_g, t_hit)
        tet_hit = dr.select(here, tet_g, tet_hit)
        s_hit = dr.select(here, s_g, s_hit)
        hit |= here
        dtau += dt
        start = dr.select(go, dr.maximum(t_end, start), start) + settings.retrace_eps
        first = mi.Bool(False)
        active = go & ~hit & (start < t_max) & (tau < TAU_STOP)
    return Flight(tau, hit, t_hit, tet_hit, s_hit), dtau


def attributes_at(ts_ad, tet, p, active=True, reduce=dr.ReduceMode.Auto):
    """The model's attributes at point ``p`` of ``tet`` (barycentric in the
    tet), attached to the parameters' AD graph: the field at a sampled point,
    moving with the vertices (``reduce``: the gathers' scatter strategy)."""
    with dr.resume_grad():
        frame = TetFrame(ts_ad.buf, tet, active, reduce)
        w = frame.weights(p)
        return weighted_sum(w, [ts_ad.model.gather(ts_ad.params, i, active, reduce)
                                for i in frame.ids])


class PathScene:
    """What the path tracer reads for one scene.

    scene : mi.Scene            the user's scene (its emitters)
    ts : TetScene                the scattering meshes, detached (the walk reads these)
    ts_ad : TetScene             the same, attached to the parameters' AD graph
    walk_scene : mi.Scene        the meshes' boundaries (the walk traces these)
    surfaces : mi.Scene          the other shapes (an empty scene without any)
    phase : mi.PhaseFunction     the meshes' phase function
    settings : WalkSettings
    max_depth, rr_depth : int    as Mitsuba's ``volpath``
    """

    def __init__(self, scene, ts, ts_ad, walk_scene, surfaces, phase, settings, max_depth,
                 rr_depth):
        self.scene, self.ts, self.ts_ad = scene, ts, ts_ad
        self.walk_scene, self.surfaces, self.phase = walk_scene, surfaces, phase
        self.settings, self.max_depth, self.rr_depth = settings, max_depth, rr_depth


def _medium_interaction(p, t, d, ray):
    """A Mitsuba medium interaction at ``p`` (for the phase function and the
    emitters' sampling), as Mitsuba's media make them: ``wi = -d``, its
    shading frame around ``wi``."""
    mei = dr.zeros(mi.MediumInteraction3f, dr.width(p))
    mei.p = p
    mei.t = t
    mei.wi = -d
    mei.sh_frame = mi.Frame3f(mei.wi)
    mei.time = ray.time
    mei.wavelengths = ray.wavelengths
    return mei


def _ratio(x_ad, x):
    """``x_ad / x`` (``x`` detached), 0 where ``x`` is 0."""
    ok = x != 0.0
    return dr.select(ok, x_ad * dr.rcp(dr.select(ok, x, 1.0)), 0.0)


class _Grad:
    """The derivative pass's propagation of a vertex's term ``X = term()``
    (a color, computed with AD resumed: the derivative passes run with it
    suspended): backward mode adds ``δL . X`` to the parameters' gradients,
    forward mode adds the tangent of ``X`` to ``dL``."""

    def __init__(self, mode):
        self.mode = mode
        self.backward = mode == dr.ADMode.Backward

    def __call__(self, δL, dL, term, mask):
        flags = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
        with dr.resume_grad():
            X = dr.select(mask, term(), 0.0)
            if self.backward:
                dr.backward_from(δL * X, flags=flags)
                return dL
            return dL + dr.forward_to(X, flags=flags)


@dr.syntax
def sample(mode, ps: PathScene, sampler, ray, δL, state_in, active):
    """Mitsuba's ``sample`` of the path tracer (see the module docstring):
    ``(L or its derivative, valid, alpha, L)``; ``alpha`` is 1 where the
    camera ray's first segment met the medium or a surface (its mean over a
    pixel's samples is the coverage: ``1 - T`` through the volume alone).
    ``mode``: ``dr.ADMode``; the derivative modes take the primal radiance
    ``state_in`` and replay the same paths (``sampler`` seeded as in the
    primal pass)."""
    primal = mode == dr.ADMode.Primal
    grad = None if primal else _Grad(mode)
    scene, ts, ts_ad = ps.scene, ps.ts, ps.ts_ad
    mis_weight = mi.ad.integrators.common.mis_weight
    phase = ps.phase          # (one object: called directly, no virtual call)
    ray = mi.Ray3f(ray)
    L = mi.Spectrum(0.0 if primal else state_in)
    δL = mi.Spectrum(δL if δL is not None else 0.0)
    dL = mi.Spectrum(0.0)                     # forward mode: the radiance's tangent
    β = mi.Spectrum(1.0)
    η = mi.Float(1.0)
    depth = mi.UInt32(0)
    valid = mi.Bool(False)
    seen = mi.Bool(False)                     # the camera segment met something
    first = mi.Bool(True)
    in_tet = mi.Bool(False)                   # the ray starts inside tet `tet` (scattered)
    tet = mi.UInt32(0)
    prev = dr.zeros(mi.Interaction3f)         # the last scattering vertex
    prev_pdf = mi.Float(1.0)
    specular = mi.Bool(True)                  # count emitters hit without MIS
    active = mi.Bool(active)
    phase_ctx = mi.PhaseFunctionContext(sampler)
    bsdf_ctx = mi.BSDFContext()
    while dr.hint(active, label="tetpath"):
        # ---- Russian roulette (Mitsuba's volpath) ----
        q = dr.minimum(dr.max(β) * dr.square(η), 0.99)
        rr = depth > ps.rr_depth
        active &= (sampler.next_1d(active) < q) | ~rr
        β = dr.select(rr, β * dr.rcp(q), β)

        # ---- free flight to a collision, a surface or out of the scene ----
        si = ps.surfaces.ray_intersect(ray, active)
        t_surf = dr.minimum(si.t, ray.maxt)
        target = -dr.log(1.0 - sampler.next_1d(active))
        walk_grad = None
        if dr.hint(not primal, mode="scalar"):
            walk_grad = (mode, ts_ad, -dr.sum(δL * L))
        fl, dtau = flight(ts, ps.walk_scene, ray.o, ray.d, t_surf, target, tet, in_tet,
                          ps.settings, active, walk_grad)
        collided = active & fl.hit
        p = ray.o + fl.t * ray.d
        a = attributes_at(ts, fl.tet, p, collided)

        # ---- a collision: emission, then absorption or scattering ----
        emit = collided & (depth < ps.max_depth)
        Le = dr.select(emit, β * a.c, 0.0)
        if dr.hint(not primal, mode="scalar"):
            dL = dL - dr.select(active, L * dtau, 0.0)

            # The collision's three terms in one pass over the field at p
            # (a second pass would find the interpolation's edges cleared):
            # the extinction's density, the emission, the albedo's weight.
            def collision_term():
                a_ad = attributes_at(ts_ad, fl.tet, p, collided, ps.settings.reduce)
                return (L * _ratio(a_ad.s, a.s) + dr.select(emit, β * a_ad.c, 0.0)
                        + (L - Le) * _ratio(a_ad.a, a.a))
            dL = grad(δL, dL, collision_term, collided)
        L = L + Le if primal else L - Le
        β = dr.select(collided, β * a.a, β)
        depth = dr.select(collided, depth + 1, depth)
        valid |= collided
        active &= depth < ps.max_depth
        scatter = collided & active & dr.any(β != 0.0)
        mei = _medium_interaction(p, fl.t, ray.d, ray)

        # ---- a surface, or the environment ----
        surface = active & ~collided
        emitter = si.emitter(scene)
        hit_e = surface & (emitter != None)   # noqa: E711 (a Dr.Jit pointer array)
        ds = mi.DirectionSample3f(scene, si, prev)
        em_pdf = scene.pdf_emitter_direction(prev, ds, hit_e & ~specular)
        Le = β * emitter.eval(si, hit_e) * dr.select(specular, 1.0, mis_weight(prev_pdf, em_pdf))
        Le = dr.select(hit_e, Le, 0.0)
        L = L + Le if primal else L - Le
        surface &= si.is_valid()
        valid |= surface
        seen |= first & (collided | surface)
        first = mi.Bool(False)
        bsdf = si.bsdf(ray)

        # ---- next-event estimation, from a collision or a surface ----
        nee_surface = surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (
            depth + 1 < ps.max_depth)
        nee = scatter | nee_surface
        ref = dr.zeros(mi.Interaction3f)
        ref[scatter] = mei
        ref[nee_surface] = si
        ds, em_val = scene.sample_emitter_direction(ref, sampler.next_2d(nee), False, nee)
        ds = dr.detach(ds)
        nee &= ds.pdf != 0.0
        shadow = ref.spawn_ray_to(ds.p)
        nee &= ~ps.surfaces.ray_test(shadow, nee)
        sh, _ = flight(ts, ps.walk_scene, shadow.o, shadow.d, shadow.maxt, dr.inf, fl.tet,
                       scatter, ps.settings, nee)
        ph_val, ph_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, scatter & nee)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), nee_surface & nee)
        f = dr.select(scatter, mi.Spectrum(ph_val), bsdf_val)
        dir_pdf = dr.select(ds.delta, 0.0, dr.select(scatter, ph_pdf, bsdf_pdf))
        C = β * f * mis_weight(ds.pdf, dir_pdf) * em_val * dr.exp(-sh.tau)
        C = dr.select(nee, C, 0.0)
        L = L + C if primal else L - C
        if dr.hint(not primal, mode="scalar"):
            _, dtau_sh = flight(ts, ps.walk_scene, shadow.o, shadow.d, shadow.maxt, dr.inf,
                                fl.tet, scatter, ps.settings, nee, (mode, ts_ad, -dr.sum(δL * C)))
            dL = dL - dr.select(nee, C * dtau_sh, 0.0)
            dL = grad(δL, dL, lambda: C * _ratio(
                phase.eval_pdf(phase_ctx, mei, ds.d, scatter & nee)[0], ph_val), scatter & nee)

        # ---- the phase function's direction ----
        wo, ph_w, ph_pdf = phase.sample(phase_ctx, mei, sampler.next_1d(scatter),
                                        sampler.next_2d(scatter), scatter)
        scatter &= ph_pdf > 0.0
        if dr.hint(not primal, mode="scalar"):
            def phase_term():
                ph = phase.eval_pdf(phase_ctx, mei, wo, scatter)[0]
                return L * _ratio(ph, dr.detach(ph))
            dL = grad(δL, dL, phase_term, scatter)
        β = dr.select(scatter, β * ph_w, β)
        ray[scatter] = mi.Ray3f(p, wo, ray.time, ray.wavelengths)
        tet = dr.select(scatter, fl.tet, tet)
        prev[scatter] = mei
        prev_pdf = dr.select(scatter, ph_pdf, prev_pdf)
        specular &= ~scatter

        # ---- the BSDF's direction ----
        bs, bsdf_w = bsdf.sample(bsdf_ctx, si, sampler.next_1d(surface), sampler.next_2d(surface),
                                 surface)
        surface &= bs.pdf > 0.0
        β = dr.select(surface, β * bsdf_w, β)
        η = dr.select(surface, η * bs.eta, η)
        ray[surface] = si.spawn_ray(si.to_world(bs.wo))
        depth = dr.select(surface, depth + 1, depth)
        prev[surface] = si
        prev_pdf = dr.select(surface, bs.pdf, prev_pdf)
        specular = dr.select(surface, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta), specular)
        in_tet = scatter
        active &= scatter | surface
    alpha = dr.select(seen, 1.0, 0.0)
    if dr.hint(primal, mode="scalar"):
        return L, valid, alpha, L
    return (δL if mode == dr.ADMode.Backward else dL), valid, alpha, L
