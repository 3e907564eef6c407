"""Multi-view data sets: NeRF / COLMAP loaders, write_nerf, and the exact Mitsuba sensors."""
import json
import math

import numpy as np
import pytest
from PIL import Image

import mitsuba as mi

from mi_tetvr.recon import datasets as D
from mi_tetvr.color import srgb_to_linear


# ---------------------------------------------------------------------------------------------
# helpers (independent pinhole math)
# ---------------------------------------------------------------------------------------------

def gl_look_at(origin, target, up):
    """OpenGL/NeRF camera-to-world: the camera looks along -z, y up, x right."""
    o, t, u = (np.asarray(v, float) for v in (origin, target, up))
    z = o - t
    z /= np.linalg.norm(z)
    x = np.cross(u, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, o
    return m


def gl_project(c2w, fx, fy, cx, cy, p):
    """Pinhole projection for an OpenGL camera; pixel centres at +0.5, v down."""
    q = (np.asarray(p, float) - c2w[:3, 3]) @ c2w[:3, :3]
    depth = -q[:, 2]
    return np.stack([cx + fx * q[:, 0] / depth, cy - fy * q[:, 1] / depth], 1), depth


def mitsuba_ray_dirs(view, uv):
    """World directions of the Mitsuba sensor's rays through continuous pixel positions."""
    sensor = mi.load_dict(view.sensor_dict())
    uv = np.asarray(uv, np.float64)
    pos = mi.Point2f((uv[:, 0] / view.width).astype(np.float32),
                     (uv[:, 1] / view.height).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    return o, d


def assert_rays_hit(view, uv, points, tol=2e-5):
    o, d = mitsuba_ray_dirs(view, uv)
    to_p = np.asarray(points, float) - o
    to_p /= np.linalg.norm(to_p, axis=1, keepdims=True)
    # angle between the ray and the direction to the point
    err = np.linalg.norm(np.cross(d, to_p), axis=1)
    assert np.all((d * to_p).sum(1) > 0)
    assert err.max() < tol, err.max()


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
        views.append(D.View.look_at(f"v{i}", o, [0, 0, 0], [0, 0, 1], w, h, fx=10.0 + i,
                                    cx=w / 2 + 0.7, cy=h / 2 - 0.3, image=img))
    return views


# ---------------------------------------------------------------------------------------------
# known pose
# ---------------------------------------------------------------------------------------------

def test_known_pose_nerf(tmp_path):
    w, h, fx, cx, cy = 32, 24, 30.0, 13.3, 14.1       # off-centre principal point
    origin = np.array([0.5, -4.0, 1.0])
    c2w = gl_look_at(origin, [0, 0, 0], [0, 0, 1])
    (tmp_path / "train").mkdir()
    write_png(tmp_path / "train" / "r_0.png", np.full((h, w, 4), 200))
    meta = {"camera_angle_x": 2 * math.atan(w / (2 * fx)),      # ignored: fl_x wins
            "frames": [{"file_path": "./train/r_0", "transform_matrix": c2w.tolist(),
                        "fl_x": fx, "fl_y": fx, "cx": cx, "cy": cy}]}
    (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
    ds = D.load_nerf(tmp_path, holdout=None)
    assert len(ds.train) == 1 and not ds.test
    v = ds.train[0]
    assert (v.width, v.height, v.fx, v.fy, v.cx, v.cy) == (w, h, fx, fx, cx, cy)
    assert v.name == "r_0"
    np.testing.assert_allclose(v.center, origin, atol=1e-12)
    # the look-at target lands on the principal point; Mitsuba's camera looks along +z
    uv, depth = v.project([[0, 0, 0]])
    np.testing.assert_allclose(uv[0], [cx, cy], atol=1e-9)
    np.testing.assert_allclose(v.to_world[:3, 2], -origin / np.linalg.norm(origin), atol=1e-12)
    # world up (+z) is image up: a point above the target projects above it (smaller v)
    assert v.project([[0, 0, 0.5]])[0][0, 1] < cy
    # independent pinhole projection of random points agrees with View.project
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.8, 0.8, (50, 3))
    uv_ref, d_ref = gl_project(c2w, fx, fx, cx, cy, pts)
    uv, d = v.project(pts)
    np.testing.assert_allclose(uv, uv_ref, atol=1e-9)
    np.testing.assert_allclose(d, d_ref, atol=1e-12)
    # and the Mitsuba sensor's ray through each expected position passes through the point
    inside = (uv_ref[:, 0] > 0) & (uv_ref[:, 0] < w) & (uv_ref[:, 1] > 0) & (uv_ref[:, 1] < h)
    assert inside.sum() > 20
    assert_rays_hit(v, uv_ref[inside], pts[inside])
    # pixel centre convention: the ray through pixel (0, 0)'s centre (0.5, 0.5)
    o, dirs = mitsuba_ray_dirs(v, [[0.5, 0.5], [w - 0.5, h - 0.5]])
    np.testing.assert_allclose(dirs, v.ray_directions([[0.5, 0.5], [w - 0.5, h - 0.5]]),
                               atol=2e-6)


def test_sensor_dict_fields():
    v = D.View.look_at("a", [0, 0, -3], [0, 0, 0], [0, 1, 0], 40, 20, fx=25.0, cx=22.0, cy=9.0)
    d = v.sensor_dict(spp=4)
    assert d["type"] == "perspective" and d["fov_axis"] == "x"
    assert d["fov"] == pytest.approx(math.degrees(2 * math.atan(20 / 25.0)))
    assert d["principal_point_offset_x"] == pytest.approx(0.5 - 22.0 / 40)
    assert d["principal_point_offset_y"] == pytest.approx(0.5 - 9.0 / 20)
    assert d["film"]["width"] == 40 and d["film"]["height"] == 20
    assert d["film"]["rfilter"]["type"] == "box" and d["film"]["pixel_format"] == "rgb"
    assert d["sampler"] == {"type": "independent", "sample_count": 4}
    sensor = mi.load_dict(d)
    assert tuple(sensor.film().size()) == (40, 20)
    # Mitsuba's look_at and View.look_at build the same frame
    ref = mi.ScalarTransform4f().look_at(origin=[0, 0, -3], target=[0, 0, 0], up=[0, 1, 0])
    np.testing.assert_allclose(np.array(ref.matrix), v.to_world, atol=1e-6)
    # non-square pixels are refused
    v.fy = 26.0
    with pytest.raises(ValueError, match="non-square"):
        v.sensor_dict()


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
    img = D.read_image(tmp_path / "a.png")
    assert img.shape == (2, 3, 4) and img.dtype == np.float32
    lin = srgb_to_linear(188 / 255)
    assert lin == pytest.approx(0.5, abs=0.005)
    np.testing.assert_allclose(img[0, :, :3], lin, rtol=1e-6)
    np.testing.assert_allclose(img[1, :2, :3], lin * 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(img[1, 2], 0.0)
    np.testing.assert_allclose(img[..., 3], rgba[..., 3] / 255, rtol=1e-6)
    # RGB (no alpha) and grey PNGs: alpha = 1
    write_png(tmp_path / "b.png", rgba[..., :3])
    np.testing.assert_allclose(D.read_image(tmp_path / "b.png")[..., 3], 1.0)
    Image.fromarray(np.full((2, 3), 188, np.uint8), "L").save(tmp_path / "c.png")
    np.testing.assert_allclose(D.read_image(tmp_path / "c.png")[..., :3], lin, rtol=1e-6)
    # compositing over white
    v = D.View("a", img, np.eye(4), 3, 3, 1.5, 1, 3, 2)
    comp = v.composite(1.0)
    np.testing.assert_allclose(comp[1, 2], 1.0)
    np.testing.assert_allclose(comp[1, 0], lin * 128 / 255 + (1 - 128 / 255), rtol=1e-6)
    np.testing.assert_allclose(v.composite([0, 0, 0]), img[..., :3])


def test_exr_is_linear_and_premultiplied(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 3, (5, 7, 4)).astype(np.float32)     # HDR values kept
    img[..., 3] = rng.uniform(0, 1, (5, 7))
    D.write_image(tmp_path / "x.exr", img)
    np.testing.assert_array_equal(D.read_image(tmp_path / "x.exr"), img)
    D.write_image(tmp_path / "y.exr", img[..., :3])
    np.testing.assert_array_equal(D.read_image(tmp_path / "y.exr")[..., 3], 1.0)


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
    np.testing.assert_allclose(-c2w[:3, 2], views[0].to_world[:3, 2], atol=1e-12)
    back = D.load_nerf(tmp_path)
    assert [v.name for v in back.train] == ["v0", "v1", "v2"]
    assert [v.name for v in back.test] == ["v3", "v4"]
    np.testing.assert_allclose(back.bbox, ds.bbox)
    np.testing.assert_allclose(back.bounds(), ds.bbox)
    for a, b in zip(views, back.views):
        np.testing.assert_allclose(b.to_world, a.to_world, atol=1e-12)
        assert (b.fx, b.fy, b.cx, b.cy, b.width, b.height) == \
            (a.fx, a.fy, a.cx, a.cy, a.width, a.height)
        if fmt == "exr":
            np.testing.assert_array_equal(b.image, a.image)
        else:   # 8-bit sRGB straight alpha
            np.testing.assert_allclose(b.image, a.image, atol=0.01)
            np.testing.assert_allclose(b.image[..., 3], a.image[..., 3], atol=0.5 / 255 + 1e-6)
            assert np.all(b.image[..., :3] <= b.image[..., 3:] + 1e-6)
    # shared intrinsics go top-level; a single list of views writes one split
    same = [D.View(v.name, v.image, v.to_world, 10, 10, 6, 4.5, 12, 9) for v in views]
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
    assert (ds.train[0].cx, ds.train[0].cy) == (3.0, 2.0)
    assert [v.name for v in D.load_nerf(tmp_path, holdout=3).test] == ["f00", "f03", "f06", "f09"]
    assert D.load_nerf(tmp_path, holdout=None).test == []
    assert [v.name for v in D.load_nerf(tmp_path, holdout=[1, 2]).test] == ["f01", "f02"]
    cams = D.load_nerf(tmp_path / "transforms.json", load_images=False)
    assert cams.train[0].image is None and cams.train[0].width == 6
    # lens distortion is refused
    meta["k1"] = 0.1
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="distortion"):
        D.load_nerf(tmp_path)


def test_downscale_intrinsics(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (7, 11, 4)).astype(np.float32)
    v = D.View.look_at("a", [1, 2, 3], [0, 0, 0], [0, 0, 1], 11, 7, fx=9.0, cx=5.2, cy=3.9,
                       image=img)
    s = v.downscaled(2)
    assert (s.width, s.height) == (5, 3)
    assert (s.fx, s.fy, s.cx, s.cy) == (4.5, 4.5, 2.6, 1.95)
    np.testing.assert_allclose(s.image[1, 2], img[2:4, 4:6].mean((0, 1)), rtol=1e-6)
    # pixel-centre convention: new pixel (i, j)'s centre is the centre of its 2x2 block
    ij = np.array([[0, 0], [4, 2], [2, 1]], float)
    np.testing.assert_allclose(s.ray_directions(ij + 0.5), v.ray_directions(2 * ij + 1.0),
                               atol=1e-12)
    # and the Mitsuba sensors of both agree
    np.testing.assert_allclose(mitsuba_ray_dirs(s, ij + 0.5)[1],
                               mitsuba_ray_dirs(v, 2 * ij + 1.0)[1], atol=2e-6)
    # downscaling while loading == loading then downscaling
    D.write_nerf([v], tmp_path, image_format="exr")
    a = D.load_nerf(tmp_path, downscale=2, holdout=None).train[0]
    b = D.load_nerf(tmp_path, holdout=None).downscaled(2).train[0]
    np.testing.assert_array_equal(a.image, b.image)
    assert (a.fx, a.cx, a.cy, a.width, a.height) == (b.fx, b.cx, b.cy, b.width, b.height)
    with pytest.raises(ValueError):
        v.downscaled(1.5)


def test_bounds_from_frusta():
    views = [D.View.look_at(f"v{i}", 4 * np.array([math.cos(t), math.sin(t), 0.3]),
                            [0, 0, 0], [0, 0, 1], 20, 20, fov_x=40.0)
             for i, t in enumerate(np.linspace(0, 2 * np.pi, 12, endpoint=False))]
    lo, hi = D.Dataset(train=views).bounds()
    assert np.all(lo < 0) and np.all(hi > 0)
    assert np.all(hi - lo < 4)
    for v in views:                                  # every camera sees the whole box
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        uv, depth = v.project(corners)
        assert np.all(depth > 0)
    # forward-facing cameras: unbounded intersection, capped at `far`
    fwd = [D.View.look_at(f"f{i}", [0.1 * i, 0, 0], [0.1 * i, 0, 1], [0, 1, 0], 20, 20,
                          fov_x=40.0) for i in range(3)]
    lo, hi = D.Dataset(train=fwd).bounds(far=5.0)
    assert hi[2] == pytest.approx(5.0, rel=1e-6) and lo[2] > 0


# ---------------------------------------------------------------------------------------------
# COLMAP
# ---------------------------------------------------------------------------------------------

def _qvec_to_rotmat(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)    # COLMAP normalizes on read
    return np.array([
        [1 - 2 * y * y - 2 * z * z, 2 * x * y - 2 * w * z, 2 * x * z + 2 * w * y],
        [2 * x * y + 2 * w * z, 1 - 2 * x * x - 2 * z * z, 2 * y * z - 2 * w * x],
        [2 * x * z - 2 * w * y, 2 * y * z + 2 * w * x, 1 - 2 * x * x - 2 * y * y]])


def test_colmap_maupertuis(data_dir):
    root = data_dir / "colmap-maupertuis"
    if not root.is_dir():
        pytest.skip("colmap-maupertuis is absent")
    import pycolmap
    ds = D.load_colmap(root, downscale=4)
    views = {v.name: v for v in ds.views}
    assert sorted(views) == ["00", "01", "02", "03"]
    assert [v.name for v in ds.test] == ["00"]       # holdout: every 8th, sorted by name
    assert ds.points.shape == (1039, 3) and ds.point_track_lengths.min() >= 2
    v = views["01"]
    assert (v.width, v.height) == (1919 // 4, 1079 // 4)
    assert v.fx == pytest.approx(1847.53 / 4) and v.cx == pytest.approx(959.5 / 4)
    assert v.image.shape == (269, 479, 4) and np.all(v.image[..., 3] == 1)
    # camera centres from the text file, parsed here: C = -R^T t
    lines = [ln for ln in (root / "sparse" / "images.txt").read_text().splitlines()
             if ln and not ln.startswith("#")]
    for ln in lines[0::2]:
        f = ln.split()
        r = _qvec_to_rotmat([float(x) for x in f[1:5]])
        t = np.array([float(x) for x in f[5:8]])
        np.testing.assert_allclose(views[f[9].split(".")[0]].center, -r.T @ t, atol=1e-6)
    # reprojection of the sparse points onto their observations (full-resolution pixels)
    rec = pycolmap.Reconstruction(str(root / "sparse"))
    errs = []
    for im in rec.images.values():
        view = views[im.name.split(".")[0]]
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


def test_colmap_radial_refused(tmp_path):
    _write_colmap_text(tmp_path / "sparse", "1 SIMPLE_RADIAL 40 30 35.0 20.0 15.0 0.05")
    with pytest.raises(ValueError, match="SIMPLE_RADIAL.*image_undistorter"):
        D.load_colmap(tmp_path, load_images=False)


def test_colmap_pinhole_synthetic(tmp_path):
    _write_colmap_text(tmp_path / "sparse" / "0", "1 PINHOLE 40 30 35.0 35.0 21.0 14.0")
    ds = D.load_colmap(tmp_path, load_images=False, holdout=None)
    v = ds.train[0]
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

def test_nerf_lego(data_dir):
    root = data_dir / "nerf-lego"
    if not root.is_dir():
        pytest.skip("nerf-lego is absent")
    ds = D.load_nerf(root, downscale=8)
    assert len(ds.train) + len(ds.test) == 80
    assert len(ds.test) == 10 and ds.test[1].name == "r_8"
    v = ds.train[0]
    assert v.image.shape == (100, 100, 4) and v.image.dtype == np.float32
    assert v.fx == pytest.approx(400 / math.tan(0.6911112070083618 / 2) / 8)
    assert (v.cx, v.cy) == (50.0, 50.0)
    a = v.image[..., 3]
    assert a.min() == 0.0 and a.max() == pytest.approx(1.0)
    assert np.all(a[:3, :3] == 0)                    # transparent corners
    assert np.all(v.image[..., :3] <= a[..., None] + 1e-6)   # premultiplied
    np.testing.assert_allclose(v.composite(1.0)[:3, :3], 1.0)  # white background
    # the frusta bound the object around the origin, cameras stay outside
    lo, hi = ds.bounds()
    assert np.all(lo < -0.5) and np.all(hi > 0.5) and np.all(hi - lo < 4)
    for c in (w.center for w in ds.views):
        assert not np.all((c >= lo) & (c <= hi))
