"""Regular-grid volumes: loaders, the Dr.Jit ray marcher, cameras and data sets."""
import gzip
import json

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.interpolate import RegularGridInterpolator

import mitsuba as mi
from mi_tetvr.recon.datasets import View

from mi_tetvr.grid import volume as V
from mi_tetvr.transfer import TransferFunction
from mi_tetvr.color import srgb_to_linear


def const_tf(color=(0.2, 0.5, 0.8), opacity=1.0):
    return TransferFunction([0.0], [color], [0.0], [opacity])


def box_chord(o, d, lo, hi):
    """Length of the part of the ray o + s d (s >= 0, |d| = 1) inside the box (numpy)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tn = np.nanmax(np.minimum(t1, t2), axis=-1)
    tf = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.maximum(tf - np.maximum(tn, 0.0), 0.0)


# ---------------------------------------------------------------------------- placement
def test_make_volume_placement_and_normalisation():
    v = np.arange(5 * 7 * 9, dtype=np.float64).reshape(5, 7, 9) * 3.0 + 10.0
    vol = V.make_volume(v, spacing=(1.0, 1.0, 2.0))
    assert vol.shape == (9, 7, 5)
    lo, hi = vol.bounds()
    # extents (8, 6, 8) * spacing -> (8, 6, 8), largest 8 -> scaled to 2
    np.testing.assert_allclose(lo, [-1, -0.75, -1])
    np.testing.assert_allclose(hi, [1, 0.75, 1])
    np.testing.assert_allclose(vol.spacing, [0.25, 0.25, 0.5])
    assert vol.values.dtype == np.float32 and vol.values.min() == 0 and vol.values.max() == 1
    assert vol.data_range == (10.0, v.max())
    vol2 = V.make_volume(v, value_range=(10.0, 20.0))
    assert vol2.values.max() == 1.0 and vol2.values[0, 0, 1] == pytest.approx(0.3)
    vol3 = V.make_volume(v.transpose(2, 1, 0), layout="xyz")
    np.testing.assert_array_equal(vol3.values, V.make_volume(v).values)


# ---------------------------------------------------------------------------- marcher
def test_constant_volume_closed_form():
    vol = V.make_volume(np.ones((5, 7, 9)))             # box [-1,1] x [-.75,.75] x [-.5,.5]
    lo, hi = vol.bounds()
    rng = np.random.default_rng(1)
    k = 64
    o = rng.normal(size=(k, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.9, 0.9, (k, 3)) * hi - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # axis-aligned, from inside, a miss, pointing away
    o[:6] = [[-3, 0, 0], [0, -3, 0.1], [0, 0.2, 3], [0.5, 0.5, 0.2], [-3, 2, 0], [0, 0, 3]]
    d[:6] = [[1, 0, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1], [1, 0, 0], [0, 0, 1]]
    c = np.array([0.2, 0.5, 0.8])
    sigma = 1.3
    C, a = V.render_rays(vol, const_tf(c, 1.0), o, d, opacity_scale=sigma, step=0.37,
                         min_transmittance=0.0)
    C = np.array(C, np.float64).reshape(3, -1).T
    a = np.array(a, np.float64)
    L = box_chord(o, d, lo, hi)
    assert np.all(L[:4] > 0) and L[0] == pytest.approx(2.0) and L[2] == pytest.approx(1.0)
    alpha = 1.0 - np.exp(-sigma * L)
    np.testing.assert_allclose(a, alpha, atol=2e-6)
    np.testing.assert_allclose(C, alpha[:, None] * c, atol=2e-6)
    assert (L == 0).any() and np.all(a[L == 0] == 0)


def ramp_volume():
    x = np.arange(9, dtype=np.float64)                   # t = (x_world + 1) / 2
    return V.make_volume(np.broadcast_to(x, (4, 4, 9)).copy(), spacing=(1, 1, 1))


def test_ramp_converges_to_analytic_integral():
    vol = ramp_volume()
    k = 2.0                                               # sigma(t) = k t, red(t) = t
    tf = TransferFunction([0, 1], [[0, 0.3, 1], [1, 0.3, 1]], [0, 1], [0, k])
    # ray along +x through the box centre line: s in [0, 2], t = s / 2
    sigma = lambda s: k * s / 2  # noqa: E731
    tau = lambda s: k * s * s / 4  # noqa: E731
    ref = [quad(lambda s: sigma(s) * col(s) * np.exp(-tau(s)), 0, 2, epsabs=1e-13)[0]
           for col in (lambda s: s / 2, lambda s: 0.3, lambda s: 1.0)]
    alpha_ref = 1 - np.exp(-tau(2.0))
    errs = []
    for step in (2.0, 1.0, 0.5):
        C, a = V.render_rays(vol, tf, [[-3, 0, 0]], [[1, 0, 0]], step=step,
                             min_transmittance=0.0)
        C = np.array(C, np.float64).ravel()
        # midpoint rule: transmittance exact for linear extinction
        assert float(np.array(a)[0]) == pytest.approx(alpha_ref, abs=2e-6)
        errs.append(np.abs(C - ref).max())
    assert errs[-1] < 2e-3
    for e0, e1 in zip(errs, errs[1:]):
        assert 3.0 < e0 / e1 < 5.0, errs                # second order


def test_trilinear_matches_scipy():
    rng = np.random.default_rng(2)
    vals = rng.uniform(size=(5, 6, 7))
    vol = V.make_volume(vals, spacing=(1.0, 2.0, 1.5))
    lo, hi = vol.bounds()
    p = rng.uniform(lo, hi, (200, 3))
    nx, ny, nz = vol.shape
    axes = [vol.origin[a] + np.arange(n) * vol.spacing[a] for a, n in enumerate((nx, ny, nz))]
    rgi = RegularGridInterpolator((axes[2], axes[1], axes[0]), vol.values.astype(np.float64))
    ref = rgi(p[:, ::-1])
    field = V.GridField(vol)
    got = np.array(field.eval(mi.Point3f(*p.astype(np.float32).T)), np.float64)
    np.testing.assert_allclose(got, ref, atol=2e-6)
    np.testing.assert_allclose(vol.sample(p), ref, atol=1e-12)


def test_tf_eval_matches_numpy():
    tf = TransferFunction([0, 0.3, 0.3, 0.8, 1], [[0, 0, 0], [1, .5, 0], [0, 1, 1], [.2, .2, .2],
                                                 [1, 1, 1]],
                          [0, 0.5, 0.5, 1.0], [0.0, 1.0, 3.0, 0.5])
    t = np.concatenate([np.linspace(-0.2, 1.2, 57) + 0.0037, [0.3, 0.5, 0.8]])
    vr = (2.0, 6.0)
    s = vr[0] + t * (vr[1] - vr[0])
    c, sig = V.TFEval(tf, value_range=vr, opacity_scale=2.5)(mi.Float(s.astype(np.float32)))
    c_ref, s_ref = tf(t)
    np.testing.assert_allclose(np.array(c, np.float64).reshape(3, -1).T, c_ref, atol=2e-6)
    np.testing.assert_allclose(np.array(sig, np.float64), 2.5 * s_ref, atol=1e-5)


# ---------------------------------------------------------------------------- cameras
def test_cameras_point_at_origin():
    cams = V.fibonacci_cameras(7, radius=3.0, res=(15, 11), fov=40.0)
    cams += V.random_cameras(3, radius=2.5, res=(15, 11), seed=3)
    cams.append(View.look_at("pole", [0, 0, 4.0], [0, 0, 0], [0, 0, 1], 15, 11,
                             fov_x=30.0))                          # at the pole of up=z
    fib = np.array([c.center for c in cams[:7]])
    assert np.allclose(np.linalg.norm(fib, axis=1), 3.0)
    assert np.ptp(fib[:, 2]) > 4.0                                   # spread over the sphere
    for cam in cams:
        m = np.asarray(cam.to_world)
        assert np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
        o, d, w, h = V.camera_rays(cam)
        o = np.array(o, np.float64).reshape(3, -1).T
        d = np.array(d, np.float64).reshape(3, -1).T.reshape(h, w, 3)
        assert np.allclose(o, cam.center, atol=1e-6)
        # the centre pixel (odd size) looks at the origin
        np.testing.assert_allclose(d[h // 2, w // 2], -cam.center / np.linalg.norm(cam.center),
                                   atol=1e-6)
        # independent NeRF/OpenGL ray from the intrinsics and the OpenGL camera-to-world
        gl = m @ np.diag([-1, 1, -1, 1])
        j, i = np.mgrid[0:h, 0:w]
        dc = np.stack([(i + 0.5 - cam.cx) / cam.fx, -(j + 0.5 - cam.cy) / cam.fy,
                       -np.ones_like(i, dtype=float)], -1)
        dw = dc @ gl[:3, :3].T
        dw /= np.linalg.norm(dw, axis=-1, keepdims=True)
        np.testing.assert_allclose(d, dw, atol=2e-6)
        # pixel (0, 0) is top-left: up and left of the view direction
        up, right = gl[:3, 1], gl[:3, 0]
        assert d[0, 0] @ up > 0 and d[0, 0] @ right < 0
    # Mitsuba's look_at agrees
    ref = mi.ScalarTransform4f().look_at(origin=[1, 2, 3], target=[0, 0, 0], up=[0, 0, 1]).matrix
    np.testing.assert_allclose(V.look_at([1, 2, 3]), np.array(ref, np.float64), atol=1e-6)


def test_sensor_matches_camera():
    rng = np.random.default_rng(4)
    vol = V.make_volume(rng.uniform(size=(6, 6, 6)))
    tf = TransferFunction([0, 1], [[1, 0, 0], [0, 0, 1]], [0, 1], [0.5, 3.0])
    cam = V.fibonacci_cameras(3, radius=3.5, res=(16, 12))[1]
    a = V.render_volume(vol, tf, cam)
    b = V.render_volume(vol, tf, mi.load_dict(cam.sensor_dict()))
    assert a.shape == (12, 16, 4) and a[..., 3].max() > 0.3
    np.testing.assert_allclose(a, b, atol=1e-4)


# ---------------------------------------------------------------------------- loaders
def test_loaders_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    v = rng.integers(0, 256, size=(3, 4, 5), dtype=np.uint8)          # (nz, ny, nx)
    ref = V.make_volume(v)

    np.save(tmp_path / "v.npy", v)
    a = V.load_volume(tmp_path / "v.npy")
    np.testing.assert_array_equal(a.values, ref.values)

    V.write_cvol(tmp_path / "v.cvol", v, voxel_size=(1.0, 1.0, 2.0))
    raw = (tmp_path / "v.cvol").read_bytes()
    assert len(raw) == 64 + v.size and raw[:4] == b"cvol"
    b = V.load_volume(tmp_path / "v.cvol")
    np.testing.assert_array_equal(b.values, ref.values)
    np.testing.assert_allclose(b.source_spacing, [1, 1, 2])
    np.testing.assert_allclose(b.spacing / b.spacing[0], [1, 1, 2])
    bad = bytearray(raw)
    bad[56] = 1
    (tmp_path / "c.cvol").write_bytes(bytes(bad))
    with pytest.raises(ValueError, match="LZ4"):
        V.load_volume(tmp_path / "c.cvol")

    V.write_mhd(tmp_path / "v.mhd", v.astype(np.int16), spacing=(0.5, 0.5, 1.5))
    c = V.load_volume(tmp_path / "v.mhd")
    np.testing.assert_array_equal(c.values, ref.values)
    np.testing.assert_allclose(c.source_spacing, [0.5, 0.5, 1.5])

    with gzip.open(tmp_path / "thing_5x4x3_uint8.raw.gz", "wb") as f:
        f.write(v.tobytes())
    d = V.load_volume(tmp_path / "thing_5x4x3_uint8.raw.gz")
    np.testing.assert_array_equal(d.values, ref.values)
    (tmp_path / "x.raw").write_bytes(v.astype("<u2").tobytes())
    e = V.load_volume(tmp_path / "x.raw", shape=(5, 4, 3), dtype="uint16", value_range=(0, 255))
    np.testing.assert_allclose(e.values, v / 255.0, atol=1e-7)
    with pytest.raises(ValueError, match="shape"):
        V.load_volume(tmp_path / "x.raw")

    import pyvista as pv
    img = pv.ImageData(dimensions=(5, 4, 3), spacing=(1.0, 2.0, 1.0))
    img.point_data["s"] = v.ravel()                                   # VTK: x fastest
    img.save(tmp_path / "v.vti")
    f = V.load_volume(tmp_path / "v.vti")
    np.testing.assert_array_equal(f.values, ref.values)
    np.testing.assert_allclose(f.source_spacing, [1, 2, 1])


def test_real_volumes_load(data_dir):
    eng = V.load_volume(data_dir / "engine-ct" / "engine_256x256x128_uint8.raw.gz")
    assert eng.shape == (256, 256, 128) and eng.values.shape == (128, 256, 256)
    lo, hi = eng.bounds()
    np.testing.assert_allclose(hi, [1, 1, 127 / 255], atol=1e-9)
    np.testing.assert_allclose(lo, -hi)
    assert eng.values.min() == 0 and eng.values.max() == 1
    c60 = V.load_volume(data_dir / "c60" / "C60Large.cvol")
    assert c60.shape == (128, 128, 128)
    head = V.load_volume(data_dir / "headmr" / "HeadMRVolume.mhd")
    assert head.shape == (48, 62, 42) and np.allclose(head.source_spacing, 4.0)
    assert V.load_volume(data_dir / "headmr" / "HeadMRVolume.mhd").values.std() > 0.05


# ---------------------------------------------------------------------------- data set
def test_make_dataset(tmp_path):
    rng = np.random.default_rng(6)
    vol = V.make_volume(rng.uniform(size=(6, 7, 8)))
    tf = TransferFunction([0, 1], [[0.9, 0.2, 0.1], [0.1, 0.4, 1.0]], [0, 1], [0.2, 4.0])
    res = V.make_dataset(vol, tf, views=3, res=(16, 12), out_dir=tmp_path / "ds", test_views=2,
                         radius=3.0, seed=1, step=0.5, progress=False)
    out = tmp_path / "ds"
    for name in ("transforms_train.json", "transforms_test.json", "volume_info.json"):
        assert (out / name).is_file()
    info = json.loads((out / "volume_info.json").read_text())
    assert info["step_voxels"] == 0.5 and info["cameras"]["n_test"] == 2
    for split, n in (("train", 3), ("test", 2)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert meta["w"] == 16 and meta["h"] == 12 and len(meta["frames"]) == n
        assert meta["fl_x"] == pytest.approx(8 / np.tan(meta["camera_angle_x"] / 2))
        imgs = res[split]
        assert imgs.shape == (n, 12, 16, 4) and imgs[..., 3].max() > 0.2
        for i, fr in enumerate(meta["frames"]):
            cam = res[f"cameras_{split}"][i]
            m = np.array(fr["transform_matrix"])
            np.testing.assert_allclose(m, cam.to_world @ np.diag([-1, 1, -1, 1]), atol=1e-12)
            # OpenGL: the camera looks along its -z axis, towards the origin
            fwd = -m[:3, 2]
            np.testing.assert_allclose(fwd, -m[:3, 3] / np.linalg.norm(m[:3, 3]), atol=1e-9)
            from PIL import Image
            path = out / fr["file_path"]
            png = np.asarray(Image.open(path if path.suffix else path.with_suffix(".png")))
            assert png.shape == (12, 16, 4) and png.dtype == np.uint8
            a = png[..., 3] / 255.0
            rgb = srgb_to_linear(png[..., :3] / 255.0) * a[..., None]
            np.testing.assert_allclose(a, imgs[i, ..., 3], atol=0.5 / 255 + 1e-6)
            np.testing.assert_allclose(rgb, imgs[i, ..., :3], atol=0.01)
