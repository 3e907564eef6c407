"""The path-traced room capture: a real capture's files (an instant-ngp
transforms.json with an OpenCV lens, PNG photos, no masks) whose photos,
undistorted by the loader, are what Mitsuba's own perspective sensor sees
from the same pinhole."""
import json

import mitsuba as mi
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from mi_tetvr.recon.capture import _scene_dict, make_room_capture
from mi_tetvr.recon.datasets import load_nerf
from mi_tetvr.recon.metrics import psnr


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("room")
    info = make_room_capture(out, views=9, width=64, height=48, spp=32, exposure_sigma=0.0,
                             gain_sigma=0.0, noise=0.0, distortion=(-0.2, 0.05, 0.002, -0.002),
                             progress=False)
    return out, info


def test_capture_files_and_protocol(capture):
    out, info = capture
    meta = json.loads((out / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["k1"] == -0.2
    data = load_nerf(out)
    # every 8th photo held out; photos are opaque (no masks)
    assert [v.name for v in data.test] == ["frame_0000", "frame_0008"]
    assert len(data.train) == 7
    assert all(v.image[..., 3].min() == 1.0 for v in data.views)
    # the cameras are inside the room
    lo, hi = np.array(info["room"])
    assert all(np.all((v.camera.center > lo) & (v.camera.center < hi)) for v in data.views)


def test_undistorted_photos_match_mitsubas_pinhole(capture):
    """The loader's undistorted photo against Mitsuba's perspective sensor at
    the same pinhole (box-filtered alike, both blurred over 1.5 pixels for
    the resampling); the photo read as if it had no distortion matches far
    worse (the lens is in the pixels)."""
    out, _ = capture
    data = load_nerf(out)
    meta = json.loads((out / "transforms.json").read_text())
    plain = {k: meta[k] for k in ("w", "h", "fl_x", "fl_y", "cx", "cy")}
    (out / "pinhole.json").write_text(json.dumps({**plain, "frames": meta["frames"]}))
    ignored = load_nerf(out / "pinhole.json", holdout=None)
    scene = mi.load_dict(_scene_dict(0))
    for v in data.test[:1]:
        d = v.camera.sensor_dict(sampler="independent")
        d["film"]["rfilter"] = {"type": "box"}
        ref = np.array(mi.render(scene, sensor=mi.load_dict(d), spp=256))[..., :3]
        blur = lambda x: gaussian_filter(np.clip(x, 0, 1), (1.5, 1.5, 0))   # noqa: E731
        right = psnr(np.mean((blur(v.image[..., :3]) - blur(ref)) ** 2))
        wrong_view = next(w for w in ignored.views if w.name == v.name)
        wrong_ref = np.array(mi.render(scene, sensor=mi.load_dict(
            {**wrong_view.camera.sensor_dict(sampler="independent"),
             "film": d["film"]}), spp=64))[..., :3]
        wrong = psnr(np.mean((blur(wrong_view.image[..., :3]) - blur(wrong_ref)) ** 2))
        assert right > 28.0 and right > wrong + 5.0, (right, wrong)
