"""The grid ray marcher: closed forms, convergence, trilinear lookup, transfer functions and
cameras against Mitsuba sensors."""
import mitsuba as mi
import numpy as np
import pytest
from scipy.integrate import quad

from mi_tetvr.grid import marcher as M
from mi_tetvr.grid import volume as V
from mi_tetvr.camera import fibonacci_cameras
from mi_tetvr.transfer import TransferFunction
from tests.grid.test_volume import scipy_trilinear_case


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
    C, a = M.render_rays(vol, const_tf(c, 1.0), o, d, opacity_scale=sigma, step=0.37,
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
    # ray along +x through the box center line: s in [0, 2], t = s / 2
    sigma = lambda s: k * s / 2  # noqa: E731
    tau = lambda s: k * s * s / 4  # noqa: E731
    ref = [quad(lambda s: sigma(s) * col(s) * np.exp(-tau(s)), 0, 2, epsabs=1e-13)[0]
           for col in (lambda s: s / 2, lambda s: 0.3, lambda s: 1.0)]
    alpha_ref = 1 - np.exp(-tau(2.0))
    errs = []
    for step in (2.0, 1.0, 0.5):
        C, a = M.render_rays(vol, tf, [[-3, 0, 0]], [[1, 0, 0]], step=step,
                             min_transmittance=0.0)
        C = np.array(C, np.float64).ravel()
        # midpoint rule: transmittance exact for linear extinction
        assert float(np.array(a)[0]) == pytest.approx(alpha_ref, abs=2e-6)
        errs.append(np.abs(C - ref).max())
    assert errs[-1] < 2e-3
    for e0, e1 in zip(errs, errs[1:]):
        assert 3.0 < e0 / e1 < 5.0, errs                # second order


def test_trilinear_matches_scipy():
    vol, p, ref = scipy_trilinear_case()
    field = M.GridField(vol)
    got = np.array(field.eval(mi.Point3f(*p.astype(np.float32).T)), np.float64)
    np.testing.assert_allclose(got, ref, atol=2e-6)


def test_tf_eval_matches_numpy():
    tf = TransferFunction([0, 0.3, 0.3, 0.8, 1], [[0, 0, 0], [1, .5, 0], [0, 1, 1], [.2, .2, .2],
                                                 [1, 1, 1]],
                          [0, 0.5, 0.5, 1.0], [0.0, 1.0, 3.0, 0.5])
    t = np.concatenate([np.linspace(-0.2, 1.2, 57) + 0.0037, [0.3, 0.5, 0.8]])
    vr = (2.0, 6.0)
    s = vr[0] + t * (vr[1] - vr[0])
    c, sig = M.TFEval(tf, value_range=vr, opacity_scale=2.5)(mi.Float(s.astype(np.float32)))
    c_ref, s_ref = tf(t)
    np.testing.assert_allclose(np.array(c, np.float64).reshape(3, -1).T, c_ref, atol=2e-6)
    np.testing.assert_allclose(np.array(sig, np.float64), 2.5 * s_ref, atol=1e-5)


# ---------------------------------------------------------------------------- cameras
def test_sensor_matches_camera():
    rng = np.random.default_rng(4)
    vol = V.make_volume(rng.uniform(size=(6, 6, 6)))
    tf = TransferFunction([0, 1], [[1, 0, 0], [0, 0, 1]], [0, 1], [0.5, 3.0])
    cam = fibonacci_cameras(3, radius=3.5, res=(16, 12))[1]
    a = M.render_volume(vol, tf, cam)
    b = M.render_volume(vol, tf, mi.load_dict(cam.sensor_dict()))
    assert a.shape == (12, 16, 4) and a[..., 3].max() > 0.3
    np.testing.assert_allclose(a, b, atol=1e-4)
