"""The ``tetvr`` integrator: emission-absorption volume rendering of ``tetmesh``
shapes by walking the tet adjacency.

.. pluginparameters::

 * - n_sub
   - |int|
   - Sub-intervals of the one approximated quantity of a tet segment, its mean
     transmittance (colors and the transmittance are exact; constant extinction at each
     sub-interval's midpoint as in DiffTetVR Alg. 1, extrapolated from n_sub / 2 for even
     n_sub: the error falls as 1/n_sub^4). See :mod:`mi_tetvr.render.segment`. (Default: 4)
 * - min_transmittance
   - |float|
   - Early ray termination once the transmittance falls below this. (Default: 1e-4)
 * - max_steps
   - |int|
   - Safety bound on tets crossed per walk. (Default: 100000)
 * - retrace_epsilon
   - |float|
   - Offset, relative to the scene's bounding-box diagonal, past a boundary
     face before tracing for re-entry. (Default: 1e-5)
 * - reduce_mode
   - |string|
   - How gradients of shared vertices are scatter-added in the derivative
     modes (one packet of a vertex's gradients per vertex a ray leaves
     behind): ``auto`` (on the LLVM backend into per-thread copies, without
     atomics, where they take at most 1 GiB, else plain atomics; Dr.Jit's
     own choice on CUDA), ``expand`` (per-thread copies), ``local``
     (pre-reduce within a SIMD packet / warp) or ``direct`` (plain atomics).
     See ``dr.ReduceMode`` and ``benchmarks/bench_backward.py``.
     (Default: ``auto``)
 * - alpha
   - |bool|
   - Add the coverage as an AOV channel named ``alpha``: 1 - T, and 1 where
     a surface is hit. (Default: true)
 * - kept_primals
   - |int|
   - Primal renders kept for the derivative passes that differentiate them (several views
     rendered before one ``dr.backward``); past it the oldest are dropped and their
     derivative pass renders the primal again, with a warning. See
     :mod:`mi_tetvr.render.replay`. (Default: 16)
 * - clip_origin, clip_normal
   - |point|, |vector|
   - A plane that cuts the volume: what lies on the side the normal points to
     is cut away (:mod:`mi_tetvr.render.clipping`; surfaces are not cut).
     (Default: none)
 * - clip_min, clip_max
   - |point|
   - A box that cuts the volume: what lies outside it is cut away. (Default: none)
 * - overlay
   - |integrator|
   - A ``tetproj`` integrator (named ``overlay``) in mode ``slice`` or
     ``iso``: its surfaces are drawn inside the volume, opaque or
     translucent (its ``opacity``, ``layers``), as ParaView shows a volume
     with a slice or a contour (:mod:`mi_tetvr.render.layers`). The scene's
     one tetmesh must be post-classified (a scalar and a transfer function).
     Derivatives as without it, and through the surfaces' colors and depths
     (not w.r.t. a differentiable camera). (Default: none)
 * - surfaces
   - |integrator|
   - Child integrator (named ``surfaces``) that renders the scene's other
     shapes, seen through the volume in front of them; it sees a scene of
     the surfaces and emitters without the tet meshes. Differentiating the
     surfaces' parameters needs one of Mitsuba's ``ADIntegrator``s (``prb``,
     ``prb_basic``, ``direct_projective``, ...). (Default: ``prb``)

Derivatives: ``mi.render`` with parameters, ``dr.backward`` and ``dr.forward``
reach ``<id>.vertex_color``, ``<id>.vertex_opacity`` and ``<id>.vertex_positions``
(post-classified: ``vertex_scalar``, ``tf_color``, ``tf_opacity``; the ``alpha``
AOV's gradient flows too), and ``dr.backward`` also the sensor's ``to_world``
(:func:`mi_tetvr.camera.orbit_to_world`); through a
differentiable nested integrator, the surfaces' parameters too (their
radiance's adjoint is ``T * δL``). The
adjoint re-walks the rays and records nothing (see
:mod:`mi_tetvr.render.walk`); the silhouettes of the mesh and of the surfaces
(which pixels they cover) have no boundary term.

The pixel value is ``C + T * L_surface`` where ``C`` is the emission
accumulated up to the first hit of another shape (a surface), ``T`` the
transmittance there and ``L_surface`` the nested integrator's radiance along
the ray (the environment where nothing is hit; in a scene of tet meshes
alone, the environment emitter's value, black without one). The
environment's parameters (an ``envmap``'s ``data``) are differentiable too.
Tet meshes of any optical models may share a scene; meshes that overlap in
space are integrated as one medium, their extinctions and emissions added
(:mod:`mi_tetvr.render.surfaces`, :mod:`mi_tetvr.render.merged`).
``sample()`` keeps the ``RBIntegrator`` contract and can be called on any
rays (with a sampler where the scene has surfaces).

.. code-block:: python

    'integrator': {
        'type': 'tetvr',
        'n_sub': 4,
        'surfaces': {'type': 'prb', 'max_depth': 6},
    }
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import drjit as dr
import mitsuba as mi

from mi_tetvr.plugins import constructor
from mi_tetvr.render.buffers import TetGroup, index_buffers, scene_tetmeshes
from mi_tetvr.render.clipping import Clip
from mi_tetvr.render.program import ProgramOptions, VolumeProgram, scaled_settings
from mi_tetvr.render.replay import CAPACITY, PrimalStates, derivative_seed
from mi_tetvr.render.surfaces import DEFAULT_SURFACES, NestedIntegrator, SceneParts
from mi_tetvr.render.cursor import WalkSettings

if TYPE_CHECKING:
    from mi_tetvr.distributed import Blocks

RBIntegrator = mi.ad.integrators.common.RBIntegrator


class TetVRIntegrator(RBIntegrator):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        n_sub = int(props.get("n_sub", 4))
        if not 1 <= n_sub <= 64:
            raise ValueError(f"tetvr: n_sub must be in [1, 64], got {n_sub}")
        t_min = float(props.get("min_transmittance", 1e-4))
        if not 0.0 <= t_min < 1.0:
            raise ValueError(f"tetvr: min_transmittance must be in [0, 1), got {t_min}")
        max_steps = int(props.get("max_steps", 100_000))
        if max_steps < 1:
            raise ValueError("tetvr: max_steps must be >= 1")
        self.retrace_epsilon = float(props.get("retrace_epsilon", 1e-5))
        modes = {"auto": None, "expand": dr.ReduceMode.Expand,
                 "local": dr.ReduceMode.Local, "direct": dr.ReduceMode.Direct}
        reduce = str(props.get("reduce_mode", "auto")).lower()
        if reduce not in modes:
            raise ValueError(f"tetvr: reduce_mode must be one of {sorted(modes)}, got {reduce!r}")
        self.n_sub = n_sub
        self.settings = WalkSettings(t_min, max_steps, reduce=modes[reduce])
        self.alpha = bool(props.get("alpha", True))
        self.clip = Clip.from_props(props)
        nested, self.overlay = None, None
        for name, obj in props.objects():
            if name == "surfaces":
                nested = obj
            elif name == "overlay":
                if not getattr(getattr(obj, "probes", None), "surfaces", False):
                    raise ValueError("tetvr: the overlay is a tetproj integrator in mode 'slice' "
                                     "or 'iso' (e.g. <integrator type=\"tetproj\" "
                                     "name=\"overlay\"> with <string name=\"mode\" "
                                     "value=\"iso\"/>)")
                self.overlay = obj
            else:
                raise ValueError(f"tetvr: unknown child {name!r} ({type(obj).__name__}); the "
                                 f"children are the integrator of the surfaces, named "
                                 f"'surfaces' (e.g. <integrator type=\"prb\" name=\"surfaces\"/>), "
                                 f"and a tetproj named 'overlay'")
        self.surfaces = NestedIntegrator(nested if nested is not None
                                         else mi.load_dict(DEFAULT_SURFACES))
        self.parts = SceneParts()
        self._index_cache = None
        #: The primal renders kept for their derivative passes (an explicit
        #: store: key, validity and lifetime in :mod:`mi_tetvr.render.replay`).
        self.kept_primals = PrimalStates(int(props.get("kept_primals", CAPACITY)))

    def traverse(self, callback: mi.TraversalCallback) -> None:
        if self.overlay is not None:
            # (its isovalues: overlay.iso)
            callback.put("overlay", self.overlay, mi.ParamFlags.Differentiable)

    def aov_names(self) -> list[str]:
        return ["alpha"] if self.alpha else []

    # What one pass fixes (see Pass): on the integrator itself, nothing.
    remote = None
    replayed = None
    recorder = None

    def program(self, scene: mi.Scene) -> VolumeProgram:
        """The ray program of ``scene`` (:mod:`mi_tetvr.render.program`): a
        view built per call from what the integrator and the scene's shapes
        keep (the split of the scene into parts, each mesh's buffers, the
        index buffers of its groups)."""
        return VolumeProgram(scene, ProgramOptions(
            self.parts, self.surfaces, self.settings_for(scene), self.n_sub, self.clip,
            self.overlay.probes if self.overlay is not None else None, self.index_buffers,
            self.remote))

    def with_medium(self, remote: Blocks) -> Pass:
        """This integrator rendering ``remote`` (a partitioned mesh's blocks,
        :mod:`mi_tetvr.distributed`) in place of the scene's tet meshes: an
        object with the integrator's ``render`` and ``render_backward``."""
        return Pass(self, remote=remote)

    def index_buffers(self, groups: list) -> list:
        """The index buffers of each group of shapes that one walk renders,
        kept while the groups hold the same shapes' buffers."""
        key = tuple(tuple(id(s.tet_buffers) for s in g) for g in groups)
        if self._index_cache is None or self._index_cache[0] != key:
            self._index_cache = (key, [index_buffers(g) for g in groups])
        return self._index_cache[1]

    def tet_groups(self, scene: mi.Scene) -> list:
        """The :class:`~mi_tetvr.render.buffers.TetGroup` of each group of
        tet meshes that one walk renders (:meth:`VolumeProgram.media`)."""
        return self.program(scene).media()

    def tet_group(self, scene: mi.Scene) -> TetGroup:
        """The one :class:`~mi_tetvr.render.buffers.TetGroup` of a scene whose
        tet meshes share one walk (see :meth:`tet_groups`)."""
        (ts,) = self.tet_groups(scene)
        return ts

    @staticmethod
    def differentiable_inputs(scene: mi.Scene) -> list:
        """The scene's arrays that the image depends on differentiably:
        vertex positions, the optical models' vertex buffers and the
        environment's parameters."""
        out = []
        for s in scene_tetmeshes(scene):
            out.append(s.vertex_positions_buffer())
            out += [s.attribute_buffer(name) for name, _ in s.optical_model.vertex_attributes]
            out += s.model_buffers()
        env = scene.environment()
        if env is not None:
            out += [v for _, v in mi.traverse(env).items() if dr.is_array_v(v)]
        return out

    # The derivative passes reuse the primal render's rays and per-ray
    # results instead of rendering it again (see mi_tetvr.render.replay):
    # Mitsuba's passes run on a Pass that records or replays them.

    def render(self, scene: mi.Scene, sensor: int | mi.Sensor = 0, seed: int | mi.UInt32 = 0,
               spp: int = 0, develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        with dr.resume_grad():
            inputs = self.differentiable_inputs(scene)
            # (with surfaces, the nested integrator samples paths: the derivative
            # pass renders its own primal with its own seed, as Mitsuba does)
            tracked = (any(dr.grad_enabled(x) for x in inputs)
                       and self.program(scene).keeps_primal())
        run = self
        if tracked:
            key = PrimalStates.key(scene, sensor, derivative_seed(seed), spp)
            kept = [dr.detach(x) for x in inputs]
            run = Pass(self, self.remote, recorder=lambda state: self.kept_primals.put(
                key, int(seed), state, kept))
        return RBIntegrator.render(run, scene, sensor, seed, spp, develop, evaluate)

    def _derivative_pass(self, base, scene, params, sensor, seed, spp, *grad_in):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        kept = self.kept_primals.take(PrimalStates.key(scene, sensor, seed, spp),
                                      [dr.detach(x) for x in self.differentiable_inputs(scene)])
        if kept is None:
            return base(self, scene, params, *grad_in, sensor, seed, spp)
        primal_seed, state = kept
        return base(Pass(self, self.remote, replayed=state), scene, params, *grad_in, sensor,
                    primal_seed, spp)

    def render_backward(self, scene: mi.Scene, params: mi.SceneParameters | None,
                        grad_in: mi.TensorXf, sensor: int | mi.Sensor = 0,
                        seed: int | mi.UInt32 = 0, spp: int = 0) -> None:
        return self._derivative_pass(RBIntegrator.render_backward, scene, params, sensor, seed,
                                     spp, grad_in)

    def render_forward(self, scene: mi.Scene, params: mi.SceneParameters | None,
                       sensor: int | mi.Sensor = 0, seed: int | mi.UInt32 = 0,
                       spp: int = 0) -> mi.TensorXf:
        return self._derivative_pass(RBIntegrator.render_forward, scene, params, sensor, seed,
                                     spp)

    def sample_rays(self, scene: mi.Scene, sensor: mi.Sensor,
                    sampler: mi.Sampler) -> tuple[mi.RayDifferential3f, mi.Float, mi.Vector2f]:
        # The sensor weight is a Spectrum; Mitsuba's render_backward and
        # render_forward multiply the AOVs by it, which makes the alpha AOV a
        # Color3f that the image block rejects. RGB sensors weight the three
        # channels equally, so keep one of them.
        # The rays keep their AD graph (to a differentiable sensor) in the
        # derivative passes, which run with AD suspended.
        with dr.resume_grad():
            ray, weight, pos = super().sample_rays(scene, sensor, sampler)
        return ray, mi.Float(dr.detach(weight)[0]), dr.detach(pos)

    def settings_for(self, scene: mi.Scene) -> WalkSettings:
        """Walk settings with the re-trace offset scaled to the scene."""
        return scaled_settings(self.settings, self.retrace_epsilon, scene)

    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL: mi.Spectrum | None, state_in: tuple | None, active: mi.Bool,
               **kwargs: Any) -> tuple[mi.Color3f, mi.Bool, list[mi.Float], tuple | None]:
        """Mitsuba's ``sample``: a function of its arguments (a :class:`Pass`
        fixes what it replays or records)."""
        program = self.program(scene)
        if mode == dr.ADMode.Primal:
            if self.replayed is not None:
                # (the derivative pass of a kept primal: its pixel values)
                L, T = self.replayed
                hit, state = mi.Bool(False), (L, T, None, None, None)
            else:
                L, T, hit, state = program.primal(ray, sampler, active)
                if self.recorder is not None:
                    self.recorder((L, T))
            alpha = dr.select(hit, 1.0, 1.0 - T)
            return L, mi.Bool(True), [alpha] if self.alpha else [], state
        if state_in is None:
            raise ValueError("tetvr: the derivative modes need the primal pass's state_in")
        δaovs = kwargs.get("δaovs", None)
        δalpha = mi.Float(δaovs[0]) if (self.alpha and δaovs) else mi.Float(0.0)
        out = program.derivative(mode, ray, sampler, δL, δalpha, state_in, active)
        if out is None:
            return mi.Color3f(0.0), mi.Bool(True), [], None
        dL, dalpha = out
        return dL, mi.Bool(True), [dalpha] if self.alpha else [], None

    def to_string(self) -> str:
        s = self.settings
        return (f"TetVRIntegrator[n_sub={self.n_sub}, min_transmittance={s.t_min}, "
                f"max_steps={s.max_steps}, surfaces={self.surfaces!r}]")




class Pass:
    """One pass of a ``tetvr`` integrator as Mitsuba's ``RBIntegrator`` runs
    it (``render``, ``render_forward``, ``render_backward``): the integrator
    itself (every other attribute is the integrator's), with what this pass
    fixes: the medium rendered in place of the scene's tet meshes
    (``remote``), the kept primal per-ray state whose pixels the primal
    pass returns (``replayed``), or where the primal pass hands its per-ray
    state to be kept (``recorder``). The integrator keeps none of these
    between calls."""

    def __init__(self, integrator: TetVRIntegrator, remote: Blocks | None = None,
                 replayed: tuple[mi.Color3f, mi.Float] | None = None,
                 recorder: Callable[[tuple[mi.Color3f, mi.Float]], None] | None = None) -> None:
        self.integrator = integrator
        self.remote, self.replayed, self.recorder = remote, replayed, recorder

    def __getattr__(self, name):
        return getattr(self.integrator, name)

    sample = TetVRIntegrator.sample
    program = TetVRIntegrator.program
    render = TetVRIntegrator.render
    render_backward = TetVRIntegrator.render_backward
    render_forward = TetVRIntegrator.render_forward
    _derivative_pass = TetVRIntegrator._derivative_pass


mi.register_integrator("tetvr", constructor(TetVRIntegrator, "tetvr"))
