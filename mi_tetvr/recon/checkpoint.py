"""A run's checkpoint: everything needed to continue it exactly.

One ``.npz`` file holds the mesh (``vertices``, ``tets``) and the fitted
values (``value:<name>``, e.g. ``value:color``), the run's state (``step``, ``stage``,
``stage_start``, ``elapsed``, ``shortened``, the ``history`` and the view-picking ``rng`` as
JSON), the ``config`` (JSON, for the record), a learned ``environment`` and the
photos' color transforms (``appearance``) when fitted, the refinement scores gathered in
the stage (``split_scores``) and Adam's state
(``<key>:t``, ``<key>:m``, ``<key>:v`` per optimized parameter). A run
resumed from it takes the same views, seeds and steps as one that never
stopped.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_tetvr.recon.config import RENAMED, FitConfig
from mi_tetvr.recon.trainer import RunState, Trainer

__all__ = ["save_checkpoint", "load_checkpoint", "check_resume", "RESUMABLE"]


def save_checkpoint(trainer: Trainer, path):
    """Write ``trainer``'s mesh, run state and optimizer state to ``path``
    (``.npz``). Atomic: the file is written next to ``path`` and then moved
    over it, so an interrupted save never corrupts the previous checkpoint."""
    vertices, tets, values = trainer.arrays()
    state = trainer.state
    tmp = Path(path).with_suffix(".tmp.npz")
    np.savez(tmp, vertices=vertices, tets=tets, **{f"value:{k}": v for k, v in values.items()},
             step=state.step,
             stage=state.stage, stage_start=state.stage_start, elapsed=state.elapsed,
             shortened=state.shortened, history=json.dumps(state.history),
             downscale=state.downscale or 0,
             config=json.dumps(trainer.config.flat()),
             rng=json.dumps(state.rng.bit_generator.state), **trainer.opt.state_dict(),
             split_scores=trainer.split_scores(),
             **({} if trainer.environment() is None else {"environment": trainer.environment()}),
             **({} if trainer.appearance() is None else
                {"appearance": trainer.appearance(), **trainer.appearance_opt.state_dict()}))
    tmp.replace(path)


def load_checkpoint(path, dataset, config: FitConfig) -> Trainer:
    """The trainer saved in ``path``, ready to continue.

    Parameters
    ----------
    path : str or Path
        A file written by :func:`save_checkpoint`.
    dataset : mi_tetvr.recon.datasets.Dataset
        The run's data set.
    config : FitConfig
        The run's settings (all stages); the trainer gets those of the saved stage.

    Returns
    -------
    Trainer
        With the saved mesh and parameters, run state (step, stage, history,
        random generator, elapsed time) and Adam moments.
    """
    ckpt = np.load(path)
    rng = np.random.default_rng(config.trainer.seed)
    rng.bit_generator.state = json.loads(str(ckpt["rng"]))
    state = RunState(rng=rng, step=int(ckpt["step"]), stage=int(ckpt["stage"]),
                     stage_start=int(ckpt["stage_start"]), elapsed=float(ckpt["elapsed"]),
                     shortened=int(ckpt["shortened"]), history=json.loads(str(ckpt["history"])),
                     downscale=int(ckpt["downscale"]) or None if "downscale" in ckpt else None)
    values = {k[len("value:"):]: ckpt[k] for k in ckpt.files if k.startswith("value:")}
    trainer = Trainer(dataset, ckpt["vertices"], ckpt["tets"], config.for_stage(state.stage),
                      values, state=state,
                      environment=ckpt["environment"] if "environment" in ckpt else None,
                      appearance=ckpt["appearance"] if "appearance" in ckpt else None)
    trainer.opt.load_state_dict(ckpt)
    if "split_scores" in ckpt:
        trainer.set_split_scores(ckpt["split_scores"])
    if trainer.appearance_index:
        trainer.appearance_opt.load_state_dict(ckpt)
    return trainer


#: Settings a resumed run may change: its time, its length, how often it logs and saves
#: (a stage's steps and position rate are in its checkpointed settings).
RESUMABLE = ("time_budget", "iterations", "lr_position", "checkpoint_every", "log_every",
             "passes")


def check_resume(config: FitConfig, ckpt_path):
    """The settings of the run checkpointed at ``ckpt_path`` (a dict, current names); raise
    ``ValueError`` naming those in which ``config`` differs (other than :data:`RESUMABLE`
    ones and those left to the run): resuming would mix the saved state with other
    settings."""
    saved = {RENAMED.get(k, k): v
             for k, v in json.loads(str(np.load(ckpt_path)["config"])).items()}
    diff = config.differences(saved, ignore=RESUMABLE)
    if diff:
        said = "; ".join(f"{k}: {json.dumps(a)} there, {json.dumps(b)} now"
                         for k, (a, b) in diff.items())
        raise ValueError(f"{ckpt_path.parent} holds a run with other settings ({said}); "
                         f"use the same settings to resume it, --restart to start it over, "
                         f"or another --out")
    return saved
