"""Multi-view reconstruction: fit a tet mesh's vertex colors, opacities and
(optionally) positions to images with known cameras (``mi-tetvr fit``).

The loop is the ordinary Mitsuba one: ``mi.traverse`` the scene, an
``mi.ad.Adam`` with one learning rate per parameter kind, ``mi.render`` of a
few views per step, an image loss, ``dr.backward``, ``opt.step()``. Around it:
values kept in range, an exponential learning-rate decay, the tet-quality
regularizer and an inversion safeguard for positions, checkpoints that survive
an interruption, and the outputs (mesh, metrics, test renders, a plot).

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
Metrics (PSNR, SSIM) are computed on RGB composited over the data set's
background (black when fitting RGBA).
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Parameter keys of the fitted mesh in the scene.
MESH_ID = "volume"
K_COLOR = f"{MESH_ID}.vertex_color"
K_OPACITY = f"{MESH_ID}.vertex_opacity"
K_POSITION = f"{MESH_ID}.vertex_positions"


@dataclass
class FitConfig:
    """Settings of a reconstruction (all have working defaults)."""
    init: str = "grid"                 # grid | tetwild | delaunay | path to a mesh file
    resolution: int = 32               # cells along the largest axis (grid, tetwild)
    bounds: list | None = None         # [[x0, y0, z0], [x1, y1, z1]]; default: from the data
    iterations: int = 1500
    time_budget: float | None = None   # minutes; stops in time and still saves
    views_per_step: int = 4
    lr_color: float = 0.02
    lr_opacity: float = 0.05           # optical depth per cell, per step
    lr_position: float = 0.0           # cell sizes per step; 0 = positions fixed
    decay: float = 0.1                 # learning rates fall exponentially to decay * lr
    loss: str = "l2"                   # l1 | l2
    background: list | None = None     # None: fit RGBA; else composite over this color
    init_color: float = 0.5
    init_opacity: float = 0.05         # optical depth per cell
    regularizer: float = 10.0          # weight lambda of the tet-quality term (DiffTetVR
    regularizer_beta: float = 100.0    # Eq. 21, their values); used when positions move
    freeze_boundary: bool = True       # keep boundary vertices fixed when positions move
    safeguard: bool = True             # shorten position steps that would invert a tet
    n_sub: int = 4                     # sub-intervals per tet segment while fitting
    spp: int = 1
    jitter: bool | None = None         # random sub-pixel positions; False: pixel centres (for
                                       # targets rendered through pixel centres); None: False
                                       # for data sets made by make-dataset, else True
    downscale: int = 1
    seed: int = 0
    checkpoint_every: int = 100
    log_every: int = 10
    # Coarse-to-fine: a list of stages run one after the other, each
    # {"iterations": N, "lr_position": x (0: colors and opacities only),
    #  "split": fraction of vertices to refine after the stage,
    #  "prune": opacity threshold (optical depth per cell) to drop empty tets after it}.
    # None: one stage of ``iterations`` steps with ``lr_position``.
    stages: list | None = None
    target_tets: int | None = None     # no more splits once the mesh has this many tets
    select: str = "gradient"           # refinement criterion: gradient | color | opacity

    @classmethod
    def from_file(cls, path):
        """Read a JSON config (keys as the field names; unknown keys are an error)."""
        data = json.loads(Path(path).read_text())
        return cls().updated(**data)

    def updated(self, **kw):
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(kw) - names)
        if bad:
            raise ValueError(f"unknown fit settings {bad}; known: {sorted(names)}")
        cfg = dataclasses.replace(self, **{k: v for k, v in kw.items() if v is not None})
        cfg.validate()
        return cfg

    def validate(self):
        if self.loss not in ("l1", "l2"):
            raise ValueError(f"loss must be 'l1' or 'l2', got {self.loss!r}")
        for name in ("iterations", "views_per_step", "resolution", "n_sub", "spp", "downscale"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1")
        for name in ("lr_color", "lr_opacity", "lr_position", "init_opacity", "regularizer"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if not 0 < self.decay <= 1:
            raise ValueError("decay must be in (0, 1]")
        if self.background is not None and len(self.background) != 3:
            raise ValueError("background must be three linear RGB values")
        if self.select not in ("gradient", "color", "opacity"):
            raise ValueError(f"select must be gradient, color or opacity, got {self.select!r}")
        for st in self.stage_list():
            bad = sorted(set(st) - {"iterations", "lr_position", "split", "prune"})
            if bad:
                raise ValueError(f"unknown stage settings {bad}: use iterations, lr_position, "
                                 f"split, prune")
            if int(st.get("iterations", 0)) < 0 or not 0 <= st.get("split", 0) <= 1:
                raise ValueError(f"bad stage {st}: iterations >= 0, split in [0, 1]")

    def stage_list(self):
        """The stages as dicts with all keys (see ``stages``)."""
        raw = self.stages or [{"iterations": self.iterations, "lr_position": self.lr_position}]
        return [{"iterations": int(st.get("iterations", 0)),
                 "lr_position": float(st.get("lr_position", 0.0)),
                 "split": float(st.get("split", 0.0)),
                 "prune": st.get("prune", None), **{k: v for k, v in st.items() if k not in
                                                    ("iterations", "lr_position", "split",
                                                     "prune")}}
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



def psnr(mse):
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def composite(rgba, background):
    """RGB of a premultiplied RGBA image (h, w, 4) over a constant background."""
    bg = np.zeros(3) if background is None else np.asarray(background, np.float64)
    return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * bg


def image_metrics(pred_rgba, target_rgba, background):
    """PSNR and SSIM of RGB composited over ``background`` (values clipped to [0, 1])."""
    from skimage.metrics import structural_similarity
    a = np.clip(composite(pred_rgba, background), 0, 1)
    b = np.clip(composite(target_rgba, background), 0, 1)
    mse = float(np.mean((a - b) ** 2))
    ssim = float(structural_similarity(a, b, channel_axis=2, data_range=1.0))
    return {"psnr": psnr(mse), "ssim": ssim, "mse": mse}


def pixel_centre_data(dataset):
    """True for data sets rendered through pixel centres (``mi-tetvr
    make-dataset`` writes ``volume_info.json``), whose pixels are point
    samples rather than pixel averages."""
    root = getattr(dataset, "root", None)
    return root is not None and (Path(root) / "volume_info.json").is_file()


def cell_size(vertices, tets):
    """Mean edge length of a tet mesh."""
    e = vertices[tets[:, [0, 0, 0, 1, 1, 2]]] - vertices[tets[:, [1, 2, 3, 2, 3, 3]]]
    return float(np.linalg.norm(e, axis=-1).mean())


def initial_mesh(config: FitConfig, dataset):
    """Vertices and tets of the starting mesh, over ``config.bounds`` or the
    region the data shows (visual hull of the alpha masks, else the sparse
    points, else the cameras' view)."""
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
    """The box to reconstruct in: the config's, else the visual hull of the
    training alpha masks (when the images have alpha), else the data set's."""
    if config.bounds is not None:
        return np.asarray(config.bounds, np.float64).reshape(2, 3)
    from mi_tetvr.mesh.initial import visual_hull_bounds
    views = dataset.train
    if views and any(float(v.image[..., 3].min()) < 0.5 for v in views):
        return visual_hull_bounds(views)
    return np.asarray(dataset.bounds(), np.float64)


class Trainer:
    """One reconstruction: the scene, the optimizer and the state of the run.

    Parameters
    ----------
    dataset : mi_tetvr.recon.datasets.Dataset
        Training and test views (premultiplied linear RGBA images + cameras).
    vertices : (n, 3) float, tets : (m, 4) int
        The mesh to fit (its colors and opacities start from the config).
    config : FitConfig
    color, opacity : optional (n, 3), (n,) starting values (e.g. a resumed run).
    """

    def __init__(self, dataset, vertices, tets, config: FitConfig, color=None, opacity=None):
        import drjit as dr
        import mitsuba as mi

        import mi_tetvr
        from mi_tetvr.mesh.topology import build_topology

        self.dr, self.mi = dr, mi
        self.config = config
        self.dataset = dataset
        self.topology = build_topology(vertices, tets)
        self.tets = self.topology.tets.astype(np.int64)
        self.h = cell_size(vertices, self.tets)
        n = len(vertices)
        if color is None:
            color = np.full((n, 3), config.init_color)
        if opacity is None:
            opacity = np.full(n, config.init_opacity / self.h)
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "tetvr", "n_sub": config.n_sub},
            MESH_ID: mi_tetvr.tetmesh_dict(vertices, self.tets, color, opacity),
        })
        self.params = mi.traverse(self.scene)
        self.jitter = config.jitter if config.jitter is not None else not pixel_centre_data(dataset)
        sampler = "independent" if self.jitter else "stratified"
        self.sensors = {}
        for v in dataset.train + dataset.test:
            d = v.sensor_dict(spp=config.spp, sampler=sampler)
            if not self.jitter:
                d["sampler"]["jitter"] = False
            self.sensors[id(v)] = mi.load_dict(d)
        self.targets = {id(v): mi.TensorXf(np.ascontiguousarray(v.image, np.float32))
                        for v in dataset.train}
        self.boundary = np.unique(self.topology.boundary_faces)
        self.opt = mi.ad.Adam(lr=config.lr_color)
        self.keys = [K_COLOR, K_OPACITY] + ([K_POSITION] if config.lr_position > 0 else [])
        for k in self.keys:
            self.opt[k] = self.params[k]
        self.base_lr = {K_COLOR: config.lr_color, K_OPACITY: config.lr_opacity / self.h,
                        K_POSITION: config.lr_position * self.h}
        self.params.update(self.opt)
        self.regularizer = None
        if config.regularizer > 0 and config.lr_position > 0:
            from mi_tetvr.recon.regularizer import QualityRegularizer
            self.regularizer = QualityRegularizer(self.tets, beta=config.regularizer_beta,
                                                  weight=config.regularizer)
        self.step_index = 0
        self.stage = 0           # index into config.stage_list()
        self.stage_start = 0     # global step at which this stage began
        self.elapsed = 0.0
        self.history = {"step": [], "time": [], "loss": [], "psnr": []}
        self.shortened = 0  # vertices whose step the safeguard shortened, in total
        self.rng = np.random.default_rng(config.seed)

    # -- one step ---------------------------------------------------------------
    def learning_rates(self):
        frac = min((self.step_index - self.stage_start) / max(self.config.iterations, 1), 1.0)
        return {k: self.base_lr[k] * self.config.decay ** frac for k in self.keys}

    def render(self, view, params=None, seed=0, spp=None):
        """(h, w, 4) tensor: premultiplied RGB and alpha."""
        return self.mi.render(self.scene, params, sensor=self.sensors[id(view)],
                              spp=spp or self.config.spp, seed=seed, seed_grad=seed + 1)

    def loss_of(self, img, view):
        dr = self.dr
        target = self.targets[id(view)]
        bg = self.config.background
        if bg is None:
            diff = img - target
        else:
            b = self.mi.TensorXf(np.asarray(bg, np.float32))
            alpha_img = img[..., 3:4]
            alpha_tgt = target[..., 3:4]
            diff = (img[..., :3] + (1.0 - alpha_img) * b) - (target[..., :3] + (1.0 - alpha_tgt) * b)
        if self.config.loss == "l1":
            return dr.mean(dr.abs(diff), axis=None)
        return dr.mean(dr.square(diff), axis=None)

    def step(self):
        """One optimizer step over ``views_per_step`` random training views;
        returns the mean image loss."""
        dr = self.dr
        cfg = self.config
        for k, lr in self.learning_rates().items():
            self.opt.set_learning_rate({k: lr})
        train = self.dataset.train
        pick = self.rng.choice(len(train), min(cfg.views_per_step, len(train)), replace=False)
        total = 0.0
        for j, i in enumerate(pick):
            view = train[i]
            seed = (self.step_index * 131 + j * 7919 + cfg.seed * 104729) % (2 ** 31)
            img = self.render(view, self.params, seed=2 * seed)
            loss = self.loss_of(img, view) / len(pick)
            dr.backward(loss)
            total += float(loss.array[0])
        if self.regularizer is not None:
            reg = self.regularizer(self.opt[K_POSITION])
            dr.backward(reg)
        old = np.array(self.opt[K_POSITION]).reshape(-1, 3) if K_POSITION in self.keys else None
        self.opt.step()
        self.opt[K_COLOR] = dr.clip(self.opt[K_COLOR], 0.0, 1.0)
        self.opt[K_OPACITY] = dr.maximum(self.opt[K_OPACITY], 0.0)
        if old is not None:
            self._safe_positions(old)
        self.params.update(self.opt)
        self.step_index += 1
        return total

    def _safe_positions(self, old):
        """Freeze the boundary (optionally) and shorten steps that would
        invert a tet."""
        from mi_tetvr.recon.regularizer import safe_step
        new = np.array(self.opt[K_POSITION], np.float64).reshape(-1, 3)
        delta = new - old
        if self.config.freeze_boundary:
            delta[self.boundary] = 0.0
        if self.config.safeguard:
            delta, n_short = safe_step(old, self.tets, delta)
            self.shortened += int(n_short)
        self.opt[K_POSITION] = self.mi.Float((old + delta).astype(np.float32).ravel())

    # -- state ------------------------------------------------------------------
    def arrays(self):
        """Current (vertices, tets, color, opacity) as numpy arrays."""
        V = np.array(self.params[K_POSITION], np.float64).reshape(-1, 3)
        C = np.array(self.params[K_COLOR], np.float64).reshape(-1, 3)
        S = np.array(self.params[K_OPACITY], np.float64)
        return V, self.tets, C, S

    def inverted_tets(self):
        from mi_tetvr.mesh.topology import signed_volumes
        V, T, _, _ = self.arrays()
        return int((signed_volumes(V, T) <= 0).sum())

    def save_checkpoint(self, path):
        V, T, C, S = self.arrays()
        opt_state = {}
        for k in self.keys:
            t, m, v = self.opt.state[k][3][:3]  # (value, promoted, lr, (t, m, v, v_max))
            opt_state[f"{k}:t"] = np.asarray(t)
            opt_state[f"{k}:m"] = np.array(m)
            opt_state[f"{k}:v"] = np.array(v)
        tmp = Path(path).with_suffix(".tmp.npz")
        np.savez(tmp, vertices=V, tets=T, color=C, opacity=S, step=self.step_index,
                 stage=self.stage, stage_start=self.stage_start,
                 elapsed=self.elapsed, shortened=self.shortened,
                 history=json.dumps(self.history), config=json.dumps(dataclasses.asdict(self.config)),
                 rng=json.dumps(self.rng.bit_generator.state), **opt_state)
        tmp.replace(path)  # atomic: an interrupted save never corrupts the checkpoint

    def load_state(self, ckpt):
        """Restore step count, history, RNG and Adam moments from a checkpoint."""
        mi = self.mi
        self.step_index = int(ckpt["step"])
        self.stage = int(ckpt["stage"])
        self.stage_start = int(ckpt["stage_start"])
        self.elapsed = float(ckpt["elapsed"])
        self.shortened = int(ckpt["shortened"])
        self.history = json.loads(str(ckpt["history"]))
        self.rng.bit_generator.state = json.loads(str(ckpt["rng"]))
        for k in self.keys:
            if f"{k}:m" not in ckpt:
                continue
            value, promoted, lr, extra = self.opt.state[k]
            t = type(extra[0])(int(np.asarray(ckpt[f"{k}:t"]).ravel()[0]))
            m = mi.Float(ckpt[f"{k}:m"].astype(np.float32))
            v = mi.Float(ckpt[f"{k}:v"].astype(np.float32))
            self.opt.state[k] = (value, promoted, lr, (t, m, v, *extra[3:]))

    def moments(self):
        """Adam's moments per vertex: {key: (t, m (n, c), v (n, c))}."""
        n = len(np.array(self.params[K_OPACITY]))
        out = {}
        for k in self.keys:
            t, m, v = self.opt.state[k][3][:3]
            out[k] = (int(np.asarray(t).ravel()[0]), np.array(m).reshape(n, -1),
                      np.array(v).reshape(n, -1))
        return out

    def set_moments(self, moments):
        """Restore per-vertex Adam moments (e.g. interpolated onto a refined mesh)."""
        mi = self.mi
        for k, (t, m, v) in moments.items():
            if k not in self.keys:
                continue
            value, promoted, lr, extra = self.opt.state[k]
            self.opt.state[k] = (value, promoted, lr,
                                 (type(extra[0])(t), mi.Float(m.astype(np.float32).ravel()),
                                  mi.Float(v.astype(np.float32).ravel()), *extra[3:]))

    def vertex_scores(self, views, criterion="gradient"):
        """Per-vertex refinement scores: absolute image-loss gradients summed
        over ``views`` without stepping (AbsGS-style), of colors, opacities
        (in optical depth per cell) or both."""
        dr = self.dr
        n = len(np.array(self.params[K_OPACITY]))
        score = np.zeros(n)
        for j, view in enumerate(views):
            for k in (K_COLOR, K_OPACITY):
                dr.clear_grad(self.opt[k])
            img = self.render(view, self.params, seed=2 * (10 ** 6 + j))
            dr.backward(self.loss_of(img, view))
            if criterion in ("gradient", "color"):
                score += np.abs(np.array(dr.grad(self.opt[K_COLOR]))).reshape(n, 3).sum(1)
            if criterion in ("gradient", "opacity"):
                score += np.abs(np.array(dr.grad(self.opt[K_OPACITY]))) / self.h
        for k in self.keys:
            dr.clear_grad(self.opt[k])
        return score

    # -- evaluation -------------------------------------------------------------
    def render_view(self, view, seed=0):
        """Numpy (h, w, 4) render of a view (no gradients); with jittered
        sampling, 16 samples per pixel approximate the pixel average."""
        spp = 16 if self.jitter else 1
        with self.dr.suspend_grad():
            return np.array(self.render(view, None, seed=seed, spp=spp))

    def evaluate(self, views):
        """Metrics per view and their mean."""
        bg = self.config.background
        per = {}
        for v in views:
            per[v.name] = image_metrics(self.render_view(v), v.image, bg)
        mean = {k: float(np.mean([m[k] for m in per.values()])) for k in ("psnr", "ssim", "mse")}
        return {"views": per, "mean": mean}


def run(dataset, out_dir, config: FitConfig, resume=True, progress=True, log=print):
    """Fit, checkpointing to ``out_dir``; returns the final metrics dict.

    Runs ``config``'s stages in order (one stage unless ``config.stages``);
    between stages the mesh may be refined and pruned (:func:`next_stage`).
    A run interrupted (Ctrl-C, or the time budget) still writes the mesh and
    metrics; ``resume=True`` continues from ``out_dir/checkpoint.npz``.
    """
    from tqdm import tqdm

    from mi_tetvr.mesh.topology import build_topology, format_summary, geometry_summary

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.npz"
    stages = config.stage_list()
    if resume and ckpt_path.exists():
        ckpt = np.load(ckpt_path)
        trainer = Trainer(dataset, ckpt["vertices"], ckpt["tets"],
                          config.for_stage(int(ckpt["stage"])), ckpt["color"], ckpt["opacity"])
        trainer.load_state(ckpt)
        log(f"resumed from {ckpt_path} at step {trainer.step_index} (stage {trainer.stage + 1})")
    else:
        V, T = initial_mesh(config, dataset)
        log(format_summary(geometry_summary(V, build_topology(V, T, warn=False))))
        trainer = Trainer(dataset, V, T, config.for_stage(0))
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2))

    budget = None if config.time_budget is None else 60.0 * config.time_budget
    start = time.perf_counter() - trainer.elapsed
    interrupted = False
    bar = tqdm(total=sum(st["iterations"] for st in stages), initial=trainer.step_index,
               disable=not progress, unit="step", dynamic_ncols=True)
    try:
        while True:
            stage = stages[trainer.stage]
            end = trainer.stage_start + stage["iterations"]
            while trainer.step_index < end:
                loss = trainer.step()
                trainer.elapsed = time.perf_counter() - start
                h = trainer.history
                h["step"].append(trainer.step_index)
                h["time"].append(trainer.elapsed)
                h["loss"].append(loss)
                h["psnr"].append(psnr(loss) if config.loss == "l2" else float("nan"))
                bar.update(1)
                if trainer.step_index % config.log_every == 0 or trainer.step_index == 1:
                    recent = float(np.mean(h["loss"][-config.log_every:]))
                    bar.set_postfix(loss=f"{recent:.3g}", tets=f"{len(trainer.tets):,}",
                                    psnr=f"{psnr(recent):.2f}" if config.loss == "l2" else "-")
                if trainer.step_index % config.checkpoint_every == 0:
                    trainer.save_checkpoint(ckpt_path)
                if budget is not None and trainer.elapsed > budget:
                    raise TimeoutError
            if trainer.stage + 1 == len(stages):
                break
            trainer = next_stage(trainer, config, log)
            trainer.save_checkpoint(ckpt_path)
    except TimeoutError:
        log(f"time budget of {config.time_budget} min reached at step {trainer.step_index}")
    except KeyboardInterrupt:
        interrupted = True
        log(f"interrupted at step {trainer.step_index}: saving")
    finally:
        bar.close()
        trainer.save_checkpoint(ckpt_path)
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
    stage = config.stage_list()[trainer.stage]
    V, T, C, S = trainer.arrays()
    moments = trainer.moments()
    data = {"color": C, "opacity": S}
    for k, (_, m, v) in moments.items():
        data[f"{k}:m"], data[f"{k}:v"] = m, v
    split = stage["split"] > 0 and (config.target_tets is None or len(T) < config.target_tets)
    # Scored on this stage's mesh; pruning only removes vertices of empty tets.
    scores = trainer.vertex_scores(trainer.dataset.train, config.select) if split else None
    if stage["prune"] is not None:
        res = prune_empty(V, T, S, float(stage["prune"]) / trainer.h, point_data=data)
        log(f"pruned {len(T) - len(res.tets):,} empty tets")
        V, T, data = res.vertices, res.tets, res.point_data
        scores = None if scores is None else scores[res.vertex_parent]
    if split:
        selected = select_top_fraction(scores, stage["split"])
        res = split_vertices(V, T, selected, point_data=data)
        log(f"split {len(selected):,} vertices: {len(T):,} -> {len(res.tets):,} tets")
        V, T, data = res.vertices, res.tets, res.point_data
    # build_topology may re-orient tets but keeps the vertex order: the
    # per-vertex moments carry over directly.
    carried = {k: (t, data[f"{k}:m"], data[f"{k}:v"]) for k, (t, _, _) in moments.items()}
    new = Trainer(trainer.dataset, V, T, config.for_stage(trainer.stage + 1), data["color"],
                  data["opacity"])
    new.step_index = new.stage_start = trainer.step_index
    new.stage = trainer.stage + 1
    new.elapsed, new.history, new.shortened, new.rng = (trainer.elapsed, trainer.history,
                                                       trainer.shortened, trainer.rng)
    new.set_moments(carried)
    return new


def write_outputs(trainer: Trainer, out: Path):
    """mesh.vtu, metrics.json, test renders and the progress plot."""
    from mi_tetvr.mesh.io import write_tetmesh
    from mi_tetvr.mesh.topology import TetMesh
    V, T, C, S = trainer.arrays()
    write_tetmesh(out / "mesh.vtu", TetMesh(V, T, C, S))
    views = trainer.dataset.test or trainer.dataset.train[:1]
    metrics = trainer.evaluate(views)
    metrics.update(step=trainer.step_index, seconds=trainer.elapsed,
                   vertices=len(V), tets=len(T), inverted_tets=trainer.inverted_tets(),
                   shortened_position_steps=trainer.shortened,
                   split="test" if trainer.dataset.test else "train (no test views)")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    renders = out / "test"
    renders.mkdir(exist_ok=True)
    for v in views:
        save_comparison(renders / f"{Path(v.name).stem}.png", trainer.render_view(v), v.image,
                        trainer.config.background)
    plot_history(trainer.history, out / "progress.png", metrics["mean"]["psnr"])
    return metrics


def save_comparison(path, pred_rgba, target_rgba, background):
    """Side by side: rendered | target (sRGB PNG)."""
    from PIL import Image

    from mi_tetvr.color import linear_to_srgb
    row = np.concatenate([composite(pred_rgba, background), composite(target_rgba, background)], 1)
    img = (np.clip(linear_to_srgb(np.clip(row, 0, 1)), 0, 1) * 255 + 0.5).astype(np.uint8)
    Image.fromarray(img).save(path)


def plot_history(history, path, test_psnr=None):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4))
    t = np.asarray(history["time"]) / 60.0
    loss = np.asarray(history["loss"])
    if len(loss):
        ax.semilogy(t, loss, color="tab:blue", alpha=0.3, lw=0.8)
        k = max(1, len(loss) // 50)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.semilogy(t[k - 1:], smooth, color="tab:blue", label="training loss")
    ax.set_xlabel("time [min]")
    ax.set_ylabel("loss", color="tab:blue")
    ps = np.asarray(history["psnr"], np.float64)
    if len(ps) and np.isfinite(ps).any():
        ax2 = ax.twinx()
        k = max(1, len(ps) // 50)
        ax2.plot(t[k - 1:], np.convolve(ps, np.ones(k) / k, mode="valid"), color="tab:red",
                 label="training PSNR")
        if test_psnr is not None:
            ax2.axhline(test_psnr, color="tab:red", ls="--", lw=0.8,
                        label=f"test PSNR {test_psnr:.2f} dB")
        ax2.set_ylabel("PSNR [dB] (RGBA or composited RGB)", color="tab:red")
        ax2.legend(loc="lower right")
    ax.set_title("mi-tetvr fit")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def evaluate_mesh(mesh_path, dataset, background=None, n_sub=8, split="test"):
    """Score a mesh file on a data set's views: PSNR/SSIM per view and mean."""
    from mi_tetvr.mesh.io import read_tetmesh
    mesh = read_tetmesh(mesh_path)
    cfg = FitConfig(background=background, n_sub=n_sub)
    trainer = Trainer(dataset, mesh.vertices, mesh.tets, cfg, mesh.color, mesh.opacity)
    views = dataset.test if split == "test" and dataset.test else dataset.train
    return trainer.evaluate(views)


__all__ = ["FitConfig", "Trainer", "run", "next_stage", "coarse_to_fine", "evaluate_mesh", "image_metrics", "initial_mesh",
           "data_bounds", "psnr", "composite"]
