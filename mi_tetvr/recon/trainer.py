"""One stage of a reconstruction: a tet mesh's unknowns (vertex colors and
opacities, an attenuation, a transfer function or a scalar field: a
:class:`~mi_tetvr.recon.fields.Field`) and optionally its positions fitted to
images with known cameras.

The loop is the ordinary Mitsuba one: ``mi.traverse`` the scene, Adam with
one learning rate per parameter kind (:class:`~mi_tetvr.recon.optim.VertexAdam`),
``mi.render`` of a few views per step, an image loss, ``dr.backward``, an
optimizer step. Around it: values kept in range, an exponential learning-rate
decay over the stage, the tet-quality regularizer and an inversion safeguard
for positions. The stages, checkpoints and outputs of a whole run are
:mod:`mi_tetvr.recon.pipeline` and :mod:`mi_tetvr.recon.checkpoint`; units and
targets are those of :mod:`mi_tetvr.recon.config`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.mesh.topology import bounding_radius, mean_edge_length
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.fields import key, make_field
from mi_tetvr.recon.metrics import display_rgb, psnr
from mi_tetvr.recon.optim import VertexAdam

__all__ = ["Trainer", "RunState", "K_POSITION", "K_ENVIRONMENT", "ENVIRONMENT_SIZE",
           "MULTISCALE", "TRAINING_VIEWS", "pixel_center_data", "vertex_cell_sizes"]

#: A mesh whose vertices' cell sizes (95th over 5th percentile) differ by more
#: than this is multiscale: opacities start and step per vertex's own cell.
MULTISCALE = 4.0


def vertex_cell_sizes(vertices, tets):
    """(n,) mean length of the edges at each vertex."""
    from mi_tetvr.mesh.topology import unique_edges
    e = unique_edges(tets)
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    total = np.bincount(e.ravel(), np.repeat(length, 2), len(vertices))
    count = np.bincount(e.ravel(), minlength=len(vertices))
    return total / np.maximum(count, 1)

#: The training photos :meth:`Trainer.training_psnr` renders (evenly spread over them).
TRAINING_VIEWS = 3

#: The fitted mesh's vertex positions in the scene.
K_POSITION = key("vertex_positions")
#: The learned background (``background="learn"``): an ``envmap`` emitter's texels.
K_ENVIRONMENT = "background.data"
#: Its texels, width x height (latitude-longitude): the surroundings' colors
#: from every direction, coarse (what lies outside the fitted box is blurred
#: by the cameras' motion anyway).
ENVIRONMENT_SIZE = (32, 16)


def pixel_center_data(dataset):
    """True for data sets rendered through pixel centers, whose pixels are point samples
    rather than pixel averages: what the data set records (``Dataset.pixel_sampling``,
    written by ``mi-tetvr make-dataset``). Data sets made before it recorded this are
    known by the info file ``make-dataset`` wrote beside them."""
    if getattr(dataset, "pixel_sampling", ""):
        return dataset.pixel_sampling == "centers"
    root = getattr(dataset, "root", None)
    return root is not None and any((Path(root) / f).is_file()
                                    for f in ("volume_info.json", "xray_info.json"))


@dataclass
class RunState:
    """Where a run stands; it carries over from stage to stage and is what a
    checkpoint restores besides the mesh and the optimizer."""
    rng: np.random.Generator     # picks the views of each step
    step: int = 0                # optimizer steps taken over the whole run
    stage: int = 0               # index into ``FitConfig.stage_list()``
    stage_start: int = 0         # the step at which this stage began
    elapsed: float = 0.0         # seconds of training
    shortened: int = 0           # vertex steps the inversion safeguard shortened
    downscale: int | None = None  # the stage's photo scale when the clock kept the last one
    history: dict = field(default_factory=lambda: {"step": [], "time": [], "loss": [],
                                                   "psnr": []})


class Trainer:
    """One stage of a reconstruction: the scene, the optimizer and the run's state.

    What is fitted (colors and opacities, an attenuation, a transfer function
    or a scalar) is the config's :class:`~mi_tetvr.recon.fields.Field`.

    Parameters
    ----------
    dataset : mi_tetvr.recon.datasets.Dataset
        Training and test views (premultiplied linear RGBA images + cameras).
    vertices : (n, 3) float
    tets : (m, 4) int
        The mesh to fit.
    config : FitConfig
        The stage's settings (:meth:`FitConfig.for_stage`).
    values : dict of numpy arrays, optional
        Starting values by the field's names (e.g. ``color`` (n, 3) and
        ``opacity`` (n,)) and the arrays it needs (a scalar field); missing
        ones start from the field's defaults (``config.field.init_color``,
        ``config.field.init_opacity`` per cell).
    state : RunState, optional
        The run so far (default: a new run seeded with ``config.trainer.seed``).
    environment : (h, w, 3) float, optional
        The learned background's texels (``config.field.background == "learn"``;
        default: the training images' mean color everywhere).
    appearance : (len(dataset.train), 12) float, optional
        The training photos' color transforms (``config.field.appearance``; default:
        the identity): per photo the row-major 3x3 matrix minus the identity
        and the offset (:meth:`apply_appearance`).
    topology : mi_tetvr.mesh.Topology, optional
        ``build_topology(vertices, tets)`` when the caller built it already: the
        trainer and its ``tetmesh`` use it instead of building it again.

    Attributes
    ----------
    tets : (m, 4) int64
        The tets, consistently oriented.
    h : float
        The mesh's mean edge length: the unit of the opacity and position settings.
    cell : (n,) float
        Each vertex's cell size (the mean length of its edges) on a mesh whose
        cells differ in size by more than :data:`MULTISCALE` (an unbounded
        scene's): its opacity settings are per *its* cell. Else ``h`` everywhere.
    params : mitsuba.SceneParameters
    opt : VertexAdam
    state : RunState
    """

    def __init__(self, dataset, vertices, tets, config: FitConfig, values=None,
                 state: RunState | None = None, environment=None, appearance=None,
                 topology=None):
        import gc

        from mi_tetvr.mesh.topology import build_topology

        # Free the scenes of earlier trainers that only reference cycles keep:
        # collected later, in the middle of a render, a scene's objects would
        # leave Dr.Jit's virtual-call tables of the kernel being traced (a crash).
        gc.collect()

        self.config = config
        self.dataset = dataset
        self.state = state or RunState(rng=np.random.default_rng(config.trainer.seed))
        stage = config.stage_list()
        stage = stage[min(self.state.stage, len(stage) - 1)]
        #: The photos this stage trains on: the data set's, area-averaged by the stage's
        #: ``downscale`` (coarse photos first); held-out views are scored as given.
        self.downscale = int(self.state.downscale or stage["downscale"])
        self.train = dataset.train if self.downscale == 1 else \
            [v.downscaled(self.downscale) for v in dataset.train]
        if topology is None:
            topology = build_topology(vertices, tets)
        self.tets = topology.tets.astype(np.int64)
        self.boundary = np.unique(topology.boundary_faces)
        self.h = mean_edge_length(vertices, self.tets)
        #: Half the mesh's box diagonal (the unit of a known transfer function's opacity).
        self.radius = bounding_radius(vertices)
        self.field = make_field(config.field, self.h, values, self.tets, config.trainer,
                                self.radius, stage["sh_degree"])
        # (the values given, converted to the field's layout, over its starting ones)
        values = {**self._initial(vertices), **self.field.adopt(values or {})}
        self.scene = mi.load_dict(self._scene_dict(vertices, values, topology))
        self.params = mi.traverse(self.scene)
        if environment is not None:
            self.params[K_ENVIRONMENT] = mi.TensorXf(np.asarray(environment, np.float32))
            self.params.update()
        jitter = config.data.jitter
        self.jitter = jitter if jitter is not None else not pixel_center_data(dataset)
        self._sensors, self._coarse = {}, {}
        for v in self.train + dataset.test:
            self.sensor(v)
        self.targets = {id(v): mi.TensorXf(np.ascontiguousarray(v.image, np.float32))
                        for v in self.train}
        self._sampling(config.trainer)
        self._optimizer(len(vertices))
        self._appearance(appearance)
        #: Per vertex, the absolute image-loss gradients of the training steps so far in this
        #: stage (:meth:`split_scores`), kept on the device.
        self._score_weights = self.field.score_weights(config.strategy.select)
        self._scores = dr.zeros(mi.Float, len(vertices))
        self.regularizer = None
        if config.trainer.regularizer > 0 and config.trainer.lr_position > 0:
            from mi_tetvr.recon.regularizer import QualityRegularizer
            self.regularizer = QualityRegularizer(self.tets, beta=config.trainer.regularizer_beta,
                                                  weight=config.trainer.regularizer)

    def _sampling(self, settings):
        """What a step renders (``sampling``): whole photos, or random rays over all of
        them (:class:`~mi_tetvr.recon.pixels.PixelSampler`, made once per stage)."""
        pixels = float(np.mean([v.camera.width * v.camera.height for v in self.train]))
        photos = min(settings.views_per_step, len(self.train))
        self.pixels = None
        #: Whole photos' worth of pixels one step renders (the stages' epochs count them).
        self.photos_per_step = float(photos)
        if settings.sampling != "rays":
            return
        if not callable(getattr(self.scene.integrator(), "program", None)):
            raise ValueError(f"sampling rays: the fit's integrator renders whole photos only "
                             f"({type(self.scene.integrator()).__name__}); use sampling "
                             f"photos")
        from mi_tetvr.recon.pixels import PixelSampler
        self.pixels = PixelSampler(self.train)
        #: Rays per step (``sampling`` rays).
        self.rays_per_step = int(settings.rays_per_step or round(photos * pixels))
        self.photos_per_step = self.rays_per_step / pixels

    def _initial(self, vertices):
        """The field's starting values; on a multiscale mesh (:data:`MULTISCALE`) the
        extinction per each vertex's own cell (:attr:`cell`)."""
        n = len(vertices)
        self.cell = np.full(n, self.h)
        initial = self.field.initial(n)
        if self.field.extinction is not None:
            cell = vertex_cell_sizes(np.asarray(vertices, np.float64), self.tets)
            lo, hi = np.percentile(cell, [5, 95])
            if hi > MULTISCALE * lo:
                self.cell = cell
                initial[self.field.extinction] = np.full(n, self.field.settings.init_opacity) / cell
        return initial

    def _scene_dict(self, vertices, values, topology):
        """The scene: the fitted mesh (on ``topology``, built once), its integrator, and
        the known lights' scene (a lit medium) or the learned background."""
        import dataclasses

        import mi_tetvr
        config = self.config
        # the shape's tets are the oriented ones: their topology is this one, built once
        shape = mi_tetvr.tetmesh_shape(self.field.shape(vertices, self.tets, values),
                                       topology=dataclasses.replace(topology, n_flipped=0))
        scene = self.field.scene(shape, config.data.lights)
        #: Whether the background is learned: then the renders already hold
        #: it (``C + T * env``) and only their RGB is compared.
        self.learned_background = self.field.settings.background == "learn"
        if self.learned_background:
            mean = np.mean([v.image[..., :3].reshape(-1, 3).mean(0) for v in self.train], 0)
            w, h = ENVIRONMENT_SIZE
            scene[K_ENVIRONMENT.split(".")[0]] = {
                "type": "envmap", "bitmap": mi.Bitmap(np.tile(mean, (h, w, 1)).astype(np.float32))}
        return scene

    def _optimizer(self, n):
        """Adam over the field's parameters, the positions (``lr_position``) and a
        learned background, with the per-value step scales (:meth:`step`)."""
        config = self.config
        rates = self.field.rates()
        if config.trainer.lr_position > 0:
            rates[K_POSITION] = config.trainer.lr_position * self.h
        if self.learned_background:
            rates[K_ENVIRONMENT] = config.trainer.lr_color
        self.opt = VertexAdam(self.params, rates, n, shared=self.field.shared + (K_ENVIRONMENT,))
        self.params.update(self.opt)
        #: Per-vertex parameters whose Adam step is scaled value by value: the
        #: opacity per vertex's own cell (multiscale meshes), the field's own.
        self._step_scales = {k: mi.Float(np.tile(np.asarray(f, np.float32), n))
                             for k, f in self.field.step_scales().items()}
        self.multiscale = self.field.extinction is not None and not np.all(self.cell == self.h)
        if self.multiscale:
            k = self.field.point_arrays[self.field.extinction][0]
            self._step_scales[k] = mi.Float((self.h / self.cell).astype(np.float32))

    def _appearance(self, appearance):
        """The training photos' color transforms and their optimizer (``config
        .appearance``; ``appearance``: their values, default the identity)."""
        self.appearance_index = {}
        if not self.field.settings.appearance:
            return
        train = self.dataset.train
        # a training photo's transform, whether it is seen at the stage's scale or whole
        self.appearance_index = {id(v): i for i, v in enumerate(self.train)}
        self.appearance_index.update({id(v): i for i, v in enumerate(train)})
        init = np.zeros((len(train), 12)) if appearance is None else appearance
        start = mi.Float(np.asarray(init, np.float32).reshape(len(train), 12).ravel())
        #: The transforms' optimizer (its state is checkpointed as the volume's).
        self.appearance_opt = VertexAdam({"appearance": start},
                                         {"appearance": self.config.trainer.lr_appearance},
                                         len(train), shared=("appearance",))

    # -- one step ---------------------------------------------------------------
    def sensor(self, view):
        """The sensor of a view (made once): its camera with the fit's samples per pixel
        and sampling (jittered or at the pixel centres)."""
        s = self._sensors.get(id(view))
        if s is None:
            s = self._sensors[id(view)] = mi.load_dict(view.camera.sensor_dict(
                spp=self.config.trainer.spp, sampler="independent" if self.jitter else "stratified",
                jitter=None if self.jitter else False))
        return s

    def render(self, view, params=None, seed=0, spp=None):
        """(h, w, 4) tensor of a view: premultiplied RGB and alpha (with
        gradients when ``params`` is given)."""
        # seed_grad left to mi.render: tetvr's derivative pass then reuses
        # this render's rays and per-ray values (mi_tetvr.render.replay).
        return mi.render(self.scene, params, sensor=self.sensor(view),
                         spp=spp or self.config.trainer.spp, seed=seed)

    @property
    def background(self):
        """The constant background the images are composited over for the
        loss and the metrics: the config's, ``None`` (black) when fitting
        RGBA or when the background is learned (the renders hold it)."""
        return None if self.learned_background else self.field.settings.background

    def _compared(self, image):
        """What the loss compares of an (h, w, 4) image: RGBA, or RGB over the
        config's background (or with the learned one); in ``srgb`` space the
        RGB sRGB-encoded; for X-ray images the optical depth."""
        return self.field.compared(image, self.background,
                                   self.field.settings.background is not None)

    def apply_appearance(self, image, view):
        """The (h, w, 4) render as photo ``view`` recorded it: its color
        transform ``rgb' = (I + D) rgb + b`` (``D``, ``b`` the view's 12
        fitted values) applied to the linear RGB; alpha kept. Views without
        one (held-out views, fits without ``appearance``) are returned as is."""
        i = self.appearance_index.get(id(view))
        if i is None:
            return image
        return self._transformed(image, i)

    def _transformed(self, rgba, photo):
        """``rgba`` (an ``(..., 4)`` tensor) through the color transforms of training
        photos ``photo``: one index, or one per pixel (``mi.UInt32``)."""
        p = [dr.gather(mi.Float, self.appearance_opt["appearance"], 12 * photo + j)
             for j in range(12)]
        idx = dr.arange(mi.UInt32, dr.width(rgba.array) // 4)
        ch = [dr.gather(mi.Float, rgba.array, 4 * idx + c) for c in range(4)]
        out = [ch[c] + p[3 * c] * ch[0] + p[3 * c + 1] * ch[1] + p[3 * c + 2] * ch[2] + p[9 + c]
               for c in range(3)]
        return mi.TensorXf(dr.ravel(mi.Vector4f(*out, ch[3])), shape=tuple(rgba.shape))

    def appearance(self):
        """The training photos' color transforms as (len(train), 12) numpy,
        or ``None`` (see :meth:`apply_appearance`)."""
        if not self.appearance_index:
            return None
        return np.array(self.appearance_opt["appearance"], np.float64).reshape(-1, 12)

    def loss(self, image, view):
        """Image loss (L1 or L2, mean over pixels and channels) of a render,
        through the view's color transform, against a training view (see
        :meth:`_compared`)."""
        return self._loss(self.apply_appearance(image, view), self.targets[id(view)])

    def _loss(self, rgba, target):
        """The image loss of ``rgba`` (through its photo's color transform) against
        ``target``: tensors of one shape, ``(h, w, 4)`` or ``(rays, 4)``."""
        diff = self._compared(rgba) - self._compared(target)
        if self.config.trainer.loss == "l1":
            return dr.mean(dr.abs(diff), axis=None)
        return dr.mean(dr.square(diff), axis=None)

    def metric_mse(self, image, view):
        """MSE of the sRGB pictures the metrics score (RGB over the config's
        background, black without one; the transmittance of X-ray images), no
        gradient: the training PSNR."""
        with dr.suspend_grad():
            return self.field.metric_mse(self.apply_appearance(dr.detach(image), view),
                                         self.targets[id(view)], self.background)

    def step(self, progress=None):
        """One optimizer step over ``config.trainer.views_per_step`` random training views
        (``sampling`` photos) or :attr:`rays_per_step` random rays of all of them
        (``sampling`` rays).

        ``progress`` is the fraction of the stage done, in [0, 1], which sets
        the learning-rate decay (default: steps taken over
        ``config.trainer.iterations``; a time-budgeted run passes its time fraction).
        Returns the mean image loss and the mean MSE of the views' sRGB
        pictures (:meth:`metric_mse`).
        """
        cfg, state = self.config, self.state
        train = self.train
        if self.pixels is not None:
            seed = (state.step * 131 + cfg.trainer.seed * 104729) % (2 ** 31)
            total, metric = self._ray_step(seed)
            pick = state.rng.choice(len(train), 1)          # (the distortion's view)
        else:
            pick = state.rng.choice(len(train), min(cfg.trainer.views_per_step, len(train)),
                                    replace=False)
            total, metric, seed = self._photo_step(pick)
        self._accumulate_scores()
        if cfg.trainer.distortion > 0:
            self.distortion(train[pick[0]], 2 * seed + 1)
        if self.regularizer is not None:
            dr.backward(self.regularizer(self.opt[K_POSITION]))
        prior = self.field.prior(self.opt)
        if prior is not None:
            dr.backward(prior)
        old = np.array(self.opt[K_POSITION]).reshape(-1, 3) if K_POSITION in self.opt else None
        # The learning rates fall exponentially to ``decay`` times their base over the stage.
        if progress is None:
            progress = (state.step - state.stage_start) / max(cfg.trainer.iterations, 1)
        lr_scale = cfg.trainer.decay ** min(max(progress, 0.0), 1.0)
        before = {k: dr.detach(self.opt[k]) for k in self._step_scales}
        self.opt.step(lr_scale=lr_scale)
        for k, scale in self._step_scales.items():
            # (e.g. Adam's step in units of each vertex's own cell)
            self.opt[k] = before[k] + (self.opt[k] - before[k]) * scale
        if self.appearance_index:
            if cfg.field.appearance_prior > 0:
                a = self.appearance_opt["appearance"]
                dr.backward(cfg.field.appearance_prior * dr.mean(dr.square(a)))
            self.appearance_opt.step(lr_scale=lr_scale)
            # the mean transform is the identity (what held-out photos get): the
            # volume keeps the photos' mean exposure and white balance
            a = np.array(self.appearance_opt["appearance"]).reshape(-1, 12)
            self.appearance_opt["appearance"] = mi.Float((a - a.mean(0)).ravel())
        self.field.project(self.opt)
        if self.learned_background:
            self.opt[K_ENVIRONMENT] = dr.maximum(self.opt[K_ENVIRONMENT], 0.0)
        if old is not None:
            self._safe_positions(old)
        self.params.update(self.opt)
        state.step += 1
        return total, metric

    def _photo_step(self, pick):
        """The image loss of the training photos ``pick`` (indices), backpropagated;
        returns it, the mean MSE of their sRGB pictures and the last render's seed."""
        cfg, state = self.config, self.state
        total, metric = 0.0, 0.0
        for j, i in enumerate(pick):
            view = self.train[i]
            seed = (state.step * 131 + j * 7919 + cfg.trainer.seed * 104729) % (2 ** 31)
            image = self.render(view, self.params, seed=2 * seed)
            loss = self.loss(image, view) / len(pick)
            mse = self.metric_mse(image, view)
            dr.backward(loss)
            total += float(loss.array[0])
            metric += float(mse.array[0]) / len(pick)
        return total, metric, seed

    def _ray_step(self, seed):
        """The image loss of :attr:`rays_per_step` rays drawn at random from all training
        photos, backpropagated; returns it and the MSE of their sRGB values."""
        from mi_tetvr.rays import render_rays
        ray, target, photo = self.pixels.draw(self.rays_per_step, seed, self.jitter)
        rgba = render_rays(self.scene, ray.o, ray.d, params=self.params, seed=2 * seed)
        if self.appearance_index:
            rgba = self._transformed(rgba, photo)
        loss = self._loss(rgba, target)
        with dr.suspend_grad():
            mse = self.field.metric_mse(dr.detach(rgba), target, self.background)
        dr.backward(loss)
        return float(loss.array[0]), float(mse.array[0])

    def distortion(self, view, seed=0):
        """The rays' distortion of a training view at half its size, times
        ``config.trainer.distortion``, backpropagated (the opacities' gradients); returns its value.

        Per ray, with ``w(t)`` the weights of its color (``T(t) sigma(t)``) and ``s(t)``
        the disparity ``near / z`` (at most 1, :meth:`disparity`), the distortion is
        ``1/2 int int w(t) w(u) (s(t) - s(u))^2 dt du = W S_2 - S_1^2``, ``W = int w``,
        ``S_k = int w s^k``: mip-NeRF 360's distortion loss with the square of the distance
        (as 2D Gaussian splatting's), small when each ray's weight lies at one depth. The
        moments are a render of the mesh with ``(s, s^2, 0)`` as its vertex colors (each
        vertex's disparity from the camera, interpolated over the tets) and no background, so
        the derivative is the walk's adjoint (memory flat in the tets a ray crosses)."""
        coarse = self._coarse.get(id(view))
        if coarse is None:
            small = min(view.camera.width, view.camera.height) < 16
            coarse = self._coarse[id(view)] = view if small else view.downscaled(2)
        k = self.field.point_arrays[self.field.rgb][0]
        s = self.disparity(coarse.camera)
        self.params[k] = self.field.color_values(mi.Vector3f(s, dr.square(s), 0.0))
        if self.learned_background:
            self.params[K_ENVIRONMENT] = dr.zeros(mi.TensorXf, self.params[K_ENVIRONMENT].shape)
        self.params.update()
        try:
            image = self.render(coarse, self.params, seed=seed)
            w, s1, s2 = image[..., 3], image[..., 0], image[..., 1]
            loss = self.config.trainer.distortion * dr.mean(w * s2 - dr.square(s1), axis=None)
            dr.backward(loss)
        finally:
            self.params.update(self.opt)
        return float(loss.array[0])

    def disparity(self, camera):
        """(n,) ``mi.Float``: each vertex's disparity from ``camera``, ``near / z`` with ``z``
        its depth along the view axis, at most 1 (:attr:`near`), no gradient."""
        p = dr.unravel(mi.Point3f, dr.detach(self.params[K_POSITION]))
        c, f = (camera.to_world[:3, j].tolist() for j in (3, 2))
        z = dr.dot(p - mi.Point3f(*c), mi.Vector3f(*f))
        return self.near / dr.maximum(z, self.near)

    @property
    def near(self):
        """The depth at which the distortion's disparity is 1: a quarter of the training
        cameras' median distance from the point they look at
        (:func:`~mi_tetvr.camera.cameras_focus`)."""
        if not hasattr(self, "_near"):
            from mi_tetvr.camera import cameras_focus
            cams = [v.camera for v in self.dataset.train]
            focus = cameras_focus(cams)
            self._near = 0.25 * float(np.median([np.linalg.norm(c.center - focus)
                                                 for c in cams]))
        return self._near

    def _safe_positions(self, old):
        """Freeze the boundary (optionally) and shorten steps that would
        invert a tet."""
        from mi_tetvr.recon.safeguard import safe_step
        new = np.array(self.opt[K_POSITION], np.float64).reshape(-1, 3)
        delta = new - old
        if self.multiscale:
            # Adam's step in units of each vertex's own cell (multiscale meshes)
            delta *= (self.cell / self.h)[:, None]
        if self.config.trainer.freeze_boundary:
            delta[self.boundary] = 0.0
        if self.config.trainer.safeguard:
            delta, n_short = safe_step(old, self.tets, delta)
            self.state.shortened += int(n_short)
        self.opt[K_POSITION] = mi.Float((old + delta).astype(np.float32).ravel())

    # -- the mesh ---------------------------------------------------------------
    def arrays(self):
        """Current ``(vertices (n, 3), tets (m, 4), values)`` as numpy arrays,
        ``values`` the field's (:meth:`Field.values
        <mi_tetvr.recon.fields.Field.values>`)."""
        vertices = np.array(self.params[K_POSITION], np.float64).reshape(-1, 3)
        return vertices, self.tets, self.field.values(self.params)

    def environment(self):
        """The learned background's texels as numpy, or ``None``."""
        if not self.learned_background:
            return None
        return np.array(self.params[K_ENVIRONMENT], np.float32)

    def inverted_tets(self):
        """Number of tets with a non-positive volume."""
        from mi_tetvr.mesh.topology import signed_volumes
        vertices, tets, _ = self.arrays()
        return int((signed_volumes(vertices, tets) <= 0).sum())

    def _accumulate_scores(self):
        """Add the image loss's absolute gradients of this step to :meth:`split_scores`
        (before the regularizer's and the prior's: what the photos ask for)."""
        n = self.opt.n_vertices
        idx = dr.arange(mi.UInt32, n)
        for k, w in self._score_weights.items():
            g = dr.grad(self.opt[k])
            c = dr.width(g) // n
            w = np.broadcast_to(np.asarray(w, np.float64), (c,))
            for j in range(c):
                if w[j] != 0:
                    self._scores += float(w[j]) * dr.abs(dr.gather(mi.Float, g, c * idx + j))
        dr.schedule(self._scores)

    def split_scores(self):
        """Per-vertex refinement scores. With ``config.strategy.select`` ``error`` the photos' error
        where each vertex contributes (:meth:`error_scores`); else the absolute image-loss
        gradients of the field's per-vertex unknowns (:meth:`Field.score_weights
        <mi_tetvr.recon.fields.Field.score_weights>` of ``config.strategy.select``: for colors and
        opacities ``color``, ``opacity`` in optical depth per cell, or both, ``gradient``)
        summed over the training steps of this stage, as AbsGS accumulates them: every
        photo's gradients as the fit saw them, at no extra render. Returns (n,) float."""
        if self.config.strategy.select == "error":
            return self.error_scores()[0]
        return np.array(self._scores, np.float64)

    def pixel_error(self, image, view):
        """(h, w) numpy: a training render's error at each pixel against its photo, the
        sRGB pictures' (:meth:`metric_mse`'s) mean absolute difference over the channels
        plus their structural dissimilarity ``(1 - SSIM) / 2`` (scikit-image's map)."""
        from mi_tetvr.recon.metrics import ssim_map
        bg = self.background
        with dr.suspend_grad():
            a = np.array(display_rgb(self.apply_appearance(dr.detach(image), view), bg))
        b = np.array(display_rgb(self.targets[id(view)], bg))
        a, b = a.astype(np.float64), b.astype(np.float64)
        return np.abs(a - b).mean(axis=2) + 0.5 * (1.0 - ssim_map(a, b))

    def error_scores(self):
        """The training photos' error (:meth:`pixel_error`) projected into the vertices
        their rays cross, weighted by each vertex's contribution to the pixel (its weight
        ``w_vp`` in the pixel's color), summed over the stage's photos; and the same of an
        error of 1 everywhere: how much each vertex is seen. Both are derivatives of the
        color: ``d(sum_p e_p I_p) / d c_v = sum_p e_p w_vp``, one render and one
        derivative pass per photo (the red channel weighted by the error, the green by
        1). Radiance Meshes splits on such an error (of SSIM). Returns ``(error (n,),
        seen (n,))``."""
        rgb = self.field.point_arrays.get(getattr(self.field, "rgb", None))
        if rgb is None:
            raise ValueError("select 'error' needs a fitted color (model emission or "
                             "scattering, optimize volume)")
        k, n = rgb[0], self.opt.n_vertices
        w = np.broadcast_to(np.asarray(self.field.score_weights("color")[k], np.float64),
                            (rgb[1],))
        self.opt.clear_grads()
        for i, view in enumerate(self.train):
            image = self.render(view, self.params, seed=2 * i + 1)
            seed = np.zeros(image.shape, np.float32)
            seed[..., 0], seed[..., 1] = self.pixel_error(image, view), 1.0
            dr.backward(dr.sum(image * mi.TensorXf(seed), axis=None))
        g = np.array(dr.grad(self.opt[k]), np.float64).reshape(n, -1)
        self.opt.clear_grads()
        return g[:, 0] * w[0], g[:, 1] * w[1]

    def set_split_scores(self, scores):
        """Restore :meth:`split_scores` (a resumed stage goes on adding to them)."""
        scores = np.asarray(scores, np.float32).ravel()
        if scores.size != self.opt.n_vertices:
            raise ValueError(f"{scores.size} scores for {self.opt.n_vertices} vertices")
        self._scores = mi.Float(scores)

    # -- evaluation -------------------------------------------------------------
    def training_views(self):
        """The whole training photos :meth:`training_psnr` scores: :data:`TRAINING_VIEWS`,
        spread evenly."""
        train = self.dataset.train
        pick = np.linspace(0, len(train) - 1, min(TRAINING_VIEWS, len(train))).round()
        return [train[i] for i in np.unique(pick).astype(int)]

    def training_psnr(self):
        """The PSNR of the sRGB pictures (:meth:`metric_mse`'s) over a fixed few
        (:data:`TRAINING_VIEWS`) of the whole training photos, each through its color
        transform, one sample per pixel as the steps render them (with jittered samples a
        little below the pixel average that :meth:`evaluate` renders with 16): the
        training PSNR at one scale across the stages (each step's own is on the stage's
        photos, area-averaged when coarse). ``None`` for X-ray images."""
        if self.field.scored != "sRGB":
            return None
        bg, mse = self.background, []
        with dr.suspend_grad():
            for i, v in enumerate(self.training_views()):
                image = self.render(v, None, seed=i, spp=1)
                a = np.array(display_rgb(self.apply_appearance(image, v), bg), np.float64)
                mse.append(np.mean((a - display_rgb(np.asarray(v.image, np.float64), bg)) ** 2))
        return psnr(float(np.mean(mse)))

    def render_view(self, view, seed=0):
        """Numpy (h, w, 4) render of a view (no gradients); with jittered
        sampling, 16 samples per pixel approximate the pixel average."""
        spp = 16 if self.jitter else 1
        with dr.suspend_grad():
            return np.array(self.render(view, None, seed=seed, spp=spp))

    def render_camera(self, camera, spp=1, seed=0):
        """Numpy (h, w, 4) render from any pinhole ``camera`` (no gradients; one sample at
        each pixel centre, jittered samples with ``spp`` above 1)."""
        d = camera.sensor_dict(spp=spp, sampler="stratified", jitter=spp > 1)
        with dr.suspend_grad():
            return np.array(mi.render(self.scene, sensor=mi.load_dict(d), spp=spp, seed=seed))

    def evaluate(self, views):
        """PSNR, SSIM and MSE per view (RGB over the config's background) and
        their mean: ``{"views": {name: metrics}, "mean": metrics}``."""
        renders = [self.render_view(v) for v in views]
        scores, more = self.field.metrics(renders, [v.image for v in views], self.background)
        per = {v.name: m for v, m in zip(views, scores)}
        mean = {k: float(np.mean([m[k] for m in per.values()]))
                for k in ("psnr", "ssim", "mse", "psnr_linear")}
        return {"views": per, "mean": {**mean, **more}}
