"""Fits on random rays (``sampling rays``): the rays drawn from all training
photos against the numpy camera model (:meth:`Camera.rays
<mi_tetvr.camera.Camera.rays>`, :meth:`Camera.project`) and the photos' own
pixels, the photos drawn in proportion to their pixels, and a fit on random
rays improving held-out PSNR as a fit on whole photos does."""
import numpy as np
import pytest

from mi_tetvr.camera import Camera
from mi_tetvr.recon.datasets import View
from mi_tetvr.recon.pipeline import initial_mesh, run
from mi_tetvr.recon.pixels import PixelSampler
from mi_tetvr.recon.trainer import Trainer
from tests.recon.conftest import CFG

K = 4096


@pytest.fixture(scope="module")
def views():
    """Three photos of different sizes from random places, random pixels."""
    rng = np.random.default_rng(0)
    out = []
    for i, (w, h) in enumerate([(8, 6), (5, 7), (9, 4)]):
        cam = Camera.look_at(rng.normal(size=3) * 3, [0, 0, 0], [0, 1, 0], w, h, fov_x=40)
        out.append(View(f"v{i}", cam, rng.uniform(size=(h, w, 4)).astype(np.float32)))
    return out


def test_centre_rays_and_their_pixels(views):
    """Without jitter each ray is the numpy camera's ray through a pixel
    centre of its photo, its target that pixel; photos are drawn in
    proportion to their pixels."""
    ray, target, photo = PixelSampler(views).draw(K, seed=3, jitter=False)
    photo, target = np.array(photo), np.array(target)
    o, d = np.array(ray.o).T, np.array(ray.d).T
    sizes = np.array([v.camera.width * v.camera.height for v in views])
    share = np.bincount(photo, minlength=3) / K
    # (binomial standard deviation below 0.008 at K rays: 5 of them)
    np.testing.assert_allclose(share, sizes / sizes.sum(), atol=0.04)
    for i in range(0, K, 7):
        v = views[photo[i]]
        O, D = v.camera.rays()
        j = int(np.argmin(np.linalg.norm(D - d[i], axis=1)))
        assert np.linalg.norm(D[j] - d[i]) < 1e-5 and np.linalg.norm(O[j] - o[i]) < 1e-4
        row, col = divmod(j, v.camera.width)
        np.testing.assert_array_equal(target[i], v.image[row, col])


def test_jittered_rays_fall_in_their_pixel(views):
    """With jitter each ray passes through a uniform point of its pixel:
    projected back by the numpy camera, inside the pixel whose value it
    carries, spread over the pixel."""
    sampler = PixelSampler(views)
    ray, target, photo = sampler.draw(K, seed=5, jitter=True)
    photo, target = np.array(photo), np.array(target)
    o, d = np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T
    frac = []
    for i in range(0, K, 3):
        v = views[photo[i]]
        uv, z = v.camera.project((o[i] + 2.0 * d[i])[None])
        col, row = np.floor(uv[0]).astype(int)
        assert z[0] > 0
        np.testing.assert_array_equal(target[i], v.image[row, col])
        frac.append(uv[0] - np.floor(uv[0]))
    frac = np.array(frac)
    assert 0.2 < frac.std(0).min() and np.abs(frac.mean(0) - 0.5).max() < 0.05
    # the same seed, the same draw
    again = np.array(sampler.draw(K, seed=5, jitter=True)[0].d)
    np.testing.assert_array_equal(again, d.T.astype(np.float32))


def test_fit_on_random_rays_improves(data, tmp_path):
    """The fit's loop on random rays (as many per step as two photos hold)
    lifts held-out PSNR as the loop on whole photos does (tests/recon/test_fit.py)."""
    cfg = CFG.updated(sampling="rays")
    V, T, _ = initial_mesh(cfg, data)
    trainer = Trainer(data, V, T, cfg)
    assert trainer.rays_per_step == 2 * 16 * 16 and trainer.photos_per_step == 2.0
    before = trainer.evaluate(data.test)["mean"]
    after = run(data, tmp_path, cfg, progress=False, log=lambda *a: None)["mean"]
    assert after["psnr"] > before["psnr"] + 3.0, (before, after)
    assert Trainer(data, V, T, cfg.updated(rays_per_step=100)).rays_per_step == 100
