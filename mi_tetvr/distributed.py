"""Beyond one machine: a partitioned mesh rendered and differentiated by Ray
workers, composited sort-last, exact to the pixel.

A ``.pvtu`` written by :func:`mi_tetvr.mesh.partition.partition_mesh` (``mi-tetvr
partition``) tiles space with k-d boxes, one piece per box. Each worker (a Ray
actor, :class:`BlockWorker`) reads only its blocks' pieces and renders the
part of each ray inside a block's box: the emission ``C_k`` and transmittance
``T_k`` of that interval (the walk integrates a clipped interval exactly). The
driver keeps the scene's camera, surfaces and lights and the ``tetvr``
integrator: Mitsuba's own ``render`` samples the rays, and where the
integrator would walk the mesh it hands the rays to the workers instead
(:class:`Blocks`), then composites the blocks front to back in the order each
ray enters their boxes (the boxes are convex and disjoint, so the order is
per ray and exact)::

    C = sum_k (prod_{j<k} T_j) C_k        T = prod_k T_k

and sees the surfaces and the environment through ``T`` as it does for one
mesh. The image is the whole mesh's, to float rounding.

The adjoint of the compositing is closed form: block ``k``'s seed is ``δL
prod_{j<k} T_j``, the radiance behind it the composite of the blocks after it
and of the background; each worker runs its block's adjoint walk and returns
the gradients of its vertices by their global ids, summed over the copies
of a vertex that several blocks share (:meth:`PartitionedMesh.backward`).

Ray starts a local cluster of processes by default; ``address`` (or
``RAY_ADDRESS``) joins a running one (``ray start --head`` on one machine,
``ray start --address HEAD:6379`` on the others), where every machine sees the
``.pvtu`` and its pieces at the same path.
"""
from __future__ import annotations

import os
import resource
from pathlib import Path

import numpy as np

from mi_tetvr.cluster import connect
from mi_tetvr.extras import needs
from mi_tetvr.mesh.partition import Partition, read_partition, read_piece

#: Vertex parameters of a block's shape, by their ``mi.traverse`` names.
VERTEX_PARAMS = ("vertex_color", "vertex_opacity", "vertex_positions", "vertex_scalar")
#: What a fit over blocks optimizes (values at the vertices, not their positions).
FITTED_PARAMS = ("vertex_color", "vertex_opacity", "vertex_scalar")
#: Parameters every block holds whole (the transfer function's texels).
SHARED_PARAMS = ("tf_color", "tf_opacity")


def floats(a):
    """A ``mi.Float`` of a 1-D ``a``, or a list of them (the columns of ``a``
    (n, k)), from 64-byte aligned memory: Dr.Jit wraps numpy's memory as it
    lies, and its alignment enters the kernel's code (each new array compiled
    the walk again)."""
    import mitsuba as mi
    a = np.asarray(a, np.float32)
    if a.ndim == 1:
        buf = np.empty(a.size + 16, np.float32)
        start = (-buf.ctypes.data % 64) // 4              # (64-byte aligned)
        out = buf[start:start + a.size]
        out[:] = a
        return mi.Float(out)
    return [floats(a[:, i]) for i in range(a.shape[1])]


def block_intervals(o, d, t0, t1, boxes):
    """``(N, B, 2)`` the part ``[a, b]`` of each ray ``o + t d`` (``t0 <= t <=
    t1``) inside each box (``boxes`` (B, 2, 3), infinite where open); empty
    where ``b <= a``. A ray parallel to a face of a box is in it where ``lo <=
    o < hi``: a ray along the plane between two blocks is in one of them."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    lo, hi = boxes[:, 0][None], boxes[:, 1][None]             # (1, B, 3)
    o3, d3 = o[:, None], d[:, None]                              # (N, 1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - o3) / d3, (hi - o3) / d3
    parallel = d3 == 0.0
    near = np.where(parallel, -np.inf, np.minimum(ta, tb))
    far = np.where(parallel, np.where((o3 >= lo) & (o3 < hi), np.inf, -np.inf),
                   np.maximum(ta, tb))
    a = np.maximum(np.asarray(t0, np.float64)[:, None], near.max(2))
    b = np.minimum(np.asarray(t1, np.float64)[:, None], far.min(2))
    return np.stack([a, b], -1)


class BlockWorker:
    """A worker's blocks (a Ray actor): each block's piece as a ``tetmesh`` in
    a scene of its own, rendered over given ray intervals, and its adjoint.

    Parameters
    ----------
    pvtu : str
        The partitioned mesh (each worker reads its pieces from it).
    blocks : list of int
        The blocks this worker holds.
    shape : dict
        ``tetmesh`` properties of every block (``transfer_function``,
        ``opacity_scale``, ``color_attribute``, ...); a transfer function's
        ``value_min``/``value_max`` default to the whole mesh's range.
    variant : str
        The Mitsuba variant.
    threads : int or None
        Dr.Jit's CPU threads in this worker.
    """

    def __init__(self, pvtu, blocks, shape, variant, threads=None):
        import drjit as dr
        import mitsuba as mi
        mi.set_variant(variant)
        import mi_tetvr
        mi_tetvr.register()
        if threads:
            dr.set_thread_count(int(threads))
        self.part = read_partition(pvtu)
        self.shape = dict(shape or {})
        self.blocks = {k: self._load(k) for k in blocks}
        self.integrators = {}

    def _load(self, k):
        """``(scene, global point ids, piece diagonal)`` of block ``k``: a
        scene of its piece alone."""
        import mitsuba as mi

        import mi_tetvr
        from mi_tetvr.mesh.io import choose_scalar
        vertices, tets, pd, cd, ids = read_piece(self.part, k)
        props = dict(self.shape)
        path = self.part.piece_path(k)
        if "transfer_function" in props or "tf_color" in props:
            name = choose_scalar(pd, props.pop("scalar_attribute", None), str(path), cd,
                                 cells=True)
            rng = (self.part.point_ranges.get(name) or self.part.cell_ranges.get(name))
            props.setdefault("value_min", rng[0])
            props.setdefault("value_max", rng[1])
            values = {"scalar": pd[name]} if name in pd else {"cell_scalar": cd[name]}
            entry = mi_tetvr.tetmesh_dict(vertices, tets, **values, **props)
        else:
            color = pd.get(props.pop("color_attribute", "color"))
            opacity = pd.get(props.pop("opacity_attribute", "opacity"))
            if "sh" in pd:       # view-dependent colors, in the place of any color
                color = None
                props.setdefault("sh", pd["sh"])
            entry = mi_tetvr.tetmesh_dict(vertices, tets, color, opacity, **props)
        diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        del vertices, tets, pd, cd
        return mi.load_dict({"type": "scene", "block": entry}), ids, diag

    def write(self, k, path):
        """Block ``k``'s piece with its present colors and opacities (as point
        data ``color`` and ``opacity``), written to ``path``."""
        import meshio

        from mi_tetvr.mesh.io import read_mesh_file
        m = read_mesh_file(self.part.piece_path(k))
        for name, array in self.arrays(k, ["vertex_color", "vertex_opacity"]).items():
            m.point_data[{"vertex_color": "color", "vertex_opacity": "opacity"}[name]] = \
                array.astype(np.float64).reshape(len(m.points), -1).squeeze()
        meshio.write(path, m)
        return True

    def _program(self, k, settings):
        """``(scene, ray program)`` of block ``k`` under the driver's walk
        ``settings`` (its ``tetvr`` kept while they stay the same)."""
        import mitsuba as mi
        scene, _, diag = self.blocks[k]
        key = (k, tuple(sorted(settings.items())))
        if key not in self.integrators:
            s = dict(settings)
            # the driver's re-trace offset (absolute) in this block's units
            s["retrace_epsilon"] = s.pop("retrace_offset") / max(diag, 1e-30)
            self.integrators = {kk: v for kk, v in self.integrators.items() if kk[0] != k}
            self.integrators[key] = mi.load_dict({"type": "tetvr", "alpha": False, **s})
        return scene, self.integrators[key].program(scene)

    @staticmethod
    def _rays(o, d, t0, t1):
        import mitsuba as mi
        ray = mi.Ray3f(mi.Point3f(*floats(o)), mi.Vector3f(*floats(d)))
        ray.maxt = floats(t1)
        start = floats(t0)
        return ray, start, ray.maxt > start

    def trace(self, k, settings, o, d, t0, t1):
        """``(C (n, 3), T (n,))`` of block ``k`` along the rays ``o + t d``
        over ``[t0, t1]``."""
        import drjit as dr
        _, program = self._program(k, settings)
        with dr.suspend_grad():
            ray, start, active = self._rays(o, d, t0, t1)
            # (entered where the ray meets the piece, not walked back from its far side)
            C, T = program.volume(program.media(), ray, start, active, t_enter=0.0)
            dr.eval(C, T)
        return np.array(C, np.float32).reshape(3, -1).T.copy(), np.array(T, np.float32)

    def backward(self, k, settings, o, d, t0, t1, L_pix, T_fin, dL, dalpha):
        """Block ``k``'s adjoint walk over the rays (its pixel value ``L_pix``
        with what lies behind it, its transmittance ``T_fin``, the seeds ``dL``
        and ``dalpha``): ``{name: gradient}`` of its parameters (per vertex
        for :data:`VERTEX_PARAMS`, in the piece's order)."""
        import drjit as dr
        import mitsuba as mi
        from mi_tetvr.render.adjoint import Adjoint, Derivative
        scene, program = self._program(k, settings)
        params = mi.traverse(scene)
        keys = [key for key in params.keys() if key.split(".", 1)[-1] in
                VERTEX_PARAMS + SHARED_PARAMS and dr.is_diff_v(params[key])]
        # (left enabled: enabling them again would rebuild the shape's buffers each call)
        off = [key for key in keys if not dr.grad_enabled(params[key])]
        for key in off:
            dr.enable_grad(params[key])
        if off:
            params.update()
        try:
            ray, start, active = self._rays(o, d, t0, t1)
            zero = mi.Vector3f(0.0)

            adj = Adjoint(mi.Color3f(*floats(L_pix)), floats(T_fin), mi.Color3f(*floats(dL)),
                          floats(dalpha), zero, zero)
            media_ad = program.media(differentiable=True)
            with dr.suspend_grad():
                program.walk([g.detached() for g in media_ad], ray, start, active,
                             (Derivative(dr.ADMode.Backward, media_ad), adj), t_enter=0.0)
            out = {key.split(".", 1)[-1]: np.array(dr.grad(params[key]), np.float32)
                   for key in keys}
        finally:
            for key in keys:
                dr.clear_grad(params[key])
        return out

    def point_ids(self, k):
        return self.blocks[k][1]

    def _params(self, k):
        import drjit as dr
        import mitsuba as mi
        params = mi.traverse(self.blocks[k][0])
        return params, {key.split(".", 1)[-1]: key for key in params.keys()
                        if dr.is_diff_v(params[key])}

    def optimizer(self, k, lr):
        """Adam (Mitsuba's) over block ``k``'s parameters named in ``lr``
        (``{name: learning rate}``)."""
        import mitsuba as mi
        params, keys = self._params(k)
        missing = sorted(set(lr) - set(keys))
        if missing:
            raise ValueError(f"block {k} has no parameters {missing} (it has {sorted(keys)})")
        opt = mi.ad.Adam(lr=1.0, params={keys[n]: params[keys[n]] for n in lr})
        opt.set_learning_rate({keys[n]: float(v) for n, v in lr.items()})
        self.optimizers = getattr(self, "optimizers", {})
        self.optimizers[k] = opt

    def apply(self, k, grads):
        """One Adam step of block ``k`` with the gradients ``{name: (n, c)}`` of
        its vertices (the whole mesh's, summed over the blocks that share a
        vertex: every copy of a vertex takes the same step)."""
        import drjit as dr
        params, keys = self._params(k)
        opt = self.optimizers[k]
        for name, g in grads.items():
            dr.set_grad(opt[keys[name]], floats(np.ravel(g)))
        opt.step()
        params.update(opt)
        dr.eval()
        return True

    def arrays(self, k, names):
        """Block ``k``'s parameters ``{name: (n, c)}`` (per vertex, the piece's order)."""
        params, keys = self._params(k)
        ids = self.blocks[k][1]
        return {n: np.array(params[keys[n]], np.float32).reshape(len(ids), -1) for n in names}

    def peak_memory(self):
        """This worker process's peak resident memory (bytes)."""
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    def pid(self):
        return os.getpid()


def walk_settings(integrator, scene, part: Partition):
    """The ``tetvr`` settings each block is rendered with: the driver's
    integrator's, its re-trace offset scaled to the whole scene (the
    driver's shapes and the partitioned mesh) as one process would."""
    lo, hi = np.array(scene.bbox().min), np.array(scene.bbox().max)
    if scene.bbox().valid():
        lo, hi = np.minimum(lo, part.bounds[0]), np.maximum(hi, part.bounds[1])
    else:
        lo, hi = part.bounds
    s = integrator.settings
    return {"n_sub": int(integrator.n_sub), "min_transmittance": float(s.t_min),
            "max_steps": int(s.max_steps),
            "retrace_offset": float(integrator.retrace_epsilon) * float(np.linalg.norm(hi - lo))}


def entry_order(iv):
    """(n, B) the blocks in the order each ray enters their boxes (``iv``
    (n, B, 2) its intervals in them; the ones it misses last)."""
    return np.argsort(np.where(iv[:, :, 1] > iv[:, :, 0], iv[:, :, 0], np.inf), 1,
                      kind="stable")


class Blocks:
    """The partitioned mesh as the driver's ray program sees it (its
    ``remote``): the rays' intervals in each block's box handed to the block's
    worker, the results composited front to back; the last primal pass's
    per-block results (the mesh's ``last``) serve the adjoint."""

    def __init__(self, mesh: "PartitionedMesh", settings, reuse=False):
        self.mesh, self.settings, self.reuse = mesh, settings, reuse
        self.grads = {}

    def _intervals(self, ray, t_start, active):
        import drjit as dr
        o = np.array(ray.o, np.float64).reshape(3, -1).T
        d = np.array(ray.d, np.float64).reshape(3, -1).T
        n = len(o)
        t0 = np.broadcast_to(np.array(dr.select(active, t_start, 0.0), np.float64), (n,))
        t1 = np.array(dr.select(active, ray.maxt, -1.0), np.float64)
        iv = block_intervals(o, d, t0, t1, self.mesh.boxes).astype(np.float32)
        return o.astype(np.float32), d.astype(np.float32), iv

    def primal(self, ray, t_start, active):
        import mitsuba as mi
        o, d, iv = self._intervals(ray, t_start, active)
        n, nb = iv.shape[:2]
        last = self.mesh.last if self.reuse else None
        if last is not None and last[0] == self.settings and all(
                np.array_equal(a, b) for a, b in zip(last[1:4], (o, d, iv))):
            # (the same rays through unchanged blocks: render_backward's primal
            # of the image just rendered)
            C, T = last[4], last[5]
        else:
            C = np.zeros((nb, n, 3), np.float32)
            T = np.ones((nb, n), np.float32)
            jobs = {}
            for k in range(nb):
                idx = np.flatnonzero(iv[:, k, 1] > iv[:, k, 0])
                if len(idx):
                    jobs[k] = (idx, self.mesh.call(k, "trace", self.settings, o[idx], d[idx],
                                                   iv[idx, k, 0], iv[idx, k, 1]))
            for k, (idx, ref) in jobs.items():
                C[k, idx], T[k, idx] = self.mesh.get(k, ref)
            self.mesh.last = (self.settings, o, d, iv, C, T)
        order = entry_order(iv)
        rows = np.arange(n)
        Cs = np.zeros((n, 3), np.float64)
        Tf = np.ones(n, np.float64)
        for r in range(nb):
            k = order[:, r]
            Cs += Tf[:, None] * C[k, rows]
            Tf *= T[k, rows]
        Cs, Tf = Cs.astype(np.float32), Tf.astype(np.float32)
        return mi.Color3f(*floats(Cs)), floats(Tf)

    def backward(self, ray, t_start, active, adj, behind):
        import drjit as dr
        last = self.mesh.last
        if last is None or len(last[1]) != dr.width(adj.dL):
            raise RuntimeError("the partitioned mesh's adjoint runs after its primal pass "
                               "over the same rays")
        _, o, d, iv, C, T = last
        order = entry_order(iv)
        n, nb = iv.shape[:2]
        rows = np.arange(n)
        dL = np.array(adj.dL, np.float64).reshape(3, -1).T
        dalpha = np.broadcast_to(np.array(adj.dalpha, np.float64), (n,))
        behind = np.broadcast_to(np.array(behind, np.float64).reshape(3, -1).T, (n, 3)) \
            if behind is not None else np.zeros((n, 3))
        # transmittance in front of and behind each rank, radiance behind it
        fronts, tails = np.ones((nb + 1, n)), np.ones((nb + 1, n))
        for r in range(nb):
            fronts[r + 1] = fronts[r] * T[order[:, r], rows]
            tails[nb - 1 - r] = tails[nb - r] * T[order[:, nb - 1 - r], rows]
        backs = np.zeros((nb, n, 3))
        B = behind.copy()
        for r in reversed(range(nb)):
            backs[r] = B
            k = order[:, r]
            B = C[k, rows] + T[k, rows, None] * B
        jobs = {}
        for k in range(nb):
            live = iv[:, k, 1] > iv[:, k, 0]
            rank = np.argmax(order == k, 1)
            front = fronts[rank, rows]
            idx = np.flatnonzero(live & (front > 0))
            if not len(idx):
                continue
            Tk = T[k, idx].astype(np.float64)
            f = front[idx]
            back_T = tails[rank[idx] + 1, idx]
            L_pix = C[k, idx] + Tk[:, None] * backs[rank[idx], idx]
            jobs[k] = (idx, self.mesh.call(
                k, "backward", self.settings, o[idx], d[idx], iv[idx, k, 0], iv[idx, k, 1],
                L_pix.astype(np.float32), Tk.astype(np.float32),
                (dL[idx] * f[:, None]).astype(np.float32),
                (dalpha[idx] * f * back_T).astype(np.float32)))
        for k, (idx, ref) in jobs.items():
            self.mesh.accumulate(k, self.mesh.get(k, ref), self.grads)


class PartitionedMesh:
    """A ``.pvtu`` written by ``partition``, held by Ray workers.

    Parameters
    ----------
    pvtu : str or Path
    workers : int, optional
        Workers (Ray actors), each holding every ``workers``-th block
        (default: one per block).
    shape : dict, optional
        ``tetmesh`` properties of the blocks (see :class:`BlockWorker`).
    address : str, optional
        A running Ray cluster (default: ``RAY_ADDRESS``, else a local one,
        started here and stopped by :meth:`close`).
    threads : int, optional
        Dr.Jit's CPU threads per worker (default: the cores over the workers).
    retries : int
        Times a worker that dies is started again (its blocks read anew) and
        its call run again before the render fails.
    stagger : bool
        Start the workers one after the other, each once the previous one
        has loaded its pieces: the machine's memory then holds one load's
        peak at a time (workers of one machine on a mesh near its memory).
    """

    def __init__(self, pvtu, workers=None, shape=None, address=None, threads=None, retries=1,
                 stagger=False):
        import mitsuba as mi
        with needs("cluster", "rendering over Ray workers"):
            import ray
        self.part = read_partition(pvtu)
        self.boxes = self.part.boxes()
        nb = len(self.part.blocks)
        self.workers = int(workers or nb)
        if self.workers < 1:
            raise ValueError(f"workers must be at least 1, got {workers}")
        self.workers = min(self.workers, nb)
        self.started = connect(self.workers, address)
        cpus = int(ray.available_resources().get("CPU", self.workers))
        threads = threads or max(1, cpus // self.workers)
        remote = ray.remote(num_cpus=0, max_restarts=int(retries),
                            max_task_retries=int(retries))(BlockWorker)
        self.assign = [list(range(w, nb, self.workers)) for w in range(self.workers)]
        self.owner = {k: w for w, ks in enumerate(self.assign) for k in ks}
        variant = mi.variant()
        path = str(Path(pvtu).resolve())
        self.actors = []
        for ks in self.assign:
            self.actors.append(remote.remote(path, ks, shape or {}, variant, threads))
            if stagger:
                # (its pieces loaded before the next worker starts: one load's peak at a time)
                ray.get(self.actors[-1].pid.remote())
        self._ids = {}
        #: the last primal pass's rays and per-block results (until a step changes the blocks)
        self.last = None

    def call(self, k, method, *args):
        """Block ``k``'s worker's ``method`` (a Ray object reference)."""
        return getattr(self.actors[self.owner[k]], method).remote(k, *args)

    def get(self, k, ref):
        with needs("cluster", "rendering over Ray workers"):
            import ray
        try:
            return ray.get(ref)
        except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as e:
            raise RuntimeError(f"the worker of block {k} of {self.part.path.name} died "
                               f"({type(e).__name__}); the render is abandoned, nothing "
                               f"written") from None

    def point_ids(self, k):
        if k not in self._ids:
            self._ids[k] = self.get(k, self.call(k, "point_ids"))
        return self._ids[k]

    def accumulate(self, k, grads, into):
        """Add block ``k``'s gradients into the whole mesh's (``into``):
        per vertex by their global ids (copies shared by blocks summed)."""
        ids = self.point_ids(k)
        for name, g in grads.items():
            if name in SHARED_PARAMS:
                into[name] = into.get(name, 0.0) + g.astype(np.float64)
                continue
            g = g.reshape(len(ids), -1)
            total = into.setdefault(name, np.zeros((self.part.vertices, g.shape[1])))
            np.add.at(total, ids, g)

    def attached(self, scene, reuse=False):
        """``(integrator, blocks)``: the scene's ``tetvr`` integrator rendering
        this mesh (its ``remote`` medium, :meth:`with_medium`) and the blocks
        it renders with; ``reuse``: the last primal
        pass's per-block results stand for a primal of the same rays (none
        changed the blocks since: :meth:`step` forgets them)."""
        integrator = scene.integrator()
        if not hasattr(integrator, "with_medium"):      # (tetvr's: the medium it hands on)
            raise ValueError(f"a partitioned mesh is rendered by the tetvr integrator, the "
                             f"scene's is {type(integrator).__name__}")
        blocks = Blocks(self, walk_settings(integrator, scene, self.part), reuse)
        return integrator.with_medium(blocks), blocks

    def render(self, scene, sensor=0, seed=0, spp=0):
        """The image of ``scene`` (its camera, surfaces and lights, its
        ``tetvr`` integrator) with this mesh in it, as ``mi.render`` returns it."""
        integrator, _ = self.attached(scene)
        return integrator.render(scene, sensor, seed, spp)

    def backward(self, scene, grad_image, sensor=0, seed=0, spp=0):
        """The gradients of ``sum(grad_image * image)`` w.r.t. the mesh's
        parameters: ``{name: array}``, per vertex of the whole mesh
        (``vertex_color`` (n, 3), ``vertex_opacity`` (n, 1), ``vertex_positions``
        (n, 3), ``vertex_scalar`` (n, 1)) or whole (``tf_color``,
        ``tf_opacity``). The primal of the same rays is the last render's where
        nothing changed since (else the workers render it again, as Mitsuba's
        ``render_backward`` does)."""
        import mitsuba as mi
        integrator, blocks = self.attached(scene, reuse=True)
        integrator.render_backward(scene, None, mi.TensorXf(grad_image), sensor, seed, spp)
        return blocks.grads

    def optimizer(self, lr):
        """Adam on every block's worker over the parameters named in ``lr``
        (``{"vertex_color": 0.02, ...}``); :meth:`step` applies it."""
        bad = sorted(set(lr) - set(FITTED_PARAMS))
        if bad:
            raise ValueError(f"a partitioned mesh optimizes {FITTED_PARAMS}, not {bad} (its "
                             f"blocks hold the tets that touch their boxes where they are: "
                             f"moved vertices could leave them)")
        self._wait([self.call(k, "optimizer", lr) for k in range(len(self.part.blocks))])
        self.optimized = list(lr)

    def step(self, grads):
        """One optimizer step of every block with the whole mesh's gradients
        (:meth:`backward`): each block takes its vertices' rows, so the copies
        of a vertex in several blocks stay equal."""
        self.last = None
        self._wait([self.call(k, "apply", {n: grads[n][self.point_ids(k)]
                                           for n in self.optimized})
                    for k in range(len(self.part.blocks))])

    def arrays(self, names):
        """The whole mesh's parameters ``{name: (n_vertices, c)}`` read back
        from the blocks (each vertex from the first block that holds it)."""
        out = {}
        for k in range(len(self.part.blocks)):
            got = self.get(k, self.call(k, "arrays", list(names)))
            ids = self.point_ids(k)
            for n, a in got.items():
                out.setdefault(n, np.zeros((self.part.vertices, a.shape[1]), np.float32))[ids] = a
        return out

    def write(self, out):
        """The blocks with their present colors and opacities as a new
        partitioned mesh ``out`` (``.pvtu``; each worker writes its pieces)."""
        import dataclasses

        from mi_tetvr.mesh.io import read_mesh_file
        from mi_tetvr.mesh.partition import PIECE_ARRAYS, _write_blocks, _write_pvtu
        out = Path(out).resolve()
        if out.suffix.lower() != ".pvtu":
            raise ValueError(f"a partitioned mesh is written as .pvtu, got {out}")
        (out.parent / out.stem).mkdir(parents=True, exist_ok=True)
        pieces = [f"{out.stem}/{out.stem}_{k}.vtu" for k in range(len(self.part.blocks))]
        self._wait([self.call(k, "write", str(out.parent / p)) for k, p in enumerate(pieces)])
        first = read_mesh_file(out.parent / pieces[0])
        _write_pvtu(out, pieces,
                    {n: v for n, v in first.point_data.items() if n not in PIECE_ARRAYS},
                    {n: v[0] for n, v in first.cell_data.items() if n not in PIECE_ARRAYS})
        blocks = [dataclasses.replace(b, piece=p) for b, p in zip(self.part.blocks, pieces)]
        _write_blocks(dataclasses.replace(self.part, path=out, blocks=blocks))
        return read_partition(out)

    def _wait(self, refs):
        for k, ref in enumerate(refs):
            self.get(k, ref)

    def peak_memory(self):
        """Each worker's peak resident memory (bytes)."""
        with needs("cluster", "rendering over Ray workers"):
            import ray
        return ray.get([a.peak_memory.remote() for a in self.actors])

    def close(self):
        with needs("cluster", "rendering over Ray workers"):
            import ray
        for a in self.actors:
            ray.kill(a)
        self.actors = []
        if self.started:
            ray.shutdown()
            self.started = False

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def map_frames(cls, init_args, method, calls, workers, address=None, progress=None):
    """``[getattr(obj, method)(*call) for call in calls]`` over ``workers`` Ray
    actors of ``cls`` (each built once with ``init_args``, so that what it
    loads serves all its frames), in order; ``progress`` is called once per
    frame done. A worker that dies is started again once."""
    with needs("cluster", "rendering over Ray workers"):
        import ray
        from ray.util import ActorPool
    started = connect(workers, address)
    try:
        cpus = int(ray.available_resources().get("CPU", workers))
        remote = ray.remote(num_cpus=0, max_restarts=1, max_task_retries=1)(cls)
        actors = [remote.remote(*init_args, threads=max(1, cpus // workers))
                  for _ in range(workers)]
        pool = ActorPool(actors)
        out = []
        try:
            for frame in pool.map(lambda a, call: getattr(a, method).remote(*call), calls):
                out.append(frame)
                if progress is not None:
                    progress()
        except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as e:
            raise RuntimeError(f"a worker died twice ({type(e).__name__}): the frames are "
                               f"abandoned, nothing written") from None
        finally:
            for a in actors:
                ray.kill(a)
        return out
    finally:
        if started:
            ray.shutdown()



def render(scene, pvtu, workers=None, shape=None, address=None, sensor=0, seed=0, spp=0):
    """``mi.render`` of ``scene`` with the partitioned mesh ``pvtu`` in it,
    rendered by ``workers`` Ray workers (see :class:`PartitionedMesh`)."""
    with PartitionedMesh(pvtu, workers, shape, address) as mesh:
        return mesh.render(scene, sensor, seed, spp)


def fit_blocks(pm: PartitionedMesh, data, out, config, progress=True):
    """``fit --workers``: Adam on the blocks' colors and opacities (learning
    rates ``lr_color``, ``lr_opacity``) towards the data set's training views,
    ``views_per_step`` per step (their gradients summed), for ``iterations``
    steps or ``time_budget`` minutes; the held-out views scored by
    :func:`~mi_tetvr.recon.metrics.image_metrics`. Writes ``out/mesh.pvtu``
    (the blocks' pieces, each written by its worker) and ``out/metrics.json``;
    returns the metrics."""
    import json
    import time

    import mitsuba as mi

    from mi_tetvr.progress import progress_bar
    from mi_tetvr.recon.metrics import image_metrics
    cfg = config
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pm.optimizer({"vertex_color": cfg.trainer.lr_color,
                  "vertex_opacity": cfg.trainer.lr_opacity})
    scene = mi.load_dict({"type": "scene",
                          "integrator": {"type": "tetvr", "n_sub": cfg.trainer.n_sub}})
    sensors = {}

    def sensor(view):
        # (by the view itself: a training and a test view may share a name)
        if id(view) not in sensors:
            sensors[id(view)] = mi.load_dict(view.camera.sensor_dict())
        return sensors[id(view)]
    rng = np.random.default_rng(cfg.trainer.seed)
    t0 = time.time()
    deadline = t0 + 60 * cfg.trainer.time_budget if cfg.trainer.time_budget else None
    steps, losses = 0, []
    for step in progress_bar(range(cfg.trainer.iterations), desc="fit", unit="step",
                             disable=not progress):
        if deadline is not None and time.time() > deadline:
            break
        picks = rng.choice(len(data.train), min(cfg.trainer.views_per_step, len(data.train)),
                           replace=False)
        total, loss = None, 0.0
        for i in picks:
            view = data.train[i]
            img = np.array(pm.render(scene, sensor(view), seed=step))
            r = img - view.image
            loss += float(np.abs(r).mean() if cfg.trainer.loss == "l1" else np.square(r).mean())
            g = (np.sign(r) if cfg.trainer.loss == "l1" else 2 * r) / r.size
            grads = pm.backward(scene, g.astype(np.float32), sensor(view), seed=step)
            total = grads if total is None else {n: total[n] + grads[n] for n in grads}
        pm.step(total)
        losses.append(loss / len(picks))
        steps += 1
    seconds = time.time() - t0
    views = {}
    for view in data.test or data.train:
        img = np.array(pm.render(scene, sensor(view)))
        views[view.name] = image_metrics(img, view.image, None)
    mean = {k: float(np.mean([v[k] for v in views.values()])) for k in ("psnr", "ssim")}
    part = pm.write(out / "mesh.pvtu")
    metrics = {"views": views, "mean": mean, "step": steps, "seconds": seconds,
               "tets": part.tets, "vertices": part.vertices, "blocks": len(part.blocks),
               "workers": pm.workers, "losses": losses,
               "split": "test" if data.test else "train"}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1, default=float))
    return metrics
