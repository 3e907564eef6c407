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

from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.render.buffers import TetGroup
from mi_tetvr.render.cursor import (Cursor, Entry, Piece, Pieces, Span, WalkSettings, entry_of,
                                    traverse, traverse_merged)
from mi_tetvr.render.geometry import RayFrame, crossing_at, face_crossing
from mi_tetvr.render.linear import TetFrame
from mi_tetvr.render.pytree import tree_select, weighted_sum
from mi_tetvr.render.segment import clip_segment

#: A walk for transmittance stops at this optical depth (T < 1e-13).
TAU_STOP = 30.0


def solve_depth(s0: mi.Float, s1: mi.Float, length: mi.Float, r: mi.Float) -> mi.Float:
    """The distance ``x`` in ``[0, length]`` at which a piece whose
    extinction goes linearly from ``s0`` to ``s1`` reaches optical depth
    ``r``: the root of ``s0 x + (s1 - s0) x^2 / (2 length) = r`` (in the
    form without cancellation, ``2 r / (s0 + sqrt(s0^2 + 2 k r))``)."""
    k = (s1 - s0) * dr.rcp(dr.select(length > 0, length, 1.0))
    disc = dr.maximum(s0 * s0 + 2.0 * k * r, 0.0)
    den = s0 + dr.safe_sqrt(disc)
    x = dr.select(den > 0, 2.0 * r * dr.rcp(dr.select(den > 0, den, 1.0)), length)
    return dr.clip(x, 0.0, length)


class Flight:
    """What a walk along a ray found (:func:`flight`).

    tau : the optical depth walked (to the collision, or to the end).
    hit : whether it reached the target depth (a collision).
    t, tet, s : the collision's ray parameter, tet and the extinction
        there (the other attributes: :func:`attributes_at`).
    mesh : where meshes overlap, the one the collision is in (else 0).
    dtau : (forward mode) the walked depth's tangent, else 0.
    """
    DRJIT_STRUCT = {"tau": mi.Float, "hit": mi.Bool, "t": mi.Float, "tet": mi.UInt32,
                    "s": mi.Float, "mesh": mi.UInt32, "dtau": mi.Float}

    def __init__(self, tau: mi.Float | None = None, hit: mi.Bool | None = None,
                 t: mi.Float | None = None, tet: mi.UInt32 | None = None,
                 s: mi.Float | None = None, mesh: mi.UInt32 | None = None,
                 dtau: mi.Float | None = None) -> None:
        self.tau, self.hit, self.t, self.tet, self.s = tau, hit, t, tet, s
        self.mesh, self.dtau = mesh, dtau


def extinction(params: Any, i: mi.UInt32, active: bool | mi.Bool = True,
               reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> mi.Float:
    """The extinction of vertex ``i`` (every scattering and emission model's
    ``opacity``): all that a free flight reads per vertex. ``reduce``: the
    scatter strategy of the gather's derivative."""
    return dr.gather(mi.Float, params.opacity, i, active, mode=reduce)


class Depth:
    """The cursor's client that adds up the optical depth along rays through
    the meshes of ``ts`` until it reaches ``target`` (a collision), reading
    only the extinction (:class:`Flight` is its state).

    ``grad`` (a derivative pass): ``(mode, seed)``; backward mode propagates
    ``seed * tau_walked`` into the parameters (through ``ts_ad``, the buffers
    attached to the AD graph), forward mode adds up the tangent of the
    walked depth (``dtau``)."""
    label = "tetpath_depth"
    cuts = False

    def __init__(self, ts: TetGroup, ts_ad: TetGroup, target: mi.Float,
                 grad: tuple[dr.ADMode, mi.Float] | None, reduce: dr.ReduceMode) -> None:
        self.ts, self.ts_ad, self.params, self.target = ts, ts_ad, ts.params, target
        self.grad, self.reduce = grad, reduce
        self.geometric = False
        if grad is not None:
            with dr.resume_grad():
                self.geometric = dr.grad_enabled(ts_ad.buf.positions)

    def gather(self, i: mi.UInt32, active: bool | mi.Bool) -> mi.Float:
        return extinction(self.params, i, active)

    def begin(self, acc: Flight, cur: Cursor, fr: RayFrame, active: mi.Bool) -> Flight:
        return acc

    def end(self, acc: Flight, cur: Cursor, stay: mi.Bool, walked: mi.Bool,
            fr: RayFrame) -> Flight:
        return acc

    def alive(self, acc: Flight) -> mi.Bool:
        return ~acc.hit & (acc.tau < TAU_STOP)

    def piece(self, acc: Flight, p: Piece, span: Span, fr: RayFrame,
              active: mi.Bool) -> tuple[Flight, mi.Bool]:
        t, a, t_out, a_out = p.cur.t, p.cur.a, p.t1, p.a1
        length, a0, a1 = clip_segment(t, a, t_out, a_out, span.begin, span.end)
        t0 = dr.clip(t, span.begin, span.end)
        tau_seg = length * (a0 + a1) * 0.5
        r = self.target - acc.tau
        here = active & (tau_seg >= r)
        x = solve_depth(a0, a1, length, r)
        frac = dr.select(length > 0, x * dr.rcp(dr.select(length > 0, length, 1.0)), 0.0)
        dtau = acc.dtau
        if self.grad is not None:
            piece = self._depth(p, Span(span.begin, dr.select(here, t0 + x, span.end)), fr,
                                active)
            dtau = _propagate(self.grad, piece, dtau, active)
        tau = dr.select(here, self.target, acc.tau + tau_seg)
        out = Flight(tau, acc.hit | here, dr.select(here, t0 + x, acc.t),
                     dr.select(here, p.cur.tet, acc.tet),
                     dr.select(here, dr.lerp(a0, a1, frac), acc.s), acc.mesh, dtau)
        return out, ~here & (tau < TAU_STOP)

    def _depth(self, p, span: Span, fr: RayFrame, active):
        """The optical depth of the piece ``p`` over ``span``, attached to
        the parameters' AD graph (the crossings computed again from the
        attached buffers where vertices move, else at the walk's own ray
        parameters with attached attributes)."""
        ts_ad, reduce, st = self.ts_ad, self.reduce, p.st
        with dr.resume_grad():
            if self.geometric:
                t0, w0 = face_crossing(ts_ad.buf, st.entry, fr, active, reduce)
                t1, w1 = face_crossing(ts_ad.buf, st.exit, fr, active, reduce)
            else:
                t0, t1 = p.cur.t, p.t1
                w0, w1 = crossing_at(p.cur.carry[0], p.cur.carry[2])[1], st.w
            s0 = weighted_sum(w0, [extinction(ts_ad.params, i, active, reduce)
                                   for i in st.entry])
            s1 = weighted_sum(w1, [extinction(ts_ad.params, i, active, reduce)
                                   for i in st.exit])
            length, b0, b1 = clip_segment(t0, s0, t1, s1, span.begin, span.end)
            return length * (b0 + b1) * 0.5


def _propagate(grad, depth, dtau, active):
    """A derivative pass's use of a walked ``depth`` (attached to the AD
    graph): backward mode propagates ``seed * depth`` into the parameters,
    forward mode returns ``dtau`` plus its tangent (``grad = (mode, seed)``)."""
    mode, seed = grad
    flags = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad
    with dr.resume_grad():
        if mode == dr.ADMode.Backward:
            dr.backward_from(dr.select(active, seed, 0.0) * depth, flags=flags)
            return dtau
        return dtau + dr.select(active, dr.forward_to(depth, flags=flags), 0.0)


class MergedDepth:
    """:class:`Depth` over meshes that overlap in space
    (:func:`~mi_tetvr.render.cursor.traverse_merged`): extinctions add, so on
    each piece the summed extinction is linear and the collision is found as
    in one mesh. The collision is in mesh ``k`` with probability ``s_k /
    s`` there (``pick``, a uniform number): the free-flight density ``s
    e^{-tau}`` times it is mesh ``k``'s own ``s_k e^{-tau}``, so the path
    tracer's collision weights stay those of one medium. Derivatives w.r.t.
    the media, not vertex positions (:func:`check_derivatives`)."""
    label = "tetpath_merged"
    boundary_terms = False

    def __init__(self, meshes: list, target: mi.Float, grad: tuple[dr.ADMode, mi.Float] | None,
                 reduce: dr.ReduceMode, pick: mi.Float) -> None:
        self.members = [Depth(ts, ts_ad, target, grad, reduce) for ts, ts_ad in meshes]
        self.target, self.grad, self.reduce, self.pick = target, grad, reduce, pick

    def piece(self, acc: Flight, pc: Pieces, fr: RayFrame,
              active: mi.Bool) -> tuple[Flight, mi.Bool]:
        K = len(self.members)
        parts = pc.parts
        s0 = sum((dr.select(pc.inside[k], parts[k].cur.a, 0.0) for k in range(K)),
                 mi.Float(0.0))
        s1 = sum((dr.select(pc.inside[k], parts[k].a1, 0.0) for k in range(K)), mi.Float(0.0))
        length = pc.length
        tau_seg = length * (s0 + s1) * 0.5
        r = self.target - acc.tau
        here = active & (tau_seg >= r)
        x = solve_depth(s0, s1, length, r)
        frac = dr.select(length > 0, x * dr.rcp(dr.select(length > 0, length, 1.0)), 0.0)
        # The mesh it collides in, with probability s_k / s (the last inside
        # mesh where round-off leaves the pick past the sum).
        s_k = [dr.select(pc.inside[k], dr.lerp(parts[k].cur.a, parts[k].a1, frac), 0.0)
               for k in range(K)]
        u = self.pick * sum(s_k, mi.Float(0.0))
        cum, found = mi.Float(0.0), mi.Bool(False)
        mesh, tet, s = mi.UInt32(0), mi.UInt32(0), mi.Float(0.0)
        for k in range(K):
            cum = cum + s_k[k]
            take = ~found & pc.inside[k]
            mesh = dr.select(take, k, mesh)
            tet = dr.select(take, parts[k].cur.tet, tet)
            s = dr.select(take, s_k[k], s)
            found |= take & (u < cum)
        dtau = acc.dtau
        if self.grad is not None:
            stop = dr.select(here, pc.t0 + x, pc.t1)
            dtau = _propagate(self.grad, self._depth(pc, stop, active), dtau, active)
        tau = dr.select(here, self.target, acc.tau + tau_seg)
        out = Flight(tau, acc.hit | here, dr.select(here, pc.t0 + x, acc.t),
                     dr.select(here, tet, acc.tet), dr.select(here, s, acc.s),
                     dr.select(here, mesh, acc.mesh), dtau)
        return out, ~here & (tau < TAU_STOP)

    def _depth(self, pc, stop, active):
        """The optical depth of the piece from ``pc.t0`` to ``stop``, attached
        to the AD graph: each mesh's extinction at the ends, blended from its
        tet's entry and exit crossings (fixed ray parameters)."""
        total = mi.Float(0.0)
        with dr.resume_grad():
            for k, m in enumerate(self.members):
                p = pc.parts[k]
                te, we, inv = entry_of(p)
                st, ids = p.st, tuple(c.i for c in p.cur.carry[0])
                act = active & pc.inside[k]
                ext = [extinction(m.ts_ad.params, i, act, self.reduce) for i in ids]
                s_e = weighted_sum(we, ext)
                s_x = weighted_sum(st.w, [extinction(m.ts_ad.params, i, act, self.reduce)
                                          for i in st.exit])
                a = dr.lerp(s_e, s_x, (pc.t0 - te) * inv)
                b = dr.lerp(s_e, s_x, (stop - te) * inv)
                total += dr.select(pc.inside[k], (stop - pc.t0) * (a + b) * 0.5, 0.0)
        return total


def check_derivatives(ps: PathInputs) -> None:
    """ValueError where a derivative pass would need what the walk does not
    differentiate: vertex positions of meshes that overlap in space."""
    if ps.apart is None:
        return
    with dr.resume_grad():
        moving = [ts_ad.shapes[0].id() or "tetmesh" for _, ts_ad in ps.meshes
                  if dr.grad_enabled(ts_ad.buf.positions)]
    if moving:
        raise ValueError(f"tetpath: meshes that overlap in space have derivatives w.r.t. their "
                         f"media, not w.r.t. their vertex positions ({', '.join(moving)}); "
                         f"disable the gradients of their vertex_positions")


def flight(ps: PathInputs, ray: mi.Ray3f, target: float | mi.Float, entry: Entry,
           active: bool | mi.Bool, grad: tuple[dr.ADMode, mi.Float] | None = None,
           pick: mi.Float | None = None) -> Flight:
    """Walk a ray (from ``ray.o`` along the normalized ``ray.d`` up to
    ``ray.maxt``) through the scattering meshes of ``ps`` until the optical
    depth reaches ``target`` (``inf``: the transmittance ``exp(-tau)`` of
    the whole ray).

    The ray starts inside the tet ``entry.tet`` where ``entry.inside`` (a
    scattered ray), else wherever Mitsuba's ray tracer finds the meshes'
    boundary (entering, or leaving when ``o`` lies inside: the start tet is
    then found by walking back). Leaving a mesh, it traces again for
    re-entry. Meshes that overlap in space (``ps.apart``) are walked with a
    cursor each (every start located from the boundaries), and ``pick`` (a
    uniform number) chooses the mesh a collision is in (:class:`MergedDepth`).
    ``grad``: see :class:`Depth`.
    """
    fr = RayFrame.of(ray.o, ray.d)
    zero = mi.Float(0.0)
    acc = Flight(zero, mi.Bool(False), mi.Float(dr.inf), mi.UInt32(0), zero, mi.UInt32(0), zero)
    span = Span(zero, mi.Float(ray.maxt))
    target = mi.Float(target)
    if ps.apart is not None:
        client = MergedDepth(ps.meshes, target, grad, ps.settings.atomics,
                             mi.Float(0.5) if pick is None else mi.Float(pick))
        acc, _ = traverse_merged(ps.apart, client, fr, acc, span, ps.settings, active)
        return acc
    client = Depth(ps.ts, ps.ts_ad, target, grad, ps.settings.atomics)
    acc, _ = traverse(ps.boundaries, [client], fr, acc, span, ps.settings, active, entry)
    return acc


def attributes_at(ts_ad: TetGroup, tet: mi.UInt32, p: mi.Point3f, active: bool | mi.Bool = True,
                  reduce: dr.ReduceMode = dr.ReduceMode.Auto) -> Any:
    """The model's attributes at point ``p`` of ``tet`` (barycentric in the
    tet), attached to the parameters' AD graph: the field at a sampled point,
    moving with the vertices (``reduce``: the gathers' scatter strategy)."""
    with dr.resume_grad():
        frame = TetFrame(ts_ad.buf, tet, active, reduce)
        w = frame.weights(p)
        return weighted_sum(w, [ts_ad.model.gather(ts_ad.params, i, active, reduce)
                                for i in frame.ids])


@dataclass
class PathInputs:
    """What the path tracer reads for one scene."""
    scene: mi.Scene              # the user's scene (its emitters)
    ts: TetGroup                 # the scattering meshes, detached (the walk reads these)
    ts_ad: TetGroup              # the same, attached to the parameters' AD graph
    boundaries: mi.Scene         # the meshes' boundaries (the walk traces these)
    surfaces: mi.Scene           # the other shapes (an empty scene without any)
    phase: mi.PhaseFunction      # the meshes' phase function
    settings: WalkSettings
    max_depth: int               # as Mitsuba's ``volpath``
    rr_depth: int
    #: Meshes that overlap in space: ``(ts, ts_ad)`` of each, and a scene of
    #: each one's boundary alone (``ts``, ``ts_ad``, ``boundaries`` unused).
    meshes: list = None
    apart: list = None


def _collision_attributes(ps: PathInputs, fl: Flight, p, active, attached: bool):
    """The medium's attributes at a collision ``p`` (:func:`attributes_at`),
    in the mesh it is in (``fl.mesh`` where meshes overlap); ``attached``: of
    the buffers attached to the AD graph."""
    if ps.apart is None:
        ts = ps.ts_ad if attached else ps.ts
        return attributes_at(ts, fl.tet, p, active, ps.settings.atomics if attached
                             else dr.ReduceMode.Auto)
    out = None
    for k, (ts, ts_ad) in enumerate(ps.meshes):
        mine = active & (fl.mesh == k)
        a = attributes_at(ts_ad if attached else ts, fl.tet, p, mine,
                          ps.settings.atomics if attached else dr.ReduceMode.Auto)
        out = a if out is None else tree_select(mine, a, out)
    return out


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
def sample(mode: dr.ADMode, ps: PathInputs, sampler: mi.Sampler, ray: mi.Ray3f,
           δL: mi.Spectrum | None, state_in: mi.Spectrum | None,
           active: bool | mi.Bool) -> tuple[mi.Spectrum, mi.Bool, mi.Float, mi.Spectrum]:
    """Mitsuba's ``sample`` of the path tracer (see the module docstring):
    ``(L or its derivative, valid, alpha, L)``; ``alpha`` is 1 where the
    camera ray's first segment met the medium or a surface (its mean over a
    pixel's samples is the coverage: ``1 - T`` through the volume alone).
    ``mode``: ``dr.ADMode``; the derivative modes take the primal radiance
    ``state_in`` and replay the same paths (``sampler`` seeded as in the
    primal pass)."""
    primal = mode == dr.ADMode.Primal
    grad = None if primal else _Grad(mode)
    scene = ps.scene
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
            walk_grad = (mode, -dr.sum(δL * L))
        pick = None
        if dr.hint(ps.apart is not None, mode="scalar"):
            pick = sampler.next_1d(active)    # (the mesh a collision is in)
        to_surface = mi.Ray3f(ray)
        to_surface.maxt = t_surf
        fl = flight(ps, to_surface, target, Entry(tet=tet, inside=in_tet), active, walk_grad,
                    pick)
        dtau = fl.dtau
        collided = active & fl.hit
        p = ray.o + fl.t * ray.d
        a = _collision_attributes(ps, fl, p, collided, False)

        # ---- a collision: emission, then absorption or scattering ----
        emit = collided & (depth < ps.max_depth)
        Le = dr.select(emit, β * a.c, 0.0)
        if dr.hint(not primal, mode="scalar"):
            dL = dL - dr.select(active, L * dtau, 0.0)

            # The collision's three terms in one pass over the field at p
            # (a second pass would find the interpolation's edges cleared):
            # the extinction's density, the emission, the albedo's weight.
            def collision_term():
                a_ad = _collision_attributes(ps, fl, p, collided, True)
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
        shadow_entry = Entry(tet=fl.tet, inside=scatter)
        sh = flight(ps, shadow, dr.inf, shadow_entry, nee)
        ph_val, ph_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, scatter & nee)
        bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), nee_surface & nee)
        f = dr.select(scatter, mi.Spectrum(ph_val), bsdf_val)
        dir_pdf = dr.select(ds.delta, 0.0, dr.select(scatter, ph_pdf, bsdf_pdf))
        C = β * f * mis_weight(ds.pdf, dir_pdf) * em_val * dr.exp(-sh.tau)
        C = dr.select(nee, C, 0.0)
        L = L + C if primal else L - C
        if dr.hint(not primal, mode="scalar"):
            dtau_sh = flight(ps, shadow, dr.inf, shadow_entry, nee,
                             (mode, -dr.sum(δL * C))).dtau
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
