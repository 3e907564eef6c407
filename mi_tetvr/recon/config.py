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

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

__all__ = ["FitConfig", "coarse_to_fine", "INITS"]

#: The starting meshes made from the data (any other ``init`` is a mesh file).
INITS = ("auto", "grid", "tetwild", "delaunay", "unbounded")


@dataclass
class FitConfig:
    """Settings of a reconstruction (all have working defaults)."""
    # What the images show: "object" (views of an object, with alpha masks: a grid over
    # the visual hull, RGBA or a constant background) or "unbounded" (photos of a scene
    # in its surroundings: the sparse points and far shells tetrahedralized, a learned
    # background, an exposure per photo, an L1 loss); "auto": "object" when some training
    # pixel is transparent, else "unbounded" (mi_tetvr.recon.pipeline.for_capture).
    scene: str = "auto"                # auto | object | unbounded
    init: str = "auto"                 # auto (grid, or unbounded for unbounded scenes) |
                                       # grid | tetwild | delaunay | unbounded | a mesh file
    outer: str = "shells"              # unbounded init beyond the scene points: "shells"
                                       # (spheres, radii growing geometrically) or
                                       # "contracted" (a grid in mip-NeRF 360's contracted
                                       # space); mi_tetvr.mesh.initial.unbounded_init
    resolution: int | None = None      # cells along the largest axis (grid, tetwild); None:
                                       # chosen for the time budget, 32 without one
    bounds: list | None = None         # [[x0, y0, z0], [x1, y1, z1]]; default: from the data
    iterations: int = 1500             # with a time budget: only the stages' time shares
    time_budget: float | None = None   # minutes for the whole command, outputs included: the
                                       # steps (and the mesh size, unless set) fill it; a
                                       # resumed run gets it again
    views_per_step: int = 2
    lr_color: float = 0.02
    lr_opacity: float = 0.05           # optical depth per cell, per step
    lr_position: float = 0.0           # cell sizes per step; 0 = positions fixed
    decay: float = 0.1                 # learning rates fall exponentially to decay * lr
    loss: str | None = None            # l1 | l2; None: l2, l1 for unbounded scenes (the
                                       # median of the residuals: robust to the pixels
                                       # that change between photos)
    loss_space: str = "srgb"           # linear | srgb: compare linear RGB, or the sRGB
                                       # pictures the metrics score (alpha stays linear)
    background: list | str | None = None  # None: fit RGBA (learn for unbounded scenes);
                                       # a color: composite over it; "learn": an
                                       # environment map learned with the volume (what
                                       # lies beyond the mesh)
    appearance: bool | None = None     # a per-photo affine color transform (exposure,
                                       # white balance) fitted with the volume, identity
                                       # on held-out views; None: on for unbounded scenes
    appearance_prior: float = 0.01     # weight of its squared distance from the identity
    lr_appearance: float = 0.005       # its entries' step (the transforms' mean is kept at
                                       # the identity: the held-out photos' transform)
    init_color: float = 0.5
    init_opacity: float = 0.05         # optical depth per cell
    regularizer: float = 10.0          # weight lambda of the tet-quality term (DiffTetVR
    regularizer_beta: float = 100.0    # Eq. 21, their values); used when positions move
    freeze_boundary: bool = True       # keep boundary vertices fixed when positions move
    safeguard: bool = True             # shorten position steps that would invert a tet
    n_sub: int = 4                     # sub-intervals per tet segment while fitting
    spp: int = 1
    jitter: bool | None = None         # random sub-pixel positions; False: pixel centers (for
                                       # targets rendered through pixel centers); None: False
                                       # for data sets made by make-dataset, else True
    downscale: int = 1
    seed: int = 0
    checkpoint_every: int = 100
    log_every: int = 10
    # Coarse-to-fine: a list of stages run one after the other, each
    # {"iterations": N, "lr_position": x (0: colors and opacities only),
    #  "split": fraction of vertices to refine after the stage,
    #  "prune": opacity threshold (optical depth per cell) to drop empty tets after it,
    #  "grid": resolution of a regular grid the stage trains on (``init`` grid only): the
    #          previous stage's field is sampled onto it; the first stage's sets the start}.
    # None: one stage of ``iterations`` steps with ``lr_position``; with a time budget and
    # no resolution, a coarse grid and then the fine one (see mi_tetvr.recon.pipeline).
    stages: list | None = None
    target_tets: int | None = None     # no more splits once the mesh has this many tets
    select: str = "gradient"           # refinement criterion: gradient | color | opacity
    # What is fitted (mi_tetvr.recon.fields): volume (colors and opacities), tf (the texels
    # of a transfer function over the init mesh's scalar field) or scalar (the scalar field
    # under a known transfer function); model absorption fits an X-ray attenuation.
    optimize: str = "volume"           # volume | tf | scalar
    model: str = "emission"            # emission | absorption
    scalar: str | None = None          # the init mesh's scalar point array (default: the only one)
    value_range: list | None = None    # [lo, hi] the transfer function spans; default: the
                                       # scalar's range
    transfer_function: str | None = None  # the known transfer function (optimize scalar)
    opacity_scale: float = 1.0         # its opacity is per mesh radius times this (as
                                       # make-dataset renders a mesh)
    tf_resolution: int = 64            # texels of a fitted or known transfer function
    tf_init: str = "flat"              # flat (init_color, init_opacity) | random
    tf_smoothing: float = 0.01         # weight of DiffDVR's smoothing prior (Eq. 12); their
                                       # 0.4 went with an L1 loss: beside this L2 loss of
                                       # sRGB pictures it smooths 40x as hard (Blunt Fin,
                                       # random start, 300 steps: 37.3 dB at 0.4, 48.8 at
                                       # 0.01; benchmarks/bench_tf_fit.py)
    lr_scalar: float = 0.01            # scalar range per step
    smoothing: float = 0.0             # weight of the mean squared difference across edges
                                       # of a fitted attenuation (optical depth per cell) or
                                       # scalar (over its range): DiffDVR's 3D prior
    scalar_init: str = "colors"        # optimize scalar: colors (a color fit first, scalars
                                       # matched to it) | mesh (the init mesh's scalar)

    @classmethod
    def from_file(cls, path):
        """Read a JSON config (keys as the field names; unknown keys are an error)."""
        data = json.loads(Path(path).read_text())
        return cls().updated(**data)

    def updated(self, **kw):
        """A validated copy with the given settings changed (``None`` values
        leave a setting as it is); unknown names are an error."""
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(kw) - names)
        if bad:
            raise ValueError(f"unknown fit settings {bad}; known: {sorted(names)}")
        cfg = dataclasses.replace(self, **{k: v for k, v in kw.items() if v is not None})
        cfg.validate()
        return cfg

    def validate(self):
        """Raise ``ValueError`` on a setting out of range."""
        if self.scene not in ("auto", "object", "unbounded"):
            raise ValueError(f"scene must be auto, object or unbounded, got {self.scene!r}")
        if self.outer not in ("shells", "contracted"):
            raise ValueError(f"outer must be shells or contracted, got {self.outer!r}")
        if self.loss not in (None, "l1", "l2"):
            raise ValueError(f"loss must be 'l1' or 'l2', got {self.loss!r}")
        if self.loss_space not in ("linear", "srgb"):
            raise ValueError(f"loss_space must be 'linear' or 'srgb', got {self.loss_space!r}")
        for name in ("iterations", "views_per_step", "resolution", "n_sub", "spp", "downscale"):
            if getattr(self, name) is not None and int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError("time_budget must be > 0 minutes")
        for name in ("lr_color", "lr_opacity", "lr_position", "init_opacity", "regularizer",
                     "lr_appearance", "appearance_prior"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if not 0 < self.decay <= 1:
            raise ValueError("decay must be in (0, 1]")
        if self.background is not None and self.background != "learn" and \
                (isinstance(self.background, str) or len(self.background) != 3):
            raise ValueError(f"background must be None, 'learn' or three linear RGB values, "
                             f"got {self.background!r}")
        if self.optimize not in ("volume", "tf", "scalar"):
            raise ValueError(f"optimize must be volume, tf or scalar, got {self.optimize!r}")
        if self.model not in ("emission", "absorption"):
            raise ValueError(f"model must be emission or absorption, got {self.model!r}")
        if self.model == "absorption" and (self.optimize != "volume" or self.background):
            raise ValueError("model absorption fits an attenuation from transmittance images: "
                             "no optimize tf/scalar, no background")
        if self.optimize != "volume" and self.init in INITS:
            raise ValueError(f"optimize {self.optimize} needs the scalar mesh as init (a file)")
        if self.optimize == "scalar" and self.transfer_function is None:
            raise ValueError("optimize scalar needs the transfer function (--tf)")
        if self.tf_init not in ("flat", "random") or int(self.tf_resolution) < 2:
            raise ValueError("tf_init must be flat or random, tf_resolution >= 2")
        if self.scalar_init not in ("colors", "mesh"):
            raise ValueError(f"scalar_init must be colors or mesh, got {self.scalar_init!r}")
        if self.value_range is not None and not (len(self.value_range) == 2 and
                                                 self.value_range[0] < self.value_range[1]):
            raise ValueError(f"value_range must be [lo, hi] with lo < hi, got {self.value_range}")
        if self.select not in ("gradient", "color", "opacity"):
            raise ValueError(f"select must be gradient, color or opacity, got {self.select!r}")
        for i, st in enumerate(self.stage_list()):
            if i and st["grid"] is not None and any(
                    p["split"] or p["prune"] is not None or p["lr_position"]
                    for p in self.stage_list()[:i]):
                raise ValueError("a stage with 'grid' must follow stages that keep the grid "
                                 "(no split, prune or lr_position)")
            bad = sorted(set(st) - {"iterations", "lr_position", "split", "prune", "grid"})
            if bad:
                raise ValueError(f"unknown stage settings {bad}: use iterations, lr_position, "
                                 f"split, prune, grid")
            if st.get("grid") is not None and (self.init not in ("grid", "auto") or int(st["grid"]) < 1):
                raise ValueError(f"bad stage {st}: 'grid' needs init 'grid' and a resolution >= 1")
            if int(st.get("iterations", 0)) < 0 or not 0 <= st.get("split", 0) <= 1:
                raise ValueError(f"bad stage {st}: iterations >= 0, split in [0, 1]")

    def stage_list(self):
        """The stages as dicts with all keys (see ``stages``)."""
        raw = self.stages or [{"iterations": self.iterations, "lr_position": self.lr_position}]
        return [{"iterations": int(st.get("iterations", 0)),
                 "lr_position": float(st.get("lr_position", 0.0)),
                 "split": float(st.get("split", 0.0)),
                 "prune": st.get("prune", None), "grid": st.get("grid", None),
                 **{k: v for k, v in st.items()
                    if k not in ("iterations", "lr_position", "split", "prune", "grid")}}
                for st in raw]

    def for_stage(self, i):
        """The settings one stage trains with (its iterations and position rate)."""
        st = self.stage_list()[i]
        return dataclasses.replace(self, iterations=max(st["iterations"], 1),
                                   lr_position=st["lr_position"])


def coarse_to_fine(rounds=3, steps=300, lr_position=0.05, split=0.05, final=None):
    """DiffTetVR's schedule: colors only, then colors and positions, then a
    split of the top ``split`` fraction of vertices; ``rounds`` times, and a
    last colors-only stage of ``final`` steps (default ``steps``)."""
    stages = []
    for _ in range(rounds):
        stages += [{"iterations": steps}, {"iterations": steps, "lr_position": lr_position,
                                           "split": split}]
    return stages + [{"iterations": steps if final is None else final}]
