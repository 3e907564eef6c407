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

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from mi_tetvr.recon.checkpoint import load_checkpoint, save_checkpoint
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.metrics import psnr
from mi_tetvr.recon.plots import plot_history, save_comparison
from mi_tetvr.recon.trainer import Trainer

__all__ = ["run", "next_stage", "write_outputs", "evaluate_mesh", "initial_mesh", "data_bounds"]


def initial_mesh(config: FitConfig, dataset):
    """Vertices (n, 3) and tets (m, 4) of the starting mesh, over
    ``config.bounds`` or the region the data shows (:func:`data_bounds`), or
    read from the file ``config.init``."""
    from mi_tetvr.mesh import initial as initmesh
    from mi_tetvr.mesh.io import read_tetmesh
    init = config.init
    if init not in ("grid", "tetwild", "delaunay"):
        mesh = read_tetmesh(init)
        return mesh.vertices, mesh.tets
    if init == "delaunay":
        if dataset.points is None:
            raise ValueError("init 'delaunay' needs sparse points (a COLMAP data set)")
        return initmesh.delaunay_init(dataset.points)
    bounds = data_bounds(config, dataset)
    if init == "grid":
        return initmesh.grid_init(bounds, config.resolution)
    edge = float(np.max(bounds[1] - bounds[0])) / config.resolution
    return initmesh.tetwild_init(bounds=bounds, edge_length_abs=edge)


def data_bounds(config: FitConfig, dataset):
    """The (2, 3) box to reconstruct in: the config's, else the visual hull of
    the training alpha masks (when the images have alpha), else the data set's."""
    if config.bounds is not None:
        return np.asarray(config.bounds, np.float64).reshape(2, 3)
    from mi_tetvr.recon.hull import visual_hull_bounds
    views = dataset.train
    if views and any(float(v.image[..., 3].min()) < 0.5 for v in views):
        return visual_hull_bounds(views)
    return np.asarray(dataset.bounds(), np.float64)


def run(dataset, out_dir, config: FitConfig, resume=True, progress=True, log=print):
    """Fit, checkpointing to ``out_dir``; returns the final metrics dict.

    Runs ``config``'s stages in order (one stage unless ``config.stages``);
    between stages the mesh may be refined and pruned (:func:`next_stage`).
    A run interrupted (Ctrl-C, or the time budget) still writes the mesh and
    metrics (:func:`write_outputs`); ``resume=True`` continues from
    ``out_dir/checkpoint.npz``. ``progress`` shows a progress bar.
    """
    from tqdm import tqdm

    from mi_tetvr.mesh.topology import build_topology, format_summary, geometry_summary

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.npz"
    stages = config.stage_list()
    if resume and ckpt_path.exists():
        trainer = load_checkpoint(ckpt_path, dataset, config)
        log(f"resumed from {ckpt_path} at step {trainer.state.step} "
            f"(stage {trainer.state.stage + 1})")
    else:
        vertices, tets = initial_mesh(config, dataset)
        log(format_summary(geometry_summary(vertices, build_topology(vertices, tets, warn=False))))
        trainer = Trainer(dataset, vertices, tets, config.for_stage(0))
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2))

    budget = None if config.time_budget is None else 60.0 * config.time_budget
    start = time.perf_counter() - trainer.state.elapsed
    interrupted = False
    bar = tqdm(total=sum(st["iterations"] for st in stages), initial=trainer.state.step,
               disable=not progress, unit="step", dynamic_ncols=True)
    try:
        while True:
            end = trainer.state.stage_start + stages[trainer.state.stage]["iterations"]
            while trainer.state.step < end:
                loss = trainer.step()
                state = trainer.state
                state.elapsed = time.perf_counter() - start
                h = state.history
                h["step"].append(state.step)
                h["time"].append(state.elapsed)
                h["loss"].append(loss)
                h["psnr"].append(psnr(loss) if config.loss == "l2" else float("nan"))
                bar.update(1)
                if state.step % config.log_every == 0 or state.step == 1:
                    recent = float(np.mean(h["loss"][-config.log_every:]))
                    bar.set_postfix(loss=f"{recent:.3g}", tets=f"{len(trainer.tets):,}",
                                    psnr=f"{psnr(recent):.2f}" if config.loss == "l2" else "-")
                if state.step % config.checkpoint_every == 0:
                    save_checkpoint(trainer, ckpt_path)
                if budget is not None and state.elapsed > budget:
                    raise TimeoutError
            if trainer.state.stage + 1 == len(stages):
                break
            trainer = next_stage(trainer, config, log)
            save_checkpoint(trainer, ckpt_path)
    except TimeoutError:
        log(f"time budget of {config.time_budget} min reached at step {trainer.state.step}")
    except KeyboardInterrupt:
        interrupted = True
        log(f"interrupted at step {trainer.state.step}: saving")
    finally:
        bar.close()
        save_checkpoint(trainer, ckpt_path)
    result = write_outputs(trainer, out)
    if interrupted:
        raise KeyboardInterrupt
    return result


def next_stage(trainer: Trainer, config: FitConfig, log=print):
    """After a stage: prune empty tets and split the top vertices as the
    stage says, rebuild the scene, and carry parameters and Adam's moments
    over (new vertices start from their edge's midpoint values). Returns the
    next stage's trainer."""
    from mi_tetvr.mesh.refine import prune_empty, select_top_fraction, split_vertices
    stage = config.stage_list()[trainer.state.stage]
    vertices, tets, color, opacity = trainer.arrays()
    moments = trainer.opt.moments()
    data = {"color": color, "opacity": opacity}
    for k, (_, m, v) in moments.items():
        data[f"{k}:m"], data[f"{k}:v"] = m, v
    split = stage["split"] > 0 and (config.target_tets is None or len(tets) < config.target_tets)
    # Scored on this stage's mesh; pruning only removes vertices of empty tets.
    scores = trainer.vertex_scores(trainer.dataset.train, config.select) if split else None
    if stage["prune"] is not None:
        res = prune_empty(vertices, tets, opacity, float(stage["prune"]) / trainer.h,
                          point_data=data)
        log(f"pruned {len(tets) - len(res.tets):,} empty tets")
        vertices, tets, data = res.vertices, res.tets, res.point_data
        scores = None if scores is None else scores[res.vertex_parent]
    if split:
        selected = select_top_fraction(scores, stage["split"])
        res = split_vertices(vertices, tets, selected, point_data=data)
        log(f"split {len(selected):,} vertices: {len(tets):,} -> {len(res.tets):,} tets")
        vertices, tets, data = res.vertices, res.tets, res.point_data
    # build_topology may re-orient tets but keeps the vertex order: the
    # per-vertex moments carry over directly.
    state = dataclasses.replace(trainer.state, stage=trainer.state.stage + 1,
                                stage_start=trainer.state.step)
    new = Trainer(trainer.dataset, vertices, tets, config.for_stage(state.stage), data["color"],
                  data["opacity"], state=state)
    new.opt.set_moments({k: (t, data[f"{k}:m"], data[f"{k}:v"])
                         for k, (t, _, _) in moments.items()})
    return new


def write_outputs(trainer: Trainer, out: Path):
    """Write ``mesh.vtu``, ``metrics.json``, ``test/*.png`` (render | target)
    and ``progress.png`` to ``out``; returns the metrics."""
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.tetmesh import TetMesh
    vertices, tets, color, opacity = trainer.arrays()
    write_tetmesh(out / "mesh.vtu", TetMesh(vertices, tets, color, opacity))
    views = trainer.dataset.test or trainer.dataset.train[:1]
    metrics = trainer.evaluate(views)
    metrics.update(step=trainer.state.step, seconds=trainer.state.elapsed,
                   vertices=len(vertices), tets=len(tets), inverted_tets=trainer.inverted_tets(),
                   shortened_position_steps=trainer.state.shortened,
                   split="test" if trainer.dataset.test else "train (no test views)")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    renders = out / "test"
    renders.mkdir(exist_ok=True)
    for v in views:
        save_comparison(renders / f"{Path(v.name).stem}.png", trainer.render_view(v), v.image,
                        trainer.config.background)
    plot_history(trainer.state.history, out / "progress.png", metrics["mean"]["psnr"])
    return metrics


def evaluate_mesh(mesh_path, dataset, background=None, n_sub=8, split="test"):
    """Score a mesh file on a data set's views (``split`` test or train):
    PSNR/SSIM per view and their mean (as :meth:`Trainer.evaluate`)."""
    from mi_tetvr.mesh.io import read_tetmesh
    mesh = read_tetmesh(mesh_path)
    cfg = FitConfig(background=background, n_sub=n_sub)
    trainer = Trainer(dataset, mesh.vertices, mesh.tets, cfg, mesh.color, mesh.opacity)
    views = dataset.test if split == "test" and dataset.test else dataset.train
    return trainer.evaluate(views)
