"""Pinhole cameras: projection, rays (numpy and Dr.Jit), axis conversions, the exact Mitsuba
sensor, downscaling and generated cameras, each against independent pinhole math or Mitsuba."""
import dataclasses
import math

import numpy as np
import pytest

import mitsuba as mi

from mi_tetvr import camera as C
from mi_tetvr.camera import Camera, camera_path


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
    """Pinhole projection for an OpenGL camera; pixel centers at +0.5, v down."""
    q = (np.asarray(p, float) - c2w[:3, 3]) @ c2w[:3, :3]
    depth = -q[:, 2]
    return np.stack([cx + fx * q[:, 0] / depth, cy - fy * q[:, 1] / depth], 1), depth


def mitsuba_ray_dirs(camera, uv):
    """World directions of the Mitsuba sensor's rays through continuous pixel positions."""
    sensor = mi.load_dict(camera.sensor_dict())
    uv = np.asarray(uv, np.float64)
    pos = mi.Point2f((uv[:, 0] / camera.width).astype(np.float32),
                     (uv[:, 1] / camera.height).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.0, pos, mi.Point2f(0.5, 0.5))
    o = np.array(ray.o, np.float64).reshape(3, -1).T
    d = np.array(ray.d, np.float64).reshape(3, -1).T
    return o, d


def assert_rays_hit(camera, uv, points, tol=2e-5):
    """The Mitsuba sensor's rays through ``uv`` pass through ``points``."""
    o, d = mitsuba_ray_dirs(camera, uv)
    to_p = np.asarray(points, float) - o
    to_p /= np.linalg.norm(to_p, axis=1, keepdims=True)
    # angle between the ray and the direction to the point
    err = np.linalg.norm(np.cross(d, to_p), axis=1)
    assert np.all((d * to_p).sum(1) > 0)
    assert err.max() < tol, err.max()


def mi_look_at(origin, target, up):
    return np.array(mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up).matrix,
                    dtype=np.float64)


def pixel_rays(camera, W, H):
    """Pixel-center rays from the Mitsuba camera frame (+x left, +y up, +z forward)."""
    j, i = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(camera.cx - j) / camera.fx, (camera.cy - i) / camera.fy,
                      np.ones_like(j)], -1)
    m = np.asarray(camera.to_world)
    d = d_cam @ m[:3, :3].T
    return m[:3, 3], d / np.linalg.norm(d, axis=-1, keepdims=True)


def sphere_mask(camera, W, H, center, radius):
    o, d = pixel_rays(camera, W, H)
    oc = o - center
    b = d @ oc
    disc = b ** 2 - (oc @ oc - radius ** 2)
    return (disc >= 0) & (-b + np.sqrt(np.maximum(disc, 0)) > 0)


def box_mask(camera, W, H, lo, hi):
    o, d = pixel_rays(camera, W, H)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    tn = np.nanmax(np.minimum(t0, t1), axis=-1)
    tf = np.nanmin(np.maximum(t0, t1), axis=-1)
    return (tn <= tf) & (tf > 0)


# ---------------------------------------------------------------------------------------------
# projection and the Mitsuba sensor
# ---------------------------------------------------------------------------------------------

def test_projection_matches_mitsuba():
    W, H, fov = 40, 30, 50.0
    for off in [(0.0, 0.0), (0.1, -0.05)]:
        to_world = mi_look_at([1.0, 2.0, 3.0], [0.2, 0.0, -0.1], [0.0, 1.0, 0.0])
        sensor = mi.load_dict({
            "type": "perspective", "fov": fov, "fov_axis": "x",
            "principal_point_offset_x": off[0], "principal_point_offset_y": off[1],
            "to_world": mi.ScalarTransform4f(to_world),
            "film": {"type": "hdrfilm", "width": W, "height": H}})
        f = W / 2 / np.tan(np.radians(fov) / 2)
        cx, cy = W * (0.5 - off[0]), H * (0.5 - off[1])
        cam = Camera(W, H, f, f, cx, cy, to_world)
        pos = np.array([[0.1, 0.2], [0.5, 0.5], [0.9, 0.7], [0.03, 0.95]])
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]), mi.Point2f(0.5, 0.5))
        o, d = np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T
        for dist in (0.5, 2.0, 7.0):
            uv, depth = cam.project(o + dist * d)
            assert np.all(depth > 0)
            np.testing.assert_allclose(uv, pos * [W, H], atol=1e-3)
    # camera space: +z forward, +y up, +x to the image's LEFT
    c2w = mi_look_at([0, 0, 0], [0, 0, 1], [0, 1, 0])
    cam = Camera(40, 30, 10.0, 10.0, 20.0, 15.0, c2w)
    uv, _ = cam.project(np.array([[1.0, 0, 5], [0, 1.0, 5]]))
    assert uv[0, 0] < 20 and np.isclose(uv[0, 1], 15)      # +x: left
    assert uv[1, 1] < 15 and np.isclose(uv[1, 0], 20)      # +y: up (row 0 is the top)
    # a point in the camera plane: no NaN
    uv, depth = cam.project([[1.0, 0.0, 0.0]])
    assert np.all(np.isfinite(uv)) and depth[0] == 0


def test_rendered_silhouette_matches_projection():
    # Mitsuba's image rows: row 0 at the top; a sphere off-center up-left in
    # camera space lands where the pinhole model puts it
    W, H, fov = 24, 16, 45.0
    to_world = mi_look_at([0.0, 0.0, 5.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    center, radius = np.array([-0.6, 0.4, 0.0]), 0.35
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": fov, "to_world": mi.ScalarTransform4f(to_world),
                   "film": {"type": "hdrfilm", "width": W, "height": H, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "ball": {"type": "sphere", "center": center.tolist(), "radius": radius,
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    img = np.array(mi.render(scene))[..., 0]
    f = W / 2 / np.tan(np.radians(fov) / 2)
    cam = Camera(W, H, f, f, W / 2, H / 2, to_world)
    mask = sphere_mask(cam, W, H, center, radius)
    rendered = img > 0.5
    assert rendered.sum() > 5
    iou = (mask & rendered).sum() / (mask | rendered).sum()
    assert iou > 0.8, iou
    # the sphere's center projects inside the rendered silhouette
    uv, depth = cam.project([center])
    assert depth[0] > 0 and rendered[int(uv[0, 1]), int(uv[0, 0])]


def test_sensor_dict_fields():
    v = Camera.look_at([0, 0, -3], [0, 0, 0], [0, 1, 0], 40, 20, fx=25.0, cx=22.0, cy=9.0)
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
    # Mitsuba's look_at and Camera.look_at build the same frame
    ref = mi.ScalarTransform4f().look_at(origin=[0, 0, -3], target=[0, 0, 0], up=[0, 1, 0])
    np.testing.assert_allclose(np.array(ref.matrix), v.to_world, atol=1e-6)
    ref = mi.ScalarTransform4f().look_at(origin=[1, 2, 3], target=[0, 0, 0], up=[0, 0, 1]).matrix
    np.testing.assert_allclose(C.look_at([1, 2, 3]), np.array(ref, np.float64), atol=1e-6)
    # near / far clip are passed on
    d = v.sensor_dict(near_clip=0.1, far_clip=50.0)
    assert (d["near_clip"], d["far_clip"]) == (0.1, 50.0)
    # non-square pixels are refused
    v.fy = 26.0
    with pytest.raises(ValueError, match="non-square"):
        v.sensor_dict()


#: A camera 4 units from the origin, looking at it, with an off-center principal point.
KNOWN_POSE = dict(w=32, h=24, fx=30.0, cx=13.3, cy=14.1, origin=np.array([0.5, -4.0, 1.0]))


def check_known_pose(v, c2w, w, h, fx, cx, cy, origin):
    """``v`` is the OpenGL camera ``c2w`` (looking at the origin, +z up) with
    these intrinsics: pose, projection and Mitsuba's rays agree with
    independent formulas."""
    assert (v.width, v.height, v.fx, v.fy, v.cx, v.cy) == (w, h, fx, fx, cx, cy)
    np.testing.assert_allclose(v.center, origin, atol=1e-12)
    assert v.fov_x == pytest.approx(math.degrees(2 * math.atan(w / (2 * fx))))
    # the look-at target lands on the principal point; Mitsuba's camera looks along +z
    uv, depth = v.project([[0, 0, 0]])
    np.testing.assert_allclose(uv[0], [cx, cy], atol=1e-9)
    np.testing.assert_allclose(v.to_world[:3, 2], -origin / np.linalg.norm(origin), atol=1e-12)
    # world up (+z) is image up: a point above the target projects above it (smaller v)
    assert v.project([[0, 0, 0.5]])[0][0, 1] < cy
    # independent pinhole projection of random points agrees with Camera.project
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
    # pixel center convention: the ray through pixel (0, 0)'s center (0.5, 0.5)
    o, dirs = mitsuba_ray_dirs(v, [[0.5, 0.5], [w - 0.5, h - 0.5]])
    np.testing.assert_allclose(dirs, v.rays([[0.5, 0.5], [w - 0.5, h - 0.5]])[1], atol=2e-6)


def test_known_pose_opengl():
    c2w = gl_look_at(KNOWN_POSE["origin"], [0, 0, 0], [0, 0, 1])
    p = KNOWN_POSE
    v = Camera.from_opengl(c2w, p["w"], p["h"], p["fx"], p["fx"], p["cx"], p["cy"])
    np.testing.assert_allclose(v.c2w_opengl, c2w, atol=1e-15)
    check_known_pose(v, c2w, **KNOWN_POSE)


def test_opencv_and_colmap_axes():
    # identity COLMAP rotation: the OpenCV camera looks along +z with y down, x right
    v = Camera.from_colmap([0, 0, 0, 2.0], [0.1, 0.2, 3.0], 40, 30, 35.0, 35.0, 21.0, 14.0)
    np.testing.assert_allclose(v.center, [-0.1, -0.2, -3.0], atol=1e-12)
    np.testing.assert_allclose(v.to_world[:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    p = np.array([[1.0, 0.5, 2.0]])
    uv, _ = v.project(p)                             # OpenCV: u = fx x_c / z_c + cx
    xc = p[0] + [0.1, 0.2, 3.0]
    np.testing.assert_allclose(uv[0], [35 * xc[0] / xc[2] + 21, 35 * xc[1] / xc[2] + 14])
    # K projects in the OpenCV frame of c2w_opencv
    rng = np.random.default_rng(1)
    q = rng.normal(size=4)
    t = rng.normal(size=3)
    v = Camera.from_colmap(q, t, 40, 30, 35.0, 33.0, 21.0, 14.0)
    w2c = np.linalg.inv(v.c2w_opencv)
    pts = v.center + rng.normal(size=(20, 3)) + 3 * v.to_world[:3, 2]
    pc = pts @ w2c[:3, :3].T + w2c[:3, 3]
    h = pc @ v.K.T
    np.testing.assert_allclose(v.project(pts)[0], h[:, :2] / h[:, 2:], atol=1e-9)
    # the pose is rigid, and from_opencv(c2w_opencv) gives the camera back
    r = v.to_world[:3, :3]
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    back = Camera.from_opencv(v.c2w_opencv, 40, 30, 35.0, 33.0, 21.0, 14.0)
    np.testing.assert_allclose(back.to_world, v.to_world, atol=1e-15)
    back = Camera.from_opengl(v.c2w_opengl, 40, 30, 35.0, 33.0, 21.0, 14.0)
    np.testing.assert_allclose(back.to_world, v.to_world, atol=1e-15)


def test_as_rigid():
    m = gl_look_at([1, 2, 3], [0, 0, 0], [0, 0, 1])
    noisy = m.copy()
    noisy[:3, :3] += 1e-5 * np.random.default_rng(2).normal(size=(3, 3))
    r = C.as_rigid(noisy)
    np.testing.assert_allclose(r[:3, :3].T @ r[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(r, m, atol=1e-4)
    np.testing.assert_allclose(C.as_rigid(m[:3]), m, atol=1e-12)        # (3, 4) accepted
    for bad in (np.diag([2.0, 1, 1, 1]), np.diag([-1.0, 1, 1, 1]), np.eye(3)):
        with pytest.raises(ValueError, match="frame 7"):
            C.as_rigid(bad, "frame 7")


# ---------------------------------------------------------------------------------------------
# rays
# ---------------------------------------------------------------------------------------------

def test_rays_numpy_and_drjit():
    cam = Camera.look_at([0.3, -2.0, 1.2], [0.1, 0, 0], [0, 0, 1], 9, 7, fx=8.0, cx=4.1,
                         cy=3.7)
    o, d = cam.rays()
    assert o.shape == d.shape == (63, 3)
    np.testing.assert_allclose(o, np.broadcast_to(cam.center, o.shape))
    _, ref = pixel_rays(cam, 9, 7)
    np.testing.assert_allclose(d.reshape(7, 9, 3), ref, atol=1e-12)
    uv = cam.pixel_centers()
    assert uv.shape == (63, 2) and tuple(uv[0]) == (0.5, 0.5) and tuple(uv[9]) == (0.5, 1.5)
    # rays hit what they project onto
    uv_back, depth = cam.project(o + 2.5 * d)
    np.testing.assert_allclose(uv_back, uv, atol=1e-9)
    np.testing.assert_allclose(depth, 2.5 * (d @ cam.to_world[:3, 2]), atol=1e-12)
    # Dr.Jit rays: the same, in float32, for pixel centers and explicit positions
    ray = cam.rays_drjit()
    assert isinstance(ray, mi.Ray3f)
    np.testing.assert_allclose(np.array(ray.o, np.float64).reshape(3, -1).T, o, atol=1e-6)
    np.testing.assert_allclose(np.array(ray.d, np.float64).reshape(3, -1).T, d, atol=2e-6)
    q = np.array([[0.0, 0.0], [9.0, 7.0], [2.25, 5.5]])
    for arg in (q, mi.Point2f(*q.astype(np.float32).T)):
        ray = cam.rays_drjit(arg)
        np.testing.assert_allclose(np.array(ray.d, np.float64).reshape(3, -1).T, cam.rays(q)[1],
                                   atol=2e-6)


# ---------------------------------------------------------------------------------------------
# downscaling and resizing
# ---------------------------------------------------------------------------------------------

def test_downscaled_and_resized():
    v = Camera.look_at([1, 2, 3], [0, 0, 0], [0, 0, 1], 11, 7, fx=9.0, cx=5.2, cy=3.9)
    s = v.downscaled(2)
    assert (s.width, s.height) == (5, 3)
    assert (s.fx, s.fy, s.cx, s.cy) == (4.5, 4.5, 2.6, 1.95)
    np.testing.assert_array_equal(s.to_world, v.to_world)
    # pixel-center convention: new pixel (i, j)'s center is the center of its 2x2 block
    ij = np.array([[0, 0], [4, 2], [2, 1]], float)
    np.testing.assert_allclose(s.rays(ij + 0.5)[1], v.rays(2 * ij + 1.0)[1], atol=1e-12)
    # and the Mitsuba sensors of both agree
    np.testing.assert_allclose(mitsuba_ray_dirs(s, ij + 0.5)[1],
                               mitsuba_ray_dirs(v, 2 * ij + 1.0)[1], atol=2e-6)
    assert dataclasses.astuple(v.downscaled(1))[:6] == dataclasses.astuple(v)[:6]
    with pytest.raises(ValueError):
        v.downscaled(1.5)
    # the same picture stored at another size: corners and center keep their rays
    r = v.resized(22, 21)
    assert (r.width, r.height) == (22, 21)
    assert (r.fx, r.fy, r.cx, r.cy) == pytest.approx((18.0, 27.0, 10.4, 11.7), rel=1e-15)
    corners = np.array([[0, 0], [11, 7], [5.5, 3.5]])
    np.testing.assert_allclose(r.rays(corners * [2, 3])[1], v.rays(corners)[1], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# generated cameras
# ---------------------------------------------------------------------------------------------

def test_cameras_point_at_origin():
    cams = C.fibonacci_cameras(7, radius=3.0, res=(15, 11), fov=40.0)
    cams += C.random_cameras(3, radius=2.5, res=(15, 11), seed=3)
    cams.append(Camera.look_at([0, 0, 4.0], [0, 0, 0], [0, 0, 1], 15, 11,
                               fov_x=30.0))                        # at the pole of up=z
    fib = np.array([c.center for c in cams[:7]])
    assert np.allclose(np.linalg.norm(fib, axis=1), 3.0)
    assert np.ptp(fib[:, 2]) > 4.0                                   # spread over the sphere
    assert cams[0].fov_x == pytest.approx(40.0)
    assert cams[7].fov_x == pytest.approx(C.default_fov(2.5))
    for cam in cams:
        m = np.asarray(cam.to_world)
        assert np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
        ray = cam.rays_drjit()
        w, h = cam.width, cam.height
        o = np.array(ray.o, np.float64).reshape(3, -1).T
        d = np.array(ray.d, np.float64).reshape(3, -1).T.reshape(h, w, 3)
        assert np.allclose(o, cam.center, atol=1e-6)
        # the center pixel (odd size) looks at the origin
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
        np.testing.assert_allclose(cam.rays()[1].reshape(h, w, 3), dw, atol=1e-12)
        # pixel (0, 0) is top-left: up and left of the view direction
        up, right = gl[:3, 1], gl[:3, 0]
        assert d[0, 0] @ up > 0 and d[0, 0] @ right < 0
    # hemisphere: every camera on the up side
    hemi = C.fibonacci_cameras(9, hemisphere=True) + C.random_cameras(9, hemisphere=True)
    assert all(c.center[2] > 0 for c in hemi)


def test_default_fov_frames_the_box():
    for radius in (2.5, 4.0, 10.0):
        cam = C.fibonacci_cameras(1, radius=radius, res=64)[0]
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)])
        uv, depth = cam.project(corners)
        assert np.all(depth > 0)
        assert np.all((uv >= 0) & (uv <= 64))


def _sphere_silhouette(cam, centre, radius):
    """Where the sphere's outline lands in the image: the projections of its tangent points
    from the camera centre (a circle of them), (n, 2) pixels."""
    c = np.asarray(centre, float)
    v = c - cam.center
    d = np.linalg.norm(v)
    axis = v / d
    # the tangent points: at angle asin(r / d) from the axis, distance sqrt(d^2 - r^2)
    e1 = np.cross(axis, [0.3, 0.5, 0.8])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t = np.linspace(0, 2 * np.pi, 721)[:-1]
    half = math.asin(radius / d)
    dirs = math.cos(half) * axis + math.sin(half) * (np.cos(t)[:, None] * e1
                                                     + np.sin(t)[:, None] * e2)
    uv, depth = cam.project(cam.center + math.sqrt(d * d - radius * radius) * dirs)
    assert np.all(depth > 0)
    return uv


@pytest.mark.parametrize("radius,fov,res", [(1.0, 40.0, None), (0.37, 40.0, (64, 64)),
                                            (2.5, 25.0, (96, 48)), (2.5, 60.0, (40, 90))])
def test_framing_distance_is_the_closed_form(radius, fov, res):
    """framing_distance(r, fov) = 1.05 r / sin(fov' / 2), fov' the horizontal field, or
    fov * h / w on a wider image; a camera there sees the sphere 1.05 r inside its image
    (touching the narrower side's edges where the field is fov itself)."""
    d = C.framing_distance(radius, fov, res)
    narrow = fov if res is None else min(fov, fov * res[1] / res[0])
    assert d == pytest.approx(1.05 * radius / math.sin(math.radians(narrow) / 2), rel=1e-14)
    assert C.framing_distance(radius, fov, res, margin=1.0) == pytest.approx(d / 1.05,
                                                                             rel=1e-14)
    w, h = res or (64, 64)
    centre = np.array([0.3, -1.2, 0.5])
    cam = Camera.look_at(centre + d * np.array([0.6, 0.0, 0.8]), centre, [0, 0, 1], w, h,
                         fov_x=fov)
    uv = _sphere_silhouette(cam, centre, 1.05 * radius)
    assert np.all((uv >= -1e-6) & (uv <= np.array([w, h]) + 1e-6))
    if narrow == fov:   # the field is the horizontal one: the sphere touches its sides
        # (to the outline's sampling, 720 points: 1e-4 of a pixel)
        assert uv[:, 0].min() == pytest.approx(0.0, abs=1e-3)
        assert uv[:, 0].max() == pytest.approx(w, abs=1e-3)
    else:               # a wider image: the vertical extent is the one that fits
        assert 0 < uv[:, 1].min() < 0.05 * h and 0.95 * h < uv[:, 1].max() < h


def test_default_fov_is_framing_distance_inverted():
    """default_fov(d) is the field in which [-1, 1]^3's bounding sphere (radius sqrt 3)
    is framed from distance d: framing_distance gives d back."""
    for d in (2.5, 4.0, 10.0):
        assert C.framing_distance(math.sqrt(3.0), C.default_fov(d)) == pytest.approx(d,
                                                                                    rel=1e-12)


def test_the_framing_distance_is_written_once():
    """Every camera that frames a bounding sphere (render MESH, the viewer's first view,
    the best viewpoint's orbit, data set cameras, the tutorials) calls framing_distance:
    no other module writes its formula."""
    import re

    from tests.helpers import ROOT
    formula = re.compile(r"1\.05\s*\*[^\n]*\bsin\(")
    found = [str(p.relative_to(ROOT)) for d in ("mi_tetvr", "tutorials", "plugins")
             for p in sorted((ROOT / d).rglob("*.py")) if formula.search(p.read_text())]
    assert found == []


def test_camera_path_through_the_cameras():
    """A fly-through along three cameras on a line (x = 0, 1, 3) turning about z by 0, 30
    and 90 degrees: the frames at the cameras' share of the distance are the cameras; between
    two, the center is the linear blend and the rotation the half turn (slerp's closed form
    about one axis). The intrinsics are those of the most common image size."""
    from scipy.spatial.transform import Rotation

    def cam(x, deg, w=40, h=30, f=35.0):
        m = np.eye(4)
        m[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
        m[:3, 3] = [x, 0.0, 0.0]
        return Camera(w, h, f, f, w / 2, h / 2, m)

    cams = [cam(0.0, 0.0), cam(1.0, 30.0, w=30, h=40, f=50.0), cam(3.0, 90.0, f=37.0)]
    path = camera_path(cams, 7)                 # t = 0, 1/6, ..., 1: the cameras at 0, 2, 6
    assert len(path) == 7
    for k, c in ((0, cams[0]), (2, cams[1]), (6, cams[2])):
        np.testing.assert_allclose(path[k].to_world, c.to_world, atol=1e-9)
    np.testing.assert_allclose(path[1].to_world, cam(0.5, 15.0).to_world, atol=1e-9)
    np.testing.assert_allclose(path[4].to_world, cam(2.0, 60.0).to_world, atol=1e-9)
    assert all((c.width, c.height, c.fx, c.cx) == (40, 30, 36.0, 20.0) for c in path)
    with pytest.raises(ValueError, match="2 or more cameras"):
        camera_path(cams[:1], 7)
