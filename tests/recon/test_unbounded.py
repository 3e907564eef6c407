"""Photos of scenes in their surroundings: what the fit decides for them
(``for_capture``), the per-photo color transform, opacities per cell on
multiscale meshes, and the unbounded fit end to end on real photos."""
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.datasets import Dataset, View, load_colmap
from mi_tetvr.recon.pipeline import for_capture, initial_mesh, run
from mi_tetvr.recon.trainer import Trainer, vertex_cell_sizes
from tests.helpers import shared_data

from tests.recon.conftest import CFG

QUIET = dict(progress=False, log=lambda *a: None)



def opaque(data, sky=(0.2, 0.5, 0.8), gains=None):
    """The views as photos in front of a colored sky (alpha 1), the training
    ones with a gain per channel (exposure and white balance)."""
    def photo(v, g):
        rgb = (v.image[..., :3] + (1 - v.image[..., 3:]) * np.asarray(sky)) * g
        return View(v.name, v.camera, np.concatenate([rgb, np.ones_like(rgb[..., :1])], -1)
                    .astype(np.float32))
    gains = np.ones((len(data.train), 3)) if gains is None else gains
    return Dataset(train=[photo(v, g) for v, g in zip(data.train, gains)],
                   test=[photo(v, 1.0) for v in data.test])


def test_for_capture_decides_by_alpha_and_keeps_what_is_set(data):
    obj = for_capture(CFG, data)
    def decided(c):
        return (c.data.scene, c.mesh.init, c.trainer.loss, c.field.appearance,
                c.field.background)
    assert decided(obj) == ("object", "grid", "l2", False, None)
    assert decided(for_capture(CFG, opaque(data))) == \
        ("unbounded", "unbounded", "l1", True, "learn")
    mine = for_capture(CFG.updated(loss="l2", appearance=False, background=[1, 1, 1],
                                   init="grid"), opaque(data))
    assert (mine.trainer.loss, mine.field.appearance, mine.field.background, mine.mesh.init) == \
        ("l2", False, [1, 1, 1], "grid")
    # X-ray and transfer-function fits are never unbounded scenes
    assert for_capture(CFG.updated(model="absorption"), opaque(data)).data.scene == "object"
    with pytest.raises(ValueError, match="scene"):
        CFG.updated(scene="outdoor")


def test_appearance_is_the_affine_color_transform(data):
    """apply_appearance against numpy's matrix product, and only on
    training views."""
    cfg = for_capture(CFG.updated(appearance=True, scene="object"), data)
    V, T, _ = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg)
    rng = np.random.default_rng(0)
    a = rng.normal(0, 0.2, (len(data.train), 12))
    trainer.appearance_opt["appearance"] = mi.Float(a.ravel().astype(np.float32))
    image = rng.uniform(0, 1, (16, 16, 4)).astype(np.float32)
    got = np.array(trainer.apply_appearance(mi.TensorXf(image), data.train[1]))
    m = np.eye(3) + a[1, :9].reshape(3, 3)
    np.testing.assert_allclose(got[..., :3], image[..., :3] @ m.T + a[1, 9:], atol=1e-5)
    np.testing.assert_array_equal(got[..., 3], image[..., 3])
    held_out = np.array(trainer.apply_appearance(mi.TensorXf(image), data.test[0]))
    np.testing.assert_array_equal(held_out, image)


def test_appearance_recovers_exposures(data):
    """Photos rendered from the fit's own starting volume with a gain per
    channel each (mean 1) and the volume held fixed: the fitted transforms
    take each render to its photo."""
    cfg = for_capture(CFG.updated(scene="object", appearance=True), data)
    V, T, _ = initial_mesh(cfg, data)
    volume = Trainer(data, V, T, cfg)
    rng = np.random.default_rng(1)
    gains = np.exp(rng.normal(0, 0.2, (len(data.train), 3)))
    gains /= gains.mean(0)
    views = []
    for v, g in zip(data.train, gains):
        image = volume.render_view(v)
        image[..., :3] *= g
        views.append(View(v.name, v.camera, image))
    photos = Dataset(train=views, test=data.test, root=data.root)
    fixed = cfg.updated(lr_color=0.0, lr_opacity=0.0, lr_appearance=0.01, decay=0.2,
                        appearance_prior=0.0, views_per_step=len(views), iterations=150)
    trainer = Trainer(photos, V, T, fixed)
    for _ in range(fixed.trainer.iterations):
        trainer.step()
    # The volume's colors are nearly grey, so a gain is any mix of its row's
    # entries and the offset: what must match is the transformed render.
    for v, target in zip(data.train, views):
        start = volume.render_view(v)
        got = np.array(trainer.apply_appearance(mi.TensorXf(start), target))
        error = np.abs(got[..., :3] - target.image[..., :3]).max()
        before = np.abs(start[..., :3] - target.image[..., :3]).max()
        assert error < 0.1 * before, (error, before)


def test_multiscale_opacity_is_per_cell(data):
    """On a mesh whose cells differ 100x in size, opacities start at
    init_opacity over each vertex's own cell, and Adam's first step (of size
    lr for every parameter with a gradient) moves each vertex's opacity by
    lr_opacity over its cell."""
    from mi_tetvr.mesh.initial import unbounded_init
    rng = np.random.default_rng(2)
    V, T, _ = unbounded_init(rng.uniform(-0.5, 0.5, (300, 3)),
                             [v.camera.center for v in data.views], far=100.0, shells=3)
    cfg = CFG.updated(scene="object", init="unbounded")
    trainer = Trainer(data, V, T, cfg)
    cell = vertex_cell_sizes(V, trainer.tets)
    assert cell.max() > 50 * cell.min()
    np.testing.assert_allclose(trainer.cell, cell)
    k = "volume.vertex_opacity"
    before = np.array(trainer.opt[k])
    np.testing.assert_allclose(before * cell, cfg.field.init_opacity, rtol=1e-5)
    trainer.step(progress=0.0)
    moved = np.abs(np.array(trainer.opt[k]) - before)
    stepped = (moved > 0) & (np.array(trainer.opt[k]) > 0)     # not clipped at zero
    assert stepped.sum() > 20
    # (Adam's epsilon shortens the steps of the tiniest gradients by < 0.3 %)
    np.testing.assert_allclose(moved[stepped] * cell[stepped], cfg.trainer.lr_opacity, rtol=5e-3)


def test_unbounded_fit_of_real_photos(tmp_path):
    """colmap-maupertuis (4 aerial photos, a COLMAP model): the default fit
    meshes the sparse points and far shells around every camera, prunes and
    splits between stages, learns, and says how it was scored."""
    from scipy.spatial import Delaunay
    photos = load_colmap(shared_data("colmap-maupertuis"), downscale=16)
    cfg = FitConfig(iterations=16, n_sub=2, log_every=4, checkpoint_every=100)
    V0, T0, _ = initial_mesh(for_capture(cfg, photos), photos)
    assert Delaunay(V0).find_simplex([v.camera.center for v in photos.views]).min() >= 0
    logs = []
    metrics = run(photos, tmp_path, cfg, progress=False, log=logs.append)
    # asked: left to the run (config.json); decided for the photos (plan.json)
    from mi_tetvr.recon.plan import FitPlan, fit_settings
    asked = FitConfig.from_file(tmp_path / "config.json")
    assert asked.mesh.init == "auto" and asked.field.background is None
    assert asked.strategy.stages is None
    plan = FitPlan.read(tmp_path)
    assert plan.settings["init"] == "unbounded" and plan.settings["background"] == "learn"
    saved = fit_settings(tmp_path)
    assert saved.mesh.init == "unbounded" and saved.field.background == "learn"
    assert saved.strategy.stages
    assert any(s.startswith("pruned") for s in logs) and any(s.startswith("split") for s in logs)
    assert metrics["tets"] > len(T0)
    psnr = json.loads(str(np.load(tmp_path / "checkpoint.npz")["history"]))["psnr"]
    assert np.mean(psnr[-4:]) > np.mean(psnr[:4]) + 1.0
    assert "every 8th image" in metrics["protocol"]["test_views"]
    # resumed: the photos' transforms and their Adam moments come back
    from mi_tetvr.recon.checkpoint import load_checkpoint
    ck = np.load(tmp_path / "checkpoint.npz")
    back = load_checkpoint(tmp_path / "checkpoint.npz", photos, for_capture(
        cfg.updated(stages=fit_settings(tmp_path).strategy.stages),
        photos))
    np.testing.assert_allclose(back.appearance(), ck["appearance"], atol=1e-7)
    assert np.abs(ck["appearance:m"]).max() > 0
    for k, v in back.appearance_opt.state_dict().items():
        np.testing.assert_array_equal(v, ck[k])
    assert metrics["split"] == "test" and len(metrics["views"]) == 1
    # the fly-through: along the photos' cameras (by name), its first and last frames the
    # fitted scene seen from the first and the last camera (H.264 at crf 18: within 2 %)
    import imageio_ffmpeg
    from mi_tetvr.recon.metrics import display_rgb
    from mi_tetvr.recon.outputs import FLYTHROUGH_FRAMES, FLYTHROUGH_SPP
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "flythrough.mp4"))
    meta = next(reader)
    video = [np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3)
             for f in reader]
    views = sorted(photos.views, key=lambda v: v.name)
    h, w = views[0].camera.height, views[0].camera.width
    assert len(video) == FLYTHROUGH_FRAMES and video[0].shape[:2] == (h + h % 2, w + w % 2)
    for k, v in ((0, views[0]), (-1, views[-1])):
        seen = display_rgb(back.render_camera(v.camera, FLYTHROUGH_SPP), None)
        assert np.abs(video[k][:h, :w] / 255.0 - seen).mean() < 0.02


def test_split_scores_are_the_steps_gradients_and_coarse_photos_train_first(data):
    """A stage with ``downscale`` 2 trains on the photos area-averaged by 2 (held-out views
    scored as given); its refinement scores are the image loss's absolute gradients of its
    steps, summed (read here from the optimizer before each of its steps)."""
    from mi_tetvr.recon.images import downscale_image
    cfg = CFG.updated(stages=[{"iterations": 3, "downscale": 2, "split": 0.1}, {"iterations": 2}])
    V, T, _ = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg.for_stage(0))
    assert trainer.downscale == 2
    for v, w in zip(trainer.train, data.train):
        np.testing.assert_allclose(v.image, downscale_image(w.image, 2), atol=1e-7)
        assert (v.camera.width, v.camera.fx) == (w.camera.width // 2, w.camera.fx / 2)
    assert trainer.render_view(data.test[0]).shape[:2] == data.test[0].image.shape[:2]
    n, seen = len(V), np.zeros(len(V))
    step = trainer.opt.step

    def recording(**kw):
        for k, w in trainer.field.score_weights(cfg.strategy.select).items():
            seen[:] += w * np.abs(np.array(dr.grad(trainer.opt[k]))).reshape(n, -1).sum(1)
        return step(**kw)

    trainer.opt.step = recording
    for _ in range(3):
        trainer.step()
    # (the regularizer and the prior add no gradient to colors and opacities here)
    assert seen.max() > 0
    np.testing.assert_allclose(trainer.split_scores(), seen, rtol=1e-5, atol=1e-7 * seen.max())
    with pytest.raises(ValueError, match="downscale"):
        CFG.updated(stages=[{"iterations": 2, "downscale": 0}])


def test_moving_points_are_tetrahedralized_anew_and_resume_after(data, tmp_path, monkeypatch):
    """Vertices that move, tetrahedralized anew (Delaunay) after their stage: the next
    stage's mesh is valid (no inverted tet, conforming), and a run interrupted after the
    rebuild resumes on the rebuilt mesh."""
    import mi_tetvr.mesh.initial as initial
    from mi_tetvr.mesh.topology import build_topology, signed_volumes
    from tests.recon.test_fit import interrupt_at
    cfg = CFG.updated(retriangulate=True, stages=[
        {"iterations": 4, "lr_position": 0.3, "prune": 1e-4, "split": 0.1}, {"iterations": 4}])
    given = []
    rebuild = initial.retriangulate

    def recording(vertices, *args, **kw):
        given.append(np.array(vertices))
        return rebuild(vertices, *args, **kw)

    monkeypatch.setattr(initial, "retriangulate", recording)
    logs = []
    full = run(data, tmp_path / "full", cfg, progress=False, log=logs.append)
    monkeypatch.undo()
    assert any(s.startswith("tetrahedralized the moved vertices anew") for s in logs)
    V0, _, _ = initial_mesh(cfg, data)
    # what was tetrahedralized anew: the vertices where the stage's steps moved them
    assert len(given) == 1 and np.abs(given[0] - V0).max() > 1e-3
    ck = np.load(tmp_path / "full" / "checkpoint.npz")
    V, T = ck["vertices"], ck["tets"]
    assert full["inverted_tets"] == 0 and (signed_volumes(V, T) > 0).all()
    build_topology(V, T)                      # conforming (raises otherwise)
    interrupt_at(monkeypatch, 6)                            # in the second stage
    with pytest.raises(KeyboardInterrupt):
        run(data, tmp_path / "part", cfg, progress=False, log=lambda *a: None)
    mid = np.load(tmp_path / "part" / "checkpoint.npz")
    assert int(mid["stage"]) == 1 and int(mid["step"]) == 5
    assert (signed_volumes(mid["vertices"], mid["tets"]) > 0).all()
    monkeypatch.undo()
    run(data, tmp_path / "part", cfg, progress=False, log=lambda *a: None)
    again = np.load(tmp_path / "part" / "checkpoint.npz")
    # the resumed stage goes on on the mesh rebuilt before the interruption
    np.testing.assert_array_equal(again["tets"], mid["tets"])
    assert json.loads(str(again["history"]))["step"] == list(range(1, 9))
