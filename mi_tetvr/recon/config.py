"""Settings of a reconstruction (``mi-tetvr fit --config FILE.json``).

Units. Colors are linear RGB. Opacity is extinction per unit length in the
data set's world units; since the right scale depends on the scene's size, the
opacity settings are given per *cell*: ``init_opacity`` and ``lr_opacity`` are
optical depths across one cell of size ``h`` (the initial mesh's mean edge
length), i.e. they are divided by ``h``. Position learning rates are in units
of ``h`` too.

Targets. Images are premultiplied linear RGB plus alpha (what ``tetvr``
renders over black, with its ``alpha`` AOV). With ``background=None`` the fit
matches RGBA; with a background color it matches RGB composited over it
(``rgb + (1 - alpha) * background``), as for NeRF's white-background renders.
"""
from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass
from typing import ClassVar
from pathlib import Path

from mi_tetvr.extras import needs


__all__ = ["FitConfig", "DataSettings", "MeshSettings", "FieldSettings", "StrategySettings",
           "TrainerSettings", "SolverSettings", "coarse_to_fine", "INITS", "RENAMED", "PARTS",
           "KINDS", "setting", "same_setting", "parse_background"]

#: Settings renamed since: old name -> name (old config files still read, with a warning).
RENAMED = {"resolution": "grid_resolution"}


#: The kinds of fit (:attr:`FitConfig.kind`): colors and opacities (``color``), a lit
#: medium (``scattering``), an X-ray attenuation (``absorption``), a transfer function
#: (``tf``) or the scalar under one (``scalar``).
KINDS = ("color", "scattering", "absorption", "tf", "scalar")
#: The starting meshes made from the data (any other ``init`` is a mesh file).
INITS = ("auto", "grid", "tetwild", "delaunay", "unbounded")
#: The settings of a stage (``FitConfig.stages``).
STAGE_KEYS = ("iterations", "lr_position", "split", "prune", "grid", "downscale", "sh_degree")


def _numbers(n):
    def parse(text):
        try:
            values = [float(x) for x in str(text).split(",")]
        except ValueError:
            values = []
        if len(values) != n:
            raise ValueError(f"expected {n} comma-separated numbers, got {text!r}")
        return values
    return parse


def parse_weight(text):
    """The penalty's weight from command-line text: a number, or ``heldout``."""
    if str(text) == "heldout":
        return "heldout"
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"tv must be a number >= 0 or heldout, got {text!r}") from None


def parse_share(text):
    """``--adapt``'s share of the grid's unknowns from command-line text."""
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"adapt must be a share of the grid's unknowns in (0.125, 1], got "
                         f"{text!r}") from None


def _json(text):
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"not JSON ({e}): {text!r}") from None


def parse_background(text):
    """``none`` (None: fit RGBA), ``learn``, ``white``, ``black`` or ``r,g,b`` (linear)."""
    if text is None or text == "none":
        return None
    if text == "learn":
        return text
    named = {"white": [1.0, 1.0, 1.0], "black": [0.0, 0.0, 0.0]}
    if text in named:
        return named[text]
    try:
        return _numbers(3)(text)
    except ValueError:
        raise ValueError(f"background must be none, learn, white, black or r,g,b; "
                         f"got {text!r}") from None


def _bounds(text):
    v = _numbers(6)(text)
    return [v[:3], v[3:]]


def setting(default, help, choices=None, flag=None, metavar=None, parse=None):
    """A :class:`FitConfig` field with its help text (and choices) written once: the
    ``mi-tetvr fit`` options are generated from them (:func:`mi_tetvr.cli.flags.config_flags`);
    ``parse`` reads the setting from command-line text (default: from its type)."""
    meta = {"help": help}
    if parse is not None:
        meta["parse"] = parse
    if choices is not None:
        meta["choices"] = tuple(choices)
    if flag is not None:
        meta["flag"] = flag
    if metavar is not None:
        meta["metavar"] = metavar
    return dataclasses.field(default=default, metadata=meta)


class _Part:
    """A part of a fit's settings: a dataclass of :func:`setting` fields, each with its
    help (``ABOUT``: what the part is; :meth:`validate`: its own settings' checks)."""
    ABOUT: ClassVar[str] = ""
    #: Settings that are at least 1 (when set), and those that are at least 0.
    POSITIVE: ClassVar[tuple] = ()
    NON_NEGATIVE: ClassVar[tuple] = ()

    def validate(self):
        """Raise ``ValueError`` on a setting of this part out of its choices or range."""
        for f in dataclasses.fields(self):
            choices = f.metadata.get("choices")
            value = getattr(self, f.name)
            if choices and value is not None and value not in choices:
                raise ValueError(f"{f.name} must be {', '.join(map(str, choices))}; "
                                 f"got {value!r}")
        for name in self.POSITIVE:
            if getattr(self, name) is not None and int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1")
        for name in self.NON_NEGATIVE:
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")


@dataclass
class DataSettings(_Part):
    """The fit's settings of part ``data``: what the images are and how they are read."""
    ABOUT: ClassVar[str] = "what the images are and how they are read"

    scene: str = setting(
        "auto", "what the images show: object (views of an object with alpha masks: a grid over "
        "its visual hull), unbounded (photos of a scene in its surroundings: its sparse points "
        "and far cells tetrahedralized, a learned background, a color transform per photo, L1 "
        "loss, cells added where the error is); auto: object when some training pixel is "
        "transparent", choices=("auto", "object", "unbounded"))
    downscale: int = setting(1, "shrink the images by this factor")
    jitter: bool | None = setting(
        None, "random sub-pixel ray positions (off: pixel centers, for targets rendered through "
        "pixel centers); default: off for data sets made by make-dataset, else on")
    xray_flux: float | None = setting(
        None, "model absorption: photons per pixel of the unattenuated beam: rays weighted by "
        "their counts (Poisson noise); default: what the data set records (none: unweighted)")
    lights: str | None = setting(
        None, "model scattering: a Mitsuba scene file (.xml) of the known lighting, the same "
        "for every view: its emitters, and any surfaces around the volume (a floor, walls)",
        metavar="XML")

    POSITIVE: ClassVar[tuple] = ("downscale",)

    def validate(self):
        super().validate()
        if self.xray_flux is not None and not self.xray_flux > 0:
            raise ValueError(f"xray_flux must be > 0 photons per pixel, got {self.xray_flux!r}")


@dataclass
class MeshSettings(_Part):
    """The fit's settings of part ``mesh``: the starting mesh."""
    ABOUT: ClassVar[str] = "the starting mesh"

    init: str = setting(
        "auto", "the starting mesh: auto (grid for objects, unbounded for scenes), grid, "
        "tetwild, delaunay, unbounded, or a mesh file (the scalar mesh with optimize tf or "
        "scalar)", metavar="INIT|MESH")
    grid_resolution: int | None = setting(
        None, "grid cells along the box's largest axis (init grid, tetwild); default: planned "
        "from the data and the time budget, else 32")
    bounds: list | None = setting(
        None, "the box to reconstruct in, x0,y0,z0,x1,y1,z1; default: the visual hull of the "
        "alpha masks, else the data set's", metavar="X0,Y0,Z0,X1,Y1,Z1", parse=_bounds)
    outer: str = setting(
        "shells", "unbounded init beyond the scene points: shells (spheres with geometrically "
        "growing radii) or contracted (a grid in mip-NeRF 360's contracted space)",
        choices=("shells", "contracted"))
    scalar: str | None = setting(None, "the init mesh's scalar point array (default: the only "
                                       "one)")
    repair: bool = setting(
        False, "init mesh file: drop folded, flat and duplicate tets (reported)")
    cell_to_point: bool = setting(
        False, "init mesh file: average per-cell arrays onto the vertices")

    POSITIVE: ClassVar[tuple] = ("grid_resolution",)


@dataclass
class FieldSettings(_Part):
    """The fit's settings of part ``field``: what is fitted and how it starts."""
    ABOUT: ClassVar[str] = "what is fitted and how it starts"

    model: str = setting(
        "emission", "emission: colors and opacities from images; absorption: an X-ray "
        "attenuation (point data 'attenuation') from transmittance images; scattering: "
        "extinction and albedo (point data 'opacity', 'albedo') of a participating medium "
        "from photos under known lighting (--lights), rendered by tetpath",
        choices=("emission", "absorption", "scattering"))
    optimize: str = setting(
        "volume", "what is fitted: volume (per-vertex colors and opacities), tf (the transfer "
        "function over the init mesh's scalar), scalar (the scalar under a known transfer "
        "function)", choices=("volume", "tf", "scalar"))
    init_color: float = setting(0.5, "starting color (linear, every channel)")
    init_opacity: float = setting(0.05, "starting opacity: optical depth per cell")
    sh_degree: int | None = setting(
        None, "view-dependent colors: spherical harmonics up to this degree (1 to 3) per "
        "vertex, degree 0 in the first stage and one more in each stage after, all of them in "
        "the last (as 3D Gaussian Splatting); 0: one color per vertex; default: 0 (degree 2 "
        "lost 0.35-0.84 dB held out on the project's photo captures at equal time; "
        "benchmarks/README.md)", metavar="DEGREE")
    background: list | str | None = setting(
        None, "none: fit RGBA; learn: an environment map fitted with the volume (what lies "
        "beyond the mesh); white, black or r,g,b (linear): composite over it; default: none, "
        "learn for unbounded scenes", metavar="none|learn|white|black|R,G,B",
        parse=parse_background)
    appearance: bool | None = setting(
        None, "fit an exposure and white balance (an affine color transform) per training "
        "photo, identity on held-out photos; default: on for unbounded scenes")
    appearance_prior: float = setting(0.01, "weight of the transforms' squared distance from "
                                            "the identity")
    value_range: list | None = setting(
        None, "lo,hi: the scalar range the transfer function spans (default: the init mesh's "
        "scalar range)", metavar="LO,HI", parse=_numbers(2))
    transfer_function: str | None = setting(
        None, "the known transfer function (optimize scalar), .json or DiffTetVR .xml",
        flag="--tf", metavar="TF")
    opacity_scale: float = setting(
        1.0, "the transfer function's opacity per mesh radius times this (as make-dataset "
        "renders a mesh)")
    tf_resolution: int = setting(64, "texels of a fitted or known transfer function")
    tf_init: str = setting("flat", "start of a fitted transfer function: flat (init_color, "
                                   "init_opacity) or random", choices=("flat", "random"))
    tf_smoothing: float = setting(
        0.01, "weight of DiffDVR's smoothing prior (Eq. 12) on a fitted transfer function; "
        "their 0.4 went with an L1 loss (Blunt Fin, random start, 300 steps: 37.3 dB at 0.4, "
        "48.8 at 0.01; benchmarks/bench_tf_fit.py)")
    smoothing: float = setting(
        0.0, "weight of the mean squared difference across edges of a fitted attenuation "
        "(optical depth per cell) or scalar (over its range): DiffDVR's 3D prior")
    scalar_init: str = setting(
        "colors", "optimize scalar: start from a color fit the scalars are matched to (colors) "
        "or from the init mesh's scalar (mesh)", choices=("colors", "mesh"))

    NON_NEGATIVE: ClassVar[tuple] = ("init_opacity", "appearance_prior")

    def validate(self):
        super().validate()
        if self.background is not None and self.background != "learn" and \
                (isinstance(self.background, str) or len(self.background) != 3):
            raise ValueError(f"background must be None, 'learn' or three linear RGB values, "
                             f"got {self.background!r}")
        if self.sh_degree is not None and not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be 0 (one color per vertex) to 3, got "
                             f"{self.sh_degree}")
        if int(self.tf_resolution) < 2:
            raise ValueError("tf_resolution must be >= 2")
        if self.value_range is not None and not (len(self.value_range) == 2 and
                                                 self.value_range[0] < self.value_range[1]):
            raise ValueError(f"value_range must be [lo, hi] with lo < hi, got {self.value_range}")
        if self.model == "absorption" and (self.optimize != "volume" or self.background):
            raise ValueError("model absorption fits an attenuation from transmittance images: "
                             "no optimize tf/scalar, no background")
        if self.model == "scattering" and (self.optimize != "volume" or self.background
                                           or self.appearance):
            raise ValueError("model scattering fits extinction and albedo from photos under "
                             "known lighting: no optimize tf/scalar, no background (the lights' "
                             "scene holds what lies around), no appearance")
        if self.optimize == "scalar" and self.transfer_function is None:
            raise ValueError("optimize scalar needs the transfer function (--tf)")
        if self.sh_degree and (self.model != "emission" or self.optimize != "volume"):
            raise ValueError("sh_degree gives an emission-absorption volume view-dependent "
                             "colors: not with model absorption/scattering or optimize tf/scalar")

    @property
    def kind(self) -> str:
        """The kind of fit (one of :data:`KINDS`), by ``model`` and ``optimize``."""
        if self.model in ("absorption", "scattering"):
            return self.model
        return "color" if self.optimize == "volume" else self.optimize


@dataclass
class StrategySettings(_Part):
    """The fit's settings of part ``strategy``: what changes the mesh between stages."""
    ABOUT: ClassVar[str] = "what changes the mesh between stages"

    stages: list | None = setting(
        None, "coarse-to-fine stages as JSON, run one after the other, each {\"iterations\": N, "
        "\"lr_position\": x (0: colors and opacities only), \"split\": fraction of vertices "
        "refined after the stage, \"prune\": optical depth per cell below which empty tets "
        "are dropped after it, \"grid\": the resolution of a regular grid the stage trains on "
        "(init grid only), \"downscale\": its training photos area-averaged by this factor "
        "(coarse photos first), \"sh_degree\": the degree of the stage's spherical harmonics "
        "(with sh_degree)}; default: one stage, or with a time budget a coarse grid and then "
        "the fine one (unbounded scenes: four stages with splits and pruning)",
        metavar="JSON", parse=_json)
    target_tets: int | None = setting(None, "no more splits once the mesh has this many tets")
    select: str = setting(
        "gradient", "refinement criterion: gradient (the absolute image-loss gradients of "
        "colors and opacities over the stage's steps), color, opacity (of one of them), error "
        "(the photos' per-pixel error projected into the vertices their rays cross, weighted by "
        "their contribution)", choices=("gradient", "color", "opacity", "error"))
    retriangulate: bool | None = setting(
        None, "after a stage that moved the vertices, tetrahedralize them anew (Delaunay of "
        "where they are), the values following their vertices; default: for meshes born "
        "Delaunay (init unbounded or delaunay)")


@dataclass
class TrainerSettings(_Part):
    """The fit's settings of part ``trainer``: the loop, the optimizer and the clock."""
    ABOUT: ClassVar[str] = "the loop, the optimizer and the clock"

    iterations: int = setting(
        1500, "optimizer steps (with a time budget only the stages' shares count)")
    time_budget: float | None = setting(
        None, "minutes for the whole command, outputs included: the steps fill it (the mesh size, "
        "unless set, is planned from the data and the budget, the same on any machine); a "
        "resumed run gets it again", metavar="MIN")
    views_per_step: int = setting(2, "training views rendered per optimizer step")
    sampling: str = setting(
        "photos", "what each optimizer step renders: whole training photos (views_per_step "
        "of them), or rays drawn at random from all of them, as nerfstudio's pixel sampler "
        "does (the same loss; each step's gradient spread over many photos)",
        choices=("photos", "rays"))
    rays_per_step: int | None = setting(
        None, "sampling rays: rays per optimizer step (default: as many as views_per_step "
        "photos hold at the stage's scale)")
    lr_color: float = setting(0.02, "color step")
    lr_opacity: float = setting(0.05, "opacity step: optical depth per cell")
    lr_position: float = setting(0.0, "position step in cell sizes; 0: positions fixed")
    lr_appearance: float = setting(0.005, "the color transforms' step (their mean is kept at "
                                          "the identity: the held-out photos' transform)")
    lr_scalar: float = setting(0.01, "scalar step, in scalar ranges")
    decay: float = setting(0.1, "learning rates fall exponentially to decay * lr over each "
                                "stage")
    loss: str | None = setting(
        None, "image loss; default: l2, l1 for unbounded scenes (robust to the pixels that "
        "change between photos)", choices=("l1", "l2"))
    loss_space: str = setting(
        "srgb", "compare linear RGB, or the sRGB pictures the metrics score (alpha stays "
        "linear)", choices=("linear", "srgb"))
    regularizer: float = setting(10.0, "weight lambda of the tet-quality term (DiffTetVR "
                                       "Eq. 21) when positions move")
    regularizer_beta: float = setting(100.0, "beta of the tet-quality term (DiffTetVR Eq. 21)")
    distortion: float = setting(
        0.0, "weight of the rays' distortion: how far apart, in disparity, the weights of each "
        "ray lie (the squared-distance form of mip-NeRF 360's distortion loss), on one training "
        "view per step at half its size; 0: none")
    freeze_boundary: bool = setting(True, "keep boundary vertices fixed when positions move")
    safeguard: bool = setting(True, "shorten position steps that would invert a tet")
    n_sub: int = setting(4, "sub-intervals per tet segment while fitting")
    spp: int = setting(1, "rays per pixel in each training render")
    seed: int = setting(0, "random seed (views picked, initial mesh)")
    checkpoint_every: int = setting(100, "steps between checkpoints")
    log_every: int = setting(10, "steps between log lines (a file, not a terminal)")

    POSITIVE: ClassVar[tuple] = ("iterations", "views_per_step", "n_sub", "spp",
                                 "checkpoint_every", "log_every")
    NON_NEGATIVE: ClassVar[tuple] = ("lr_color", "lr_opacity", "lr_position", "regularizer",
                                     "lr_appearance", "distortion")

    def validate(self):
        super().validate()
        if self.rays_per_step is not None and self.rays_per_step < 1:
            raise ValueError("rays_per_step must be >= 1")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError("time_budget must be > 0 minutes")
        if not 0 < self.decay <= 1:
            raise ValueError("decay must be in (0, 1]")


@dataclass
class SolverSettings(_Part):
    """The fit's settings of part ``solver``: X-ray projections' linear solvers (model
    absorption)."""
    ABOUT: ClassVar[str] = "X-ray projections' linear solvers (model absorption)"

    solver: str | None = setting(
        None, "pwls (penalized weighted least squares: Poisson-count weights and the tets' "
        "total variation, its weight chosen on held-out views; ordered subsets with "
        "separable surrogates), sart (ordered-subset SART on the tets, one view per update, "
        "attenuation >= 0), sirt (all views per update), lsqr (CGLS/LSQR through scipy, then "
        ">= 0): model absorption only; adam: the image-loss optimizer; default: pwls for "
        "model absorption (chosen by measurement, benchmarks/bench_tomography.py), else adam",
        choices=("pwls", "sart", "sirt", "lsqr", "adam"))
    passes: int | None = setting(
        None, "model absorption, linear solvers: passes over the views (lsqr: iterations); "
        "pwls: of the first penalty weight tried, half as many for each other and for the "
        "final solve (default 24); sart/sirt: default chosen on held-out views (at most 30, "
        "300; without held-out views 15, 200); lsqr: default 12")
    relaxation: float = setting(1.0, "model absorption, sart/sirt: the update's relaxation")
    tv: float | str | None = setting(
        None, "model absorption, pwls: the total-variation penalty's weight, relative to the "
        "data's curvature (0: none); heldout: chosen on held-out views (0.1, 0.3, 0.03, then "
        "on by factors of 3 while the held-out error falls); default 0.1, which holds from "
        "noise-free data to 10^4 photons, at 24 and 64 views and over 90 degrees",
        metavar="W|heldout", parse=parse_weight)
    adapt: float | None = setting(
        None, "model absorption, pwls: unknowns where the volume has detail: solve a grid of "
        "half the cells per axis (trilinear basis: for a third of the passes, its field only "
        "choosing the cells), then split its cells (trilinear) or vertices (linear basis) "
        "where the field changes most, back to the fine grid's vertices, until there are "
        "SHARE of the fine grid's unknowns (more than 1/8, at most 1; flat regions keep the "
        "coarse cells, and are walked on coarse tets), the penalty the grid's; default: the "
        "grid. What each share gains and costs: the tomography guide",
        metavar="SHARE", parse=parse_share)
    basis: str | None = setting(
        None, "model absorption, linear solvers: the attenuation between the grid's "
        "unknowns (one per vertex): linear in each of its tets, or trilinear (the grid's "
        "trilinear field, walked on tets of twice its cells per axis: the same unknowns, "
        "eight times the tets, two to four times the time); default: trilinear where that "
        "walk has at most 16M tets, else linear (a resumed fit keeps its own). What each "
        "gains and costs: the tomography guide",
        choices=("linear", "trilinear"))
    validation: int = setting(
        8, "model absorption, sart/sirt (and pwls with --tv heldout): every K-th training view "
        "is held out to choose the passes (stopping once they stop improving its projections) "
        "or pwls's penalty weight, then all views are solved with them; 0: the fixed passes "
        "(sart: and the noise rule)")

    POSITIVE: ClassVar[tuple] = ("passes",)

    def validate(self):
        super().validate()
        if not 0 < self.relaxation <= 2:
            raise ValueError("relaxation must be in (0, 2]")
        if self.tv == "heldout" and self.validation < 1:
            raise ValueError("tv heldout chooses the weight on held-out views: it needs "
                             "validation >= 1")
        if (self.tv not in (None, "heldout") and not (isinstance(self.tv, (int, float)) and
                                                     self.tv >= 0)) or self.validation < 0:
            raise ValueError(f"tv must be a number >= 0 or heldout (got {self.tv!r}) and "
                             f"validation >= 0")
        # true: the earlier switch, every unknown of the grid (config files written before)
        if self.adapt is not None and not isinstance(self.adapt, bool) and \
                not (isinstance(self.adapt, (int, float)) and 0.125 < self.adapt <= 1):
            raise ValueError(f"adapt must be a share of the grid's unknowns in (0.125, 1] "
                             f"(the coarse grid has an eighth of them), got {self.adapt!r}")

    @property
    def adapt_share(self) -> float | None:
        """The adaptive mesh's share of the grid's unknowns, or ``None`` (the grid);
        ``true`` (earlier config files' switch) is all of them."""
        if self.adapt is None or self.adapt is False:
            return None
        return 1.0 if self.adapt is True else float(self.adapt)


#: The fit's parts, in the order a config file lists them: the ``--config`` file's
#: sections, :meth:`FitConfig.nested`, the groups of ``fit --help``.
PART_TYPES = {"data": DataSettings, "mesh": MeshSettings, "field": FieldSettings,
              "strategy": StrategySettings, "trainer": TrainerSettings, "solver": SolverSettings}
#: Each part's description and settings, by part.
PARTS = {part: (cls.ABOUT, tuple(f.name for f in dataclasses.fields(cls)))
         for part, cls in PART_TYPES.items()}
#: The settings that apply to some kinds only (the others apply to all).
ONLY = {
    "lights": ("scattering",), "xray_flux": ("absorption",), "outer": ("color",),
    "scalar": ("tf", "scalar"), "sh_degree": ("color",), "distortion": ("color",),
    "background": ("color", "tf", "scalar"), "appearance": ("color", "tf", "scalar"),
    "appearance_prior": ("color", "tf", "scalar"), "lr_appearance": ("color", "tf", "scalar"),
    "value_range": ("tf", "scalar"), "tf_resolution": ("tf", "scalar"),
    "transfer_function": ("scalar",), "opacity_scale": ("scalar",), "lr_scalar": ("scalar",),
    "scalar_init": ("scalar",), "tf_init": ("tf",), "tf_smoothing": ("tf",),
    "smoothing": ("absorption", "scalar"), "init_color": ("color", "scattering", "tf"),
    "lr_color": ("color", "scattering", "tf"),
    "init_opacity": ("color", "scattering", "absorption", "tf"),
    "lr_opacity": ("color", "scattering", "absorption", "tf"),
    "loss_space": ("color", "scattering", "tf", "scalar"),
    **{name: ("absorption",) for name in PARTS["solver"][1]},
}
#: Each setting's part.
PART_OF = {name: part for part, (_, names) in PARTS.items() for name in names}


@dataclass(init=False)
class FitConfig:
    """Settings of a reconstruction, by part (all have working defaults): what the data
    is (``data``), the starting mesh (``mesh``), what is fitted (``field``), what changes
    the mesh between stages (``strategy``), the loop (``trainer``) and an X-ray fit's
    linear solver (``solver``), each its own dataclass whose fields hold their help
    (``mi-tetvr fit --help`` lists them, by part). What a run decides for its data is
    its plan (:class:`mi_tetvr.recon.plan.FitPlan`), written beside it.

    ``FitConfig(lr_color=0.1, init="grid")`` sets settings by name (their names are
    unique across the parts; ``solver="sart"`` is the setting, ``solver=SolverSettings(...)``
    the part); ``FitConfig(trainer=TrainerSettings(...))`` gives a part whole."""
    data: DataSettings
    mesh: MeshSettings
    field: FieldSettings
    strategy: StrategySettings
    trainer: TrainerSettings
    solver: SolverSettings

    def __init__(self, data=None, mesh=None, field=None, strategy=None, trainer=None,
                 solver=None, **settings):
        if isinstance(solver, str):
            # (the part ``solver`` has a setting of its name: a name is the setting)
            settings["solver"], solver = solver, None
        given = dict(data=data, mesh=mesh, field=field, strategy=strategy, trainer=trainer,
                     solver=solver)
        settings = {RENAMED.get(k, k): v for k, v in settings.items()}
        unknown = sorted(set(settings) - set(PART_OF))
        if unknown:
            raise TypeError(f"unknown fit settings {unknown}; the parts and their settings: "
                            f"mi-tetvr fit DATA --print-config")
        for part, cls in PART_TYPES.items():
            value = given[part]
            if value is None:
                value = cls()
            elif isinstance(value, dict):
                value = cls(**value)
            elif not isinstance(value, cls):
                raise TypeError(f"the fit's part '{part}' is a {cls.__name__}, got "
                                f"{type(value).__name__}")
            own = {n: v for n, v in settings.items() if PART_OF[n] == part}
            object.__setattr__(self, part, dataclasses.replace(value, **own) if own else value)

    def __getattr__(self, name):
        # only for names not found: a setting asked of the whole config says its part
        if name in PART_OF:
            raise AttributeError(f"'{name}' is a setting of the fit's part "
                                 f"'{PART_OF[name]}': config.{PART_OF[name]}.{name}")
        raise AttributeError(f"'FitConfig' object has no attribute '{name}'")

    @staticmethod
    def settings():
        """Every setting as ``(part, dataclasses.Field)``, part by part."""
        return [(part, f) for part, cls in PART_TYPES.items() for f in dataclasses.fields(cls)]

    @classmethod
    def from_file(cls, path):
        """Read a JSON or YAML config (``.yaml``/``.yml``): settings by part as
        :meth:`nested` writes them, or (older files) one flat mapping of names; unknown
        names are an error, renamed ones read with a warning (:meth:`from_dict`)."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"config file not found: {path}")
        yaml_file = path.suffix.lower() in (".yaml", ".yml")
        if yaml_file:
            with needs("recon", "a YAML config"):
                import yaml
        try:
            text = path.read_text()
            if yaml_file:
                data = yaml.safe_load(text)
            else:
                data = json.loads(text)
        except Exception as e:
            raise ValueError(f"cannot read the config {path} (JSON, or YAML for .yaml/.yml): "
                             f"{e}") from None
        if not isinstance(data, dict):
            raise ValueError(f"the config {path} must be a mapping of parts (or setting "
                             f"names) to values")
        return cls.from_dict(data, str(path))

    @classmethod
    def from_dict(cls, data: dict, source: str = "the config"):
        """The config of ``data``: ``{part: {name: value}}`` (:meth:`nested`) or a flat
        ``{name: value}`` (:meth:`flat`, older files), or both mixed; a setting under the
        wrong part, or an unknown one, is an error that says where it belongs or what it
        may have meant."""
        import difflib
        import warnings
        flat = {}
        for k, v in data.items():
            if k in PARTS and isinstance(v, dict):
                for name, value in v.items():
                    name = RENAMED.get(name, name)
                    if name in PART_OF and PART_OF[name] != k:
                        raise ValueError(f"{source}: '{name}' is a setting of part "
                                         f"'{PART_OF[name]}', not '{k}'")
                    flat[name if name in PART_OF else f"{k}.{name}"] = value
            else:
                flat[k] = v
        for old, new in RENAMED.items():
            if old in flat:
                warnings.warn(f"{source}: the setting '{old}' is now '{new}' (part "
                              f"'{PART_OF[new]}'); read as such", stacklevel=3)
                flat[new] = flat.pop(old)
        unknown = sorted(k for k in flat if k not in PART_OF)
        if unknown:
            said = []
            for k in unknown:
                close = difflib.get_close_matches(k.split(".")[-1], PART_OF, n=1)
                said.append(f"'{k}'" + (f" (did you mean '{close[0]}'?)" if close else ""))
            raise ValueError(f"{source}: unknown fit settings {', '.join(said)}; the parts "
                             f"and their settings: mi-tetvr fit DATA --print-config")
        return cls().updated(**flat)

    @property
    def kind(self) -> str:
        """The kind of fit (one of :data:`KINDS`), by ``model`` and ``optimize``."""
        return self.field.kind

    def flat(self) -> dict:
        """``{name: value}`` of every setting, part after part (what a checkpoint keeps)."""
        return {name: value for part in PART_TYPES
                for name, value in dataclasses.asdict(getattr(self, part)).items()}

    def nested(self, kind: str | None = None) -> dict:
        """``{part: {name: value}}`` of the settings that apply to ``kind`` (default:
        this config's): what ``--print-config`` prints and a fit's ``config.json`` holds,
        a file ``--config`` reads."""
        kind = kind or self.kind
        values = self.flat()
        return {part: {n: values[n] for n in names if kind in ONLY.get(n, KINDS)}
                for part, (_, names) in PARTS.items()
                if any(kind in ONLY.get(n, KINDS) for n in names)}

    @property
    def linear_solver(self):
        """The linear solver of an absorption fit (``pwls``, ``sart``, ``sirt``,
        ``lsqr``; ``pwls`` unless ``solver`` says), or ``None`` (an Adam fit)."""
        if self.field.model != "absorption" or self.solver.solver == "adam":
            return None
        return self.solver.solver or "pwls"

    def replaced(self, **settings):
        """A copy with the given settings (by name) set, ``None`` included, not
        validated: what a run decides for its data."""
        unknown = sorted(set(settings) - set(PART_OF))
        if unknown:
            raise TypeError(f"unknown fit settings {unknown}")
        out = copy.copy(self)
        for part in PART_TYPES:
            own = {n: v for n, v in settings.items() if PART_OF[n] == part}
            if own:
                object.__setattr__(out, part, dataclasses.replace(getattr(self, part), **own))
        return out

    def updated(self, **kw):
        """A validated copy with the given settings (by name) changed (``None`` values
        leave a setting as it is); unknown names are an error."""
        kw = {RENAMED.get(k, k): v for k, v in kw.items()}
        bad = sorted(set(kw) - set(PART_OF))
        if bad:
            raise ValueError(f"unknown fit settings {bad}; known: {sorted(PART_OF)}")
        cfg = self.replaced(**{k: v for k, v in kw.items() if v is not None})
        cfg.validate()
        return cfg

    def differences(self, saved: dict, ignore=()):
        """The settings that differ from ``saved`` (a :meth:`flat` of another config by
        today's names, e.g. a checkpoint's as :func:`~mi_tetvr.recon.checkpoint.check_resume`
        reads it), as ``{name: (saved value, this value)}``; settings that are ``None``
        here (chosen by the run) and those in ``ignore`` are not compared."""
        out = {}
        for name, value in self.flat().items():
            if name in ignore or value is None or name not in saved:
                continue
            if not same_setting(value, saved[name]):
                out[name] = (saved[name], value)
        return out

    def validate(self):
        """Raise ``ValueError`` on a setting out of range (each part checks its own),
        settings of different parts that do not go together, or a bad stage."""
        for part in PART_TYPES:
            getattr(self, part).validate()
        self._validate_parts()
        self._validate_stages()

    def _validate_parts(self):
        """Settings of one part that belong to a model, solver or kind set in another."""
        field, solver = self.field, self.solver
        if solver.basis == "trilinear" and self.linear_solver is None:
            raise ValueError(f"basis {solver.basis} is the field of model absorption's linear "
                             f"solvers")
        if solver.tv is not None and self.linear_solver not in (None, "pwls"):
            raise ValueError(f"tv is the penalty weight of solver pwls; solver "
                             f"{self.linear_solver} has none")
        if solver.solver not in (None, "adam") and field.model != "absorption":
            raise ValueError(f"solver {solver.solver} solves model absorption (X-ray "
                             f"projections); fits of images use solver adam")
        if (field.model == "scattering") != (self.data.lights is not None):
            raise ValueError("model scattering learns a medium lit by known lights: give both "
                             "--model scattering and --lights XML (the scene of the lights)")
        if field.optimize != "volume" and self.mesh.init in INITS:
            raise ValueError(f"optimize {field.optimize} needs the scalar mesh as init (a "
                             f"file)")
        if self.strategy.select == "error" and self.kind not in ("color", "scattering"):
            raise ValueError("select error ranks vertices by the photos' error through their "
                             "colors: model emission or scattering, optimize volume")
        if self.trainer.distortion and self.kind != "color":
            raise ValueError("distortion concentrates the rays' weights of a fit of colors and "
                             "opacities: model emission, optimize volume")

    def _validate_stages(self):
        """The stages' settings (see ``stages``)."""
        stages = self.stage_list()
        sh_degree = self.field.sh_degree
        for i, st in enumerate(stages):
            if i and st["grid"] is not None and any(
                    p["split"] or p["prune"] is not None or p["lr_position"]
                    for p in stages[:i]):
                raise ValueError("a stage with 'grid' must follow stages that keep the grid "
                                 "(no split, prune or lr_position)")
            bad = sorted(set(st) - set(STAGE_KEYS))
            if bad:
                raise ValueError(f"unknown stage settings {bad}: use {', '.join(STAGE_KEYS)}")
            if int(st.get("downscale", 1)) != st.get("downscale", 1) or st.get("downscale", 1) < 1:
                raise ValueError(f"bad stage {st}: 'downscale' is an integer >= 1")
            if st.get("grid") is not None and (self.mesh.init not in ("grid", "auto")
                                               or int(st["grid"]) < 1):
                raise ValueError(f"bad stage {st}: 'grid' needs init 'grid' and a resolution >= 1")
            if int(st.get("iterations", 0)) < 0 or not 0 <= st.get("split", 0) <= 1:
                raise ValueError(f"bad stage {st}: iterations >= 0, split in [0, 1]")
            if st["sh_degree"] is not None and \
                    not (sh_degree and 0 <= st["sh_degree"] <= sh_degree):
                raise ValueError(f"bad stage {st}: 'sh_degree' is 0 to the fit's sh_degree "
                                 f"({sh_degree or 0}: view-dependent colors off)")

    def stage_list(self):
        """The stages as dicts with all keys (see ``stages``); ``sh_degree`` None:
        one color per vertex."""
        trainer = self.trainer
        raw = self.strategy.stages or [{"iterations": trainer.iterations,
                                        "lr_position": trainer.lr_position}]
        return [{"iterations": int(st.get("iterations", 0)),
                 "lr_position": float(st.get("lr_position", 0.0)),
                 "split": float(st.get("split", 0.0)),
                 "prune": st.get("prune", None), "grid": st.get("grid", None),
                 "downscale": int(st.get("downscale", 1)),
                 "sh_degree": st.get("sh_degree", self.stage_sh_degree(i, len(raw))),
                 **{k: v for k, v in st.items() if k not in STAGE_KEYS}}
                for i, st in enumerate(raw)]

    def stage_sh_degree(self, i, stages):
        """The default degree of stage ``i`` of ``stages``: none without
        ``sh_degree``, else degree 0 first and one more per stage, the last stage
        all of ``sh_degree``."""
        sh_degree = self.field.sh_degree
        if not sh_degree:
            return None
        return sh_degree if i + 1 == stages else min(i, sh_degree)

    def for_stage(self, i):
        """The settings one stage trains with (its iterations and position rate)."""
        st = self.stage_list()[i]
        return self.replaced(iterations=max(st["iterations"], 1), lr_position=st["lr_position"])


def same_setting(a, b) -> bool:
    """Settings equal, numbers up to rounding (lists element by element)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_setting(x, y) for x, y in zip(a, b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_setting(a[k], b[k]) for k in a)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and \
            not isinstance(a, bool) and not isinstance(b, bool):
        return abs(a - b) <= 1e-9 * max(abs(a), abs(b), 1.0)
    return a == b


def coarse_to_fine(rounds=3, steps=300, lr_position=0.05, split=0.05, final=None):
    """DiffTetVR's schedule: colors only, then colors and positions, then a
    split of the top ``split`` fraction of vertices; ``rounds`` times, and a
    last colors-only stage of ``final`` steps (default ``steps``)."""
    stages = []
    for _ in range(rounds):
        stages += [{"iterations": steps}, {"iterations": steps, "lr_position": lr_position,
                                           "split": split}]
    return stages + [{"iterations": steps if final is None else final}]
