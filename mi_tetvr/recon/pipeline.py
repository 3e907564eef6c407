"""A whole reconstruction (``mi-tetvr fit``): the starting mesh, the stages
with refinement between them, checkpoints, and the outputs.

:func:`run` fits a :class:`~mi_tetvr.recon.config.FitConfig`'s stages one
after the other with a :class:`~mi_tetvr.recon.trainer.Trainer` each;
between stages :func:`next_stage` prunes and splits the mesh and carries the
parameters and Adam's moments over. A run stopped by Ctrl-C or its time
budget still writes its outputs, and the same call resumes it exactly from
its checkpoint (:mod:`mi_tetvr.recon.checkpoint`). Metrics (PSNR, SSIM) are
computed on RGB composited over the data set's background (black when
fitting RGBA).
"""
from __future__ import annotations

import collections
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from mi_tetvr.extras import needs
from mi_tetvr.recon.checkpoint import check_resume, load_checkpoint, save_checkpoint
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.metrics import psnr
from mi_tetvr.recon.outputs import output_seconds, write_outputs
from mi_tetvr.recon.plan import (BUDGET_STEPS, DEFAULT_RESOLUTION, FitPlan, budget_stages,
                                 data_bounds, fit_settings, nominal_step_seconds,
                                 planned_resolution, write_settings)
from mi_tetvr.recon.strategy import (MIN_STAGE_EPOCHS, StageRefinement, affordable,
                                     unbounded_stages)
from mi_tetvr.recon.trainer import RunState, Trainer

__all__ = ["run", "next_stage", "for_capture", "capture_kind", "with_sparse_points",
           "evaluate_mesh", "evaluate_fit", "load_fit", "initial_mesh", "scalar_from_colors",
           "data_warnings", "SH_DEGREE_UNBOUNDED"]


#: The spherical harmonics' degree of an unbounded scene's colors (``sh_degree``
#: left open): none. Measured with 5-minute fits at equal time, degree 2 against one color
#: per vertex, held-out sRGB PSNR, two runs each: the path-traced room at 1/2 -0.35 and
#: -0.83 dB, monstree at 1/4 -0.66 and -0.84 dB (benchmarks/README.md, "View-dependent
#: color in the fit").
SH_DEGREE_UNBOUNDED = 0


def capture_kind(dataset):
    """``object`` when some training pixel is transparent (alpha masks: views
    of an object), else ``unbounded`` (photos of a scene in its surroundings)."""
    if any(float(v.image[..., 3].min()) < 0.5 for v in dataset.train):
        return "object"
    return "unbounded"


def for_capture(config: FitConfig, dataset):
    """The config with what ``scene``, ``init``, ``loss``, ``appearance`` and
    ``background`` leave open decided for the data (see :class:`FitConfig`):
    an unbounded scene starts from its sparse points and far shells
    (``init="unbounded"``), learns its background and a color transform per
    photo, with an L1 loss; an object a grid, L2, no transform."""
    kind = config.data.scene
    if kind == "auto":
        kind = "object" if (config.field.model != "emission" or config.field.optimize != "volume"
                            or config.mesh.init not in ("auto", "unbounded")) \
            else capture_kind(dataset)
    unbounded = kind == "unbounded"
    changes = {"scene": kind}
    if config.mesh.init == "auto":
        changes["init"] = "unbounded" if unbounded else "grid"
    if config.trainer.loss is None:
        changes["loss"] = "l1" if unbounded else "l2"
    if config.field.appearance is None:
        changes["appearance"] = unbounded
    if unbounded and config.field.background is None:
        changes["background"] = "learn"
    if config.field.sh_degree is None and config.kind == "color":
        changes["sh_degree"] = SH_DEGREE_UNBOUNDED if unbounded else 0
    return config.updated(**changes)


def with_sparse_points(dataset, work_dir, progress=True, log=print):
    """The data set with sparse points: its own (a COLMAP model's, those
    seen from at least 3 photos when there are enough of them), else
    triangulated from its training photos and their known poses
    (:func:`mi_tetvr.recon.sfm.triangulate`, cached in
    ``work_dir/sparse_points.npz``)."""
    if dataset.points is not None:
        tracks = dataset.point_track_lengths
        if tracks is not None and np.count_nonzero(tracks >= 3) >= 100:
            keep = tracks >= 3
            colors = None if dataset.point_colors is None else dataset.point_colors[keep]
            return dataclasses.replace(dataset, points=dataset.points[keep], point_colors=colors)
        return dataset
    cache = Path(work_dir) / "sparse_points.npz"
    if cache.is_file():
        data = np.load(cache)
        points, colors = data["points"], data["colors"]
    else:
        from mi_tetvr.recon.sfm import triangulate
        views = _full_resolution(dataset)
        log(f"no sparse points in the data set: triangulating them from the "
            f"{len(views)} training photos ({views[0].camera.width}x"
            f"{views[0].camera.height}) and their poses")
        points, colors, errors, _ = triangulate(views, Path(work_dir) / "sfm",
                                                progress=progress, log=log)
        log(f"{len(points):,} points, mean reprojection error {float(np.mean(errors)):.2f} px")
        np.savez(cache, points=points, colors=colors)
    return dataclasses.replace(dataset, points=points, point_colors=colors)


def _full_resolution(dataset):
    """The training views as their files hold them (features are found in
    the photos, not in the downscaled copies a fit trains on)."""
    from mi_tetvr.recon.datasets import load_dataset
    if dataset.root is None:
        return dataset.train
    try:
        full = load_dataset(dataset.root, holdout=None)
    except (ValueError, FileNotFoundError):
        return dataset.train
    by_name = {v.name: v for v in full.views}
    if not all(v.name in by_name for v in dataset.train):
        return dataset.train
    return [by_name[v.name] for v in dataset.train]


def initial_mesh(config: FitConfig, dataset):
    """Vertices (n, 3), tets (m, 4) and starting values (a dict, or None for
    the field's defaults) of the starting mesh, over ``config.mesh.bounds`` or the
    region the data shows (:func:`data_bounds`), or read from the file
    ``config.mesh.init`` (with its scalar field, ``config.mesh.scalar``, when a
    transfer function or a scalar is fitted)."""
    from mi_tetvr.mesh import initial as initmesh
    from mi_tetvr.mesh.io import choose_scalar, read_tetmesh
    if config.mesh.init == "auto":
        config = for_capture(config, dataset)
    init = config.mesh.init
    if init == "unbounded":
        return unbounded_mesh(config, dataset)
    if init not in ("grid", "tetwild", "delaunay"):
        if config.field.optimize == "volume":
            mesh = read_tetmesh(init, repair=config.mesh.repair,
                                cell_to_point=config.mesh.cell_to_point)
            return mesh.vertices, mesh.tets, None
        mesh = read_tetmesh(init, color=None, opacity=None, repair=config.mesh.repair,
                            cell_to_point=config.mesh.cell_to_point)
        if config.field.optimize == "scalar" and config.field.scalar_init == "colors" and \
                config.field.value_range is not None:
            return mesh.vertices, mesh.tets, None     # the scalar comes from the colors
        name = choose_scalar(mesh.point_data, config.mesh.scalar, init, mesh.cell_data)
        return mesh.vertices, mesh.tets, {"scalar": np.asarray(mesh.point_data[name],
                                                               np.float64).reshape(-1)}
    if init == "delaunay":
        if dataset.points is None:
            raise ValueError("init 'delaunay' needs sparse points (a COLMAP data set)")
        return (*initmesh.delaunay_init(dataset.points), None)
    bounds = data_bounds(config.mesh, dataset)
    resolution = config.stage_list()[0]["grid"] or config.mesh.grid_resolution or DEFAULT_RESOLUTION
    if init == "grid":
        return (*initmesh.grid_init(bounds, resolution), None)
    edge = float(np.max(bounds[1] - bounds[0])) / resolution
    return (*initmesh.tetwild_init(bounds=bounds, edge_length_abs=edge), None)


def unbounded_mesh(config: FitConfig, dataset):
    """The starting mesh of an unbounded scene (:func:`mi_tetvr.mesh.initial
    .unbounded_init` of the data set's sparse points and its cameras), the
    vertices at points starting from the points' colors, the shells' from the
    photos' mean color."""
    with needs("recon", "the fit's mesh from points"):
        from scipy.spatial import cKDTree

    from mi_tetvr.color import srgb_to_linear
    from mi_tetvr.mesh.initial import unbounded_init
    if dataset.points is None or len(dataset.points) < 4:
        raise ValueError("init 'unbounded' needs sparse points (a COLMAP model, or photos "
                         "with poses to triangulate them from)")
    centers = np.array([v.camera.center for v in dataset.views])
    vertices, tets, is_shell = unbounded_init(dataset.points, centers, seed=config.trainer.seed,
                                              outer=config.mesh.outer)
    mean = np.mean([v.image[..., :3].reshape(-1, 3).mean(0) for v in dataset.train], 0)
    color = np.tile(mean, (len(vertices), 1))
    if dataset.point_colors is not None:
        d, i = cKDTree(dataset.points).query(vertices[~is_shell])
        color[~is_shell] = srgb_to_linear(np.asarray(dataset.point_colors, np.float64)[i] / 255)
    return vertices, tets, {"color": np.clip(color, 0.0, 1.0)}


def data_warnings(config: FitConfig, dataset):
    """What looks wrong about fitting ``dataset`` with ``config``: photos of a
    scene in its surroundings (no transparent pixel, or cameras inside the
    region fitted) with nothing that models what lies outside the box."""
    if config.field.background == "learn" or config.field.model == "scattering":
        return []       # (a lit medium: the lights' scene holds the surroundings)
    out = []
    if config.field.background is None and all(float(v.image[..., 3].min()) >= 0.999
                                               for v in dataset.train):
        out.append("every training pixel is opaque, yet the fit matches alpha (background "
                   "none): the volume must explain the surroundings too; for photos of a "
                   "scene in its surroundings try --background learn")
    lo, hi = data_bounds(config.mesh, dataset)
    inside = [v.name for v in dataset.train
              if np.all((v.camera.center >= lo) & (v.camera.center <= hi))]
    if inside:
        out.append(f"{len(inside)} camera(s) inside the fitted box ({', '.join(inside[:3])}"
                   f"{', ...' if len(inside) > 3 else ''}): the scene looks unbounded; "
                   f"--background learn models what lies outside the box")
    return out


class _Clock:
    """Where a time-budgeted run stands: the run ends at ``end``, the
    optimization ``reserve`` seconds earlier (the outputs of the stage's mesh,
    :func:`output_seconds`); each stage gets the share of what is left that
    its ``iterations`` weigh among the stages still to run."""

    def __init__(self, end, weights, now=time.perf_counter):
        self.end, self.weights, self.now = end, weights, now
        self.stage_begin = self.stage_end = None
        self.reserve = 0.0          # seconds the outputs of the current mesh take

    def begin_stage(self, stage, reserve):
        self.reserve = reserve
        now = self.now()
        left = max(self.end - reserve - now, 0.0)
        share = self.weights[stage] / max(sum(self.weights[stage:]), 1e-9)
        self.stage_begin, self.stage_end = now, now + left * share

    def progress(self):
        now = self.now()
        return (now - self.stage_begin) / max(self.stage_end - self.stage_begin, 1e-9)


def run(dataset, out_dir, config: FitConfig, resume=True, progress=True, log=print,
        now=time.perf_counter, viewer=None):
    """Fit, checkpointing to ``out_dir``; returns the final metrics dict.

    Runs ``config``'s stages in order (one stage unless ``config.strategy.stages``);
    between stages the mesh may be refined and pruned (:func:`next_stage`).
    With ``config.trainer.time_budget`` the whole call (steps, outputs) takes that long
    (a resumed run gets the budget again, for more steps): the grid resolution,
    unless set, is planned from the data and the budget (:func:`planned_resolution`,
    no clock read: the same mesh on any machine), a coarse grid trains first
    (:func:`budget_stages`),
    the steps fill the time left after the outputs, and the learning rates
    decay over each stage's share of it.
    A run interrupted (Ctrl-C) still writes the mesh and metrics
    (:func:`write_outputs`); ``resume=True`` continues from
    ``out_dir/checkpoint.npz``. ``progress`` shows a progress bar. ``now`` is
    the clock the time budget is kept by (seconds; tests pass a simulated one).
    ``viewer``: a function of the trainer that returns a
    :class:`~mi_tetvr.apps.viewer.FitViewer` (``fit --viewer``): it renders
    the mesh between steps, within its share of the time, and is stopped at
    the end.
    """
    t_start = now()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if config.linear_solver:
        # X-ray projections: the linear problem, solved as such
        from mi_tetvr.recon.tomography import LinearCourse
        course = LinearCourse(dataset, out, config, resume, progress, log, now)
    else:
        course = _Loop.start(dataset, out, config, resume, progress, log, now, t_start, viewer)
    write_settings(out, config, course.config, **course.said)
    interrupted = False
    try:
        course.run()
    except KeyboardInterrupt:
        if course.trainer is None:
            raise
        interrupted = True
        log(f"interrupted at step {course.trainer.state.step}: saving")
    finally:
        course.close()
    trainer, optimization = course.trainer, now() - course.train_begin
    result = write_outputs(trainer, out)
    result.update(course.metrics(optimization))
    result["optimization_seconds"] = optimization
    result["wall_seconds"] = now() - t_start
    (out / "metrics.json").write_text(json.dumps(result, indent=2))
    if interrupted:
        raise KeyboardInterrupt
    return result


def prepare(dataset, out: Path, config: FitConfig, resume=True, budget=None, progress=True,
            log=print):
    """What a fit starts from: the config with what it leaves open decided for the data
    (:func:`for_capture`, the stages, the box, the grid for the time ``budget`` in
    seconds), the data set (with sparse points where the mesh is made of them) and the
    first trainer, or the one checkpointed in ``out`` (``resume``). Returns
    ``(config, dataset, trainer)``."""
    ckpt_path = out / "checkpoint.npz"
    config = for_capture(config, dataset)
    saved = check_resume(config, ckpt_path) if resume and ckpt_path.exists() else None
    if config.mesh.init in ("unbounded", "delaunay"):
        dataset = with_sparse_points(dataset, out, progress, log)
        if config.strategy.stages is None and config.mesh.init == "unbounded":
            config = config.updated(stages=unbounded_stages(config, dataset))
    if config.mesh.bounds is None and config.mesh.init in ("grid", "tetwild"):
        # the region once (a visual hull is carved from every view): the plan,
        # limits, warnings, the mesh and each grid stage read it, config.json keeps it
        config = config.replaced(bounds=data_bounds(config.mesh, dataset).tolist())
    if saved is None:
        config, trainer = first_trainer(dataset, config, budget, progress, log)
        return config, dataset, trainer
    plan = FitPlan.read(out)
    if plan is not None:
        # what the run decided when it began (the mesh sizes and stages among them)
        config = plan.applied(config)
    elif config.mesh.grid_resolution is None and config.strategy.stages is None:
        # a fit written before plans were kept apart: its checkpoint's settings
        config = config.replaced(grid_resolution=saved["grid_resolution"],
                                 stages=saved["stages"])
    trainer = load_checkpoint(ckpt_path, dataset, config)
    log(f"resumed from {ckpt_path} at step {trainer.state.step} "
        f"(stage {trainer.state.stage + 1})")
    return config, dataset, trainer


def first_trainer(dataset, config: FitConfig, budget=None, progress=True, log=print):
    """The trainer of a new run's first stage on its starting mesh (:func:`initial_mesh`,
    a grid planned for the time ``budget`` in seconds when it is not set: no clock is
    read), and the config
    with the sizes and ranges it chose. Returns ``(config, trainer)``."""
    from mi_tetvr.mesh.topology import build_topology, format_summary, geometry_summary
    for text in data_warnings(config, dataset):
        log(f"warning: {text}")
    if config.mesh.grid_resolution is None and config.mesh.init in ("grid", "tetwild"):
        resolution = DEFAULT_RESOLUTION
        if budget is not None:
            resolution = planned_resolution(config, dataset, 0.85 * budget)
            log(f"plan: grid {resolution}, {BUDGET_STEPS} steps of "
                f"{nominal_step_seconds(config, dataset, resolution):.3f} s on the reference "
                f"machine in {0.85 * budget / 60:.1f} min (the budget ends the run: a faster "
                f"machine takes more steps)")
        config = config.replaced(grid_resolution=resolution)
        if budget is not None and config.mesh.init == "grid" and config.strategy.stages is None:
            config = config.updated(stages=budget_stages(config, resolution))
            log("stages: " + " -> ".join(f"grid {st['grid']}" for st in config.strategy.stages))
    vertices, tets, values = initial_mesh(config, dataset)
    if values is not None and "scalar" in values and config.field.value_range is None:
        # recorded in config.json: the range the transfer function spans
        s = values["scalar"]
        config = config.replaced(value_range=[float(s.min()), float(s.max())])
    topology = build_topology(vertices, tets)      # once: the summary and the trainer's
    log(format_summary(geometry_summary(vertices, topology)))
    if config.field.optimize == "scalar" and config.field.scalar_init == "colors":
        values = {"scalar": scalar_from_colors(config, dataset, vertices, tets, progress, log)}
    return config, Trainer(dataset, vertices, tets, config.for_stage(0), values,
                           topology=topology)


class _Loop:
    """A run's steps, stage after stage (:func:`next_stage` between them): the
    progress bar, log lines, checkpoints, the viewer's hook (``live``) and, with a time
    budget, the :class:`_Clock` that ends each stage.

    It is the course of a fit whose trainer steps (Adam); an X-ray fit's linear solver
    is another (:class:`~mi_tetvr.recon.tomography.LinearCourse`). :func:`run` runs
    either the same way: ``config`` (what the run decided) and ``said`` (its budget, for
    the plan) before; ``run()`` and ``close()``; then ``trainer`` (the fit, which the
    outputs are written from), ``train_begin`` and ``metrics(seconds)`` (what the
    course adds to the metrics)."""

    @classmethod
    def start(cls, dataset, out, config, resume, progress, log, now, t_start, viewer=None):
        """The course of a new or resumed run (:func:`prepare`), its clock set for a time
        budget, its viewer open."""
        ckpt_path = out / "checkpoint.npz"
        resuming = resume and ckpt_path.exists()
        budget = None if config.trainer.time_budget is None else 60.0 * config.trainer.time_budget
        asked = config
        # (a resumed run keeps what its plan said of the budget it began with)
        earlier = FitPlan.read(out) if resuming else None
        config, dataset, trainer = prepare(dataset, out, config, resume, budget, progress, log)
        loop = cls(trainer, config, ckpt_path, progress, log, now)
        if earlier is not None:
            loop.said = dict(budget_seconds=earlier.budget_seconds,
                             planned_steps=earlier.planned_steps,
                             step_seconds=earlier.step_seconds)
        elif budget is not None and asked.mesh.grid_resolution is None and \
                config.mesh.grid_resolution is not None and not resuming:
            loop.said = dict(budget_seconds=budget, planned_steps=BUDGET_STEPS,
                             step_seconds=nominal_step_seconds(config, dataset,
                                                               config.mesh.grid_resolution))
        else:
            loop.said = dict(budget_seconds=budget)
        if budget is not None:
            loop.clock = _Clock(t_start + budget,
                                [max(st["iterations"], 1) for st in loop.stages], now)
            loop.clock.begin_stage(trainer.state.stage, output_seconds(trainer, now))
        loop.live = viewer(trainer) if viewer is not None else None
        return loop

    def metrics(self, seconds):
        if self.clock:
            self.log(f"time budget: {self.trainer.state.step - self.steps_begin} steps in "
                     f"{seconds:.0f} s")
        return {}

    def __init__(self, trainer, config, ckpt_path, progress, log, now):
        self.trainer, self.config, self.ckpt_path = trainer, config, ckpt_path
        self.log, self.now, self.progress = log, now, progress
        self.stages = config.stage_list()
        self.clock = self.live = self.bar = None
        self.between = 0.0          # seconds the last change of stage took (no steps)
        self.steps_begin, self.train_begin = trainer.state.step, now()
        self.seconds = trainer.state.elapsed
        # sRGB MSE of the last steps (the PSNR the bar shows)
        self.recent_mse = collections.deque(maxlen=config.trainer.log_every)

    def run(self):
        self.bar = self._bar()
        self.steps_begin, self.train_begin = self.trainer.state.step, self.now()
        while True:
            self.train_stage()
            if self.trainer.state.stage + 1 == len(self.stages):
                return
            t0 = self.now()
            self.trainer = self.refine()
            if self.live is not None:
                self.live.set_trainer(self.trainer)
            if self.clock:
                self.clock.begin_stage(self.trainer.state.stage,
                                       output_seconds(self.trainer, self.now))
            save_checkpoint(self.trainer, self.ckpt_path)
            self.between = self.now() - t0

    def refine(self):
        """The next stage's trainer (:func:`next_stage`), with the training PSNR on whole
        photos before and after the mesh changed (:meth:`Trainer.training_psnr
        <mi_tetvr.recon.trainer.Trainer.training_psnr>`) logged and kept in the history
        (``refinements``: step, seconds of training, before, after)."""
        before = self.trainer.training_psnr()
        max_tets, downscale = self.affordable() if self.clock else (None, None)
        trainer = next_stage(self.trainer, self.config, self.log,
                             StageRefinement(self.config, max_tets), downscale)
        after = trainer.training_psnr()
        if before is not None:
            trainer.state.history.setdefault("refinements", []).append(
                [trainer.state.step, trainer.state.elapsed, before, after])
            self.log(f"training PSNR on whole photos across the change: {before:.2f} -> "
                     f"{after:.2f} dB")
        return trainer

    def affordable(self):
        """What the next stage can afford in its share of the time left
        (:func:`~mi_tetvr.recon.strategy.affordable`): at most so many tets, and whether it
        keeps this stage's photo scale. ``(None, None)`` before 5 steps of this stage."""
        trainer, clock = self.trainer, self.clock
        i, times = trainer.state.stage, trainer.state.history["time"]
        done = trainer.state.step - trainer.state.stage_start
        if done < 5:
            return None, None
        step_seconds = float(np.median(np.diff(times[-min(done, 20):])))
        left = max(clock.end - clock.reserve - self.now(), 0.0)
        # (less what the last change of stage took: the refinement, the new trainer, the
        # outputs' estimate and the checkpoint)
        share = clock.weights[i + 1] / max(sum(clock.weights[i + 1:]), 1e-9)
        seconds = max(left * share - self.between, 0.0)
        steps = MIN_STAGE_EPOCHS * len(trainer.dataset.train) / trainer.photos_per_step
        max_tets, held = affordable(len(trainer.tets), step_seconds, seconds, steps,
                                    trainer.downscale, self.stages[i + 1]["downscale"])
        if held:
            self.log(f"the time left keeps the photos at 1/{held} for the next stage")
        return max_tets, held

    def _bar(self):
        from mi_tetvr.progress import progress_bar as tqdm
        if self.clock:
            total = round(max(self.clock.end - self.clock.reserve - self.now(), 0.0))
            return tqdm(total=total, disable=not self.progress, unit="s", dynamic_ncols=True,
                        bar_format="{l_bar}{bar}| {n:.0f}/{total} s [{elapsed}{postfix}]")
        return tqdm(total=sum(st["iterations"] for st in self.stages),
                    initial=self.trainer.state.step, disable=not self.progress, unit="step",
                    dynamic_ncols=True)

    def train_stage(self):
        """The steps of the trainer's stage: until its iterations, or its share of the time."""
        trainer, clock = self.trainer, self.clock
        end = trainer.state.stage_start + self.stages[trainer.state.stage]["iterations"]
        while (clock.progress() < 1.0) if clock else (trainer.state.step < end):
            t0 = self.now()
            loss, mse = trainer.step(clock.progress() if clock else None)
            dt = self.now() - t0
            self.seconds += dt
            trainer.state.elapsed = self.seconds
            self.after_step(loss, mse, dt)

    def after_step(self, loss, mse, dt):
        """The step recorded: history, progress bar, checkpoint, viewer, time estimate."""
        trainer, config = self.trainer, self.config
        state, h = trainer.state, trainer.state.history
        h["step"].append(state.step)
        h["time"].append(state.elapsed)
        h["loss"].append(loss)
        h["psnr"].append(psnr(mse))
        self.recent_mse.append(mse)
        # (seconds, at most to the bar's end: a stage's last step may end past its share,
        # and a bar past its total no longer shows one)
        self.bar.update(min(dt, max(self.bar.total - self.bar.n, 0.0)) if self.clock else 1)
        if state.step % config.trainer.log_every == 0 or state.step == 1:
            self.bar.set_postfix(step=state.step, loss=f"{loss:.3g}",
                                 psnr=f"{psnr(float(np.mean(self.recent_mse))):.2f}",
                                 tets=f"{len(trainer.tets):,}")
        if state.step % config.trainer.checkpoint_every == 0:
            save_checkpoint(trainer, self.ckpt_path)
        if self.live is not None:
            self.live.after_step(trainer, loss, h["psnr"][-1], self.stage_text())
        if self.clock is None and state.step == self.steps_begin + 5:
            rate = (self.now() - self.train_begin) / 5
            total = sum(st["iterations"] for st in self.stages) - self.steps_begin
            self.log(f"estimated time: {rate * total / 60:.1f} min "
                     f"({rate:.2f} s per step; --time-budget fits the run to a time)")

    def stage_text(self):
        st = self.stages[self.trainer.state.stage]
        grid = f", grid {st['grid']}" if st.get("grid") else ""
        return (f"stage {self.trainer.state.stage + 1} of {len(self.stages)}{grid}: "
                f"{len(self.trainer.tets):,} tets")

    def close(self):
        """The last checkpoint; the bar and the viewer stopped."""
        if self.bar is not None:
            self.bar.close()
        save_checkpoint(self.trainer, self.ckpt_path)
        if self.live is not None:
            self.live.stop()


def scalar_from_colors(config: FitConfig, dataset, vertices, tets, progress=True, log=print):
    """The start of a scalar fit under a known transfer function (DiffDVR's
    remedy for its non-convexity, :mod:`mi_tetvr.recon.density`): per-vertex
    colors and opacities fitted on the mesh for ``config.trainer.iterations`` steps,
    then the scalar whose classified color matches them. Returns (n,) float."""
    from mi_tetvr.progress import progress_bar as tqdm

    from mi_tetvr.recon.density import match_scalars
    from mi_tetvr.recon.fields import ScalarField
    colors = Trainer(dataset, vertices, tets,
                     config.replaced(optimize="volume", stages=None),
                     state=RunState(rng=np.random.default_rng(config.trainer.seed + 2)))
    for _ in tqdm(range(config.trainer.iterations), desc="colors first", disable=not progress):
        colors.step()
    _, oriented, values = colors.arrays()
    lo, hi = config.field.value_range
    # the known transfer function in world units, as the scalar fit will use it
    field = ScalarField(config.field, colors.h, radius=colors.radius)
    scalar = match_scalars(values["color"], values["opacity"],
                           field.transfer_function(field.fixed), (lo, hi), oriented, colors.h)
    psnr_colors = colors.evaluate(dataset.test or dataset.train[:1])["mean"]["psnr"]
    log(f"colors first: {config.trainer.iterations} steps (held-out PSNR {psnr_colors:.2f} "
        f"dB), then the scalars their colors match")
    return scalar


def next_stage(trainer: Trainer, config: FitConfig, log=print, strategy=None, downscale=None):
    """After a stage: the mesh changed by ``strategy`` (default: the stages' own,
    :class:`~mi_tetvr.recon.strategy.StageRefinement`), the next stage's trainer on it
    with the run's state, the learned background and color transforms, and Adam's
    moments carried over (in the field's layout: a higher degree of spherical
    harmonics starts from zero); its photos area-averaged by ``downscale`` (None: the
    stage's own). Returns the next stage's trainer."""
    strategy = strategy or StageRefinement(config)
    vertices, tets, values, moments = strategy.refine(trainer, log)
    state = dataclasses.replace(trainer.state, stage=trainer.state.stage + 1,
                                stage_start=trainer.state.step, downscale=downscale)
    new = Trainer(trainer.dataset, vertices, tets, config.for_stage(state.stage), values,
                  state=state, environment=trainer.environment(),
                  appearance=trainer.appearance())
    if moments:
        adopt = new.field.adopt_moments
        new.opt.set_moments({k: (t, adopt(k, m), adopt(k, v))
                             for k, (t, m, v) in moments.items()})
    return new


def evaluate_mesh(mesh_path, dataset, background=None, n_sub=4, split="test", repair=False,
                  cell_to_point=False):
    """Score a mesh file with ``color`` and ``opacity`` point arrays on a data set's views
    (``split`` test or train): PSNR/SSIM per view and their mean (as
    :meth:`Trainer.evaluate`). A mesh without them (an attenuation, a scalar) is an error
    that points to :func:`evaluate_fit`."""
    from mi_tetvr.mesh.io import read_tetmesh
    mesh = read_tetmesh(mesh_path, color=None, opacity=None, repair=repair,
                        cell_to_point=cell_to_point)
    missing = [k for k in ("color", "opacity") if k not in mesh.point_data]
    if missing:
        raise ValueError(
            f"{mesh_path} has no {' and no '.join(repr(k) for k in missing)} point array "
            f"(it holds {sorted(mesh.point_data) or 'no point arrays'}): a mesh fitted with "
            f"--model absorption or --optimize scalar/tf is scored from its fit folder, "
            f"mi-tetvr eval FIT_DIR DATA")
    n = len(mesh.vertices)
    values = {"color": np.asarray(mesh.point_data["color"], np.float64).reshape(n, -1)[:, :3],
              "opacity": np.asarray(mesh.point_data["opacity"], np.float64).reshape(n)}
    cfg = FitConfig(background=background, n_sub=n_sub)
    if "sh" in mesh.point_data:
        # view-dependent colors (as the fit writes them, beside their mean color)
        values["sh"] = np.asarray(mesh.point_data["sh"], np.float64).reshape(n, -1)
        cfg = cfg.updated(sh_degree=int(round(np.sqrt(values["sh"].shape[1] / 3))) - 1)
    trainer = Trainer(dataset, mesh.vertices, mesh.tets, cfg, values)
    views = dataset.test if split == "test" and dataset.test else dataset.train
    return {**trainer.evaluate(views), "scored": "sRGB"}


def load_fit(fit_dir, data, downscale=None, holdout=8):
    """The fit in ``fit_dir`` (its checkpoint, with its settings) on the data set ``data``
    (a path, loaded at the fit's downscale unless given): a :class:`Trainer`."""
    from mi_tetvr.recon.datasets import load_dataset
    fit_dir = Path(fit_dir)
    ckpt, saved = fit_dir / "checkpoint.npz", fit_dir / "config.json"
    if not ckpt.is_file() or not saved.is_file():
        raise FileNotFoundError(f"{fit_dir} is not a fit's output folder (it has no "
                                f"checkpoint.npz and config.json); give the folder a fit "
                                f"wrote (mi-tetvr fit DATA -o FOLDER)")
    config = fit_settings(fit_dir)
    dataset = load_dataset(data, downscale=downscale or config.data.downscale, holdout=holdout)
    return load_checkpoint(ckpt, dataset, config)


def evaluate_fit(fit_dir, data, split="test", downscale=None, holdout=8, images=None):
    """Score what a fit in ``fit_dir`` fitted (its checkpoint: colors and opacities, an
    attenuation, a scalar or a transfer function, with its background and settings) on
    the data set ``data`` (:func:`load_fit`), as the fit scores itself: PSNR/SSIM per view
    and their mean, ``scored`` says of what. ``images``: a folder that gets a PNG per view
    (:func:`~mi_tetvr.recon.outputs.write_view_panels`: render | target | the fit's
    uncertainty where ``mi-tetvr uncertainty`` wrote it)."""
    trainer = load_fit(fit_dir, data, downscale, holdout)
    dataset = trainer.dataset
    views = dataset.test if split == "test" and dataset.test else dataset.train
    if images is not None:
        from mi_tetvr.recon.outputs import write_view_panels
        write_view_panels(trainer, views, Path(images), Path(fit_dir) / trainer.field.fitted_file)
    return {**trainer.evaluate(views), "scored": trainer.field.scored}
