"""A photo capture the project makes itself: an object in a textured room,
path traced by Mitsuba, written as a real capture would come.

:func:`make_room_capture` renders a closed room (textured floor, walls and
ceiling, two ceiling lights) with a textured sphere and box standing in its
middle, from cameras *inside* the room on a ring around the objects, with
Mitsuba's own ``path`` integrator. Each picture is what a camera records:

* the average over each pixel's area (box filter, ``spp`` samples) seen
  through a real lens: COLMAP's ``OPENCV`` model (radial ``k1, k2`` and
  tangential ``p1, p2`` distortion) -- every sample's ray comes from
  pycolmap's inverse of the lens model, so the image is distorted exactly,
  not resampled;
* a per-photo exposure and white balance (a random gain per channel);
* sensor noise (Gaussian in linear RGB) and 8-bit sRGB quantization.

The capture is written as instant-ngp's single ``transforms.json`` (OpenGL
camera-to-world poses, the lens keys ``camera_model, fl_x, fl_y, cx, cy, k1,
k2, p1, p2``) with PNG photos and no masks and no sparse points -- what a
phone capture posed by a SLAM app looks like. ``capture_info.json`` records
the truth (exposures, gains, the scene's size) for tests; the fit never reads
it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mi_tetvr.extras import needs

__all__ = ["make_room_capture", "room_cameras", "ROOM"]

#: The room: x, y in [-2, 2], z (up) in [0, 2.5] (world units: metres).
ROOM = np.array([[-2.0, -2.0, 0.0], [2.0, 2.0, 2.5]])
#: Where the cameras look: the middle of the objects.
TARGET = np.array([0.1, 0.05, 0.35])


def _texture(rng, size=256, shapes=90):
    """An (size, size, 3) linear RGB texture rich in corners and colors
    (random rectangles and discs over a base color, plus fine grain): what
    feature matching and a reconstruction need to see."""
    base = rng.uniform(0.15, 0.6, 3)
    img = np.tile(base, (size, size, 1))
    y, x = np.mgrid[0:size, 0:size]
    for _ in range(shapes):
        color = rng.uniform(0.02, 0.9, 3)
        cx, cy = rng.uniform(0, size, 2)
        r = rng.uniform(0.02, 0.12) * size
        if rng.random() < 0.5:
            mask = (np.abs(x - cx) < r) & (np.abs(y - cy) < rng.uniform(0.3, 1.0) * r)
        else:
            mask = (x - cx) ** 2 + (y - cy) ** 2 < r * r
        img[mask] = color
    img *= rng.uniform(0.9, 1.1, (size, size, 1))
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _scene_dict(seed=0):
    """The room and its objects as a Mitsuba scene dict (``path`` integrator)."""
    import mitsuba as mi
    T = mi.ScalarTransform4f
    rng = np.random.default_rng(seed)
    (x0, y0, z0), (x1, y1, z1) = ROOM
    cx, cy, cz = (ROOM[0] + ROOM[1]) / 2
    sx, sy, sz = (ROOM[1] - ROOM[0]) / 2

    def textured(reflectance=1.0):
        return {"type": "diffuse", "reflectance": {
            "type": "bitmap", "bitmap": mi.Bitmap(_texture(rng) * reflectance),
            "raw": True, "filter_type": "bilinear"}}

    # rectangles are [-1, 1]^2 in z = 0 with normal +z: each faces into the room
    walls = {
        "floor": T().translate([cx, cy, z0]).scale([sx, sy, 1]),
        "ceiling": T().translate([cx, cy, z1]).rotate([1, 0, 0], 180).scale([sx, sy, 1]),
        "wall_x0": T().translate([x0, cy, cz]).rotate([0, 1, 0], 90).scale([sz, sy, 1]),
        "wall_x1": T().translate([x1, cy, cz]).rotate([0, 1, 0], -90).scale([sz, sy, 1]),
        "wall_y0": T().translate([cx, y0, cz]).rotate([1, 0, 0], -90).scale([sx, sz, 1]),
        "wall_y1": T().translate([cx, y1, cz]).rotate([1, 0, 0], 90).scale([sx, sz, 1]),
    }
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 5}}
    for name, to_world in walls.items():
        scene[name] = {"type": "rectangle", "to_world": to_world, "bsdf": textured(0.8)}
    for i, x in enumerate((-0.8, 0.8)):
        scene[f"light_{i}"] = {
            "type": "rectangle", "to_world": T().translate([x, 0.0, z1 - 0.01])
            .rotate([1, 0, 0], 180).scale([0.4, 0.6, 1]),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [9.0, 8.6, 8.0]}}}
    scene["sphere"] = {"type": "sphere", "center": [-0.25, -0.1, 0.35], "radius": 0.35,
                       "bsdf": textured()}
    scene["box"] = {"type": "cube", "to_world": T().translate([0.45, 0.35, 0.25])
                    .rotate([0, 0, 1], 30).scale(0.25), "bsdf": textured()}
    return scene


def room_cameras(n, width, height, fov_x=70.0, seed=0, arc=360.0):
    """``n`` cameras inside the room on a ring around the objects (radius
    1.2 to 1.6, height 0.6 to 1.4, evenly spaced with jitter over ``arc``
    degrees of the ring: 360 walks all around, less walks part of the way),
    each looking at the objects. Returns a list of pinhole
    :class:`~mi_tetvr.camera.Camera`."""
    from mi_tetvr.camera import Camera
    rng = np.random.default_rng(seed + 1)
    cams = []
    for i in range(n):
        phi = np.radians(arc) * (i + rng.uniform(-0.3, 0.3)) / n
        r, z = rng.uniform(1.2, 1.6), rng.uniform(0.6, 1.4)
        origin = TARGET + [r * np.cos(phi), r * np.sin(phi), z - TARGET[2]]
        target = TARGET + rng.uniform(-0.15, 0.15, 3)
        cams.append(Camera.look_at(origin, target, (0, 0, 1), width, height, fov_x=fov_x))
    return cams


def _lens_rays(camera, lens, spp, rng):
    """Camera-space ray directions (spp, h * w, 3) of ``spp`` uniform
    samples over each pixel of the distorted image: pycolmap's inverse of the
    lens model, per sample."""
    h, w = camera.height, camera.width
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    out = np.empty((spp, h * w, 3))
    for s in range(spp):
        px = np.stack([x.ravel() + rng.random(h * w), y.ravel() + rng.random(h * w)], -1)
        d = lens.cam_from_img(px)
        out[s] = np.concatenate([d, np.ones((len(d), 1))], -1)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def _render_rays(scene, integrator, origin, dirs, seed):
    """Mean radiance (k, 3) of the rays ``dirs`` (spp, k, 3) from ``origin``:
    one call of the integrator's ``sample`` per sample."""
    import drjit as dr
    import mitsuba as mi
    spp, k, _ = dirs.shape
    sampler = mi.load_dict({"type": "independent"})
    total = np.zeros((k, 3))
    for s in range(spp):
        sampler.seed(seed * 1009 + s, k)
        d = mi.Vector3f(*[mi.Float(dirs[s, :, j].astype(np.float32)) for j in range(3)])
        ray = mi.Ray3f(mi.Point3f(*[float(c) for c in origin]), d)
        with dr.suspend_grad():
            L, _, _ = integrator.sample(scene, sampler, ray)
        total += np.stack([np.array(L[j]) for j in range(3)], -1)
    return total / spp


def make_room_capture(out_dir, views=48, width=400, height=300, fov_x=70.0, spp=64,
                      distortion=(-0.12, 0.03, 0.001, -0.001), exposure_sigma=0.15,
                      gain_sigma=0.03, noise=0.01, seed=0, arc=360.0, progress=True):
    """Render the room capture (see the module docstring) to ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Gets ``transforms.json``, ``images/frame_XXXX.png`` and ``capture_info.json``.
    views : int
        Photos (every 8th is held out by the fit, as Mip-NeRF 360 does).
    width, height : int
        Photo size in pixels.
    fov_x : float
        Horizontal field of view of the pinhole before distortion (degrees).
    spp : int
        Path-traced samples per pixel (box filter over the pixel).
    distortion : (4,) float
        OPENCV ``k1, k2, p1, p2``.
    exposure_sigma, gain_sigma : float
        Standard deviations of the log exposure and the log gain per channel.
    noise : float
        Standard deviation of Gaussian sensor noise in linear RGB.
    seed : int
    arc : float
        Degrees of the ring the cameras spread over (360: all around the objects).

    Returns
    -------
    dict
        What ``capture_info.json`` holds.
    """
    import mitsuba as mi
    with needs("sfm", "a capture's COLMAP model"):
        import pycolmap
        from mi_tetvr.progress import progress_bar as tqdm

    from mi_tetvr.color import linear_to_srgb
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    scene = mi.load_dict(_scene_dict(seed))
    integrator = scene.integrator()
    cams = room_cameras(views, width, height, fov_x, seed, arc)
    f = cams[0].fx
    k1, k2, p1, p2 = (float(v) for v in distortion)
    lens = pycolmap.Camera(model="OPENCV", width=width, height=height,
                           params=[f, f, width / 2, height / 2, k1, k2, p1, p2])
    rng = np.random.default_rng(seed + 2)
    exposures = np.exp(rng.normal(0.0, exposure_sigma, views))
    gains = np.exp(rng.normal(0.0, gain_sigma, (views, 3)))
    frames = []
    with needs("recon", "writing a capture's photos"):
        from PIL import Image
    for i, cam in enumerate(tqdm(cams, desc="path trace photos", disable=not progress)):
        dirs = _lens_rays(cam, lens, spp, rng)
        c2w = cam.c2w_opencv[:3, :3]                  # camera axes x right, y down, z forward
        world = np.einsum("ij,skj->ski", c2w, dirs)
        rgb = _render_rays(scene, integrator, cam.center, world, seed * 7919 + i)
        rgb = rgb.reshape(height, width, 3) * exposures[i] * gains[i]
        rgb = rgb + rng.normal(0.0, noise, rgb.shape)
        png = np.round(linear_to_srgb(np.clip(rgb, 0.0, 1.0)) * 255).astype(np.uint8)
        name = f"images/frame_{i:04d}.png"
        Image.fromarray(png, "RGB").save(out / name)
        frames.append({"file_path": name, "transform_matrix": cam.c2w_opengl.tolist()})
    meta = {"camera_model": "OPENCV", "w": width, "h": height, "fl_x": f, "fl_y": f,
            "cx": width / 2, "cy": height / 2, "k1": k1, "k2": k2, "p1": p1, "p2": p2,
            "frames": frames}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    info = {"scene": "textured room with a sphere and a box, Mitsuba path (max_depth 5)",
            "room": ROOM.tolist(), "target": TARGET.tolist(), "views": views,
            "width": width, "height": height, "fov_x_deg": fov_x, "spp": spp,
            "distortion_opencv": [k1, k2, p1, p2], "exposures": exposures.tolist(),
            "gains": gains.tolist(), "noise_linear_sigma": noise, "seed": seed, "arc_deg": arc}
    (out / "capture_info.json").write_text(json.dumps(info, indent=1) + "\n")
    return info
