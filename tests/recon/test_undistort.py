"""Real lenses: distorted and non-square-pixel images resampled at load into
the square-pixel pinhole images Mitsuba renders, checked against an
independent numpy model of OpenCV's distortion."""
import json
import warnings

import numpy as np
import pytest

from mi_tetvr.recon import datasets as D
from mi_tetvr.recon.images import read_image, write_image
from mi_tetvr.recon.undistort import SQUARE_RTOL, Lens

W, H = 96, 72
FX, FY, CX, CY = 80.0, 80.0, 47.3, 36.6
DIST = dict(k1=0.15, k2=0.04, p1=0.002, p2=-0.003)      # pincushion


def distort(x, y, k1, k2, p1, p2):
    """OpenCV's radial-tangential model on normalized coordinates."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def undistort_points(xd, yd, coeffs, iterations=50):
    """Inverse of :func:`distort` by fixed-point iteration (the reference)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        dx, dy = distort(x, y, **coeffs)
        x, y = x + (xd - dx), y + (yd - dy)
    return x, y


def scene(x, y):
    """A smooth picture as a function of the normalized image-plane position
    (what an ideal pinhole sees), premultiplied RGBA."""
    r = 0.5 + 0.5 * np.sin(5 * x) * np.cos(4 * y)
    g = 0.5 + 0.5 * np.cos(3 * x + 2 * y)
    b = np.clip(0.8 - x * x - y * y, 0, 1)
    return np.stack([r, g, b, np.ones_like(r)], -1).astype(np.float32)


def distorted_photo(fx=FX, fy=FY, coeffs=DIST):
    """What a camera with this lens records of :func:`scene`."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    x, y = undistort_points((u - CX) / fx, (v - CY) / fy, coeffs)
    return scene(x, y)


def pinhole_photo(f, cx=CX, cy=CY):
    v, u = np.mgrid[0:H, 0:W] + 0.5
    return scene((u - cx) / f, (v - cy) / f)


def test_opencv_lens_undistorts_to_the_pinhole_picture():
    lens = Lens.from_params("OPENCV", W, H, [FX, FY, CX, CY, *DIST.values()])
    assert lens.resample
    f, f2, cx, cy = lens.pinhole()
    assert f == f2 and (cx, cy) == (CX, CY)
    assert f > FX                                       # zoomed in: no blank border
    out = lens.undistort(distorted_photo())
    np.testing.assert_allclose(out, pinhole_photo(f), atol=0.01)
    # every border pixel of the pinhole sees a pixel of the photo, and it is
    # the smallest such zoom: 1 % less and a corner falls outside
    v, u = np.array([0.0, 0, H, H]), np.array([0.0, W, 0, W])
    for scale, inside in ((1.0, True), (0.99, False)):
        xd, yd = distort((u - CX) / (f * scale), (v - CY) / (f * scale), **DIST)
        ud, vd = xd * FX + CX, yd * FY + CY
        ok = (ud >= -1e-6) & (ud <= W + 1e-6) & (vd >= -1e-6) & (vd <= H + 1e-6)
        assert ok.all() == inside


def test_barrel_distortion_widens_the_view():
    coeffs = dict(k1=-0.15, k2=0.0, p1=0.0, p2=0.0)
    lens = Lens.from_params("OPENCV", W, H, [FX, FY, CX, CY, *coeffs.values()])
    f = lens.pinhole()[0]
    assert f < FX
    np.testing.assert_allclose(lens.undistort(distorted_photo(coeffs=coeffs)), pinhole_photo(f),
                               atol=0.01)


def test_non_square_pixels_are_resampled_or_averaged():
    coeffs = dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    lens = Lens.from_params("PINHOLE", W, H, [80.0, 82.0, CX, CY])     # 2.5 % apart
    assert lens.resample and lens.pinhole()[0] == pytest.approx(82.0)       # fy: no blanks
    out = lens.undistort(distorted_photo(80.0, 82.0, coeffs))
    np.testing.assert_allclose(out, pinhole_photo(lens.pinhole()[0]), atol=0.01)
    close = Lens.from_params("PINHOLE", W, H, [80.0, 80.0 * (1 + 0.75e-3), CX, CY])
    assert not close.resample and 0.75e-3 < SQUARE_RTOL
    assert close.pinhole()[0] == pytest.approx(80.0 * np.sqrt(1 + 0.75e-3))


def write_capture(root, frames, **meta):
    root.mkdir(parents=True, exist_ok=True)
    for fr in frames:
        if fr.pop("_image", True):
            write_image(root / f"{fr['file_path']}.png", distorted_photo())
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": frames}))


def pose(i):
    m = np.eye(4)
    m[:3, 3] = [0.1 * i, 0.0, 3.0]
    return m.tolist()


def test_instant_ngp_capture_with_distortion_and_missing_frames(tmp_path):
    root = tmp_path / "fox"
    frames = [{"file_path": f"images/{i:04d}", "transform_matrix": pose(i)} for i in range(4)]
    frames[2]["_image"] = False                          # listed, not on disk
    (root / "images").mkdir(parents=True)
    write_capture(root, frames, fl_x=FX, fl_y=FY, cx=CX, cy=CY,
                  w=W, h=H, aabb_scale=4, **DIST)
    with pytest.warns(UserWarning, match="1 of 4 frames have no image.*images/0002"):
        ds = D.load_nerf(root, holdout=None)
    assert [v.name for v in ds.train] == ["0000", "0001", "0003"]
    cam = ds.train[0].camera
    assert cam.fx == cam.fy > FX and (cam.cx, cam.cy) == (CX, CY)
    np.testing.assert_allclose(ds.train[0].image, pinhole_photo(cam.fx), atol=0.01)
    # the cameras only: the same pinhole without reading pixels
    with pytest.warns(UserWarning, match="no image"):
        cameras = D.load_nerf(root, holdout=None, load_images=False)
    assert cameras.train[0].camera.fx == cam.fx


def test_any_json_file_and_near_square_focal_lengths(tmp_path):
    root = tmp_path / "cap"
    frames = [{"file_path": f"images/{i}", "transform_matrix": pose(i)} for i in range(2)]
    (root / "images").mkdir(parents=True)
    coeffs = dict(k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    write_capture(root, frames, fl_x=FX, fl_y=FX * 1.00075, cx=CX, cy=CY, w=W, h=H, **coeffs)
    other = root / "transforms_subset.json"
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:1]
    other.write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = D.load_dataset(other, holdout=None)
    assert len(ds.train) == 1                            # the named file, not transforms.json
    cam = ds.train[0].camera
    assert cam.fx == cam.fy == pytest.approx(FX * np.sqrt(1.00075))
    assert cam.sensor_dict()["type"] == "perspective"     # square pixels for Mitsuba


def test_unknown_camera_model_is_named(tmp_path):
    root = tmp_path / "cap"
    (root / "images").mkdir(parents=True)
    write_capture(root, [{"file_path": "images/0", "transform_matrix": pose(0)}], fl_x=FX,
                  w=W, h=H, camera_model="EQUIRECTANGULAR")
    with pytest.raises(ValueError, match="camera_model 'EQUIRECTANGULAR' is not supported"):
        D.load_nerf(root)


def test_colmap_radial_camera_is_undistorted(tmp_path):
    from tests.recon.test_datasets import _write_colmap_text
    _write_colmap_text(tmp_path / "sparse", f"1 SIMPLE_RADIAL {W} {H} {FX} {CX} {CY} 0.1")
    (tmp_path / "images").mkdir()
    coeffs = dict(k1=0.1, k2=0.0, p1=0.0, p2=0.0)
    write_image(tmp_path / "images" / "a.png", distorted_photo(coeffs=coeffs))
    ds = D.load_colmap(tmp_path, holdout=None)
    cam = ds.train[0].camera
    assert cam.fx == cam.fy > FX
    np.testing.assert_allclose(ds.train[0].image, pinhole_photo(cam.fx), atol=0.01)


def test_distorted_capture_reconstructs_like_the_pinhole_one(tmp_path):
    """A data set rendered through pinholes, then distorted with known OpenCV
    coefficients and written as a capture with those coefficients: after
    undistortion at load, the fit scores on its held-out views as the fit of
    the pinhole data set does."""
    from scipy.ndimage import map_coordinates

    from mi_tetvr.grid import make_volume
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.mesh.scenes import default_volume
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.pipeline import run
    from mi_tetvr.transfer import read_transfer_function
    from tests.helpers import ROOT
    tf = read_transfer_function(ROOT / "scenes" / "tf_default.json")
    pin = tmp_path / "pinhole"
    make_dataset(make_volume(default_volume(16)), tf, views=8, res=32, out_dir=pin,
                 test_views=2, fov=30, progress=False)
    coeffs = dict(k1=0.12, k2=0.0, p1=0.001, p2=-0.001)
    out = tmp_path / "distorted"
    for split in ("train", "test"):
        meta = json.loads((pin / f"transforms_{split}.json").read_text())
        w = h = 32
        f = 0.5 * w / np.tan(0.5 * meta["camera_angle_x"])
        for fr in meta["frames"]:
            path = pin / fr["file_path"]
            src = read_image(path)
            v, u = np.mgrid[0:h, 0:w] + 0.5
            x, y = undistort_points((u - w / 2) / f, (v - h / 2) / f, coeffs)
            rows, cols = y * f + h / 2 - 0.5, x * f + w / 2 - 0.5
            img = np.stack([map_coordinates(src[..., c], [rows, cols], order=1, mode="nearest")
                            for c in range(4)], -1)
            (out / path.relative_to(pin)).parent.mkdir(parents=True, exist_ok=True)
            write_image(out / path.relative_to(pin), img)
        meta.update(fl_x=f, fl_y=f, cx=w / 2, cy=h / 2, w=w, h=h, **coeffs)
        (out / f"transforms_{split}.json").write_text(json.dumps(meta))
    cfg = FitConfig(grid_resolution=6, iterations=60, lr_color=0.05, lr_opacity=0.2, n_sub=2,
                    jitter=False)
    scores = {}
    for name in ("pinhole", "distorted"):
        ds = D.load_nerf(tmp_path / name)
        scores[name] = run(ds, tmp_path / f"{name}_fit", cfg, progress=False,
                           log=lambda *a: None)["mean"]["psnr"]
    assert D.load_nerf(out).train[0].camera.fx > f
    assert abs(scores["distorted"] - scores["pinhole"]) < 1.5, scores
