"""The reconstruction loop (``mi_tetvr.recon.pipeline``) on a tiny data set rendered by
the grid ray marcher: the fit improves held-out PSNR, writes its outputs,
resumes exactly where it stopped, and saves when interrupted."""
import json

import numpy as np
import pytest

import mitsuba as mi

from mi_tetvr.recon.config import FitConfig, coarse_to_fine
from mi_tetvr.recon.pipeline import evaluate_mesh, initial_mesh, next_stage, run
from mi_tetvr.recon.plan import (BUDGET_STEPS, KIND_COST, PIXELS_PER_VERTEX, STEP_COST,
                                 budget_stages, nominal_step_seconds, planned_resolution,
                                 resolution_limits)
from mi_tetvr.mesh.initial import grid_shape
from mi_tetvr.recon.trainer import Trainer

from tests.recon.conftest import CFG



def params_of(out):
    ck = np.load(out / "checkpoint.npz")
    return ck["value:color"], ck["value:opacity"], int(ck["step"])


def test_fit_improves_and_writes_outputs(data, tmp_path):
    V, T, _ = initial_mesh(CFG, data)
    before = Trainer(data, V, T, CFG).evaluate(data.test)["mean"]
    metrics = run(data, tmp_path, CFG, progress=False, log=lambda *a: None)
    after = metrics["mean"]
    assert after["psnr"] > before["psnr"] + 3.0, (before, after)
    for name in ("mesh.vtu", "metrics.json", "progress.png", "config.json", "checkpoint.npz"):
        assert (tmp_path / name).is_file(), name
    assert len(list((tmp_path / "test").glob("*.png"))) == len(data.test)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["step"] == CFG.trainer.iterations and saved["inverted_tets"] == 0
    # Scoring the written mesh again gives the same numbers (world units kept).
    again = evaluate_mesh(tmp_path / "mesh.vtu", data, n_sub=CFG.trainer.n_sub)["mean"]["psnr"]
    # make-dataset data are point samples at pixel centers: detected, no jitter.
    assert not Trainer(data, V, T, FitConfig()).jitter
    assert again == pytest.approx(saved["mean"]["psnr"], abs=0.05)


def interrupt_at(monkeypatch, n):
    """Make the n-th Trainer.step of the next run raise KeyboardInterrupt."""
    calls = {"n": 0}
    original = Trainer.step

    def step(self, *args):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return original(self, *args)

    monkeypatch.setattr(Trainer, "step", step)


def test_interrupt_then_resume_continues_exactly(data, tmp_path, monkeypatch):
    full, part = tmp_path / "full", tmp_path / "part"
    run(data, full, CFG, progress=False, log=lambda *a: None)
    interrupt_at(monkeypatch, 11)
    with pytest.raises(KeyboardInterrupt):
        run(data, part, CFG, progress=False, log=lambda *a: None)
    # Interrupted runs still write their outputs.
    assert params_of(part)[2] == 10
    assert (part / "mesh.vtu").is_file() and (part / "metrics.json").is_file()
    monkeypatch.undo()
    run(data, part, CFG, progress=False, log=lambda *a: None)  # resumes at step 10
    c1, s1, n1 = params_of(full)
    c2, s2, n2 = params_of(part)
    assert n1 == n2 == CFG.trainer.iterations
    # Same views, seeds and Adam moments: the same parameters (up to the
    # order of atomic gradient sums).
    np.testing.assert_allclose(c2, c1, atol=1e-4)
    np.testing.assert_allclose(s2, s1, rtol=1e-3, atol=1e-3 * s1.max())
    hist = json.loads(str(np.load(part / "checkpoint.npz")["history"]))
    assert hist["step"] == list(range(1, CFG.trainer.iterations + 1))


def test_joint_positions_never_invert(data, tmp_path):
    """Large position steps: without the safeguard tets invert, with it none
    do, and the regularized joint fit still improves on the start."""
    cfg = CFG.updated(lr_position=0.5, iterations=16)
    raw = run(data, tmp_path / "raw", cfg.updated(safeguard=False, regularizer=0.0),
              progress=False, log=lambda *a: None)
    safe = run(data, tmp_path / "safe", cfg, progress=False, log=lambda *a: None)
    assert raw["inverted_tets"] > 0
    assert safe["inverted_tets"] == 0 and safe["shortened_position_steps"] > 0
    V0, _, _ = initial_mesh(CFG, data)
    V = np.load(tmp_path / "safe" / "checkpoint.npz")["vertices"]
    assert np.abs(V - V0).max() > 0.01  # positions did move


def test_coarse_to_fine_stages_and_resume(data, tmp_path, monkeypatch):
    """Colors, then joint with a split, then colors: the mesh grows, the
    step count and history run on across stages, and an interruption in the
    last stage resumes there with the refined mesh."""
    stages = [{"iterations": 5}, {"iterations": 5, "lr_position": 0.1, "split": 0.1},
              {"iterations": 5}]
    cfg = CFG.updated(stages=stages)
    V0, T0, _ = initial_mesh(cfg, data)
    interrupt_at(monkeypatch, 13)
    with pytest.raises(KeyboardInterrupt):
        run(data, tmp_path, cfg, progress=False, log=lambda *a: None)
    ck = np.load(tmp_path / "checkpoint.npz")
    assert int(ck["stage"]) == 2 and int(ck["step"]) == 12 and len(ck["tets"]) > len(T0)
    monkeypatch.undo()
    metrics = run(data, tmp_path, cfg, progress=False, log=lambda *a: None)
    ck = np.load(tmp_path / "checkpoint.npz")
    assert int(ck["step"]) == 15 and metrics["tets"] == len(ck["tets"]) > len(T0)
    assert metrics["inverted_tets"] == 0
    hist = json.loads(str(ck["history"]))
    assert hist["step"] == list(range(1, 16))


def test_next_stage_prunes_splits_and_carries_state(data):
    """Pruning drops exactly the empty tets, the split grows the mesh, and
    colors, opacities and Adam moments follow the vertices."""
    cfg = CFG.updated(stages=[{"iterations": 2, "prune": 1e-3, "split": 0.1},
                              {"iterations": 2}])
    V, T, _ = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg.for_stage(0))
    for _ in range(2):
        trainer.step()
    # Every view's derivative pass used its primal render's kept state.
    assert len(trainer.scene.integrator().kept_primals) == 0
    # Empty the half x < 0 (opacity zero there).
    S = np.array(trainer.opt["volume.vertex_opacity"])
    S[V[:, 0] < -1e-9] = 0.0
    trainer.opt["volume.vertex_opacity"] = mi.Float(S)
    trainer.params.update(trainer.opt)
    before = trainer.opt.moments()
    nxt = next_stage(trainer, cfg, log=lambda *a: None)
    Vn, Tn, new = nxt.arrays()
    Sn = new["opacity"]
    empty = (S[trainer.tets] <= 1e-3 / trainer.h).all(1)
    assert empty.any() and nxt.state.stage == 1 and nxt.state.step == 2
    assert nxt.state.stage_start == 2
    assert len(Tn) > int((~empty).sum())  # pruned, then split
    assert np.all(Sn[Tn].max(1) > 0)      # no empty tet left
    after = nxt.opt.moments()
    for k in ("volume.vertex_color", "volume.vertex_opacity"):
        assert after[k][0] == before[k][0]                 # Adam's step count carried
        assert after[k][1].shape[0] == len(Vn)              # moments on the new vertices


def test_grid_stage_samples_the_coarse_field(data):
    """A stage on a finer grid starts from the previous grid's field: its
    vertex values are the coarse mesh's linear field at its vertices, and it
    starts a fresh optimizer."""
    from mi_tetvr.mesh.initial import grid_sample
    cfg = CFG.updated(grid_resolution=None, stages=[{"iterations": 2, "grid": 3},
                                               {"iterations": 2, "grid": 6}])
    V, T, _ = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg.for_stage(0))
    for _ in range(2):
        trainer.step()
    _, _, old = trainer.arrays()
    C, S = old["color"], old["opacity"]
    nxt = next_stage(trainer, cfg, log=lambda *a: None)
    Vn, Tn, new = nxt.arrays()
    Cn, Sn = new["color"], new["opacity"]
    fine, fine_tets, _ = initial_mesh(cfg.updated(stages=[{"grid": 6}]), data)
    assert len(Tn) == len(fine_tets) == 8 * len(T) and nxt.state.stage == 1
    np.testing.assert_allclose(Vn, fine, atol=1e-6)
    bounds = np.stack([V.min(0), V.max(0)])
    np.testing.assert_allclose(Cn, grid_sample(bounds, 3, C, Vn), atol=1e-6)
    np.testing.assert_allclose(Sn, grid_sample(bounds, 3, S, Vn), rtol=1e-5, atol=1e-6)
    assert all(t == 0 for t, _, _ in nxt.opt.moments().values())
    with pytest.raises(ValueError, match="keep the grid"):
        CFG.updated(stages=[{"iterations": 2, "split": 0.1}, {"iterations": 2, "grid": 6}])
    with pytest.raises(ValueError, match="needs init 'grid'"):
        CFG.updated(init="tetwild", stages=[{"grid": 6}])


def test_budget_stages_and_resolution_limits(data):
    """A budgeted run trains half the grid first, then the chosen one; the
    chosen one has at most 1/PIXELS_PER_VERTEX vertices per training pixel."""
    cfg = FitConfig(iterations=1000)
    assert budget_stages(cfg, 60) == [{"iterations": 250, "grid": 30},
                                      {"iterations": 750, "grid": 60}]
    assert budget_stages(cfg, 20) == [{"iterations": 1000, "grid": 20}]
    from types import SimpleNamespace as NS
    views = [NS(camera=NS(width=100, height=100))] * 10
    cube = CFG.updated(bounds=[[0, 0, 0], [1, 1, 1]])
    # (r + 1)^3 vertices <= 10 * 100^2 / PIXELS_PER_VERTEX
    r = int((10 * 100 ** 2 / PIXELS_PER_VERTEX) ** (1 / 3)) - 1
    assert 12 < r < 100 / 1.5
    assert resolution_limits(cube, NS(train=views)) == (12, r)
    # a box half as deep has about half the vertices per resolution
    slab = CFG.updated(bounds=[[0, 0, 0], [1, 1, 0.5]])
    assert resolution_limits(slab, NS(train=views))[1] > r
    # at most the image width over 1.5, at least the smallest grid
    assert resolution_limits(cube, NS(train=[NS(camera=NS(width=30, height=30))] * 1000)) == \
        (12, 20)
    assert resolution_limits(cube, NS(train=[NS(camera=NS(width=30, height=30))])) == (12, 12)


class TickClock:
    """A simulated clock: every reading is ``tick`` seconds after the last, so a
    budgeted run's time is its count of clock readings (deterministic)."""

    def __init__(self, tick):
        self.t, self.tick, self.readings = 0.0, tick, 0

    def __call__(self):
        self.t += self.tick
        self.readings += 1
        return self.t


def test_time_budget_is_used_and_honoured(data, tmp_path):
    """With a time budget (on a simulated clock) the whole run ends within it: the
    optimizer steps stop where the time left is what the outputs were estimated to take
    (their measured render time), and the steps take the rest; running it again resumes
    and takes the budget again. (How long real runs take against their budget is
    benchmarks/bench_training.py's to measure.)"""
    from mi_tetvr.recon.outputs import output_seconds
    budget, tick = 20.0, 0.05
    clock = TickClock(tick)
    metrics = run(data, tmp_path, CFG.updated(time_budget=budget / 60), progress=False,
                  log=lambda *a: None, now=clock)
    # the outputs' estimate: 0.5 s + 1.5 x (held-out views + the training PSNR's) x one
    # render (two readings: one tick)
    from mi_tetvr.recon.trainer import TRAINING_VIEWS
    reserve = output_seconds(trainer_of(data), TickClock(tick))
    assert reserve == pytest.approx(0.5 + 1.5 * (len(data.test) + TRAINING_VIEWS) * tick)
    # steps until the stage's end (the budget less the reserve)
    assert metrics["wall_seconds"] <= budget
    assert budget - reserve - 4 * tick <= metrics["wall_seconds"]
    assert metrics["optimization_seconds"] >= budget - reserve - 8 * tick, metrics
    steps = metrics["step"]
    assert steps > CFG.trainer.iterations and (tmp_path / "mesh.vtu").is_file()
    again = run(data, tmp_path, CFG.updated(time_budget=6.0 / 60), progress=False,
                log=lambda *a: None, now=TickClock(tick))
    assert 6.0 - reserve - 4 * tick <= again["wall_seconds"] <= 6.0, again
    assert again["step"] > steps
    # a budget half as long: the steps in proportion to the time they get
    half = run(data, tmp_path / "half", CFG.updated(time_budget=budget / 120), progress=False,
               log=lambda *a: None, now=TickClock(tick))
    expected = steps * (budget / 2 - reserve) / (budget - reserve)
    assert abs(half["step"] - expected) <= 2, (half["step"], expected)


def trainer_of(data):
    from mi_tetvr.recon.trainer import Trainer
    V, T, values = initial_mesh(CFG, data)
    return Trainer(data, V, T, CFG.for_stage(0), values)


def test_the_plan_is_kept_apart_and_read_back(data, tmp_path):
    """config.json holds what was asked, plan.json what the run decided for the data and
    the budget (the box, the planned grid, the scene's kind, the steps planned and their
    nominal cost); the settings a fit ran with are both (fit_settings). A resumed run reads
    the plan back, and a folder written before plans were kept apart (config.json holding
    both, no plan.json) still resumes."""
    import shutil
    from mi_tetvr.recon.plan import FitPlan, fit_settings
    asked = CFG.replaced(grid_resolution=None, time_budget=4.0 / 60)
    new = tmp_path / "new"
    first = run(data, new, asked, progress=False, log=lambda *a: None, now=TickClock(0.05))
    written = FitConfig.from_file(new / "config.json")
    assert written == asked
    plan = FitPlan.read(new)
    ran = fit_settings(new)
    grid = ran.mesh.grid_resolution
    assert set(plan.settings) >= {"bounds", "grid_resolution", "scene", "init", "loss"}
    assert grid == planned_resolution(ran, data, 0.85 * 4.0)
    assert plan.budget_seconds == 4.0 and plan.planned_steps == BUDGET_STEPS
    assert plan.step_seconds == pytest.approx(nominal_step_seconds(ran, data, grid))
    assert ran == plan.applied(asked) and ran.data.scene == "object" and ran.mesh.init == "grid"
    assert len(np.load(new / "checkpoint.npz")["tets"]) == 6 * np.prod(
        grid_shape(ran.mesh.bounds, grid))
    # resumed: the same plan, more steps
    old = tmp_path / "old"
    shutil.copytree(new, old)
    again = run(data, new, asked, progress=False, log=lambda *a: None, now=TickClock(0.05))
    assert again["step"] > first["step"] and FitPlan.read(new) == plan
    # as an earlier version left its folder: the decided settings in config.json
    (old / "plan.json").unlink()
    (old / "config.json").write_text(json.dumps(ran.nested(), indent=2))
    assert fit_settings(old) == ran
    before = run(data, old, asked, progress=False, log=lambda *a: None, now=TickClock(0.05))
    assert before["step"] == again["step"] and fit_settings(old) == ran
    # both resumed folders hold a plan again; a damaged plan is said to be one
    assert FitPlan.read(old).budget_seconds == FitPlan.read(new).budget_seconds == 4.0
    for text in ("not json", "[1, 2]", '{"settings": {"no_such_setting": 1}}',
                 '{"settings": {"solver": "sart"}}'):      # (an X-ray solver on a color fit)
        (old / "plan.json").write_text(text)
        with pytest.raises(ValueError, match="plan"):
            fit_settings(old)


def test_planned_grid_from_the_data_and_the_budget():
    """A budget's grid is planned from the photos, the box and the budget alone (no clock:
    the same mesh on a busy machine): the finest within the limits whose BUDGET_STEPS steps
    fit at the reference machine's cost per step, written out in closed form here."""
    from types import SimpleNamespace as NS
    data = NS(train=[NS(camera=NS(width=200, height=100))] * 70)
    box = CFG.replaced(bounds=[[0, 0, 0], [2, 1, 1]])
    fixed, per_ray, per_ray_cell, per_tet = STEP_COST
    rays = 2 * 200 * 100            # views_per_step photos, one ray per pixel
    assert nominal_step_seconds(box, data, 40) == pytest.approx(
        fixed + rays * (per_ray + per_ray_cell * 40) + per_tet * 6 * 40 * 20 * 20)
    lo, hi = resolution_limits(box, data)
    assert lo < hi
    chosen = []
    for seconds in (20.0, 60.0, 200.0, 600.0):
        r = planned_resolution(box, data, seconds)
        assert lo <= r <= hi
        assert r == lo or BUDGET_STEPS * nominal_step_seconds(box, data, r) <= seconds
        assert r == hi or BUDGET_STEPS * nominal_step_seconds(box, data, r + 1) > seconds
        chosen.append(r)
    assert chosen == sorted(chosen) and len(set(chosen)) > 2, chosen
    assert planned_resolution(box, data, 1e-3) == lo and planned_resolution(box, data, 1e9) == hi
    # a path-traced step costs KIND_COST times as much: a coarser grid in the same time
    lit = box.replaced(model="scattering", lights="lights.xml")
    assert nominal_step_seconds(lit, data, 40) == pytest.approx(
        KIND_COST["scattering"] * nominal_step_seconds(box, data, 40))
    assert planned_resolution(lit, data, 200.0) < planned_resolution(box, data, 200.0)


@pytest.mark.parametrize("init", ["tetwild", "delaunay"])
def test_other_initial_meshes(data, init):
    from mi_tetvr.mesh.topology import build_topology
    cfg = CFG.updated(init=init)
    if init == "delaunay":
        with pytest.raises(ValueError, match="sparse points"):
            initial_mesh(cfg, data)
        rng = np.random.default_rng(0)
        data = type(data)(data.train, data.test, points=rng.uniform(-0.8, 0.8, (300, 3)))
    V, T, _ = initial_mesh(cfg, data)
    topo = build_topology(V, T)
    assert topo.n_tets > 50 and topo.n_flipped == 0
    lo, hi = V.min(0), V.max(0)
    assert np.all(hi - lo > 0.5) and np.all(hi - lo < 3.0)


def test_config_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown fit settings"):
        FitConfig().updated(learning_rate=1)
    with pytest.raises(ValueError, match="loss"):
        FitConfig().updated(loss="l3")
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"resolution": 8, "lr_color": 0.1}))
    with pytest.warns(UserWarning, match="'resolution' is now 'grid_resolution'"):
        cfg = FitConfig.from_file(p)
    assert cfg.mesh.grid_resolution == 8 and cfg.trainer.lr_color == 0.1
    assert cfg.trainer.loss is None
    with pytest.raises(ValueError, match="unknown stage settings"):
        FitConfig().updated(stages=[{"iterations": 5, "lr": 1}])
    st = FitConfig().updated(stages=coarse_to_fine(rounds=2, steps=10, split=0.05)).stage_list()
    assert [s["iterations"] for s in st] == [10] * 5
    assert [s["split"] for s in st] == [0, 0.05, 0, 0.05, 0]
    assert [s["lr_position"] > 0 for s in st] == [False, True, False, True, False]


# -- optimizer state and compositing --------------------------------------------------------
def adam_of(n, seed, rates=None):
    """A VertexAdam over n vertices (3 colors and 1 opacity each) after three
    steps with fixed gradients."""
    import drjit as dr
    from mi_tetvr.recon.optim import VertexAdam
    rng = np.random.default_rng(seed)
    params = {"m.vertex_color": mi.Float(rng.uniform(0, 1, 3 * n)),
              "m.vertex_opacity": mi.Float(rng.uniform(0, 1, n))}
    opt = VertexAdam(params, rates or {"m.vertex_color": 0.1, "m.vertex_opacity": 0.2}, n)
    for _ in range(3):
        w = {k: mi.Float(rng.normal(size=dr.width(v))) for k, v in params.items()}
        dr.backward(sum(dr.sum(w[k] * dr.square(opt[k])) for k in opt))
        opt.step(lr_scale=0.5)
    return opt


def test_optimizer_state_round_trip(tmp_path):
    """Moments saved to numpy (and an .npz) and loaded into a fresh optimizer
    are the same, and the optimizer then takes the same step."""
    import drjit as dr
    opt = adam_of(5, seed=1)
    np.savez(tmp_path / "s.npz", **opt.state_dict())
    fresh = adam_of(5, seed=1)  # same values, other moments once reset
    fresh.set_moments({k: (0, np.zeros_like(m), np.zeros_like(v))
                       for k, (t, m, v) in fresh.moments().items()})
    fresh.load_state_dict(np.load(tmp_path / "s.npz"))
    for k, (t, m, v) in opt.moments().items():
        t2, m2, v2 = fresh.moments()[k]
        assert t == t2 == 3 and m.shape == m2.shape == (5, 3 if "color" in k else 1)
        np.testing.assert_array_equal(m2, m)
        np.testing.assert_array_equal(v2, v)
    for o in (opt, fresh):
        dr.backward(sum(dr.sum(dr.square(o[k])) for k in o))
        o.step()
    for k in opt:
        np.testing.assert_array_equal(np.array(fresh[k]), np.array(opt[k]))


def test_vertex_adam_is_adam_and_reads_its_state():
    """VertexAdam's steps and the moments it reads out of Dr.Jit's Adam equal Adam written
    here in float64 numpy (Kingma & Ba, Alg. 1, with Dr.Jit's epsilon inside the square
    root's argument as eps^2): this pins the layout of Dr.Jit's optimizer state that
    VertexAdam depends on."""
    import drjit as dr
    from mi_tetvr.recon.optim import VertexAdam
    rng = np.random.default_rng(5)
    n, rates, b1, b2, eps = 4, {"a": 0.1, "b": 0.03}, 0.9, 0.999, 1e-8
    x = {"a": rng.uniform(0, 1, 3 * n), "b": rng.uniform(0, 1, n)}
    opt = VertexAdam({k: mi.Float(v) for k, v in x.items()}, rates, n)
    m = {k: np.zeros_like(v) for k, v in x.items()}
    v2 = {k: np.zeros_like(v) for k, v in x.items()}
    for t, scale in enumerate((1.0, 0.5, 0.25), start=1):
        g = {k: rng.normal(size=len(v)) for k, v in x.items()}
        dr.backward(sum(dr.sum(mi.Float(g[k]) * opt[k]) for k in opt))   # gradient g
        opt.step(lr_scale=scale)
        for k in x:
            m[k] = b1 * m[k] + (1 - b1) * g[k]
            v2[k] = b2 * v2[k] + (1 - b2) * g[k] ** 2
            lr = rates[k] * scale * np.sqrt(1 - b2 ** t) / (1 - b1 ** t)
            x[k] = x[k] - lr * m[k] / np.sqrt(v2[k] + eps ** 2)
        for k, (tk, mk, vk) in opt.moments().items():
            assert tk == t and mk.shape == (n, 3 if k == "a" else 1)
            # (float32 moments: Dr.Jit's lerp by 1 - beta_2 = 0.001 rounds v to ~1e-5)
            np.testing.assert_allclose(mk.ravel(), m[k], rtol=1e-4, atol=1e-7)
            np.testing.assert_allclose(vk.ravel(), v2[k], rtol=1e-4, atol=1e-9)
            np.testing.assert_allclose(np.array(opt[k]), x[k], rtol=1e-5, atol=1e-6)


def test_optimizer_moments_carry_over_vertex_change():
    """Per-vertex moments move onto a mesh with more vertices (as after a
    split): the step count is kept, new vertices get their given moments."""
    old = adam_of(4, seed=2)
    carried = {}
    for k, (t, m, v) in old.moments().items():
        # Two new vertices, each the midpoint of vertices 0 and 1 / 2 and 3.
        carried[k] = (t, np.concatenate([m, (m[[0, 2]] + m[[1, 3]]) / 2]),
                      np.concatenate([v, (v[[0, 2]] + v[[1, 3]]) / 2]))
    new = adam_of(6, seed=3)
    new.set_moments({**carried, "other.key": (1, np.zeros(1), np.zeros(1))})  # ignored
    for k, (t, m, v) in new.moments().items():
        assert t == carried[k][0] == 3 and m.shape[0] == 6
        np.testing.assert_allclose(m, carried[k][1], rtol=1e-6)
        np.testing.assert_allclose(v[4], (v[0] + v[1]) / 2, rtol=1e-6)
    with pytest.raises(ValueError, match="moments"):
        adam_of(5, seed=4).set_moments(carried)  # 6 vertices' moments for 5


def test_composite_numpy_and_drjit():
    """One compositing for numpy images and Dr.Jit tensors."""
    from mi_tetvr.recon.metrics import composite
    rng = np.random.default_rng(0)
    rgba = rng.uniform(0, 1, (3, 5, 4)).astype(np.float32)
    rgba[..., :3] *= rgba[..., 3:4]
    for bg in (None, 1.0, [0.2, 0.5, 1.0], np.array([0.2, 0.5, 1.0], np.float32)):
        want = rgba[..., :3] + (1 - rgba[..., 3:4]) * (0.0 if bg is None else np.asarray(bg))
        out = composite(rgba, bg)
        assert isinstance(out, np.ndarray) and out.shape == (3, 5, 3)
        np.testing.assert_allclose(out, want, rtol=1e-6)
        tensor = composite(mi.TensorXf(rgba), bg)
        assert isinstance(tensor, mi.TensorXf) and tensor.shape == (3, 5, 3)
        np.testing.assert_allclose(np.array(tensor), want, rtol=1e-6)
    # numpy: float64 unless the background is a numpy array, whose dtype is kept.
    assert composite(rgba, [1, 1, 1]).dtype == np.float64
    assert composite(rgba, np.ones(3, np.float32)).dtype == np.float32


def test_learned_background_explains_the_surroundings(data, tmp_path):
    """Photos of the volume in front of colored surroundings (alpha 1
    everywhere): fitting RGBA makes the volume explain the surroundings and
    warns; a learned background scores far better on held-out views, is
    written as an EXR and survives a resume."""
    from mi_tetvr.recon.datasets import Dataset, View
    from mi_tetvr.recon.pipeline import data_warnings
    from mi_tetvr.recon.trainer import K_ENVIRONMENT
    sky = np.array([0.2, 0.5, 0.8])

    def photo(v):
        rgb = v.image[..., :3] + (1 - v.image[..., 3:]) * sky
        return View(v.name, v.camera, np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)
                    .astype(np.float32))

    photos = Dataset(train=[photo(v) for v in data.train], test=[photo(v) for v in data.test])
    # (on the grid of an object: the default for such photos, an unbounded
    # scene, needs sparse points: tests/recon/test_unbounded.py)
    cfg = CFG.updated(iterations=40, scene="object", appearance=False)
    assert any("--background learn" in w for w in data_warnings(cfg, photos))
    assert data_warnings(cfg.updated(background="learn"), photos) == []
    plain = run(photos, tmp_path / "plain", cfg, progress=False, log=lambda *a: None)
    learned = run(photos, tmp_path / "learn", cfg.updated(background="learn"), progress=False,
                  log=lambda *a: None)
    assert learned["mean"]["psnr"] > plain["mean"]["psnr"] + 3.0, (plain["mean"], learned["mean"])
    env = np.array(mi.Bitmap(str(tmp_path / "learn" / "background.exr")))
    assert env.shape[:2] == (16, 32) and env.min() >= 0
    ck = np.load(tmp_path / "learn" / "checkpoint.npz")
    np.testing.assert_allclose(ck["environment"][:, 1:-1], env, atol=1e-6)
    # resumed: the environment and its optimizer state come back
    from mi_tetvr.recon.checkpoint import load_checkpoint
    trainer = load_checkpoint(tmp_path / "learn" / "checkpoint.npz", photos,
                              cfg.updated(background="learn"))
    np.testing.assert_allclose(np.array(trainer.params[K_ENVIRONMENT]), ck["environment"])
