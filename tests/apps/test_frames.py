"""Frames of one scene from many cameras (mi_tetvr.apps.frames): the
replayed kernels give the images ``mi.render`` gives with a sensor made
afresh for each camera, one recording serves every pose of a film, and
after a parameter change and :meth:`Frames.clear` the images follow."""
import numpy as np

from tests.helpers import use_variant

use_variant()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_tetvr  # noqa: E402
from mi_tetvr.apps.frames import Frames  # noqa: E402
from mi_tetvr.camera import Camera, look_at  # noqa: E402
from mi_tetvr.mesh.generate import blob_field, grid_mesh  # noqa: E402


def cameras():
    out = []
    for a in (0.0, 0.7, 1.9, 2.6, 4.0):
        eye = [4.0 * np.cos(a), 4.0 * np.sin(a), 1.5]
        out.append(Camera(40, 30, 45.0, 45.0, 20.0, 15.0, look_at(eye, [0, 0, 0], [0, 0, 1])))
    return out


def plain(scene, camera):
    """``mi.render`` with the camera's sensor made afresh."""
    d = camera.sensor_dict(spp=1, sampler="stratified")
    d["sampler"]["jitter"] = False
    d["film"]["pixel_format"] = "rgba"
    with dr.suspend_grad():
        return np.array(mi.render(scene, sensor=mi.load_dict(d), seed=0))


def test_frames_replay_the_images_of_fresh_renders():
    V, T = grid_mesh(4, jitter=0.1, seed=3)
    color, opacity = blob_field(V)
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "tetvr"},
                          "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity)})
    frames = Frames(scene)
    before = None
    for camera in cameras():
        image = np.array(frames.render(camera))
        np.testing.assert_allclose(image, plain(scene, camera), atol=1e-6)
        assert image[..., 3].max() > 0.1            # the volume is seen
        before = image if before is None else before
    # five poses of one film, two recordings: the first pose's (its values
    # as literals), then one with the pose an input, which the others replay
    (_, frozen), = frames._recorded.values()
    assert frozen.n_recordings <= 2
    # a parameter changed: after clear(), the frames show it
    params = mi.traverse(scene)
    params["volume.vertex_opacity"] = params["volume.vertex_opacity"] * 0.25
    params.update()
    frames.clear()
    camera = cameras()[0]
    after = np.array(frames.render(camera))
    np.testing.assert_allclose(after, plain(scene, camera), atol=1e-6)
    assert np.abs(after - before).max() > 0.05
