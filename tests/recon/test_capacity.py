"""Where a photo fit puts its capacity and how its rays' weights gather: the rays'
distortion (:meth:`Trainer.distortion <mi_tetvr.recon.trainer.Trainer.distortion>`)
and the photos' error projected into the vertices (:meth:`Trainer.error_scores
<mi_tetvr.recon.trainer.Trainer.error_scores>`), both against the float64 brute-force
renderer of ``tests/reference.py`` (which the fit does not use)."""
import json

import drjit as dr
import numpy as np
import pytest

from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.fields import key
from mi_tetvr.recon.pipeline import initial_mesh
from mi_tetvr.recon.trainer import Trainer

from tests.recon.conftest import CFG
from tests.reference import reference_render

OPACITY = key("vertex_opacity")


def _values(n, seed=3):
    rng = np.random.default_rng(seed)
    return {"color": rng.uniform(0.1, 0.9, (n, 3)), "opacity": rng.uniform(0.0, 3.0, n)}


def _distortion_reference(trainer, view, opacity):
    """The distortion of ``view``'s rays at half size through the pixel centres, from the
    reference renderer's moments: ``W S_2 - S_1^2`` of the disparity ``near / z``."""
    cam = view.camera.downscaled(2)
    V = trainer.arrays()[0]
    z = cam.project(V)[1]
    s = trainer.near / np.maximum(z, trainer.near)
    o, d = cam.rays()
    rgb, alpha = reference_render(V, trainer.tets, np.stack([s, s * s, 0 * s], 1), opacity,
                                  o, d)
    return float(np.mean(alpha * rgb[:, 1] - rgb[:, 0] ** 2))


def test_distortion_matches_the_reference_and_its_finite_differences(data):
    """The distortion is ``W S_2 - S_1^2`` of the disparity moments
    (``1/2 int int w w' (s - s')^2 >= 0``), equal to the reference renderer's within float32;
    its derivative w.r.t. the opacities is the reference's central differences; the render
    after it is the fit's own again; a learned background does not enter it."""
    V, T, _ = initial_mesh(CFG, data)
    values = _values(len(V))
    trainer = Trainer(data, V, T, CFG.updated(distortion=2.0), values)
    view = data.train[1]
    before = trainer.render_view(view)
    trainer.opt.clear_grads()
    value = trainer.distortion(view)
    opacity = values["opacity"]
    ref = _distortion_reference(trainer, view, opacity)
    assert ref > 1e-4
    assert value == pytest.approx(2.0 * ref, rel=2e-3)
    np.testing.assert_array_equal(trainer.render_view(view), before)

    grad = np.array(dr.grad(trainer.opt[OPACITY]), np.float64)
    seen = np.argsort(-np.abs(grad))[:4]
    assert np.abs(grad[seen]).min() > 1e-4
    h = 1e-3
    for i in seen:
        up, down = opacity.copy(), opacity.copy()
        up[i] += h
        down[i] -= h
        fd = 2.0 * (_distortion_reference(trainer, view, up)
                    - _distortion_reference(trainer, view, down)) / (2 * h)
        assert grad[i] == pytest.approx(fd, rel=2e-2, abs=1e-5)

    learned = Trainer(data, V, T, CFG.updated(distortion=2.0, background="learn"), values)
    assert learned.distortion(view) == pytest.approx(value, rel=1e-5)


def test_error_scores_are_the_error_weighted_by_each_vertex_contribution(data):
    """``error_scores`` gives, per vertex ``v``, ``sum_p e_p w_vp`` and ``sum_p w_vp`` over the
    training photos, ``w_vp`` its weight in pixel ``p``'s color: the reference renderer's
    image of a color of 1 at ``v`` only (and 0 elsewhere); ``e_p`` the fit's per-pixel
    error (mean absolute sRGB difference plus half the SSIM dissimilarity)."""
    V, T, _ = initial_mesh(CFG, data)
    values = _values(len(V), seed=5)
    trainer = Trainer(data, V, T, CFG.updated(select="error"), values)
    error, seen = trainer.error_scores()
    np.testing.assert_allclose(error, trainer.split_scores(), rtol=1e-5)  # (atomic sums)
    picks = np.r_[np.argsort(-seen)[:3], np.argsort(-error)[:3]]
    errors = [trainer.pixel_error(trainer.render(v, seed=2 * i + 1), v).ravel()
              for i, v in enumerate(trainer.train)]
    assert min(e.max() for e in errors) > 0.05
    for vtx in picks:
        onehot = np.zeros((len(V), 3))
        onehot[vtx, 0] = 1.0
        want_e = want_w = 0.0
        for v, e in zip(trainer.train, errors):
            o, d = v.camera.rays()
            w = reference_render(V, trainer.tets, onehot, values["opacity"], o, d)[0][:, 0]
            want_e += float(e @ w)
            want_w += float(w.sum())
        assert seen[vtx] == pytest.approx(want_w, rel=2e-3)
        assert error[vtx] == pytest.approx(want_e, rel=2e-3)
    # the step's gradients are left clean
    assert all(not np.any(np.array(dr.grad(trainer.opt[k])))
               for k in trainer.opt)


def test_capacity_settings_are_checked():
    for bad, said in ((dict(select="error", model="absorption"), "select error"),
                      (dict(distortion=1.0, optimize="tf", init="m.vtu"), "distortion"),
                      (dict(distortion=-1.0), "distortion must be >= 0")):
        with pytest.raises(ValueError, match=said):
            FitConfig().updated(**bad)


def test_a_split_keeps_the_training_psnr_and_the_fit_records_it(data, tmp_path):
    """A split starts its new vertices at their edge's midpoint values, so the field (linear
    in each tet) and the image are the same: the training PSNR on whole photos across it is
    unchanged to 0.01 dB. The fit logs and keeps it (``refinements`` in the history) and
    writes the final one; ``training_psnr`` is the PSNR of the mean sRGB MSE of the
    training photos that ``evaluate`` scores one by one (three, at pixel centres)."""
    from mi_tetvr.recon.metrics import psnr
    from mi_tetvr.recon.pipeline import run
    cfg = CFG.updated(stages=[{"iterations": 6, "split": 0.2}, {"iterations": 2}])
    said = []
    metrics = run(data, tmp_path, cfg, progress=False, log=said.append)
    history = json.loads(str(np.load(tmp_path / "checkpoint.npz")["history"]))
    (step, _, before, after), = history["refinements"]
    assert step == 6 and before > 10.0 and after == pytest.approx(before, abs=0.01)
    assert any(s.startswith("training PSNR on whole photos across the change") for s in said)
    V, T, _ = initial_mesh(CFG, data)
    trainer = Trainer(data, V, T, CFG, _values(len(V)))
    assert len(trainer.training_views()) == 3 and not trainer.jitter
    per_view = trainer.evaluate(trainer.training_views())["views"]
    want = psnr(float(np.mean([m["mse"] for m in per_view.values()])))
    assert trainer.training_psnr() == pytest.approx(want, abs=1e-3)
    assert metrics["training_psnr"] > 10.0


def test_the_time_left_sets_the_tets_and_the_photo_scale():
    """``affordable``: the next stage gets ``steps`` steps in its seconds, a step costing as
    the pixels and as the tets to the power 1/2; finer photos only where their steps fit
    on the mesh as it is. ``StageRefinement`` then splits as much as that affords (a split
    of 5 % of the vertices doubles the tets), or not at all under an eighth of the asked."""
    from mi_tetvr.recon.strategy import StageRefinement, affordable
    # same photos: 60 s for 100 steps of 0.1 s leaves 6x the time: 36x the tets
    assert affordable(1000, 0.1, 60.0, 100, 2, 2) == (pytest.approx(36000.0), None)
    # twice finer photos cost 4x: 1.5x the time left, 2.25x the tets
    assert affordable(1000, 0.1, 60.0, 100, 2, 1) == (pytest.approx(2250.0), None)
    # their steps do not fit (30 s < 40 s): the photos stay at 1/2, 3x the time, 9x the tets
    assert affordable(1000, 0.1, 30.0, 100, 2, 1) == (pytest.approx(9000.0), 2)
    said = []
    refine = StageRefinement(FitConfig(), max_tets=1500)
    assert refine.affordable_split(1000, 0.05, said.append) == pytest.approx(0.025)
    assert StageRefinement(FitConfig(), 1050).affordable_split(1000, 0.05, said.append) == 0
    assert StageRefinement(FitConfig(), 5000).affordable_split(1000, 0.05, said.append) == 0.05
    assert StageRefinement(FitConfig()).affordable_split(1000, 0.05, said.append) == 0.05
    assert said == ["the time left affords about 1,500 tets: split 2.50% of the vertices, "
                    "not 5%", "the time left affords about 1,050 tets: no split"]
