"""A fit's uncertainty and the next view (mi_tetvr.recon.uncertainty).

The probed information ``diag(J^T W J)`` is checked against ``J`` formed densely by
another computation: forward-mode derivatives, one render per value (colors and
opacities), and the primal walk's own projections of unit attenuations (X-ray: the
model is linear, ``A`` column by column); the prior's curvature against the closed form
of the edge smoothing's Hessian; the candidates' geometry against the scan's.
"""
import json

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_tetvr.rays import render_rays
from mi_tetvr.recon import uncertainty as U
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.pipeline import first_trainer
from mi_tetvr.recon.trainer import Trainer
from tests.recon.conftest import CFG


@pytest.fixture(scope="module")
def color_fit(data):
    """A coarse color fit (a grid of 2 cells: few values, each seen by many pixels)."""
    cfg = CFG.updated(grid_resolution=2, background=[1.0, 1.0, 1.0])
    _, trainer = first_trainer(data, cfg, log=lambda *a: None)
    for _ in range(12):
        trainer.step()
    return trainer


def dense_information(trainer, views):
    """``sum_r J_ri^2`` per value, every column of ``J`` by forward mode."""
    o = np.concatenate([v.camera.rays()[0] for v in views])
    d = np.concatenate([v.camera.rays()[1] for v in views])
    out = {}
    n = trainer.opt.n_vertices
    for name, (key, c) in trainer.field.point_arrays.items():
        col = np.zeros((n, c))
        for j in range(n * c):
            dr.set_grad(trainer.opt[key], 0)
            y = trainer._compared(render_rays(trainer.scene, o, d, params=trainer.params))
            e = np.zeros(n * c, np.float32)
            e[j] = 1.0
            dr.set_grad(trainer.opt[key], mi.Float(e))
            dr.forward_to(y)
            col[j // c, j % c] = np.sum(np.array(dr.grad(y), np.float64) ** 2)
        out[name] = col
    return out


def test_probing_is_exact_where_the_stars_are_apart(color_fit):
    """With pixels further apart than any vertex star's footprint probed together, one
    channel at a time, the probed diagonal is J^T J's exactly; Hutchinson's plain
    estimator (stride 1) is not."""
    views = color_fit.train[:2]
    dense = dense_information(color_fit, views)
    info = U.information(color_fit, views, cap=64)
    assert info.exact
    for name, ref in dense.items():
        assert np.all(ref >= 0) and ref.max() > 0
        np.testing.assert_allclose(info.diagonal[name], ref, rtol=2e-4, atol=1e-6 * ref.max())
    plain = U.information(color_fit, views, strides=[1] * len(views))
    assert not plain.exact
    err = np.linalg.norm(plain.diagonal["opacity"] - dense["opacity"]) / \
        np.linalg.norm(dense["opacity"])
    assert err > 1e-2
    # every vertex a ray reaches counts that ray: at most every pixel of every view
    assert np.all(info.crossings <= sum(v.camera.width * v.camera.height for v in views))
    assert np.all((info.crossings > 0) == (dense["opacity"][:, 0] > 0))


def test_xray_information_is_the_weighted_column_norms(blob_data):
    """For an attenuation the compared optical depth is A x: the information with pixel
    weights is sum_r w_r A_ri^2, A's columns the primal walk's projections of each
    vertex's hat function (tomography's Projector, no adjoint)."""
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.recon.tomography import Projector
    _, _, dataset = blob_data
    views = dataset.train[:3]
    # (a box whose faces no ray runs along: such a ray's walk is degenerate)
    vertices, tets = grid_init(np.array([[-0.93, -0.91, -0.89], [0.92, 0.9, 0.94]]), 2)
    rng = np.random.default_rng(0)
    x = rng.uniform(0.05, 0.3, len(vertices))
    cfg = FitConfig(model="absorption", grid_resolution=2, n_sub=2, jitter=False)
    trainer = Trainer(dataset, vertices, tets, cfg, {"attenuation": x})
    weights = [rng.uniform(0.5, 2.0, v.camera.width * v.camera.height) for v in views]
    info = U.information(trainer, views, weights=weights, cap=64)
    assert info.exact
    proj = Projector(vertices, trainer.tets, [v.camera for v in views])
    w = np.concatenate(weights)
    ref = np.array([np.sum(w * proj.forward(np.eye(len(vertices))[j]) ** 2)
                    for j in range(len(vertices))])
    np.testing.assert_allclose(info.diagonal["attenuation"][:, 0], ref, rtol=2e-4,
                               atol=1e-6 * ref.max())


def test_prior_curvature_is_the_smoothing_hessian(blob_data):
    """The edge smoothing ``lam mean_e ((x_a - x_b) h)^2`` has the Hessian diagonal
    ``2 lam h^2 deg_i / E``: what the colored Hessian-vector products give."""
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.mesh.topology import unique_edges
    _, _, dataset = blob_data
    vertices, tets = grid_init(np.array(dataset.bbox, np.float64), 3)
    lam = 0.7
    cfg = FitConfig(model="absorption", grid_resolution=3, n_sub=2, jitter=False,
                    smoothing=lam)
    x = np.random.default_rng(1).uniform(0.0, 0.5, len(vertices))
    trainer = Trainer(dataset, vertices, tets, cfg, {"attenuation": x})
    got = U.prior_curvature(trainer, 3.0)["attenuation"][:, 0]
    e = unique_edges(trainer.tets)
    deg = np.bincount(e.ravel(), minlength=len(vertices))
    want = 3.0 * 2.0 * lam * trainer.h ** 2 * deg / len(e)
    np.testing.assert_allclose(got, want, rtol=2e-3)
    # no two vertices of a tet share a color (what makes the products exact)
    color = U._colors(trainer.tets, len(vertices))
    t = trainer.tets
    for i in range(4):
        for j in range(i + 1, 4):
            assert np.all(color[t[:, i]] != color[t[:, j]])


def test_laplace_variance(color_fit):
    """The variance is 1 / (information / sigma^2 + prior) with sigma^2 the training
    residuals' mean square; where no ray reaches, the floor (the values' spread)."""
    u = U.laplace(color_fit, strides=[4] * len(color_fit.train))
    assert u.sigma2 == pytest.approx(U.noise_variance(color_fit), rel=1e-6)
    _, _, values = color_fit.arrays()
    for name, var in u.variance.items():
        spread = np.asarray(values[name], np.float64).reshape(len(var), -1).var(axis=0)
        assert np.all(var > 0) and np.all(var <= spread[None, :] * (1 + 1e-9))
        np.testing.assert_allclose(
            var, 1.0 / (u.information.diagonal[name] / u.sigma2 + u.prior[name]), rtol=1e-12)
    std = u.std()
    assert set(std) == {"color_std", "opacity_std"}


def test_candidate_cameras(blob_data, data):
    """X-ray candidates turn the first angle about the scan's axis in 180/n steps;
    pinhole ones sit on a sphere around the point the cameras look at."""
    from mi_tetvr.camera import cameras_focus
    _, _, xray = blob_data
    cams = [v.camera for v in xray.train]
    cand = U.candidate_cameras(cams, 6)
    axis = np.linalg.svd(np.array([c.to_world[:3, 2] for c in cams]))[2][-1]
    dirs = np.array([c.to_world[:3, 2] for c in cand])
    assert np.allclose(dirs @ axis, 0.0, atol=1e-9)
    np.testing.assert_allclose(cand[0].to_world, cams[0].to_world, atol=1e-12)
    angles = np.degrees(np.arccos(np.clip(dirs @ dirs[0], -1, 1)))
    np.testing.assert_allclose(angles, 30.0 * np.arange(6), atol=1e-6)
    pin = [v.camera for v in data.train]
    focus = cameras_focus(pin)
    cand = U.candidate_cameras(pin, 5)
    radius = np.median([np.linalg.norm(c.center - focus) for c in pin])
    for c in cand:
        assert np.linalg.norm(c.center - focus) == pytest.approx(radius, rel=1e-9)
        assert c.width == pin[0].width and c.fx == pytest.approx(pin[0].fx)


def test_cli_uncertainty_eval_images_next_view(data, tiny_data_path, tmp_path):
    """The commands on a fit's folder: the std arrays land in its mesh (ParaView reads
    them as point data), eval's images gain a panel per array, next-view ranks the
    candidates by the gain it prints; bad input is one line."""
    import meshio
    from PIL import Image

    from tests.test_cli import run
    fit, d = tmp_path / "fit", str(tiny_data_path)
    r = run("fit", d, "--out", str(fit), "--grid-resolution", "3", "--iterations", "6",
            "--views-per-step", "2", "--n-sub", "2")
    assert r.returncode == 0, r.stderr
    r = run("uncertainty", str(fit), d, "-q", "--stride", "4")
    assert r.returncode == 0, r.stderr
    point = meshio.read(fit / "mesh.vtu").point_data
    assert {"color", "opacity", "color_std", "opacity_std", "rays_crossing"} <= set(point)
    assert np.all(point["opacity_std"] > 0)
    record = json.loads((fit / "uncertainty.json").read_text())
    assert record["strides"] == [4] * len(data.train) and record["renders"] > 0
    # the viewer shows an uncertainty as any scalar: its maximum projection is projection()'s
    from mi_tetvr.apps.viewer import MeshShown
    shown = MeshShown(fit / "mesh.vtu", tf="viridis", scalar="opacity_std")
    shown.mode = "maximum"
    assert shown.apply("integrator")
    cam, s = data.test[0].camera, point["opacity_std"]
    seen = shown.render(cam)
    mesh = meshio.read(fit / "mesh.vtu")
    ref = U.projection(mesh.points, mesh.cells_dict["tetra"], s, cam, "max",
                       (float(s.min()), float(s.max())))
    hit = seen[..., 3] > 0.999
    assert hit.sum() > 0.3 * hit.size
    np.testing.assert_allclose(seen[..., :3][hit], ref[hit], atol=1e-5)
    r = run("eval", str(fit), d, "--images", str(tmp_path / "img"))
    assert r.returncode == 0, r.stderr
    w, h = data.test[0].camera.width, data.test[0].camera.height
    im = Image.open(tmp_path / "img" / f"{data.test[0].name}.png")
    assert im.size == (4 * w, h)
    r = run("next-view", str(fit), d, "--candidates", "5", "-q", "--stride", "4",
            "-o", str(tmp_path / "rank.json"))
    assert r.returncode == 0, r.stderr
    rank = json.loads((tmp_path / "rank.json").read_text())
    assert len(rank) == 5 and [x["rank"] for x in rank] == [1, 2, 3, 4, 5]
    gains = [x["gain"] for x in rank]
    assert gains == sorted(gains, reverse=True) and gains[0] > 0
    for args, said in ((("uncertainty", str(tmp_path / "none"), d), "not a fit's folder"),
                       (("uncertainty", str(fit), d, "--draws", "0"), "at least 1"),
                       (("next-view", str(fit), d, "--candidates", "nowhere"),
                        "neither a number nor a data set")):
        r = run(*args)
        assert r.returncode == 1 and said in r.stderr and "Traceback" not in r.stderr


def test_total_variation_curvature_is_exact(blob_data):
    """The smooth total variation's Hessian diagonal (an X-ray fit's prior curvature)
    equals central differences of its gradient, and joins the Laplace prior as
    ``beta`` times it."""
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.recon.tomography import TetGradient
    _, _, dataset = blob_data
    vertices, tets = grid_init(np.array([[-0.93, -0.91, -0.89], [0.92, 0.9, 0.94]]), 2)
    x = np.random.default_rng(2).uniform(0.0, 0.4, len(vertices))
    cfg = FitConfig(model="absorption", grid_resolution=2, n_sub=2, jitter=False)
    trainer = Trainer(dataset, vertices, tets, cfg, {"attenuation": x})
    tg, delta = TetGradient(vertices, trainer.tets), 0.05
    got = tg.hessian_diagonal(x, delta)
    eps = 1e-6
    want = np.array([(tg.penalty(x + eps * e, delta)[1][i] - tg.penalty(x - eps * e, delta)[1][i])
                     / (2 * eps) for i, e in enumerate(np.eye(len(x)))])
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9 * np.abs(want).max())
    beta = 3.0
    u = U.laplace(trainer, penalty=(beta, delta), strides=[8] * len(trainer.train))
    floor = 1.0 / np.var(np.array(trainer.arrays()[2]["attenuation"]))
    np.testing.assert_allclose(u.prior["attenuation"][:, 0],
                               beta * got / u.sigma2 + floor, rtol=1e-5)


def test_posterior_samples_have_the_laplace_covariance(blob_data):
    """Draws of an X-ray fit's posterior are ``z = H^-1 b`` with ``b = A^T W^(1/2) e1 /
    sigma + prior^(1/2) e2`` (``e`` standard normal), whose covariance is ``H^-1`` for the
    full precision ``H = A^T W A / sigma^2 + diag(prior)``: the conjugate gradients
    through the walk give the dense solve's ``z`` (``A`` formed column by column by the
    primal walk, the same normal draws); the candidates' sampled gains are
    ``sum_r E[(a_r^T z)^2] / sigma^2`` of those draws, projected densely."""
    from mi_tetvr.mesh.initial import grid_init
    from mi_tetvr.recon.tomography import Projector
    _, _, dataset = blob_data
    vertices, tets = grid_init(np.array([[-0.93, -0.91, -0.89], [0.92, 0.9, 0.94]]), 2)
    x = np.random.default_rng(3).uniform(0.05, 0.3, len(vertices))
    cfg = FitConfig(model="absorption", grid_resolution=2, n_sub=2, jitter=False)
    trainer = Trainer(dataset, vertices, tets, cfg, {"attenuation": x})
    trainer.train = trainer.train[:3]
    u = U.laplace(trainer, strides=[8] * 3)
    n = len(vertices)
    A = Projector(vertices, trainer.tets, [v.camera for v in trainer.train])
    cols = np.stack([A.forward(e) for e in np.eye(n)], 1)
    prior = u.prior["attenuation"][:, 0]
    H = cols.T @ cols / u.sigma2 + np.diag(prior)
    z = U.posterior_samples(trainer, u, k=3, iterations=n, seed=1)
    rng = np.random.default_rng(1)
    for j in range(3):
        b = cols.T @ (rng.standard_normal(len(cols)) / np.sqrt(u.sigma2)) + \
            np.sqrt(prior) * rng.standard_normal(n)
        want = np.linalg.solve(H, b)
        np.testing.assert_allclose(z[j], want, rtol=0, atol=1e-4 * np.abs(want).max())
    cams = [v.camera for v in dataset.test[:3]]
    ranked = U.rank_by_samples(trainer, u, cams, z)
    C = Projector(vertices, trainer.tets, cams)
    proj = np.stack([C.forward(e) for e in np.eye(n)], 1) @ z.T
    for r in ranked:
        i = r["index"]
        want = np.sum(np.mean(proj[C.offsets[i]:C.offsets[i + 1]] ** 2, axis=1)) / u.sigma2
        assert r["gain"] == pytest.approx(want, rel=1e-4)
