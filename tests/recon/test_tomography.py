"""Absorption-only tomography: exact X-ray projections of a grid volume, the
orthographic (parallel-beam) camera, the X-ray data format, the ``absorption``
tet model rendering it, and a fit of an attenuation from projections."""
import json

import mitsuba as mi
import numpy as np
import pytest

import mi_tetvr
from mi_tetvr.grid.volume import make_volume
from mi_tetvr.grid.xray import line_integrals
from mi_tetvr.recon.synthetic import make_xray_dataset
from mi_tetvr.mesh.initial import grid_init
from mi_tetvr.mesh.sample import sample_field
from mi_tetvr.camera import Camera
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.datasets import load_nerf
from mi_tetvr.recon.images import read_image, write_image
from mi_tetvr.recon.pipeline import run
from tests.recon.conftest import blob_volume


def dense_integral(volume, o, d, n=200_000):
    """Midpoint rule with ``n`` samples over the ray's chord of the box."""
    lo, hi = volume.bounds()
    d = d / np.linalg.norm(d)
    with np.errstate(divide="ignore"):
        ta, tb = (lo - o) / d, (hi - o) / d
    t0, t1 = np.max(np.minimum(ta, tb)), np.min(np.maximum(ta, tb))
    if t1 <= t0:
        return 0.0
    t = t0 + (np.arange(n) + 0.5) * (t1 - t0) / n
    return float(np.sum(volume.sample(o + t[:, None] * d)) * (t1 - t0) / n)


def test_line_integrals_are_exact_for_the_trilinear_field():
    rng = np.random.default_rng(1)
    vol = make_volume(rng.uniform(0, 1, (4, 5, 6)))
    lo, hi = vol.bounds()
    o = rng.uniform(-3, 3, (12, 3))
    target = rng.uniform(lo, hi, (12, 3))         # every ray crosses the box
    d = target - o
    got = line_integrals(vol, o, d)
    ref = np.array([dense_integral(vol, oo, dd) for oo, dd in zip(o, d)])
    assert np.all(ref > 0.05)
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7)
    # rays that miss the box integrate to 0; an axis-parallel ray through a grid plane
    miss = line_integrals(vol, [[0, 0, 5.0], [0.0, 0.0, 0.0]], [[1, 0, 0], [1.0, 0, 0]])
    assert miss[0] == 0.0
    assert miss[1] == pytest.approx(dense_integral(vol, np.zeros(3), np.array([1.0, 0, 0])),
                                    rel=1e-6)


def test_orthographic_camera_matches_mitsuba_sensor():
    cam = Camera.orthographic([3, 1, 0.5], [0, 0, 0.2], [0, 0, 1], 10, 6, 0.3)
    cam.cx, cam.cy = cam.cx + 1.0, cam.cy - 0.5               # off-centre principal point
    sensor = mi.load_dict(cam.sensor_dict(sampler="stratified"))
    uv = np.array([[0.5, 0.5], [9.5, 5.5], [3.2, 1.7]])
    o, d = cam.rays(uv)
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(*(uv / [10.0, 6.0]).T.astype(np.float32)),
                               mi.Point2f(0.5, 0.5))
    mo = np.array(ray.o).reshape(3, -1).T
    md = np.broadcast_to(np.array(ray.d).reshape(3, -1).T, d.shape)
    np.testing.assert_allclose(md, d, atol=1e-6)
    # Mitsuba starts the ray at its near clip plane: the same line
    along = np.sum((mo - o) * d, 1)
    np.testing.assert_allclose(mo, o + along[:, None] * d, atol=1e-5)
    np.testing.assert_allclose(cam.project(o + 2.0 * d)[0], uv, atol=1e-9)
    rd = cam.rays_drjit(uv)
    np.testing.assert_allclose(np.array(rd.o).reshape(3, -1).T, o, atol=1e-5)
    half = cam.downscaled(2)
    assert half.pixel_size == pytest.approx(0.6) and half.is_orthographic


def linear_volume(n=(6, 7, 5)):
    """A grid of a linear field (trilinear = linear = what tets interpolate)."""
    nx, ny, nz = n
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return make_volume(0.2 + 0.1 * x + 0.05 * y + 0.08 * z)


@pytest.fixture(scope="module")
def xray_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("xray")
    made = make_xray_dataset(linear_volume(), out, views=12, test_views=4, progress=False)
    return out, made


def test_xray_dataset_round_trip_and_absorption_render(xray_data):
    """The data set reads back as orthographic views of transmittance; a tet
    grid holding the same linear attenuation, rendered by tetvr's absorption
    model through the same sensor, reproduces every image."""
    out, made = xray_data
    info = json.loads((out / "xray_info.json").read_text())
    data = load_nerf(out)
    assert len(data.train) == 12 and len(data.test) == 4
    vol = linear_volume()
    cam = data.train[3].camera
    assert cam.is_orthographic and cam.width % 2 == 1 and cam.height == vol.shape[2]
    np.testing.assert_allclose(cam.to_world, made["train"][3].camera.to_world, atol=1e-9)
    np.testing.assert_allclose(data.train[3].image, made["train"][3].image, atol=1e-7)
    scale = info["attenuation_scale"]
    assert info["max_depth"] == pytest.approx(2.5)
    lo, hi = vol.bounds()
    # the outermost rows run along the box's faces: the grid reaches a hair beyond it
    m = 1e-5 * vol.spacing[0]
    V, T = grid_init(np.stack([lo - m, hi + m]), 4)
    mu = scale * vol.sample(np.clip(V, lo, hi))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "v": mi_tetvr.tetmesh_dict(V, T, opacity=mu, model="absorption")})
    for view in (data.train[3], data.test[1]):
        d = view.camera.sensor_dict(sampler="stratified")
        d["sampler"]["jitter"] = False
        img = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=1))
        assert np.all(img[..., :3] == 0)
        np.testing.assert_allclose(1 - img[..., 3], 1 - view.image[..., 3], atol=2e-5)


def test_npy_images_are_transmittance(tmp_path):
    img = np.zeros((3, 4, 4), np.float32)
    img[..., 3] = np.linspace(0, 0.9, 12).reshape(3, 4)
    write_image(tmp_path / "a.npy", img)
    np.testing.assert_allclose(np.load(tmp_path / "a.npy"), 1 - img[..., 3], atol=1e-7)
    np.testing.assert_allclose(read_image(tmp_path / "a.npy"), img, atol=1e-7)
    np.save(tmp_path / "bad.npy", np.full((2, 2), 2.5, np.float32))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        read_image(tmp_path / "bad.npy")
    np.save(tmp_path / "rgb.npy", np.zeros((2, 2, 3), np.float32))
    with pytest.raises(ValueError, match="transmittance"):
        read_image(tmp_path / "rgb.npy")


def test_absorption_model_refuses_a_transfer_function():
    V, T = grid_init(np.array([[0, 0, 0], [1, 1, 1.0]]), 1)
    with pytest.raises(Exception, match="per-vertex opacity"):
        mi.load_dict(mi_tetvr.tetmesh_dict(V, T, scalar=V[:, 0], model="absorption",
                                           tf_color=mi.TensorXf(np.ones((2, 3), np.float32)),
                                           tf_opacity=mi.TensorXf(np.ones(2, np.float32))))
    with pytest.raises(Exception, match="model must be"):
        mi.load_dict(mi_tetvr.tetmesh_dict(V, T, model="xray"))


def test_attenuation_fit_recovers_the_volume(tmp_path):
    """From 16 parallel-beam projections of a blob phantom, a coarse-to-fine
    tet fit by Adam (``solver="adam"``) brings the attenuation much closer to the truth than
    its start, and its held-out projections match (transmittance PSNR)."""
    g = np.linspace(-1, 1, 9)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    vol = make_volume(np.exp(-3 * ((x - 0.2) ** 2 + y ** 2 + (z + 0.1) ** 2)))
    made = make_xray_dataset(vol, tmp_path / "data", views=16, test_views=4, progress=False)
    data = load_nerf(tmp_path / "data")
    lo, hi = vol.bounds()
    m = 1e-3 * vol.spacing[0]          # the rows along the faces run inside the grid
    cfg = FitConfig(model="absorption", solver="adam", bounds=[(lo - m).tolist(),
                                                               (hi + m).tolist()],
                    views_per_step=4,
                    stages=[{"iterations": 40, "grid": 4}, {"iterations": 80, "grid": 8}],
                    checkpoint_every=1000)
    metrics = run(data, tmp_path / "fit", cfg, progress=False, log=lambda *a: None)
    mesh = mi_tetvr.read_tetmesh(tmp_path / "fit" / "attenuation.vtu", opacity="attenuation")
    pts = np.random.default_rng(0).uniform(lo, hi, (2000, 3))
    truth = made["info"]["attenuation_scale"] * vol.sample(pts)
    fitted = sample_field(mesh.vertices, mesh.tets, mesh.opacity, pts)
    from mi_tetvr.mesh.topology import mean_edge_length
    coarse = grid_init(np.stack([lo - m, hi + m]), 4)
    start = cfg.field.init_opacity / mean_edge_length(*coarse)     # the fit's flat start
    err, err0 = np.sqrt(np.mean((fitted - truth) ** 2)), np.sqrt(np.mean((start - truth) ** 2))
    assert err < 0.35 * err0, (err, err0)
    assert metrics["mean"]["psnr"] > 35.0, metrics["mean"]
    assert (tmp_path / "fit" / "test").is_dir()


def test_sample_field_is_exact_for_linear_fields():
    V, T = grid_init(np.array([[0, 0, 0], [1, 2, 1.0]]), 5)
    f = 1 + 2 * V[:, 0] - V[:, 1] + 0.5 * V[:, 2]
    p = np.random.default_rng(0).uniform(-0.1, 1.1, (500, 3))
    s = sample_field(V, T, f, p, outside=np.nan)
    inside = np.all((p >= 0) & (p <= [1, 2, 1]), 1)
    np.testing.assert_allclose(s[inside], (1 + 2 * p[:, 0] - p[:, 1] + 0.5 * p[:, 2])[inside],
                               atol=1e-9)
    assert np.isnan(s[~inside]).all()


def test_reconstruct_slices_recovers_the_volume(tmp_path):
    """Filtered back-projection and SART of exact parallel-beam projections
    of a smooth phantom land on the volume's samples: close to the truth
    (measured 42.8 and 45.0 dB), and far from it when the slices are mirrored
    (17-18 dB: the orientation is right)."""
    from mi_tetvr.grid.slices import reconstruct_slices
    g = np.linspace(-1, 1, 16)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    vol = make_volume(np.exp(-4 * ((x - 0.3) ** 2 + 2 * (y + 0.2) ** 2 + z ** 2)))
    made = make_xray_dataset(vol, tmp_path, views=48, test_views=0, progress=False)
    scale = made["info"]["attenuation_scale"]
    truth = vol.values.astype(np.float64)

    def psnr(v):
        return -10 * np.log10(np.mean((np.clip(v, 0, None) - truth) ** 2))

    fbp = reconstruct_slices(vol, made["train"], scale, "fbp")
    sart = reconstruct_slices(vol, made["train"], scale, "sart", passes=5)
    assert fbp.shape == truth.shape
    assert psnr(fbp) > 30 and psnr(sart) > 30, (psnr(fbp), psnr(sart))
    assert psnr(fbp[:, ::-1, :]) < psnr(fbp) - 8 and psnr(fbp[:, :, ::-1]) < psnr(fbp) - 8


def test_cone_beam_projections_match_the_absorption_render(tmp_path):
    """Cone-beam (perspective) X-ray views: the same exact integrals, and a
    tet grid holding the linear attenuation renders them through the views'
    perspective sensors."""
    vol = linear_volume()
    made = make_xray_dataset(vol, tmp_path, views=4, test_views=0, beam="cone", progress=False)
    data = load_nerf(tmp_path)
    assert not data.train[0].camera.is_orthographic
    lo, hi = vol.bounds()
    V, T = grid_init(np.stack([lo, hi]), 4)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "v": mi_tetvr.tetmesh_dict(V, T, model="absorption",
                                                     opacity=made["info"]["attenuation_scale"]
                                                     * vol.sample(V))})
    view = data.train[1]
    d = view.camera.sensor_dict(sampler="stratified")
    d["sampler"]["jitter"] = False
    img = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=1))
    assert view.image[..., 3].max() > 0.5
    np.testing.assert_allclose(img[..., 3], view.image[..., 3], atol=2e-5)


def test_frusta_bounds_of_orthographic_cameras():
    """Two parallel-beam cameras looking along x and along y: the region both
    see is the box their slabs cut (the hull's start for X-ray data)."""
    from mi_tetvr.recon.hull import frusta_bounds
    a = Camera.orthographic([5, 0, 0], [0, 0, 0], [0, 0, 1], 20, 10, 0.1)   # y in [-1, 1]
    b = Camera.orthographic([0, 5, 0], [0, 0, 0], [0, 0, 1], 30, 10, 0.1)   # x in [-1.5, 1.5]
    box = frusta_bounds([a, b])
    np.testing.assert_allclose(box, [[-1.5, -1.0, -0.5], [1.5, 1.0, 0.5]], atol=1e-6)


# -- tomography as a linear problem --------------------------------------------


def sample_grid(volume):
    """A tet grid whose vertices are the volume's samples (the box a hair larger:
    1e-4 cells, so that rays along its faces run inside)."""
    from mi_tetvr.recon.tomography import aligned_resolution
    lo, hi = volume.bounds()
    s = float(volume.spacing[0])
    V, T = grid_init(np.stack([lo - 1e-4 * s, hi + 1e-4 * s]),
                     aligned_resolution(np.stack([lo, hi]), s))
    return V, T


def test_projector_adjoint_is_its_transpose(blob_data):
    """<A x, y> = <x, A^T y> for random x, y: the walk's reverse-mode
    derivative is the projector's transpose (to float32 precision)."""
    from mi_tetvr.recon.tomography import Projector
    vol, _, data = blob_data
    V, T = sample_grid(vol)
    proj = Projector(V, T, [v.camera for v in data.train[:3]])
    rng = np.random.default_rng(3)
    for _ in range(2):
        x = rng.uniform(-1, 1, proj.shape[1])
        y = rng.uniform(-1, 1, proj.shape[0])
        lhs, rhs = np.dot(proj.forward(x), y), np.dot(x, proj.adjoint(y))
        assert abs(lhs - rhs) <= 2e-5 * np.sum(np.abs(proj.forward(np.abs(x))) * np.abs(y))
    # a subset of views is the same rows of A
    x = rng.uniform(0, 1, proj.shape[1])
    np.testing.assert_allclose(proj.forward(x, [2]), proj.forward(x)[proj.rows([2])],
                               rtol=1e-6, atol=1e-7)
    # the row sums are the rays' lengths in the box (the grid reaches 1e-3 cells beyond)
    lengths = proj.forward(np.ones(proj.shape[1])).reshape(-1, data.train[0].camera.width)
    lo, hi = vol.bounds()
    inside = lengths[lengths > 0]
    assert inside.max() <= np.linalg.norm((hi - lo)[:2]) * 1.01


def test_one_yardstick_through_every_path(blob_data):
    """One reconstruction (a linear field: the tets and the trilinear grid
    hold it alike) scored through the grid path (its samples, its trilinear
    projections), the tet path (the field sampled at the samples, projections
    walked by tetvr) and the fit's own evaluation (metrics.json): the same
    numbers."""
    from mi_tetvr.grid.volume import Volume
    from mi_tetvr.grid.xray import project_volume
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.metrics import tomography_scores
    from mi_tetvr.recon.tomography import Projector
    from mi_tetvr.recon.trainer import Trainer
    vol, made, data = blob_data
    scale = made["info"]["attenuation_scale"]
    nx, ny, nz = vol.shape
    pts = vol.sample_points()
    linear = lambda p: 0.5 + 0.1 * p[..., 0] - 0.05 * p[..., 1] + 0.08 * p[..., 2]  # noqa: E731
    recon = linear(pts).reshape(nz, ny, nx)
    truth = vol.values.astype(np.float64)
    targets = [1.0 - v.image[..., 3] for v in data.test]
    grid = Volume(recon.astype(np.float32), vol.spacing, vol.origin)
    by_grid = tomography_scores(recon, truth, [project_volume(grid, v.camera, scale)
                                               for v in data.test], targets)
    V, T = sample_grid(vol)
    mu = scale * linear(V)
    field = sample_field(V, T, mu / scale, pts).reshape(truth.shape)
    proj = Projector(V, T, [v.camera for v in data.test])
    depth = proj.forward(mu)
    by_tets = tomography_scores(field, truth, [
        np.exp(-depth[proj.rows([i])]).reshape(v.camera.height, v.camera.width)
        for i, v in enumerate(data.test)], targets)
    assert by_grid.keys() == by_tets.keys() == {"volume_psnr", "slice_ssim",
                                                "projection_psnr_views", "projection_psnr_pixels"}
    for k in by_grid:
        assert by_tets[k] == pytest.approx(by_grid[k], abs=2e-3), k
    assert by_grid["projection_psnr_views"] != pytest.approx(by_grid["projection_psnr_pixels"],
                                                             abs=1e-3)
    fit = Trainer(data, V, T, FitConfig(model="absorption"), {"attenuation": mu}).evaluate(
        data.test)["mean"]
    assert fit["psnr"] == pytest.approx(by_grid["projection_psnr_views"], abs=2e-3)
    assert fit["psnr_all_pixels"] == pytest.approx(by_grid["projection_psnr_pixels"], abs=2e-3)


def test_graded_mesh_keeps_the_grids_penalty(blob_data):
    """A coarse grid's own penalty scale is stiffer than the detector's grid's:
    the data's curvature per vertex, ``A^T W A 1``, grows as ``h^3`` (``A 1`` is
    a ray's length, the hat functions summing to 1; a vertex meets ``h^2``
    rays over ``h``), the penalty's as ``h``, so 4 times at twice the cell. A
    mesh graded from it keeps the grid's scale (``reference``,
    :func:`grid_penalty_scale`)."""
    from mi_tetvr.mesh.topology import build_topology
    from mi_tetvr.recon.tomography import (PenalizedLS, Projector, TetGradient, coarse_grid,
                                           grid_penalty_scale)
    from mi_tetvr.recon.tomography import depths
    vol, _, data = blob_data
    V, T = sample_grid(vol)
    lo, hi = vol.bounds()
    s = float(vol.spacing[0])
    box = np.stack([lo - 1e-4 * s, hi + 1e-4 * s])
    cams, b = [v.camera for v in data.train], depths(data.train, None)

    def scale(v, t, **kw):
        t = build_topology(v, t).tets
        pls = PenalizedLS(Projector(v, t, cams), b, None, TetGradient(v, t), **kw)
        return pls.beta0, pls.cell

    fine = scale(V, T)
    assert grid_penalty_scale(box, 8, cams, b, None) == pytest.approx(fine, rel=1e-6)
    coarse = scale(*coarse_grid(box, 8))
    assert coarse[1] == pytest.approx(2 * fine[1], rel=1e-6)
    # A 1 is the ray's length (the hat functions sum to 1): d grows as h^3, c as h
    assert coarse[0] / fine[0] == pytest.approx(4.0, rel=1e-3), (coarse, fine)
    assert scale(*coarse_grid(box, 8), reference=fine) == fine


def test_graded_grid_keeps_the_fine_grids_penalty(blob_data):
    """``fine_penalty_scale`` from the coarse trilinear field's projector (no cell
    split) is the fine grid's own :class:`PenalizedLS` scale (every cell split: one
    unknown per fine vertex): the data's curvatures sum to ``sum_i w_i L_i^2``
    whatever the unknowns, since every basis row sums to 1."""
    from mi_tetvr.recon.octree import GradedGrid
    from mi_tetvr.recon.tomography import (PenalizedLS, Projector, TetGradient, depths,
                                           fine_penalty_scale)
    vol, _, data = blob_data
    lo, hi = vol.bounds()
    cell = (hi - lo) / 8
    cams, b = [v.camera for v in data.train], depths(data.train, None)
    w = np.random.default_rng(0).uniform(0.5, 2.0, len(b))        # weights of any kind

    def projector(split):
        g = GradedGrid(lo, cell, split)
        v, t, basis = g.walk()
        return g, Projector(v, t, cams, basis=basis @ g.P)

    g, coarse = projector(np.zeros((4, 4, 4), bool))
    plain = TetGradient(*g.fine_mesh())
    _, fine = projector(np.ones((4, 4, 4), bool))
    own = PenalizedLS(fine, b, w, plain)
    assert fine_penalty_scale(coarse, w, plain) == pytest.approx((own.beta0, own.cell),
                                                                  rel=1e-4)


def test_default_basis_is_trilinear_under_its_cap(blob_data, tmp_path, monkeypatch):
    """The default basis is trilinear where its walk has at most ``TRILINEAR_TETS``
    tets (a graded grid's over its cells made even), else linear, and the log says why;
    a resumed fit keeps its own basis by default, and another one given is refused in
    one line."""
    import mi_tetvr.recon.tomography as tomo
    data = blob_data[2]
    quick = dict(model="absorption", solver="sart", passes=2, validation=0)
    # the blob's grid has 8^3 cells: the walk 48 tets each, one more than the cap
    monkeypatch.setattr(tomo, "TRILINEAR_TETS", 48 * 8 ** 3 - 1)
    logs = []
    m = run(data, tmp_path / "fit", FitConfig(**quick), progress=False, log=logs.append)
    assert m["solver"]["basis"] == "linear" and m["unknowns"] == 9 ** 3
    assert "basis linear (the default: its walk would have 24,576 tets, more than " \
        "24,575)" in logs, logs
    monkeypatch.setattr(tomo, "TRILINEAR_TETS", 48 * 8 ** 3)
    logs.clear()
    m = run(data, tmp_path / "fit", FitConfig(**quick), progress=False, log=logs.append)
    assert m["solver"]["basis"] == "linear" and "basis linear: the resumed fit's" in logs
    with pytest.raises(ValueError, match='basis: "linear" there, "trilinear" now'):
        run(data, tmp_path / "fit", FitConfig(**quick, basis="trilinear"), progress=False,
            log=logs.append)
    m = run(data, tmp_path / "new", FitConfig(**quick), progress=False, log=logs.append)
    assert m["solver"]["basis"] == "trilinear" and "basis trilinear (the default)" in logs
    # a graded grid walks its cells made even: 7 per axis walk as 8
    monkeypatch.setattr(tomo, "TRILINEAR_TETS", 48 * 7 ** 3)
    logs.clear()
    m = run(data, tmp_path / "graded", FitConfig(model="absorption", grid_resolution=7,
                                                 adapt=0.75, tv=0.1, passes=2),
            progress=False, log=logs.append)
    assert m["solver"]["basis"] == "linear" and "basis linear (the default: its walk would " \
        "have 24,576 tets, more than 16,464)" in logs, logs


def test_adaptive_grid_resumes_and_splits_anew(blob_data, tmp_path):
    """A resumed adaptive fit on the trilinear field splits the coarse cells anew from the
    saved field, within its share, and goes on from that field: its first pass fits the
    projections far better than a fresh fit's first. A fresh one solves the graded grid
    from zero, the coarse field only choosing the cells."""
    data = blob_data[2]

    def history():
        with np.load(tmp_path / "fit" / "checkpoint.npz") as saved:
            return json.loads(str(saved["history"]))["loss"]

    config = FitConfig(model="absorption", adapt=0.75, tv=0.1, passes=4)
    first = run(data, tmp_path / "fit", config, progress=False, log=lambda *a: None)
    loss = history()
    fresh = loss[0]
    # the coarse grid's 2 + 2 passes (a third of 4, at least 2: its field only chooses the
    # cells), then the graded grid's 2 + 4 from zero (as the grid's fit starts): its first
    # pass is about as far off as the coarse grid's first, not near its last
    assert len(loss) == 10 and loss[4] > 0.5 * fresh, loss
    logs = []
    again = run(data, tmp_path / "fit", config, progress=False, log=logs.append)
    assert any(line.startswith("resumed from") for line in logs), logs
    assert any(line.startswith("adaptive grid: split") for line in logs), logs
    assert again["solver"]["basis"] == first["solver"]["basis"] == "trilinear"
    assert 729 // 2 < again["unknowns"] <= 0.75 * 729
    resumed = history()[0]
    assert resumed < 1e-2 * fresh, (fresh, resumed)


def test_faces_are_in_the_projections_and_cameras_survive_json(tmp_path):
    """A volume whose faces are not empty: the detector rows on its top and
    bottom faces (and the columns on its side faces at 0 and 90 degrees) see
    them in every view, after the JSON round trip too, whose cameras are the
    written ones bit for bit (parallel and cone beam)."""
    vol = make_volume(np.full((5, 6, 7), 0.5) + np.random.default_rng(0).uniform(0, 0.5, (5, 6, 7)))
    for beam in ("parallel", "cone"):
        made = make_xray_dataset(vol, tmp_path / beam, views=8, test_views=4, beam=beam,
                                 progress=False)
        data = load_nerf(tmp_path / beam)
        for written, read in zip(made["train"] + made["test"], data.train + data.test):
            a, b = written.camera, read.camera
            for k in ("to_world", "fx", "fy", "cx", "cy", "pixel_size", "width", "height"):
                assert np.array_equal(getattr(a, k), getattr(b, k)), (beam, k)
            np.testing.assert_allclose(written.image, read.image, atol=1e-7)
        if beam == "parallel":
            for view in data.train + data.test:
                alpha = view.image[..., 3]
                assert alpha[0].max() > 0 and alpha[-1].max() > 0, view.name
                # a face row integrates the face: exact against a ray just inside it
                o, d = view.camera.rays(np.array([[view.camera.cx, 0.5]]))
                inner = line_integrals(vol, o - [0, 0, 1e-9], d)
                face = -np.log(1 - alpha[0, int(view.camera.cx)]) / made["info"][
                    "attenuation_scale"]
                assert face == pytest.approx(inner[0], rel=1e-4)
            # at 0 degrees the columns on the y samples see the volume: both faces too
            at0 = data.train[0].image[..., 3]
            assert np.count_nonzero(at0.max(0) > 0) == vol.shape[1]


def test_anisotropic_volume_is_resampled_for_a_parallel_beam(tmp_path):
    """Spacings that differ by 0.3 % between axes: the volume is resampled to
    its x spacing (trilinear, so a linear field stays exact), and the data set
    records both."""
    nz, ny, nx = 6, 7, 8
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    vol = make_volume(0.2 + 0.05 * x + 0.03 * y + 0.04 * z, spacing=(1.0, 1.003, 0.997),
                      value_range=(0.0, 1.0))
    made = make_xray_dataset(vol, tmp_path, views=4, test_views=0, progress=False)
    got = made["volume"]
    assert got.isotropic() and got.spacing[0] == vol.spacing[0]
    info = json.loads((tmp_path / "xray_info.json").read_text())
    assert info["resampled_from"]["spacing"] == [float(s) for s in vol.spacing]
    # the linear field in closed form at the new samples' world positions
    i, j, k = ((got.sample_points() - vol.origin) / vol.spacing).T
    np.testing.assert_allclose(got.values.ravel(), 0.2 + 0.05 * i + 0.03 * j + 0.04 * k,
                               atol=1e-6)


def test_refined_volume_interpolates_a_smooth_field():
    """Volume.refined (the data sets' finer field): every k-th sample is the
    volume's own; between samples the cubic spline is far closer to a smooth
    field (closed form) than the trilinear one, and a constant stays exact."""
    n = 16
    z, y, x = np.meshgrid(*(np.arange(n) / (n - 1),) * 3, indexing="ij")
    f = lambda x, y, z: 1.0 + np.sin(2 * x) * np.cos(1.5 * y) * np.sin(z + 0.5)   # noqa: E731
    vol = make_volume(f(x, y, z), spacing=(1.0, 1.0, 1.0), value_range=(0.0, 2.0))
    fine = vol.refined(2)
    assert fine.values.shape == (2 * n - 1,) * 3
    np.testing.assert_allclose(fine.spacing, vol.spacing / 2)
    np.testing.assert_allclose(fine.values[::2, ::2, ::2], vol.values, atol=1e-7)
    inner = slice(8, -8)            # 4 samples from the mirrored faces, whose effect decays
    p = fine.sample_points().reshape(*fine.values.shape, 3)[inner, inner, inner]
    exact = f(*np.moveaxis((p - vol.origin) / vol.spacing / (n - 1), -1, 0)) / 2.0
    spline = np.abs(fine.values[inner, inner, inner] - exact).max()
    trilinear = np.abs(vol.sample(p) - exact).max()
    assert spline < trilinear / 10, (spline, trilinear)
    flat = make_volume(np.full((5, 6, 7), 0.3), value_range=(0.0, 1.0)).refined(3)
    np.testing.assert_allclose(flat.values, 0.3, atol=1e-6)


def test_poisson_counts_and_their_weights(tmp_path):
    """Training projections with a flux are Poisson counts: their variance
    about the noise-free transmittance is T / flux; the held-out ones are
    noise-free; the fit weights each ray by its count."""
    from mi_tetvr.recon.tomography import statistical_weights
    vol = blob_volume(12)
    clean = make_xray_dataset(vol, tmp_path / "clean", views=8, test_views=2, progress=False)
    noisy = make_xray_dataset(vol, tmp_path / "noisy", views=8, test_views=2, flux=400.0,
                              scale=clean["info"]["attenuation_scale"], progress=False)
    t = np.concatenate([1 - v.image[..., 3].ravel() for v in clean["train"]]).astype(np.float64)
    n = np.concatenate([1 - v.image[..., 3].ravel() for v in noisy["train"]]).astype(np.float64)
    ratio = np.mean((n - t) ** 2) / np.mean(t / 400.0)
    assert 0.85 < ratio < 1.15, ratio
    assert abs(np.mean(n - t)) < 3 * np.sqrt(np.mean(t / 400.0) / len(t))     # unbiased
    for a, b in zip(clean["test"], noisy["test"]):
        np.testing.assert_array_equal(a.image, b.image)
    data = load_nerf(tmp_path / "noisy")
    assert data.xray_flux == 400.0
    w = statistical_weights(data.train, data.xray_flux)
    np.testing.assert_allclose(w, np.maximum(400.0 * n, 1.0), rtol=1e-5)


def test_fdk_recovers_a_ball(tmp_path):
    """FDK of cone-beam projections of a ball of value 0.6 holding a ball of
    1.0: the values at their centres (closed form) within 3 %."""
    from mi_tetvr.grid.xray import fdk
    g = np.linspace(-1, 1, 25)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    vol = make_volume(((x ** 2 + y ** 2 + z ** 2) < 0.6) * 0.6
                      + (((x - 0.35) ** 2 + y ** 2 + z ** 2) < 0.06) * 0.4)
    made = make_xray_dataset(vol, tmp_path / "cone", views=72, test_views=0, beam="cone",
                             distance=4.0, fov=2 * np.degrees(np.arctan(1.5 / 4.0)),
                             progress=False)
    r = fdk(vol, made["train"], made["info"]["attenuation_scale"])
    assert r[12, 12, 12] == pytest.approx(0.6, rel=0.03)
    assert r[12, 12, 16] == pytest.approx(1.0, rel=0.03)
    parallel = make_xray_dataset(vol, tmp_path / "parallel", views=2, test_views=0,
                                 progress=False)
    with pytest.raises(ValueError, match="cone-beam"):
        fdk(vol, parallel["train"], 1.0)


def ellipse_volume(n=33, nz=2):
    """Two ellipses in each of ``nz`` z slices, on an isotropic grid."""
    from mi_tetvr.grid.volume import Volume
    g = np.linspace(-1, 1, n)
    yy, xx = np.meshgrid(g, g, indexing="ij")
    v = 0.7 * (((xx - 0.2) / 0.6) ** 2 + ((yy + 0.1) / 0.45) ** 2 <= 1)
    v += 0.3 * (((xx + 0.35) / 0.25) ** 2 + ((yy - 0.3) / 0.3) ** 2 <= 1)
    s = 2.0 / (n - 1)
    return Volume(np.repeat(v[None], nz, 0).astype(np.float32), np.full(3, s),
                  np.array([-1.0, -1.0, -0.5 * s * (nz - 1)]))


def test_tuned_baselines_choose_on_held_out_views(tmp_path):
    """On sparse, noisy projections of a piecewise-constant phantom, FISTA-TV
    and SART tuned on views held out of the training ones (never on the
    truth) beat filtered back-projection against the truth, and FISTA-TV
    chooses a TV weight above the smallest it tries (the noise calls for it);
    the chosen pass count is one whose held-out error is the least seen."""
    from mi_tetvr.grid.slices import reconstruct_slices, tuned_slices
    vol = ellipse_volume()
    made = make_xray_dataset(vol, tmp_path, views=16, test_views=0, flux=2e3, progress=False)
    scale = made["info"]["attenuation_scale"]
    truth = vol.values.astype(np.float64)

    def psnr(v):
        return -10 * np.log10(np.mean((np.clip(v, 0, 1) - truth) ** 2))

    fbp = psnr(reconstruct_slices(vol, made["train"], scale, "fbp"))
    tv, chosen = tuned_slices(vol, made["train"], scale, "fista_tv", 40, flux=2e3)
    sart, chosen_sart = tuned_slices(vol, made["train"], scale, "sart", 10, flux=2e3)
    assert psnr(tv) > fbp + 3 and psnr(sart) > fbp + 1, (psnr(tv), psnr(sart), fbp)
    assert chosen["tv"] > min(r["tv"] for r in chosen["trials"])
    best = min(chosen_sart["trials"], key=lambda r: r["validation_mse"])
    assert chosen_sart["passes"] == best["passes"]


def test_held_out_stopping_returns_the_best_pass(tmp_path):
    """SART on the tets with a held-out split: the attenuation returned is the
    pass with the least held-out error, and that error is what it projects."""
    from mi_tetvr.recon.tomography import HeldOut, Projector, depths, sart
    vol = ellipse_volume(n=13)
    made = make_xray_dataset(vol, tmp_path, views=12, test_views=0, flux=500, progress=False)
    lo, hi = vol.bounds()
    V, T = grid_init(np.stack([lo - 1e-3, hi + 1e-3]), 12)
    proj = Projector(V, T, [v.camera for v in made["train"]])
    b = depths(made["train"], 500)
    held = HeldOut(proj, b, [2, 9], patience=2)
    x = sart(proj, b, 12, views=[0, 1, 3, 4, 5, 6, 7, 8, 10, 11], held_out=held)
    assert held.best[1] == int(np.argmin(held.errors)) + 1
    assert len(held.errors) == 12 or len(held.errors) - held.best[1] == 2
    got = float(np.mean((np.exp(-proj.forward(x, [2, 9])) - held.target) ** 2))
    assert got == pytest.approx(min(held.errors), rel=1e-6)


def test_trilinear_basis_walks_the_trilinear_field(blob_data):
    """``basis trilinear``: the tets of twice the cells take the grid's trilinear
    field at their vertices (scipy's ``RegularGridInterpolator`` says so), the
    projector through them is ``A E`` with adjoint ``E^T A^T``, and its optical
    depths approach the trilinear field's exact line integrals
    (:func:`~mi_tetvr.grid.xray.line_integrals`, against a dense quadrature
    above) at a quarter of the error of the grid's own tets (h^2)."""
    from scipy.interpolate import RegularGridInterpolator

    from mi_tetvr.grid.volume import Volume
    from mi_tetvr.recon.tomography import Projector, aligned_resolution, trilinear_grid
    vol, _, data = blob_data
    lo, hi = vol.bounds()
    s = float(vol.spacing[0])
    box = np.stack([lo - 1e-4 * s, hi + 1e-4 * s])
    res = aligned_resolution(np.stack([lo, hi]), s)
    V, T = grid_init(box, res)
    Vf, Tf, E = trilinear_grid(box, res)
    assert E.shape == (len(Vf), len(V)) and len(Tf) == 8 * len(T)
    rng = np.random.default_rng(5)
    u = rng.uniform(0, 1, len(V))                      # rough: every cell twisted
    axes = [np.unique(V[:, i]) for i in range(3)]
    values = u.reshape([len(a) for a in axes])          # (x, y, z): grid_init's order
    np.testing.assert_allclose(E @ u, RegularGridInterpolator(axes, values)(Vf), atol=1e-12)
    cams = [v.camera for v in data.train[:3]]
    tri, lin = Projector(Vf, Tf, cams, basis=E), Projector(V, T, cams)
    assert tri.shape == lin.shape
    y = rng.uniform(-1, 1, tri.shape[0])
    lhs, rhs = np.dot(tri.forward(u), y), np.dot(u, tri.adjoint(y))
    assert abs(lhs - rhs) <= 2e-5 * np.sum(np.abs(tri.forward(u)) * np.abs(y))
    grid = Volume(values.transpose(2, 1, 0).astype(np.float64), (box[1] - box[0]) /
                  (np.array(values.shape) - 1), box[0])
    ref = np.concatenate([line_integrals(grid, *c.rays()) for c in cams])
    hit = ref > 0.1 * ref.max()
    err = {k: np.sqrt(np.mean((p.forward(u)[hit] - ref[hit]) ** 2))
           for k, p in (("trilinear", tri), ("linear", lin))}
    assert err["trilinear"] < 0.35 * err["linear"], err
