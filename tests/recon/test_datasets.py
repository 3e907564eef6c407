"""Multi-view data sets: NeRF / COLMAP loaders, write_nerf, views (cameras: test_camera.py)."""
import json
import math

import numpy as np
import pytest
from PIL import Image

from mi_tetvr.recon import datasets as D
from mi_tetvr.camera import Camera
from mi_tetvr.recon.images import (exif_focal_px, image_size, read_image, upright_copy,
                                   write_image)
from mi_tetvr.color import srgb_to_linear
from tests.helpers import shared_data
from tests.test_camera import (KNOWN_POSE, assert_rays_hit, check_known_pose, gl_look_at,
                                     mitsuba_ray_dirs)


# ---------------------------------------------------------------------------------------------
# helpers (independent pinhole math)
# ---------------------------------------------------------------------------------------------

def write_png(path, arr):
    Image.fromarray(np.asarray(arr, np.uint8)).save(path)


def random_views(rng, n, w=12, h=9):
    views = []
    for i in range(n):
        o = rng.normal(size=3)
        o *= 3.0 / np.linalg.norm(o)
        a = rng.uniform(0, 1, (h, w, 1)).astype(np.float32)
        a[0, 0] = 0.0
        a[0, 1] = 1.0
        rgb = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
        img = np.concatenate([rgb * a, a], axis=2)
        views.append(D.View(f"v{i}", Camera.look_at(o, [0, 0, 0], [0, 0, 1], w, h, fx=10.0 + i,
                                                    cx=w / 2 + 0.7, cy=h / 2 - 0.3), img))
    return views


# ---------------------------------------------------------------------------------------------
# known pose
# ---------------------------------------------------------------------------------------------

def test_known_pose_nerf(tmp_path):
    w, h, fx, cx, cy, origin = (KNOWN_POSE[k] for k in ("w", "h", "fx", "cx", "cy", "origin"))
    c2w = gl_look_at(origin, [0, 0, 0], [0, 0, 1])
    (tmp_path / "train").mkdir()
    write_png(tmp_path / "train" / "r_0.png", np.full((h, w, 4), 200))
    meta = {"camera_angle_x": 2 * math.atan(w / (2 * fx)),      # ignored: fl_x wins
            "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w.tolist(),
                        "fl_x": fx, "fl_y": fx, "cx": cx, "cy": cy}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    ds = D.load_nerf(tmp_path, holdout=None)
    assert len(ds.train) == 1 and not ds.test
    assert ds.train[0].name == "r_0"
    check_known_pose(ds.train[0].camera, c2w, **KNOWN_POSE)


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------

def test_srgb_decode_and_premultiply(tmp_path):
    rgba = np.zeros((2, 3, 4), np.uint8)
    rgba[..., :3] = 188
    rgba[0, :, 3] = 255
    rgba[1, :, 3] = 128
    rgba[1, 2, 3] = 0
    write_png(tmp_path / "a.png", rgba)
    img = read_image(tmp_path / "a.png")
    assert img.shape == (2, 3, 4) and img.dtype == np.float32
    lin = srgb_to_linear(188 / 255)
    assert lin == pytest.approx(0.5, abs=0.005)
    np.testing.assert_allclose(img[0, :, :3], lin, rtol=1e-6)
    np.testing.assert_allclose(img[1, :2, :3], lin * 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(img[1, 2], 0.0)
    np.testing.assert_allclose(img[..., 3], rgba[..., 3] / 255, rtol=1e-6)
    # RGB (no alpha) and grey PNGs: alpha = 1
    write_png(tmp_path / "b.png", rgba[..., :3])
    np.testing.assert_allclose(read_image(tmp_path / "b.png")[..., 3], 1.0)
    Image.fromarray(np.full((2, 3), 188, np.uint8), "L").save(tmp_path / "c.png")
    np.testing.assert_allclose(read_image(tmp_path / "c.png")[..., :3], lin, rtol=1e-6)
    # compositing over white
    v = D.View("a", Camera(3, 2, 3, 3, 1.5, 1, np.eye(4)), img)
    comp = v.composite(1.0)
    np.testing.assert_allclose(comp[1, 2], 1.0)
    np.testing.assert_allclose(comp[1, 0], lin * 128 / 255 + (1 - 128 / 255), rtol=1e-6)
    np.testing.assert_allclose(v.composite([0, 0, 0]), img[..., :3])


#: The pixels a camera stores for an upright picture ``u`` under each EXIF orientation (tag 274:
#: how to turn the stored pixels for display), written with numpy from the EXIF specification.
STORED_FOR_ORIENTATION = {
    1: lambda u: u,
    2: lambda u: u[:, ::-1],                       # shown mirrored left-right
    3: lambda u: u[::-1, ::-1],                    # shown turned 180 degrees
    4: lambda u: u[::-1],                          # shown mirrored top-bottom
    5: lambda u: u.transpose(1, 0, 2),             # shown transposed
    6: lambda u: np.rot90(u, 1),                   # shown turned 90 degrees clockwise
    7: lambda u: u[::-1, ::-1].transpose(1, 0, 2),  # shown transverse
    8: lambda u: np.rot90(u, -1),                  # shown turned 90 degrees counter-clockwise
}


def _exif(orientation, f35=None):
    e = Image.Exif()
    e[0x0112] = orientation
    if f35 is not None:
        e.get_ifd(0x8769)[41989] = f35
    return e


@pytest.mark.parametrize("orientation", range(1, 9))
def test_photos_are_read_upright(tmp_path, orientation):
    """A photo stored turned, with the EXIF orientation that says so, reads as the upright
    picture (pixel for pixel, PNG), sized upright, and its upright copy carries no turn left."""
    upright = np.random.default_rng(orientation).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    stored = np.ascontiguousarray(STORED_FOR_ORIENTATION[orientation](upright))
    Image.fromarray(stored).save(tmp_path / "p.png", exif=_exif(orientation))
    expected = np.take(srgb_to_linear(np.arange(256) / 255.0).astype(np.float32), upright)
    np.testing.assert_array_equal(read_image(tmp_path / "p.png")[..., :3], expected)
    assert image_size(tmp_path / "p.png") == (7, 5)
    assert upright_copy(tmp_path / "p.png", tmp_path / "q.png") == (orientation != 1)
    with Image.open(tmp_path / "q.png") as im:
        assert im.getexif().get(0x0112, 1) == 1
        np.testing.assert_array_equal(np.asarray(im), upright)


def test_focal_length_from_exif(tmp_path):
    """The 35 mm equivalent focal length is defined on the frame's diagonal: for a 3:2 picture
    (the 36 x 24 mm frame's shape) it is ``f35 / 36 mm`` of the width; the focal length in mm
    with the focal plane's resolution gives ``f_mm * pixels per mm``, scaled to a downsized
    file. Kept in an upright copy of a turned JPEG."""
    Image.new("RGB", (60, 40)).save(tmp_path / "a.jpg", exif=_exif(6, f35=28))
    assert exif_focal_px(tmp_path / "a.jpg") == pytest.approx(28 / 36 * 60, rel=1e-12)
    upright_copy(tmp_path / "a.jpg", tmp_path / "b.jpg")
    assert image_size(tmp_path / "b.jpg") == (40, 60)
    assert exif_focal_px(tmp_path / "b.jpg") == pytest.approx(28 / 36 * 60, rel=1e-12)
    e = _exif(1)
    ifd = e.get_ifd(0x8769)
    ifd.update({37386: 4.0, 41486: 500.0, 41488: 4, 40962: 1200})   # 500 px/mm, taken 1200 wide
    Image.new("RGB", (300, 200)).save(tmp_path / "c.jpg", exif=e)
    assert exif_focal_px(tmp_path / "c.jpg") == pytest.approx(4.0 * 500.0 * 300 / 1200)
    Image.new("RGB", (30, 20)).save(tmp_path / "d.jpg")
    assert exif_focal_px(tmp_path / "d.jpg") is None


def test_exr_is_linear_and_premultiplied(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 3, (5, 7, 4)).astype(np.float32)     # HDR values kept
    img[..., 3] = rng.uniform(0, 1, (5, 7))
    write_image(tmp_path / "x.exr", img)
    np.testing.assert_array_equal(read_image(tmp_path / "x.exr"), img)
    write_image(tmp_path / "y.exr", img[..., :3])
    np.testing.assert_array_equal(read_image(tmp_path / "y.exr")[..., 3], 1.0)


# ---------------------------------------------------------------------------------------------
# write_nerf -> load_nerf
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ["png", "exr"])
def test_round_trip(tmp_path, fmt):
    rng = np.random.default_rng(2)
    views = random_views(rng, 5)
    ds = D.Dataset(train=views[:3], test=views[3:], bbox=np.array([[-1, -2, -3], [1, 2, 3.]]))
    D.write_nerf(ds, tmp_path, image_format=fmt)
    meta = json.loads((tmp_path / "transforms_train.json").read_text())
    assert "camera_angle_x" in meta["frames"][0]        # intrinsics differ: per frame
    # OpenGL convention in the file: the camera looks along -z
    c2w = np.array(meta["frames"][0]["transform_matrix"])
    np.testing.assert_allclose(-c2w[:3, 2], views[0].camera.to_world[:3, 2], atol=1e-12)
    back = D.load_nerf(tmp_path)
    assert [v.name for v in back.train] == ["v0", "v1", "v2"]
    assert [v.name for v in back.test] == ["v3", "v4"]
    np.testing.assert_allclose(back.bbox, ds.bbox)
    np.testing.assert_allclose(back.bounds(), ds.bbox)
    for a, b in zip(views, back.views):
        ca, cb = a.camera, b.camera
        np.testing.assert_allclose(cb.to_world, ca.to_world, atol=1e-12)
        assert (cb.fx, cb.fy, cb.cx, cb.cy, cb.width, cb.height) == \
            (ca.fx, ca.fy, ca.cx, ca.cy, ca.width, ca.height)
        if fmt == "exr":
            np.testing.assert_array_equal(b.image, a.image)
        else:   # 8-bit sRGB straight alpha
            np.testing.assert_allclose(b.image, a.image, atol=0.01)
            np.testing.assert_allclose(b.image[..., 3], a.image[..., 3], atol=0.5 / 255 + 1e-6)
            assert np.all(b.image[..., :3] <= b.image[..., 3:] + 1e-6)
    # shared intrinsics go top-level; a single list of views writes one split
    same = [D.View(v.name, Camera(12, 9, 10, 10, 6, 4.5, v.camera.to_world), v.image)
            for v in views]
    D.write_nerf(same, tmp_path / "one")
    meta = json.loads((tmp_path / "one" / "transforms_train.json").read_text())
    assert meta["fl_x"] == 10 and "fl_x" not in meta["frames"][0]
    back = D.load_nerf(tmp_path / "one", holdout=None)
    assert len(back.train) == 5 and back.test == []


def test_holdout_and_instant_ngp_layout(tmp_path):
    n = 10
    (tmp_path / "images").mkdir()
    frames = []
    for i in range(n):
        write_png(tmp_path / "images" / f"f{i:02d}.png", np.full((4, 6, 3), 20 * i))
        c2w = gl_look_at([3, 0, i * 0.1], [0, 0, 0], [0, 0, 1])
        frames.append({"file_path": f"images/f{i:02d}.png", "transform_matrix": c2w.tolist()})
    meta = {"fl_x": 5.0, "fl_y": 5.0, "w": 6, "h": 4, "frames": frames}   # no cx, cy
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    ds = D.load_nerf(tmp_path)                       # default: every 8th view is test
    assert [v.name for v in ds.test] == ["f00", "f08"]
    assert len(ds.train) == 8 and ds.train[0].name == "f01"
    assert (ds.train[0].camera.cx, ds.train[0].camera.cy) == (3.0, 2.0)
    assert [v.name for v in D.load_nerf(tmp_path, holdout=3).test] == ["f00", "f03", "f06", "f09"]
    assert D.load_nerf(tmp_path, holdout=None).test == []
    assert [v.name for v in D.load_nerf(tmp_path, holdout=[1, 2]).test] == ["f01", "f02"]
    cams = D.load_nerf(tmp_path / "transforms.json", load_images=False)
    assert cams.train[0].image is None and cams.train[0].camera.width == 6
    # lens distortion is resampled away (tests/recon/test_undistort.py); a key
    # of another lens model is an error
    meta["k3"] = 0.1
    meta["camera_model"] = "OPENCV_FISHEYE"
    meta["p1"] = 0.01
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"distortion keys \['p1'\] do not belong"):
        D.load_nerf(tmp_path)


def test_downscale_intrinsics(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (7, 11, 4)).astype(np.float32)
    v = D.View("a", Camera.look_at([1, 2, 3], [0, 0, 0], [0, 0, 1], 11, 7, fx=9.0, cx=5.2,
                                   cy=3.9), img)
    s = v.downscaled(2)
    assert s.name == "a" and s.image.shape == (3, 5, 4)
    assert (s.camera.width, s.camera.height) == (5, 3)
    assert (s.camera.fx, s.camera.fy, s.camera.cx, s.camera.cy) == (4.5, 4.5, 2.6, 1.95)
    np.testing.assert_allclose(s.image[1, 2], img[2:4, 4:6].mean((0, 1)), rtol=1e-6)
    # pixel-center convention: new pixel (i, j)'s center is the center of its 2x2 block
    ij = np.array([[0, 0], [4, 2], [2, 1]], float)
    np.testing.assert_allclose(s.camera.rays(ij + 0.5)[1], v.camera.rays(2 * ij + 1.0)[1],
                               atol=1e-12)
    # and the Mitsuba sensors of both agree
    np.testing.assert_allclose(mitsuba_ray_dirs(s.camera, ij + 0.5)[1],
                               mitsuba_ray_dirs(v.camera, 2 * ij + 1.0)[1], atol=2e-6)
    # downscaling while loading == loading then downscaling
    D.write_nerf([v], tmp_path, image_format="exr")
    a = D.load_nerf(tmp_path, downscale=2, holdout=None).train[0]
    b = D.load_nerf(tmp_path, holdout=None).downscaled(2).train[0]
    np.testing.assert_array_equal(a.image, b.image)
    ca, cb = a.camera, b.camera
    assert (ca.fx, ca.cx, ca.cy, ca.width, ca.height) == (cb.fx, cb.cx, cb.cy, cb.width, cb.height)
    with pytest.raises(ValueError):
        v.downscaled(1.5)
    # an image that does not match its camera is refused
    with pytest.raises(ValueError, match="image shape"):
        D.View("b", v.camera, img[:6])


# ---------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------

def _qvec_to_rotmat(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)    # COLMAP normalizes on read
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * x * z + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * x * z - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def test_colmap_maupertuis():
    root = shared_data("colmap-maupertuis")
    import pycolmap
    ds = D.load_colmap(root, downscale=4)
    views = {v.name: v for v in ds.views}
    assert sorted(views) == ["00", "01", "02", "03"]
    assert [v.name for v in ds.test] == ["00"]       # holdout: every 8th, sorted by name
    assert ds.points.shape == (1039, 3) and ds.point_track_lengths.min() >= 2
    v = views["01"]
    assert (v.camera.width, v.camera.height) == (1919 // 4, 1079 // 4)
    assert v.camera.fx == pytest.approx(1847.53 / 4) and v.camera.cx == pytest.approx(959.5 / 4)
    assert v.image.shape == (269, 479, 4) and np.all(v.image[..., 3] == 1)
    # camera centers from the text file, parsed here: C = -R^T t
    lines = [ln for ln in (root / "sparse" / "images.txt").read_text().splitlines()
             if ln and not ln.startswith("#")]
    for ln in lines[0::2]:
        f = ln.split()
        r = _qvec_to_rotmat([float(x) for x in f[1:5]])
        t = np.array([float(x) for x in f[5:8]])
        np.testing.assert_allclose(views[f[9].split(".")[0]].camera.center, -r.T @ t,
                                   atol=1e-6)
    # reprojection of the sparse points onto their observations (full-resolution pixels)
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    errs = []
    for im in rec.images.values():
        view = views[im.name.split(".")[0]].camera
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        xy = np.array([o[0] for o in obs])
        xyz = np.array([o[1] for o in obs])
        uv, depth = view.project(xyz)
        uv *= 4.0                                    # back to full resolution (exact)
        assert np.all(depth > 0)
        assert np.all((uv > 0) & (uv < [1919, 1079]))
        errs.append(np.linalg.norm(uv - xy, axis=1))
        # the Mitsuba sensor's rays through the observed positions pass through the points
        assert_rays_hit(view, uv[:20] / 4.0, xyz[:20], tol=1e-4)
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.5 and errs.max() < 4.0
    # bounds from the points contain most of them
    lo, hi = ds.bounds()
    assert np.mean(np.all((ds.points >= lo) & (ds.points <= hi), axis=1)) > 0.98


def _write_colmap_text(d, model_line):
    d.mkdir(parents=True)
    (d / "cameras.txt").write_text(f"# cam\n{model_line}\n")
    (d / "images.txt").write_text("# im\n1 1 0 0 0 0.1 0.2 3.0 1 a.png\n\n")
    (d / "points3D.txt").write_text("# pts\n")


def test_colmap_pinhole_synthetic(tmp_path):
    _write_colmap_text(tmp_path / "sparse" / "0", "1 PINHOLE 40 30 35.0 35.0 21.0 14.0")
    ds = D.load_colmap(tmp_path, load_images=False, holdout=None)
    v = ds.train[0].camera
    assert (v.fx, v.fy, v.cx, v.cy, v.width, v.height) == (35, 35, 21, 14, 40, 30)
    # identity rotation: OpenCV camera looks along +z with y down, x right
    np.testing.assert_allclose(v.center, [-0.1, -0.2, -3.0], atol=1e-12)
    np.testing.assert_allclose(v.to_world[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    uv, _ = v.project([[1.0, 0.5, 2.0]])             # OpenCV: u = fx x_c / z_c + cx
    xc = np.array([1.0, 0.5, 2.0]) + [0.1, 0.2, 3.0]
    np.testing.assert_allclose(uv[0], [35 * xc[0] / xc[2] + 21, 35 * xc[1] / xc[2] + 14])
    assert_rays_hit(v, uv, [[1.0, 0.5, 2.0]])
    assert ds.points is None


# ---------------------------------------------------------------------------------------------
# NeRF synthetic Lego
# ---------------------------------------------------------------------------------------------

def test_nerf_lego():
    root = shared_data("nerf-lego")
    ds = D.load_nerf(root, downscale=8)
    assert len(ds.train) + len(ds.test) == 80
    assert len(ds.test) == 10 and ds.test[1].name == "r_8"
    v = ds.train[0]
    assert v.image.shape == (100, 100, 4) and v.image.dtype == np.float32
    assert v.camera.fx == pytest.approx(400 / math.tan(0.6911112070083618 / 2) / 8)
    assert (v.camera.cx, v.camera.cy) == (50.0, 50.0)
    a = v.image[..., 3]
    assert a.min() == 0.0 and a.max() == pytest.approx(1.0)
    assert np.all(a[:3, :3] == 0)                    # transparent corners
    assert np.all(v.image[..., :3] <= a[..., None] + 1e-6)   # premultiplied
    np.testing.assert_allclose(v.composite(1.0)[:3, :3], 1.0)  # white background
    # the frusta bound the object around the origin, cameras stay outside
    lo, hi = ds.bounds()
    assert np.all(lo < -0.5) and np.all(hi > 0.5) and np.all(hi - lo < 4)
    for c in (w.camera.center for w in ds.views):
        assert not np.all((c >= lo) & (c <= hi))
