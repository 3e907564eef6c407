"""What a fit decides from its data before it trains: the box to reconstruct in
(:func:`data_bounds`), the range of grid resolutions the photos support
(:func:`resolution_limits`) and, for a time budget, the grid and its stages
(:func:`planned_resolution`, :func:`budget_stages`). Nothing here reads a clock:
the same data and budget give the same plan on a busy machine and an idle one.

A fit's folder keeps what the user asked for (``config.json``) apart from what the run
decided (:class:`FitPlan`, ``plan.json``); :func:`fit_settings` reads both back.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mi_tetvr.recon.config import PART_OF, FitConfig, MeshSettings, same_setting

__all__ = ["FitPlan", "fit_settings", "write_settings", "data_bounds", "resolution_limits",
           "nominal_step_seconds", "planned_resolution", "budget_stages", "DEFAULT_RESOLUTION",
           "BUDGET_STEPS", "STEP_COST", "KIND_COST", "COARSE_SHARE", "RESOLUTION_RANGE",
           "PIXELS_PER_VERTEX"]


#: Grid resolution without a time budget.
DEFAULT_RESOLUTION = 32
#: Steps a time-budgeted run plans for when it picks its mesh size, at the reference
#: machine's speed (:data:`STEP_COST`): enough for every training view to be seen many
#: times and the learning rates to decay. The plan comes from the data and the budget,
#: never from a clock: a faster machine gets more steps on the same mesh, a busy one
#: fewer. (Measured on the engine CT with a 2-minute budget: planning 1,000 steps of 4
#: views picked a 12-cell grid, 23.6 dB; of 2 views a 54-cell grid, 32.5 dB.)
BUDGET_STEPS = 500
#: Seconds of one optimizer step of an emission fit on the reference machine (a 2-core
#: CPU, ``llvm_ad_rgb``): fixed, per ray, per ray and grid cell along the box's largest
#: axis, per tet (:func:`nominal_step_seconds`). Fitted to the step times of ten grids
#: (12 to 96 cells) on two data sets, the default volume's 2 views of 64x64 and the Lego's
#: of 200x200: within 16 % of each (benchmarks/README.md, "A plan from the data").
STEP_COST = (0.021, 1.46e-7, 2.33e-8, 6.6e-8)
#: A step of these kinds of fit against an emission step on the same grid and photos
#: (scattering: path traced by ``tetpath``, 9-10x measured at 64x64 on grids 12 and 24).
KIND_COST = {"scattering": 10.0}
#: A time-budgeted run without a set resolution trains a grid of half the
#: chosen resolution for this share of its steps, then the chosen grid starting
#: from the coarse one's field (:func:`budget_stages`; benchmarks/README.md, the
#: budgeted default fit's C60 and head runs).
COARSE_SHARE = 0.25
#: The range a planned grid resolution is kept in (the upper end also at most the image
#: width over 1.5: finer cells than pixels see nothing more).
RESOLUTION_RANGE = (12, 96)
#: Training pixels per grid vertex at least. A vertex carries 4 unknowns
#: (RGB, opacity) and a pixel gives 3 values (4 with a mask), so 2 pixels per
#: vertex keep the measurements at 1.5-2x the unknowns: the fit is determined
#: by the data. A grid with more unknowns than the views pin down matches the
#: training views and not the others (C60, 48
#: views of 128x128 and a 629k-vertex grid: 41.4 dB on training views, 39.1 dB
#: held out, below a pre-shaded grid of that size). Measured with 10-minute
#: budgets: 2 gives C60 42.53 dB (384k vertices), 4 gave 42.71 dB (192k) but
#: cost the engine 2.2 dB and setup.sh's one-minute job 3.2 dB.
PIXELS_PER_VERTEX = 2


def data_bounds(mesh: MeshSettings, dataset):
    """The (2, 3) box to reconstruct in: the ``mesh`` settings' ``bounds``, else the
    visual hull of the training alpha masks (when the images have alpha), else the data
    set's."""
    if mesh.bounds is not None:
        return np.asarray(mesh.bounds, np.float64).reshape(2, 3)
    from mi_tetvr.recon.hull import visual_hull_bounds
    views = dataset.train
    if views and any(float(v.image[..., 3].min()) < 0.5 for v in views):
        return visual_hull_bounds(views)
    return np.asarray(dataset.bounds(), np.float64)


def nominal_step_seconds(config: FitConfig, dataset, resolution):
    """Seconds of one optimizer step on a grid of ``resolution`` on the reference machine
    (:data:`STEP_COST`): a fixed part, a part per ray, per ray and cell along the box's
    largest axis (the tets a ray crosses), and per tet (the optimizer's update), times
    :data:`KIND_COST` of the fit's kind. It reads no clock: the plan it sizes is the
    same on a busy machine and an idle one."""
    from mi_tetvr.mesh.initial import grid_shape
    pixels = np.mean([v.camera.width * v.camera.height for v in dataset.train])
    rays = config.trainer.rays_per_step if config.trainer.sampling == "rays" else None
    rays = rays or min(config.trainer.views_per_step, len(dataset.train)) * pixels \
        * config.trainer.spp
    tets = 6 * np.prod(grid_shape(data_bounds(config.mesh, dataset), resolution))
    fixed, per_ray, per_ray_cell, per_tet = STEP_COST
    seconds = fixed + rays * (per_ray + per_ray_cell * resolution) + per_tet * tets
    return float(seconds * KIND_COST.get(config.kind, 1.0))


def planned_resolution(config: FitConfig, dataset, seconds, steps=BUDGET_STEPS):
    """The grid resolution of a fit with ``seconds`` of optimization: the finest within
    :func:`resolution_limits` whose ``steps`` steps take at most ``seconds`` on the
    reference machine (:func:`nominal_step_seconds`); the coarsest when none does."""
    lo, hi = resolution_limits(config, dataset)
    fits = [r for r in range(lo, hi + 1)
            if steps * nominal_step_seconds(config, dataset, r) <= seconds]
    return max(fits, default=lo)


def resolution_limits(config: FitConfig, dataset):
    """The range of grid resolutions a time budget may choose from:
    :data:`RESOLUTION_RANGE`, at most the training images' width over 1.5
    (finer cells than pixels see nothing more) and at most
    :data:`PIXELS_PER_VERTEX` training pixels per vertex."""
    from mi_tetvr.mesh.initial import grid_shape
    width = max(max(v.camera.width, v.camera.height) for v in dataset.train)
    pixels = sum(v.camera.width * v.camera.height for v in dataset.train)
    bounds = data_bounds(config.mesh, dataset)
    top = min(RESOLUTION_RANGE[1], int(width / 1.5))
    while top > RESOLUTION_RANGE[0] and \
            np.prod(np.add(grid_shape(bounds, top), 1)) * PIXELS_PER_VERTEX > pixels:
        top -= 1
    return RESOLUTION_RANGE[0], max(RESOLUTION_RANGE[0], top)


def budget_stages(config: FitConfig, resolution):
    """The stages of a time-budgeted run on a grid of ``resolution``: a grid of
    half that resolution for :data:`COARSE_SHARE` of the time, then the full
    one (one stage when the half would be below :data:`RESOLUTION_RANGE`).
    The iterations are time weights."""
    coarse = resolution // 2
    if coarse < RESOLUTION_RANGE[0]:
        return [{"iterations": config.trainer.iterations, "grid": resolution}]
    first = max(1, round(COARSE_SHARE * config.trainer.iterations))
    return [{"iterations": first, "grid": coarse},
            {"iterations": max(1, config.trainer.iterations - first), "grid": resolution}]


@dataclass
class FitPlan:
    """What a run decided for its data where the config left a setting open (``settings``:
    the box, the grid and its stages, the scene's kind and what follows from it, a solver's
    basis, ...), and for a time budget what it planned: the budget in seconds, the steps
    planned and their nominal seconds on the reference machine (:data:`STEP_COST`). A
    fit's folder holds it as ``plan.json`` beside ``config.json`` (what was asked); a
    resumed run reads it back rather than deciding again."""
    settings: dict = field(default_factory=dict)
    budget_seconds: float | None = None
    planned_steps: int | None = None
    step_seconds: float | None = None

    FILE = "plan.json"

    @classmethod
    def between(cls, asked: FitConfig, run: FitConfig, **budget):
        """The plan that turns ``asked`` into ``run``: the settings that differ."""
        a, r = asked.flat(), run.flat()
        return cls({k: v for k, v in r.items() if not same_setting(a[k], v)}, **budget)

    def applied(self, config: FitConfig) -> FitConfig:
        """``config`` (what was asked) with the plan's settings, checked together."""
        unknown = sorted(set(self.settings) - set(PART_OF))
        if unknown:
            raise ValueError(f"a fit's plan with settings a fit does not have: {unknown}")
        run = config.replaced(**self.settings)
        try:
            run.validate()
        except ValueError as e:
            raise ValueError(f"a fit's plan ({self.FILE}) that does not go with its config: "
                             f"{e}") from None
        return run

    def write(self, folder):
        Path(folder, self.FILE).write_text(json.dumps(dataclasses.asdict(self), indent=2))

    @classmethod
    def read(cls, folder):
        """The plan in ``folder``, or None (fits written before plans were kept apart)."""
        path = Path(folder, cls.FILE)
        if not path.is_file():
            return None
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}: not a fit's plan (not JSON: {e})") from None
        names = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(data, dict) or not isinstance(data.get("settings", {}), dict):
            raise ValueError(f"{path}: not a fit's plan (a mapping with 'settings' expected)")
        return cls(**{k: v for k, v in data.items() if k in names})


def write_settings(folder, asked: FitConfig, run: FitConfig, **budget):
    """A fit's ``config.json`` (what was ``asked``, by part) and ``plan.json`` (what the
    ``run`` decided, :meth:`FitPlan.between`); every kind of fit writes them so."""
    folder = Path(folder)
    (folder / "config.json").write_text(json.dumps(asked.nested(run.kind), indent=2))
    plan = FitPlan.between(asked, run, **budget)
    plan.write(folder)
    return plan


def fit_settings(folder) -> FitConfig:
    """The settings a fit in ``folder`` ran with: its ``config.json`` with its
    ``plan.json`` applied (a folder without a plan: its ``config.json`` holds both)."""
    config = FitConfig.from_file(Path(folder) / "config.json")
    plan = FitPlan.read(folder)
    return plan.applied(config) if plan is not None else config
