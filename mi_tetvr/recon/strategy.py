"""What changes the fitted mesh between stages: the fit's *strategy*, as gsplat's
``strategy/`` is for Gaussians.

A :class:`Strategy` takes the trainer of a finished stage and returns the next
stage's mesh with everything that follows its vertices (:class:`VertexState`:
the field's values, Adam's moments, the refinement scores, the cell sizes).
:class:`StageRefinement` is the one the fit uses; in order, as the stage's
settings say (:meth:`FitConfig.stage_list <mi_tetvr.recon.config.FitConfig.stage_list>`):

1. a finer grid (the next stage's ``grid``): the field sampled onto it;
2. a Delaunay tetrahedralization of vertices that moved (:func:`retriangulates`);
3. pruning of empty tets (``prune``: optical depth per cell);
4. splitting at the vertices with the largest image-loss gradients (``split``).

The trainer, the optimizer and the clock are not the strategy's business
(:mod:`mi_tetvr.recon.trainer`, :mod:`mi_tetvr.recon.pipeline`); the schedules
of an unbounded scene's stages is here too (:func:`unbounded_stages`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mi_tetvr.recon.config import FitConfig

__all__ = ["Strategy", "StageRefinement", "VertexState", "retriangulates", "unbounded_stages",
           "UNBOUNDED_PRUNE", "UNBOUNDED_SPLIT", "UNBOUNDED_SPLITS",
           "UNBOUNDED_DOWNSCALE", "COARSE_PIXELS", "affordable", "MIN_STAGE_EPOCHS",
           "TET_COST_EXPONENT", "SPLIT_GROWTH"]

#: An unbounded scene's stages (:func:`unbounded_stages`): after each of the first
#: :data:`UNBOUNDED_SPLITS`, tets empty below this optical depth per cell are pruned and the
#: edges at this fraction of the vertices (largest image-loss gradients) are split; after the
#: others up to the last, only pruned.
UNBOUNDED_PRUNE = 0.01
UNBOUNDED_SPLIT = 0.05
UNBOUNDED_SPLITS = 3
#: The factor each stage's photos are area-averaged by (coarse photos first), at most
#: the photos' shorter side over :data:`COARSE_PIXELS`. Measured on monstree (20 photos of
#: 252x189, 4-minute fits, held-out sRGB PSNR): every stage on the whole photos 18.36 dB
#: (102 steps), the first two at half size 18.71 dB (281 steps), 4, 2, 2, 1 19.10 dB (541
#: steps; benchmarks/README.md).
UNBOUNDED_DOWNSCALE = (4, 2, 2, 1)
COARSE_PIXELS = 40
#: With a time budget, a stage is to get at least this many passes over the training photos
#: (:func:`affordable`): the mesh grows, and the photos get finer, only as far as that allows.
MIN_STAGE_EPOCHS = 5
#: A step's time grows as the tets' count to this power (the tets a ray crosses grow with
#: them; measured on the path-traced room's stages at one photo size: twice the tets, 1.49
#: times the time).
TET_COST_EXPONENT = 0.5
#: The tets a split adds per split fraction of the vertices (splitting the edges at 5 % of
#: the vertices doubled the tets of the room's and monstree's meshes).
SPLIT_GROWTH = 20.0


@dataclass
class VertexState:
    """A mesh and what follows its vertices when it changes.

    Attributes
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    data : dict of (n, ...) arrays
        The field's per-vertex values and Adam's moments (``<key>:m``, ``<key>:v``).
    scores : (n,) float or None
        The refinement scores of the stage (None: no split asked for).
    cell : (n,) float or None
        Each vertex's cell size (the unit of its opacity); None after a split (the
        next stage's trainer measures the cells anew).
    """
    vertices: np.ndarray
    tets: np.ndarray
    data: dict
    scores: np.ndarray | None
    cell: np.ndarray | None

    def keep(self, vertices, tets, data, parent):
        """The state on a mesh whose vertex ``i`` was vertex ``parent[i]``."""
        return VertexState(vertices, tets, data,
                           None if self.scores is None else self.scores[parent], self.cell[parent])


class Strategy:
    """What changes the mesh between stages (the interface).

    ``refine(trainer, log)`` is called when a stage ends, before the next one
    (never after the last); it returns ``(vertices, tets, values, moments)``: the next
    stage's mesh, the field's values on it (a dict), and Adam's ``{key: (t, m, v)}``
    to carry over (``None``: a fresh optimizer).
    """

    def refine(self, trainer, log=print):
        raise NotImplementedError


class StageRefinement(Strategy):
    """The stages' own refinement (see the module docstring), by their settings."""

    def __init__(self, config: FitConfig, max_tets=None):
        #: The strategy's settings (``target_tets``, ``retriangulate``), and the stages.
        self.settings, self.stages = config.strategy, config.stage_list()
        #: The starting mesh's settings (its box and grid: what a grid stage refines).
        self.mesh = config.mesh
        #: Whether a stage that moved the vertices is followed by their Delaunay
        #: tetrahedralization, and its seed.
        self.retriangulates, self.seed = retriangulates(config), config.trainer.seed
        #: The most tets the next stage can afford (:func:`affordable`; None: no limit).
        self.max_tets = max_tets

    def refine(self, trainer, log=print):
        done = trainer.state.stage
        if self.stages[done + 1]["grid"] is not None:
            return self.regrid(trainer, self.stages[done + 1]["grid"], log)
        stage = self.stages[done]
        state, values, moments = self.collect(trainer, stage)
        if stage["lr_position"] > 0 and self.retriangulates:
            state = self.retriangulate(state, done + 1, log)
        if stage["prune"] is not None:
            state = self.prune(state, trainer.field.extinction, float(stage["prune"]), log)
        if state.scores is not None:
            fraction = self.affordable_split(len(state.tets), stage["split"], log)
            if fraction > 0:
                state = self.split(state, fraction, log)
        values.update({k: state.data[k] for k in trainer.field.point_arrays})
        # build_topology may re-orient tets but keeps the vertex order: the
        # per-vertex moments carry over directly.
        moments = {k: (t, state.data[f"{k}:m"], state.data[f"{k}:v"])
                   for k, (t, _, _) in moments.items()}
        return state.vertices, state.tets, values, moments

    def regrid(self, trainer, grid, log):
        """The field sampled onto a finer grid over the same box (no moments)."""
        from mi_tetvr.mesh.initial import grid_init, grid_sample
        from mi_tetvr.recon.plan import data_bounds
        _, _, values = trainer.arrays()
        bounds = data_bounds(self.mesh, trainer.dataset)
        current = self.stages[trainer.state.stage]["grid"] or self.mesh.grid_resolution
        vertices, tets = grid_init(bounds, grid)
        values.update({k: grid_sample(bounds, current, values[k], vertices)
                       for k in trainer.field.point_arrays})
        log(f"grid {current} -> {grid}: {len(tets):,} tets")
        return vertices, tets, values, None

    def collect(self, trainer, stage):
        """The stage's mesh with its per-vertex values, moments and (when it asks for a
        split below ``target_tets``) scores; the field's values; Adam's moments per key."""
        vertices, tets, values = trainer.arrays()
        moments = trainer.opt.moments()
        data = {k: values[k] for k in trainer.field.point_arrays}
        for k, (_, m, v) in moments.items():
            data[f"{k}:m"], data[f"{k}:v"] = m, v
        target = self.settings.target_tets
        split = stage["split"] > 0 and (target is None or len(tets) < target)
        # scored on this stage's mesh; the vertices kept carry their scores
        scores = trainer.split_scores() if split else None
        return VertexState(vertices, tets, data, scores, trainer.cell), values, moments

    def retriangulate(self, state, stage, log):
        """The moved vertices tetrahedralized anew (Delaunay)."""
        from mi_tetvr.mesh.initial import retriangulate
        vertices, tets, data, parent = retriangulate(state.vertices, state.data,
                                                     seed=self.seed + stage)
        log(f"tetrahedralized the moved vertices anew (Delaunay): {len(state.tets):,} -> "
            f"{len(tets):,} tets")
        return state.keep(vertices, tets, data, parent)

    def prune(self, state, extinction, threshold, log):
        """Tets empty below ``threshold`` (optical depth per each vertex's cell) dropped."""
        from mi_tetvr.mesh.refine import prune_empty
        if extinction is None:
            raise ValueError("'prune' needs a fitted extinction (colors and opacities or an "
                             "attenuation)")
        res = prune_empty(state.vertices, state.tets, state.data[extinction] * state.cell,
                          threshold, point_data=state.data)
        log(f"pruned {len(state.tets) - len(res.tets):,} empty tets")
        return state.keep(res.vertices, res.tets, res.point_data, res.vertex_parent)

    def affordable_split(self, tets, fraction, log):
        """The split fraction the next stage can afford (:attr:`max_tets`, :data:`SPLIT_GROWTH`):
        the stage's, less, or none (under an eighth of it)."""
        if self.max_tets is None:
            return fraction
        can = min(fraction, max(self.max_tets / tets - 1.0, 0.0) / SPLIT_GROWTH)
        if can < fraction:
            can = can if can >= fraction / 8 else 0.0
            log(f"the time left affords about {self.max_tets:,.0f} tets: "
                + (f"split {can:.2%} of the vertices, not {fraction:.0%}" if can else "no split"))
        return can

    def split(self, state, fraction, log):
        """The edges at the top ``fraction`` of vertices by score split (new vertices
        start from their edge's midpoint values)."""
        from mi_tetvr.mesh.refine import select_top_fraction, split_vertices
        selected = select_top_fraction(state.scores, fraction)
        res = split_vertices(state.vertices, state.tets, selected, point_data=state.data)
        log(f"split {len(selected):,} vertices: {len(state.tets):,} -> {len(res.tets):,} tets")
        return VertexState(res.vertices, res.tets, res.point_data, None, None)


def retriangulates(config) -> bool:
    """Whether a stage that moved the vertices is followed by their Delaunay
    tetrahedralization (``retriangulate``; by default for meshes born Delaunay)."""
    if config.strategy.retriangulate is not None:
        return bool(config.strategy.retriangulate)
    return config.mesh.init in ("unbounded", "delaunay")


def unbounded_stages(config, dataset):
    """An unbounded scene's stages: one per :data:`UNBOUNDED_DOWNSCALE` entry, of equal
    length (time shares with a budget), on photos area-averaged by its factor (at most the
    shorter side of the smallest photo over :data:`COARSE_PIXELS`), the first
    :data:`UNBOUNDED_SPLITS` followed by pruning and a split of the vertices with the largest
    gradients (cells where the error is), the others but the last by pruning."""
    stages = len(UNBOUNDED_DOWNSCALE)
    total = int(config.trainer.iterations)
    n = max(total // stages, 1)
    side = min(min(v.camera.width, v.camera.height) for v in dataset.train)
    top = max(1, side // COARSE_PIXELS)
    out = []
    for i, k in enumerate(UNBOUNDED_DOWNSCALE):
        st = {"iterations": n if i + 1 < stages else max(total - n * i, 1)}
        if min(k, top) > 1:
            st["downscale"] = int(min(k, top))
        if i + 1 < stages:
            st["prune"] = UNBOUNDED_PRUNE
        if i < UNBOUNDED_SPLITS:
            st["split"] = UNBOUNDED_SPLIT
        out.append(st)
    return out


def affordable(tets, step_seconds, seconds, steps, downscale, next_downscale):
    """``(max_tets, downscale)`` of the next stage under a time budget: the stage is to get
    ``steps`` steps (:data:`MIN_STAGE_EPOCHS` passes over the photos) in its ``seconds``,
    a step costing ``step_seconds`` now (on ``tets`` tets, photos area-averaged by
    ``downscale``), in proportion to the photos' pixels and to the tets to the power
    :data:`TET_COST_EXPONENT`. The next stage's finer photos (``next_downscale``) are
    kept only if their steps fit on the mesh as it is; else it keeps this stage's scale
    (returned; None: its own)."""
    pixels = (downscale / next_downscale) ** 2
    held = None
    if next_downscale < downscale and seconds < steps * step_seconds * pixels:
        held, pixels = downscale, 1.0
    room = seconds / max(steps * step_seconds * pixels, 1e-12)
    return tets * max(room, 0.0) ** (1.0 / TET_COST_EXPONENT), held
