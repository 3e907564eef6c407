"""What a reconstruction fits: the unknowns of a tet mesh and how they enter the scene.

A :class:`Field` names the scene parameters a fit optimizes, their starting
values, learning rates and valid range, an optional prior, and what of a
render is compared with a target. :class:`~mi_tetvr.recon.trainer.Trainer`,
the checkpoints and the pipeline go through it, so that one loop fits

* ``volume`` (:class:`VolumeField`): per-vertex color and opacity (emission
  and absorption), the default; with ``sh_degree`` (:class:`ViewDependentField`)
  the color is spherical harmonics, seen differently from each direction;
* ``attenuation`` (:class:`AttenuationField`, ``model="absorption"``): a
  per-vertex attenuation from X-ray transmittance images;
* ``scattering`` (:class:`ScatteringField`, ``model="scattering"``): a
  participating medium's extinction and albedo from photos under known
  lights (``tetpath``);
* ``tf`` (:class:`TransferFunctionField`): the texels of a transfer function
  that post-classifies a fixed scalar field;
* ``scalar`` (:class:`ScalarField`): the per-vertex scalar under a known
  transfer function.

Values are a dict of numpy arrays (``Field.values``): per-vertex arrays
(:attr:`Field.point_arrays`, carried when the mesh is refined) and, for a
transfer function, its texels.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_tetvr.color import linear_to_srgb
from mi_tetvr.recon.config import FieldSettings, TrainerSettings
from mi_tetvr.recon.metrics import (composite, display_rgb, image_metrics, tomography_scores,
                                    transmittance_metrics)

__all__ = ["Field", "VolumeField", "ViewDependentField", "ScatteringField", "AttenuationField",
           "TransferFunctionField", "ScalarField", "make_field", "MESH_ID", "key"]

#: The fitted mesh's id in the scene.
MESH_ID = "volume"


def key(name):
    """The scene-parameter key of the fitted mesh's parameter ``name``."""
    return f"{MESH_ID}.{name}"


class Field:
    """The unknowns of a fit (see the module docstring).

    Parameters
    ----------
    settings : FieldSettings
        The fit's settings of part ``field`` (what is fitted and how it starts).
    h : float
        The mesh's mean edge length (the unit of opacity settings).
    values : dict of numpy arrays
        Arrays the field needs besides its unknowns (a scalar field's values).
    tets : (m, 4) int, optional
        The mesh (its edges carry the smoothing priors).
    trainer : TrainerSettings, optional
        The steps of the field's values (``lr_*``) and the seed of a random start.
    """
    #: ``{value name: (parameter key, channels)}`` of per-vertex unknowns.
    point_arrays: dict = {}
    #: What the images record and the metrics score: ``sRGB`` pictures, or the
    #: ``transmittance`` of X-ray projections.
    scored = "sRGB"
    #: The file a fit writes what it fitted to
    #: (:func:`~mi_tetvr.recon.outputs.write_fitted`).
    fitted_file = "mesh.vtu"
    #: The per-vertex array that is an extinction (what pruning reads), if any.
    extinction = None

    def __init__(self, settings: FieldSettings, h, values=None, tets=None,
                 trainer: TrainerSettings | None = None):
        self.settings, self.h = settings, float(h)
        self.trainer = trainer or TrainerSettings()
        self.fixed = dict(values or {})
        self.tets = tets

    def initial(self, n):
        """Starting values for ``n`` vertices (dict of numpy arrays)."""
        raise NotImplementedError

    # -- what the field's images are, and how they are compared -------------------
    def scene(self, shape, lights=None) -> dict:
        """The scene that renders the field's mesh ``shape`` (its ``tetmesh`` entry):
        ``tetvr`` with the trainer's sub-intervals."""
        return {"type": "scene", "integrator": {"type": "tetvr", "n_sub": self.trainer.n_sub},
                MESH_ID: shape}

    def compared(self, image, background, rgb_only):
        """What the loss compares of an (h, w, 4) premultiplied RGBA image: RGBA, or
        (``rgb_only``) RGB over ``background`` (``None``: black, or the learned one the
        render holds); in ``srgb`` space (``loss_space``) the RGB sRGB-encoded."""
        if self.trainer.loss_space == "linear":
            return composite(image, background) if rgb_only else image
        rgb = linear_to_srgb(composite(image, background))
        if rgb_only:
            return rgb
        return dr.concat([rgb, image[..., 3:4]], axis=-1)

    def metric_mse(self, image, target, background):
        """MSE of the pictures the metrics score (:func:`display_rgb`), no gradient."""
        a, b = display_rgb(image, background), display_rgb(target, background)
        return dr.mean(dr.square(a - b), axis=None)

    def metrics(self, renders, targets, background) -> tuple[list, dict]:
        """The metrics of numpy (h, w, 4) ``renders`` against their ``targets``: per
        image (PSNR, SSIM, MSE of the sRGB pictures over ``background``), and what the
        mean over them adds (none here)."""
        return [image_metrics(r, t, background) for r, t in zip(renders, targets)], {}

    def shown(self, background):
        """The background the pictures of renders are shown over (``test/*.png``)."""
        return background

    def shape(self, vertices, tets, values):
        """The ``tetmesh`` entry of the scene for these values."""
        raise NotImplementedError

    def rates(self):
        """``{parameter key: base learning rate}`` of the optimized parameters."""
        raise NotImplementedError

    @property
    def shared(self):
        """Optimized keys that are not per vertex."""
        per_vertex = {k for k, _ in self.point_arrays.values()}
        return tuple(k for k in self.rates() if k not in per_vertex)

    def project(self, opt):
        """Put the optimizer's values back into their valid range."""

    def prior(self, opt):
        """A regularizing loss on the unknowns (Dr.Jit Float) or None."""
        return None

    def edge_smoothing(self, values, weight, unit=1.0):
        """``weight`` times the mean squared difference of ``values`` (a
        per-vertex Dr.Jit array, times ``unit``) across the mesh's edges
        (DiffDVR's 3D smoothing prior), or None for a weight of 0."""
        if weight <= 0:
            return None
        if not hasattr(self, "_edges"):
            from mi_tetvr.mesh.topology import unique_edges
            e = unique_edges(self.tets)
            self._edges = (mi.UInt32(e[:, 0].astype(np.uint32)),
                           mi.UInt32(e[:, 1].astype(np.uint32)))
        a, b = self._edges
        d = (dr.gather(mi.Float, values, a) - dr.gather(mi.Float, values, b)) * unit
        return weight * dr.mean(dr.square(d))

    def values(self, params):
        """The current values (dict of numpy arrays), fixed ones included."""
        out = dict(self.fixed)
        for name, (k, c) in self.point_arrays.items():
            a = np.array(params[k], np.float64)
            out[name] = a.reshape(-1, c) if c > 1 else a
        return out

    def score_weights(self, criterion):
        """``{parameter key: weight}`` of the per-vertex gradients that rank
        vertices for refinement (``criterion``: gradient | color | opacity); a
        weight is a number, or one number per value of a vertex."""
        return {k: 1.0 for k, _ in self.point_arrays.values()}

    def adopt(self, values):
        """``values`` (dict of numpy arrays, e.g. an earlier stage's) as this field
        holds them (another layout of the same unknowns converted)."""
        return values

    def adopt_moments(self, key, a):
        """Adam's moments ``a`` (n, c') of the parameter ``key`` as this field holds
        it (:meth:`adopt`'s conversion)."""
        return a

    def step_scales(self):
        """``{parameter key: (c,) factors}``: a per-vertex parameter's step, value by
        value of a vertex, times these (default: none)."""
        return {}


class VolumeField(Field):
    """Per-vertex color (linear RGB) and opacity (extinction per unit length)."""
    point_arrays = {"color": (key("vertex_color"), 3), "opacity": (key("vertex_opacity"), 1)}
    extinction = "opacity"
    #: The per-vertex RGB array (its value name): emitted color, or an albedo.
    rgb = "color"

    def initial(self, n):
        return {self.rgb: np.full((n, 3), self.settings.init_color),
                "opacity": np.full(n, self.settings.init_opacity / self.h)}

    def shape(self, vertices, tets, values):
        import mi_tetvr
        return mi_tetvr.tetmesh_dict(vertices, tets, values["color"], values["opacity"])

    def rates(self):
        return {self.point_arrays[self.rgb][0]: self.trainer.lr_color,
                key("vertex_opacity"): self.trainer.lr_opacity / self.h}

    def project(self, opt):
        rgb = self.point_arrays[self.rgb][0]
        opt[rgb] = dr.clip(opt[rgb], 0.0, 1.0)
        opt[key("vertex_opacity")] = dr.maximum(opt[key("vertex_opacity")], 0.0)

    def color_values(self, rgb):
        """The color parameter (a flat ``mi.Float``) of per-vertex colors ``rgb``
        (``mi.Vector3f``, any values)."""
        return dr.ravel(rgb)

    def score_weights(self, criterion):
        w = {}
        if criterion in ("gradient", "color"):
            w[self.point_arrays[self.rgb][0]] = 1.0
        if criterion in ("gradient", "opacity"):
            w[key("vertex_opacity")] = 1.0 / self.h   # per optical depth of a cell
        return w


class ViewDependentField(VolumeField):
    """Per-vertex view-dependent color, the coefficients of real spherical harmonics
    up to ``degree`` (``sh``: ``(degree + 1)^2`` RGB triples per vertex, the
    ``tetmesh``'s ``vertex_sh``), and opacity. A color ``c`` is the degree-0
    coefficient ``(c - 0.5) / Y_0`` (:meth:`adopt`: a plain color field's values, an
    earlier stage's of another degree, padded with zeros or cut). As 3D Gaussian
    Splatting: the degree-0 coefficients step as a color does, the others
    :data:`REST_RATE` times slower; refinement reads the degree-0 gradients."""
    point_arrays = {"sh": (key("vertex_sh"), 3), "opacity": (key("vertex_opacity"), 1)}
    rgb = "sh"
    #: The higher degrees' step over the degree-0 one (3DGS: ``feature_lr / 20``).
    REST_RATE = 1.0 / 20.0

    def __init__(self, settings, h, values=None, tets=None, trainer=None, degree=0):
        from mi_tetvr.render.optical import sh_basis
        super().__init__(settings, h, values, tets, trainer)
        self.fixed.pop("color", None)         # (the coefficients hold it)
        if not 0 <= int(degree) <= 3:
            raise ValueError(f"spherical harmonics have degree 0 to 3, got {degree}")
        self.degree = int(degree)
        self.K = (self.degree + 1) ** 2
        #: Y_0, the degree-0 harmonic (a constant).
        self.Y0 = float(sh_basis(np.zeros((1, 3)), 0)[0][0])
        self.point_arrays = {"sh": (key("vertex_sh"), 3 * self.K),
                             "opacity": (key("vertex_opacity"), 1)}

    def color_to_sh(self, color):
        """(n, 3 K) coefficients of the view-independent ``color`` (n, 3)."""
        sh = np.zeros((len(color), 3 * self.K))
        sh[:, :3] = (np.asarray(color, np.float64).reshape(-1, 3) - 0.5) / self.Y0
        return sh

    def mean_color(self, sh):
        """(n, 3) the colors' mean over directions (the degree-0 term), in [0, 1]."""
        return np.clip(np.asarray(sh, np.float64)[:, :3] * self.Y0 + 0.5, 0.0, 1.0)

    def color_values(self, rgb):
        n, c = dr.width(rgb), 3 * self.K
        out = dr.zeros(mi.Float, n * c)
        idx = dr.arange(mi.UInt32, n) * c
        for j in range(3):
            dr.scatter(out, (rgb[j] - 0.5) / self.Y0, idx + j)
        return out

    def initial(self, n):
        return {"sh": self.color_to_sh(np.full((n, 3), self.settings.init_color)),
                "opacity": np.full(n, self.settings.init_opacity / self.h)}

    def adopt(self, values):
        values = dict(values)
        if "sh" not in values and "color" in values:
            values["sh"] = self.color_to_sh(values["color"])
        values.pop("color", None)
        if "sh" in values:
            values["sh"] = self.resize(values["sh"])
        return values

    def resize(self, a):
        """(n, 3 K) of an (n, 3 K') array of coefficients (or their moments): the
        degrees beyond K' are zero, those beyond K dropped."""
        a = np.asarray(a).reshape(-1, np.asarray(a).size // max(len(a), 1))
        out = np.zeros((len(a), 3 * self.K), a.dtype)
        c = min(a.shape[1], 3 * self.K)
        out[:, :c] = a[:, :c]
        return out

    def adopt_moments(self, k, a):
        return self.resize(a) if k == key("vertex_sh") else a

    def shape(self, vertices, tets, values):
        import mi_tetvr
        sh = np.asarray(values["sh"], np.float64).reshape(len(vertices), self.K, 3)
        return mi_tetvr.tetmesh_dict(vertices, tets, opacity=values["opacity"], sh=sh)

    def rates(self):
        return {key("vertex_sh"): self.trainer.lr_color / self.Y0,
                key("vertex_opacity"): self.trainer.lr_opacity / self.h}

    def step_scales(self):
        if self.K == 1:
            return {}
        return {key("vertex_sh"): np.r_[np.ones(3), np.full(3 * self.K - 3, self.REST_RATE)]}

    def project(self, opt):
        opt[key("vertex_opacity")] = dr.maximum(opt[key("vertex_opacity")], 0.0)

    def score_weights(self, criterion):
        w = super().score_weights(criterion)
        if key("vertex_sh") in w:
            # the degree-0 gradients in color units: what a plain color field's give
            w[key("vertex_sh")] = np.r_[np.full(3, 1.0 / self.Y0), np.zeros(3 * self.K - 3)]
        return w


class ScatteringField(VolumeField):
    """A participating medium (``model="scattering"``): per-vertex extinction
    (the opacity) and single-scattering albedo (linear RGB, in the place of
    the color), rendered by ``tetpath`` under the fit's known lights; renders
    and photos are compared by their RGB (the renders hold the lights'
    surroundings)."""
    point_arrays = {"albedo": (key("vertex_albedo"), 3), "opacity": (key("vertex_opacity"), 1)}
    rgb = "albedo"

    def scene(self, shape, lights=None):
        # a medium lit by the known lights: paths through it and the lights' scene
        from mi_tetvr.render.surfaces import lights_scene
        return {"type": "scene", "integrator": {"type": "tetpath"}, MESH_ID: shape,
                **lights_scene(lights)}

    def compared(self, image, background, rgb_only):
        # (the render holds everything the photo shows: its RGB is compared)
        rgb = image[..., :3]
        return rgb if self.trainer.loss_space == "linear" else linear_to_srgb(
            dr.clip(rgb, 0.0, 1.0))

    def shape(self, vertices, tets, values):
        import mi_tetvr
        return mi_tetvr.tetmesh_dict(vertices, tets, opacity=values["opacity"],
                                     albedo=np.asarray(values["albedo"], np.float64))


class AttenuationField(Field):
    """Per-vertex X-ray attenuation (per unit length), rendered by the
    ``absorption`` model; renders are compared by their transmittance."""
    point_arrays = {"attenuation": (key("vertex_opacity"), 1)}
    scored = "transmittance"
    fitted_file = "attenuation.vtu"
    extinction = "attenuation"

    def compared(self, image, background, rgb_only):
        # the optical depth -log T: linear in the attenuation (a least-squares
        # problem, every ray weighted alike, as in algebraic reconstruction)
        return -dr.log(dr.maximum(1.0 - image[..., 3:4], 1e-6))

    def metric_mse(self, image, target, background):
        return dr.mean(dr.square(image[..., 3] - target[..., 3]), axis=None)

    def metrics(self, renders, targets, background):
        per = [transmittance_metrics(r, t) for r, t in zip(renders, targets)]
        # beside the mean of the views' PSNRs: the PSNR over all their pixels
        return per, {"psnr_all_pixels": tomography_scores(
            projections=[1.0 - r[..., 3] for r in renders],
            targets=[1.0 - t[..., 3] for t in targets])["projection_psnr_pixels"]}

    def shown(self, background):
        # an absorbing volume over white shows its transmittance
        return [1.0] * 3

    def initial(self, n):
        return {"attenuation": np.full(n, self.settings.init_opacity / self.h)}

    def shape(self, vertices, tets, values):
        import mi_tetvr
        return mi_tetvr.tetmesh_dict(vertices, tets, opacity=values["attenuation"],
                                     model="absorption")

    def rates(self):
        return {key("vertex_opacity"): self.trainer.lr_opacity / self.h}

    def project(self, opt):
        opt[key("vertex_opacity")] = dr.maximum(opt[key("vertex_opacity")], 0.0)

    def prior(self, opt):
        # on optical depths per cell: the projections leave some patterns unseen
        return self.edge_smoothing(opt[key("vertex_opacity")], self.settings.smoothing, self.h)

    def score_weights(self, criterion):
        return {key("vertex_opacity"): 1.0 / self.h}


class _Classified(Field):
    """A scalar field post-classified by a transfer function of ``R`` texels
    over ``value_range``."""

    def __init__(self, settings, h, values=None, tets=None, trainer=None):
        super().__init__(settings, h, values, tets, trainer)
        if settings.value_range is not None:
            self.value_range = tuple(float(v) for v in settings.value_range)
        elif "scalar" not in self.fixed:
            raise ValueError("a post-classified fit needs the mesh's scalar field or its "
                             "value_range (--value-range lo,hi)")
        else:
            s = np.asarray(self.fixed["scalar"], np.float64)
            self.value_range = (float(s.min()), float(s.max()))
        if not self.value_range[1] > self.value_range[0]:
            raise ValueError(f"the scalar range must have lo < hi, got {self.value_range} "
                             f"(give value_range)")

    def shape(self, vertices, tets, values):
        import mi_tetvr
        lo, hi = self.value_range
        values = {**self.fixed, **values}
        return mi_tetvr.tetmesh_dict(
            vertices, tets, scalar=values["scalar"],
            tf_color=mi.TensorXf(np.asarray(values["tf_color"], np.float32).reshape(-1, 3)),
            tf_opacity=mi.TensorXf(np.asarray(values["tf_opacity"], np.float32).ravel()),
            value_min=lo, value_max=hi)

    def transfer_function(self, values):
        """The texels of ``values`` as a :class:`~mi_tetvr.transfer.TransferFunction`."""
        from mi_tetvr.transfer import TransferFunction
        return TransferFunction.from_texels(values["tf_color"], values["tf_opacity"])


class TransferFunctionField(_Classified):
    """The ``R`` texels of a transfer function (linear RGB, extinction per
    unit length) over a fixed scalar field, with DiffDVR's smoothing prior
    (Eq. 12: the mean squared difference of neighbouring texels over the four
    channels, weighted by ``tf_smoothing``; the opacity channel in
    optical depth per cell so that it weighs like a color)."""
    K_COLOR, K_OPACITY = key("tf_color"), key("tf_opacity")
    fitted_file = "transfer_function.json"

    def initial(self, n):
        r = int(self.settings.tf_resolution)
        opacity = self.settings.init_opacity / self.h
        if self.settings.tf_init == "random":
            rng = np.random.default_rng(self.trainer.seed)
            return {"tf_color": rng.uniform(0, 1, (r, 3)),
                    "tf_opacity": rng.uniform(0, 2 * opacity, r)}
        return {"tf_color": np.full((r, 3), self.settings.init_color),
                "tf_opacity": np.full(r, opacity)}

    def rates(self):
        return {self.K_COLOR: self.trainer.lr_color,
                self.K_OPACITY: self.trainer.lr_opacity / self.h}

    def project(self, opt):
        opt[self.K_COLOR] = dr.clip(opt[self.K_COLOR], 0.0, 1.0)
        opt[self.K_OPACITY] = dr.maximum(opt[self.K_OPACITY], 0.0)

    def prior(self, opt):
        lam = self.settings.tf_smoothing
        if lam <= 0:
            return None
        r = int(self.settings.tf_resolution)
        i = dr.arange(mi.UInt32, r - 1)
        total = mi.Float(0.0)
        for c in range(3):
            d = (dr.gather(mi.Float, opt[self.K_COLOR], 3 * (i + 1) + c)
                 - dr.gather(mi.Float, opt[self.K_COLOR], 3 * i + c))
            total += dr.sum(dr.square(d))
        d = (dr.gather(mi.Float, opt[self.K_OPACITY], i + 1)
             - dr.gather(mi.Float, opt[self.K_OPACITY], i)) * self.h
        total += dr.sum(dr.square(d))
        return lam * total / (4 * (r - 1))

    def values(self, params):
        out = dict(self.fixed)
        out["tf_color"] = np.array(params[self.K_COLOR], np.float64).reshape(-1, 3)
        out["tf_opacity"] = np.array(params[self.K_OPACITY], np.float64)
        return out


class ScalarField(_Classified):
    """The per-vertex scalar under a known transfer function (``transfer_function``,
    resampled to ``tf_resolution`` texels, its opacity per mesh radius times
    ``opacity_scale`` as ``mi-tetvr
    make-dataset`` renders it); kept in ``value_range``."""
    point_arrays = {"scalar": (key("vertex_scalar"), 1)}
    fitted_file = "scalar.vtu"

    def __init__(self, settings, h, values=None, tets=None, trainer=None, radius=1.0):
        from mi_tetvr.transfer import read_transfer_function
        if settings.transfer_function is None:
            raise ValueError("a scalar fit needs the transfer function (transfer_function)")
        values = dict(values or {})
        if "tf_color" not in values:
            tf = read_transfer_function(settings.transfer_function)
            color, opacity = tf.texels(settings.tf_resolution)
            values.update(tf_color=color, tf_opacity=opacity * settings.opacity_scale / radius)
        super().__init__(settings, h, values, tets, trainer)

    def initial(self, n):
        return {"scalar": np.full(n, 0.5 * sum(self.value_range))}

    def rates(self):
        lo, hi = self.value_range
        return {key("vertex_scalar"): self.trainer.lr_scalar * (hi - lo)}

    def project(self, opt):
        lo, hi = self.value_range
        opt[key("vertex_scalar")] = dr.clip(opt[key("vertex_scalar")], lo, hi)

    def prior(self, opt):
        lo, hi = self.value_range
        return self.edge_smoothing(opt[key("vertex_scalar")], self.settings.smoothing,
                                   1.0 / (hi - lo))


FIELDS = {"volume": VolumeField, "tf": TransferFunctionField}


def field_type(settings: FieldSettings, sh_degree=None) -> type:
    """The :class:`Field` class of the fit's ``field`` settings (see :func:`make_field`)."""
    if sh_degree is not None and settings.kind == "color":
        return ViewDependentField
    if settings.model == "absorption":
        return AttenuationField
    if settings.model == "scattering":
        return ScatteringField
    return ScalarField if settings.optimize == "scalar" else FIELDS[settings.optimize]


def make_field(settings: FieldSettings, h, values=None, tets=None, trainer=None, radius=1.0,
               sh_degree=None) -> Field:
    """The :class:`Field` of the fit's ``field`` settings: ``optimize`` (volume | tf |
    scalar), with ``model`` absorption an attenuation, scattering a lit medium, on the
    mesh ``tets`` (its edges carry the smoothing priors); ``trainer``: the trainer's
    settings (the values' steps). ``radius`` is the mesh's (half its box diagonal): the
    unit of a known transfer function's opacity. ``sh_degree``: a volume's colors are
    spherical harmonics of this degree (the stage's, :meth:`FitConfig.stage_list`; None:
    plain colors)."""
    kind = field_type(settings, sh_degree)
    if kind is ViewDependentField:
        return kind(settings, h, values, tets, trainer, sh_degree)
    if kind is ScalarField:
        return kind(settings, h, values, tets, trainer, radius)
    return kind(settings, h, values, tets, trainer)
