"""The reconstruction loop (``mi_tetvr.recon.fit``) on a tiny data set rendered by
the grid ray marcher: the fit improves held-out PSNR, writes its outputs,
resumes exactly where it stopped, and saves when interrupted."""
import json
from pathlib import Path

import numpy as np
import pytest

import mitsuba as mi

from mi_tetvr.recon.datasets import load_nerf
from mi_tetvr.recon.fit import FitConfig, Trainer, evaluate_mesh, initial_mesh, run
from mi_tetvr.mesh.scenes import default_volume
from mi_tetvr.transfer import TransferFunction
from mi_tetvr.grid.volume import make_dataset, make_volume

ROOT = Path(__file__).resolve().parents[1]
CFG = FitConfig(resolution=4, iterations=24, views_per_step=2, lr_color=0.08, lr_opacity=0.3,
                n_sub=2, jitter=False, checkpoint_every=4, log_every=4)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    tf = TransferFunction.from_file(ROOT / "scenes" / "tf_default.json")
    make_dataset(make_volume(default_volume(16)), tf, views=6, res=16, out_dir=out,
                 test_views=2, fov=30, progress=False)
    return load_nerf(out)


def params_of(out):
    ck = np.load(out / "checkpoint.npz")
    return ck["color"], ck["opacity"], int(ck["step"])


def test_fit_improves_and_writes_outputs(data, tmp_path):
    V, T = initial_mesh(CFG, data)
    before = Trainer(data, V, T, CFG).evaluate(data.test)["mean"]["psnr"]
    metrics = run(data, tmp_path, CFG, progress=False, log=lambda *a: None)
    assert metrics["mean"]["psnr"] > before + 3.0, (before, metrics["mean"]["psnr"])
    for name in ("mesh.vtu", "metrics.json", "progress.png", "config.json", "checkpoint.npz"):
        assert (tmp_path / name).is_file(), name
    assert len(list((tmp_path / "test").glob("*.png"))) == len(data.test)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["step"] == CFG.iterations and saved["inverted_tets"] == 0
    # Scoring the written mesh again gives the same numbers (world units kept).
    again = evaluate_mesh(tmp_path / "mesh.vtu", data, n_sub=CFG.n_sub)["mean"]["psnr"]
    # make-dataset data are point samples at pixel centres: detected, no jitter.
    assert not Trainer(data, V, T, FitConfig()).jitter
    assert again == pytest.approx(saved["mean"]["psnr"], abs=0.05)


def interrupt_at(monkeypatch, n):
    """Make the n-th Trainer.step of the next run raise KeyboardInterrupt."""
    calls = {"n": 0}
    original = Trainer.step

    def step(self):
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return original(self)

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
    assert n1 == n2 == CFG.iterations
    # Same views, seeds and Adam moments: the same parameters (up to the
    # order of atomic gradient sums).
    np.testing.assert_allclose(c2, c1, atol=1e-4)
    np.testing.assert_allclose(s2, s1, rtol=1e-3, atol=1e-3 * s1.max())
    hist = json.loads(str(np.load(part / "checkpoint.npz")["history"]))
    assert hist["step"] == list(range(1, CFG.iterations + 1))


def test_joint_positions_never_invert(data, tmp_path):
    """Large position steps: without the safeguard tets invert, with it none
    do, and the regularized joint fit still improves on the start."""
    cfg = CFG.updated(lr_position=0.5, iterations=16)
    raw = run(data, tmp_path / "raw", cfg.updated(safeguard=False, regularizer=0.0),
              progress=False, log=lambda *a: None)
    safe = run(data, tmp_path / "safe", cfg, progress=False, log=lambda *a: None)
    assert raw["inverted_tets"] > 0
    assert safe["inverted_tets"] == 0 and safe["shortened_position_steps"] > 0
    V0, _ = initial_mesh(CFG, data)
    V = np.load(tmp_path / "safe" / "checkpoint.npz")["vertices"]
    assert np.abs(V - V0).max() > 0.01  # positions did move


def test_coarse_to_fine_stages_and_resume(data, tmp_path, monkeypatch):
    """Colors, then joint with a split, then colors: the mesh grows, the
    step count and history run on across stages, and an interruption in the
    last stage resumes there with the refined mesh."""
    stages = [{"iterations": 5}, {"iterations": 5, "lr_position": 0.1, "split": 0.1},
              {"iterations": 5}]
    cfg = CFG.updated(stages=stages)
    V0, T0 = initial_mesh(cfg, data)
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
    from mi_tetvr.recon.fit import next_stage
    cfg = CFG.updated(stages=[{"iterations": 2, "prune": 1e-3, "split": 0.1},
                              {"iterations": 2}])
    V, T = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg.for_stage(0))
    for _ in range(2):
        trainer.step()
    # Empty the half x < 0 (opacity zero there).
    S = np.array(trainer.opt["volume.vertex_opacity"])
    S[V[:, 0] < -1e-9] = 0.0
    trainer.opt["volume.vertex_opacity"] = mi.Float(S)
    trainer.params.update(trainer.opt)
    before = trainer.moments()
    nxt = next_stage(trainer, cfg, log=lambda *a: None)
    Vn, Tn, Cn, Sn = nxt.arrays()
    empty = (S[trainer.tets] <= 1e-3 / trainer.h).all(1)
    assert empty.any() and nxt.stage == 1 and nxt.step_index == 2 and nxt.stage_start == 2
    assert len(Tn) > int((~empty).sum())  # pruned, then split
    assert np.all(Sn[Tn].max(1) > 0)      # no empty tet left
    after = nxt.moments()
    for k in ("volume.vertex_color", "volume.vertex_opacity"):
        assert after[k][0] == before[k][0]                 # Adam's step count carried
        assert after[k][1].shape[0] == len(Vn)              # moments on the new vertices


def test_time_budget_stops_and_saves(data, tmp_path):
    metrics = run(data, tmp_path, CFG.updated(time_budget=1e-6), progress=False,
                  log=lambda *a: None)
    assert metrics["step"] == 1 and (tmp_path / "mesh.vtu").is_file()


@pytest.mark.parametrize("init", ["tetwild", "delaunay"])
def test_other_initial_meshes(data, init):
    from mi_tetvr.mesh.topology import build_topology
    cfg = CFG.updated(init=init)
    if init == "delaunay":
        with pytest.raises(ValueError, match="sparse points"):
            initial_mesh(cfg, data)
        rng = np.random.default_rng(0)
        data = type(data)(data.train, data.test, points=rng.uniform(-0.8, 0.8, (300, 3)))
    V, T = initial_mesh(cfg, data)
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
    cfg = FitConfig.from_file(p)
    assert cfg.resolution == 8 and cfg.lr_color == 0.1 and cfg.loss == "l2"
    with pytest.raises(ValueError, match="unknown stage settings"):
        FitConfig().updated(stages=[{"iterations": 5, "lr": 1}])
    from mi_tetvr.recon.fit import coarse_to_fine
    st = FitConfig().updated(stages=coarse_to_fine(rounds=2, steps=10, split=0.05)).stage_list()
    assert [s["iterations"] for s in st] == [10] * 5
    assert [s["split"] for s in st] == [0, 0.05, 0, 0.05, 0]
    assert [s["lr_position"] > 0 for s in st] == [False, True, False, True, False]
